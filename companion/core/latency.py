"""Latency compensation: the error state predicted to the moment the command takes effect.

A frame is captured at ``t_cap``; its command reaches the vehicle at ``t_eff = now +
actuation_delay_s``. Meanwhile the vehicle kept flying on the commands sent before, so the RMPC
must start from ``eta_e(t_eff)``, not from the measured ``eta_e(t_cap)`` (a Smith-predictor
step). The prediction integrates the error dynamics of spec 4 (``companion.core.dynamics``)
from ``t_cap`` to ``t_eff`` with the inputs actually commanded over that interval (piecewise
constant, each from the time it took effect) and the target's motion held at its current value.
With the offset-free estimator the commanded input is the vehicle's achieved acceleration, so
the model is the right one to integrate. Pure numpy.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from companion.core.errors import ParamError
from companion.core.frozen import make


@dataclass(frozen=True)
class LatencyParams:
    """``[control.latency]``: ``enabled``; ``actuation_delay_s``: from the step's "now" to
    the vehicle acting on its setpoint (link + PX4's attitude loop onset; 0 in the lockstep
    emulator's ideal link); with ``auto_delay`` it is only the value used until the delay is
    measured. ``auto_delay``: measure that delay online from TIMESYNC probes sent with the
    setpoints (``companion.control.timesync.ActuationDelayMeter``): the median of the last
    ``auto_delay_window`` samples, once ``auto_delay_min_samples`` are in, probes at most
    ``auto_delay_probe_hz``; a sample above ``auto_delay_max_s`` is dropped (a reply queued
    behind a stall says nothing about the usual delay). ``max_prediction_s``: the prediction is
    never longer (a stale frame beyond it is predicted only this far, and the step notes it);
    ``step_s``: integration step (s). ``propagate_target``: advance the target's
    FOLLOW_TARGET sample (constant turn, :func:`companion.core.prediction.advance_target`)
    from its receipt to the frame's time for the error state, and to the predicted state's
    time for the horizon (docs/guides/vehicle-limits.md, the lag on curves)."""

    enabled: bool = True
    actuation_delay_s: float = 0.0
    auto_delay: bool = True
    auto_delay_window: int = 21
    auto_delay_min_samples: int = 5
    auto_delay_max_s: float = 0.5
    auto_delay_probe_hz: float = 10.0
    max_prediction_s: float = 0.3
    step_s: float = 0.01
    propagate_target: bool = False

    def __post_init__(self) -> None:
        if not (math.isfinite(self.actuation_delay_s) and 0.0 <= self.actuation_delay_s <= 1.0):
            raise ParamError("control.latency.actuation_delay_s: must be in [0, 1]")
        if not 1 <= self.auto_delay_window <= 1000:
            raise ParamError("control.latency.auto_delay_window: must be in [1, 1000]")
        if not 1 <= self.auto_delay_min_samples <= self.auto_delay_window:
            raise ParamError("control.latency.auto_delay_min_samples: must be in "
                             "[1, auto_delay_window]")
        if not (math.isfinite(self.auto_delay_max_s) and 0.0 < self.auto_delay_max_s <= 1.0):
            raise ParamError("control.latency.auto_delay_max_s: must be in (0, 1]")
        if not (math.isfinite(self.auto_delay_probe_hz) and 0.0 < self.auto_delay_probe_hz
                <= 100.0):
            raise ParamError("control.latency.auto_delay_probe_hz: must be in (0, 100]")
        if not (math.isfinite(self.max_prediction_s) and 0.0 < self.max_prediction_s <= 2.0):
            raise ParamError("control.latency.max_prediction_s: must be in (0, 2]")
        if not (math.isfinite(self.step_s) and 0.0 < self.step_s <= 0.05):
            raise ParamError("control.latency.step_s: must be in (0, 0.05]")


@dataclass(frozen=True)
class Prediction:
    """``eta_e`` (7,) at ``t_to_s``, predicted from ``t_from_s``; ``horizon_s`` actually
    predicted (``<= max_prediction_s``); ``clipped``: the wanted horizon was longer."""

    eta_e: np.ndarray
    t_from_s: float
    t_to_s: float
    horizon_s: float
    clipped: bool


def input_at(history: Sequence[tuple[float, np.ndarray]], t_s: float) -> np.ndarray:
    """The input in effect at ``t_s``: the newest ``(t_effect_s, u)`` with ``t_effect_s <=
    t_s`` (``history`` sorted by time); zero acceleration and yaw rate before the first."""
    # from the newest back (the wanted input is nearly always among the last few of a
    # history that keeps ~64): the same entry as the forward scan on a sorted history
    for i in range(len(history) - 1, -1, -1):
        t_eff, uu = history[i]
        if t_eff <= t_s + 1e-9:
            return np.asarray(uu, dtype=float)
    return np.zeros(4)


def predict_error_state(
    eta_e: ArrayLike,
    t_from_s: float,
    t_to_s: float,
    history: Sequence[tuple[float, np.ndarray]],
    v_a: ArrayLike,
    vdot_a: ArrayLike,
    psidot_a: float,
    z_star: float,
    params: LatencyParams,
) -> Prediction:
    """Integrate spec 4's ``f`` from ``t_from_s`` to ``t_to_s`` (explicit Euler, steps of at
    most ``params.step_s``, split at every input change). ``history``: ``(t_effect_s, u (4,))``
    sorted by time; ``v_a``, ``vdot_a`` (2,) and ``psidot_a`` the target's motion in the
    virtual frame, held constant. A non-positive horizon returns ``eta_e`` unchanged."""
    # plain floats (the same IEEE arithmetic as numpy's element-wise form, without its
    # per-call overhead on 7-vectors)
    eta = np.asarray(eta_e, dtype=float).reshape(7).tolist()
    va = np.asarray(v_a, dtype=float).tolist()
    vda = np.asarray(vdot_a, dtype=float).tolist()
    psidot_a = float(psidot_a)
    want = float(t_to_s) - float(t_from_s)
    horizon = min(max(want, 0.0), params.max_prediction_s)
    clipped = want > params.max_prediction_s
    t = float(t_from_s)
    t_end = t + horizon
    # the input changes inside (t, t_end): the history is sorted, so from the newest back
    changes: list[float] = []
    for i in range(len(history) - 1, -1, -1):
        te = history[i][0]
        if te <= t:
            break
        if te < t_end:
            changes.append(te)
    changes.reverse()
    for bound in [*changes, t_end]:
        while t < bound - 1e-12:
            h = min(params.step_s, bound - t)
            eta = _euler(eta, input_at(history, t).tolist(), va, vda, psidot_a, z_star, h)
            t += h
    return make(Prediction, eta_e=np.array(eta), t_from_s=float(t_from_s), t_to_s=t_end,
                horizon_s=horizon, clipped=clipped)


def _euler(eta: list[float], u: list[float], va: list[float], vda: list[float],
           psidot_a: float, z_star: float, h: float) -> list[float]:
    """``eta + h f(eta, u)``: :func:`companion.core.dynamics.error_dynamics` (spec 4) written
    out on plain floats, term by term (the same values; the generic form checks its
    arguments for CasADi symbols on every call, many times per control step here)."""
    s1, s2, _, _, ve1, ve2, ve3 = eta
    psidot = u[3]
    ue0 = u[0] + u[3] * va[1] - vda[0]
    ue1 = u[1] - u[3] * va[0] - vda[1]
    f = (-ve1 / z_star + s2 * psidot, -ve2 / z_star - s1 * psidot, -ve3 / z_star,
         -psidot + psidot_a, psidot * ve2 + ue0, -psidot * ve1 + ue1, u[2])
    return [e + h * d for e, d in zip(eta, f, strict=True)]


__all__ = ["LatencyParams", "Prediction", "input_at", "predict_error_state"]
