"""``[camera]``, ``[target]``, ``[sim.agv]``, ``[sim.camera]`` and ``[sim.scenarios.NAME]``: the
world the emulator renders and flies in."""

from __future__ import annotations

from dataclasses import dataclass, field

from sim_bridge.config.checks import checked, nonneg, one_of, positive, unit, valid_sysid


# --------------------------------------------------------------------------------------------
# [camera] and [target]: the physical camera and target the emulator renders
@dataclass(frozen=True)
class CameraConfig:
    """Pinhole camera and its mount in the body frame (FRD); camera axes = body axes rotated
    by ``mount_rpy_rad`` (ZYX)."""

    focal_length_m: float = field(metadata=checked(positive))
    pixel_size_m: float = field(metadata=checked(positive))
    width_px: int = field(metadata=checked(positive))
    height_px: int = field(metadata=checked(positive))
    visible_fraction: float = field(metadata=checked(unit))
    report_pixel_size_m: float = field(metadata=checked(positive))
    mount_offset_m: tuple[float, float, float]
    mount_rpy_rad: tuple[float, float, float]
    calibration_file: str = ""


@dataclass(frozen=True)
class TargetConfig:
    """The AGV's top (a rectangle or an ArUco marker) and its MAVLink identity."""

    length_m: float = field(metadata=checked(positive))
    width_m: float = field(metadata=checked(positive))
    height_m: float = field(metadata=checked(nonneg))
    pattern: str = field(metadata=checked(one_of("rectangle", "aruco")))
    aruco_dictionary: str
    aruco_id: int = field(metadata=checked(nonneg))
    aruco_size_m: float = field(metadata=checked(positive))
    mavlink_sysid: int = field(metadata=checked(valid_sysid))
    mavlink_compid: int = field(metadata=checked(valid_sysid))
    origin_lat_deg: float
    origin_lon_deg: float
    origin_alt_m: float



@dataclass(frozen=True)
class AgvConfig:
    trajectory: str = field(metadata=checked(one_of("paper", "line", "circle", "figure8",
                                                  "stop_and_go", "ramp")))
    speed_scale: float = field(metadata=checked(nonneg))
    rate_hz: float = field(metadata=checked(positive))
    top_z_m: float
    ramp_accel_m_s2: float = field(default=1.0, metadata=checked(positive))  # trajectory "ramp"


@dataclass(frozen=True)
class SimCameraConfig:
    rate_hz: float = field(metadata=checked(positive))
    noise_std: float = field(metadata=checked(nonneg))
    blur_px: float = field(metadata=checked(nonneg))
    occlusions: tuple[tuple[float, float], ...] = ()

    def occluded(self, t_s: float) -> bool:
        """Whether the target is hidden at ``t_s`` (s since boot)."""
        return any(a <= t_s < b for a, b in self.occlusions)


@dataclass(frozen=True)
class ScenarioConfig:
    """Initial UAV pose: position (m, NED) and roll, pitch, yaw (rad, ZYX)."""

    name: str
    uav_pose: tuple[float, float, float, float, float, float]

