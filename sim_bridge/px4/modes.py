"""The PX4 state machine the emulator imitates (commander + offboard handling + the simple
position controllers of the non-offboard modes). Pure logic: every call takes the time
explicitly (``t_s``, seconds since boot, wall or simulated), no sockets or clocks.

Behaviour (docs/reference/px4-offboard.md; PX4 ``commander/``, ``mavlink_receiver.cpp``):

* Modes: POSCTL (default), ALTCTL, STABILIZED, MANUAL, ACRO, OFFBOARD, AUTO.TAKEOFF,
  AUTO.LOITER (Hold), AUTO.RTL, AUTO.LAND, TERMINATION. With no RC, the manual modes hold
  what they can: POSCTL holds position, ALTCTL holds altitude (level), STABILIZED/MANUAL/ACRO
  stay level at hover thrust.
* SET_ATTITUDE_TARGET with attitude (bit 128 clear) or body rates (bits 1 and 2 clear) is the
  offboard signal, in every mode; it is applied only while in OFFBOARD (nothing is stored
  before). THROTTLE_IGNORE (bit 64) without thrust_body (pymavlink's dialect has no such field)
  makes the message neither a signal nor applied (PX4 after PR #27627).
* DO_SET_MODE to OFFBOARD: accepted when disarmed; armed without a fresh signal ->
  TEMPORARILY_REJECTED. Arming in OFFBOARD without the signal -> TEMPORARILY_REJECTED.
  Disarming in the air without force (param2 = 21196) -> TEMPORARILY_REJECTED.
* Armed in OFFBOARD and the last signal older than ``COM_OF_LOSS_T``: switch at once to
  ``COM_OBL_RC_ACT`` (0 Position, 1 Altitude, 2 Stabilized, 3 Return, 4 Land, 5 Hold,
  6 Terminate, 7 Disarm). The vehicle stays in that mode until a client asks again.
* Auto-disarm: on the ground ``COM_DISARM_PRFLT`` after arming without take-off, and
  ``COM_DISARM_LAND`` (2 s) after landing.
* Airborne start (the paper starts hovering): PX4 cannot boot armed in the air, so this is a
  documented emulator choice: the vehicle starts ARMED, in POSCTL, holding its start pose, as if
  a pilot had taken off and handed over.
* Take-off: MAV_CMD_NAV_TAKEOFF (AUTO.TAKEOFF, climb to param7 AMSL or 2.5 m above home, then
  Hold), or arming in OFFBOARD and commanding thrust above hover.
* RTL (simplified): fly at the current altitude to above home, then land.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass

# MAV_RESULT
ACCEPTED = 0
TEMPORARILY_REJECTED = 1
DENIED = 2
UNSUPPORTED = 3
FAILED = 4

# MAV_CMD handled by the state machine
CMD_NAV_RETURN_TO_LAUNCH = 20
CMD_NAV_LAND = 21
CMD_NAV_TAKEOFF = 22
CMD_DO_SET_MODE = 176
CMD_DO_FLIGHTTERMINATION = 185
CMD_COMPONENT_ARM_DISARM = 400
FORCE_MAGIC = 21196

# SET_ATTITUDE_TARGET type_mask bits
MASK_ROLL_RATE_IGNORE = 1
MASK_PITCH_RATE_IGNORE = 2
MASK_YAW_RATE_IGNORE = 4
MASK_THRUST_BODY_SET = 32
MASK_THROTTLE_IGNORE = 64
MASK_ATTITUDE_IGNORE = 128

# MAV_MODE_FLAG
FLAG_CUSTOM_MODE_ENABLED = 1
FLAG_AUTO_ENABLED = 4
FLAG_GUIDED_ENABLED = 8
FLAG_STABILIZE_ENABLED = 16
FLAG_MANUAL_INPUT_ENABLED = 64
FLAG_SAFETY_ARMED = 128

# MAV_STATE
STATE_STANDBY = 3
STATE_ACTIVE = 4
STATE_CRITICAL = 5
STATE_FLIGHT_TERMINATION = 8

# MAV_LANDED_STATE
LANDED_ON_GROUND = 1
LANDED_IN_AIR = 2
LANDED_TAKEOFF = 3
LANDED_LANDING = 4

COM_DISARM_LAND_S = 2.0
MIS_TAKEOFF_ALT_M = 2.5
MPC_LAND_SPEED_M_S = 0.7
MPC_TKO_SPEED_M_S = 1.5
RTL_ARRIVE_RADIUS_M = 0.5
MAX_ABS_FIELD = 1e6  # setpoint fields beyond this are nonsense (a unit quaternion, rad/s, 0..1)


class Mode(enum.Enum):
    """PX4 navigation state -> (main_mode, sub_mode) of px4_custom_mode.h."""

    MANUAL = (1, 0)
    ALTCTL = (2, 0)
    POSCTL = (3, 0)
    AUTO_TAKEOFF = (4, 2)
    AUTO_LOITER = (4, 3)
    AUTO_RTL = (4, 5)
    AUTO_LAND = (4, 6)
    ACRO = (5, 0)
    OFFBOARD = (6, 0)
    STABILIZED = (7, 0)
    TERMINATION = (1, 99)  # reported as MANUAL (PX4 does the same)

    @property
    def custom_mode(self) -> int:
        main, sub = self.value
        return (main << 16) | ((sub if sub != 99 else 0) << 24)

    @property
    def label(self) -> str:
        """Name used in ground truth and logs (``"OFFBOARD"``, ``"AUTO.LOITER"``)."""
        return self.name.replace("AUTO_", "AUTO.")

    @property
    def is_auto(self) -> bool:
        main: int = self.value[0]
        return main == 4


OBL_RC_ACT = {0: Mode.POSCTL, 1: Mode.ALTCTL, 2: Mode.STABILIZED, 3: Mode.AUTO_RTL,
              4: Mode.AUTO_LAND, 5: Mode.AUTO_LOITER, 6: Mode.TERMINATION}  # 7: disarm

MAIN_TO_MODE = {1: Mode.MANUAL, 2: Mode.ALTCTL, 3: Mode.POSCTL, 5: Mode.ACRO, 6: Mode.OFFBOARD,
                 7: Mode.STABILIZED}
AUTO_SUB_TO_MODE = {2: Mode.AUTO_TAKEOFF, 3: Mode.AUTO_LOITER, 5: Mode.AUTO_RTL,
                     6: Mode.AUTO_LAND}


@dataclass(frozen=True)
class Px4Params:
    com_of_loss_t_s: float = 1.0
    com_obl_rc_act: int = 0
    com_disarm_prflt_s: float = 10.0
    com_disarm_land_s: float = COM_DISARM_LAND_S
    hover_thrust: float = 0.5
    max_tilt_rad: float = 0.6
    g_m_s2: float = 9.81
    origin_alt_m: float = 0.0  # AMSL altitude of the NED origin (for NAV_TAKEOFF param7)


@dataclass(frozen=True)
class AttitudeTarget:
    """A decoded SET_ATTITUDE_TARGET (#82). ``q_wxyz``: body FRD relative to NED;
    ``body_rates_rad_s``: FRD; ``thrust_norm``: 0..1."""

    type_mask: int
    q_wxyz: tuple[float, float, float, float]
    body_rates_rad_s: tuple[float, float, float]
    thrust_norm: float

    @property
    def uses_attitude(self) -> bool:
        return not self.type_mask & MASK_ATTITUDE_IGNORE

    @property
    def uses_rates(self) -> bool:
        return not self.type_mask & (MASK_ROLL_RATE_IGNORE | MASK_PITCH_RATE_IGNORE)

    @property
    def is_signal(self) -> bool:
        """Whether PX4 takes this message as offboard proof of life (and applies it)."""
        if self.type_mask & MASK_THROTTLE_IGNORE and not self.type_mask & MASK_THRUST_BODY_SET:
            return False
        if not (self.uses_attitude or self.uses_rates):
            return False
        vals = (*self.q_wxyz, *self.body_rates_rad_s, self.thrust_norm)
        if not all(math.isfinite(v) and abs(v) < MAX_ABS_FIELD for v in vals):
            return False
        return not (self.uses_attitude and not math.hypot(*self.q_wxyz) > 1e-6)


@dataclass(frozen=True)
class CommandResult:
    result: int
    text: str = ""
