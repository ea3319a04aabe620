"""The per-frame control computation, shared by the live process and the offline replay.

``ControlPipeline.step(image, t_s, store)`` reads as the data flow, one named stage each
(their values are :mod:`companion.control.stages`):

perceive (pixels -> target corners) -> state at the frame's time (attitude, kinematics,
virtual-camera moments and error state) -> predict to the command's effect (latency
compensation, the target's motion) -> plan (RMPC or a fallback law) -> decide (the safety
ladder) -> command (attitude/thrust setpoint, spec 5, or the hover).

It does no I/O and reads no clock: given the same frames and telemetry in the same order it
returns the same commands, which is what makes replay exact.

The vehicle is never sent a command computed from bad data: every value that reaches a
setpoint passed a finiteness check, and a setpoint that fails one is replaced by the level
hover setpoint (which depends on no measurement) or by silence.
"""

from __future__ import annotations

import logging
import math
from collections import deque
from collections.abc import Callable
from typing import Any

import numpy as np

from companion.config import Config
from companion.control.estimator_feed import EstimatorFeed
from companion.control.safety import Health, SafetyDecision, SafetyLevel, SafetySupervisor
from companion.control.seams import Controller, Perceiver
from companion.control.stages import (
    Command,
    FrameState,
    Plan,
    Predicted,
    Sighting,
    StepResult,
    VelocityEstimate,
)
from companion.control.telemetry import KinematicsSample, TelemetryStore
from companion.core.design import design_terminal
from companion.core.disturbance import DisturbanceEstimate, DisturbanceEstimator
from companion.core.estimator import ImageVelocityEstimator
from companion.core.frozen import make
from companion.core.geometry import (
    camera_to_body_rotation,
    euler_zyx_from_quat,
    rectangle_corners_m,
    wrap_pi,
)
from companion.core.latency import Prediction, predict_error_state
from companion.core.lead import TiltLead
from companion.core.moments import DegenerateTargetError, a_star, fold_s4
from companion.core.prediction import advance_target, load_kernel, predict_target_motion
from companion.core.reacquire import reacquire_input
from companion.core.rmpc import RmpcResult, TargetMotion, terminal_law
from companion.core.setpoint import (
    AttitudeSetpoint,
    SetpointError,
    attitude_setpoint,
    hover_setpoint,
    yaw_reference,
)
from companion.core.state import ErrorState, MeasurementError, build_error_state
from companion.core.terminal import TerminalDesign
from companion.perception import PerceptionResult

log = logging.getLogger(__name__)

#: How far the yaw reference may lead the measured yaw (rad): PX4's yaw loop (MC_YAW_P 2.8,
#: its default) lags a yaw ramp by rate / 2.8, 0.3 rad at the 0.84 rad/s the vehicle's limits
#: allow; a re-sync to the measured yaw at 0.2 rad (before) capped the achieved rate near
#: 0.2-0.4 rad/s whatever was commanded, and the yaw ran away from a 0.5 rad/s target.
YAW_LEAD_MAX_RAD = 0.4


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
        load_kernel()  # (the horizon's prediction, compiled: checked now, not at step 1)
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
            DisturbanceEstimator(est, cfg.control.hover_thrust, cfg.rmpc.g_m_s2,
                                 cfg.rmpc.cache_dir if cfg.rmpc.jit else None)
            if est.enabled else None)
        # (t_effect_s, u: the vehicle's acceleration/yaw rate asked for (4,), thrust sent)
        self._commands: deque[tuple[float, np.ndarray, float]] = deque(maxlen=64)
        # the same history as (t_effect_s, u), kept beside it so the latency prediction gets
        # its input history without a 64-tuple list built every step
        self._inputs: deque[tuple[float, np.ndarray]] = deque(maxlen=64)
        self._feed = (None if self._dist is None
                      else EstimatorFeed(cfg, self._dist, self._commands))
        self._lead = TiltLead(cfg.control.lead)
        self.force_solver_failure = False
        # Optional stage timing (seconds clock, e.g. time.perf_counter): measurement only,
        # it never changes a result, so replay stays exact with or without it.
        self._timer = timer  # fault injection (tests, MAV_CMD_INJECT_FAILURE-like)

    # ------------------------------------------------------------------------------------------

    def step(self, image: np.ndarray | None, t_s: float, store: TelemetryStore,
             t_now_s: float | None = None, in_control: bool | None = None,
             perceived: PerceptionResult | None = None,
             actuation_delay_s: float | None = None,
             send: Callable[[AttitudeSetpoint, float], None] | None = None) -> StepResult:
        """One frame captured at ``t_s``; ``t_now_s``: the time the step runs (same time base;
        default ``t_s``, i.e. no latency known); ``actuation_delay_s``: from ``t_now_s`` to the
        vehicle flying this step's command, as measured by the runtime
        (``control.latency.auto_delay``; default ``control.latency.actuation_delay_s``);
        ``in_control``: our setpoints fly the vehicle
        (the runtime knows OFFBOARD was requested before the 1 Hz HEARTBEAT confirms it;
        default: the HEARTBEAT's mode). ``perceived``: the perception result of that frame
        computed elsewhere (a replay from logged detections); ``image`` is then not looked at.
        ``send(setpoint, now)``: called with the setpoint as soon as the command stage (the
        last check that gates it) built it, before the result is assembled (the runtime sends
        it there)."""
        t_now = t_s if t_now_s is None or not math.isfinite(t_now_s) else max(t_s, t_now_s)
        clock = self._timer
        marks: list[tuple[str, float]] = [("start", clock())] if clock else []
        seen = self.perceive(image, perceived)
        if clock:
            marks.append(("detect", clock()))
        state = self.state_at_frame(seen, t_s, store, in_control, t_now)
        if clock:
            marks.append(("moments", clock()))
        delay_s = self._actuation_delay(actuation_delay_s)
        predicted = self.predict(state, t_s, t_now, delay_s)
        plan = self.plan(predicted)
        if clock:
            marks.append(("solve", clock()))
        decision = self.decide(t_s, store, state, plan)
        cmd = self.command(decision, state, predicted, plan, store, in_control, t_now + delay_s,
                           t_now)
        if clock:
            marks.append(("command", clock()))
        if send is not None and cmd.setpoint is not None:
            send(cmd.setpoint, t_now)
        timings = {name: (t - marks[i][1]) * 1e3 for i, (name, t) in enumerate(marks[1:])}
        # (the stage values are built by make: a frozen __init__ costs ~0.3 us a field)
        return make(
            StepResult, timings_ms=timings,
            t_s=t_s, perception_status=state.perception_status,
            perception_reason=state.perception_reason, corners_px=seen.corners_px,
            error_state=state.error_state, target_velocity=state.velocity, rmpc=plan.result,
            safety=decision, u=cmd.u, setpoint=cmd.setpoint,
            notes=(() if predicted is None else predicted.notes) + cmd.notes,
            estimator=cmd.estimate,
            prediction=None if predicted is None else predicted.prediction, t_now_s=t_now,
            in_control=in_control, input_region=seen.region, lead_m_s2=cmd.lead_m_s2,
            actuation_delay_s=delay_s,
        )

    # -- the stages, in the order of the data flow ----------------------------------------------

    def perceive(self, image: np.ndarray | None,
                 perceived: PerceptionResult | None = None) -> Sighting:
        """Pixels -> the target's corners (or ``perceived``, computed elsewhere)."""
        region = None
        if perceived is None and image is not None:
            perceived = self.perception.process(image)
            region = getattr(self.perception, "last_region", None)
        if perceived is None:
            return Sighting("lost", "no image", region=region)
        if perceived.status != "ok":
            return Sighting(perceived.status, perceived.reason, region=region)
        return make(Sighting, status=perceived.status, reason=perceived.reason,
                    corners_px=perceived.corners_px, points_m=perceived.points_m, region=region)

    def state_at_frame(self, seen: Sighting, t_s: float, store: TelemetryStore,
                       in_control: bool | None, t_now: float) -> FrameState:
        """The attitude and kinematics at the frame's time, the disturbance estimator fed up
        to now, and (with a target) the virtual-camera moments and the error state."""
        att = store.attitude_at(t_s)
        kin = store.kinematics
        if self._feed is not None:
            self._feed.update(store, in_control, t_now)
        kin_cap = store.kinematics_at(t_s) if self.cfg.control.latency.enabled else kin
        yaw: float | None = None
        if att is not None:
            roll, pitch, yaw = euler_zyx_from_quat(att.q_wxyz)
            self._last_yaw = yaw if math.isfinite(yaw) else self._last_yaw
        if seen.points_m is None or att is None or kin is None:
            return FrameState(att, kin, yaw, None, None, True, seen.status, seen.reason)
        assert yaw is not None
        vel = self._target_velocity(t_s, store)
        try:
            es = self._error_state(seen.points_m, roll, pitch, yaw, att.yaw_rate_rad_s,
                                   (kin_cap or kin).vel_ned_m_s, vel)
        except (MeasurementError, DegenerateTargetError) as exc:
            return FrameState(att, kin, yaw, None, vel, not isinstance(exc, MeasurementError),
                              "rejected", f"moments: {exc}")
        self._s4_prev = float(es.s[3])
        self._last_seen_s = t_s
        v_img = self._estimator.update(t_s, es.s, es.v_q_v_m_s, yaw, att.yaw_rate_rad_s)
        if vel.source != "follow_target":
            vel = make(VelocityEstimate, v_a_ned_m_s=v_img, a_a_ned_m_s2=np.zeros(3),
                       yaw_rate_rad_s=0.0, source="image_estimator")
        return make(FrameState, attitude=att, kinematics=kin, yaw_rad=yaw, error_state=es,
                    velocity=vel, inputs_finite=True, perception_status=seen.status,
                    perception_reason=seen.reason)

    def predict(self, state: FrameState, t_s: float, t_now: float,
                delay_s: float) -> Predicted | None:
        """The target's motion over the horizon and the error state moved from the frame's
        time ``t_s`` to when the command takes effect, ``delay_s`` after ``t_now``
        (``control.latency``); ``None`` without an error state."""
        es, vel = state.error_state, state.velocity
        if es is None or vel is None:
            return None
        cfg = self.cfg
        lat = cfg.control.latency
        v_m, a_m = vel.v_a_ned_m_s, vel.a_a_ned_m_s2
        if lat.enabled and lat.propagate_target and vel.source == "follow_target":
            # the horizon starts where the latency prediction puts eta0: now + delay
            v_m, a_m = advance_target(v_m, a_m, vel.yaw_rate_rad_s,
                                      min(t_now + delay_s - t_s, lat.max_prediction_s))
        motion = predict_target_motion(
            v_m, a_m, vel.yaw_rate_rad_s, es.yaw_rad,
            cfg.rmpc.horizon, cfg.rmpc.dt_s,
            None if self._dist is None else self._dist.estimate().d_ned_m_s2,
            cfg.rmpc.eta_max[4] if cfg.rmpc.target_speed_extrapolation == "box" else None)
        if not lat.enabled:
            return Predicted(es.eta_e, motion, None)
        v_a, vdot_a, psidot_a = motion.stage(0)
        pred: Prediction | None = predict_error_state(
            es.eta_e, t_s, t_now + delay_s, self._inputs, v_a, vdot_a,
            psidot_a, cfg.rmpc.desired_depth_m, lat)
        assert pred is not None
        if (not math.isfinite(float(pred.eta_e.sum()))  # (one sum: finite iff every entry
                and not np.isfinite(pred.eta_e).all()):   # is, short of an overflow)
            return Predicted(es.eta_e, motion, None,
                             ("latency: non-finite prediction, measured state used",))
        notes: tuple[str, ...] = ()
        if pred.clipped:
            notes = (f"latency: frame {t_now - t_s:.3f} s old, predicted "
                     f"{pred.horizon_s:.3f} s only",)
        return make(Predicted, eta0=pred.eta_e, motion=motion, prediction=pred, notes=notes)

    def plan(self, predicted: Predicted | None) -> Plan:
        """The controller's solve from the predicted state (or the fallback law while a
        solver failure is injected); no plan without a state."""
        if predicted is None:
            return Plan(None, True)
        if self.force_solver_failure:
            res = self._fallback(predicted.eta0, predicted.motion, "injected failure")
        else:
            res = self.rmpc.solve(predicted.eta0, predicted.motion)
        return make(Plan, result=res, solver_ok=res.mode != "fallback")

    def decide(self, t_s: float, store: TelemetryStore, state: FrameState,
               plan: Plan) -> SafetyDecision:
        """The safety ladder's level for this step, from the health of its inputs."""
        decision = self.safety.update(make(
            Health, t_s=t_s,
            telemetry_age_s=store.telemetry_age_s(t_s),
            target_age_s=t_s - self._last_seen_s,
            follow_target_age_s=store.target_age_s(t_s),
            inputs_finite=state.inputs_finite,
            solver_ok=plan.solver_ok,
        ))
        if decision.changed:
            log.warning("safety -> %s: %s", decision.level.value, decision.reason)
        return decision

    def command(self, decision: SafetyDecision, state: FrameState,
                predicted: Predicted | None, plan: Plan, store: TelemetryStore,
                in_control: bool | None, t_effect_s: float, t_now: float) -> Command:
        """The input the safety level asks for, mapped to an attitude setpoint (led for the
        tilt lag while tracking); the hover when that fails (silence only at SILENT); the
        command is remembered for the latency prediction and the thrust estimate."""
        level = decision.level
        u = self._input_for(level, state, predicted, plan, store)
        est = self._dist.estimate() if self._dist is not None else None
        notes: list[str] = []
        sp: AttitudeSetpoint | None = None
        lead_m_s2: np.ndarray | None = None
        if u is not None:
            try:
                # led only while our setpoints fly the vehicle (before OFFBOARD PX4 holds
                # level with its own controller, so a difference of streamed commands is not
                # a change of tilt the vehicle must catch up with) and the controller tracks
                # in its nominal problem: the recovery's chase and the fallbacks' jumps are
                # flown as commanded (docs/reference/estimator.md 2b)
                res = plan.result
                led = (in_control is not False and level is SafetyLevel.TRACKING
                       and res is not None and res.mode not in ("recovery", "fallback"))
                sp, lead_m_s2 = self._setpoint(u, self._yaw_reference(), self.cfg.rmpc.dt_s,
                                               est, t_now if led else None)
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
            sp = self._hover(est, notes)
        if sp is not None:
            self._remember(sp, u, in_control, t_effect_s)
        self._yaw_sp = sp.yaw_rad if sp is not None else None
        return make(Command, u=u, setpoint=sp, lead_m_s2=lead_m_s2, estimate=est,
                    notes=tuple(notes) if notes else ())

    # -- the stages' parts ----------------------------------------------------------------------

    def _actuation_delay(self, measured_s: float | None) -> float:
        """From "now" to the vehicle flying the command (s): the runtime's measure, bounded
        to [0, 1] s, or the configured constant."""
        if measured_s is not None and math.isfinite(measured_s):
            return min(max(float(measured_s), 0.0), 1.0)
        return self.cfg.control.latency.actuation_delay_s

    def _error_state(self, points_m: np.ndarray, roll: float, pitch: float, yaw: float,
                     yaw_rate_rad_s: float, v_q_ned_m_s: Any,
                     vel: VelocityEstimate) -> ErrorState:
        cfg = self.cfg
        return build_error_state(
            points_m, roll_rad=roll, pitch_rad=pitch, yaw_rad=yaw,
            yaw_rate_rad_s=yaw_rate_rad_s, v_q_ned_m_s=v_q_ned_m_s,
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

    def _input_for(self, level: SafetyLevel, state: FrameState, predicted: Predicted | None,
                   plan: Plan, store: TelemetryStore) -> np.ndarray | None:
        """The input (r1, r2, r3, psidot_q) of the safety level: the plan's while tracking,
        the terminal law at TERMINAL, the climb-and-turn at REACQUIRE; else none."""
        if level is SafetyLevel.TRACKING and plan.result is not None:
            return np.asarray(plan.result.u0, dtype=float)
        if level is SafetyLevel.TERMINAL and predicted is not None:
            return self._fallback(predicted.eta0, predicted.motion, "safety terminal").u0
        if (level is SafetyLevel.REACQUIRE and state.attitude is not None
                and state.kinematics is not None and state.yaw_rad is not None):
            return self._reacquire(store, state.kinematics, state.yaw_rad)
        return None

    def _hover(self, est: DisturbanceEstimate | None, notes: list[str]) -> AttitudeSetpoint:
        """Hold still: against the estimated disturbance when there is one, else level."""
        c = self.cfg.control
        if est is not None:
            try:
                return self._setpoint(np.zeros(4), self._last_yaw, 0.0, est)[0]
            except ValueError as exc:
                notes.append(f"compensated hover refused: {exc}")
        return hover_setpoint(self._last_yaw, hover_thrust=c.hover_thrust,
                              thrust_min=c.thrust_min, thrust_max=c.thrust_max)

    def _remember(self, sp: AttitudeSetpoint, u: np.ndarray | None, in_control: bool | None,
                  t_effect_s: float) -> None:
        """The command history: when the command takes effect, the input the vehicle will
        fly and the thrust sent."""
        t_eff = t_effect_s
        if self._commands and t_eff < self._commands[-1][0]:
            t_eff = self._commands[-1][0]  # keep the history in time order
        # what the vehicle will fly: before OFFBOARD (in_control False) PX4 holds with its
        # own controller and ignores the stream, so the latency prediction must integrate
        # zero acceleration there, not the inputs we streamed
        flown = u is not None and in_control is not False
        u_flown = np.array(u, dtype=float) if flown else np.zeros(4)
        self._commands.append((t_eff, u_flown, sp.thrust_norm))
        self._inputs.append((t_eff, u_flown))

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
        # plain floats throughout (compensated_input's, the lead's and
        # input_in_reference_frame's formulas, the same values): numpy's per-call overhead on
        # 4-vectors cost more than the arithmetic
        uu = [float(x) for x in np.asarray(u, dtype=float).reshape(4).tolist()]
        cy, sy = math.cos(self._last_yaw), math.sin(self._last_yaw)
        if est is not None:
            d0, d1, d2 = est.d_ned_m_s2
            uu[0] -= cy * d0 + sy * d1
            uu[1] -= -sy * d0 + cy * d1
            uu[2] -= d2
            hover = est.hover_thrust
        lead: np.ndarray | None = None
        if lead_at_s is None:
            self._lead.reset()
        else:
            a_ned = (cy * uu[0] - sy * uu[1], sy * uu[0] + cy * uu[1])
            led, lead = self._lead.apply(lead_at_s, a_ned)
            lx, ly = led.tolist()
            uu[0], uu[1] = cy * lx + sy * ly, -sy * lx + cy * ly
        # u is in the measured yaw's frame; the attitude is built on the yaw reference
        dy = wrap_pi(float(yaw_rad) - float(self._last_yaw))
        if not math.isfinite(dy):
            raise SetpointError("yaw: non-finite value")
        cd, sd = math.cos(dy), math.sin(dy)
        r1, r2 = uu[0], uu[1]
        uu[0], uu[1] = cd * r1 + sd * r2, -sd * r1 + cd * r2
        return attitude_setpoint(uu, yaw_rad, dt_s, g_m_s2=self.cfg.rmpc.g_m_s2,
                                 hover_thrust=hover, thrust_min=c.thrust_min,
                                 thrust_max=c.thrust_max), lead

    # ------------------------------------------------------------------------------------------

    def _fallback(self, eta: np.ndarray, motion: TargetMotion, why: str) -> RmpcResult:
        """The terminal law ``K eta + Gamma`` clipped to U (spec 7), as a 'fallback' result."""
        v_a, vdot_a, psidot_a = motion.stage(0)
        u0 = terminal_law(eta, v_a, vdot_a, psidot_a, self.terminal.k, self.cfg.rmpc.u_max)
        n = self.cfg.rmpc.horizon
        return RmpcResult(False, "fallback", why, why, math.nan, 0, 0.0, u0,
                          np.tile(eta, (n + 1, 1)), np.tile(u0, (n, 1)), 0.0, (), motion)

    def _yaw_reference(self) -> float:
        """Yaw the next setpoint builds on: :func:`companion.core.setpoint.yaw_reference` of
        the previous yaw setpoint (``None``: the measured yaw)."""
        return yaw_reference(self._yaw_sp, self._last_yaw, YAW_LEAD_MAX_RAD)

    def _target_velocity(self, t_s: float, store: TelemetryStore) -> VelocityEstimate:
        tgt = store.target
        if tgt is not None and t_s - tgt.t_s <= self.cfg.safety.follow_target_timeout_s:
            v, a = np.array(tgt.vel_ned_m_s), np.array(tgt.acc_ned_m_s2)
            if self.cfg.control.latency.propagate_target:  # the sample at the frame's time
                v, a = advance_target(v, a, tgt.yaw_rate_rad_s, t_s - tgt.t_s)
            return make(VelocityEstimate, v_a_ned_m_s=v, a_a_ned_m_s2=a,
                        yaw_rate_rad_s=tgt.yaw_rate_rad_s, source="follow_target")
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


__all__ = ["ControlPipeline", "StepResult", "VelocityEstimate"]
