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
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from companion.config import Config
from companion.control.safety import Health, SafetyDecision, SafetyLevel, SafetySupervisor
from companion.control.seams import Controller, Perceiver
from companion.control.telemetry import KinematicsSample, TelemetryStore
from companion.core.design import design_terminal
from companion.core.disturbance import (
    DisturbanceEstimate,
    DisturbanceEstimator,
    compensated_input,
)
from companion.core.estimator import ImageVelocityEstimator
from companion.core.geometry import (
    camera_to_body_rotation,
    euler_zyx_from_quat,
    rectangle_corners_m,
    rotation_from_quat,
    wrap_pi,
)
from companion.core.latency import Prediction, predict_error_state
from companion.core.lead import TiltLead
from companion.core.moments import DegenerateTargetError, a_star, fold_s4
from companion.core.prediction import predict_target_motion
from companion.core.reacquire import reacquire_input
from companion.core.rmpc import RmpcResult, TargetMotion, terminal_law
from companion.core.setpoint import AttitudeSetpoint, attitude_setpoint, hover_setpoint
from companion.core.state import ErrorState, MeasurementError, build_error_state
from companion.core.terminal import TerminalDesign
from companion.perception import PerceptionResult

log = logging.getLogger(__name__)

YAW_RESYNC_RAD = 0.2
PX4_MAIN_OFFBOARD = 6  # PX4 custom main mode (companion/link/px4.py; core-side copy)


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
        # a camera turned about its optical axis: points re-projected into body axes
        self._cam_to_body = (None if cfg.camera.mount_yaw_rad == 0.0
                             else camera_to_body_rotation(cfg.camera.mount_rpy_rad))
        self._last_seen_s = -math.inf
        self._last_yaw = 0.0
        self._yaw_sp: float | None = None
        est = cfg.control.estimator
        self._dist: DisturbanceEstimator | None = (
            DisturbanceEstimator(est, cfg.control.hover_thrust, cfg.rmpc.g_m_s2)
            if est.enabled else None)
        # (t_effect_s, u: the vehicle's acceleration/yaw rate asked for (4,), thrust sent)
        self._commands: deque[tuple[float, np.ndarray, float]] = deque(maxlen=64)
        self._control_since: float | None = None  # since when our setpoints fly the vehicle
        self._lead = TiltLead(cfg.control.lead)
        self.force_solver_failure = False
        # Optional stage timing (seconds clock, e.g. time.perf_counter): measurement only,
        # it never changes a result, so replay stays exact with or without it.
        self._timer = timer  # fault injection (tests, MAV_CMD_INJECT_FAILURE-like)

    # ------------------------------------------------------------------------------------------

    def step(self, image: np.ndarray | None, t_s: float, store: TelemetryStore,
             t_now_s: float | None = None, in_control: bool | None = None,
             perceived: PerceptionResult | None = None,
             actuation_delay_s: float | None = None) -> StepResult:
        """One frame captured at ``t_s``; ``t_now_s``: the time the step runs (same time base;
        default ``t_s``, i.e. no latency known); ``actuation_delay_s``: from ``t_now_s`` to the
        vehicle flying this step's command, as measured by the runtime
        (``control.latency.auto_delay``; default ``control.latency.actuation_delay_s``);
        ``in_control``: our setpoints fly the vehicle
        (the runtime knows OFFBOARD was requested before the 1 Hz HEARTBEAT confirms it;
        default: the HEARTBEAT's mode). ``perceived``: the perception result of that frame
        computed elsewhere (a replay from logged detections); ``image`` is then not looked at."""
        cfg = self.cfg
        t_now = t_s if t_now_s is None or not math.isfinite(t_now_s) else max(t_s, t_now_s)
        notes: list[str] = []
        clock = self._timer
        marks: list[tuple[str, float]] = [("start", clock())] if clock else []
        # 1. perception
        corners = None
        points_m = None
        region = None
        if perceived is None and image is not None:
            perceived = self.perception.process(image)
            region = getattr(self.perception, "last_region", None)
        if perceived is None:
            p_status, p_reason = "lost", "no image"
        else:
            pr = perceived
            p_status, p_reason = pr.status, pr.reason
            if pr.status == "ok":
                corners, points_m = pr.corners_px, pr.points_m
        if clock:
            marks.append(("detect", clock()))
        # 2. telemetry at the frame's time
        att = store.attitude_at(t_s)
        kin = store.kinematics
        self._update_estimator(store, in_control, t_now)
        lat = cfg.control.latency
        delay_s = lat.actuation_delay_s
        if actuation_delay_s is not None and math.isfinite(actuation_delay_s):
            delay_s = min(max(float(actuation_delay_s), 0.0), 1.0)
        kin_cap = store.kinematics_at(t_s) if lat.enabled else kin
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
                    yaw_rate_rad_s=att.yaw_rate_rad_s,
                    v_q_ned_m_s=(kin_cap or kin).vel_ned_m_s,
                    v_a_ned_m_s=vel.v_a_ned_m_s, a_a_ned_m_s2=vel.a_a_ned_m_s2,
                    psidot_a_rad_s=vel.yaw_rate_rad_s, a_star=self.a_star,
                    lam=cfg.camera.focal_length_m,
                    # folded: a target turning faster than the yaw-rate bound must not wind
                    # s4 up (its period: pi for the moments, 2 pi for ordered corners)
                    s4_prev_rad=fold_s4(self._s4_prev, 2.0 * math.pi
                                        if cfg.target.pattern == "aruco" else math.pi),
                    # a square marker's moments carry no orientation: use its corner order
                    heading_from_corners=cfg.target.pattern == "aruco",
                    cam_to_body=self._cam_to_body,
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
        pred: Prediction | None = None
        eta0: np.ndarray | None = None
        if es is not None and vel is not None:
            motion = predict_target_motion(
                vel.v_a_ned_m_s, vel.a_a_ned_m_s2, vel.yaw_rate_rad_s, es.yaw_rad,
                cfg.rmpc.horizon, cfg.rmpc.dt_s,
                None if self._dist is None else np.array(self._dist.estimate().d_ned_m_s2),
                cfg.rmpc.eta_max[4] if cfg.rmpc.target_speed_extrapolation == "box" else None)
            eta0 = es.eta_e
            if lat.enabled:
                v_a, vdot_a, psidot_a = motion.stage(0)
                pred = predict_error_state(
                    es.eta_e, t_s, t_now + delay_s,
                    [(t, u) for t, u, _ in self._commands], v_a, vdot_a, psidot_a,
                    cfg.rmpc.desired_depth_m, lat)
                if np.all(np.isfinite(pred.eta_e)):
                    eta0 = pred.eta_e
                    if pred.clipped:
                        notes.append(f"latency: frame {t_now - t_s:.3f} s old, predicted "
                                     f"{pred.horizon_s:.3f} s only")
                else:
                    notes.append("latency: non-finite prediction, measured state used")
                    pred = None
            if self.force_solver_failure:
                rmpc_res = self._fallback(eta0, motion, "injected failure")
            else:
                rmpc_res = self.rmpc.solve(eta0, motion)
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
        elif level is SafetyLevel.TERMINAL and eta0 is not None and motion is not None:
            u = self._fallback(eta0, motion, "safety terminal").u0
        elif level is SafetyLevel.REACQUIRE and att is not None and kin is not None:
            u = self._reacquire(store, kin, yaw)
        est = self._dist.estimate() if self._dist is not None else None
        lead_m_s2: np.ndarray | None = None
        if u is not None:
            try:
                # led only while our setpoints fly the vehicle (before OFFBOARD PX4 holds
                # level with its own controller, so a difference of streamed commands is not
                # a change of tilt the vehicle must catch up with) and the controller tracks
                # in its nominal problem: the recovery's chase and the fallbacks' jumps are
                # flown as commanded (docs/reference/estimator.md 2b)
                led = (in_control is not False and level is SafetyLevel.TRACKING
                       and rmpc_res is not None
                       and rmpc_res.mode not in ("recovery", "fallback"))
                sp, lead_m_s2 = self._setpoint(u, self._yaw_reference(), cfg.rmpc.dt_s, est,
                                               t_now if led else None)
            except ValueError as exc:
                notes.append(f"setpoint refused: {exc}")
                self._lead.reset()
                sp = None
                level = SafetyLevel.HOVER
        if sp is None:
            lead_m_s2 = None  # a refused setpoint's lead was never sent
            self._lead.reset()
        if sp is None and level is not SafetyLevel.SILENT:
            u = None
            sp = None
            if est is not None:  # hold still against the estimated disturbance
                try:
                    sp, _ = self._setpoint(np.zeros(4), self._last_yaw, 0.0, est)
                except ValueError as exc:
                    notes.append(f"compensated hover refused: {exc}")
            if sp is None:
                sp = hover_setpoint(self._last_yaw, hover_thrust=cfg.control.hover_thrust,
                                    thrust_min=cfg.control.thrust_min,
                                    thrust_max=cfg.control.thrust_max)
        if sp is not None:
            t_eff = t_now + delay_s
            if self._commands and t_eff < self._commands[-1][0]:
                t_eff = self._commands[-1][0]  # keep the history in time order
            # what the vehicle will fly: before OFFBOARD (in_control False) PX4 holds with its
            # own controller and ignores the stream, so the latency prediction must integrate
            # zero acceleration there, not the inputs we streamed
            flown = u is not None and in_control is not False
            self._commands.append((t_eff,
                                   np.array(u, dtype=float) if flown else np.zeros(4),
                                   sp.thrust_norm))
        self._yaw_sp = sp.yaw_rad if sp is not None else None
        if clock:
            marks.append(("command", clock()))
        timings = {name: (t - marks[i][1]) * 1e3 for i, (name, t) in enumerate(marks[1:])}
        return StepResult(
            timings_ms=timings,
            t_s=t_s, perception_status=p_status, perception_reason=p_reason,
            corners_px=corners, error_state=es, target_velocity=vel, rmpc=rmpc_res,
            safety=decision, u=u, setpoint=sp, notes=tuple(notes), estimator=est,
            prediction=pred, t_now_s=t_now, in_control=in_control, input_region=region,
            lead_m_s2=lead_m_s2, actuation_delay_s=delay_s,
        )

    def _setpoint(self, u: np.ndarray, yaw_rad: float, dt_s: float,
                  est: DisturbanceEstimate | None,
                  lead_at_s: float | None = None
                  ) -> tuple[AttitudeSetpoint, np.ndarray | None]:
        """Spec 5 for the acceleration ``u``; with the estimator, the specific force that gives
        ``u`` despite the disturbance, at the estimated hover thrust. ``lead_at_s``: the
        controller's command at that time, led for the vehicle's tilt lag (companion/core/
        lead.py); ``None``: a command that is not led (level hover), which restarts the lead.
        Returns the setpoint and the lead term added (``None``: not led)."""
        c = self.cfg.control
        hover = c.hover_thrust
        if est is not None:
            u = compensated_input(u, est.d_ned_m_s2, self._last_yaw)
            hover = est.hover_thrust
        lead: np.ndarray | None = None
        if lead_at_s is None:
            self._lead.reset()
        else:
            cy, sy = math.cos(self._last_yaw), math.sin(self._last_yaw)
            uu = np.array(u, dtype=float).reshape(4)
            a_ned = np.array([cy * uu[0] - sy * uu[1], sy * uu[0] + cy * uu[1]])
            led, lead = self._lead.apply(lead_at_s, a_ned)
            uu[0], uu[1] = cy * led[0] + sy * led[1], -sy * led[0] + cy * led[1]
            u = uu
        return attitude_setpoint(u, yaw_rad, dt_s, g_m_s2=self.cfg.rmpc.g_m_s2,
                                 hover_thrust=hover, thrust_min=c.thrust_min,
                                 thrust_max=c.thrust_max), lead

    def _update_estimator(self, store: TelemetryStore, in_control: bool | None,
                          t_now: float) -> None:
        """Feed every velocity sample newer than the filter's with the thrust commanded over
        the interval (time-weighted) and the body z axis measured at its middle. While PX4 is
        in OFFBOARD and armed that is our thrust; before (armed, in the air, PX4's own mode)
        the autopilot's thrust setpoint from ATTITUDE_TARGET, when it streams one. With the
        accelerometer (``control.estimator.accelerometer``), the HIGHRES_IMU samples newer
        than the filter and not newer than the newest velocity sample go in between, in time
        order (each with the attitude at its own time)."""
        f = self._dist
        if f is None:
            return
        mode = store.mode
        ours = mode is not None and mode.armed and mode.main_mode == PX4_MAIN_OFFBOARD
        if in_control is not None:
            ours = in_control
        if not ours:
            self._control_since = None
        elif self._control_since is None:
            # our setpoints fly the vehicle from the next one on: an interval that began
            # earlier was flown by PX4's own controller and says nothing about our thrust
            self._control_since = t_now
        since = self._control_since
        own = self.cfg.control.estimator.autopilot_thrust and mode is not None and mode.armed
        events: list[tuple[float, int, Any]] = [
            (k.t_s, 0, k) for k in store.kinematics_history if f.t_s is None or k.t_s > f.t_s]
        if f.params.accelerometer and events and store.accel:
            newest_v = events[-1][0]
            events += [(a.t_s, 1, a) for a in store.accel
                       if (f.t_s is None or a.t_s > f.t_s) and a.t_s <= newest_v]
            events.sort(key=lambda e: (e[0], e[1]))
        for t_s, kind, sample in events:
            # (a velocity sample goes before an accelerometer sample of the same instant)
            if f.t_s is not None and (t_s < f.t_s or (kind == 0 and t_s == f.t_s)):
                continue
            thrust, body_z = self._inputs_over(f.t_s, t_s, store, since, own)
            if kind == 0:
                f.update(t_s, sample.vel_ned_m_s, thrust, body_z)
                continue
            a = store.attitude_at(t_s)
            if a is None:
                continue
            rot = rotation_from_quat(np.array(a.q_wxyz))
            f.update_accel(t_s, sample.f_frd_m_s2[:2], thrust, body_z, rot)

    def _inputs_over(self, t0: float | None, t1: float, store: TelemetryStore,
                     since: float | None, own: bool) -> tuple[float | None, np.ndarray | None]:
        """The thrust that flew over ``[t0, t1]`` (ours while in control, the autopilot's
        before) and the body z axis at its middle; ``(None, None)`` when unknown."""
        if t0 is None:
            return None, None
        thrust = None
        if since is not None and t0 >= since - 1e-9:
            thrust = self._thrust_over(t0, t1)
        elif own and (since is None or t1 <= since + 1e-9):
            # PX4's own modes fly the vehicle (e.g. the pre-flight stream before OFFBOARD):
            # the thrust it reports is the one flying, so the hover thrust is estimated before
            # our first command is flown
            thrust = store.autopilot_thrust_over(
                t0, t1, self.cfg.control.estimator.autopilot_thrust_max_age_s)
        if thrust is None:
            return None, None
        a = store.attitude_at(0.5 * (t0 + t1))
        if a is None:
            return None, None
        return thrust, rotation_from_quat(np.array(a.q_wxyz))[:, 2]

    def _thrust_over(self, t0: float, t1: float) -> float | None:
        """Time-weighted thrust commanded over ``[t0, t1]``; ``None`` if nothing was in force
        at ``t0``."""
        cmds = self._commands
        if not cmds or cmds[0][0] > t0 + 1e-9 or t1 <= t0:
            return None
        total = 0.0
        for i, (te, _, thr) in enumerate(cmds):
            end = cmds[i + 1][0] if i + 1 < len(cmds) else math.inf
            lo, hi = max(te, t0), min(end, t1)
            if hi > lo:
                total += thr * (hi - lo)
        return total / (t1 - t0)

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
