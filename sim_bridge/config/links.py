"""``[sim.link]``, ``[sim.faults]``, ``[sim.impairment]`` and ``[sim.signing]``: the emulator's
sockets and what may go wrong on them."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from sim_bridge import ConfigError
from sim_bridge.config.checks import address, checked, valid_port, valid_sysid
from sim_bridge.impairment import ImpairmentParams


@dataclass(frozen=True)
class LinkConfig:
    """Sockets (docs/reference/wire.md). Local ports may be 0 (any free port; the app logs the real
    one)."""

    sysid: int = field(metadata=checked(valid_sysid))
    compid: int = field(metadata=checked(valid_sysid))
    offboard_local_port: int = field(metadata=checked(valid_port))
    offboard_remote: str = field(metadata=checked(address))
    gcs_local_port: int = field(metadata=checked(valid_port))
    gcs_remote: str = field(metadata=checked(address))
    agv_local_port: int = field(metadata=checked(valid_port))
    frame_port: int = field(metadata=checked(valid_port))
    truth_remote: str = field(metadata=checked(address))


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

    links: tuple[str, ...] = field(default=("offboard",), metadata=checked(_links))
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
    key_hex: str = field(default="", metadata=checked(_hex_key))
    key_file: str = ""
    links: tuple[str, ...] = field(default=LINK_NAMES, metadata=checked(_links))

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
