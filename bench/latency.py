"""Companion latency and memory over a lockstep flight (issue: the companion process).

    python bench/latency.py [--duration 251] [--scenario paper] [--json]

Flies the scenario (emulator + companion as separate processes, 1000 x 1000 frames), then
reads the companion's own step records from the log:
- frame received -> SET_ATTITUDE_TARGET sent, median / p95 / max, with the stage breakdown
  (decode = receipt -> step start: decoding the frame and waiting for the loop; detect,
  moments, solve, command, send);
- the companion process's resident memory (VmRSS, sampled every 50 ms): peak, and the growth
  from 30 s of flight to the end (flat after warm-up = < 5 %).
Targets: latency median <= 3 ms, p95 <= 6 ms; peak RSS <= 400 MB; growth < 5 %.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from companion.config import DEFAULT_CONFIG  # noqa: E402
from companion.flight import run_demo  # noqa: E402
from companion.log.reader import LogReader  # noqa: E402


def rss_mb(pid: int) -> float | None:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    except OSError:
        return None
    return None


def _window_median(t: np.ndarray, mem: np.ndarray, a_s: float, b_s: float,
                   duration_s: float) -> float | None:
    """Median RSS over flight seconds [a_s, b_s) (wall samples mapped linearly onto the
    flight)."""
    if t.size == 0:
        return None
    frac = (t - t[0]) / max(t[-1] - t[0], 1e-9) * duration_s
    sel = (frac >= a_s) & (frac < b_s)
    return float(np.median(mem[sel])) if np.any(sel) else None


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=251.0)
    ap.add_argument("--scenario", default="paper")
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="config override for the companion (e.g. logging.image_encoding=\"raw\")")
    args = ap.parse_args()
    out = args.out or Path(tempfile.mkdtemp(prefix="bench-latency-"))
    samples: list[tuple[float, float]] = []

    def monitor(proc: subprocess.Popen[bytes]) -> None:
        v = rss_mb(proc.pid)
        if v is not None:
            samples.append((time.monotonic(), v))

    rep = run_demo(DEFAULT_CONFIG, args.scenario, args.duration, out, args.set, [], plots=False,
                   monitor=monitor)
    lat: list[float] = []
    stages: dict[str, list[float]] = {}
    with LogReader(out / "flight.mcap") as r:
        for m in r.messages(topics=["/control/step"]):
            d = m.data or {}
            if d.get("latency_ms") is None:
                continue
            lat.append(d["latency_ms"])
            for k, v in (d.get("timings_ms") or {}).items():
                stages.setdefault(k, []).append(v)
    a = np.array(lat)
    t = np.array([s[0] for s in samples])
    mem = np.array([s[1] for s in samples])
    frac30 = 30.0 / args.duration
    i30 = int(np.searchsorted(t, t[0] + frac30 * (t[-1] - t[0]))) if t.size else 0
    res = {
        "steps": int(a.size),
        "median_ms": float(np.median(a)),
        "p95_ms": float(np.percentile(a, 95)),
        "max_ms": float(np.max(a)),
        "stages_median_ms": {k: float(np.median(v)) for k, v in stages.items()},
        "stages_p95_ms": {k: float(np.percentile(v, 95)) for k, v in stages.items()},
        "rss_peak_mb": float(mem.max()) if mem.size else None,
        "rss_at_30s_mb": float(mem[i30]) if mem.size else None,
        "rss_end_mb": float(mem[-1]) if mem.size else None,
        "rss_growth_30s_to_end": float(mem[-1] / mem[i30] - 1.0) if mem.size else None,
        # Point samples swing with the frames queued for encoding (up to
        # logging.max_pending_image_mb); a leak shows in window medians too.
        "rss_median_30_60s_mb": _window_median(t, mem, 30.0, 60.0, args.duration),
        "rss_median_last_30s_mb": _window_median(t, mem, args.duration - 30.0, args.duration,
                                                 args.duration),
        "real_time_factor": rep["real_time_factor"],
        "companion_cpu_ms_per_step": rep.get("companion_cpu_ms_per_step"),
        "emulator_cpu_ms_per_step": rep.get("emulator_cpu_ms_per_step"),
        "load_1min": os.getloadavg()[0],
        "targets": {"median_ms": 3.0, "p95_ms": 6.0, "rss_peak_mb": 400.0, "growth": 0.05},
    }
    if args.json:
        print(json.dumps(res, indent=2))
    else:
        print(f"frame -> SET_ATTITUDE_TARGET over {res['steps']} steps: median "
              f"{res['median_ms']:.2f} ms (target 3), p95 {res['p95_ms']:.2f} ms (target 6), "
              f"max {res['max_ms']:.2f} ms")
        for k in res["stages_median_ms"]:
            print(f"  {k:>8}: median {res['stages_median_ms'][k]:.2f} ms, "
                  f"p95 {res['stages_p95_ms'][k]:.2f} ms")
        print(f"companion RSS: peak {res['rss_peak_mb']:.0f} MB (target 400), "
              f"{res['rss_at_30s_mb']:.0f} MB at 30 s -> {res['rss_end_mb']:.0f} MB at the end "
              f"({100 * res['rss_growth_30s_to_end']:+.1f} %, target < 5 %)")
        a, b = res["rss_median_30_60s_mb"], res["rss_median_last_30s_mb"]
        if a and b:
            print(f"  window medians: {a:.0f} MB over 30-60 s -> {b:.0f} MB over the last 30 s "
                  f"({100 * (b / a - 1):+.1f} %)")
        cpu, emu = res["companion_cpu_ms_per_step"], res["emulator_cpu_ms_per_step"]
        print(f"CPU per step (getrusage): companion {'-' if cpu is None else f'{cpu:.2f} ms'} "
              f"(all threads), emulator {'-' if emu is None else f'{emu:.2f} ms'}; "
              f"load average {res['load_1min']:.1f}")
        print(f"flight ran at {res['real_time_factor']:.1f}x real time; log in {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
