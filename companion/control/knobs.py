"""Config knobs that have no effect in the chosen mode, named so a user is told (issue 25).

A knob counts as *set* when its value differs from the shipped default config's
(``config/paper.toml``): a file that copies the defaults is not warned about. Each rule says
which knobs a switch makes inert, checked against what the code does with them:

- ``control.lead.*`` with ``control.lead.enabled = false`` (the lead filter returns the command
  unchanged);
- ``control.estimator.*`` with ``control.estimator.enabled = false`` (no estimator is built;
  ``accelerometer`` then only lets HIGHRES_IMU through the link);
- ``control.latency.auto_delay_*`` with ``control.latency.auto_delay = false`` (no delay meter);
- ``control.latency.max_prediction_s`` / ``step_s`` with ``control.latency.enabled = false``
  (no prediction is made);
- ``logging.preview_scale`` / ``preview_jpeg_quality`` with ``logging.preview_rate_hz = 0``
  (no preview);
- ``logging.image_encoding`` with ``logging.perception_input = "none"`` (no input is logged);
- ``live.host`` / ``port`` / ``queue_size`` / ``client_backlog`` without the live view.
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Callable, Sequence
from functools import lru_cache
from typing import Any

from companion.config import Config, load_config

log = logging.getLogger(__name__)

#: (section path, knobs (None: every field but the switch), is the section in effect, why not)
_RULES: tuple[tuple[str, Sequence[str] | None, Callable[[Config], bool], str], ...] = (
    ("control.lead", None, lambda c: c.control.lead.enabled, "control.lead.enabled = false"),
    ("control.estimator", None, lambda c: c.control.estimator.enabled,
     "control.estimator.enabled = false"),
    ("control.latency", ("auto_delay_window", "auto_delay_min_samples", "auto_delay_max_s",
                         "auto_delay_probe_hz"),
     lambda c: c.control.latency.auto_delay, "control.latency.auto_delay = false"),
    ("control.latency", ("max_prediction_s", "step_s"), lambda c: c.control.latency.enabled,
     "control.latency.enabled = false"),
    ("logging", ("preview_scale", "preview_jpeg_quality"),
     lambda c: c.logging.preview_rate_hz > 0, "logging.preview_rate_hz = 0 (no preview)"),
    ("logging", ("image_encoding",), lambda c: c.logging.perception_input != "none",
     'logging.perception_input = "none" (no perception input is logged)'),
    ("live", ("host", "port", "queue_size", "client_backlog"), lambda c: c.live.enabled,
     "the live view is off (live.enabled = false, no --live)"),
)


@lru_cache(maxsize=1)
def _shipped() -> Config:
    return load_config(None)


def _section(cfg: Config, path: str) -> Any:
    obj: Any = cfg
    for part in path.split("."):
        obj = getattr(obj, part)
    return obj


def ineffective_knobs(cfg: Config, reference: Config | None = None) -> list[str]:
    """One sentence per knob of ``cfg`` that is set (differs from ``reference``, default the
    shipped config) but has no effect in the mode ``cfg`` chooses."""
    ref = reference if reference is not None else _shipped()
    out: list[str] = []
    for path, knobs, active, why in _RULES:
        if active(cfg):
            continue
        section, ref_section = _section(cfg, path), _section(ref, path)
        names = knobs if knobs is not None else [
            f.name for f in dataclasses.fields(section) if f.name != "enabled"]
        for name in names:
            value = getattr(section, name)
            if value != getattr(ref_section, name):
                out.append(f"{path}.{name} = {value!r} has no effect: {why}")
    return out


def warn_ineffective_knobs(cfg: Config) -> list[str]:
    """Log :func:`ineffective_knobs` as warnings; returns them."""
    found = ineffective_knobs(cfg)
    for text in found:
        log.warning("config: %s", text)
    return found
