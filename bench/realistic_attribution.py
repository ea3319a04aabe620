"""Which imperfection of the realistic world leaves the residual error (issue 12)?

Flies ``config/realistic.toml`` (companion and emulator both read it, so the lens calibration
stays shared) in lockstep, once as it is and then with ONE imperfection at a time switched back
to ideal, and scores each flight from the emulator's ground truth: RMS horizontal and height
error after settling, and their split into a steady part (the mean of the error in the vehicle's
virtual frame: along / across the heading, height) and a fluctuating part (the std about it).
A variant that removes most of the residual names what dominates it; the ``only-*`` variants
fly the paper world (``config/paper.toml`` + the PX4 cascade) with just that imperfection on.

    python bench/realistic_attribution.py [--scenario paper] [--duration 60] [--only a,b]
        [--extra KEY=VALUE ...]      (companion/emulator override on every flight)

Lockstep: the figures are simulated-time figures and do not depend on the machine's load (the
emulator waits up to 10 s of wall time per step); the load and the CPU are printed anyway.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from companion import CompanionError  # noqa: E402
from companion.config import load_config  # noqa: E402
from companion.flight import run_demo  # noqa: E402
from companion.log.reader import LogReader  # noqa: E402
from companion.report.figures import true_features  # noqa: E402
from companion.report.files import build_report  # noqa: E402

REALISTIC = ROOT / "config" / "realistic.toml"
PAPER = ROOT / "config" / "paper.toml"
PATIENT = ["sim.lockstep_timeout_s=10.0"]
IDEAL_CAMERA_NOISE = ["sim.camera_model.exposure_ms=0.0", "sim.camera_model.read_noise_std_dn=0.0",
                      "sim.camera_model.shot_noise_dn_per_e=0.0",
                      "sim.camera_model.brightness_drift_std=0.0"]

# name -> (config, overrides): one imperfection back to ideal
VARIANTS: dict[str, tuple[Path, list[str]]] = {
    "realistic": (REALISTIC, []),
    "no-turbulence": (REALISTIC, ["sim.disturbance.turbulence_std_m_s2=0.0"]),
    "no-wind": (REALISTIC, ["sim.disturbance.wind_accel_ned_m_s2=[0.0, 0.0, 0.0]"]),
    "ideal-camera": (REALISTIC, ['sim.camera_model.level="ideal"']),
    "no-camera-latency": (REALISTIC, ["sim.camera_model.latency_ms=0.0",
                                      "sim.camera_model.latency_jitter_ms=0.0"]),
    "no-camera-noise-blur": (REALISTIC, IDEAL_CAMERA_NOISE),
    "ideal-lens": (REALISTIC, ['camera.calibration_file=""']),
    "ideal-telemetry": (REALISTIC, ['sim.telemetry.level="ideal"']),
    "no-battery-sag": (REALISTIC, ['sim.battery.level="ideal"']),
    "ideal-vehicle": (REALISTIC, ['sim.vehicle.level="ideal"']),
    "first-order": (REALISTIC, ['sim.vehicle.attitude_model="first-order"']),
    "no-turb-no-camera": (REALISTIC, ["sim.disturbance.turbulence_std_m_s2=0.0",
                                      'sim.camera_model.level="ideal"']),
    "only-turbulence": (PAPER, ['sim.vehicle.attitude_model="px4"',
                                "sim.disturbance.turbulence_std_m_s2=0.05",
                                "sim.disturbance.turbulence_tau_s=2.0"]),
    "paper-px4": (PAPER, ['sim.vehicle.attitude_model="px4"']),
}


def fly(out: Path, config: Path, scenario: str, duration: float,
        overrides: list[str]) -> tuple[dict[str, Any], float]:
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.monotonic()
    try:
        rep = run_demo(config, scenario, duration, out, PATIENT + overrides, [], plots=False)
    except CompanionError as exc:
        rep = build_report(out / "flight.mcap", load_config(config, overrides), out, plots=False)
        rep["error"] = str(exc)
    return rep, time.monotonic() - t0


def split(log: Path, settle_s: float | None, z_star: float = 2.0) -> dict[str, Any]:
    """Mean (steady) and std (fluctuating) of the error after settling, in the virtual frame
    (along, across the vehicle's heading; height), mm; and the estimator's last hover thrust."""
    rows, est = [], None
    with LogReader(log) as r:
        for m in r.messages(topics=["/truth", "/control/step"]):
            if not m.data:
                continue
            if m.topic == "/control/step":
                est = m.data.get("estimator") or est
                continue
            se = true_features(m.data, z_star)
            if se is not None:
                t = m.data.get("sim_t_s")
                t = m.data["t_us"] * 1e-6 if t is None else t
                rows.append((t, se[0] * z_star, se[1] * z_star, se[2] * z_star))
    if not rows or settle_s is None:
        return {}
    a = np.array(rows)
    a = a[a[:, 0] >= settle_s]
    if a.size == 0:
        return {}
    mean = 1e3 * a[:, 1:].mean(axis=0)
    std = 1e3 * a[:, 1:].std(axis=0)
    return {"mean_along_across_height_mm": [round(float(v), 1) for v in mean],
            "std_along_across_height_mm": [round(float(v), 1) for v in std],
            "hover_thrust_est_end": None if est is None else est.get("hover_thrust")}


def _mm_of(trk: dict[str, Any]) -> Any:
    def mm(k: str) -> float | None:
        v = trk.get(k)
        return None if v is None else round(1e3 * v, 1)
    return mm


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scenario", default="paper")
    ap.add_argument("--duration", type=float, default=60.0)
    ap.add_argument("--only", default=",".join(VARIANTS))
    ap.add_argument("--extra", action="append", default=[],
                    help="override applied to every flight (e.g. a companion setting)")
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()
    tmp = args.out or Path(tempfile.mkdtemp(prefix="attribution-"))
    res: dict[str, Any] = {"scenario": args.scenario, "duration_s": args.duration,
                           "extra": args.extra, "load_start": os.getloadavg()[0]}
    print(f"attribution: {args.scenario}, {args.duration:.0f} s, extra {args.extra}, "
          f"load {os.getloadavg()[0]:.2f}, out {tmp}", flush=True)
    for name in args.only.split(","):
        config, ov = VARIANTS[name]
        c0 = resource.getrusage(resource.RUSAGE_CHILDREN)
        rep, wall = fly(tmp / name, config, args.scenario, args.duration, ov + args.extra)
        c1 = resource.getrusage(resource.RUSAGE_CHILDREN)
        cpu = (c1.ru_utime + c1.ru_stime) - (c0.ru_utime + c0.ru_stime)
        trk, vis, sol = rep["tracking"], rep["visibility"], rep["solver"]
        settle = trk.get("settle_time_s")
        sp = split(tmp / name / "flight.mcap", settle)

        mm = _mm_of(trk)
        row = {"settle_s": settle, "rms_h_mm": mm("rms_horizontal_error_after_settle_m"),
               "rms_z_mm": mm("rms_height_error_after_settle_m"),
               "peak_px": round(max(vis["max_abs_u_px"], vis["max_abs_n_px"])),
               "lost": vis["frames_target_lost"], "failures": sol["failures"],
               "fallbacks": sol["fallbacks"], "wall_s": round(wall, 1),
               "cpu_s_both_processes": round(cpu, 1), "load": round(os.getloadavg()[0], 2),
               "error": rep.get("error"), **sp}
        res[name] = row
        print(f"{name:22s} settle {settle} s  RMS h/z {row['rms_h_mm']} / {row['rms_z_mm']} mm"
              f"  mean(along,across,z) {sp.get('mean_along_across_height_mm')}  std "
              f"{sp.get('std_along_across_height_mm')}  peak {row['peak_px']} px lost "
              f"{row['lost']} fail {row['failures']}  [{wall:.0f} s wall, {cpu:.0f} s CPU, "
              f"load {row['load']}]", flush=True)
        if args.json:
            args.json.write_text(json.dumps(res, indent=2, default=str))
    if args.json:
        args.json.write_text(json.dumps(res, indent=2, default=str))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
