"""The pure core's error root. The shell (``companion``) has its own root,
:class:`companion.CoreError`; the core never imports the shell."""

from __future__ import annotations


class CoreError(Exception):
    """Root of every error the pure core raises on purpose."""


class ParamError(CoreError, ValueError):
    """A parameter set is inconsistent; the message names the config key (``rmpc.tube_h``)."""
