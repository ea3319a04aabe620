"""PX4 companion: RMPC image-based visual servoing of a quadrotor following a ground vehicle.

Implements Q. Yang and H. Li, "RMPC-Based Visual Servoing for Trajectory Tracking of Quadrotor
UAVs With Visibility Constraints", IEEE/CAA J. Autom. Sinica 11(9), 2024, with the conventions
of docs/reference/math.md.
"""

from __future__ import annotations

__version__ = "0.1.0"


class CompanionError(Exception):
    """Root of every error the shell (I/O, config, logs) raises on purpose. The pure core has
    its own root, :class:`companion.core.errors.CoreError`; the CLI reports both."""


class ConfigError(CompanionError):
    """A configuration file or value is invalid; the message names the key."""
