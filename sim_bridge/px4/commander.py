"""The emulated autopilot's commander: arming, mode switches, the offboard signal and its loss
failsafe, auto-disarm, and the simple position controllers of the non-offboard modes (see
``sim_bridge.px4.modes`` for the behaviour it imitates). Pure logic: every call takes the time
explicitly, no sockets or clocks."""

from __future__ import annotations

import math

import numpy as np

from sim_bridge.physics.vehicle import (
    MOTORS_OFF,
    AttitudeCommand,
    VehicleState,
    euler_from_quat,
    wrap_pi,
)
from sim_bridge.px4.modes import (
    ACCEPTED,
    AUTO_SUB_TO_MODE,
    CMD_COMPONENT_ARM_DISARM,
    CMD_DO_FLIGHTTERMINATION,
    CMD_DO_SET_MODE,
    CMD_NAV_LAND,
    CMD_NAV_RETURN_TO_LAUNCH,
    CMD_NAV_TAKEOFF,
    FLAG_AUTO_ENABLED,
    FLAG_CUSTOM_MODE_ENABLED,
    FLAG_GUIDED_ENABLED,
    FLAG_MANUAL_INPUT_ENABLED,
    FLAG_SAFETY_ARMED,
    FLAG_STABILIZE_ENABLED,
    FORCE_MAGIC,
    LANDED_IN_AIR,
    LANDED_LANDING,
    LANDED_ON_GROUND,
    LANDED_TAKEOFF,
    MAIN_TO_MODE,
    MASK_YAW_RATE_IGNORE,
    MIS_TAKEOFF_ALT_M,
    MPC_LAND_SPEED_M_S,
    OBL_RC_ACT,
    RTL_ARRIVE_RADIUS_M,
    STATE_ACTIVE,
    STATE_CRITICAL,
    STATE_FLIGHT_TERMINATION,
    STATE_STANDBY,
    TEMPORARILY_REJECTED,
    UNSUPPORTED,
    AttitudeTarget,
    CommandResult,
    Mode,
    Px4Params,
)

#: PX4's commander runs its health and arming checks, the offboard signal check among them
#: (``offboardCheck.cpp``), at 10 Hz ("Run arming checks @ 10Hz" in ``Commander::run``), or at
#: once after a status change; a DO_SET_MODE is judged against the last check's verdict
#: (``canRun``). A setpoint that arrives while that verdict is "signal lost" is such a change
#: (``Commander::offboardControlCheck``: "Run arming checks immediately to allow for offboard
#: mode activation"), so a request that follows the first setpoint is judged on a check that
#: has seen it; one that overtakes it is refused.
HEALTH_CHECK_PERIOD_S = 0.1


class Px4:
    """The emulated autopilot's logic. Feed it setpoints and commands as they arrive, call
    :meth:`update` with the vehicle state once per control tick, and take the
    :class:`AttitudeCommand` for the physics from :meth:`attitude_command`."""

    def __init__(self, params: Px4Params, state: VehicleState, *, armed: bool,
                 mode: Mode = Mode.POSCTL, t_s: float = 0.0) -> None:
        self.p = params
        self.mode = mode
        self.armed = armed
        self.home_ned_m = np.array([state.pos_ned_m[0], state.pos_ned_m[1],
                                    state.pos_ned_m[2]])
        self.landed = state.on_ground
        self.has_flown = not state.on_ground
        self.last_signal_t_s = -math.inf
        #: the last health check's verdict on the offboard signal (:data:`HEALTH_CHECK_PERIOD_S`)
        self.signal_checked = False
        self._check_t_s = -math.inf
        self.signals = 0
        self.ignored_setpoints = 0
        self.offboard_losses = 0
        #: a failsafe action is in force (PX4's vehicle_status.failsafe): set by an offboard
        #: loss, cleared by a mode a client asks for or by disarming (PX4's failsafe framework
        #: clears the offboard-loss action on a mode change or disarm)
        self.failsafe = False
        self.events: list[str] = []
        self._armed_t_s = t_s
        self._landed_since_t_s = t_s if state.on_ground else math.inf
        self._sp: AttitudeTarget | None = None
        self._rate_att: np.ndarray | None = None  # integrated attitude for rate setpoints
        self._hold_pos = np.array(state.pos_ned_m, dtype=float)
        self._hold_yaw = state.yaw_rad
        self._target_z = float(state.pos_ned_m[2])
        self._state = state
        self._t_s = t_s
        # PX4's hover-thrust estimate for its own modes (the runtime sets it to the vehicle's
        # true hover thrust: MPC_USE_HTE's estimate after a while in the air); None: the
        # parameter MPC_THR_HOVER
        self.hover_thrust_estimate: float | None = None

    # ------------------------------------------------------------------ queries
    def signal_fresh(self, t_s: float) -> bool:
        return t_s - self.last_signal_t_s <= self.p.com_of_loss_t_s

    def setpoint_age_s(self, t_s: float) -> float:
        return t_s - self.last_signal_t_s

    def _health_check(self, t_s: float) -> None:
        """PX4's health checks when due (every :data:`HEALTH_CHECK_PERIOD_S`, or at once after
        a status change: ``_check_t_s`` reset): they run before the commands of the same
        commander cycle."""
        if t_s >= self._check_t_s + HEALTH_CHECK_PERIOD_S - 1e-9:
            self._check_t_s = t_s
            self.signal_checked = self.signal_fresh(t_s)

    @property
    def base_mode(self) -> int:
        """HEARTBEAT base_mode, as PX4's HEARTBEAT.hpp derives it from the control flags."""
        b = FLAG_CUSTOM_MODE_ENABLED | (FLAG_SAFETY_ARMED if self.armed else 0)
        m = self.mode
        if m in (Mode.MANUAL, Mode.ALTCTL, Mode.POSCTL, Mode.STABILIZED):
            b |= FLAG_MANUAL_INPUT_ENABLED | FLAG_STABILIZE_ENABLED
        elif m is Mode.ACRO:
            b |= FLAG_MANUAL_INPUT_ENABLED
        elif m is Mode.OFFBOARD:
            b |= FLAG_STABILIZE_ENABLED
        elif m.is_auto:
            b |= FLAG_AUTO_ENABLED | FLAG_STABILIZE_ENABLED | FLAG_GUIDED_ENABLED
        return b

    @property
    def custom_mode(self) -> int:
        return self.mode.custom_mode

    @property
    def system_status(self) -> int:
        """HEARTBEAT system_status as PX4's HEARTBEAT.hpp: armed -> CRITICAL while a failsafe
        is in force, else ACTIVE; disarmed -> STANDBY; TERMINATION overrides."""
        if self.mode is Mode.TERMINATION:
            return STATE_FLIGHT_TERMINATION
        if not self.armed:
            return STATE_STANDBY
        return STATE_CRITICAL if self.failsafe else STATE_ACTIVE

    @property
    def landed_state(self) -> int:
        if self.landed:
            return LANDED_ON_GROUND
        if self.mode is Mode.AUTO_TAKEOFF:
            return LANDED_TAKEOFF
        if self.mode is Mode.AUTO_LAND:
            return LANDED_LANDING
        return LANDED_IN_AIR

    # ------------------------------------------------------------------ inputs
    def on_attitude_target(self, t_s: float, sp: AttitudeTarget) -> bool:
        """A SET_ATTITUDE_TARGET addressed to us. Returns whether it counted as a signal."""
        if not sp.is_signal:
            self.ignored_setpoints += 1
            return False
        self.last_signal_t_s = t_s
        self.signals += 1
        if not self.signal_checked:  # PX4 re-runs its checks at once (HEALTH_CHECK_PERIOD_S)
            self._status_changed()
        if self.mode is Mode.OFFBOARD:
            if sp.uses_attitude:
                self._rate_att = None
            elif self._rate_att is None:
                s = self._state
                self._rate_att = np.array([s.roll_rad, s.pitch_rad, s.yaw_rad])
            self._sp = sp
        return True

    def handle_command(self, t_s: float, command: int, params: tuple[float, ...],
                       *, from_self: bool = False) -> CommandResult:
        """A COMMAND_LONG addressed to the autopilot; ``params`` = param1..param7. An accepted
        command that changes the mode (or a DO_SET_MODE) ends a failsafe action."""
        del from_self
        self._health_check(t_s)
        before = self.mode
        res = self._command(t_s, command, params)
        if res.result == ACCEPTED and (self.mode is not before or command == CMD_DO_SET_MODE):
            self.failsafe = False
        return res

    def _status_changed(self) -> None:
        """A mode or arming change: PX4 runs its checks again in the next commander cycle."""
        self._check_t_s = -math.inf

    def _command(self, t_s: float, command: int, params: tuple[float, ...]) -> CommandResult:
        p1, p2, p3, _p4, _p5, _p6, p7 = (list(params) + [math.nan] * 7)[:7]
        if command == CMD_COMPONENT_ARM_DISARM:
            return self._arm_disarm(t_s, p1, p2)
        if command == CMD_DO_SET_MODE:
            return self._set_mode_cmd(t_s, p1, p2, p3)
        if command == CMD_NAV_TAKEOFF:
            if self.mode is Mode.AUTO_TAKEOFF:
                return CommandResult(ACCEPTED)
            if not self.landed:
                return CommandResult(TEMPORARILY_REJECTED, "Takeoff denied: already flying")
            z = self.home_ned_m[2] - MIS_TAKEOFF_ALT_M
            if math.isfinite(p7):
                z = -(p7 - self.p.origin_alt_m)
            self._target_z = min(z, self._state.pos_ned_m[2] - 0.5)
            self._switch(t_s, Mode.AUTO_TAKEOFF)
            return CommandResult(ACCEPTED)
        if command == CMD_NAV_LAND:
            self._switch(t_s, Mode.AUTO_LAND)
            return CommandResult(ACCEPTED)
        if command == CMD_NAV_RETURN_TO_LAUNCH:
            self._switch(t_s, Mode.AUTO_RTL)
            return CommandResult(ACCEPTED)
        if command == CMD_DO_FLIGHTTERMINATION:
            if p1 > 0.5:
                self._switch(t_s, Mode.TERMINATION)
            return CommandResult(ACCEPTED)
        return CommandResult(UNSUPPORTED)

    def _arm_disarm(self, t_s: float, p1: float, p2: float) -> CommandResult:
        if not math.isfinite(p1) or round(p1) not in (0, 1):
            return CommandResult(UNSUPPORTED, "Unsupported ARM_DISARM param")
        forced = math.isfinite(p2) and round(p2) == FORCE_MAGIC
        if round(p1) == 1:
            if self.armed:
                return CommandResult(ACCEPTED)
            if self.mode is Mode.TERMINATION:
                return CommandResult(TEMPORARILY_REJECTED, "Arming denied: terminated")
            if not forced and self.mode is Mode.OFFBOARD and not self.signal_fresh(t_s):
                return CommandResult(TEMPORARILY_REJECTED, "Arming denied: no offboard signal")
            if not forced and self.mode in (Mode.AUTO_LAND, Mode.AUTO_RTL):
                return CommandResult(TEMPORARILY_REJECTED, "Arming denied: mode not armable")
            self.armed = True
            self._status_changed()
            self._armed_t_s = t_s
            self.has_flown = not self.landed
            self._landed_since_t_s = t_s if self.landed else math.inf
            self.home_ned_m = np.array(self._state.pos_ned_m, dtype=float)
            self._enter_mode(self.mode)
            self.events.append(f"{t_s:.3f} armed")
            return CommandResult(ACCEPTED)
        if not self.armed:
            return CommandResult(ACCEPTED)
        if not forced and not self.landed:
            return CommandResult(TEMPORARILY_REJECTED, "Disarming denied: not landed")
        self._disarm(t_s, "command")
        return CommandResult(ACCEPTED)

    def _set_mode_cmd(self, t_s: float, p1: float, p2: float, p3: float) -> CommandResult:
        if not math.isfinite(p1):
            return CommandResult(TEMPORARILY_REJECTED, "invalid base mode")
        base = int(p1)
        target: Mode | None
        if base & FLAG_CUSTOM_MODE_ENABLED:
            main = int(p2) if math.isfinite(p2) else -1
            sub = int(p3) if math.isfinite(p3) else 0
            target = AUTO_SUB_TO_MODE.get(sub) if main == 4 else MAIN_TO_MODE.get(main)
        elif base & FLAG_AUTO_ENABLED:
            target = None  # AUTO.MISSION: no mission loaded
        elif base & FLAG_MANUAL_INPUT_ENABLED:
            if base & FLAG_GUIDED_ENABLED:
                target = Mode.POSCTL
            elif base & FLAG_STABILIZE_ENABLED:
                target = Mode.STABILIZED
            else:
                target = Mode.MANUAL
        else:
            target = None
        if target is None:
            return CommandResult(TEMPORARILY_REJECTED, "Rejecting mode switch cmd")
        if target is self.mode:
            return CommandResult(ACCEPTED)
        # judged on the last health check's verdict (HEALTH_CHECK_PERIOD_S), and never on a
        # signal lost since
        if target is Mode.OFFBOARD and self.armed and not (self.signal_checked
                                                           and self.signal_fresh(t_s)):
            return CommandResult(TEMPORARILY_REJECTED, "Switching to Offboard denied: no signal")
        if target is Mode.AUTO_TAKEOFF and not self.landed:
            return CommandResult(TEMPORARILY_REJECTED, "Takeoff denied: already flying")
        if self.mode is Mode.TERMINATION:
            return CommandResult(TEMPORARILY_REJECTED, "terminated")
        if target is Mode.AUTO_TAKEOFF:
            self._target_z = self.home_ned_m[2] - MIS_TAKEOFF_ALT_M
        self._switch(t_s, target)
        return CommandResult(ACCEPTED)

    # ------------------------------------------------------------------ transitions
    def _switch(self, t_s: float, mode: Mode, why: str = "") -> None:
        if mode is not self.mode:
            self._status_changed()
            self.events.append(f"{t_s:.3f} {self.mode.label} -> {mode.label}"
                               + (f" ({why})" if why else ""))
        self.mode = mode
        self._enter_mode(mode)

    def _enter_mode(self, mode: Mode) -> None:
        s = self._state
        self._hold_pos = np.array(s.pos_ned_m, dtype=float)
        self._hold_yaw = s.yaw_rad
        if mode is not Mode.AUTO_TAKEOFF:
            self._target_z = float(s.pos_ned_m[2])
        if mode is not Mode.OFFBOARD:
            self._sp = None
            self._rate_att = None

    def _disarm(self, t_s: float, why: str) -> None:
        self._status_changed()
        self.armed = False
        self.failsafe = False
        self.events.append(f"{t_s:.3f} disarmed ({why})")
        self._sp = None

    # ------------------------------------------------------------------ tick
    def update(self, t_s: float, state: VehicleState) -> None:
        """Advance the logic to ``t_s`` with the current vehicle ``state``: landing detection,
        offboard loss, auto-disarm, mode sequencing."""
        dt = max(0.0, t_s - self._t_s)
        self._t_s = t_s
        self._state = state
        self._health_check(t_s)
        was_landed = self.landed
        self.landed = state.on_ground
        if not self.landed:
            self.has_flown = True
            self._landed_since_t_s = math.inf
        elif not was_landed:
            self._landed_since_t_s = t_s
        if not self.armed:
            return
        if self.mode is Mode.OFFBOARD and not self.signal_fresh(t_s):
            self.offboard_losses += 1
            act = self.p.com_obl_rc_act
            if act == 7:
                self.events.append(f"{t_s:.3f} offboard lost -> disarm")
                self._disarm(t_s, "offboard lost")
                self._switch(t_s, Mode.POSCTL, "offboard lost")
                return
            self._switch(t_s, OBL_RC_ACT[act], "offboard lost")
            self.failsafe = True
        if self.landed:
            if not self.has_flown:
                if t_s - self._armed_t_s >= self.p.com_disarm_prflt_s > 0:
                    self._disarm(t_s, "no take-off (COM_DISARM_PRFLT)")
                    return
            elif t_s - self._landed_since_t_s >= self.p.com_disarm_land_s > 0:
                self._disarm(t_s, "landed (COM_DISARM_LAND)")
                return
        if self.mode is Mode.AUTO_TAKEOFF and state.pos_ned_m[2] <= self._target_z + 0.1:
            self._switch(t_s, Mode.AUTO_LOITER, "take-off done")
        if self.mode is Mode.AUTO_RTL:
            d = np.hypot(*(self.home_ned_m[:2] - state.pos_ned_m[:2]))
            if d < RTL_ARRIVE_RADIUS_M and np.linalg.norm(state.vel_ned_m_s[:2]) < 0.3:
                self._switch(t_s, Mode.AUTO_LAND, "RTL: above home")
        if self._rate_att is not None and self._sp is not None:
            self._rate_att = self._rate_att + np.asarray(self._sp.body_rates_rad_s) * dt

    # ------------------------------------------------------------------ control output
    @property
    def _hover(self) -> float:
        h = self.hover_thrust_estimate
        return self.p.hover_thrust if h is None or not 0 < h < 1 else h

    def attitude_command(self) -> AttitudeCommand:
        """What the attitude loop tracks now (from the offboard setpoint or the mode's own
        controller)."""
        s = self._state
        if not self.armed or self.mode is Mode.TERMINATION:
            return MOTORS_OFF
        m = self.mode
        if m is Mode.OFFBOARD:
            sp = self._sp
            if sp is None:  # in OFFBOARD with nothing applied yet: keep level, hover
                return AttitudeCommand(0.0, 0.0, s.yaw_rad, self._hover)
            if sp.uses_attitude:
                r, p, y = euler_from_quat(np.asarray(sp.q_wxyz))
                ff = 0.0 if sp.type_mask & MASK_YAW_RATE_IGNORE else sp.body_rates_rad_s[2]
                return AttitudeCommand(r, p, y, sp.thrust_norm, ff)
            att = self._rate_att if self._rate_att is not None else np.array(
                [s.roll_rad, s.pitch_rad, s.yaw_rad])
            return AttitudeCommand(float(att[0]), float(att[1]), wrap_pi(float(att[2])),
                                   sp.thrust_norm, body_rates_frd_rad_s=sp.body_rates_rad_s)
        if self.landed and m in (Mode.AUTO_LAND, Mode.AUTO_RTL):
            return AttitudeCommand(0.0, 0.0, s.yaw_rad, 0.1 * self._hover)
        if m in (Mode.STABILIZED, Mode.MANUAL, Mode.ACRO):
            return AttitudeCommand(0.0, 0.0, self._hold_yaw, self._hover)
        if self.landed and m in (Mode.POSCTL, Mode.ALTCTL, Mode.AUTO_LOITER):
            return AttitudeCommand(0.0, 0.0, s.yaw_rad, 0.1 * self._hover)
        pos_sp = self._hold_pos.copy()
        vel_ff = np.zeros(3)
        hold_xy = True
        if m is Mode.ALTCTL:
            hold_xy = False
        elif m is Mode.AUTO_TAKEOFF:
            pos_sp[2] = self._target_z
        elif m is Mode.AUTO_LAND:
            pos_sp[2] = s.pos_ned_m[2]
            vel_ff[2] = MPC_LAND_SPEED_M_S
        elif m is Mode.AUTO_RTL:
            pos_sp[:2] = self.home_ned_m[:2]
        return self._position_control(pos_sp, vel_ff, hold_xy, m is Mode.AUTO_LAND)

    def _position_control(self, pos_sp: np.ndarray, vel_ff: np.ndarray, hold_xy: bool,
                          velocity_z_only: bool) -> AttitudeCommand:
        s, g = self._state, self.p.g_m_s2
        kp_xy, kd_xy, kp_z, kd_z = 1.0, 1.8, 1.5, 2.5
        err = pos_sp - s.pos_ned_m
        acc = np.zeros(3)
        if hold_xy:
            vel_sp_xy = np.clip(kp_xy * err[:2], -2.0, 2.0)
            acc[:2] = kd_xy * (vel_sp_xy - s.vel_ned_m_s[:2])
        else:
            acc[:2] = -kd_xy * s.vel_ned_m_s[:2]
        vz_sp = vel_ff[2] if velocity_z_only else float(np.clip(kp_z * err[2], -1.5, 1.0))
        acc[2] = kd_z * (vz_sp - s.vel_ned_m_s[2])
        a_xy_max = g * math.tan(0.7 * self.p.max_tilt_rad)
        n = float(np.hypot(acc[0], acc[1]))
        if n > a_xy_max:
            acc[:2] *= a_xy_max / n
        acc[2] = float(np.clip(acc[2], -0.5 * g, 0.5 * g))
        f = acc - np.array([0.0, 0.0, g])  # specific force (NED), points up
        fn = float(np.linalg.norm(f))
        cy, sy = math.cos(self._hold_yaw), math.sin(self._hold_yaw)
        b = -f / fn
        bx = cy * b[0] + sy * b[1]
        by = -sy * b[0] + cy * b[1]
        roll = -math.asin(max(-1.0, min(1.0, by)))
        pitch = math.atan2(bx, b[2])
        thrust = min(1.0, fn / g * self._hover)
        return AttitudeCommand(roll, pitch, self._hold_yaw, thrust)
