"""The values that flow through one control step, stage to stage (``ControlPipeline.step``).

perceive -> :class:`Sighting`; state at the frame's time -> :class:`FrameState`; predict to the
command's effect -> :class:`Predicted`; plan -> :class:`Plan`; decide ->
:class:`~companion.control.safety.SafetyDecision`; command -> :class:`Command`; the whole step
-> :class:`StepResult` (logged as ``/control/step``). Frozen and typed, so a test can build
one, run a stage alone and read what it produced.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from companion.control.safety import SafetyDecision
from companion.control.telemetry import AttitudeSample, KinematicsSample
from companion.core.disturbance import DisturbanceEstimate
from companion.core.latency import Prediction
from companion.core.rmpc import RmpcResult, TargetMotion
from companion.core.setpoint import AttitudeSetpoint
from companion.core.state import ErrorState


@dataclass(frozen=True)
class Sighting:
    """What perception made of one frame: ``status`` ("ok", "lost", "rejected", ...) and
    ``reason``; with "ok", the corners (4, 2) in pixels and the points (4, 2) on the virtual
    image plane (m, focal-length units); ``region``: ``(x0, y0, x1, y1)`` pixels (end
    exclusive) of the image perception read, when known."""

    status: str
    reason: str
    corners_px: np.ndarray | None = None
    points_m: np.ndarray | None = None
    region: tuple[int, int, int, int] | None = None


@dataclass(frozen=True)
class VelocityEstimate:
    """The target's velocity used this step and where it came from."""

    v_a_ned_m_s: np.ndarray
    a_a_ned_m_s2: np.ndarray
    yaw_rate_rad_s: float
    source: str  # "follow_target" | "image_estimator" | "none"


@dataclass(frozen=True)
class StepResult:
    """Everything one control step computed (logged as ``/control/step``)."""

    t_s: float
    perception_status: str
    perception_reason: str
    corners_px: np.ndarray | None
    error_state: ErrorState | None
    target_velocity: VelocityEstimate | None
    rmpc: Any | None  # companion.core.rmpc.RmpcResult
    safety: SafetyDecision
    u: np.ndarray | None  # (r1, r2, r3, psidot_q) actually commanded
    setpoint: AttitudeSetpoint | None
    notes: tuple[str, ...] = ()
    timings_ms: dict[str, float] = field(default_factory=dict)
    estimator: DisturbanceEstimate | None = None  # what the command used (None: disabled)
    prediction: Prediction | None = None  # latency compensation (None: not applied)
    t_now_s: float | None = None  # "now" on the frame's time base when the step ran
    in_control: bool | None = None  # the runtime's view: our setpoints fly the vehicle
    #: ``(x0, y0, x1, y1)`` pixels (end exclusive) of the image perception read, when known
    input_region: tuple[int, int, int, int] | None = None
    #: tilt-lag lead term added to the horizontal command (2,) NED m/s^2 (None: not led)
    lead_m_s2: np.ndarray | None = None
    #: the actuation delay (s) the step placed its command and prediction with
    actuation_delay_s: float | None = None

    def to_record(self) -> dict[str, Any]:
        """JSON-ready record for the log."""
        es = self.error_state
        r = self.rmpc
        return {
            "t_s": self.t_s,
            "perception": {"status": self.perception_status, "reason": self.perception_reason,
                           "corners_px": _lst(self.corners_px)},
            "eta_e": _lst(es.eta_e) if es else None,
            "s": _lst(es.s) if es else None,
            "p_e": _p_e(es) if es else None,
            "attitude_rpy_rad": [es.roll_rad, es.pitch_rad, es.yaw_rad] if es else None,
            "target_velocity": None if self.target_velocity is None else {
                "v_a_ned_m_s": _lst(self.target_velocity.v_a_ned_m_s),
                "source": self.target_velocity.source,
            },
            "rmpc": None if r is None else {
                "mode": r.mode, "success": bool(r.success), "status": str(r.status),
                "cost": _f(r.cost), "iterations": int(r.iterations),
                "solve_time_s": _f(r.solve_time_s), "u0": _lst(r.u0),
                "eta_pred": _lst(r.eta_pred), "u_pred": _lst(r.u_pred),
            },
            "safety": {"level": self.safety.level.value, "reason": self.safety.reason,
                       "changed": self.safety.changed},
            "u": _lst(self.u),
            "setpoint": None if self.setpoint is None else {
                "q_wxyz": _lst(self.setpoint.q_wxyz), "thrust": self.setpoint.thrust_norm,
                "roll_rad": self.setpoint.roll_rad, "pitch_rad": self.setpoint.pitch_rad,
                "yaw_rad": self.setpoint.yaw_rad,
            },
            "notes": list(self.notes),
            "timings_ms": self.timings_ms,
            "t_now_s": self.t_now_s,
            "in_control": self.in_control,
            "estimator": None if self.estimator is None else self.estimator.to_record(),
            "lead_m_s2": _lst(self.lead_m_s2),
            "actuation_delay_s": self.actuation_delay_s,
            "latency": None if self.prediction is None else {
                "frame_age_s": self.prediction.t_to_s - self.prediction.t_from_s,
                "horizon_s": self.prediction.horizon_s,
                "clipped": self.prediction.clipped,
                "eta_pred": _lst(self.prediction.eta_e),
            },
        }


@dataclass(frozen=True)
class FrameState:
    """The state at the frame's capture time: the attitude and kinematics then, the measured
    yaw (rad, ``None`` without attitude), the error state (``None``: no target, or moments
    rejected) with the target velocity it used, whether the inputs were finite, and the
    perception verdict (a target whose moments are rejected turns "ok" into "rejected")."""

    attitude: AttitudeSample | None
    kinematics: KinematicsSample | None
    yaw_rad: float | None
    error_state: ErrorState | None
    velocity: VelocityEstimate | None
    inputs_finite: bool
    perception_status: str
    perception_reason: str


@dataclass(frozen=True)
class Predicted:
    """The error state moved to when the command takes effect: ``eta0`` (9,) the planner
    starts from (the measured one when not predicted), the target's motion over the horizon,
    the latency prediction (``None``: not applied) and its notes."""

    eta0: np.ndarray
    motion: TargetMotion
    prediction: Prediction | None
    notes: tuple[str, ...] = ()


@dataclass(frozen=True)
class Plan:
    """The controller's answer (``None``: no valid state to plan from) and whether it solved
    (a fallback is not)."""

    result: RmpcResult | None
    solver_ok: bool


@dataclass(frozen=True)
class Command:
    """What is commanded: ``u`` (r1, r2, r3, psidot_q) actually commanded (``None``: the
    hover or silence), the attitude setpoint (``None``: silence), the tilt-lag lead added
    (2,) NED m/s^2 (``None``: not led), the disturbance estimate used and the notes."""

    u: np.ndarray | None
    setpoint: AttitudeSetpoint | None
    lead_m_s2: np.ndarray | None
    estimate: DisturbanceEstimate | None
    notes: tuple[str, ...] = ()


def _lst(a: Any) -> Any:
    if a is None:
        return None
    if isinstance(a, np.ndarray) and a.dtype == np.float64:
        return a.tolist()  # most values: no conversion to make
    return np.asarray(a, dtype=float).tolist()


def _p_e(es: ErrorState) -> list[float]:
    """``eta_e[:2] / s[2]`` (numpy's element-wise quotients, on floats)."""
    e0, e1 = es.eta_e[:2].tolist()
    s3 = float(es.s[2])
    return [e0 / s3, e1 / s3]


def _f(x: Any) -> float | None:
    try:
        v = float(x)
    except (TypeError, ValueError):
        return None
    return v if math.isfinite(v) else None


__all__ = ["Command", "FrameState", "Plan", "Predicted", "Sighting", "StepResult",
           "VelocityEstimate"]
