"""Values built without their frozen ``__init__`` (companion/core/frozen.py) are the ones the
constructor builds: the same fields, the arrays read-only as ``__post_init__`` makes them."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

import numpy as np
import pytest

from companion.core.frozen import make
from companion.core.moments import image_moments_xy
from companion.core.prediction import predict_target_motion
from companion.core.rmpc_types import RmpcParameterError, TargetMotion
from companion.core.setpoint import attitude_setpoint
from companion.core.state import build_error_state


@dataclass(frozen=True)
class _Three:
    a: float
    b: str = "b"
    c: tuple[int, ...] = ()


def _same(built: Any) -> None:
    """``built`` equals the constructor's object of its fields, and the constructor's
    ``__post_init__`` would have kept its arrays as they are (owned, read-only)."""
    again = dataclasses.replace(built)  # (the constructor, __post_init__ included)
    for f in dataclasses.fields(built):
        x, y = getattr(built, f.name), getattr(again, f.name)
        if isinstance(x, np.ndarray):
            assert not x.flags.writeable, f.name
            assert x.dtype == y.dtype and x.shape == y.shape, f.name
            assert np.array_equal(x, y), f.name
        elif dataclasses.is_dataclass(x):
            _same(x)
        else:
            assert x == y or (x != x and y != y), f.name  # (NaN)


def test_make_fills_defaults_and_stays_frozen() -> None:
    v = make(_Three, a=1.0, c=(2,))
    assert v == _Three(1.0, "b", (2,))
    assert repr(v) == repr(_Three(1.0, "b", (2,)))
    with pytest.raises(dataclasses.FrozenInstanceError):
        v.a = 2.0  # type: ignore[misc]


def test_the_control_steps_values_are_the_constructors() -> None:
    pts = np.array([[1.0e-4, 2.0e-4], [-3.0e-4, 2.5e-4], [-2.0e-4, -3.0e-4], [3.5e-4, -2.0e-4]])
    es = build_error_state(pts, roll_rad=0.05, pitch_rad=-0.03, yaw_rad=0.4,
                           yaw_rate_rad_s=0.1, v_q_ned_m_s=(0.5, 0.2, 0.0),
                           v_a_ned_m_s=(0.6, 0.1, 0.0), a_a_ned_m_s2=(0.01, 0.02, 0.0),
                           psidot_a_rad_s=0.05, a_star=8.036e-7, lam=2.8e-3)
    _same(es)
    assert es.eta_e is dataclasses.replace(es).eta_e  # owned and read-only: not copied
    _same(image_moments_xy([1e-4, -2e-4, 3e-4], [2e-4, 1e-4, -2e-4], 8.036e-7, 2.8e-3, None))
    sp = attitude_setpoint([0.3, -0.2, 0.1, 0.05], 0.4, 0.05, hover_thrust=0.5,
                           thrust_min=0.1, thrust_max=0.9)
    _same(sp)
    assert sp.q_wxyz is dataclasses.replace(sp).q_wxyz


@pytest.mark.parametrize("d", [None, (0.01, -0.02, 0.03)])
def test_the_predicted_motion_is_the_constructors(d: tuple[float, float, float] | None) -> None:
    m = predict_target_motion(np.array([0.5, 0.3, 0.0]), np.array([0.01, 0.02, 0.0]), 0.05,
                              0.3, 16, 0.05, d, 1.2)
    _same(m)
    # the same numbers as the array form of the disturbance
    m2 = predict_target_motion(np.array([0.5, 0.3, 0.0]), np.array([0.01, 0.02, 0.0]), 0.05,
                               0.3, 16, 0.05, None if d is None else np.array(d), 1.2)
    for f in dataclasses.fields(m):
        assert np.array_equal(getattr(m, f.name), getattr(m2, f.name))


def test_built_target_motion_checks_as_the_constructor() -> None:
    n = 4
    with pytest.raises(RmpcParameterError, match="v_a_m_s"):
        TargetMotion.built(np.full((n, 2), np.nan), np.zeros((n, 2)), np.zeros(n))
    with pytest.raises(RmpcParameterError, match="need"):
        TargetMotion.built(np.zeros((n, 3)), np.zeros((n, 2)), np.zeros(n))
    v = np.ones((n, 2))
    m = TargetMotion.built(v, np.zeros((n, 2)), np.zeros(n))
    assert m.v_a_m_s is v and not v.flags.writeable  # taken, not copied
    assert np.array_equal(m.disturbance_v_m_s2, np.zeros((n, 3)))
