"""The campaign's scenario library: controllers x scenarios x seeds, and the sampled starts.

A campaign file (``config/campaigns/default.toml``, documented in ``docs/reference/campaigns.md``)
names a base config, the controllers (named override lists), the scenarios (an AGV path at a
speed scale plus override lists for disturbances and the vehicle) and the distribution of the
starts. Every run is one lockstep flight (``companion demo``) whose overrides are the
campaign's, the scenario's, the sampled start's (``sim.scenarios.campaign.uav_pose``), the
seed's (``sim.seed``, which also seeds the emulator's random disturbance) and the controller's,
in that order.

Starts are sampled near the edge of the visible area: the target's centroid at a fraction of
the visible half-size (Chebyshev norm, the visible area is a square) in a uniform direction,
the camera ``height_m`` above the target's top, the heading error ``s4 = psi_agv - psi_uav``
uniform; a start whose corners would not all be inside ``max_corner_fraction`` of the visible
area is redrawn. The sample depends on the scenario's name and the seed only, so every
controller flies the same start (a paired comparison).
"""

from __future__ import annotations

import hashlib
import math
import tomllib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from companion import ConfigError

__all__ = ["PATHS", "Campaign", "Controller", "RunSpec", "Scenario", "StartDistribution",
           "load_campaign", "sample_start"]

REPO_ROOT = Path(__file__).resolve().parent.parent.parent
DEFAULT_CAMPAIGN = REPO_ROOT / "config" / "campaigns" / "default.toml"
SCENARIO_NAME = "campaign"  # the [sim.scenarios.NAME] each run's sampled start is written to


@dataclass(frozen=True)
class PathInfo:
    """An AGV path of the emulator at speed scale 1 (``sim_bridge/physics/agv.py``; a test
    checks these against it): the heading at t = 0 (rad, NED), the peak ground speed (m/s),
    heading rate (rad/s) and acceleration (m/s^2). Speed and heading rate scale with the speed
    scale, acceleration with its square (``accel_scales``; the ``ramp``'s acceleration is
    ``sim.agv.ramp_accel_m_s2`` whatever the scale)."""

    trajectory: str
    yaw0_rad: float
    peak_speed_m_s: float
    peak_yaw_rate_rad_s: float
    peak_accel_m_s2: float
    accel_scales: bool = True


PATHS: dict[str, PathInfo] = {
    "paper": PathInfo("paper", math.pi / 4, 0.1414, 0.0250, 0.0025),
    "line": PathInfo("line", 0.0, 0.3000, 0.0, 0.0),
    "circle": PathInfo("circle", 0.0, 0.3000, 0.1000, 0.0300),
    "figure-eight": PathInfo("figure8", math.pi / 4, 0.4443, 0.3324, 0.0699),
    "stop-and-go": PathInfo("stop_and_go", math.atan(0.2), 0.5099, 0.0200, 0.2003),
    "ramp": PathInfo("ramp", 0.0, 0.3000, 0.0, 1.0, accel_scales=False),
}


@dataclass(frozen=True)
class StartDistribution:
    """Where a run starts (see the module docstring); ranges are ``[low, high]``, uniform."""

    height_m: tuple[float, float] = (2.4, 3.6)
    yaw_error_rad: tuple[float, float] = (-math.pi / 3, math.pi / 3)
    edge_fraction: tuple[float, float] = (0.6, 0.9)
    max_corner_fraction: float = 0.95

    def __post_init__(self) -> None:
        for name in ("height_m", "yaw_error_rad", "edge_fraction"):
            lo, hi = getattr(self, name)
            if not (math.isfinite(lo) and math.isfinite(hi) and lo <= hi):
                raise ConfigError(f"start.{name}: must be [low, high] with low <= high")
        if self.height_m[0] <= 0:
            raise ConfigError("start.height_m: must be > 0")
        if not (self.edge_fraction[0] >= 0 and self.edge_fraction[1] < self.max_corner_fraction):
            raise ConfigError("start.edge_fraction: must lie in [0, max_corner_fraction)")
        if not 0 < self.max_corner_fraction <= 1:
            raise ConfigError("start.max_corner_fraction: must be in (0, 1]")


@dataclass(frozen=True)
class Controller:
    name: str
    set: tuple[str, ...] = ()


@dataclass(frozen=True)
class Scenario:
    """An AGV path (a key of :data:`PATHS`) at ``speed_scale``, plus overrides."""

    name: str
    path: str
    speed_scale: float
    set: tuple[str, ...] = ()

    @property
    def peak_speed_m_s(self) -> float:
        return PATHS[self.path].peak_speed_m_s * self.speed_scale

    @property
    def peak_yaw_rate_rad_s(self) -> float:
        return PATHS[self.path].peak_yaw_rate_rad_s * self.speed_scale

    def overrides(self) -> list[str]:
        return [f'sim.agv.trajectory="{PATHS[self.path].trajectory}"',
                f"sim.agv.speed_scale={self.speed_scale!r}", *self.set]


@dataclass(frozen=True)
class Camera:
    """What sampling needs of the config's camera and target (metres, report pixels)."""

    focal_length_m: float
    report_pixel_size_m: float
    visible_bound_px: float
    target_length_m: float
    target_width_m: float
    target_top_z_m: float  # NED z of the AGV top (sim.agv.top_z_m)


@dataclass(frozen=True)
class Start:
    """A sampled start: the UAV pose (NED m, rad) and what it was drawn as."""

    uav_pose: tuple[float, float, float, float, float, float]
    height_m: float
    yaw_error_rad: float
    centroid_px: tuple[float, float]  # (u, n) in report pixels
    max_corner_px: float

    def overrides(self) -> list[str]:
        pose = ", ".join(repr(round(v, 6)) for v in self.uav_pose)
        return [f"sim.scenarios.{SCENARIO_NAME}.uav_pose=[{pose}]"]


def _rng(scenario: str, seed: int) -> np.random.Generator:
    salt = int.from_bytes(hashlib.sha256(scenario.encode()).digest()[:4], "little")
    return np.random.default_rng(np.random.SeedSequence([seed % 2**32, salt]))


def sample_start(dist: StartDistribution, cam: Camera, path: str, scenario: str,
                 seed: int) -> Start:
    """The start of (``scenario``, ``seed``); the AGV is at the origin heading
    ``PATHS[path].yaw0_rad`` at t = 0. Image coordinates: ``u`` forward, ``n`` right (body
    FRD axes, level camera looking down), in report pixels."""
    rng = _rng(scenario, seed)
    yaw_a = PATHS[path].yaw0_rad
    px_per_m_at_1m = cam.focal_length_m / cam.report_pixel_size_m
    b = cam.visible_bound_px
    hl, hw = cam.target_length_m / 2, cam.target_width_m / 2
    corners_a = np.array([[hl, hw], [hl, -hw], [-hl, -hw], [-hl, hw]])
    for _ in range(10_000):
        h = float(rng.uniform(*dist.height_m))
        e = float(rng.uniform(*dist.yaw_error_rad))
        phi = float(rng.uniform(0.0, 2 * math.pi))
        r = float(rng.uniform(*dist.edge_fraction))
        d = np.array([math.cos(phi), math.sin(phi)])
        c_px = r * b * d / np.max(np.abs(d))  # on the square of Chebyshev radius r b
        c_b = c_px / px_per_m_at_1m * h  # AGV centre in the body frame (x fwd, y right), m
        rot_e = np.array([[math.cos(e), -math.sin(e)], [math.sin(e), math.cos(e)]])
        corners_px = (c_b + corners_a @ rot_e.T) / h * px_per_m_at_1m
        worst = float(np.max(np.abs(corners_px)))
        if worst <= dist.max_corner_fraction * b:
            break
    else:  # pragma: no cover - only with a distribution that cannot be met
        raise ConfigError("start: no start with every corner inside max_corner_fraction of "
                          "the visible area (widen edge_fraction or height_m)")
    psi = yaw_a - e
    rot = np.array([[math.cos(psi), -math.sin(psi)], [math.sin(psi), math.cos(psi)]])
    p_uav = -(rot @ c_b)  # the AGV (origin) = p_uav + R(psi) c_b
    z = cam.target_top_z_m - h
    return Start(uav_pose=(float(p_uav[0]), float(p_uav[1]), z, 0.0, 0.0, psi), height_m=h,
                 yaw_error_rad=e, centroid_px=(float(c_px[0]), float(c_px[1])),
                 max_corner_px=worst)


@dataclass(frozen=True)
class RunSpec:
    """One flight of the matrix: everything a worker needs (picklable, plain values)."""

    run_id: str
    controller: str
    scenario: str
    seed: int
    config: str  # base config file
    duration_s: float
    overrides: tuple[str, ...]
    out_dir: str
    start: Start
    path: str
    speed_scale: float
    nominal_peak_speed_m_s: float
    nominal_peak_yaw_rate_rad_s: float
    keep_log: bool = False


@dataclass(frozen=True)
class Campaign:
    source: str
    config: Path
    duration_s: float
    seeds: int
    start: StartDistribution
    controllers: tuple[Controller, ...]
    scenarios: tuple[Scenario, ...]
    set: tuple[str, ...] = field(default=())

    def camera(self) -> Camera:
        from companion.config import config_from_dict, read_document
        from companion.config_file import merged_document

        doc = merged_document(read_document(self.config), self.set)
        cfg = config_from_dict(doc, source=str(self.config))
        top_z = doc.get("sim", {}).get("agv", {}).get("top_z_m", 0.0)
        if isinstance(top_z, bool) or not isinstance(top_z, (int, float)):
            raise ConfigError(f"{self.config}: sim.agv.top_z_m: must be a number")
        return Camera(cfg.camera.focal_length_m, cfg.camera.report_pixel_size_m,
                      cfg.camera.visible_bound_report_px, cfg.target.length_m,
                      cfg.target.width_m, float(top_z))

    def runs(self, out: Path, seeds: Sequence[int] | None = None,
             controllers: Sequence[str] | None = None, scenarios: Sequence[str] | None = None,
             duration_s: float | None = None, keep_logs: bool = False) -> list[RunSpec]:
        """The matrix (controller-major within each scenario and seed), optionally narrowed."""
        cam = self.camera()
        seeds = list(range(self.seeds)) if seeds is None else list(seeds)
        ctrls = _pick(self.controllers, controllers, "controller")
        scens = _pick(self.scenarios, scenarios, "scenario")
        dur = self.duration_s if duration_s is None else duration_s
        out_runs = []
        for seed in seeds:
            for sc in scens:
                start = sample_start(self.start, cam, sc.path, sc.name, seed)
                for ct in ctrls:
                    run_id = f"{sc.name}__{ct.name}__s{seed}"
                    ov = (*self.set, *sc.overrides(), *start.overrides(), f"sim.seed={seed}",
                          *ct.set)
                    out_runs.append(RunSpec(
                        run_id=run_id, controller=ct.name, scenario=sc.name, seed=seed,
                        config=str(self.config), duration_s=dur, overrides=tuple(ov),
                        out_dir=str(out / "runs" / run_id), start=start, path=sc.path,
                        speed_scale=sc.speed_scale,
                        nominal_peak_speed_m_s=sc.peak_speed_m_s,
                        nominal_peak_yaw_rate_rad_s=sc.peak_yaw_rate_rad_s,
                        keep_log=keep_logs))
        return out_runs


def _pick(items: Sequence[Any], names: Sequence[str] | None, what: str) -> list[Any]:
    if names is None:
        return list(items)
    have = {i.name: i for i in items}
    bad = [n for n in names if n not in have]
    if bad:
        raise ConfigError(f"--{what}s: unknown {what}(s) {', '.join(bad)} "
                          f"(have: {', '.join(have)})")
    return [have[n] for n in names]


# ---------------------------------------------------------------------------------------------
# Loading


def _strs(v: Any, key: str) -> tuple[str, ...]:
    if not isinstance(v, list) or not all(isinstance(x, str) for x in v):
        raise ConfigError(f"{key}: must be a list of 'key=value' strings")
    return tuple(v)


def _pair(v: Any, key: str) -> tuple[float, float]:
    if (not isinstance(v, list) or len(v) != 2
            or not all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in v)):
        raise ConfigError(f"{key}: must be [low, high]")
    return float(v[0]), float(v[1])


def _names(items: Sequence[Mapping[str, Any]], key: str) -> None:
    seen: set[str] = set()
    for i, it in enumerate(items):
        n = it.get("name")
        if not isinstance(n, str) or not n or not all(c.isalnum() or c in "-_." for c in n):
            raise ConfigError(f"{key}[{i}].name: a non-empty name of letters, digits, - _ .")
        if n in seen:
            raise ConfigError(f"{key}[{i}].name: {n!r} appears twice")
        seen.add(n)


def load_campaign(path: str | Path | None = None) -> Campaign:
    """Read and validate a campaign file (default ``config/campaigns/default.toml``)."""
    p = Path(path) if path is not None else DEFAULT_CAMPAIGN
    try:
        doc = tomllib.loads(p.read_text())
    except OSError as exc:
        raise ConfigError(f"{p}: cannot read campaign file ({exc.strerror})") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{p}: not valid TOML: {exc}") from None
    known = {"config", "duration_s", "seeds", "set", "start", "controllers", "scenarios"}
    unknown = sorted(set(doc) - known)
    if unknown:
        raise ConfigError(f"{p}: unknown key(s) {', '.join(unknown)}")
    cfg = p.parent / str(doc.get("config", "../paper.toml"))
    dur = doc.get("duration_s", 30.0)
    if isinstance(dur, bool) or not isinstance(dur, (int, float)) or not dur > 0:
        raise ConfigError("duration_s: must be a number > 0")
    seeds = doc.get("seeds", 1)
    if isinstance(seeds, bool) or not isinstance(seeds, int) or seeds < 1:
        raise ConfigError("seeds: must be an integer >= 1")
    st = doc.get("start", {})
    if not isinstance(st, dict) or set(st) - {"height_m", "yaw_error_rad", "edge_fraction",
                                               "max_corner_fraction"}:
        raise ConfigError("start: a table of height_m, yaw_error_rad, edge_fraction, "
                          "max_corner_fraction")
    kw: dict[str, Any] = {}
    for k, v in st.items():
        if k == "max_corner_fraction":
            if isinstance(v, bool) or not isinstance(v, (int, float)):
                raise ConfigError("start.max_corner_fraction: must be a number")
            kw[k] = float(v)
        else:
            kw[k] = _pair(v, f"start.{k}")
    start = StartDistribution(**kw)
    ctrl_t, scen_t = doc.get("controllers"), doc.get("scenarios")
    if not isinstance(ctrl_t, list) or not ctrl_t:
        raise ConfigError("controllers: at least one [[controllers]] table")
    if not isinstance(scen_t, list) or not scen_t:
        raise ConfigError("scenarios: at least one [[scenarios]] table")
    _names(ctrl_t, "controllers")
    _names(scen_t, "scenarios")
    ctrls = []
    for i, c in enumerate(ctrl_t):
        if set(c) - {"name", "set"}:
            raise ConfigError(f"controllers[{i}]: only name and set")
        ctrls.append(Controller(c["name"], _strs(c.get("set", []), f"controllers[{i}].set")))
    scens = []
    for i, s in enumerate(scen_t):
        if set(s) - {"name", "path", "speed_scale", "set"}:
            raise ConfigError(f"scenarios[{i}]: only name, path, speed_scale and set")
        if s.get("path") not in PATHS:
            raise ConfigError(f"scenarios[{i}].path: one of {', '.join(PATHS)}")
        sc = s.get("speed_scale", 1.0)
        if isinstance(sc, bool) or not isinstance(sc, (int, float)) or not 0 < sc <= 100:
            raise ConfigError(f"scenarios[{i}].speed_scale: a number in (0, 100]")
        scens.append(Scenario(s["name"], s["path"], float(sc),
                              _strs(s.get("set", []), f"scenarios[{i}].set")))
    return Campaign(source=str(p), config=cfg.resolve(), duration_s=float(dur), seeds=seeds,
                    start=start, controllers=tuple(ctrls), scenarios=tuple(scens),
                    set=_strs(doc.get("set", []), "set"))
