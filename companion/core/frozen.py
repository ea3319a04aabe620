"""Frozen dataclasses built without their generated ``__init__`` (the control step's values).

A frozen dataclass's ``__init__`` sets each field through ``object.__setattr__`` (~0.2-0.3 us
a field, plus the call): the ~20 values one control step builds cost ~30-60 us that way.
:func:`make` gives the same object (equal, the same ``repr``, frozen afterwards) by writing
the instance's ``__dict__`` at once. It runs no ``__post_init__``: only for values whose
fields the caller built as the class wants them (its arrays read-only where the class makes
them so), which is what a test holding each call site to the constructor checks.
"""

from __future__ import annotations

import dataclasses
from typing import Any, TypeVar

T = TypeVar("T")

_new = object.__new__
_DEFAULTS: dict[type, dict[str, Any]] = {}


def _defaults(cls: type) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for f in dataclasses.fields(cls):
        if f.default is not dataclasses.MISSING:  # (a default factory's field: given)
            out[f.name] = f.default
    _DEFAULTS[cls] = out
    return out


def make(cls: type[T], **fields: Any) -> T:
    """``cls(**fields)`` without ``__init__`` and ``__post_init__`` (module docstring); the
    fields not given take their defaults (a field with a default factory must be given)."""
    obj = _new(cls)
    d = obj.__dict__
    defaults = _DEFAULTS.get(cls)
    d.update(_defaults(cls) if defaults is None else defaults)
    d.update(fields)
    return obj


__all__ = ["make"]
