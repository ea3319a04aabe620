"""Offboard state machine, as PX4 expects it (docs/reference/px4-offboard.md).

Pure logic with explicit time: the runtime feeds it observations (HEARTBEAT mode/armed,
COMMAND_ACK results, whether a setpoint was just streamed) and executes the actions it returns.

Sequence: stream setpoints for ``preflight_stream_s`` -> (optionally) arm -> request OFFBOARD
(DO_SET_MODE, main mode 6) -> confirm from HEARTBEAT -> ACTIVE. While the controller reports
that it needs authority now (:meth:`OffboardManager.on_controller`: its hard problem is
infeasible, the target escaping the view), the stream is cut to ``preflight_escape_stream_s``:
PX4 asks only for a fresh setpoint, and every second of position hold lets the target drive
on. Rejections are retried every
``mode_retry_s``. Leaving: request Hold/Position, then stop streaming. If PX4 leaves OFFBOARD
on its own (pilot, failsafe), the machine goes to ``LOST`` and does not fight the pilot: it
re-requests OFFBOARD only when ``reengage`` is set.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass

from companion.config import OffboardConfig

PX4_MAIN_MODE_POSCTL = 3
PX4_MAIN_MODE_AUTO = 4
PX4_MAIN_MODE_OFFBOARD = 6
PX4_SUB_MODE_AUTO_LOITER = 3
MAV_CMD_DO_SET_MODE = 176
MAV_RESULT_ACCEPTED = 0
MAV_RESULT_IN_PROGRESS = 5
#: PX4 sees the offboard signal while the last setpoint is younger than COM_OF_LOSS_T (1.0 s by
#: default, commander's offboard check): a pause shorter than half of it (a stale frame, a slow
#: step on a small computer) keeps the pre-flight stream running; a longer one restarts it.
STREAM_GAP_S = 0.5
#: A stream is measured in frame times (e.g. 37.55 - 37.40 = 0.1499999... s in floats): a
#: microsecond of tolerance, so that it is not judged one step short
STREAM_TOL_S = 1e-6
#: MAV_LANDED_STATE: the values EXTENDED_SYS_STATE.landed_state takes
LANDED_STATE_NAMES = {0: "UNDEFINED", 1: "ON_GROUND", 2: "IN_AIR", 3: "TAKEOFF", 4: "LANDING"}
MAV_LANDED_STATE_IN_AIR = 2


class OffboardPhase(enum.Enum):
    PREFLIGHT = "preflight"  # streaming, not yet asked
    ARMING = "arming"
    REQUESTING = "requesting"  # DO_SET_MODE sent, waiting for HEARTBEAT to say OFFBOARD
    ACTIVE = "active"
    LOST = "lost"  # PX4 left OFFBOARD on its own
    EXITING = "exiting"
    DONE = "done"


@dataclass(frozen=True)
class Action:
    """What the runtime must do now. ``kind``: 'arm', 'set_mode', 'stop_stream'."""

    kind: str
    main_mode: int = 0
    sub_mode: int = 0
    reason: str = ""


@dataclass(frozen=True)
class VehicleStatus:
    """From the autopilot's HEARTBEAT: ``main_mode``/``sub_mode`` of PX4's custom_mode."""

    armed: bool
    main_mode: int
    sub_mode: int
    t_s: float


class OffboardManager:
    def __init__(self, cfg: OffboardConfig, reengage: bool = False) -> None:
        self._cfg = cfg
        self._reengage = reengage
        self.phase = OffboardPhase.PREFLIGHT
        self._stream_start_s: float | None = None
        self._last_streamed_s: float | None = None
        self._last_request_s = -1e9
        self._status: VehicleStatus | None = None
        #: the autopilot refused the last OFFBOARD request (COMMAND_ACK): our setpoints do not
        #: fly the vehicle until a new request is accepted
        self.request_rejected = False
        self.transitions: list[tuple[float, OffboardPhase, str]] = []
        #: the controller's last word (on_controller): it needs authority now
        self._escaping = False
        #: the autopilot's EXTENDED_SYS_STATE.landed_state (None: not heard yet)
        self.landed_state: int | None = None
        #: why a due OFFBOARD request (or arming) is held back now, None when it is not; the
        #: runtime logs each new reason once (:meth:`Vehicle.log_offboard`)
        self.held: str | None = None

    @property
    def in_offboard(self) -> bool:
        s = self._status
        return s is not None and s.main_mode == PX4_MAIN_MODE_OFFBOARD

    def on_heartbeat(self, status: VehicleStatus) -> None:
        self._status = status
        if self.phase is OffboardPhase.REQUESTING and self.in_offboard:
            self._go(status.t_s, OffboardPhase.ACTIVE, "HEARTBEAT reports OFFBOARD")
        elif self.phase is OffboardPhase.ACTIVE and not self.in_offboard:
            self._go(status.t_s, OffboardPhase.LOST,
                     f"autopilot left OFFBOARD (main mode {status.main_mode})")
        elif self.phase is OffboardPhase.EXITING and not self.in_offboard:
            self._go(status.t_s, OffboardPhase.DONE, "autopilot out of OFFBOARD")

    def on_landed_state(self, landed_state: int) -> None:
        """The autopilot's EXTENDED_SYS_STATE.landed_state. With ``offboard.require_in_air``
        OFFBOARD is asked for (and the vehicle armed) only while it is ``IN_AIR``: the
        companion follows a target from the air; on the ground, PX4 would take our attitude
        and thrust setpoints as a take-off."""
        self.landed_state = int(landed_state)

    def _airborne_gate(self) -> str | None:
        """None when a request may go out now, else the reason it may not."""
        if not self._cfg.require_in_air or self.landed_state == MAV_LANDED_STATE_IN_AIR:
            return None
        state = ("not reported yet (no EXTENDED_SYS_STATE from the autopilot)"
                 if self.landed_state is None else
                 LANDED_STATE_NAMES.get(self.landed_state, str(self.landed_state)))
        return (f"OFFBOARD held back: the vehicle is not in the air (landed state {state}); "
                "take off first (e.g. in Position mode), or set offboard.require_in_air = false")

    def on_command_ack(self, command: int, result: int, t_s: float) -> None:
        """A COMMAND_ACK from the autopilot: a refused OFFBOARD request (PX4 answers
        ``TEMPORARILY_REJECTED`` without a fresh offboard signal) is remembered until the next
        request, so nobody takes our setpoints for what flies the vehicle meanwhile."""
        if command != MAV_CMD_DO_SET_MODE or self.phase is not OffboardPhase.REQUESTING:
            return
        self.request_rejected = result not in (MAV_RESULT_ACCEPTED, MAV_RESULT_IN_PROGRESS)

    @property
    def awaiting_switch(self) -> bool:
        """OFFBOARD requested and not refused: PX4 switches on the request, the 1 Hz
        HEARTBEAT confirms it later."""
        return self.phase is OffboardPhase.REQUESTING and not self.request_rejected

    def on_streamed(self, t_s: float) -> None:
        """A setpoint was just sent (the offboard proof of life). After a pause of more than
        :data:`STREAM_GAP_S` the pre-flight stream starts over."""
        last = self._last_streamed_s
        if self._stream_start_s is None or (last is not None and t_s - last > STREAM_GAP_S):
            self._stream_start_s = t_s
        self._last_streamed_s = t_s

    def on_controller(self, needs_authority: bool) -> None:
        """The last control step's verdict: ``True`` when its hard problem was infeasible
        (the target escaping the view; an RMPC 'recovery' solve), which shortens the
        pre-flight stream to ``preflight_escape_stream_s``."""
        self._escaping = bool(needs_authority)

    def on_stream_gap(self) -> None:
        """A step sent no setpoint (safety silence, a stale frame). Whether the pre-flight
        stream starts over is decided by the pause's length at the next setpoint
        (:meth:`on_streamed`): one missing setpoint of a 20 Hz stream is no loss of the offboard
        signal for PX4, and restarting the 1 s stream on each made a computer that drops a
        frame now and then never reach OFFBOARD (bench/cpu_budget.py at 0.15 of a core)."""

    def request_exit(self, t_s: float) -> None:
        if self.phase not in (OffboardPhase.EXITING, OffboardPhase.DONE):
            self._go(t_s, OffboardPhase.EXITING, "exit requested")
            self._last_request_s = -1e9

    def step(self, t_s: float) -> list[Action]:
        """Actions due at ``t_s``."""
        st = self._status
        acts: list[Action] = []
        streamed = None if self._stream_start_s is None else t_s - self._stream_start_s
        streamed_long_enough = (streamed is not None
                                and streamed >= self._cfg.preflight_stream_s - STREAM_TOL_S)
        escape_s = self._cfg.preflight_escape_stream_s
        escaping = (streamed is not None and escape_s is not None and self._escaping
                    and streamed >= escape_s - STREAM_TOL_S)
        due = t_s - self._last_request_s >= self._cfg.mode_retry_s
        # With offboard.arm = false the pilot arms: OFFBOARD is asked for only once the
        # HEARTBEAT says armed (asked on the ground, PX4 would take our setpoints at the arming)
        ready = (self.phase is OffboardPhase.PREFLIGHT and (streamed_long_enough or escaping)
                 and st is not None and (self._cfg.arm or st.armed))
        reengaging = (self.phase is OffboardPhase.LOST and self._reengage
                      and streamed_long_enough)
        self.held = self._airborne_gate() if ready or reengaging else None
        if ready and self.held is None and st is not None:
            done = ("pre-flight stream done" if streamed_long_enough else
                    f"pre-flight stream cut to {escape_s:g} s: the controller's hard problem"
                    " is infeasible (target escaping)")
            if self._cfg.arm and not st.armed:
                self._go(t_s, OffboardPhase.ARMING, f"{done}, arming")
            else:
                self._go(t_s, OffboardPhase.REQUESTING, done)
            due = True
        if self.phase is OffboardPhase.ARMING and st is not None:
            if st.armed:
                self._go(t_s, OffboardPhase.REQUESTING, "armed")
                due = True
            elif due:
                acts.append(Action("arm", reason="arming for the scenario"))
        if reengaging and self.held is None:
            self._go(t_s, OffboardPhase.REQUESTING, "re-engaging")
            due = True
        if self.phase is OffboardPhase.REQUESTING and due and not self.in_offboard:
            acts.append(Action("set_mode", PX4_MAIN_MODE_OFFBOARD, 0, "request OFFBOARD"))
            self.request_rejected = False
        if self.phase is OffboardPhase.EXITING:
            if self.in_offboard and due:
                if self._cfg.exit_mode == "hold":
                    acts.append(Action("set_mode", PX4_MAIN_MODE_AUTO, PX4_SUB_MODE_AUTO_LOITER,
                                       "exit to Hold"))
                else:
                    acts.append(Action("set_mode", PX4_MAIN_MODE_POSCTL, 0, "exit to Position"))
            elif not self.in_offboard:
                self._go(t_s, OffboardPhase.DONE, "out of OFFBOARD")
        if self.phase is OffboardPhase.DONE:
            acts.append(Action("stop_stream", reason="offboard finished"))
        if any(a.kind in ("set_mode", "arm") for a in acts):
            self._last_request_s = t_s
        return acts

    def _go(self, t_s: float, phase: OffboardPhase, reason: str) -> None:
        self.phase = phase
        self.transitions.append((t_s, phase, reason))
