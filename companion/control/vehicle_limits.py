"""The vehicle's limits from the autopilot, and the controller's bounds built from them.

On connect the companion reads the PX4 parameters that bound what it may ask of the vehicle
(:data:`PARAM_NAMES`, over :class:`companion.link.params.ParamReader`), logs them (every
PARAM_VALUE on ``/mavlink/in/PARAM_VALUE`` like any message, plus one record on
``/control/vehicle_limits`` and a line on ``/control/safety``), reports every configured bound
beyond them, and, with ``[vehicle_limits] from_autopilot = true``, replaces the controller's
bounds by the autopilot's less a margin before the controller is built
(docs/guides/vehicle-limits.md):

====================  ==========================================================================
``rmpc.eta_max[4:6]`` ``(1 - margin) MPC_XY_VEL_MAX`` (horizontal velocity, m/s)
``rmpc.eta_max[6]``   ``(1 - margin) min(MPC_Z_VEL_MAX_UP, MPC_Z_VEL_MAX_DN)``
``rmpc.u_max[0:2]``   ``(1 - margin) min(MPC_ACC_HOR, g tan MPC_TILTMAX_AIR)`` (m/s^2)
``rmpc.u_max[2]``     ``(1 - margin) min(MPC_ACC_UP_MAX, MPC_ACC_DOWN_MAX)``
``rmpc.u_max[3]``     ``(1 - margin) min(MC_YAWRATE_MAX, MPC_YAWRAUTO_MAX)`` (rad/s)
``control.hover_thrust`` ``MPC_THR_HOVER`` (no margin: it is an estimate, not a bound)
====================  ==========================================================================

A parameter the autopilot does not answer for leaves its bound as configured (reported).
This module is pure except :class:`VehicleLimitsStage`, the runtime's glue.
"""

from __future__ import annotations

import asyncio
import dataclasses
import logging
import math
import time
from collections.abc import Callable, Mapping
from typing import Any

from companion.config import Config
from companion.control.faults import check_faults
from companion.control.solver_server import start_server
from companion.link.params import ParamReader, ParamReadResult
from companion.log import schemas as sch

__all__ = ["PARAM_NAMES", "VehicleLimitsStage", "adopt_vehicle_limits", "apply_limits",
           "refused_bounds"]

log = logging.getLogger(__name__)

PARAM_NAMES: tuple[str, ...] = (
    "MPC_XY_VEL_MAX", "MPC_Z_VEL_MAX_UP", "MPC_Z_VEL_MAX_DN", "MPC_ACC_HOR", "MPC_ACC_HOR_MAX",
    "MPC_ACC_UP_MAX", "MPC_ACC_DOWN_MAX", "MPC_TILTMAX_AIR", "MC_YAWRATE_MAX",
    "MPC_YAWRAUTO_MAX", "MPC_THR_HOVER",
)
TOPIC_VEHICLE_LIMITS = "/control/vehicle_limits"


def _p(values: Mapping[str, float], name: str) -> float | None:
    v = values.get(name)
    return None if v is None or not math.isfinite(v) else float(v)


def _min(*xs: float | None) -> float | None:
    have = [x for x in xs if x is not None]
    return min(have) if have else None


def autopilot_bounds(values: Mapping[str, float], g: float) -> dict[str, float | None]:
    """What the autopilot allows (SI units; None: not known): horizontal and vertical
    velocity, horizontal and vertical acceleration, yaw rate, tilt."""
    tilt = _p(values, "MPC_TILTMAX_AIR")
    yaw = _min(_p(values, "MC_YAWRATE_MAX"), _p(values, "MPC_YAWRAUTO_MAX"))
    return {
        "v_xy_m_s": _p(values, "MPC_XY_VEL_MAX"),
        "v_z_m_s": _min(_p(values, "MPC_Z_VEL_MAX_UP"), _p(values, "MPC_Z_VEL_MAX_DN")),
        "a_xy_m_s2": _min(_p(values, "MPC_ACC_HOR"),
                          None if tilt is None else g * math.tan(math.radians(tilt))),
        "a_z_m_s2": _min(_p(values, "MPC_ACC_UP_MAX"), _p(values, "MPC_ACC_DOWN_MAX")),
        "yaw_rate_rad_s": None if yaw is None else math.radians(yaw),
        "tilt_rad": None if tilt is None else math.radians(tilt),
    }


def commanded_tilt_rad(u_max: tuple[float, ...], g: float) -> float:
    """The largest tilt inputs within ``u_max`` command: both horizontal axes at their bound
    with the least thrust allowed (``g - u_max[2]``)."""
    return math.atan2(math.hypot(u_max[0], u_max[1]), g - u_max[2])


def refused_bounds(cfg: Config, values: Mapping[str, float]) -> list[str]:
    """Every configured bound beyond what the autopilot allows, one line each naming the key."""
    r, g = cfg.rmpc, cfg.rmpc.g_m_s2
    ap = autopilot_bounds(values, g)
    out: list[str] = []

    def beyond(key: str, have: float, limit: float | None, what: str, unit: str) -> None:
        if limit is not None and have > limit + 1e-9:
            out.append(f"{key} = {have:g} {unit} is beyond the autopilot's {what} "
                       f"({limit:.3g} {unit})")

    for i in (4, 5):
        beyond(f"rmpc.eta_max[{i}]", r.eta_max[i], ap["v_xy_m_s"], "MPC_XY_VEL_MAX", "m/s")
    beyond("rmpc.eta_max[6]", r.eta_max[6], ap["v_z_m_s"],
           "min(MPC_Z_VEL_MAX_UP, MPC_Z_VEL_MAX_DN)", "m/s")
    for i in (0, 1):
        beyond(f"rmpc.u_max[{i}]", r.u_max[i], ap["a_xy_m_s2"],
               "min(MPC_ACC_HOR, g tan MPC_TILTMAX_AIR)", "m/s^2")
    beyond("rmpc.u_max[2]", r.u_max[2], ap["a_z_m_s2"],
           "min(MPC_ACC_UP_MAX, MPC_ACC_DOWN_MAX)", "m/s^2")
    beyond("rmpc.u_max[3]", r.u_max[3], ap["yaw_rate_rad_s"],
           "min(MC_YAWRATE_MAX, MPC_YAWRAUTO_MAX)", "rad/s")
    tilt = ap["tilt_rad"]
    if tilt is not None and commanded_tilt_rad(r.u_max, g) > tilt + 1e-9:
        out.append(f"rmpc.u_max = {list(r.u_max)} commands a tilt of "
                   f"{math.degrees(commanded_tilt_rad(r.u_max, g)):.1f} deg, beyond the "
                   f"autopilot's MPC_TILTMAX_AIR ({math.degrees(tilt):.1f} deg)")
    return out


def apply_limits(cfg: Config, values: Mapping[str, float]) -> tuple[Config, list[str]]:
    """``cfg`` with its bounds built from the autopilot's ``values`` (module docstring), and
    the config overrides that express the change (``rmpc.u_max=[...]``: logged, and what a
    replay applies). A bound whose parameters are missing keeps its configured value."""
    r, k = cfg.rmpc, 1.0 - cfg.vehicle_limits.margin
    ap = autopilot_bounds(values, r.g_m_s2)

    def scaled(name: str, have: float) -> float:
        # rounded: the compiled solver is keyed by these numbers, and a float32 parameter
        # (34.377 deg arrives as 34.37699890...) must not make a new vehicle of the same one
        v = ap[name]
        return have if v is None else round(k * v, 3)

    eta = list(r.eta_max)
    eta[4] = scaled("v_xy_m_s", eta[4])
    eta[5] = scaled("v_xy_m_s", eta[5])
    eta[6] = scaled("v_z_m_s", eta[6])
    u = [scaled("a_xy_m_s2", r.u_max[0]), scaled("a_xy_m_s2", r.u_max[1]),
         scaled("a_z_m_s2", r.u_max[2]), scaled("yaw_rate_rad_s", r.u_max[3])]
    hover = _p(values, "MPC_THR_HOVER")
    overrides = [f"rmpc.eta_max={eta!r}", f"rmpc.u_max={u!r}"]
    control = cfg.control
    if hover is not None:
        control = dataclasses.replace(control, hover_thrust=hover)
        overrides.append(f"control.hover_thrust={hover!r}")
    rmpc = dataclasses.replace(r, eta_max=tuple(eta), u_max=tuple(u))  # type: ignore[arg-type]
    return dataclasses.replace(cfg, rmpc=rmpc, control=control), overrides


class VehicleLimitsStage:
    """The runtime's glue: feed it every PARAM_VALUE (:meth:`on_param_value`), then
    ``await run(link, ...)`` once connected; it returns the config to fly."""

    def __init__(self, cfg: Config) -> None:
        self.cfg = cfg
        self.reader: ParamReader | None = None
        self.result: ParamReadResult | None = None
        self.overrides: list[str] = []
        self.task: asyncio.Task[Config] | None = None  # the background read (not from_autopilot)

    def on_param_value(self, fields: Mapping[str, Any], src_sysid: int, src_compid: int) -> None:
        if self.reader is not None:
            self.reader.on_param_value(fields, src_sysid, src_compid)

    async def run(self, link: Any, text: Callable[[str, str], None],
                  record: Callable[[dict[str, Any]], None],
                  peer_timeout_s: float = 60.0) -> Config:
        """Read, log (``text(level, line)``, ``record(payload)``), check, and (when asked)
        build the bounds. Returns the config to fly (``cfg`` itself unless from_autopilot).
        ``peer_timeout_s``: how long to wait for the autopilot to be heard at all."""
        vl, cfg = self.cfg.vehicle_limits, self.cfg
        self.reader = ParamReader(link, cfg.mavlink.target_system, cfg.mavlink.target_component)
        res = await self.reader.read(PARAM_NAMES, vl.read_timeout_s, vl.read_retries,
                                     peer_timeout_s=peer_timeout_s)
        self.result = res
        values = {n: p.value for n, p in res.values.items()}
        got = ", ".join(f"{n}={v:g}" for n, v in values.items())
        text("INFO", f"vehicle limits read from the autopilot ({res.requests_sent} requests, "
                     f"{res.elapsed_s:.2f} s): {got or 'none'}")
        if res.missing:
            text("WARNING", f"vehicle limits: no answer for {', '.join(res.missing)} after "
                            f"{vl.read_retries} tries in {res.elapsed_s:.1f} s (the first "
                            f"waiting {vl.read_timeout_s} s, each retry twice the one before; "
                            f"their bounds stay as configured)")
        out = cfg
        if vl.from_autopilot and not values:
            text("WARNING", "vehicle limits: from_autopilot asked, nothing read: the controller "
                            "flies the configured rmpc.eta_max / rmpc.u_max")
        if vl.from_autopilot and values:
            out, self.overrides = apply_limits(cfg, values)
            text("INFO", f"controller bounds from the autopilot less {vl.margin:.0%}: "
                         f"rmpc.eta_max = {_fmt(out.rmpc.eta_max)}, rmpc.u_max = "
                         f"{_fmt(out.rmpc.u_max)}, control.hover_thrust = "
                         f"{out.control.hover_thrust:g}")
        refused = refused_bounds(out, values)
        for line in refused:
            text("WARNING", f"configured bound refused by the autopilot: {line}")
        record({"params": values, "missing": list(res.missing),
                "requests_sent": res.requests_sent, "elapsed_s": res.elapsed_s,
                "from_autopilot": vl.from_autopilot, "margin": vl.margin,
                "overrides": self.overrides, "refused": refused,
                "eta_max": list(out.rmpc.eta_max), "u_max": list(out.rmpc.u_max),
                "hover_thrust": out.control.hover_thrust})
        return out


def _fmt(xs: tuple[float, ...]) -> str:
    return "[" + ", ".join(f"{x:.3g}" for x in xs) + "]"


async def adopt_vehicle_limits(app: Any, build: Callable[..., Any]) -> None:
    """The runtime's first control step (``app``: the :class:`CompanionApp`, its link open).
    Without a pipeline yet (``from_autopilot``): read the limits, then build the pipeline from
    the config they give (``build(cfg, timer=...)``, in a thread: a solver compile for a new
    vehicle takes seconds, the link keeps being served meanwhile). With one: read them in the
    background (reported and logged only)."""
    vl = app.cfg.vehicle_limits
    built = getattr(app, "pipeline", None) is not None
    if built and not vl.read:
        return
    records = app._records  # companion/control/recording.py: RuntimeLog

    def text(level: str, line: str) -> None:
        log.log(logging.WARNING if level == "WARNING" else logging.INFO, "%s", line)
        if records is not None:
            records.text("/control/safety", line, level, "vehicle_limits")

    def record(payload: dict[str, Any]) -> None:
        if records is not None:
            logger = records.logger
            records.at(records.clock.now_ns(), lambda t: logger.log(
                TOPIC_VEHICLE_LIMITS, t, payload, schema=sch.JSON))

    wait_s = float(app.startup_timeout_s)  # as long as the first frame may take
    if built:
        app.limits.task = asyncio.create_task(app.limits.run(app._link, text, record, wait_s))
        return
    if app.cfg.rmpc.solve_isolation == "process" and app.cfg.controller.kind != "ibvs-pd":
        start_server()  # (its CasADi import while the limits are read, not after)
    cfg = await app.limits.run(app._link, text, record, wait_s)
    t0 = time.monotonic()
    pipeline = await asyncio.to_thread(build, cfg, timer=time.perf_counter)
    app.cfg = cfg
    set_pipeline(app, pipeline)
    text("INFO", f"controller built for the vehicle's limits in {time.monotonic() - t0:.1f} s "
                 "(a compile on the first flight with new bounds, cached after)")


def set_pipeline(app: Any, pipeline: Any) -> None:
    """The runtime's pipeline, built now or once the limits are read; an injected solver hang
    needs a solver process (``companion.control.faults.check_faults``)."""
    app.pipeline = pipeline
    check_faults(app.faults, pipeline.rmpc)
