"""The per-frame control computation, shared by the live process and the offline replay.

``ControlPipeline.step(image, t_s, store)`` runs: perception (pixels -> target corners) ->
virtual-camera moments and error state (core) -> safety supervision -> RMPC or a fallback law
-> attitude/thrust setpoint (spec 5). It does no I/O and reads no clock: given the same frames
and telemetry in the same order it returns the same commands, which is what makes replay exact.

The vehicle is never sent a command computed from bad data: every value that reaches a
setpoint passed a finiteness check, and a setpoint that fails one is replaced by the level
hover setpoint (which depends on no measurement) or by silence.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from companion.config import Config
from companion.control.safety import Health, SafetyDecision, SafetyLevel, SafetySupervisor
from companion.control.seams import Controller, Perceiver
from companion.control.telemetry import KinematicsSample, TelemetryStore
from companion.core.design import design_terminal
from companion.core.estimator import ImageVelocityEstimator
from companion.core.geometry import euler_zyx_from_quat, rectangle_corners_m, wrap_pi
from companion.core.moments import DegenerateTargetError, a_star, fold_s4
from companion.core.prediction import predict_target_motion
from companion.core.reacquire import reacquire_input
from companion.core.rmpc import RmpcResult, TargetMotion, terminal_law
from companion.core.setpoint import AttitudeSetpoint, attitude_setpoint, hover_setpoint
from companion.core.state import ErrorState, MeasurementError, build_error_state
from companion.core.terminal import TerminalDesign

log = logging.getLogger(__name__)

YAW_RESYNC_RAD = 0.2


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
            "p_e": _lst(es.eta_e[:2] / es.s[2]) if es else None,
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
        }


class ControlPipeline:
    """One object per flight; ``step`` once per camera frame, in order."""

    def __init__(self, cfg: Config, perception: Perceiver, rmpc: Controller | None = None,
                 terminal: TerminalDesign | None = None,
                 timer: Callable[[], float] | None = None) -> None:
        self.cfg = cfg
        self.perception = perception
        self.terminal = terminal or design_terminal(cfg.rmpc, cfg.camera)
        if rmpc is None:
            from companion.control.factory import build_controller

            rmpc = build_controller(cfg, self.terminal)
        self.rmpc: Controller = rmpc
        self.safety = SafetySupervisor(cfg.safety)
        self.a_star = a_star(_target_points(cfg), cfg.rmpc.desired_depth_m,
                             cfg.camera.focal_length_m)
        self._estimator = ImageVelocityEstimator(cfg.rmpc.desired_depth_m)
        self._s4_prev: float | None = None
        self._last_seen_s = -math.inf
        self._last_yaw = 0.0
        self._yaw_sp: float | None = None
        self.force_solver_failure = False
        # Optional stage timing (seconds clock, e.g. time.perf_counter): measurement only,
        # it never changes a result, so replay stays exact with or without it.
        self._timer = timer  # fault injection (tests, MAV_CMD_INJECT_FAILURE-like)

    # ------------------------------------------------------------------------------------------

    def step(self, image: np.ndarray | None, t_s: float, store: TelemetryStore) -> StepResult:
        cfg = self.cfg
        notes: list[str] = []
        clock = self._timer
        marks: list[tuple[str, float]] = [("start", clock())] if clock else []
        # 1. perception
        corners = None
        points_m = None
        if image is None:
            p_status, p_reason = "lost", "no image"
        else:
            pr = self.perception.process(image)
            p_status, p_reason = pr.status, pr.reason
            if pr.status == "ok":
                corners, points_m = pr.corners_px, pr.points_m
        if clock:
            marks.append(("detect", clock()))
        # 2. telemetry at the frame's time
        att = store.attitude_at(t_s)
        kin = store.kinematics
        finite = True
        es: ErrorState | None = None
        vel: VelocityEstimate | None = None
        if att is not None:
            roll, pitch, yaw = euler_zyx_from_quat(att.q_wxyz)
            self._last_yaw = yaw if math.isfinite(yaw) else self._last_yaw
        if points_m is not None and att is not None and kin is not None:
            vel = self._target_velocity(t_s, store)
            try:
                es = build_error_state(
                    points_m, roll_rad=roll, pitch_rad=pitch, yaw_rad=yaw,
                    yaw_rate_rad_s=att.yaw_rate_rad_s, v_q_ned_m_s=kin.vel_ned_m_s,
                    v_a_ned_m_s=vel.v_a_ned_m_s, a_a_ned_m_s2=vel.a_a_ned_m_s2,
                    psidot_a_rad_s=vel.yaw_rate_rad_s, a_star=self.a_star,
                    lam=cfg.camera.focal_length_m,
                    # folded: a target turning faster than the yaw-rate bound must not wind
                    # s4 up (its period: pi for the moments, 2 pi for ordered corners)
                    s4_prev_rad=fold_s4(self._s4_prev, 2.0 * math.pi
                                        if cfg.target.pattern == "aruco" else math.pi),
                    # a square marker's moments carry no orientation: use its corner order
                    heading_from_corners=cfg.target.pattern == "aruco",
                )
            except (MeasurementError, DegenerateTargetError) as exc:
                finite = not isinstance(exc, MeasurementError)
                p_status, p_reason = "rejected", f"moments: {exc}"
                es = None
            if es is not None:
                self._s4_prev = float(es.s[3])
                self._last_seen_s = t_s
                if vel.source != "follow_target":
                    vel = VelocityEstimate(
                        self._estimator.update(t_s, es.s, es.v_q_v_m_s, yaw, att.yaw_rate_rad_s),
                        np.zeros(3), 0.0, "image_estimator")
                else:
                    self._estimator.update(t_s, es.s, es.v_q_v_m_s, yaw, att.yaw_rate_rad_s)
        if clock:
            marks.append(("moments", clock()))
        # 3. solve while the state is valid
        rmpc_res = None
        solver_ok = True
        motion: TargetMotion | None = None
        if es is not None and vel is not None:
            motion = predict_target_motion(
                vel.v_a_ned_m_s, vel.a_a_ned_m_s2, vel.yaw_rate_rad_s, es.yaw_rad,
                cfg.rmpc.horizon, cfg.rmpc.dt_s)
            if self.force_solver_failure:
                rmpc_res = self._fallback(es.eta_e, motion, "injected failure")
            else:
                rmpc_res = self.rmpc.solve(es.eta_e, motion)
            solver_ok = rmpc_res.mode != "fallback"
        if clock:
            marks.append(("solve", clock()))
        health = Health(
            t_s=t_s,
            telemetry_age_s=store.telemetry_age_s(t_s),
            target_age_s=t_s - self._last_seen_s,
            follow_target_age_s=store.target_age_s(t_s),
            inputs_finite=finite,
            solver_ok=solver_ok,
        )
        decision = self.safety.update(health)
        if decision.changed:
            log.warning("safety -> %s: %s", decision.level.value, decision.reason)
        # 4. the command
        u: np.ndarray | None = None
        sp: AttitudeSetpoint | None = None
        level = decision.level
        if level is SafetyLevel.TRACKING and rmpc_res is not None:
            u = np.asarray(rmpc_res.u0, dtype=float)
        elif level is SafetyLevel.TERMINAL and es is not None and motion is not None:
            u = self._fallback(es.eta_e, motion, "safety terminal").u0
        elif level is SafetyLevel.REACQUIRE and att is not None and kin is not None:
            u = self._reacquire(store, kin, yaw)
        if u is not None:
            try:
                sp = attitude_setpoint(
                    u, self._yaw_reference(), cfg.rmpc.dt_s, g_m_s2=cfg.rmpc.g_m_s2,
                    hover_thrust=cfg.control.hover_thrust, thrust_min=cfg.control.thrust_min,
                    thrust_max=cfg.control.thrust_max)
            except ValueError as exc:
                notes.append(f"setpoint refused: {exc}")
                sp = None
                level = SafetyLevel.HOVER
        if sp is None and level is not SafetyLevel.SILENT:
            sp = hover_setpoint(self._last_yaw, hover_thrust=cfg.control.hover_thrust,
                                thrust_min=cfg.control.thrust_min,
                                thrust_max=cfg.control.thrust_max)
            u = None
        self._yaw_sp = sp.yaw_rad if sp is not None else None
        if clock:
            marks.append(("command", clock()))
        timings = {name: (t - marks[i][1]) * 1e3 for i, (name, t) in enumerate(marks[1:])}
        return StepResult(
            timings_ms=timings,
            t_s=t_s, perception_status=p_status, perception_reason=p_reason,
            corners_px=corners, error_state=es, target_velocity=vel, rmpc=rmpc_res,
            safety=decision, u=u, setpoint=sp, notes=tuple(notes),
        )

    # ------------------------------------------------------------------------------------------

    def _fallback(self, eta: np.ndarray, motion: TargetMotion, why: str) -> RmpcResult:
        """The terminal law ``K eta + Gamma`` clipped to U (spec 7), as a 'fallback' result."""
        v_a, vdot_a, psidot_a = motion.stage(0)
        u0 = terminal_law(eta, v_a, vdot_a, psidot_a, self.terminal.k, self.cfg.rmpc.u_max)
        n = self.cfg.rmpc.horizon
        return RmpcResult(False, "fallback", why, why, math.nan, 0, 0.0, u0,
                          np.tile(eta, (n + 1, 1)), np.tile(u0, (n, 1)), 0.0, (), motion)

    def _yaw_reference(self) -> float:
        """Yaw the next setpoint builds on: the previous yaw setpoint, re-synced to the measured
        yaw when they differ by more than ``YAW_RESYNC_RAD`` (or there is none).

        Spec 5 writes ``psi_d = psi_q + psidot dt`` with the measured ``psi_q``. Behind a real
        attitude loop (first order, time constant tau) that commands a yaw step of only
        ``psidot dt`` per step and the achieved rate settles near ``psidot dt / tau`` rather
        than ``psidot``; integrating the setpoint makes the achieved yaw rate equal the
        commanded one in steady state. With an instantaneous attitude (the paper's model) the
        two are the same.
        """
        prev = self._yaw_sp
        if prev is None or abs(wrap_pi(prev - self._last_yaw)) > YAW_RESYNC_RAD:
            return self._last_yaw
        return prev

    def _target_velocity(self, t_s: float, store: TelemetryStore) -> VelocityEstimate:
        tgt = store.target
        if tgt is not None and t_s - tgt.t_s <= self.cfg.safety.follow_target_timeout_s:
            return VelocityEstimate(np.array(tgt.vel_ned_m_s), np.array(tgt.acc_ned_m_s2),
                                    tgt.yaw_rate_rad_s, "follow_target")
        return VelocityEstimate(self._estimator.v_ned.copy(), np.zeros(3), 0.0, "image_estimator")

    def _reacquire(self, store: TelemetryStore, kin: KinematicsSample,
                   yaw: float) -> np.ndarray | None:
        tgt = store.target
        if tgt is None:
            return None
        rel = np.array(tgt.pos_ned_m) - np.array(kin.pos_ned_m)
        sc = self.cfg.safety
        return reacquire_input(
            rel, np.array(kin.vel_ned_m_s), np.array(tgt.vel_ned_m_s), np.array(tgt.acc_ned_m_s2),
            yaw_q_rad=yaw, yaw_a_rad=tgt.yaw_rad, height_above_target_m=float(rel[2]),
            climb_rate_m_s=sc.reacquire_climb_rate_m_s, max_height_m=sc.reacquire_max_height_m,
            u_max=self.cfg.rmpc.u_max)


def _target_points(cfg: Config) -> np.ndarray:
    t = cfg.target
    if t.pattern == "aruco":
        return rectangle_corners_m(t.aruco_size_m, t.aruco_size_m)
    return rectangle_corners_m(t.length_m, t.width_m)


def _lst(a: Any) -> Any:
    if a is None:
        return None
    return np.asarray(a, dtype=float).tolist()


def _f(x: Any) -> float | None:
    try:
        v = float(x)
    except (TypeError, ValueError):
        return None
    return v if math.isfinite(v) else None


__all__ = ["ControlPipeline", "StepResult", "VelocityEstimate"]
