"""How much of the realistic world's residual can a disturbance estimate remove at all?

The realistic variant's turbulence (``[sim.disturbance] level = "realistic"``: a Gauss-Markov
acceleration, std 0.05 m/s^2 north/east and 0.025 down, correlation 2 s, a new random step
every 50 ms) is flown here in a linear closed loop with the same parts the companion uses, and
nothing else:

- the error dynamics of spec 4 (``companion.core.dynamics.error_dynamics``, target at rest,
  yaw fixed), integrated at the emulator's 2.5 ms physics step;
- the controller: the paper's terminal gain ``K`` (``design_terminal``: the LQR of the paper's
  ``q_diag``/``r_diag`` at 20 Hz, what the RMPC reduces to when no constraint is active),
  applied at 20 Hz with a zero-order hold;
- the attitude loop as a first-order lag of the realised acceleration (``--tau``: 0.1 s gives
  PX4's 215 ms 10-90 % roll-step rise, docs/reference/emulator.md);
- the compensation ``u - d_hat`` with ``d_hat`` from: nothing; the companion's own estimator
  (``DisturbanceEstimator``, fed at 30 Hz with the true velocity, the thrust and the realised
  body axis, as in flight); or an oracle that knows the true disturbance at the control instant
  (the best any estimate can do); and the oracle without the attitude lag;
- with ``accelerometer``: the estimator also fed, at 50 Hz (PX4's HIGHRES_IMU on an onboard
  link), the horizontal specific force in body axes as a biased, noisy accelerometer reads it
  (``--accel-noise``, ``--accel-bias``; the realistic world's 0.35 m/s^2 and (0.1, -0.08)).

The turbulence is the emulator's own generator (``sim_bridge.physics.vehicle.Disturbance``,
same seed). RMS horizontal and height position errors over ``--duration`` s.

    python bench/turbulence_bound.py [--duration 600] [--tau 0.1] [--config config/realistic.toml]
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from companion.config import load_config  # noqa: E402
from companion.core.design import design_terminal  # noqa: E402
from companion.core.disturbance import DisturbanceEstimator, EstimatorParams  # noqa: E402
from companion.core.dynamics import error_dynamics  # noqa: E402
from sim_bridge.physics.vehicle import Disturbance, DisturbanceParams  # noqa: E402

G = 9.81
H = 0.5


def _rot_from_body_z(bz: np.ndarray) -> np.ndarray:
    """Body -> NED rotation at yaw 0 whose third column is the unit vector ``bz``."""
    ez = np.array([0.0, 0.0, 1.0])
    c = float(ez @ bz)
    ax = np.cross(ez, bz)
    s = float(np.linalg.norm(ax))
    if s < 1e-12:
        return np.eye(3)
    kx = np.array([[0.0, -ax[2], ax[1]], [ax[2], 0.0, -ax[0]], [-ax[1], ax[0], 0.0]]) / s
    return np.eye(3) + s * kx + (1.0 - c) * kx @ kx


def fly(mode: str, duration: float, tau: float, seed: int, std: float, corr: float,
        est_params: EstimatorParams | None = None, vel_noise: float = 0.0,
        score_from_s: float = 20.0, accel_noise: float = 0.35,
        accel_bias: tuple[float, float] = (0.1, -0.08),
        config: Path | None = None) -> dict[str, float]:
    cfg = load_config(config)
    k = design_terminal(cfg.rmpc, cfg.camera).k
    z = cfg.rmpc.desired_depth_m
    umax = np.asarray(cfg.rmpc.u_max, dtype=float)
    dist = Disturbance(DisturbanceParams(seed=seed, turbulence_std_m_s2=std,
                                         turbulence_tau_s=corr))
    est = DisturbanceEstimator(est_params or EstimatorParams(), H)
    rng = np.random.default_rng(seed)
    dt, ctrl_every, est_every = 0.0025, 20, 13  # 400 Hz physics, 20 Hz control, ~30 Hz telemetry
    imu_every = 8  # 50 Hz HIGHRES_IMU
    use_imu = est.params.accelerometer
    bias = np.asarray(accel_bias, dtype=float)
    eta = np.zeros(7)
    tb_cmd = np.array([0.0, 0.0, H])  # thrust x body z axis (NED) commanded ...
    tb = tb_cmd.copy()  # ... and flown (the attitude loop's lag)
    d_hat = np.zeros(3)
    h_hat = H
    n = int(duration / dt)
    err_h, err_z = [], []
    for i in range(n):
        t = i * dt
        d = np.asarray(dist.accel_ned_m_s2(t), dtype=float)
        if use_imu and i % imu_every == 0 and i % est_every != 0 and mode == "estimator":
            thrust = float(np.linalg.norm(tb))
            rot = _rot_from_body_z(tb / thrust)
            f_body = rot.T @ (-G / H * tb + d)
            meas = f_body[:2] + bias + rng.normal(0.0, accel_noise, 2)
            est.update_accel(t, meas, thrust, tb / thrust, rot)
        if i % est_every == 0 and mode == "estimator":
            thrust = float(np.linalg.norm(tb))
            v = eta[4:7] + (rng.normal(0.0, vel_noise, 3) if vel_noise else 0.0)
            est.update(t, v, thrust, tb / thrust)
        if i % ctrl_every == 0:
            if mode == "estimator":
                e = est.estimate()
                d_hat, h_hat = np.array(e.d_ned_m_s2), e.hover_thrust
            elif mode.startswith("oracle"):
                d_hat = d.copy()
            u = np.clip(k @ eta, -umax, umax)
            f = u[:3] - d_hat - np.array([0.0, 0.0, G])  # specific force asked for (spec 5)
            tb_cmd = -h_hat * f / G
        tb = tb_cmd.copy() if mode == "oracle-no-lag" else tb + dt / tau * (tb_cmd - tb)
        # PX4's thrust mapping with the true hover thrust, plus the true disturbance (virtual
        # frame = NED at yaw 0; eta's velocity part is the vehicle's for a target at rest)
        a = np.array([0.0, 0.0, G]) - G / H * tb + d
        acc = np.concatenate([a, [0.0]])
        eta = eta + dt * np.asarray(error_dynamics(eta, acc, np.zeros(2), np.zeros(2), 0.0, z))
        if t >= score_from_s:  # after the start-up of the estimator
            err_h.append(z * math.hypot(eta[0], eta[1]))
            err_z.append(z * eta[2])
    return {"rms_h_mm": 1e3 * float(np.sqrt(np.mean(np.square(err_h)))),
            "rms_z_mm": 1e3 * float(np.sqrt(np.mean(np.square(err_z))))}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--duration", type=float, default=600.0)
    ap.add_argument("--tau", type=float, default=0.1, help="attitude-loop lag (s)")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--std", type=float, default=0.05, help="turbulence std (m/s^2)")
    ap.add_argument("--corr", type=float, default=2.0, help="turbulence correlation (s)")
    ap.add_argument("--score-from", type=float, default=20.0,
                    help="score from this time (s); with --duration 60 the same turbulence "
                    "as the 60 s flight's 20-60 s (same seed, same generator)")
    ap.add_argument("--only", default="", help="comma-separated case numbers (0-10)")
    ap.add_argument("--config", type=Path, default=None,
                    help="the companion's config whose weights give K (default: the paper's; "
                    "config/realistic.toml: the stiffer tuning, "
                    "docs/records/2026-11-offset-free.md section 4)")
    ap.add_argument("--accel-noise", type=float, default=0.35,
                    help="accelerometer white noise per 50 Hz sample (m/s^2)")
    ap.add_argument("--accel-rw", type=float, default=1.0,
                    help="the estimator's disturbance random walk with the accelerometer")
    args = ap.parse_args()
    c0 = time.process_time()
    print(f"turbulence std {args.std} m/s^2, correlation {args.corr} s, attitude lag "
          f"{args.tau} s, {args.duration:.0f} s, "
          f"terminal gain K of {args.config or 'the paper weights'}")
    cases: list[tuple[str, str, EstimatorParams | None, float]] = [
        ("no compensation", "none", None, 0.0),
        ("companion's estimator (defaults)", "estimator", None, 0.0),
        ("estimator, d random walk 1.0", "estimator",
         EstimatorParams(disturbance_noise_m_s2_sqrt_s=1.0), 0.0),
        ("estimator, d random walk 1.0, 0.02 m/s velocity noise", "estimator",
         EstimatorParams(disturbance_noise_m_s2_sqrt_s=1.0), 0.02),
        ("estimator (defaults), 0.02 m/s velocity noise", "estimator", None, 0.02),
        ("oracle d (true disturbance at each control step)", "oracle", None, 0.0),
        ("oracle d, no attitude lag", "oracle-no-lag", None, 0.0),
        ("accelerometer, d random walk 0.3", "estimator",
         EstimatorParams(accelerometer=True, accel_noise_m_s2=args.accel_noise), 0.0),
        (f"accelerometer, d random walk {args.accel_rw}", "estimator",
         EstimatorParams(accelerometer=True, accel_noise_m_s2=args.accel_noise,
                         accel_disturbance_noise_m_s2_sqrt_s=args.accel_rw), 0.0),
        (f"accelerometer, d random walk {args.accel_rw}, 0.02 m/s velocity noise",
         "estimator",
         EstimatorParams(accelerometer=True, accel_noise_m_s2=args.accel_noise,
                         accel_disturbance_noise_m_s2_sqrt_s=args.accel_rw), 0.02),
        ("accelerometer, d random walk 0.3, 0.02 m/s velocity noise", "estimator",
         EstimatorParams(accelerometer=True, accel_noise_m_s2=args.accel_noise), 0.02),
    ]
    pick = {int(x) for x in args.only.split(",") if x}
    for i, (name, mode, ep, vn) in enumerate(cases):
        if pick and i not in pick:
            continue
        r = fly(mode, args.duration, args.tau, args.seed, args.std, args.corr, ep, vn,
                args.score_from, args.accel_noise, config=args.config)
        print(f"{name:58s} RMS horizontal {r['rms_h_mm']:6.1f} mm, height {r['rms_z_mm']:6.1f} mm",
              flush=True)
    print(f"CPU {time.process_time() - c0:.1f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
