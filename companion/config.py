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

DEFAULT_CONFIG = Path(__file__).resolve().parent.parent / "config" / "paper.toml"
_FOREIGN_TABLES = frozenset({"sim"})


def _positive(x: float) -> str | None:
    return None if x > 0 else "must be > 0"


def _nonneg(x: float) -> str | None:
    return None if x >= 0 else "must be >= 0"


def _unit(x: float) -> str | None:
    return None if 0 < x <= 1 else "must be in (0, 1]"


def _check(fn: typing.Callable[[Any], str | None]) -> dict[str, Any]:
    return {"check": fn}


@dataclass(frozen=True)
class CameraConfig:
    """Pinhole camera and its mount (spec section 1)."""

    focal_length_m: float = field(metadata=_check(_positive))
    pixel_size_m: float = field(metadata=_check(_positive))
    width_px: int = field(metadata=_check(_positive))
    height_px: int = field(metadata=_check(_positive))
    visible_fraction: float = field(metadata=_check(_unit))
    report_pixel_size_m: float = field(metadata=_check(_positive))
    mount_offset_m: tuple[float, float, float]
    mount_rpy_rad: tuple[float, float, float]
    calibration_file: str = ""

    @property
    def visible_half_m(self) -> float:
        """Half side of the visible area on the image plane (metres): ``u~_b = n~_b``."""
        return 0.5 * self.visible_fraction * min(self.width_px, self.height_px) * self.pixel_size_m

    @property
    def r_v(self) -> float:
        """Radius of the inscribed circle of the visible area, normalised (spec 6)."""
        return self.visible_half_m / self.focal_length_m

    @property
    def visible_bound_report_px(self) -> float:
        """Half side of the visible area in report pixels (the paper's 500 px)."""
        return self.visible_half_m / self.report_pixel_size_m


@dataclass(frozen=True)
class TargetConfig:
    length_m: float = field(metadata=_check(_positive))
    width_m: float = field(metadata=_check(_positive))
    height_m: float = field(metadata=_check(_nonneg))
    pattern: str
    aruco_dictionary: str
    aruco_id: int = field(metadata=_check(_nonneg))
    aruco_size_m: float = field(metadata=_check(_positive))
    mavlink_sysid: int = field(metadata=_check(_positive))
    mavlink_compid: int = field(metadata=_check(_nonneg))
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
class TerminalConfig:
    method: str
    p_scale: float = field(default=1.0, metadata=_check(_positive))
    # Optional explicit terminal matrices (from an offline LMI design); empty = compute.
    p_matrix: tuple[tuple[float, ...], ...] = ()
    k_matrix: tuple[tuple[float, ...], ...] = ()
    kappa: float = 0.0

    def __post_init__(self) -> None:
        if self.method not in ("dare", "lmi", "given"):
            raise ConfigError(
                f"rmpc.terminal.method: {self.method!r} is not 'dare', 'lmi' or 'given'"
            )
        if self.method == "given" and (len(self.p_matrix) != 7 or len(self.k_matrix) != 4):
            raise ConfigError("rmpc.terminal: method 'given' needs p_matrix (7x7), k_matrix (4x7)")


@dataclass(frozen=True)
class RmpcConfig:
    """The RMPC of spec section 6 with the paper's numbers as defaults (spec section 8)."""

    dt_s: float = field(metadata=_check(_positive))
    horizon: int = field(metadata=_check(_positive))
    tube_h: float = field(metadata=_check(_positive))
    eps: float = field(metadata=_check(_positive))
    rho: float = field(metadata=_check(_nonneg))
    desired_depth_m: float = field(metadata=_check(_positive))
    q_diag: tuple[float, float, float, float, float, float, float]
    r_diag: tuple[float, float, float, float]
    eta_max: tuple[float, float, float, float, float, float, float]
    u_max: tuple[float, float, float, float]
    g_m_s2: float = field(metadata=_check(_positive))
    enable_visibility: bool
    enable_tube: bool
    enable_terminal: bool
    recovery_penalty: float = field(metadata=_check(_positive))
    solver: str
    jit: bool
    cache_dir: str
    max_iter: int = field(metadata=_check(_positive))
    terminal: TerminalConfig
    # Which image the visibility circle about M(u(n)) constrains: "spec" = p(n) (spec 6 and
    # the paper's (2d); the applied input u(0) is in no row), "causal" = p(n+1), the image
    # taken with the attitude u(n) produces (u(0) checked against the next image).
    visibility_pairing: str = "spec"

    def __post_init__(self) -> None:
        if self.visibility_pairing not in ("spec", "causal"):
            raise ConfigError(
                f"rmpc.visibility_pairing: {self.visibility_pairing!r} is not 'spec' or 'causal'"
            )
        for name in ("q_diag", "r_diag", "eta_max", "u_max"):
            for i, v in enumerate(getattr(self, name)):
                if not v > 0:
                    raise ConfigError(f"rmpc.{name}[{i}]: must be > 0 (got {v})")
        if self.solver not in ("fatrop", "ipopt"):
            raise ConfigError(f"rmpc.solver: {self.solver!r} is not 'fatrop' or 'ipopt'")
        if self.tube_h < 1:
            raise ConfigError("rmpc.tube_h: must be >= 1 (X(n) must not shrink below eps)")
        if self.u_max[2] >= self.g_m_s2:
            raise ConfigError("rmpc.u_max[2]: must be < g (the thrust must stay positive)")

    @property
    def psidot_max(self) -> float:
        return self.u_max[3]

    @property
    def lipschitz_l(self) -> float:
        """Remark 1: ``L = psidot_max + 1/z*``."""
        return self.psidot_max + 1.0 / self.desired_depth_m


@dataclass(frozen=True)
class ControlConfig:
    rate_hz: float = field(metadata=_check(_positive))
    hover_thrust: float = field(metadata=_check(_unit))
    thrust_min: float = field(metadata=_check(_nonneg))
    thrust_max: float = field(metadata=_check(_unit))
    # Whose clock stamps frames and telemetry: "receipt" (local monotonic clock on arrival:
    # a real vehicle) or "autopilot" (source stamps: frames and telemetry share the
    # autopilot's boot clock, as the emulator's do; needed in lockstep).
    time_source: str = "receipt"

    def __post_init__(self) -> None:
        if not self.thrust_min < self.hover_thrust < self.thrust_max:
            raise ConfigError("control: need thrust_min < hover_thrust < thrust_max")
        if self.time_source not in ("receipt", "autopilot"):
            raise ConfigError(
                f"control.time_source: {self.time_source!r} is not 'receipt' or 'autopilot'"
            )


@dataclass(frozen=True)
class MavlinkConfig:
    url: str
    source_system: int = field(metadata=_check(_positive))
    source_component: int = field(metadata=_check(_positive))
    target_system: int = field(metadata=_check(_positive))
    target_component: int = field(metadata=_check(_nonneg))
    signing_key_file: str = ""


@dataclass(frozen=True)
class OffboardConfig:
    preflight_stream_s: float = field(metadata=_check(_nonneg))
    mode_retry_s: float = field(metadata=_check(_positive))
    arm: bool
    exit_mode: str
    # Ask for OFFBOARD again after PX4 left it on its own (failsafe). Off on a real vehicle:
    # the companion must not fight the pilot.
    reengage: bool = False

    def __post_init__(self) -> None:
        if self.exit_mode not in ("hold", "position"):
            raise ConfigError(f"offboard.exit_mode: {self.exit_mode!r} is not 'hold' or 'position'")


@dataclass(frozen=True)
class SafetyConfig:
    telemetry_timeout_s: float = field(metadata=_check(_positive))
    target_lost_timeout_s: float = field(metadata=_check(_positive))
    follow_target_timeout_s: float = field(metadata=_check(_positive))
    hover_fallback_s: float = field(metadata=_check(_positive))
    silence_after_s: float = field(metadata=_check(_positive))
    reacquire_climb_rate_m_s: float = field(metadata=_check(_nonneg))
    reacquire_max_height_m: float = field(metadata=_check(_positive))


@dataclass(frozen=True)
class LoggingConfig:
    dir: str
    image_encoding: str
    chunk_size_bytes: int = field(metadata=_check(_positive))
    flush_interval_s: float = field(metadata=_check(_positive))
    queue_size: int = field(metadata=_check(_positive))
    # Frames waiting to be encoded, at most (MiB); beyond it frames are dropped (counted) ...
    max_pending_image_mb: int = field(default=64, metadata=_check(_positive))
    # ... unless this is set: then logging a frame waits for the writer. Only where no
    # wall-clock deadline exists (lockstep simulation); never on a vehicle.
    block_on_backlog: bool = False
    # MCAP chunk compression: "lz4" (fast), "zstd" (smaller, ~2x the CPU) or "none"
    compression: str = "lz4"

    def __post_init__(self) -> None:
        if self.image_encoding not in ("png", "jpeg", "raw"):
            raise ConfigError(
                f"logging.image_encoding: {self.image_encoding!r} is not 'png', 'jpeg' or 'raw'"
            )
        if self.compression not in ("lz4", "zstd", "none"):
            raise ConfigError(
                f"logging.compression: {self.compression!r} is not 'lz4', 'zstd' or 'none'"
            )


@dataclass(frozen=True)
class Config:
    """The whole companion configuration. ``source`` is the file it came from."""

    camera: CameraConfig
    target: TargetConfig
    rmpc: RmpcConfig
    control: ControlConfig
    mavlink: MavlinkConfig
    offboard: OffboardConfig
    safety: SafetyConfig
    logging: LoggingConfig
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
            raise ConfigError(f"{f.name}: missing table [{f.name}]")
        sections[f.name] = _build(_resolve(f.type), data[f.name], f.name)
    plain = {k: v for k, v in data.items() if k not in _FOREIGN_TABLES}
    return Config(**sections, source=source, raw=types.MappingProxyType(plain))


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
    raise ConfigError(f"{key}: unsupported type {tp!r}")  # pragma: no cover - programming error
