"""Emulator configuration: ``[sim]``, ``[camera]`` and ``[target]`` of a scenario TOML file,
loaded once into validated, frozen dataclasses.

The emulator parses the file itself (it shares no code with the companion). A file may start
with ``base = "other.toml"`` (relative to itself): the base is loaded first, then this file's
tables and keys override it (deep merge; tables merge key by key, every other value replaces).
A bad value raises :class:`sim_bridge.ConfigError` naming the key (``sim.vehicle.hover_thrust:
must be in (0, 1)``). The scenario (initial UAV pose) is picked by name from
``[sim.scenarios.<name>]``.
"""

from __future__ import annotations

import dataclasses
import math
import tomllib
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from sim_bridge import ConfigError
from sim_bridge.impairment import ImpairmentParams

DEFAULT_CONFIG = Path(__file__).resolve().parent.parent / "config" / "paper.toml"

Check = Callable[[Any], str | None]


def _positive(x: float) -> str | None:
    return None if x > 0 else "must be > 0"


def _nonneg(x: float) -> str | None:
    return None if x >= 0 else "must be >= 0"


def _open_unit(x: float) -> str | None:
    return None if 0 < x < 1 else "must be in (0, 1)"


def _unit(x: float) -> str | None:
    return None if 0 < x <= 1 else "must be in (0, 1]"


def _port(x: int) -> str | None:
    return None if 0 <= x <= 65535 else "must be a port number in 0..65535 (0 = any free port)"


def _sysid(x: int) -> str | None:
    return None if 1 <= x <= 255 else "must be in 1..255"


def _one_of(*choices: Any) -> Check:
    def check(x: Any) -> str | None:
        return None if x in choices else f"must be one of {', '.join(map(repr, choices))}"

    return check


def _address(x: str) -> str | None:
    try:
        parse_address(x)
    except ValueError as e:
        return str(e)
    return None


def _c(fn: Check) -> dict[str, Any]:
    return {"check": fn}


def parse_address(text: str) -> tuple[str, int]:
    """``"HOST:PORT"`` -> ``(host, port)``; raises ``ValueError`` on anything else."""
    host, sep, port_s = text.rpartition(":")
    if not sep or not host:
        raise ValueError(f"must be 'HOST:PORT', got {text!r}")
    try:
        port = int(port_s)
    except ValueError:
        raise ValueError(f"port of {text!r} is not an integer") from None
    if not 1 <= port <= 65535:
        raise ValueError(f"port of {text!r} must be in 1..65535")
    return host, port


# --------------------------------------------------------------------------------------------
# [camera] and [target]: the physical camera and target the emulator renders
@dataclass(frozen=True)
class CameraConfig:
    """Pinhole camera and its mount in the body frame (FRD); camera axes = body axes rotated
    by ``mount_rpy_rad`` (ZYX)."""

    focal_length_m: float = field(metadata=_c(_positive))
    pixel_size_m: float = field(metadata=_c(_positive))
    width_px: int = field(metadata=_c(_positive))
    height_px: int = field(metadata=_c(_positive))
    visible_fraction: float = field(metadata=_c(_unit))
    report_pixel_size_m: float = field(metadata=_c(_positive))
    mount_offset_m: tuple[float, float, float]
    mount_rpy_rad: tuple[float, float, float]
    calibration_file: str = ""


@dataclass(frozen=True)
class TargetConfig:
    """The AGV's top (a rectangle or an ArUco marker) and its MAVLink identity."""

    length_m: float = field(metadata=_c(_positive))
    width_m: float = field(metadata=_c(_positive))
    height_m: float = field(metadata=_c(_nonneg))
    pattern: str = field(metadata=_c(_one_of("rectangle", "aruco")))
    aruco_dictionary: str
    aruco_id: int = field(metadata=_c(_nonneg))
    aruco_size_m: float = field(metadata=_c(_positive))
    mavlink_sysid: int = field(metadata=_c(_sysid))
    mavlink_compid: int = field(metadata=_c(_sysid))
    origin_lat_deg: float
    origin_lon_deg: float
    origin_alt_m: float


# --------------------------------------------------------------------------------------------
# [sim.*]
# Named levels of the vehicle's own imperfections ([sim.vehicle], [sim.battery],
# [sim.disturbance]); explicit keys win over the level (docs/reference/emulator.md).
VEHICLE_LEVELS: dict[str, dict[str, Any]] = {
    "ideal": {},
    "mild": {"hover_thrust_error": 0.05, "mass_error": 0.02, "drag_error": 0.5,
             "motor_curve_factor": 0.1},
    "realistic": {"hover_thrust_error": 0.1, "mass_error": 0.05, "drag_error": 1.0,
                  "motor_curve_factor": 0.3},
    "harsh": {"hover_thrust_error": 0.3, "mass_error": 0.1, "drag_error": 2.0,
              "motor_curve_factor": 0.5},
}
BATTERY_LEVELS: dict[str, dict[str, Any]] = {
    "ideal": {},
    "mild": {"thrust_loss_per_min": 0.008, "max_thrust_loss": 0.15},
    "realistic": {"thrust_loss_per_min": 0.015, "max_thrust_loss": 0.25},
    "harsh": {"thrust_loss_per_min": 0.04, "max_thrust_loss": 0.3},
}
DISTURBANCE_LEVELS: dict[str, dict[str, Any]] = {
    "ideal": {},
    "mild": {"turbulence_std_m_s2": 0.02, "turbulence_tau_s": 2.0},
    "realistic": {"turbulence_std_m_s2": 0.05, "turbulence_tau_s": 2.0},
    "harsh": {"turbulence_std_m_s2": 0.15, "turbulence_tau_s": 1.0},
}


@dataclass(frozen=True)
class VehicleConfig:
    """Quadrotor model: ``attitude_model = "first-order"`` (``sim_bridge.physics.vehicle``) or
    ``"px4"`` (PX4's cascade on a rigid body, ``sim_bridge.physics.rigid_body``, gains in
    ``[sim.px4_control]``).

    ``hover_thrust`` is PX4's ``MPC_THR_HOVER`` parameter (what the autopilot believes and the
    parameter a ground station reads). The vehicle itself may differ: ``true_hover_thrust`` (0:
    ``hover_thrust (1 + hover_thrust_error)``) hovers it at full battery; ``mass_error``
    (payload, relative: raises the true hover thrust and the inertia), ``drag_error`` (true
    drag = ``drag_per_s (1 + drag_error)``), ``motor_curve_factor`` (the motors' true thrust
    curve, px4 model only; PX4 assumes ``thr_mdl_fac``). ``level`` presets them.
    """

    hover_thrust: float = field(metadata=_c(_open_unit))
    attitude_tau_s: float = field(metadata=_c(_positive))
    max_tilt_rate_rad_s: float = field(metadata=_c(_positive))
    max_yaw_rate_rad_s: float = field(metadata=_c(_positive))
    drag_per_s: float = field(metadata=_c(_nonneg))
    max_tilt_rad: float = field(metadata=_c(lambda x: None if 0 < x < math.pi / 2 else
                                            "must be in (0, pi/2)"))
    attitude_model: str = field(default="first-order",
                                metadata=_c(_one_of("first-order", "px4")))
    level: str = field(default="ideal", metadata=_c(_one_of(*VEHICLE_LEVELS)))
    true_hover_thrust: float = field(default=0.0, metadata=_c(
        lambda x: None if 0 <= x < 1 else "must be in (0, 1), or 0 (derived)"))
    hover_thrust_error: float = field(default=0.0, metadata=_c(
        lambda x: None if -0.5 < x < 1 else "must be in (-0.5, 1)"))
    mass_error: float = field(default=0.0, metadata=_c(
        lambda x: None if -0.5 < x < 1 else "must be in (-0.5, 1)"))
    drag_error: float = field(default=0.0, metadata=_c(
        lambda x: None if x >= -1 else "must be >= -1"))
    motor_curve_factor: float = field(default=0.0, metadata=_c(
        lambda x: None if 0 <= x <= 1 else "must be in [0, 1]"))

    def __post_init__(self) -> None:
        if self.true_hover_thrust_full_battery * (1 + self.mass_error) >= 0.95:
            raise ConfigError("sim.vehicle.true_hover_thrust: the true hover thrust "
                              "(with hover_thrust_error and mass_error) must stay below 0.95")

    @property
    def true_hover_thrust_full_battery(self) -> float:
        """Collective thrust that hovers the nominal vehicle (no payload) at full battery."""
        if self.true_hover_thrust > 0:
            return self.true_hover_thrust
        return self.hover_thrust * (1.0 + self.hover_thrust_error)

    @property
    def true_drag_per_s(self) -> float:
        return self.drag_per_s * (1.0 + self.drag_error)


@dataclass(frozen=True)
class BatteryConfig:
    """Battery sag: the maximum thrust falls by ``thrust_loss_per_min`` (fraction per minute of
    simulated time) down to ``1 - max_thrust_loss``, so the true hover thrust rises during the
    flight (PX4's ``MC_BAT_SCALE_EN`` is off by default)."""

    level: str = field(default="ideal", metadata=_c(_one_of(*BATTERY_LEVELS)))
    thrust_loss_per_min: float = field(default=0.0, metadata=_c(_nonneg))
    max_thrust_loss: float = field(default=0.0, metadata=_c(
        lambda x: None if 0 <= x <= 0.5 else "must be in [0, 0.5]"))


def _deg_s(x: float) -> str | None:
    return None if 0 < x <= 1800 else "must be in (0, 1800] deg/s"


@dataclass(frozen=True)
class Px4ControlConfig:
    """PX4's attitude and rate controller parameters (names after PX4's, lower case; defaults
    are PX4's, docs/reference/emulator.md) and the airframe the ``px4`` model flies."""

    mc_roll_p: float = field(default=6.5, metadata=_c(_nonneg))
    mc_pitch_p: float = field(default=6.5, metadata=_c(_nonneg))
    mc_yaw_p: float = field(default=2.8, metadata=_c(_nonneg))
    mc_yaw_weight: float = field(default=0.4, metadata=_c(
        lambda x: None if 0 <= x <= 1 else "must be in [0, 1]"))
    mc_rollrate_max_deg_s: float = field(default=220.0, metadata=_c(_deg_s))
    mc_pitchrate_max_deg_s: float = field(default=220.0, metadata=_c(_deg_s))
    mc_yawrate_max_deg_s: float = field(default=200.0, metadata=_c(_deg_s))
    mc_rollrate_p: float = field(default=0.15, metadata=_c(_nonneg))
    mc_rollrate_i: float = field(default=0.2, metadata=_c(_nonneg))
    mc_rollrate_d: float = field(default=0.003, metadata=_c(_nonneg))
    mc_rollrate_ff: float = field(default=0.0, metadata=_c(_nonneg))
    mc_rollrate_k: float = field(default=1.0, metadata=_c(_positive))
    mc_rr_int_lim: float = field(default=0.3, metadata=_c(_nonneg))
    mc_pitchrate_p: float = field(default=0.15, metadata=_c(_nonneg))
    mc_pitchrate_i: float = field(default=0.2, metadata=_c(_nonneg))
    mc_pitchrate_d: float = field(default=0.003, metadata=_c(_nonneg))
    mc_pitchrate_ff: float = field(default=0.0, metadata=_c(_nonneg))
    mc_pitchrate_k: float = field(default=1.0, metadata=_c(_positive))
    mc_pr_int_lim: float = field(default=0.3, metadata=_c(_nonneg))
    mc_yawrate_p: float = field(default=0.2, metadata=_c(_nonneg))
    mc_yawrate_i: float = field(default=0.1, metadata=_c(_nonneg))
    mc_yawrate_d: float = field(default=0.0, metadata=_c(_nonneg))
    mc_yawrate_ff: float = field(default=0.0, metadata=_c(_nonneg))
    mc_yawrate_k: float = field(default=1.0, metadata=_c(_positive))
    mc_yr_int_lim: float = field(default=0.3, metadata=_c(_nonneg))
    thr_mdl_fac: float = field(default=0.0, metadata=_c(
        lambda x: None if 0 <= x <= 1 else "must be in [0, 1]"))
    imu_dgyro_cutoff_hz: float = field(default=30.0, metadata=_c(_nonneg))
    # the airframe (x500-like quad X)
    mass_kg: float = field(default=2.0, metadata=_c(_positive))
    inertia_kg_m2: tuple[float, float, float] = field(default=(0.0217, 0.0217, 0.04), metadata=_c(
        lambda x: None if all(v > 0 for v in x) else "every entry must be > 0"))
    arm_xy_m: float = field(default=0.174, metadata=_c(_positive))
    km_m: float = field(default=0.05, metadata=_c(_nonneg))
    motor_tau_s: float = field(default=0.02, metadata=_c(_positive))


@dataclass(frozen=True)
class DisturbanceConfig:
    """Additive acceleration disturbance (the wind's effect on the vehicle): constant wind +
    sinusoidal gust + seeded bounded random + seeded turbulence (first-order Gauss-Markov,
    stationary std ``turbulence_std_m_s2`` horizontally and half of it vertically, correlation
    time ``turbulence_tau_s``). ``level`` presets the turbulence."""

    wind_accel_ned_m_s2: tuple[float, float, float]
    gust_amplitude_m_s2: float = field(metadata=_c(_nonneg))
    gust_period_s: float = field(metadata=_c(_positive))
    random_bound_m_s2: float = field(metadata=_c(_nonneg))
    level: str = field(default="ideal", metadata=_c(_one_of(*DISTURBANCE_LEVELS)))
    turbulence_std_m_s2: float = field(default=0.0, metadata=_c(_nonneg))
    turbulence_tau_s: float = field(default=2.0, metadata=_c(_positive))


@dataclass(frozen=True)
class Px4Config:
    """The PX4 parameters the emulator imitates (names after PX4's)."""

    com_of_loss_t_s: float = field(metadata=_c(_positive))
    com_obl_rc_act: int = field(metadata=_c(_one_of(0, 1, 2, 3, 4, 5, 6, 7)))
    com_disarm_prflt_s: float = field(metadata=_c(_nonneg))


@dataclass(frozen=True)
class LinkConfig:
    """Sockets (docs/reference/wire.md). Local ports may be 0 (any free port; the app logs the real
    one)."""

    sysid: int = field(metadata=_c(_sysid))
    compid: int = field(metadata=_c(_sysid))
    offboard_local_port: int = field(metadata=_c(_port))
    offboard_remote: str = field(metadata=_c(_address))
    gcs_local_port: int = field(metadata=_c(_port))
    gcs_remote: str = field(metadata=_c(_address))
    agv_local_port: int = field(metadata=_c(_port))
    frame_port: int = field(metadata=_c(_port))
    truth_remote: str = field(metadata=_c(_address))


@dataclass(frozen=True)
class AgvConfig:
    trajectory: str = field(metadata=_c(_one_of("paper", "line", "circle", "figure8",
                                                  "stop_and_go")))
    speed_scale: float = field(metadata=_c(_nonneg))
    rate_hz: float = field(metadata=_c(_positive))
    top_z_m: float


@dataclass(frozen=True)
class SimCameraConfig:
    rate_hz: float = field(metadata=_c(_positive))
    noise_std: float = field(metadata=_c(_nonneg))
    blur_px: float = field(metadata=_c(_nonneg))
    occlusions: tuple[tuple[float, float], ...] = ()

    def occluded(self, t_s: float) -> bool:
        """Whether the target is hidden at ``t_s`` (s since boot)."""
        return any(a <= t_s < b for a, b in self.occlusions)


@dataclass(frozen=True)
class FaultsConfig:
    """Failure injection for testing a client's safety logic (like PX4's failure injection).

    Windows ``[t_start_s, t_end_s)`` in seconds since boot: ``telemetry_dropouts``: attitude
    and local-position streams (ATTITUDE_QUATERNION, ATTITUDE, LOCAL_POSITION_NED) are not
    sent; ``telemetry_nan``: those messages carry NaN in place of the attitude and velocity.
    """

    telemetry_dropouts: tuple[tuple[float, float], ...] = ()
    telemetry_nan: tuple[tuple[float, float], ...] = ()

    def dropout(self, t_s: float) -> bool:
        return any(a <= t_s < b for a, b in self.telemetry_dropouts)

    def nan(self, t_s: float) -> bool:
        return any(a <= t_s < b for a, b in self.telemetry_nan)


LINK_NAMES = ("offboard", "gcs", "agv")


def _links(x: tuple[str, ...]) -> str | None:
    bad = [n for n in x if n not in LINK_NAMES]
    return f"unknown link(s) {', '.join(map(repr, bad))} (have: {', '.join(LINK_NAMES)})" \
        if bad else None


@dataclass(frozen=True)
class ImpairmentConfig:
    """Network impairment of the emulator's MAVLink links (``sim_bridge.impairment``).

    ``links``: which links are impaired (``"offboard"``, ``"gcs"``, ``"agv"``); ``cuts``: windows
    ``[t_start_s, t_end_s)`` of boot time in which nothing passes either way;
    ``heartbeat_stop_s``: from then on the vehicle sends no HEARTBEAT on those links (< 0:
    never). The two directions are the sub-tables ``vehicle_to_companion`` and
    ``companion_to_vehicle`` (:class:`ImpairmentParams`). Times count in simulated time in
    lockstep.
    """

    links: tuple[str, ...] = field(default=("offboard",), metadata=_c(_links))
    seed: int = 1
    cuts: tuple[tuple[float, float], ...] = ()
    heartbeat_stop_s: float = -1.0
    vehicle_to_companion: ImpairmentParams = field(default_factory=ImpairmentParams)
    companion_to_vehicle: ImpairmentParams = field(default_factory=ImpairmentParams)

    @property
    def active(self) -> bool:
        return bool(self.links) and (
            bool(self.cuts) or self.heartbeat_stop_s >= 0
            or self.vehicle_to_companion.active or self.companion_to_vehicle.active)


def _hex_key(x: str) -> str | None:
    if x == "":
        return None
    try:
        key = bytes.fromhex(x)
    except ValueError:
        return "must be hexadecimal"
    return None if len(key) == 32 else f"must be 32 bytes (64 hex digits), got {len(key)}"


@dataclass(frozen=True)
class SigningConfig:
    """MAVLink 2 message signing like PX4 with a provisioned key (``sim_bridge.signing``).

    Off by default (MAVSDK has no signing). ``key_hex`` (64 hex digits) or ``key_file`` (64
    hex digits as text, or the 32 raw bytes, optionally followed by PX4's 8-byte timestamp;
    a relative path is relative to the config file). ``links``: where outgoing frames are
    signed and incoming ones verified (``"agv"``: the AGV node signs its FOLLOW_TARGET).
    """

    enabled: bool = False
    key_hex: str = field(default="", metadata=_c(_hex_key))
    key_file: str = ""
    links: tuple[str, ...] = field(default=LINK_NAMES, metadata=_c(_links))

    def __post_init__(self) -> None:
        if self.key_hex and self.key_file:
            raise ConfigError("sim.signing: give key_hex or key_file, not both")
        if self.enabled and not (self.key_hex or self.key_file):
            raise ConfigError("sim.signing.key_hex: a 32-byte key (or key_file) is needed "
                              "when signing is enabled")

    def key(self) -> bytes:
        """The 32-byte secret key (reads ``key_file``); raises ConfigError."""
        if self.key_hex:
            return bytes.fromhex(self.key_hex)
        p = Path(self.key_file).expanduser()
        try:
            raw = p.read_bytes()
        except OSError as e:
            raise ConfigError(f"sim.signing.key_file: cannot read {p} ({e.strerror})") from e
        text = raw.strip()
        if len(text) == 64:
            try:
                return bytes.fromhex(text.decode("ascii"))
            except (UnicodeDecodeError, ValueError):
                pass
        if len(raw) in (32, 40):  # raw key, or PX4's key + little-endian u64 timestamp
            return raw[:32]
        raise ConfigError(f"sim.signing.key_file: {p} holds neither 64 hex digits nor a "
                          "32-byte key")


# Named levels of [sim.camera_model] and [sim.telemetry]: every knob of the level's preset can
# be overridden by a key of the table (explicit keys win over the level).
CAMERA_LEVELS: dict[str, dict[str, Any]] = {
    "ideal": {},
    "mild": {"latency_ms": 30.0, "latency_jitter_ms": 5.0, "drop_probability": 0.01,
             "exposure_ms": 4.0, "read_noise_std_dn": 1.0, "shot_noise_dn_per_e": 0.01,
             "brightness_drift_std": 0.03, "brightness_drift_tau_s": 10.0},
    "realistic": {"latency_ms": 60.0, "latency_jitter_ms": 15.0, "drop_probability": 0.03,
                  "exposure_ms": 8.0, "read_noise_std_dn": 2.0, "shot_noise_dn_per_e": 0.03,
                  "brightness_drift_std": 0.08, "brightness_drift_tau_s": 5.0},
    "harsh": {"latency_ms": 120.0, "latency_jitter_ms": 40.0, "drop_probability": 0.10,
              "exposure_ms": 16.0, "read_noise_std_dn": 4.0, "shot_noise_dn_per_e": 0.06,
              "brightness_drift_std": 0.2, "brightness_drift_tau_s": 3.0},
}
TELEMETRY_LEVELS: dict[str, dict[str, Any]] = {
    "ideal": {},
    "mild": {"rates": "px4", "delay_ms": 2.0, "delay_jitter_ms": 1.0, "boot_offset_s": 12.0,
             "accel_noise_m_s2": 0.15, "accel_bias_m_s2": [0.03, -0.02, 0.05]},
    "realistic": {"rates": "px4", "delay_ms": 4.0, "delay_jitter_ms": 2.0,
                  "boot_offset_s": 37.25, "accel_noise_m_s2": 0.35,
                  "accel_bias_m_s2": [0.1, -0.08, 0.15]},
    "harsh": {"rates": "px4", "delay_ms": 20.0, "delay_jitter_ms": 15.0,
              "boot_offset_s": 1234.5, "accel_noise_m_s2": 1.0,
              "accel_bias_m_s2": [0.3, -0.25, 0.4]},
}


@dataclass(frozen=True)
class CameraModelConfig:
    """The camera's imperfections (``sim_bridge.camera_model``); all off = the ideal camera.

    ``latency_ms`` +- ``latency_jitter_ms`` (uniform): capture (exposure middle) to delivery on
    the frame socket, in order (a frame never overtakes the previous one); in lockstep the
    frame leaves at the first step at or after that time. ``drop_probability``: a captured
    frame is never delivered (its ``seq`` is skipped). ``exposure_ms``: motion blur along the
    target's image motion over the exposure. ``read_noise_std_dn`` (grey levels) and
    ``shot_noise_dn_per_e`` (conversion gain: shot-noise variance = gain x signal, DN^2).
    ``brightness_drift_std`` (relative, stationary std of the log gain) with time constant
    ``brightness_drift_tau_s``: auto-exposure/gain wandering. ``timestamp_clock``:
    ``"autopilot"`` (hardware-synced camera: header ``t_us`` = capture time on the autopilot's
    clock) or ``"camera"`` (its own clock: autopilot time + ``clock_offset_ms`` + drift).
    """

    level: str = field(default="ideal", metadata=_c(_one_of(*CAMERA_LEVELS)))
    latency_ms: float = field(default=0.0, metadata=_c(_nonneg))
    latency_jitter_ms: float = field(default=0.0, metadata=_c(_nonneg))
    drop_probability: float = field(default=0.0, metadata=_c(
        lambda x: None if 0 <= x < 1 else "must be in [0, 1)"))
    exposure_ms: float = field(default=0.0, metadata=_c(_nonneg))
    read_noise_std_dn: float = field(default=0.0, metadata=_c(_nonneg))
    shot_noise_dn_per_e: float = field(default=0.0, metadata=_c(_nonneg))
    brightness_drift_std: float = field(default=0.0, metadata=_c(_nonneg))
    brightness_drift_tau_s: float = field(default=5.0, metadata=_c(_positive))
    timestamp_clock: str = field(default="autopilot",
                                 metadata=_c(_one_of("autopilot", "camera")))
    clock_offset_ms: float = field(default=0.0, metadata=_c(_nonneg))
    clock_drift_ppm: float = field(default=0.0, metadata=_c(
        lambda x: None if abs(x) <= 1000 else "must be in [-1000, 1000]"))

    def __post_init__(self) -> None:
        if self.latency_jitter_ms > self.latency_ms:
            raise ConfigError("sim.camera_model.latency_jitter_ms: must be <= latency_ms")

    @property
    def ideal(self) -> bool:
        return self == CameraModelConfig(level=self.level)


@dataclass(frozen=True)
class TelemetryConfig:
    """How the autopilot's MAVLink output departs from the ideal (``docs/reference/wire.md``,
    Clocks).

    ``rates``: ``"emulator"`` (the emulator's historical stream rates) or ``"px4"`` (PX4's
    MAVLink "onboard" mode on the offboard link and "normal" mode on the GCS link, with its
    10 Hz TIMESYNC requests and 1 Hz SYSTEM_TIME). ``delay_ms`` +- ``delay_jitter_ms``
    (uniform, in order): autopilot -> client transport delay of every message on the vehicle's
    links (in lockstep at its due time in simulated time, inside the step: docs/reference/wire.md).
    ``boot_offset_s``: the autopilot booted this long before the simulation started: every
    autopilot stamp (``time_boot_ms``, ``time_usec``, TIMESYNC ``tc1``/``ts1``, the camera's
    ``t_us`` and the ground truth's ``t_us``) is simulation time + this offset.
    ``accel_noise_m_s2`` (white, std per axis and HIGHRES_IMU sample) and ``accel_bias_m_s2``
    (body FRD, constant): the accelerometer of HIGHRES_IMU departs from the true specific
    force by these (docs/reference/wire.md, HIGHRES_IMU). ``velocity_noise_m_s`` (white, std per
    axis and LOCAL_POSITION_NED sample; 0 at every level): the velocity estimate departs from the
    truth by this, as an EKF's does (a white model: EKF2's output is smoother, so this is the
    harsher case for a given std).
    """

    level: str = field(default="ideal", metadata=_c(_one_of(*TELEMETRY_LEVELS)))
    rates: str = field(default="emulator", metadata=_c(_one_of("emulator", "px4")))
    delay_ms: float = field(default=0.0, metadata=_c(_nonneg))
    delay_jitter_ms: float = field(default=0.0, metadata=_c(_nonneg))
    boot_offset_s: float = field(default=0.0, metadata=_c(
        lambda x: None if 0 <= x < 4e6 else "must be in [0, 4e6) (time_boot_ms is a u32)"))
    accel_noise_m_s2: float = field(default=0.0, metadata=_c(
        lambda x: None if 0 <= x <= 20 else "must be in [0, 20] m/s^2"))
    accel_bias_m_s2: tuple[float, float, float] = field(default=(0.0, 0.0, 0.0), metadata=_c(
        lambda x: None if len(x) == 3 and all(abs(v) <= 5 for v in x)
        else "must be 3 values within +-5 m/s^2"))
    velocity_noise_m_s: float = field(default=0.0, metadata=_c(
        lambda x: None if 0 <= x <= 5 else "must be in [0, 5] m/s"))

    def __post_init__(self) -> None:
        if self.delay_jitter_ms > self.delay_ms:
            raise ConfigError("sim.telemetry.delay_jitter_ms: must be <= delay_ms")


@dataclass(frozen=True)
class ScenarioConfig:
    """Initial UAV pose: position (m, NED) and roll, pitch, yaw (rad, ZYX)."""

    name: str
    uav_pose: tuple[float, float, float, float, float, float]


@dataclass(frozen=True)
class SimConfig:
    time_mode: str = field(metadata=_c(_one_of("realtime", "lockstep")))
    lockstep_timeout_s: float = field(metadata=_c(_positive))
    physics_dt_s: float = field(metadata=_c(_positive))
    step_dt_s: float = field(metadata=_c(_positive))
    seed: int
    start: str = field(metadata=_c(_one_of("airborne", "ground")))
    scenario: str
    duration_s: float = field(metadata=_c(_positive))
    vehicle: VehicleConfig
    disturbance: DisturbanceConfig
    px4: Px4Config
    link: LinkConfig
    agv: AgvConfig
    camera: SimCameraConfig
    faults: FaultsConfig = field(default_factory=FaultsConfig)
    impairment: ImpairmentConfig = field(default_factory=ImpairmentConfig)
    signing: SigningConfig = field(default_factory=SigningConfig)
    camera_model: CameraModelConfig = field(default_factory=CameraModelConfig)
    telemetry: TelemetryConfig = field(default_factory=TelemetryConfig)
    battery: BatteryConfig = field(default_factory=BatteryConfig)
    px4_control: Px4ControlConfig = field(default_factory=Px4ControlConfig)

    def __post_init__(self) -> None:
        if self.physics_dt_s > self.step_dt_s:
            raise ConfigError("sim.physics_dt_s: must be <= sim.step_dt_s")


@dataclass(frozen=True)
class EmulatorConfig:
    """Everything the emulator reads: ``[sim]``, ``[camera]``, ``[target]`` and the chosen
    ``[sim.scenarios.<name>]``."""

    sim: SimConfig
    camera: CameraConfig
    target: TargetConfig
    scenario: ScenarioConfig
    source: str = ""

    @property
    def ground_z_m(self) -> float:
        """NED z of the ground: the AGV top (``sim.agv.top_z_m``) is ``target.height_m`` above
        it."""
        return self.sim.agv.top_z_m + self.target.height_m


# --------------------------------------------------------------------------------------------
# Loading
def deep_merge(base: Mapping[str, Any], over: Mapping[str, Any]) -> dict[str, Any]:
    """Tables merge key by key (recursively); any other value in ``over`` replaces."""
    out: dict[str, Any] = dict(base)
    for k, v in over.items():
        if isinstance(v, Mapping) and isinstance(out.get(k), Mapping):
            out[k] = deep_merge(out[k], v)
        else:
            out[k] = v
    return out


def read_toml(path: str | Path, _seen: tuple[Path, ...] = ()) -> dict[str, Any]:
    """Read a TOML file, resolving ``base = "file.toml"`` chains (relative to the file)."""
    p = Path(path).expanduser().resolve()
    if p in _seen:
        raise ConfigError(f"{p}: 'base' chain loops back to itself")
    try:
        with p.open("rb") as f:
            data = tomllib.load(f)
    except OSError as e:
        raise ConfigError(f"{p}: cannot read ({e.strerror})") from e
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(f"{p}: not valid TOML ({e})") from e
    base = data.pop("base", None)
    if base is None:
        return data
    if not isinstance(base, str):
        raise ConfigError(f"{p}: base: must be a file name (string)")
    return deep_merge(read_toml(p.parent / base, (*_seen, p)), data)


def _convert(value: Any, tp: Any, key: str) -> Any:
    """Check ``value`` against the annotation string ``tp`` and convert it."""
    tp = str(tp)
    if tp == "float":
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise ConfigError(f"{key}: must be a number, got {value!r}")
        if not math.isfinite(value):
            raise ConfigError(f"{key}: must be finite")
        return float(value)
    if tp == "int":
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{key}: must be an integer, got {value!r}")
        return value
    if tp == "bool":
        if not isinstance(value, bool):
            raise ConfigError(f"{key}: must be true or false, got {value!r}")
        return value
    if tp == "tuple[str, ...]":
        if not isinstance(value, list) or not all(isinstance(x, str) for x in value):
            raise ConfigError(f"{key}: must be a list of strings")
        return tuple(value)
    if tp == "str":
        if not isinstance(value, str):
            raise ConfigError(f"{key}: must be a string, got {value!r}")
        return value
    if tp.startswith("tuple[tuple[float, float], ...]"):
        if not isinstance(value, list):
            raise ConfigError(f"{key}: must be a list of [start, end] pairs")
        out = []
        for i, pair in enumerate(value):
            if not isinstance(pair, list) or len(pair) != 2:
                raise ConfigError(f"{key}[{i}]: must be [start_s, end_s]")
            a, b = (_convert(x, "float", f"{key}[{i}]") for x in pair)
            if b < a:
                raise ConfigError(f"{key}[{i}]: end must be >= start")
            out.append((a, b))
        return tuple(out)
    if tp.startswith("tuple[float"):
        n = tp.count("float")
        if not isinstance(value, list) or len(value) != n:
            raise ConfigError(f"{key}: must be a list of {n} numbers")
        return tuple(_convert(x, "float", f"{key}[{i}]") for i, x in enumerate(value))
    raise ConfigError(f"{key}: unsupported type {tp}")  # pragma: no cover - programming error


def _build(cls: Any, table: Any, prefix: str, extra: Mapping[str, Any] | None = None) -> Any:
    if not isinstance(table, Mapping):
        raise ConfigError(f"{prefix}: must be a table")
    kwargs: dict[str, Any] = dict(extra or {})
    known = {f.name for f in dataclasses.fields(cls)}
    for f in dataclasses.fields(cls):
        if f.name in kwargs:
            continue
        key = f"{prefix}.{f.name}"
        if f.name not in table:
            if f.default is not dataclasses.MISSING:
                continue
            raise ConfigError(f"{key}: missing")
        value = _convert(table[f.name], f.type, key)
        check = f.metadata.get("check")
        if check is not None and (msg := check(value)) is not None:
            raise ConfigError(f"{key}: {msg}")
        kwargs[f.name] = value
    unknown = set(table) - known - set(extra or {})
    if unknown:
        raise ConfigError(f"{prefix}: unknown key(s) {', '.join(sorted(unknown))}")
    try:
        return cls(**kwargs)
    except ValueError as e:  # a value type's own check (``__post_init__``) names the field
        raise ConfigError(f"{prefix}.{e}") from None


_SIM_SUBTABLES = {
    "vehicle": VehicleConfig,
    "disturbance": DisturbanceConfig,
    "px4": Px4Config,
    "link": LinkConfig,
    "agv": AgvConfig,
    "camera": SimCameraConfig,
    "faults": FaultsConfig,
    "impairment": ImpairmentConfig,
    "signing": SigningConfig,
    "camera_model": CameraModelConfig,
    "telemetry": TelemetryConfig,
    "battery": BatteryConfig,
    "px4_control": Px4ControlConfig,
}
_OPTIONAL_SUBTABLES = frozenset({"faults", "impairment", "signing", "camera_model", "telemetry",
                                 "battery", "px4_control"})
_IMPAIRMENT_DIRECTIONS = ("vehicle_to_companion", "companion_to_vehicle")


def _build_impairment(table: Any) -> ImpairmentConfig:
    if not isinstance(table, Mapping):
        raise ConfigError("sim.impairment: must be a table")
    dirs = {d: _build(ImpairmentParams, table.get(d, {}), f"sim.impairment.{d}")
            for d in _IMPAIRMENT_DIRECTIONS}
    cfg: ImpairmentConfig = _build(ImpairmentConfig, table, "sim.impairment", extra=dirs)
    return cfg


_LEVELS: dict[str, dict[str, dict[str, Any]]] = {
    "camera_model": CAMERA_LEVELS, "telemetry": TELEMETRY_LEVELS, "vehicle": VEHICLE_LEVELS,
    "battery": BATTERY_LEVELS, "disturbance": DISTURBANCE_LEVELS}


def _with_level(name: str, table: Any) -> Any:
    """``table`` with its ``level``'s preset filled in under the explicit keys."""
    levels = _LEVELS.get(name)
    if levels is None or not isinstance(table, Mapping):
        return table
    level = table.get("level", "ideal")
    if not isinstance(level, str) or level not in levels:
        raise ConfigError(f"sim.{name}.level: must be one of {', '.join(map(repr, levels))}")
    return {**levels[level], **table}


def config_from_dict(data: Mapping[str, Any], scenario: str | None = None,
                     source: str = "") -> EmulatorConfig:
    """Validate a merged TOML document. ``scenario`` overrides ``sim.scenario``."""
    for t in ("sim", "camera", "target"):
        if t not in data:
            raise ConfigError(f"{t}: missing table")
    sim_t = data["sim"]
    if not isinstance(sim_t, Mapping):
        raise ConfigError("sim: must be a table")
    subs = {}
    for name, cls in _SIM_SUBTABLES.items():
        if name not in sim_t:
            if name in _OPTIONAL_SUBTABLES:
                subs[name] = cls()
                continue
            raise ConfigError(f"sim.{name}: missing table")
        if name == "impairment":
            subs[name] = _build_impairment(sim_t[name])
        else:
            subs[name] = _build(cls, _with_level(name, sim_t[name]), f"sim.{name}")
    sig = subs["signing"]
    if sig.key_file and source and not Path(sig.key_file).expanduser().is_absolute():
        subs["signing"] = dataclasses.replace(
            sig, key_file=str(Path(source).resolve().parent / sig.key_file))
    scenarios = sim_t.get("scenarios", {})
    sim_flat = {k: v for k, v in sim_t.items() if k != "scenarios"}
    sim = _build(SimConfig, sim_flat, "sim", extra=subs)
    name = scenario if scenario is not None else sim.scenario
    if not isinstance(scenarios, Mapping) or name not in scenarios:
        have = ", ".join(sorted(scenarios)) if isinstance(scenarios, Mapping) else ""
        raise ConfigError(f"sim.scenarios.{name}: no such scenario (have: {have})")
    scen = _build(ScenarioConfig, scenarios[name], f"sim.scenarios.{name}",
                  extra={"name": name})
    if scenario is not None:
        sim = dataclasses.replace(sim, scenario=name)
    camera = _build(CameraConfig, data["camera"], "camera")
    target = _build(TargetConfig, data["target"], "target")
    return EmulatorConfig(sim=sim, camera=camera, target=target, scenario=scen, source=source)


def load_config(path: str | Path | None = None, scenario: str | None = None) -> EmulatorConfig:
    """Load and validate the emulator's part of a scenario file (default ``config/paper.toml``)."""
    p = Path(path) if path is not None else DEFAULT_CONFIG
    return config_from_dict(read_toml(p), scenario=scenario, source=str(p))


def with_link(cfg: EmulatorConfig, **changes: Any) -> EmulatorConfig:
    """A copy of ``cfg`` with ``sim.link`` fields replaced (validated like the file's)."""
    link = cfg.sim.link
    for k, v in changes.items():
        f = next((f for f in dataclasses.fields(LinkConfig) if f.name == k), None)
        if f is None:
            raise ConfigError(f"sim.link.{k}: unknown key")
        v = _convert(v, f.type, f"sim.link.{k}")
        check = f.metadata.get("check")
        if check is not None and (msg := check(v)) is not None:
            raise ConfigError(f"sim.link.{k}: {msg}")
        link = dataclasses.replace(link, **{k: v})
    return dataclasses.replace(cfg, sim=dataclasses.replace(cfg.sim, link=link))


def with_sim(cfg: EmulatorConfig, **changes: Any) -> EmulatorConfig:
    """A copy of ``cfg`` with top-level ``sim`` fields (or whole sub-configs) replaced."""
    return dataclasses.replace(cfg, sim=dataclasses.replace(cfg.sim, **changes))
