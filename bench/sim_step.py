"""Speed of one emulator step's world half: AGV state + a vehicle-pose stub (point-mass
integration of 50 ms at 2.5 ms steps) + render a frame + encode it for the wire.

    python bench/sim_step.py [--steps 1000] [--pattern rectangle|aruco] [--size 1000] [--json]
                             [--level ideal|mild|realistic|harsh] [--lens]
                             [--vehicle stub|first-order|px4|realistic]

``--level`` adds the camera model of that level (``sim.camera_model``: motion blur over the
exposure, sensor noise and brightness drift; latency and drops cost nothing per frame);
``--lens`` renders through ``config/camera-distorted.yaml`` (1000 px only). ``--vehicle``: the
physics stage is a point-mass stub (default, the historical figure) or the emulator's real
vehicle model of ``config/paper.toml`` with ``sim.vehicle.attitude_model`` = first-order or px4
(PX4's cascade, 20 sub-steps of 2.5 ms), or that of ``config/realistic.toml`` (px4 + vehicle
imperfections + turbulence), tracking a pose setpoint that follows the AGV. CPU time per step
(``getrusage``, whole loop) is printed beside the wall figures. ``--cv-threads`` (default 1,
as ``sim-bridge`` runs OpenCV; 0: OpenCV's own pool).

Target (issue "sim_bridge"): median <= 2 ms per step at 1000 x 1000, i.e. >= 25x real time at
the 20 Hz frame rate. Prints median/p95 per stage and for the whole step.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import platform
import resource
import sys
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from sim_bridge.camera import Camera, read_calibration
from sim_bridge.camera.frames import encode_frame
from sim_bridge.camera.sensor import Sensor
from sim_bridge.config import CAMERA_LEVELS, CameraModelConfig, load_config
from sim_bridge.physics.agv import AgvTrajectory
from sim_bridge.physics.vehicle import AttitudeCommand, initial_state
from sim_bridge.vehicle_model import VehicleDynamics, build_vehicle_model

STEP_S = 0.05
PHYSICS_DT_S = 0.0025


def _quat_from_euler(phi: float, theta: float, psi: float) -> np.ndarray:
    cr, sr = math.cos(phi / 2), math.sin(phi / 2)
    cp, sp = math.cos(theta / 2), math.sin(theta / 2)
    cy, sy = math.cos(psi / 2), math.sin(psi / 2)
    return np.array(
        [
            cr * cp * cy + sr * sp * sy,
            sr * cp * cy - cr * sp * sy,
            cr * sp * cy + sr * cp * sy,
            cr * cp * sy - sr * sp * cy,
        ]
    )


def _physics_stub(pos: np.ndarray, vel: np.ndarray, target: np.ndarray) -> None:
    """Point mass pulled towards ``target`` (PD), linear drag, 20 steps of 2.5 ms, in place."""
    for _ in range(round(STEP_S / PHYSICS_DT_S)):
        acc = 2.0 * (target - pos) - 2.5 * vel - 0.05 * vel
        vel += acc * PHYSICS_DT_S
        pos += vel * PHYSICS_DT_S


def _vehicle(kind: str) -> VehicleDynamics | None:
    if kind == "stub":
        return None
    root = Path(__file__).resolve().parent.parent / "config"
    cfg = load_config(root / ("realistic.toml" if kind == "realistic" else "paper.toml"))
    if kind in ("first-order", "px4"):
        veh = dataclasses.replace(cfg.sim.vehicle, attitude_model=kind)
        cfg = dataclasses.replace(cfg, sim=dataclasses.replace(cfg.sim, vehicle=veh))
    return build_vehicle_model(cfg)


def _camera(size: int, pattern: str, lens: bool) -> Camera:
    pixel = 5.04e-6 * 1000 / size  # same field of view at any resolution
    k = d = None
    if lens:
        k, d = read_calibration(Path(__file__).resolve().parent.parent / "config"
                                / "camera-distorted.yaml", size, size)
    return Camera(2.8e-3, pixel, size, size, pattern=pattern, aruco_size_m=0.3,
                  camera_matrix=k, dist_coeffs=d)


def _physics_stage(model: VehicleDynamics | None, hover: float, state: Any, pos: np.ndarray,
                   vel: np.ndarray, agv: Any, t: float) -> tuple[Any, np.ndarray, np.ndarray,
                                                                 np.ndarray, np.ndarray]:
    """One step's physics: the point-mass stub (``pos``/``vel`` in place) or the real model
    tracking a pose above the AGV. Returns (state, pos, vel, q, rates)."""
    if model is None:
        _physics_stub(pos, vel, agv.pos_ned_m + np.array([0.0, 0.0, -2.0]))
        q = _quat_from_euler(0.05 * math.sin(t), -0.05 * math.cos(0.7 * t), agv.yaw_rad)
        rates = np.array([0.3 * math.cos(t), 0.3 * math.sin(0.7 * t), agv.yaw_rate_rad_s])
        return state, pos, vel, q, rates
    # a PD pose tracker above the AGV -> tilt setpoint -> the real model
    err = agv.pos_ned_m + np.array([0.0, 0.0, -2.0]) - state.pos_ned_m
    acc = 1.0 * err - 1.8 * state.vel_ned_m_s
    cy, sy = math.cos(agv.yaw_rad), math.sin(agv.yaw_rad)
    cmd = AttitudeCommand(max(-0.3, min(0.3, (-sy * acc[0] + cy * acc[1]) / 9.81)),
                          max(-0.3, min(0.3, -(cy * acc[0] + sy * acc[1]) / 9.81)),
                          agv.yaw_rad, hover * (1 - acc[2] / 9.81))
    state = model.step(state, cmd, STEP_S)
    return (state, state.pos_ned_m, state.vel_ned_m_s, state.q_wxyz,
            state.rates_frd_rad_s)


@dataclasses.dataclass
class _Measured:
    """What the measuring loop gathers over the steps after the warm-up."""

    stages: dict[str, list[float]]
    total: list[float] = dataclasses.field(default_factory=list)
    physics_cpu_s: float = 0.0
    cpu0: float = 0.0  # getrusage utime at the first measured step
    in_image: int = 0
    n_bytes: int = 0


def _measure(steps: int, cam: Camera, sensor: Sensor, exposure_s: float,
             model: VehicleDynamics | None) -> _Measured:
    """``steps`` emulator steps after 20 warm-up steps, each stage timed (perf_counter)."""
    agv_traj = AgvTrajectory("paper")
    pos = np.array([-0.2, 0.4, -2.0])
    vel = np.zeros(3)
    state = initial_state(pos, yaw_rad=0.39)
    hover = model.true_hover_thrust(0.0) if model is not None else 0.5
    m = _Measured({k: [] for k in ("agv", "physics", "render", "sensor", "encode")})
    for k in range(steps + 20):  # 20 warm-up steps
        t = k * STEP_S
        t0 = time.perf_counter()
        agv = agv_traj.state(t)
        if k == 20:
            m.cpu0 = resource.getrusage(resource.RUSAGE_SELF).ru_utime
        t1 = time.perf_counter()
        c1 = time.process_time()
        state, pos, vel, q, rates = _physics_stage(model, hover, state, pos, vel, agv, t)
        c2 = time.process_time()
        t2 = time.perf_counter()
        frame = cam.render(pos, q, agv, uav_vel_ned_m_s=vel.copy(), uav_rates_frd_rad_s=rates,
                           exposure_s=exposure_s)
        t3 = time.perf_counter()
        image = sensor.apply(frame.image, t)
        t35 = time.perf_counter()
        rec = encode_frame(k, int(t * 1e6), image)
        t4 = time.perf_counter()
        if k < 20:
            continue
        m.physics_cpu_s += c2 - c1
        for name, dt in zip(m.stages, (t1 - t0, t2 - t1, t3 - t2, t35 - t3, t4 - t35),
                            strict=True):
            m.stages[name].append(dt)
        m.total.append(t4 - t0)
        m.in_image += frame.target_in_image
        m.n_bytes = len(rec)
    return m


def _ms(xs: list[float], p: float) -> float:
    return round(float(np.percentile(xs, p)) * 1e3, 4)


def run(steps: int, pattern: str, size: int, level: str = "ideal",
        lens: bool = False, vehicle: str = "stub") -> dict[str, Any]:
    cam = _camera(size, pattern, lens)
    cam_model = CameraModelConfig(level=level, **CAMERA_LEVELS[level])
    sensor = Sensor(cam_model, size, size, seed=1)
    m = _measure(steps, cam, sensor, cam_model.exposure_ms * 1e-3, _vehicle(vehicle))
    cpu_s = resource.getrusage(resource.RUSAGE_SELF).ru_utime - m.cpu0
    med = float(np.median(m.total))
    return {
        "vehicle": vehicle,
        "cpu_ms_per_step": round(cpu_s / steps * 1e3, 4),
        "physics_cpu_ms_per_step": round(m.physics_cpu_s / steps * 1e3, 4),
        "steps": steps,
        "size_px": size,
        "pattern": pattern,
        "level": level,
        "lens": lens,
        "record_bytes": m.n_bytes,
        "target_in_image_fraction": m.in_image / steps,
        "median_ms": _ms(m.total, 50),
        "p95_ms": _ms(m.total, 95),
        "max_ms": _ms(m.total, 100),
        "stages_median_ms": {k: _ms(v, 50) for k, v in m.stages.items()},
        "stages_p95_ms": {k: _ms(v, 95) for k, v in m.stages.items()},
        "frames_per_s": round(1.0 / med, 1),
        "realtime_ratio_at_20hz": round(STEP_S / med, 1),
        "target_median_ms": 2.0,
        "meets_target": med * 1e3 <= 2.0,
        "cv_threads": cv2.getNumThreads(),
        "host": {
            "python": platform.python_version(),
            "cpus": os.cpu_count(),
            "loadavg_1min": round(os.getloadavg()[0], 2),
        },
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--steps", type=int, default=1000)
    ap.add_argument("--pattern", choices=("rectangle", "aruco"), default="rectangle")
    ap.add_argument("--size", type=int, default=1000, help="image side in pixels")
    ap.add_argument("--level", choices=tuple(CAMERA_LEVELS), default="ideal",
                    help="camera model level (sim.camera_model)")
    ap.add_argument("--lens", action="store_true", help="render through the distorted lens")
    ap.add_argument("--vehicle", choices=("stub", "first-order", "px4", "realistic"),
                    default="stub", help="physics stage: stub or the emulator's model")
    ap.add_argument("--cv-threads", type=int, default=1,
                    help="cv2.setNumThreads (default 1, as the emulator runs; 0 = OpenCV's "
                         "default pool)")
    ap.add_argument("--json", action="store_true", help="print one JSON object")
    args = ap.parse_args()
    if args.cv_threads > 0:
        cv2.setNumThreads(args.cv_threads)
    res = run(args.steps, args.pattern, args.size, args.level, args.lens, args.vehicle)
    if args.json:
        print(json.dumps(res))
        return 0
    print(
        f"sim step (AGV + physics stub + render {res['size_px']}^2 {res['pattern']} + sensor + "
        f"encode), vehicle {res['vehicle']}, level {res['level']}"
        f"{', lens' if res['lens'] else ''}, {res['cv_threads']} OpenCV thread(s), "
        f"{res['steps']} steps, load {res['host']['loadavg_1min']}"
    )
    print(
        f"  median {res['median_ms']} ms, p95 {res['p95_ms']} ms, max {res['max_ms']} ms "
        f"(target <= {res['target_median_ms']} ms median: "
        f"{'met' if res['meets_target'] else 'NOT met'})"
    )
    print(f"  CPU (getrusage) {res['cpu_ms_per_step']} ms per step, physics stage "
          f"{res['physics_cpu_ms_per_step']} ms (process_time)")
    for name in res["stages_median_ms"]:
        print(
            f"  {name:8s} median {res['stages_median_ms'][name]:.4f} ms, "
            f"p95 {res['stages_p95_ms'][name]:.4f} ms"
        )
    print(
        f"  {res['frames_per_s']} frames/s, {res['realtime_ratio_at_20hz']}x real time at 20 Hz, "
        f"target in image {res['target_in_image_fraction']:.0%}"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
