"""The vehicle's MAVLink telemetry: each streamed or requested message encoded from the state
the emulator flies (PX4's stream definitions, docs/reference/wire.md), with the sensor noise and
injected
faults of ``[sim.telemetry]`` and ``[sim.faults]``, sent through the transport delay."""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np
from pymavlink.dialects.v20 import common as mavlink2

from sim_bridge import SimBridgeError, mavpack
from sim_bridge.delay import rngs
from sim_bridge.follow_target import latlon_from_ned
from sim_bridge.link import Address, MavUdpLink
from sim_bridge.physics.vehicle import G_M_S2, VehicleState, quat_from_euler
from sim_bridge.px4.streams import (
    ATTITUDE,
    ATTITUDE_QUATERNION,
    ATTITUDE_TARGET,
    AUTOPILOT_VERSION,
    CAPABILITIES,
    EXTENDED_SYS_STATE,
    FLIGHT_SW_VERSION,
    GLOBAL_POSITION_INT,
    HEARTBEAT,
    HIGHRES_IMU,
    HOME_POSITION,
    LOCAL_POSITION_NED,
    STATE_STREAMS,
    SYS_STATUS,
    SYSTEM_TIME,
    TIMESYNC,
    Streams,
)

if TYPE_CHECKING:
    from sim_bridge.app import SimBridge

# the streamed messages' encoders, by id: pymavlink's ``*_encode`` arguments, the payload
# packed at once (no pymavlink message object; the same bytes, tests/sim/test_mavpack.py)
_ENC: dict[int, Callable[..., mavpack.Encoded]] = {
    cls.id: mavpack.encoder(cls) for cls in (
        mavlink2.MAVLink_heartbeat_message, mavlink2.MAVLink_sys_status_message,
        mavlink2.MAVLink_attitude_quaternion_message, mavlink2.MAVLink_attitude_message,
        mavlink2.MAVLink_attitude_target_message, mavlink2.MAVLink_highres_imu_message,
        mavlink2.MAVLink_local_position_ned_message,
        mavlink2.MAVLink_global_position_int_message,
        mavlink2.MAVLink_extended_sys_state_message, mavlink2.MAVLink_timesync_message,
        mavlink2.MAVLink_system_time_message, mavlink2.MAVLink_home_position_message,
        mavlink2.MAVLink_autopilot_version_message)}


def _floats(x: Any) -> list[float]:
    """``x``'s elements as Python floats (``float()`` of each), in one ``tolist``."""
    out: list[float] = np.asarray(x, dtype=float).reshape(-1).tolist()
    return out


def specific_force_frd(s: VehicleState) -> np.ndarray:
    """What an ideal accelerometer reads (m/s^2, body FRD): the vehicle's acceleration
    less gravity, i.e. thrust, drag, wind and turbulence (``R' (a - g e_z)``); ``-g``
    along z in a level hover or at rest on the ground."""
    f_ned = np.asarray(s.acc_ned_m_s2, dtype=float) - np.array([0.0, 0.0, G_M_S2])
    out: np.ndarray = s.rot_body_to_ned.T @ f_ned
    return out


class Telemetry:
    """The streams of every vehicle link (:attr:`streams`, by link name) and the encoding of
    each message from ``sim``'s state, autopilot and clocks."""

    def __init__(self, sim: SimBridge) -> None:
        self.sim = sim
        seed, tm = sim.cfg.sim.seed, sim.cfg.sim.telemetry
        self.streams: dict[str, Streams] = {}
        # HIGHRES_IMU: its own generators (accelerometer noise, transport jitter), so that the
        # other messages draw the same jitter with or without it
        self._imu_rng, self._imu_tx_rng = rngs(seed, 2, salt=5)
        self._accel_noise = tm.accel_noise_m_s2
        self._accel_bias = np.asarray(tm.accel_bias_m_s2, dtype=float)
        # LOCAL_POSITION_NED's velocity noise: its own generator too
        (self._vel_rng,) = rngs(seed, 1, salt=7)
        self._vel_noise = tm.velocity_noise_m_s
        #: our TIMESYNC requests' ``ts1`` (ns) -> the simulation time they were sent
        self.timesync_sent_ns: dict[int, float] = {}
        # messages whose encoding draws no random numbers and changes nothing (TIMESYNC
        # records its stamp): one encoding serves every link at the same time
        noisy = set()
        # whether HIGHRES_IMU draws noise or adds a bias (np.any once, not ~7 us a message)
        self._imu_noisy = self._accel_noise > 0 or bool(np.any(self._accel_bias))
        if self._imu_noisy:
            noisy.add(HIGHRES_IMU)
        if self._vel_noise > 0:
            noisy.add(LOCAL_POSITION_NED)
        self._shareable = frozenset({
            HEARTBEAT, SYS_STATUS, ATTITUDE_QUATERNION, ATTITUDE, ATTITUDE_TARGET, HIGHRES_IMU,
            LOCAL_POSITION_NED, GLOBAL_POSITION_INT, EXTENDED_SYS_STATE, SYSTEM_TIME,
            HOME_POSITION, AUTOPILOT_VERSION} - noisy)

    def ned_to_global(self, pos: np.ndarray) -> tuple[float, float, float]:
        tg = self.sim.cfg.target
        return latlon_from_ned(pos, tg.origin_lat_deg, tg.origin_lon_deg, tg.origin_alt_m)

    def encode(self, link: MavUdpLink, mid: int, t: float) -> Any:
        s, px4, ms = self.sim.state, self.sim.px4, self.sim.ms(t)
        if mid == HEARTBEAT:
            return _ENC[HEARTBEAT](2, 12, px4.base_mode, px4.custom_mode,
                                        px4.system_status, 3)
        if mid == SYS_STATUS:
            sensors = 1 | 2 | 4 | 8 | 32 | 0x8000 | 0x200000 | 0x2000000
            return _ENC[SYS_STATUS](sensors, sensors, sensors, 100, 16000, -1, 100,
                                         0, 0, 0, 0, 0, 0)
        if mid == ATTITUDE_QUATERNION:
            q, w = s.q_wxyz, s.rates_frd_rad_s
            return _ENC[ATTITUDE_QUATERNION](ms, *_floats(q), *_floats(w))
        if mid == ATTITUDE:
            w = s.rates_frd_rad_s
            return _ENC[ATTITUDE](ms, s.roll_rad, s.pitch_rad, s.yaw_rad, *_floats(w))
        if mid == ATTITUDE_TARGET:  # PX4 streams/ATTITUDE_TARGET.hpp: the attitude setpoint
            cmd = self.sim.attitude_target or px4.attitude_command()
            q = quat_from_euler(cmd.roll_rad, cmd.pitch_rad, cmd.yaw_rad)
            rates = cmd.body_rates_frd_rad_s or (0.0, 0.0, cmd.yaw_rate_ff_rad_s)
            return _ENC[ATTITUDE_TARGET](ms, 0, [float(v) for v in q],
                                              *(float(v) for v in rates),
                                              float(cmd.thrust_norm))
        if mid == HIGHRES_IMU:  # PX4 streams/HIGHRES_IMU.hpp (docs/reference/wire.md, HIGHRES_IMU)
            f = specific_force_frd(s)
            if self._imu_noisy:
                f = f + self._accel_bias + self._accel_noise * self._imu_rng.standard_normal(3)
            w = s.rates_frd_rad_s
            return _ENC[HIGHRES_IMU](self.sim.us(t), *_floats(f), *_floats(w), 0.0, 0.0,
                                          0.0, 0.0, 0.0, 0.0, 0.0, 0b111111)
        if mid == LOCAL_POSITION_NED:
            vel = s.vel_ned_m_s
            if self._vel_noise > 0:
                vel = vel + self._vel_noise * self._vel_rng.standard_normal(3)
            return _ENC[LOCAL_POSITION_NED](ms, *_floats(s.pos_ned_m), *_floats(vel))
        if mid == GLOBAL_POSITION_INT:
            lat, lon, alt = self.ned_to_global(s.pos_ned_m)
            rel = float(px4.home_ned_m[2] - s.pos_ned_m[2])
            v = s.vel_ned_m_s * 100
            hdg = round(math.degrees(s.yaw_rad) % 360 * 100) % 36000
            return _ENC[GLOBAL_POSITION_INT](ms, int(lat * 1e7), int(lon * 1e7),
                                                  int(alt * 1000), int(rel * 1000),
                                                  int(v[0]), int(v[1]), int(v[2]), hdg)
        if mid == EXTENDED_SYS_STATE:
            return _ENC[EXTENDED_SYS_STATE](0, px4.landed_state)
        if mid == TIMESYNC:  # PX4's own request (streams/TIMESYNC.hpp): tc1 = 0, ts1 = now ns
            ts1 = round(self.sim.boot_s(t) * 1e9)
            self.timesync_sent_ns[ts1] = t
            if len(self.timesync_sent_ns) > 64:
                self.timesync_sent_ns.pop(next(iter(self.timesync_sent_ns)))
            return _ENC[TIMESYNC](0, ts1)
        if mid == SYSTEM_TIME:
            return _ENC[SYSTEM_TIME](round((self.sim.unix_t0_s + t) * 1e6), ms)
        if mid == HOME_POSITION:
            h = px4.home_ned_m
            lat, lon, alt = self.ned_to_global(h)
            return _ENC[HOME_POSITION](int(lat * 1e7), int(lon * 1e7), int(alt * 1000),
                                            float(h[0]), float(h[1]), float(h[2]),
                                            [1.0, 0.0, 0.0, 0.0], 0.0, 0.0, 0.0,
                                            self.sim.us(t))
        if mid == AUTOPILOT_VERSION:
            return _ENC[AUTOPILOT_VERSION](CAPABILITIES, FLIGHT_SW_VERSION, 0, 0, 0,
                                                [0] * 8, [0] * 8, [0] * 8, 0x26AC, 0x11,
                                                0x5EB1D6E0)
        raise SimBridgeError(f"no encoder for message {mid}")  # pragma: no cover

    def send_message(self, link: MavUdpLink, mid: int, t: float,
                     addr: Address | None = None, *, reply: bool = False) -> None:
        self.sim.transport.tx(link, self.encode(link, mid, t), addr, reply=reply,
                              rng=self._imu_tx_rng if mid == HIGHRES_IMU else None)

    def send_streams(self, t: float) -> None:
        """Send every stream message due at ``t`` on every link. A message due on both links
        is encoded once when its encoding draws no noise and has no side effect (the links
        pack it each with their own sequence number): the same fields either way."""
        faults = self.sim.cfg.sim.faults
        dropout, nan = faults.dropout(t), faults.nan(t)  # of t only: once a step
        encoded: dict[int, Any] = {}
        for name, streams in self.streams.items():
            link = self.sim.links[name]
            for mid in streams.due(t):
                if dropout and mid in STATE_STREAMS:
                    continue  # injected telemetry dropout
                if nan and mid in STATE_STREAMS:
                    self.sim.transport.tx(link, self.encode_nan(link, mid, t),
                                          rng=self._imu_tx_rng if mid == HIGHRES_IMU else None)
                    continue
                msg = encoded.get(mid)
                if msg is None:
                    msg = self.encode(link, mid, t)
                    if mid in self._shareable:
                        encoded[mid] = msg
                self.sim.transport.tx(link, msg,
                                      rng=self._imu_tx_rng if mid == HIGHRES_IMU else None)

    def encode_nan(self, link: MavUdpLink, mid: int, t: float) -> Any:
        """The state message ``mid`` with NaN attitude/velocity (injected fault)."""
        nan, ms = float("nan"), self.sim.ms(t)
        if mid == ATTITUDE_QUATERNION:
            return _ENC[ATTITUDE_QUATERNION](ms, nan, nan, nan, nan, nan, nan, nan)
        if mid == ATTITUDE:
            return _ENC[ATTITUDE](ms, nan, nan, nan, nan, nan, nan)
        if mid == HIGHRES_IMU:
            return _ENC[HIGHRES_IMU](self.sim.us(t), nan, nan, nan, nan, nan, nan, 0.0, 0.0,
                                          0.0, 0.0, 0.0, 0.0, 0.0, 0b111111)
        p = self.sim.state.pos_ned_m
        return _ENC[LOCAL_POSITION_NED](ms, float(p[0]), float(p[1]), float(p[2]),
                                             nan, nan, nan)
