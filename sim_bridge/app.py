"""The emulator's asyncio runtime: wires the vehicle physics, the PX4 state machine, the MAVLink
links, the AGV (FOLLOW_TARGET from its own node), the camera frame server and the ground-truth
publisher (docs/reference/wire.md).

Two clocks:

* ``realtime``: boot time follows the wall clock (``time.monotonic``); the physics is integrated
  in fixed steps up to "now" every tick; setpoints are applied as they arrive.
* ``lockstep``: simulated time advances one ``step_dt_s`` at a time. At step ``k`` the emulator
  sends the MAVLink messages due by ``t = k step_dt_s`` (stamped ``t``), FOLLOW_TARGET if due,
  the ground-truth record and the camera frame(s) due; then waits up to ``lockstep_timeout_s``
  of wall time until every frame delivered so far has been answered by one SET_ATTITUDE_TARGET
  (camera latency jitter can deliver two frames in one step: the step then waits for two
  answers; a timeout is counted as a lost setpoint, is no offboard signal, and clears the
  count); then
  integrates to ``t + step_dt_s``, stopping at every link event in between: each message
  leaving the transport delay (``[sim.telemetry]``) at its due time, each delayed delivery of
  an impaired link, and, with a transport delay, each stream's messages at their own rates
  (stamped with the time they sample; on the ideal link the streams are sampled at the step
  boundaries only). The telemetry a client holds when step ``k``'s frame arrives is therefore
  what a real link would have delivered by ``t``. Commands are handled whenever they arrive,
  stamped ``t``.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import logging
import math
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from sim_bridge import SimBridgeError
from sim_bridge.camera import Camera, RenderedFrame, read_calibration
from sim_bridge.camera_model import CameraTiming, DelayLine, Sensor, rngs
from sim_bridge.config import EmulatorConfig, parse_address
from sim_bridge.follow_target import follow_target_fields, latlon_from_ned
from sim_bridge.frames import FrameServer
from sim_bridge.gcs import PARAM_TYPE_INT32, PARAM_TYPE_REAL32, GcsServices, ParamSpec, ParamStore
from sim_bridge.impairment import LinkImpairment, msgid_of
from sim_bridge.link import Address, LinkCounters, MavUdpLink
from sim_bridge.physics.agv import AgvState, AgvTrajectory
from sim_bridge.physics.vehicle import (
    G_M_S2,
    AttitudeCommand,
    VehicleState,
    initial_state,
    quat_from_euler,
)
from sim_bridge.px4 import (
    ACCEPTED,
    DENIED,
    AttitudeTarget,
    Mode,
    Px4,
    Px4Params,
)
from sim_bridge.signing import SigningState
from sim_bridge.truth import TruthPublisher, truth_record
from sim_bridge.vehicle_model import build_vehicle_model, vehicle_is_ideal

log = logging.getLogger(__name__)

# MAVLink message ids the emulator streams or answers
HEARTBEAT = 0
SYS_STATUS = 1
SYSTEM_TIME = 2
ATTITUDE = 30
ATTITUDE_QUATERNION = 31
LOCAL_POSITION_NED = 32
HIGHRES_IMU = 105
SET_ATTITUDE_TARGET = 82
ATTITUDE_TARGET = 83
# ATTITUDE, ATTITUDE_QUATERNION, LOCAL_POSITION_NED, HIGHRES_IMU: what a telemetry fault hits
_STATE_STREAMS = frozenset({30, 31, 32, 105})
GLOBAL_POSITION_INT = 33
TIMESYNC = 111
AUTOPILOT_VERSION = 148
HOME_POSITION = 242
EXTENDED_SYS_STATE = 245

# MAV_CMD answered by the link layer (not the commander)
CMD_REQUEST_MESSAGE = 512
CMD_SET_MESSAGE_INTERVAL = 511
CMD_REQUEST_AUTOPILOT_CAPABILITIES = 520
CMD_GET_HOME_POSITION = 410

# Default stream rates (Hz), like a PX4 "onboard" MAVLink instance; 0 = only on request
DEFAULT_RATES_HZ: dict[int, float] = {
    HEARTBEAT: 1.0,
    SYS_STATUS: 2.0,
    ATTITUDE_QUATERNION: 50.0,
    ATTITUDE: 25.0,
    LOCAL_POSITION_NED: 30.0,
    HIGHRES_IMU: 50.0,
    ATTITUDE_TARGET: 10.0,
    GLOBAL_POSITION_INT: 10.0,
    EXTENDED_SYS_STATE: 5.0,
    HOME_POSITION: 0.0,
    AUTOPILOT_VERSION: 0.0,
    SYSTEM_TIME: 0.0,
    TIMESYNC: 0.0,
}

# PX4's own defaults (src/modules/mavlink/mavlink_main.cpp, configure_streams_to_default) for
# the messages the emulator implements: mode "onboard" (the offboard API link, SITL -m onboard)
# and mode "normal" (the GCS link). HEARTBEAT is always 1 Hz.
PX4_ONBOARD_RATES_HZ: dict[int, float] = {
    HEARTBEAT: 1.0,
    TIMESYNC: 10.0,
    HIGHRES_IMU: 50.0,
    LOCAL_POSITION_NED: 30.0,
    ATTITUDE: 100.0,
    ATTITUDE_QUATERNION: 50.0,
    ATTITUDE_TARGET: 10.0,
    EXTENDED_SYS_STATE: 5.0,
    GLOBAL_POSITION_INT: 50.0,
    HOME_POSITION: 0.5,
    SYS_STATUS: 5.0,
    SYSTEM_TIME: 1.0,
    AUTOPILOT_VERSION: 0.0,
}
PX4_NORMAL_RATES_HZ: dict[int, float] = {
    HEARTBEAT: 1.0,
    ATTITUDE: 15.0,
    ATTITUDE_TARGET: 2.0,
    EXTENDED_SYS_STATE: 1.0,
    GLOBAL_POSITION_INT: 5.0,
    HOME_POSITION: 0.5,
    LOCAL_POSITION_NED: 1.0,
    SYS_STATUS: 1.0,
    ATTITUDE_QUATERNION: 0.0,
    HIGHRES_IMU: 0.0,
    TIMESYNC: 0.0,
    SYSTEM_TIME: 0.0,
    AUTOPILOT_VERSION: 0.0,
}
FLIGHT_SW_VERSION = (1 << 24) | (16 << 16) | (0 << 8) | 255  # v1.16.0 official
# MAVLINK2, COMMAND_INT, SET_ATTITUDE_TARGET, SET_POSITION_TARGET_LOCAL_NED, MISSION_INT,
# PARAM_ENCODE_BYTEWISE (integer parameters travel byte-wise, as PX4's do)
CAPABILITIES = 8192 | 8 | 64 | 128 | 4 | 16

# PX4 parameters that change what the emulated commander does (others are only stored)
_PARAM_FIELDS = {"MPC_THR_HOVER": "hover_thrust", "COM_OF_LOSS_T": "com_of_loss_t_s",
                 "COM_OBL_RC_ACT": "com_obl_rc_act", "COM_DISARM_PRFLT": "com_disarm_prflt_s",
                 "COM_DISARM_LAND": "com_disarm_land_s", "MPC_TILTMAX_AIR": "max_tilt_rad"}


def px4_param_specs(cfg: EmulatorConfig) -> tuple[ParamSpec, ...]:
    """The parameters a ground station sees (PX4 names, units and ranges; defaults from the
    scenario where the emulator models them, PX4's defaults otherwise)."""
    sim, link = cfg.sim, cfg.sim.link
    real, i32 = PARAM_TYPE_REAL32, PARAM_TYPE_INT32
    return (
        ParamSpec("MAV_SYS_ID", i32, link.sysid, 1, 250),
        ParamSpec("MAV_COMP_ID", i32, link.compid, 1, 250),
        ParamSpec("MAV_TYPE", i32, 2, 0, 50),                  # quadrotor
        ParamSpec("SYS_AUTOSTART", i32, 4001, 0, 9_999_999),   # generic quadrotor x
        ParamSpec("MPC_THR_HOVER", real, sim.vehicle.hover_thrust, 0.1, 0.8),
        ParamSpec("MPC_TILTMAX_AIR", real, round(math.degrees(sim.vehicle.max_tilt_rad), 3),
                  20.0, 89.0),                                 # deg
        ParamSpec("MPC_LAND_SPEED", real, 0.7, 0.6, 10.0),     # m/s (the emulator's fixed value)
        ParamSpec("MPC_TKO_SPEED", real, 1.5, 1.0, 5.0),       # m/s (fixed)
        ParamSpec("MIS_TAKEOFF_ALT", real, 2.5, 0.0, 80.0),    # m (fixed)
        ParamSpec("COM_OF_LOSS_T", real, sim.px4.com_of_loss_t_s, 0.0, 60.0),  # s
        ParamSpec("COM_OBL_RC_ACT", i32, sim.px4.com_obl_rc_act, 0, 7),
        ParamSpec("COM_DISARM_PRFLT", real, sim.px4.com_disarm_prflt_s, -1.0, 20.0),  # s
        ParamSpec("COM_DISARM_LAND", real, 2.0, -1.0, 20.0),   # s
        ParamSpec("COM_RC_IN_MODE", i32, 4, 0, 4),             # 4: no RC (companion flight)
        ParamSpec("NAV_DLL_ACT", i32, 0, 0, 6),                # GCS loss: disabled
        ParamSpec("NAV_RCL_ACT", i32, 2, 0, 6),                # RC loss: Return
    )


@dataclass(frozen=True)
class BridgeStats:
    """What the runtime counted (for logs and tests)."""

    t_s: float
    steps: int
    lockstep_timeouts: int
    setpoints_received: int
    setpoints_ignored: int
    commands: int
    acks_sent: int
    frames: int
    offboard: LinkCounters
    gcs: LinkCounters
    frames_dropped: int = 0
    frames_delivered: int = 0
    timesync_replies: int = 0
    timesync_offset_us: float | None = None
    timesync_rtt_us: float | None = None


class _Streams:
    """Per-link stream schedule in boot time (s)."""

    def __init__(self, rates_hz: dict[int, float] | None = None) -> None:
        self.rates_hz = DEFAULT_RATES_HZ if rates_hz is None else rates_hz
        self.interval_s: dict[int, float | None] = {
            mid: (1.0 / hz if hz > 0 else None) for mid, hz in self.rates_hz.items()}
        self.next_s: dict[int, float] = dict.fromkeys(self.rates_hz, 0.0)

    def set_interval(self, msgid: int, interval_us: float, now_s: float) -> bool:
        if msgid not in self.rates_hz:
            return False
        if interval_us == 0:  # default rate
            hz = self.rates_hz[msgid]
            self.interval_s[msgid] = 1.0 / hz if hz > 0 else None
        elif interval_us < 0:
            self.interval_s[msgid] = None
        else:
            self.interval_s[msgid] = interval_us * 1e-6
        self.next_s[msgid] = now_s
        return True

    def next_due_s(self) -> float:
        """Boot time of the next message due on this link (``inf``: none streams)."""
        return min((self.next_s[mid] for mid, iv in self.interval_s.items() if iv is not None),
                   default=math.inf)

    def due(self, now_s: float) -> list[int]:
        out = []
        for mid, iv in self.interval_s.items():
            if iv is None or now_s + 1e-9 < self.next_s[mid]:
                continue
            out.append(mid)
            # no catch-up bursts: the next one is one interval after now (or the schedule)
            self.next_s[mid] = max(self.next_s[mid] + iv, now_s + 0.5 * iv)
        return out


class SimBridge:
    """The emulator. ``async with SimBridge(cfg) as sim: await sim.run(duration_s)``.

    ``bind_host`` is where the UDP links and the frame server listen (PX4 SITL listens on all
    interfaces; tests use 127.0.0.1). After ``__aenter__``, :attr:`ports` holds the bound ports.
    """

    def __init__(self, cfg: EmulatorConfig, *, bind_host: str = "0.0.0.0") -> None:
        self.cfg = cfg
        self.bind_host = bind_host
        sim = cfg.sim
        self.lockstep = sim.time_mode == "lockstep"
        self.model = build_vehicle_model(cfg)
        x, y, z, roll, pitch, yaw = cfg.scenario.uav_pose
        airborne = sim.start == "airborne"
        if not airborne:
            z = cfg.ground_z_m
            roll = pitch = 0.0
        self.state: VehicleState = initial_state((x, y, z), roll, pitch, yaw,
                                                 on_ground=not airborne)
        self.px4 = Px4(
            Px4Params(com_of_loss_t_s=sim.px4.com_of_loss_t_s,
                      com_obl_rc_act=sim.px4.com_obl_rc_act,
                      com_disarm_prflt_s=sim.px4.com_disarm_prflt_s,
                      hover_thrust=sim.vehicle.hover_thrust,
                      max_tilt_rad=sim.vehicle.max_tilt_rad,
                      origin_alt_m=cfg.target.origin_alt_m),
            self.state, armed=airborne, mode=Mode.POSCTL)
        self._t0_wall = time.monotonic()
        self._unix_t0_s = time.time()  # SYSTEM_TIME: Unix time at simulation time 0
        self.t_s = 0.0
        self._setpoint_event = asyncio.Event()
        # lockstep: frames delivered and not yet answered by a setpoint (one answer per frame)
        self._unanswered = 0
        # links whose setpoints are counted before the impairment (_on_raw_datagram)
        self._raw_counted: set[str] = set()
        self._links: dict[str, MavUdpLink] = {}
        self._streams: dict[str, _Streams] = {}
        self._attitude_target: AttitudeCommand | None = None  # what the vehicle flies now
        c, tg = cfg.camera, cfg.target
        self.agv = AgvTrajectory(sim.agv.trajectory, sim.agv.speed_scale, sim.agv.top_z_m)
        lens_k = lens_d = None
        if c.calibration_file:
            lens_k, lens_d = read_calibration(c.calibration_file, c.width_px, c.height_px,
                                              relative_to=cfg.source)
        self.camera = Camera(
            c.focal_length_m, c.pixel_size_m, c.width_px, c.height_px,
            mount_rpy_rad=c.mount_rpy_rad, mount_offset_m=c.mount_offset_m,
            target_length_m=tg.length_m, target_width_m=tg.width_m, target_height_m=tg.height_m,
            pattern=tg.pattern, aruco_dictionary=tg.aruco_dictionary, aruco_id=tg.aruco_id,
            aruco_size_m=tg.aruco_size_m, noise_std=sim.camera.noise_std,
            blur_px=sim.camera.blur_px, seed=sim.seed, camera_matrix=lens_k,
            dist_coeffs=lens_d)
        # The autopilot's clock: simulation time + the boot offset (docs/reference/wire.md, Clocks).
        self.boot_offset_s = sim.telemetry.boot_offset_s
        cm = sim.camera_model
        self.cam_timing = CameraTiming(cm, sim.seed, clock_offset_s=self.boot_offset_s)
        self.sensor = Sensor(cm, c.width_px, c.height_px, sim.seed)
        self._exposure_s = cm.exposure_ms * 1e-3
        self._frame_line: DelayLine[tuple[int, int, np.ndarray]] = DelayLine()
        self._frames_dropped = 0
        self._frames_delivered = 0
        self._delivered_this_step = 0
        tm = sim.telemetry
        self._tx_delay = (tm.delay_ms * 1e-3, tm.delay_jitter_ms * 1e-3)
        # Lockstep streams: with a transport delay they run at their own rates inside each
        # step (a sample taken at a step boundary would reach the client only after it answered
        # that step's frame). On the ideal link (no delay) they are sampled at each step
        # boundary, as the emulator always did: the client gets the step's exact time.
        self._streams_in_step = self.lockstep and tm.delay_ms > 0
        (self._tx_rng,) = rngs(sim.seed, 1, salt=3)
        # HIGHRES_IMU: its own generators (accelerometer noise, transport jitter), so that the
        # other messages draw the same jitter with or without it
        self._imu_rng, self._imu_tx_rng = rngs(sim.seed, 2, salt=5)
        self._accel_noise = tm.accel_noise_m_s2
        self._accel_bias = np.asarray(tm.accel_bias_m_s2, dtype=float)
        # LOCAL_POSITION_NED's velocity noise: its own generator too
        (self._vel_rng,) = rngs(sim.seed, 1, salt=7)
        self._vel_noise = tm.velocity_noise_m_s
        self._tx_lines: dict[str, DelayLine[tuple[list[bytes], Address | None]]] = {}
        self._timesync_sent_ns: dict[int, float] = {}
        self._timesync_replies = 0
        self._timesync_offset_us: float | None = None
        self._timesync_rtt_us: float | None = None
        self._vehicle_ideal = vehicle_is_ideal(cfg)
        self._frame_server: FrameServer | None = None
        self._truth: TruthPublisher | None = None
        self._frame_seq = 0
        self._steps = 0
        self._timeouts = 0
        self._setpoints = 0
        self._commands = 0
        self._acks = 0
        self._last_mode = self.px4.mode
        self._last_armed = self.px4.armed
        self._stack = contextlib.AsyncExitStack()
        self.ports: dict[str, int] = {}
        # one signing state (key, timestamps, streams) for all links, as in PX4
        self.signing: SigningState | None = (
            SigningState(sim.signing.key()) if sim.signing.enabled else None)
        self.gcs = GcsServices(ParamStore(px4_param_specs(cfg), on_change=self._on_param))

    # ------------------------------------------------------------------ lifecycle
    async def __aenter__(self) -> SimBridge:
        await self._stack.__aenter__()
        try:
            await self._open()
        except BaseException:
            await self._stack.aclose()
            raise
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self._stack.aclose()

    async def _open(self) -> None:
        cfg, link = self.cfg, self.cfg.sim.link
        self._setpoint_event = asyncio.Event()
        for name, port, remote in (("offboard", link.offboard_local_port, link.offboard_remote),
                                   ("gcs", link.gcs_local_port, link.gcs_remote)):
            ml = MavUdpLink(name, self.bind_host, port, parse_address(remote), link.sysid,
                            link.compid, handler=self._on_message, **self._link_options(name))
            await ml.open()
            self._stack.callback(ml.close)
            self._links[name] = ml
            rates = None
            if cfg.sim.telemetry.rates == "px4":
                rates = PX4_ONBOARD_RATES_HZ if name == "offboard" else PX4_NORMAL_RATES_HZ
            self._streams[name] = _Streams(rates)
            self._tx_lines[name] = DelayLine()
            self.ports[name] = ml.port
        agv_link = MavUdpLink("agv", self.bind_host, link.agv_local_port, None,
                              cfg.target.mavlink_sysid, cfg.target.mavlink_compid,
                              **self._link_options("agv"))
        await agv_link.open()
        self._stack.callback(agv_link.close)
        self._links["agv"] = agv_link
        self.ports["agv"] = agv_link.port
        self._frame_server = await self._stack.enter_async_context(
            FrameServer(self.bind_host, link.frame_port))
        self.ports["frames"] = self._frame_server.port
        self._truth = TruthPublisher(*parse_address(link.truth_remote))
        self._stack.callback(self._truth.close)
        self._t0_wall = time.monotonic()
        self._unix_t0_s = time.time()
        log.info("sim_bridge %s, scenario %s, start %s: MAVLink offboard udp %s:%d -> %s, "
                 "GCS udp %s:%d -> %s, AGV udp :%d (sysid %d), frames tcp :%s, truth udp -> %s",
                 self.cfg.sim.time_mode, cfg.scenario.name, cfg.sim.start, self.bind_host,
                 self.ports["offboard"], link.offboard_remote, self.bind_host,
                 self.ports["gcs"], link.gcs_remote, self.ports["agv"],
                 cfg.target.mavlink_sysid, self.ports.get("frames", "-"), link.truth_remote)

    def _link_options(self, name: str) -> dict[str, Any]:
        """Signing and impairment of link ``name`` (``[sim.signing]``, ``[sim.impairment]``)."""
        sim = self.cfg.sim
        opts: dict[str, Any] = {"time_s": self.now_s, "deferred": self.lockstep}
        if self.signing is not None and name in sim.signing.links:
            opts["signing"] = self.signing
            opts["signing_link_id"] = ("offboard", "gcs", "agv").index(name)
        imp = sim.impairment
        if imp.active and name in imp.links:
            opts["impairment"] = LinkImpairment.build(
                name, imp.seed, imp.vehicle_to_companion, imp.companion_to_vehicle, imp.cuts,
                imp.heartbeat_stop_s if imp.heartbeat_stop_s >= 0 else None)
            opts["on_raw_datagram"] = self._on_raw_datagram
            self._raw_counted.add(name)
        return opts

    def _on_raw_datagram(self, data: bytes) -> None:
        """A datagram reached an impaired link, before the impairment. In lockstep a setpoint
        releases the step even if the network then drops, corrupts or delays it: the client
        has answered; what the network does to the answer is the experiment."""
        if self.lockstep and msgid_of(data) == SET_ATTITUDE_TARGET:
            self._answered()

    def _answered(self) -> None:
        """Lockstep: a setpoint answers one delivered frame; the step is released once every
        frame delivered in it has its answer. (Releasing on the first setpoint let the answer
        to a step's second frame, when latency jitter delivers two, release the NEXT step
        before its frame was handled: the emulator then ran a frame ahead of its client.)"""
        self._unanswered = max(0, self._unanswered - 1)
        if self._unanswered == 0:
            self._setpoint_event.set()

    def _deliver_due(self, t_s: float) -> None:
        """Lockstep: hand on every delayed datagram due by ``t_s`` (simulated time)."""
        for ml in self._links.values():
            ml.pump(t_s)

    def _next_state_event_s(self) -> float:
        """Lockstep: the next link event that needs the vehicle's state at its time: a delayed
        delivery (impairment; a setpoint takes effect then) or a stream message due."""
        due = [d for ml in self._links.values() if (d := ml.next_due_s()) is not None]
        if self._streams_in_step:
            due += [st.next_due_s() for st in self._streams.values()]
        return min(due, default=math.inf)

    def _advance_delivering(self, t_target: float) -> None:
        """Lockstep: integrate to ``t_target``, stopping at every link event in between, as a
        real autopilot's links run while it flies: a delayed setpoint takes effect at its
        arrival time, a message leaves the transport delay when it is due and (with a
        transport delay, :attr:`_streams_in_step`) each stream is sampled at its own rate,
        stamped with the time it samples (each to a physics step). So the telemetry a client
        holds when the next frame arrives is what a real link would have delivered by then:
        stamped at most the transport delay plus one stream period before the frame's step.
        (Streams sampled only at step boundaries, with any delay, arrived a whole step late.)"""
        while True:
            state_due = self._next_state_event_s()
            due = min(state_due, self._next_tx_s())
            if due >= t_target - 1e-9:
                break
            if state_due <= due:  # a message leaving the delay needs no state
                self._advance(due)
            self.t_s = due
            self._deliver_due(due)
            self._send_streams(due)
            self._flush_tx(due)
        self._advance(t_target)

    # ------------------------------------------------------------------ clock
    def now_s(self) -> float:
        """Boot time (s): wall clock since start in realtime, simulated time in lockstep."""
        if self.lockstep:
            return self.t_s
        return time.monotonic() - self._t0_wall

    def boot_s(self, t_s: float) -> float:
        """The autopilot's clock (s since its boot) at simulation time ``t_s``."""
        return t_s + self.boot_offset_s

    def _ms(self, t_s: float) -> int:
        """``time_boot_ms`` at simulation time ``t_s`` (whole ms, as PX4's; the nanosecond
        of slack keeps a float sum such as 37.25 + 0.04 = 37.28999... on 37290 ms)."""
        return math.floor(self.boot_s(t_s) * 1000 + 1e-6) & 0xFFFFFFFF

    def _us(self, t_s: float) -> int:
        """``time_usec`` (boot time) at simulation time ``t_s``."""
        return round(self.boot_s(t_s) * 1e6)

    # ------------------------------------------------------------------ transmit
    def _tx(self, link: MavUdpLink, msg: Any, addr: Address | None = None, *,
            reply: bool = False, rng: np.random.Generator | None = None) -> None:
        """Send ``msg`` on a vehicle link, through the transport delay (``sim.telemetry``).
        In lockstep a ``reply`` (ACK, requested message, TIMESYNC/PING answer) is not delayed:
        simulated time stands still while the step waits."""
        delay, jitter = self._tx_delay
        if delay <= 0 or (reply and self.lockstep):
            link.send(msg, addr)
            return
        d = delay + jitter * float((rng or self._tx_rng).uniform(-1.0, 1.0))
        self._tx_lines[link.name].push(self.now_s() + max(0.0, d), (link.pack(msg), addr))

    def _flush_tx(self, now_s: float) -> None:
        for name, line in self._tx_lines.items():
            link = self._links[name]
            for frames, addr in line.pop_due(now_s):
                link.send_frames(frames, addr)

    def _next_tx_s(self) -> float:
        return min((line.next_due_s for line in self._tx_lines.values()), default=math.inf)

    # ------------------------------------------------------------------ receive
    def _on_message(self, link: MavUdpLink, msg: Any, addr: Address) -> None:
        mtype = msg.get_type()
        t = self.now_s()
        if mtype == "SET_ATTITUDE_TARGET":
            self._setpoints += 1
            sp = AttitudeTarget(
                type_mask=int(msg.type_mask),
                q_wxyz=(float(msg.q[0]), float(msg.q[1]), float(msg.q[2]), float(msg.q[3])),
                body_rates_rad_s=(float(msg.body_roll_rate), float(msg.body_pitch_rate),
                                  float(msg.body_yaw_rate)),
                thrust_norm=float(msg.thrust))
            self.px4.on_attitude_target(t, sp)
            if link.name not in self._raw_counted:
                self._answered()
            self._note_changes(t)
        elif mtype in ("COMMAND_LONG", "COMMAND_INT"):
            self._on_command(link, msg, addr, t)
        elif mtype == "PING":
            if msg.target_system == 0 and msg.target_component == 0:
                self._tx(link, link.mav.ping_encode(msg.time_usec, msg.seq, msg.get_srcSystem(),
                                                    msg.get_srcComponent()), addr, reply=True)
        elif mtype == "TIMESYNC":
            self._on_timesync(link, msg, addr, t)
        else:
            self.gcs.handle(link, msg, addr)

    def _on_param(self, name: str, value: float) -> None:
        """A PARAM_SET changed ``name``: apply it to the commander if it models it."""
        field_name = _PARAM_FIELDS.get(name)
        if field_name is None:
            return
        v: float | int = value
        if name == "COM_OBL_RC_ACT":
            v = int(value)
        elif name == "MPC_TILTMAX_AIR":
            v = math.radians(value)
        self.px4.p = dataclasses.replace(self.px4.p, **{field_name: v})  # type: ignore[arg-type]
        log.info("param %s = %g", name, value)

    def _on_timesync(self, link: MavUdpLink, msg: Any, addr: Address, t: float) -> None:
        """PX4 (mavlink_timesync.cpp): a request (tc1 == 0) is answered with tc1 = own boot
        time in ns and ts1 echoed; an answer to one of our requests (ts1 = our stamp) gives
        PX4's offset sample ``(ts1 + now - 2 tc1) / 2`` and the round trip ``now - ts1``."""
        now_ns = round(self.boot_s(t) * 1e9)
        if msg.tc1 == 0:
            self._tx(link, link.mav.timesync_encode(now_ns, msg.ts1), addr, reply=True)
            return
        if msg.tc1 > 0 and int(msg.ts1) in self._timesync_sent_ns:
            self._timesync_sent_ns.pop(int(msg.ts1))
            self._timesync_replies += 1
            self._timesync_offset_us = (msg.ts1 + now_ns - 2 * msg.tc1) / 2 / 1000
            self._timesync_rtt_us = (now_ns - msg.ts1) / 1000

    def _on_command(self, link: MavUdpLink, msg: Any, addr: Address, t: float) -> None:
        self._commands += 1
        cmd = int(msg.command)
        if msg.get_type() == "COMMAND_LONG":
            params = (msg.param1, msg.param2, msg.param3, msg.param4, msg.param5, msg.param6,
                      msg.param7)
        else:
            params = (msg.param1, msg.param2, msg.param3, msg.param4, float(msg.x),
                      float(msg.y), float(msg.z))
        params = tuple(float(p) for p in params)  # type: ignore[assignment]
        after: int | None = None
        if cmd == CMD_REQUEST_MESSAGE:
            mid = int(params[0]) if math.isfinite(params[0]) else -1
            result = ACCEPTED if mid in DEFAULT_RATES_HZ else DENIED
            after = mid if result == ACCEPTED else None
        elif cmd == CMD_REQUEST_AUTOPILOT_CAPABILITIES:
            result, after = ACCEPTED, AUTOPILOT_VERSION
        elif cmd == CMD_GET_HOME_POSITION:
            result, after = ACCEPTED, HOME_POSITION
        elif cmd == CMD_SET_MESSAGE_INTERVAL:
            ok = math.isfinite(params[0]) and math.isfinite(params[1]) and self._streams[
                link.name].set_interval(int(params[0]), params[1], t)
            result = ACCEPTED if ok else DENIED
        else:
            res = self.px4.handle_command(t, cmd, params)
            result = res.result
            if res.text:
                log.info("command %d from %d/%d: result %d (%s)", cmd, msg.get_srcSystem(),
                         msg.get_srcComponent(), result, res.text)
        self._tx(link, link.mav.command_ack_encode(cmd, result, 0, 0, msg.get_srcSystem(),
                                                   msg.get_srcComponent()), addr, reply=True)
        self._acks += 1
        if after is not None:
            self._send_message(link, after, t, addr, reply=True)
        self._note_changes(t)

    def _note_changes(self, t: float) -> None:
        if self.px4.mode is not self._last_mode or self.px4.armed != self._last_armed:
            log.info("t=%.3f s: %s, %s", t, self.px4.mode.label,
                     "armed" if self.px4.armed else "disarmed")
            self._last_mode, self._last_armed = self.px4.mode, self.px4.armed

    # ------------------------------------------------------------------ telemetry
    def _ned_to_global(self, pos: np.ndarray) -> tuple[float, float, float]:
        tg = self.cfg.target
        return latlon_from_ned(pos, tg.origin_lat_deg, tg.origin_lon_deg, tg.origin_alt_m)

    def _encode(self, link: MavUdpLink, mid: int, t: float) -> Any:
        s, px4, mav, ms = self.state, self.px4, link.mav, self._ms(t)
        if mid == HEARTBEAT:
            return mav.heartbeat_encode(2, 12, px4.base_mode, px4.custom_mode,
                                        px4.system_status, 3)
        if mid == SYS_STATUS:
            sensors = 1 | 2 | 4 | 8 | 32 | 0x8000 | 0x200000 | 0x2000000
            return mav.sys_status_encode(sensors, sensors, sensors, 100, 16000, -1, 100,
                                         0, 0, 0, 0, 0, 0)
        if mid == ATTITUDE_QUATERNION:
            q, w = s.q_wxyz, s.rates_frd_rad_s
            return mav.attitude_quaternion_encode(ms, *(float(v) for v in q),
                                                  *(float(v) for v in w))
        if mid == ATTITUDE:
            w = s.rates_frd_rad_s
            return mav.attitude_encode(ms, s.roll_rad, s.pitch_rad, s.yaw_rad,
                                       *(float(v) for v in w))
        if mid == ATTITUDE_TARGET:  # PX4 streams/ATTITUDE_TARGET.hpp: the attitude setpoint
            cmd = self._attitude_target or self.px4.attitude_command()
            q = quat_from_euler(cmd.roll_rad, cmd.pitch_rad, cmd.yaw_rad)
            rates = cmd.body_rates_frd_rad_s or (0.0, 0.0, cmd.yaw_rate_ff_rad_s)
            return mav.attitude_target_encode(ms, 0, [float(v) for v in q],
                                              *(float(v) for v in rates),
                                              float(cmd.thrust_norm))
        if mid == HIGHRES_IMU:  # PX4 streams/HIGHRES_IMU.hpp (docs/reference/wire.md, HIGHRES_IMU)
            f = self.specific_force_frd(s)
            if self._accel_noise > 0 or np.any(self._accel_bias):
                f = f + self._accel_bias + self._accel_noise * self._imu_rng.standard_normal(3)
            w = s.rates_frd_rad_s
            return mav.highres_imu_encode(self._us(t), *(float(v) for v in f),
                                          *(float(v) for v in w), 0.0, 0.0, 0.0, 0.0, 0.0,
                                          0.0, 0.0, 0b111111)
        if mid == LOCAL_POSITION_NED:
            vel = s.vel_ned_m_s
            if self._vel_noise > 0:
                vel = vel + self._vel_noise * self._vel_rng.standard_normal(3)
            return mav.local_position_ned_encode(ms, *(float(v) for v in s.pos_ned_m),
                                                 *(float(v) for v in vel))
        if mid == GLOBAL_POSITION_INT:
            lat, lon, alt = self._ned_to_global(s.pos_ned_m)
            rel = float(px4.home_ned_m[2] - s.pos_ned_m[2])
            v = s.vel_ned_m_s * 100
            hdg = round(math.degrees(s.yaw_rad) % 360 * 100) % 36000
            return mav.global_position_int_encode(ms, int(lat * 1e7), int(lon * 1e7),
                                                  int(alt * 1000), int(rel * 1000),
                                                  int(v[0]), int(v[1]), int(v[2]), hdg)
        if mid == EXTENDED_SYS_STATE:
            return mav.extended_sys_state_encode(0, px4.landed_state)
        if mid == TIMESYNC:  # PX4's own request (streams/TIMESYNC.hpp): tc1 = 0, ts1 = now ns
            ts1 = round(self.boot_s(t) * 1e9)
            self._timesync_sent_ns[ts1] = t
            if len(self._timesync_sent_ns) > 64:
                self._timesync_sent_ns.pop(next(iter(self._timesync_sent_ns)))
            return mav.timesync_encode(0, ts1)
        if mid == SYSTEM_TIME:
            return mav.system_time_encode(round((self._unix_t0_s + t) * 1e6), ms)
        if mid == HOME_POSITION:
            h = px4.home_ned_m
            lat, lon, alt = self._ned_to_global(h)
            return mav.home_position_encode(int(lat * 1e7), int(lon * 1e7), int(alt * 1000),
                                            float(h[0]), float(h[1]), float(h[2]),
                                            [1.0, 0.0, 0.0, 0.0], 0.0, 0.0, 0.0,
                                            self._us(t))
        if mid == AUTOPILOT_VERSION:
            return mav.autopilot_version_encode(CAPABILITIES, FLIGHT_SW_VERSION, 0, 0, 0,
                                                [0] * 8, [0] * 8, [0] * 8, 0x26AC, 0x11,
                                                0x5EB1D6E0)
        raise SimBridgeError(f"no encoder for message {mid}")  # pragma: no cover

    @staticmethod
    def specific_force_frd(s: VehicleState) -> np.ndarray:
        """What an ideal accelerometer reads (m/s^2, body FRD): the vehicle's acceleration
        less gravity, i.e. thrust, drag, wind and turbulence (``R' (a - g e_z)``); ``-g``
        along z in a level hover or at rest on the ground."""
        f_ned = np.asarray(s.acc_ned_m_s2, dtype=float) - np.array([0.0, 0.0, G_M_S2])
        out: np.ndarray = s.rot_body_to_ned.T @ f_ned
        return out

    def _send_message(self, link: MavUdpLink, mid: int, t: float,
                      addr: Address | None = None, *, reply: bool = False) -> None:
        self._tx(link, self._encode(link, mid, t), addr, reply=reply,
                 rng=self._imu_tx_rng if mid == HIGHRES_IMU else None)

    def _send_streams(self, t: float) -> None:
        faults = self.cfg.sim.faults
        for name, streams in self._streams.items():
            link = self._links[name]
            for mid in streams.due(t):
                if mid in _STATE_STREAMS and faults.dropout(t):
                    continue  # injected telemetry dropout
                if mid in _STATE_STREAMS and faults.nan(t):
                    self._tx(link, self._encode_nan(link, mid, t),
                             rng=self._imu_tx_rng if mid == HIGHRES_IMU else None)
                    continue
                self._send_message(link, mid, t)

    def _encode_nan(self, link: MavUdpLink, mid: int, t: float) -> Any:
        """The state message ``mid`` with NaN attitude/velocity (injected fault)."""
        nan, ms, mav = float("nan"), self._ms(t), link.mav
        if mid == ATTITUDE_QUATERNION:
            return mav.attitude_quaternion_encode(ms, nan, nan, nan, nan, nan, nan, nan)
        if mid == ATTITUDE:
            return mav.attitude_encode(ms, nan, nan, nan, nan, nan, nan)
        if mid == HIGHRES_IMU:
            return mav.highres_imu_encode(self._us(t), nan, nan, nan, nan, nan, nan, 0.0, 0.0,
                                          0.0, 0.0, 0.0, 0.0, 0.0, 0b111111)
        p = self.state.pos_ned_m
        return mav.local_position_ned_encode(ms, float(p[0]), float(p[1]), float(p[2]),
                                             nan, nan, nan)

    # ------------------------------------------------------------------ world outputs
    def _send_follow_target(self, t: float) -> None:
        """FOLLOW_TARGET from the AGV's own node (sysid ``target.mavlink_sysid``) to every peer
        of the vehicle's links (the configured remotes and whoever talks to the vehicle)."""
        tg = self.cfg.target
        fields = follow_target_fields(self.agv.state(t), self._ms(t), tg.origin_lat_deg,
                                      tg.origin_lon_deg, tg.origin_alt_m)
        agv_link = self._links["agv"]
        targets: list[Address] = []
        for name in ("offboard", "gcs"):
            targets += [a for a in self._links[name].peers if a not in targets]
        for a in targets:
            agv_link.send(agv_link.mav.follow_target_encode(**fields), a)

    async def _publish_frame(self, t: float) -> None:
        """Capture the camera frame exposed around ``t``: render it, publish the ground-truth
        record at once, and queue the frame for delivery after the camera's latency (or drop
        it), then deliver every frame due by ``t``."""
        agv = self.agv.state(t)
        s = self.state
        blur = self._exposure_s > 0
        frame = self.camera.render(
            s.pos_ned_m, s.q_wxyz, agv, occluded=self.cfg.sim.camera.occluded(t),
            uav_vel_ned_m_s=s.vel_ned_m_s if blur else None,
            uav_rates_frd_rad_s=s.rates_frd_rad_s if blur else None,
            exposure_s=self._exposure_s)
        seq = self._frame_seq
        self._frame_seq += 1
        cap = self.cam_timing.capture(t)
        if self._truth is not None:
            self._truth.publish(self._truth_record(t, seq, agv, frame, cap.stamp_us,
                                                   None if cap.dropped else cap.deliver_s))
        if cap.dropped:
            self._frames_dropped += 1
        else:
            image = self.sensor.apply(frame.image, self.boot_s(t))
            self._frame_line.push(cap.deliver_s, (seq, cap.stamp_us, image))
        await self._deliver_frames(t)

    async def _deliver_frames(self, now_s: float) -> None:
        for seq, stamp_us, image in self._frame_line.pop_due(now_s):
            self._frames_delivered += 1
            self._delivered_this_step += 1
            self._unanswered += 1
            if self._frame_server is not None:
                await self._frame_server.publish(seq, stamp_us, image)

    def _truth_record(self, t: float, seq: int, agv: AgvState, frame: RenderedFrame,
                      stamp_us: int, deliver_s: float | None) -> dict[str, Any]:
        s = self.state
        age = self.px4.setpoint_age_s(t)
        rec = truth_record(
            self._us(t), seq, s.pos_ned_m, s.vel_ned_m_s, s.q_wxyz, s.rates_frd_rad_s, agv,
            frame, disturbance_accel_ned_m_s2=s.disturbance_ned_m_s2, mode=self.px4.mode.label,
            armed=self.px4.armed, setpoint_age_s=age if math.isfinite(age) else None)
        rec["sim_t_s"] = t  # t_us is on the autopilot's clock (boot offset); this is sim time
        if not self._vehicle_ideal:
            rec["hover_thrust_true"] = self.model.true_hover_thrust(t)
        if not self.cfg.sim.camera_model.ideal:
            rec["frame_t_us"] = stamp_us
            rec["frame_dropped"] = deliver_s is None
            rec["frame_deliver_t_us"] = None if deliver_s is None else self._us(deliver_s)
            rec["brightness_gain"] = self.sensor.gain
        return rec

    # ------------------------------------------------------------------ stepping
    def _advance(self, t_target: float) -> None:
        """Integrate the physics from ``state.t_s`` to ``t_target`` in whole physics steps,
        running the commander logic at the start of each step."""
        dt = self.model.dt_s
        n = math.floor((t_target - self.state.t_s) / dt + 1e-9)
        if n <= 0:
            return
        self.px4.update(self.state.t_s, self.state)
        self._note_changes(self.state.t_s)
        # PX4's own modes fly with its converged hover-thrust estimate (MPC_USE_HTE)
        self.px4.hover_thrust_estimate = self.model.true_hover_thrust(self.state.t_s)
        self._attitude_target = self.px4.attitude_command()
        self.state = self.model.step(self.state, self._attitude_target, n * dt)
        self.px4.update(self.state.t_s, self.state)
        self._note_changes(self.state.t_s)

    async def run(self, duration_s: float | None = None) -> BridgeStats:
        """Run for ``duration_s`` of boot time (default: ``sim.duration_s``)."""
        d = self.cfg.sim.duration_s if duration_s is None else duration_s
        if self.lockstep:
            await self._run_lockstep(d)
        else:
            await self._run_realtime(d)
        self._log_link_faults()
        return self.stats()

    def _log_link_faults(self) -> None:
        """What the impairment did and what signing rejected, per link (end of run)."""
        for name, ml in self._links.items():
            if ml.impairment is not None:
                for direction, d in (("vehicle->peer", ml.impairment.outgoing),
                                     ("peer->vehicle", ml.impairment.incoming)):
                    log.info("impairment %s %s: %s", name, direction,
                             dataclasses.asdict(d.counters))
            if ml.signing is not None:
                c = ml.counters
                log.info("signing %s: rejected %d unsigned, %d bad signature, %d replayed; "
                         "accepted %d unsigned (allowed ids)", name, c.rx_unsigned,
                         c.rx_bad_signature, c.rx_replayed, c.rx_unsigned_allowed)

    async def _run_realtime(self, duration_s: float) -> None:
        sim = self.cfg.sim
        tick = min(0.01, sim.step_dt_s)
        frame_dt = 1.0 / sim.camera.rate_hz
        ft_dt = 1.0 / sim.agv.rate_hz
        next_frame = next_ft = 0.0
        while True:
            now = self.now_s()
            if now >= duration_s:
                break
            self._advance(now)
            self.t_s = self.state.t_s
            self._send_streams(now)
            if now >= next_ft:
                self._send_follow_target(now)
                next_ft = max(next_ft + ft_dt, now)
            if now >= next_frame:
                await self._publish_frame(self.state.t_s)
                self._steps += 1
                next_frame = max(next_frame + frame_dt, now)
            now2 = self.now_s()
            await self._deliver_frames(now2)
            self._flush_tx(now2)
            wake = min(now + tick, self._frame_line.next_due_s, self._next_tx_s())
            await asyncio.sleep(max(0.0, wake - self.now_s()))

    async def _run_lockstep(self, duration_s: float) -> None:
        sim = self.cfg.sim
        step = sim.step_dt_s
        ft_dt = 1.0 / sim.agv.rate_hz
        next_ft = 0.0
        k = 0
        while k * step < duration_s - 1e-9:
            t = k * step
            self.t_s = t
            self._deliver_due(t)
            self.px4.update(t, self.state)
            self._note_changes(t)
            self._send_streams(t)
            self._flush_tx(t)
            if t + 1e-9 >= next_ft:
                self._send_follow_target(t)
                next_ft += ft_dt
            self._delivered_this_step = 0
            self._setpoint_event.clear()
            await self._publish_frame(t)
            # the step is released once every frame delivered in it has been answered (one
            # setpoint each; a step that delivers two frames, by latency jitter, waits for
            # two). A step that delivers no frame (latency, drop) does not wait: a client that
            # answers frames has nothing to answer, and PX4 keeps the last setpoint.
            if self._delivered_this_step and self._unanswered > 0:
                try:
                    await asyncio.wait_for(self._setpoint_event.wait(),
                                           sim.lockstep_timeout_s)
                except TimeoutError:
                    self._timeouts += 1
                    self._unanswered = 0  # a frame left unanswered: start counting afresh
            self._advance_delivering((k + 1) * step)
            self._steps += 1
            k += 1
        self.t_s = k * step

    def stats(self) -> BridgeStats:
        return BridgeStats(
            t_s=self.t_s, steps=self._steps, lockstep_timeouts=self._timeouts,
            setpoints_received=self._setpoints, setpoints_ignored=self.px4.ignored_setpoints,
            commands=self._commands, acks_sent=self._acks, frames=self._frame_seq,
            offboard=self._links["offboard"].counters, gcs=self._links["gcs"].counters,
            frames_dropped=self._frames_dropped, frames_delivered=self._frames_delivered,
            timesync_replies=self._timesync_replies,
            timesync_offset_us=self._timesync_offset_us, timesync_rtt_us=self._timesync_rtt_us)


def stats_dict(stats: BridgeStats) -> dict[str, Any]:
    return dataclasses.asdict(stats)
