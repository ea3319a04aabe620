"""The emulator's asyncio runtime: wires the vehicle physics, the PX4 state machine, the MAVLink
links, the AGV (FOLLOW_TARGET from its own node), the camera frame server and the ground-truth
publisher (docs/reference/wire.md), and runs them on one of two clocks (``sim_bridge.clocks``:
realtime
or lockstep).

What runs where: ``px4/`` (the commander, the telemetry streams, the answers to a client's
messages), ``camera/`` (rendering, lens, sensor, frame socket), ``transport`` (the telemetry's
transport delay), ``vehicle_model`` (the vehicle the physics flies), ``clocks`` (the loops);
this module owns the state they share and the world outputs (frames, ground truth, the AGV).
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import logging
import math
import socket
import time
from dataclasses import dataclass
from typing import Any

import numpy as np
from pymavlink.dialects.v20 import common as mavlink2

from sim_bridge import mavpack
from sim_bridge.camera import Camera, RenderedFrame, read_calibration
from sim_bridge.camera.frames import FrameServer
from sim_bridge.camera.sensor import CameraTiming, Sensor
from sim_bridge.clocks import run_lockstep, run_realtime
from sim_bridge.config import EmulatorConfig, parse_address
from sim_bridge.delay import DelayLine
from sim_bridge.follow_target import follow_target_fields
from sim_bridge.gcs import GcsServices, ParamStore
from sim_bridge.impairment import LinkImpairment, msgid_of
from sim_bridge.link import Address, LinkCounters, MavUdpLink
from sim_bridge.physics.agv import AgvState, AgvTrajectory
from sim_bridge.physics.vehicle import AttitudeCommand, VehicleState, initial_state
from sim_bridge.px4 import Mode, Px4, Px4Params
from sim_bridge.px4.services import Services
from sim_bridge.px4.streams import (
    PX4_NORMAL_RATES_HZ,
    PX4_ONBOARD_RATES_HZ,
    SET_ATTITUDE_TARGET,
    Streams,
)
from sim_bridge.px4.telemetry import Telemetry
from sim_bridge.px4_params import px4_param_specs
from sim_bridge.signing import SigningState
from sim_bridge.transport import Transport
from sim_bridge.truth import TruthPublisher, truth_record
from sim_bridge.vehicle_model import build_vehicle_model, vehicle_is_ideal

log = logging.getLogger(__name__)

# FOLLOW_TARGET packed without a pymavlink message object (mavpack.encoder: the same bytes)
_FOLLOW_TARGET = mavpack.encoder(mavlink2.MAVLink_follow_target_message)
_FOLLOW_TARGET_FIELDS: tuple[str, ...] = tuple(mavlink2.MAVLink_follow_target_message.fieldnames)


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


def build_camera(cfg: EmulatorConfig) -> Camera:
    """The renderer of ``[camera]``, ``[target]`` and ``[sim.camera]`` (with the calibrated lens
    of ``camera.calibration_file``, if any)."""
    c, tg, sim = cfg.camera, cfg.target, cfg.sim
    lens_k = lens_d = None
    if c.calibration_file:
        lens_k, lens_d = read_calibration(c.calibration_file, c.width_px, c.height_px,
                                          relative_to=cfg.source)
    return Camera(
        c.focal_length_m, c.pixel_size_m, c.width_px, c.height_px,
        mount_rpy_rad=c.mount_rpy_rad, mount_offset_m=c.mount_offset_m,
        target_length_m=tg.length_m, target_width_m=tg.width_m, target_height_m=tg.height_m,
        pattern=tg.pattern, aruco_dictionary=tg.aruco_dictionary, aruco_id=tg.aruco_id,
        aruco_size_m=tg.aruco_size_m, noise_std=sim.camera.noise_std,
        blur_px=sim.camera.blur_px, seed=sim.seed, camera_matrix=lens_k,
        dist_coeffs=lens_d)


def _build_px4(cfg: EmulatorConfig, state: VehicleState, airborne: bool) -> Px4:
    sim = cfg.sim
    return Px4(
        Px4Params(com_of_loss_t_s=sim.px4.com_of_loss_t_s,
                  com_obl_rc_act=sim.px4.com_obl_rc_act,
                  com_disarm_prflt_s=sim.px4.com_disarm_prflt_s,
                  hover_thrust=sim.vehicle.hover_thrust,
                  max_tilt_rad=sim.vehicle.max_tilt_rad,
                  origin_alt_m=cfg.target.origin_alt_m),
        state, armed=airborne, mode=Mode.POSCTL)


class SimBridge:
    """The emulator. ``async with SimBridge(cfg) as sim: await sim.run(duration_s)``.

    ``bind_host`` is where the UDP links and the frame server listen (PX4 SITL listens on all
    interfaces; tests use 127.0.0.1). After ``__aenter__``, :attr:`ports` holds the bound ports.
    ``frame_sock``: a listening socket for the frame server instead of ``link.frame_port``
    (``sim-bridge --frame-fd``).
    """

    def __init__(self, cfg: EmulatorConfig, *, bind_host: str = "0.0.0.0",
                 frame_sock: socket.socket | None = None) -> None:
        self.cfg = cfg
        self.bind_host = bind_host
        self._frame_sock = frame_sock
        sim = cfg.sim
        self.lockstep = sim.time_mode == "lockstep"
        # the vehicle: its dynamics, its start and its autopilot
        self.model = build_vehicle_model(cfg)
        x, y, z, roll, pitch, yaw = cfg.scenario.uav_pose
        airborne = sim.start == "airborne"
        if not airborne:
            z = cfg.ground_z_m
            roll = pitch = 0.0
        self.state: VehicleState = initial_state((x, y, z), roll, pitch, yaw,
                                                 on_ground=not airborne)
        self.px4 = _build_px4(cfg, self.state, airborne)
        self.attitude_target: AttitudeCommand | None = None  # what the vehicle flies now
        self._vehicle_ideal = vehicle_is_ideal(cfg)
        self._last_mode = self.px4.mode
        self._last_armed = self.px4.armed
        # clocks: the autopilot's is simulation time + the boot offset (docs/reference/wire.md,
        # Clocks)
        self._t0_wall = time.monotonic()
        self.unix_t0_s = time.time()  # SYSTEM_TIME: Unix time at simulation time 0
        self.t_s = 0.0
        self.boot_offset_s = sim.telemetry.boot_offset_s
        self._init_world()
        self._init_links()

    def _init_world(self) -> None:
        """The AGV, the camera and what happens to its frames."""
        sim = self.cfg.sim
        self.agv = AgvTrajectory(sim.agv.trajectory, sim.agv.speed_scale, sim.agv.top_z_m,
                                 ramp_accel_m_s2=sim.agv.ramp_accel_m_s2)
        self.camera = build_camera(self.cfg)
        cm = sim.camera_model
        self.cam_timing = CameraTiming(cm, sim.seed, clock_offset_s=self.boot_offset_s)
        self.sensor = Sensor(cm, self.cfg.camera.width_px, self.cfg.camera.height_px, sim.seed)
        self._exposure_s = cm.exposure_ms * 1e-3
        self.frame_line: DelayLine[tuple[int, int, np.ndarray]] = DelayLine()
        self._frame_server: FrameServer | None = None
        self._truth: TruthPublisher | None = None
        self._frame_seq = 0
        self._frames_dropped = 0
        self._frames_delivered = 0

    def _init_links(self) -> None:
        """The MAVLink side: links, telemetry, the answers to clients, lockstep bookkeeping."""
        sim, tm = self.cfg.sim, self.cfg.sim.telemetry
        self.links: dict[str, MavUdpLink] = {}
        self.transport = Transport(tm.delay_ms * 1e-3, tm.delay_jitter_ms * 1e-3, sim.seed,
                                   lockstep=self.lockstep, now_s=self.now_s)
        self.telemetry = Telemetry(self)
        self.services = Services(self)
        # Lockstep streams: with a transport delay they run at their own rates inside each
        # step (a sample taken at a step boundary would reach the client only after it answered
        # that step's frame). On the ideal link (no delay) they are sampled at each step
        # boundary, as the emulator always did: the client gets the step's exact time.
        self.streams_in_step = self.lockstep and tm.delay_ms > 0
        self.setpoint_event = asyncio.Event()
        # lockstep: frames delivered and not yet answered by a setpoint (one answer per frame)
        self.unanswered = 0
        self.delivered_this_step = 0
        # the newest delivered frame's header stamp in ms: an answer stamped with it answers
        # every frame delivered before it too (answered())
        self.newest_stamp_ms: int | None = None
        # links whose setpoints are counted before the impairment (_on_raw_datagram)
        self.raw_counted: set[str] = set()
        self.steps = 0
        self.timeouts = 0
        self._stack = contextlib.AsyncExitStack()
        self.ports: dict[str, int] = {}
        # one signing state (key, timestamps, streams) for all links, as in PX4
        self.signing: SigningState | None = (
            SigningState(sim.signing.key()) if sim.signing.enabled else None)
        self.gcs = GcsServices(ParamStore(px4_param_specs(self.cfg),
                                          on_change=self.services.on_param))

    # ------------------------------------------------------------------ lifecycle
    @property
    def frame_clients(self) -> int:
        """Camera clients connected now (lockstep's start wait, sim_bridge/clocks.py)."""
        return 0 if self._frame_server is None else self._frame_server.n_clients

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
        self.setpoint_event = asyncio.Event()
        for name, port, remote in (("offboard", link.offboard_local_port, link.offboard_remote),
                                   ("gcs", link.gcs_local_port, link.gcs_remote)):
            ml = MavUdpLink(name, self.bind_host, port, parse_address(remote), link.sysid,
                            link.compid, handler=self.services.on_message,
                            **self._link_options(name))
            await ml.open()
            self._stack.callback(ml.close)
            self.links[name] = ml
            # the GCS link at PX4's "normal" rates with either setting: the emulator's own
            # (offboard) rates there doubled the datagrams a step for a ground station that
            # PX4 sends no ATTITUDE_QUATERNION or HIGHRES_IMU at all
            rates = None if name == "offboard" else PX4_NORMAL_RATES_HZ
            if cfg.sim.telemetry.rates == "px4" and name == "offboard":
                rates = PX4_ONBOARD_RATES_HZ
            self.telemetry.streams[name] = Streams(rates)
            self.transport.add(ml)
            self.ports[name] = ml.port
        agv_link = MavUdpLink("agv", self.bind_host, link.agv_local_port, None,
                              cfg.target.mavlink_sysid, cfg.target.mavlink_compid,
                              **self._link_options("agv"))
        await agv_link.open()
        self._stack.callback(agv_link.close)
        self.links["agv"] = agv_link
        self.ports["agv"] = agv_link.port
        self._frame_server = await self._stack.enter_async_context(
            FrameServer(self.bind_host, link.frame_port, sock=self._frame_sock))
        self.ports["frames"] = self._frame_server.port
        self._truth = TruthPublisher(*parse_address(link.truth_remote))
        self._stack.callback(self._truth.close)
        self._t0_wall = time.monotonic()
        self.unix_t0_s = time.time()
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
            self.raw_counted.add(name)
        return opts

    def _on_raw_datagram(self, data: bytes) -> None:
        """A datagram reached an impaired link, before the impairment. In lockstep a setpoint
        releases the step even if the network then drops, corrupts or delays it: the client
        has answered; what the network does to the answer is the experiment."""
        if self.lockstep and msgid_of(data) == SET_ATTITUDE_TARGET:
            # time_boot_ms: the payload's first field (MAVLink 2 strips trailing zeros)
            self.answered(int.from_bytes(data[10:10 + min(4, data[1])], "little"))

    def answered(self, time_boot_ms: int | None = None) -> None:
        """Lockstep: a setpoint answers one delivered frame; the step is released once every
        frame delivered in it has its answer. (Releasing on the first setpoint let the answer
        to a step's second frame, when latency jitter delivers two, release the NEXT step
        before its frame was handled: the emulator then ran a frame ahead of its client.)

        A setpoint whose ``time_boot_ms`` is the newest delivered frame's stamp (its header's
        ``t_us`` in ms, within half a step: two frames are captured a step apart or more)
        answers all of them: a client that reads only the newest frame (the companion's
        ``?frames=newest``) skips the older one of a step that delivered two, and releases the
        step with its answer. Any other stamp counts as one answer, as before."""
        if self.unanswered > 1 and time_boot_ms is not None and self._is_newest(time_boot_ms):
            self.unanswered = 0
        self.unanswered = max(0, self.unanswered - 1)
        if self.unanswered == 0:
            self.setpoint_event.set()

    def _is_newest(self, time_boot_ms: int) -> bool:
        """Whether ``time_boot_ms`` is the newest delivered frame's stamp (+- half a step,
        modulo the u32 wrap)."""
        if self.newest_stamp_ms is None:
            return False
        d = (time_boot_ms - self.newest_stamp_ms + 2**31) % 2**32 - 2**31
        return abs(d) < 500 * self.cfg.sim.step_dt_s

    def note_changes(self, t: float) -> None:
        """Log a change of the autopilot's mode or arming state."""
        if self.px4.mode is not self._last_mode or self.px4.armed != self._last_armed:
            log.info("t=%.3f s: %s, %s", t, self.px4.mode.label,
                     "armed" if self.px4.armed else "disarmed")
            self._last_mode, self._last_armed = self.px4.mode, self.px4.armed

    # ------------------------------------------------------------------ clock
    def now_s(self) -> float:
        """Boot time (s): wall clock since start in realtime, simulated time in lockstep."""
        if self.lockstep:
            return self.t_s
        return time.monotonic() - self._t0_wall

    def boot_s(self, t_s: float) -> float:
        """The autopilot's clock (s since its boot) at simulation time ``t_s``."""
        return t_s + self.boot_offset_s

    def ms(self, t_s: float) -> int:
        """``time_boot_ms`` at simulation time ``t_s`` (whole ms, as PX4's; the nanosecond
        of slack keeps a float sum such as 37.25 + 0.04 = 37.28999... on 37290 ms)."""
        return math.floor(self.boot_s(t_s) * 1000 + 1e-6) & 0xFFFFFFFF

    def us(self, t_s: float) -> int:
        """``time_usec`` (boot time) at simulation time ``t_s``."""
        return round(self.boot_s(t_s) * 1e6)

    # ------------------------------------------------------------------ world outputs
    def send_follow_target(self, t: float) -> None:
        """FOLLOW_TARGET from the AGV's own node (sysid ``target.mavlink_sysid``) to every peer
        of the vehicle's links (the configured remotes and whoever talks to the vehicle)."""
        tg = self.cfg.target
        fields = follow_target_fields(self.agv.state(t), self.ms(t), tg.origin_lat_deg,
                                      tg.origin_lon_deg, tg.origin_alt_m)
        agv_link = self.links["agv"]
        targets: list[Address] = []
        for name in ("offboard", "gcs"):
            targets += [a for a in self.links[name].peers if a not in targets]
        if not targets:
            return
        msg = _FOLLOW_TARGET(*[fields[n] for n in _FOLLOW_TARGET_FIELDS])
        for a in targets:  # one encoding; each send packs it with the link's next sequence
            agv_link.send(msg, a)

    async def publish_frame(self, t: float) -> None:
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
            self.frame_line.push(cap.deliver_s, (seq, cap.stamp_us, image))
        await self.deliver_frames(t)

    async def deliver_frames(self, now_s: float) -> None:
        for seq, stamp_us, image in self.frame_line.pop_due(now_s):
            self.newest_stamp_ms = (stamp_us // 1000) & 0xFFFFFFFF
            self._frames_delivered += 1
            self.delivered_this_step += 1
            self.unanswered += 1
            if self._frame_server is not None:
                await self._frame_server.publish(seq, stamp_us, image)

    def _truth_record(self, t: float, seq: int, agv: AgvState, frame: RenderedFrame,
                      stamp_us: int, deliver_s: float | None) -> dict[str, Any]:
        s = self.state
        age = self.px4.setpoint_age_s(t)
        rec = truth_record(
            self.us(t), seq, s.pos_ned_m, s.vel_ned_m_s, s.q_wxyz, s.rates_frd_rad_s, agv,
            frame, disturbance_accel_ned_m_s2=s.disturbance_ned_m_s2, mode=self.px4.mode.label,
            armed=self.px4.armed, setpoint_age_s=age if math.isfinite(age) else None)
        rec["sim_t_s"] = t  # t_us is on the autopilot's clock (boot offset); this is sim time
        if not self._vehicle_ideal:
            rec["hover_thrust_true"] = self.model.true_hover_thrust(t)
        if not self.cfg.sim.camera_model.ideal:
            rec["frame_t_us"] = stamp_us
            rec["frame_dropped"] = deliver_s is None
            rec["frame_deliver_t_us"] = None if deliver_s is None else self.us(deliver_s)
            rec["brightness_gain"] = self.sensor.gain
        return rec

    # ------------------------------------------------------------------ stepping
    def advance(self, t_target: float) -> None:
        """Integrate the physics from ``state.t_s`` to ``t_target`` in whole physics steps,
        running the commander logic at the start of each step."""
        dt = self.model.dt_s
        n = math.floor((t_target - self.state.t_s) / dt + 1e-9)
        if n <= 0:
            return
        self.px4.update(self.state.t_s, self.state)
        self.note_changes(self.state.t_s)
        # PX4's own modes fly with its converged hover-thrust estimate (MPC_USE_HTE)
        self.px4.hover_thrust_estimate = self.model.true_hover_thrust(self.state.t_s)
        self.attitude_target = self.px4.attitude_command()
        self.state = self.model.step(self.state, self.attitude_target, n * dt)
        self.px4.update(self.state.t_s, self.state)
        self.note_changes(self.state.t_s)

    async def run(self, duration_s: float | None = None) -> BridgeStats:
        """Run for ``duration_s`` of boot time (default: ``sim.duration_s``)."""
        d = self.cfg.sim.duration_s if duration_s is None else duration_s
        if self.lockstep:
            await run_lockstep(self, d)
        else:
            await run_realtime(self, d)
        self._log_link_faults()
        return self.stats()

    def _log_link_faults(self) -> None:
        """What the impairment did and what signing rejected, per link (end of run)."""
        for name, ml in self.links.items():
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

    def stats(self) -> BridgeStats:
        sv = self.services
        return BridgeStats(
            t_s=self.t_s, steps=self.steps, lockstep_timeouts=self.timeouts,
            setpoints_received=sv.setpoints, setpoints_ignored=self.px4.ignored_setpoints,
            commands=sv.commands, acks_sent=sv.acks, frames=self._frame_seq,
            offboard=self.links["offboard"].counters, gcs=self.links["gcs"].counters,
            frames_dropped=self._frames_dropped, frames_delivered=self._frames_delivered,
            timesync_replies=sv.timesync_replies,
            timesync_offset_us=sv.timesync_offset_us, timesync_rtt_us=sv.timesync_rtt_us)


def stats_dict(stats: BridgeStats) -> dict[str, Any]:
    return dataclasses.asdict(stats)
