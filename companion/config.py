"""Companion configuration: loaded once from TOML into validated, frozen dataclasses.

Every stage receives its own frozen section in its constructor. A bad value raises
:class:`companion.ConfigError` naming the key (``rmpc.q_diag[2]: must be > 0``); nothing starts
with a half-read config. The ``[sim]`` table belongs to the emulator and is ignored here.

A file may start with ``base = "other.toml"`` (relative to itself): the base is loaded first
and this file's tables/keys override it (deep merge). ``overrides`` (``"rmpc.eps=0.11"``) are
applied last, with TOML value syntax.
"""

from __future__ import annotations

import dataclasses
import math
import tomllib
import types
import typing
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from companion import ConfigError
from companion.control.vehicle_limits_config import VehicleLimitsConfig
from companion.core.errors import ParamError
from companion.core.geometry import rectangle_corners_m
from companion.core.params import (
    CameraParams,
    ControlParams,
    RmpcParams,
    checked,
    nonneg,
    positive,
)
from companion.perception_config import PerceptionConfig as PerceptionConfig

DEFAULT_CONFIG = Path(__file__).resolve().parent.parent / "config" / "paper.toml"
_FOREIGN_TABLES = frozenset({"sim"})


@dataclass(frozen=True)
class TargetConfig:
    length_m: float = field(metadata=checked(positive))
    width_m: float = field(metadata=checked(positive))
    height_m: float = field(metadata=checked(nonneg))
    pattern: str
    aruco_dictionary: str
    aruco_id: int = field(metadata=checked(nonneg))
    aruco_size_m: float = field(metadata=checked(positive))
    mavlink_sysid: int = field(metadata=checked(positive))
    mavlink_compid: int = field(metadata=checked(nonneg))
    origin_lat_deg: float
    origin_lon_deg: float
    origin_alt_m: float

    def __post_init__(self) -> None:
        if self.pattern not in ("rectangle", "aruco"):
            raise ConfigError(f"target.pattern: {self.pattern!r} is not 'rectangle' or 'aruco'")
        if not -90.0 <= self.origin_lat_deg <= 90.0:
            raise ConfigError("target.origin_lat_deg: must be in [-90, 90]")
        if not -180.0 <= self.origin_lon_deg <= 180.0:
            raise ConfigError("target.origin_lon_deg: must be in [-180, 180]")


@dataclass(frozen=True)
class MavlinkConfig:
    url: str
    source_system: int = field(metadata=checked(positive))
    source_component: int = field(metadata=checked(positive))
    target_system: int = field(metadata=checked(positive))
    target_component: int = field(metadata=checked(nonneg))
    signing_key_file: str = ""
    # Receive guard (companion/link/guard.py, docs/reference/reliability.md): pin the autopilot
    # (and the AGV) to the address of its first valid frame and drop other senders claiming its
    # sysid
    # unparsed; addresses that may always speak for it ("host" or "host:port", routers).
    pin_source: bool = True
    allowed_sources: tuple[str, ...] = ()
    repin_after_s: float = field(default=5.0, metadata=checked(positive))
    # Work bounds: datagram size, datagrams read per event-loop wake-up, parses per second of
    # datagrams from unknown addresses, rejected frames logged per second, socket buffer.
    max_datagram_bytes: int = field(default=2048, metadata=checked(positive))
    max_datagrams_per_wakeup: int = field(default=256, metadata=checked(positive))
    untrusted_parse_per_s: float = field(default=500.0, metadata=checked(positive))
    reject_log_per_s: float = field(default=200.0, metadata=checked(positive))
    recv_buffer_bytes: int = field(default=4194304, metadata=checked(positive))
    # Link counters on /mavlink/stats every this many seconds.
    stats_interval_s: float = field(default=1.0, metadata=checked(positive))

    def __post_init__(self) -> None:
        for i, src in enumerate(self.allowed_sources):
            host, sep, port = src.rpartition(":")
            if not sep:
                host, port = src, ""
            octets = host.split(".")
            ok = len(octets) == 4 and all(o.isdigit() and int(o) <= 255 for o in octets)
            if not ok or not (port == "" or (port.isdigit() and 1 <= int(port) <= 65535)):
                raise ConfigError(
                    f"mavlink.allowed_sources[{i}]: {src!r} is not an IPv4 address with an "
                    "optional :PORT (1..65535)"
                )


@dataclass(frozen=True)
class OffboardConfig:
    preflight_stream_s: float = field(metadata=checked(nonneg))
    mode_retry_s: float = field(metadata=checked(positive))
    arm: bool
    exit_mode: str
    # Ask for OFFBOARD again after PX4 left it on its own (failsafe). Off on a real vehicle:
    # the companion must not fight the pilot.
    reengage: bool = False
    # Ask for OFFBOARD (and arm) only while the autopilot's EXTENDED_SYS_STATE says IN_AIR: the
    # companion follows from the air; on the ground PX4 would take its setpoints as a take-off.
    require_in_air: bool = True
    # The pre-flight stream while the controller reports its hard problem infeasible (the
    # target escaping the view; a 'recovery' solve): OFFBOARD is requested once this much has
    # been streamed instead of preflight_stream_s. None: always the full stream.
    preflight_escape_stream_s: float | None = field(default=None, metadata=checked(nonneg))

    def __post_init__(self) -> None:
        if self.exit_mode not in ("hold", "position"):
            raise ConfigError(f"offboard.exit_mode: {self.exit_mode!r} is not 'hold' or 'position'")
        if (self.preflight_escape_stream_s is not None
                and self.preflight_escape_stream_s > self.preflight_stream_s):
            raise ConfigError(
                f"offboard.preflight_escape_stream_s ({self.preflight_escape_stream_s}) must not"
                f" exceed offboard.preflight_stream_s ({self.preflight_stream_s})")


@dataclass(frozen=True)
class SafetyConfig:
    telemetry_timeout_s: float = field(metadata=checked(positive))
    target_lost_timeout_s: float = field(metadata=checked(positive))
    follow_target_timeout_s: float = field(metadata=checked(positive))
    hover_fallback_s: float = field(metadata=checked(positive))
    silence_after_s: float = field(metadata=checked(positive))
    reacquire_climb_rate_m_s: float = field(metadata=checked(nonneg))
    reacquire_max_height_m: float = field(metadata=checked(positive))
    # A camera frame or telemetry message whose delay exceeds its stream's smallest delay by
    # more than this is stale (a stalled process, a backlog): no command is built from it.
    # Receipt time base only (control.time_source = "receipt").
    max_frame_age_s: float = field(default=0.25, metadata=checked(positive))


@dataclass(frozen=True)
class LoggingConfig:
    dir: str
    image_encoding: str
    chunk_size_bytes: int = field(metadata=checked(positive))
    flush_interval_s: float = field(metadata=checked(positive))
    queue_size: int = field(metadata=checked(positive))
    # Frames waiting to be encoded, at most (MiB); beyond it frames are dropped (counted) ...
    max_pending_image_mb: int = field(default=64, metadata=checked(positive))
    # ... unless this is set: then logging a frame waits for the writer. Only where no
    # wall-clock deadline exists (lockstep simulation); never on a vehicle.
    block_on_backlog: bool = False
    # MCAP chunk compression: "lz4" (fast), "zstd" (smaller, ~2x the CPU) or "none"
    compression: str = "lz4"
    # What perception read, on /perception/input, encoded with ``image_encoding``: "crop"
    # (the region the detector read: the whole frame when it searched), "full" (every frame
    # whole) or "none" (replay then needs an old log's full frames, or --from-detections)
    perception_input: str = "crop"
    # The preview for people on /camera/image (JPEG): at most this many frames per second of
    # camera time (0: none), scaled by ``preview_scale``, JPEG quality ``preview_jpeg_quality``.
    # 2 Hz: a preview costs the writer thread ~0.6-0.9 ms (downscale + JPEG of 500 x 500 px),
    # ~45 us a step at 20 Hz instead of ~0.2 ms at 5 Hz (bench/log_kinds.py)
    preview_rate_hz: float = field(default=2.0, metadata=checked(nonneg))
    preview_scale: float = 0.5
    preview_jpeg_quality: int = 75
    # Log times: "receipt" (the companion's monotonic clock; a real vehicle) or "source" (the
    # autopilot's clock carried by frames and telemetry: a lockstep simulation then plays at
    # its real speed)
    timestamps: str = "receipt"
    # When the writer thread forces the file to the disk: "interval" (os.fsync every
    # flush_interval_s and at each full chunk: power loss costs at most that much), "close"
    # (only at the end: the OS writes back when it likes) or "never".
    fsync: str = "interval"

    def __post_init__(self) -> None:
        if self.fsync not in ("interval", "close", "never"):
            raise ConfigError(
                f"logging.fsync: {self.fsync!r} is not 'interval', 'close' or 'never'"
            )
        if self.image_encoding not in ("png", "jpeg", "raw"):
            raise ConfigError(
                f"logging.image_encoding: {self.image_encoding!r} is not 'png', 'jpeg' or 'raw'"
            )
        if self.compression not in ("lz4", "zstd", "none"):
            raise ConfigError(
                f"logging.compression: {self.compression!r} is not 'lz4', 'zstd' or 'none'"
            )
        if self.perception_input not in ("crop", "full", "none"):
            raise ConfigError(f"logging.perception_input: {self.perception_input!r} is not "
                              "'crop', 'full' or 'none'")
        if not 0.0 < self.preview_scale <= 1.0:
            raise ConfigError(f"logging.preview_scale: {self.preview_scale!r} is not in (0, 1]")
        if not 1 <= self.preview_jpeg_quality <= 100:
            raise ConfigError(f"logging.preview_jpeg_quality: {self.preview_jpeg_quality!r} "
                              "is not in 1..100")
        if self.timestamps not in ("receipt", "source"):
            raise ConfigError(
                f"logging.timestamps: {self.timestamps!r} is not 'receipt' or 'source'")


@dataclass(frozen=True)
class LiveConfig:
    """Live view: the log's channels served over the Foxglove WebSocket protocol
    (:mod:`companion.log.live`). Off by default: on a vehicle it is one more open port."""

    enabled: bool = False
    # Interface to bind: loopback by default; "0.0.0.0" serves every interface (see docs)
    host: str = "127.0.0.1"
    port: int = field(default=8765, metadata=checked(nonneg))  # TCP; 0 picks a free port
    # Messages waiting for the publisher thread, at most; beyond it the oldest are dropped (counted)
    queue_size: int = field(default=512, metadata=checked(positive))
    # Messages buffered per connected client by the SDK; a slow client loses the oldest
    client_backlog: int = field(default=256, metadata=checked(positive))

    def __post_init__(self) -> None:
        if not self.host or any(c.isspace() for c in self.host):
            raise ConfigError(f"live.host: {self.host!r} is not a host name or address")
        if self.port > 65535:
            raise ConfigError(f"live.port: {self.port} is not a TCP port (0..65535)")


CONTROLLER_KINDS = ("rmpc", "rmpc-centroid", "mpc-novis", "ibvs-pd")


@dataclass(frozen=True)
class ControllerConfig:
    """Which control law flies (docs/reference/visibility.md, ``companion/control/factory.py``).

    ``kind``: ``rmpc`` (the RMPC as configured in [rmpc]; paper.toml keeps every corner in
    view), ``rmpc-centroid`` (the same with the paper's centroid rows), ``mpc-novis`` (the same
    MPC without visibility rows), ``ibvs-pd`` (classical moment-based IBVS: a PD on the same
    virtual-camera moments). ``ibvs_*``: the IBVS gains (1/s): image-error decay rate
    ``lambda``, velocity-loop gain ``k_v`` (critically damped at ``k_v = 4 lambda``) and the
    yaw gain.
    """

    kind: str = "rmpc"
    ibvs_lambda_1_s: float = field(default=0.5, metadata=checked(positive))
    ibvs_kv_1_s: float = field(default=2.0, metadata=checked(positive))
    ibvs_yaw_gain_1_s: float = field(default=1.0, metadata=checked(positive))

    def __post_init__(self) -> None:
        if self.kind not in CONTROLLER_KINDS:
            raise ConfigError(
                f"controller.kind: {self.kind!r} is not one of {', '.join(CONTROLLER_KINDS)}"
            )


@dataclass(frozen=True)
class Config:
    """The whole companion configuration. ``source`` is the file it came from."""

    camera: CameraParams
    target: TargetConfig
    rmpc: RmpcParams
    control: ControlParams
    mavlink: MavlinkConfig
    offboard: OffboardConfig
    safety: SafetyConfig
    logging: LoggingConfig
    controller: ControllerConfig = field(default_factory=ControllerConfig)
    live: LiveConfig = field(default_factory=LiveConfig)  # optional table [live]
    perception: PerceptionConfig = field(default_factory=PerceptionConfig)  # optional
    vehicle_limits: VehicleLimitsConfig = field(default_factory=VehicleLimitsConfig)  # optional
    source: str = ""
    raw: Mapping[str, Any] = field(default_factory=dict, repr=False, compare=False)


# ----------------------------------------------------------------------------------------------
# Loading


def load_config(path: str | Path | None = None, overrides: Sequence[str] = ()) -> Config:
    """Load, merge and validate a config file (default: ``config/paper.toml``)."""
    p = Path(path) if path is not None else DEFAULT_CONFIG
    data = _read_with_base(p, seen=())
    for ov in overrides:
        _apply_override(data, ov)
    return config_from_dict(data, source=str(p))


def config_from_dict(data: Mapping[str, Any], source: str = "") -> Config:
    """Validate a parsed TOML document (already merged) into a :class:`Config`."""
    known = {f.name for f in dataclasses.fields(Config)} - {"source", "raw"}
    for key in data:
        if key not in known and key not in _FOREIGN_TABLES and key != "base":
            raise ConfigError(f"{key}: unknown table (expected one of {sorted(known)})")
    sections: dict[str, Any] = {}
    for f in dataclasses.fields(Config):
        if f.name in ("source", "raw"):
            continue
        if f.name not in data:
            if f.default_factory is not dataclasses.MISSING:  # an optional table
                sections[f.name] = f.default_factory()
                continue
            raise ConfigError(f"{f.name}: missing table [{f.name}]")
        table = data[f.name]
        if f.name == "rmpc" and isinstance(table, Mapping):
            table = _with_target_corners(_legacy_solver(table), sections["target"])
        sections[f.name] = _build(_resolve(f.type), table, f.name)
    plain = {k: v for k, v in data.items() if k not in _FOREIGN_TABLES}
    return Config(**sections, source=source, raw=types.MappingProxyType(_resolved(plain, sections)))


def _resolved(plain: dict[str, Any], sections: Mapping[str, Any]) -> dict[str, Any]:
    """The document with the choices a replay must know spelled out even where the file left
    them to their defaults (the recorded config is this document): the rectangle detector's
    edge method, whose absence in a log means the method before the key existed."""
    perception = plain.get("perception")
    if isinstance(perception, Mapping) and "rectangle_edges" in perception:
        return plain
    table = dict(perception) if isinstance(perception, Mapping) else {}
    table["rectangle_edges"] = sections["perception"].rectangle_edges
    return {**plain, "perception": table}


LEGACY_NLP_SOLVERS = ("fatrop", "ipopt")
"""What ``rmpc.solver`` named before ``"nlp" | "rti"``: the NLP solver (now
``rmpc.nlp_solver``)."""


def _legacy_solver(table: Mapping[str, Any]) -> Mapping[str, Any]:
    """A config written before ``rmpc.solver = "nlp" | "rti"`` existed (every log recorded
    before it) says ``solver = "fatrop"`` or ``"ipopt"``: that is the full NLP with that NLP
    solver, so it is read as ``solver = "nlp"``, ``nlp_solver = <it>`` and replays as flown."""
    old = table.get("solver")
    if old not in LEGACY_NLP_SOLVERS:
        return table
    if "nlp_solver" in table and table["nlp_solver"] != old:
        raise ConfigError(f"rmpc.solver: {old!r} (the old spelling of rmpc.nlp_solver) "
                          f"contradicts rmpc.nlp_solver = {table['nlp_solver']!r}")
    return {**table, "solver": "nlp", "nlp_solver": old}


def _with_target_corners(table: Mapping[str, Any], target: TargetConfig) -> dict[str, Any]:
    """The [rmpc] table with ``target_corners_m`` filled from [target] (the corners the
    detector returns: the rectangle's, or the marker's)."""
    if "target_corners_m" in table:
        raise ConfigError("rmpc.target_corners_m: not a config key (it comes from [target])")
    if target.pattern == "aruco":
        pts = rectangle_corners_m(target.aruco_size_m, target.aruco_size_m)
    else:
        pts = rectangle_corners_m(target.length_m, target.width_m)
    return {**table, "target_corners_m": [[float(x), float(y)] for x, y in pts]}


def read_document(path: str | Path) -> dict[str, Any]:
    """The whole TOML document of a config file with its ``base`` chain merged (every table,
    the emulator's ``[sim]`` included), unvalidated."""
    return _read_with_base(Path(path), seen=())


def with_overrides(data: Mapping[str, Any], overrides: Sequence[str]) -> dict[str, Any]:
    """A deep copy of a parsed config document with ``key=value`` overrides applied."""
    import copy

    out = copy.deepcopy(dict(data))
    for ov in overrides:
        _apply_override(out, ov)
    return out


def _read_with_base(path: Path, seen: tuple[Path, ...]) -> dict[str, Any]:
    path = path.expanduser().resolve()
    if path in seen:
        raise ConfigError(f"base: circular base chain at {path}")
    try:
        with path.open("rb") as fh:
            data = tomllib.load(fh)
    except FileNotFoundError:
        raise ConfigError(f"{path}: config file not found") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML: {exc}") from None
    base = data.pop("base", None)
    if base is None:
        return data
    if not isinstance(base, str):
        raise ConfigError(f"{path}: base: must be a file name string")
    merged = _read_with_base(path.parent / base, (*seen, path))
    _deep_merge(merged, data)
    return merged


def _deep_merge(dst: dict[str, Any], src: Mapping[str, Any]) -> None:
    for k, v in src.items():
        if isinstance(v, Mapping) and isinstance(dst.get(k), dict):
            _deep_merge(dst[k], v)
        else:
            dst[k] = v


def _apply_override(data: dict[str, Any], text: str) -> None:
    key, sep, value = text.partition("=")
    key = key.strip()
    if not sep or not key:
        raise ConfigError(f"override {text!r}: expected key=value, e.g. rmpc.eps=0.11")
    try:
        parsed = tomllib.loads(f"v = {value.strip()}")["v"]
    except tomllib.TOMLDecodeError:
        parsed = value.strip()  # bare word: a string
    node = data
    parts = key.split(".")
    for part in parts[:-1]:
        nxt = node.get(part)
        if not isinstance(nxt, dict):
            raise ConfigError(f"override {key}: no table {part!r}")
        node = nxt
    if parts[-1] not in node:
        raise ConfigError(f"override {key}: no such key")
    node[parts[-1]] = parsed


def _resolve(tp: Any) -> Any:
    if isinstance(tp, str):
        return eval(tp, globals())  # annotations are strings (from __future__ import annotations)
    return tp


def _build(cls: Any, table: Any, where: str) -> Any:
    if not isinstance(table, Mapping):
        raise ConfigError(f"{where}: must be a table")
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}
    for key in table:
        if key not in names:
            raise ConfigError(f"{where}.{key}: unknown key")
    kwargs: dict[str, Any] = {}
    for f in dataclasses.fields(cls):
        key = f"{where}.{f.name}"
        if f.name not in table:
            if f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
                raise ConfigError(f"{key}: missing")
            continue
        value = _coerce(hints[f.name], table[f.name], key)
        check = f.metadata.get("check")
        if check is not None:
            msg = check(value)
            if msg:
                raise ConfigError(f"{key}: {msg} (got {value!r})")
        kwargs[f.name] = value
    try:
        return cls(**kwargs)
    except ConfigError:
        raise
    except ParamError as exc:
        raise ConfigError(str(exc)) from None
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"{where}: {exc}") from None


def _coerce(tp: Any, value: Any, key: str) -> Any:
    origin = typing.get_origin(tp)
    if dataclasses.is_dataclass(tp):
        return _build(tp, value, key)
    if tp is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{key}: must be true or false (got {value!r})")
        return value
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{key}: must be an integer (got {value!r})")
        return value
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{key}: must be a number (got {value!r})")
        if not math.isfinite(value):
            raise ConfigError(f"{key}: must be finite (got {value!r})")
        return float(value)
    if tp is str:
        if not isinstance(value, str):
            raise ConfigError(f"{key}: must be a string (got {value!r})")
        return value
    if origin is tuple:
        args = typing.get_args(tp)
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{key}: must be a list (got {value!r})")
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_coerce(args[0], v, f"{key}[{i}]") for i, v in enumerate(value))
        if len(value) != len(args):
            raise ConfigError(f"{key}: must have {len(args)} elements (got {len(value)})")
        pairs = enumerate(zip(args, value, strict=True))
        return tuple(_coerce(a, v, f"{key}[{i}]") for i, (a, v) in pairs)
    args = typing.get_args(tp)
    if origin in (types.UnionType, typing.Union) and len(args) == 2 and type(None) in args:
        # ``X | None``: TOML has no null; a key that is present holds an X (absent: None)
        return _coerce(next(a for a in args if a is not type(None)), value, key)
    raise ConfigError(f"{key}: unsupported type {tp!r}")  # pragma: no cover - programming error
