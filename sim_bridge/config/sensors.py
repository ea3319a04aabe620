"""``[sim.camera_model]`` and ``[sim.telemetry]``: how the camera and the autopilot's MAVLink output
depart from the ideal, with their named levels."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from sim_bridge import ConfigError
from sim_bridge.config.checks import checked, nonneg, one_of, positive

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
    """The camera's imperfections (``sim_bridge.camera.sensor``); all off = the ideal camera.

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

    level: str = field(default="ideal", metadata=checked(one_of(*CAMERA_LEVELS)))
    latency_ms: float = field(default=0.0, metadata=checked(nonneg))
    latency_jitter_ms: float = field(default=0.0, metadata=checked(nonneg))
    drop_probability: float = field(default=0.0, metadata=checked(
        lambda x: None if 0 <= x < 1 else "must be in [0, 1)"))
    exposure_ms: float = field(default=0.0, metadata=checked(nonneg))
    read_noise_std_dn: float = field(default=0.0, metadata=checked(nonneg))
    shot_noise_dn_per_e: float = field(default=0.0, metadata=checked(nonneg))
    brightness_drift_std: float = field(default=0.0, metadata=checked(nonneg))
    brightness_drift_tau_s: float = field(default=5.0, metadata=checked(positive))
    timestamp_clock: str = field(default="autopilot",
                                 metadata=checked(one_of("autopilot", "camera")))
    clock_offset_ms: float = field(default=0.0, metadata=checked(nonneg))
    clock_drift_ppm: float = field(default=0.0, metadata=checked(
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
    axis
    and LOCAL_POSITION_NED sample; 0 at every level): the velocity estimate departs from the
    truth by this, as an EKF's does (a white model: EKF2's output is smoother, so this is the
    harsher case for a given std).
    """

    level: str = field(default="ideal", metadata=checked(one_of(*TELEMETRY_LEVELS)))
    rates: str = field(default="emulator", metadata=checked(one_of("emulator", "px4")))
    delay_ms: float = field(default=0.0, metadata=checked(nonneg))
    delay_jitter_ms: float = field(default=0.0, metadata=checked(nonneg))
    boot_offset_s: float = field(default=0.0, metadata=checked(
        lambda x: None if 0 <= x < 4e6 else "must be in [0, 4e6) (time_boot_ms is a u32)"))
    accel_noise_m_s2: float = field(default=0.0, metadata=checked(
        lambda x: None if 0 <= x <= 20 else "must be in [0, 20] m/s^2"))
    accel_bias_m_s2: tuple[float, float, float] = field(default=(0.0, 0.0, 0.0), metadata=checked(
        lambda x: None if len(x) == 3 and all(abs(v) <= 5 for v in x)
        else "must be 3 values within +-5 m/s^2"))
    velocity_noise_m_s: float = field(default=0.0, metadata=checked(
        lambda x: None if 0 <= x <= 5 else "must be in [0, 5] m/s"))

    def __post_init__(self) -> None:
        if self.delay_jitter_ms > self.delay_ms:
            raise ConfigError("sim.telemetry.delay_jitter_ms: must be <= delay_ms")

