"""One formula, two backends: numpy (vectorised numbers) and CasADi (symbols).

The controller's model and the perception math use the same functions, so they cannot drift.
"""

from __future__ import annotations

from types import ModuleType
from typing import Any

import casadi as ca
import numpy as np

_SYMBOLIC = (ca.SX, ca.MX, ca.DM)


def is_symbolic(*args: Any) -> bool:
    return any(isinstance(a, _SYMBOLIC) for a in args)


def xp(*args: Any) -> ModuleType:
    """The module (``casadi`` or ``numpy``) whose sin/cos/sqrt/... fit these arguments."""
    return ca if is_symbolic(*args) else np


def atan(mod: ModuleType, x: Any) -> Any:
    return ca.atan(x) if mod is ca else np.arctan(x)


def asin(mod: ModuleType, x: Any) -> Any:
    return ca.asin(x) if mod is ca else np.arcsin(x)
