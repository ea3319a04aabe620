"""Impaired link: the paper and edge flights in lockstep with 20 % loss, 10 % duplication,
5 % reordering and 50 +- 30 ms delay in both directions (``config/impaired-link.toml``), beside
the same flights on a clean link. Pass: target in view (detected on every frame), OFFBOARD never
left, every command finite; the paper's visible bound (corners within 500 px, from the
emulator's ground truth) is reported beside it."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

from bench.reliab.common import (
    PAPER,
    ROOT,
    ProbeResult,
    children_cpu_s,
    flight_figures,
    load_avg,
)
from companion.flight import run_demo

IMPAIRED = ROOT / "config" / "impaired-link.toml"


def _sim_impairment_counters(sim_log: Path) -> dict[str, str]:
    out = {}
    for line in sim_log.read_text().splitlines():
        if "impairment " in line and ": {" in line:
            k, _, v = line.split("impairment ", 1)[1].partition(": ")
            out[k] = v
    return out


def fly(out: Path, scenario: str, duration_s: float, impaired: bool) -> dict[str, Any]:
    rep = run_demo(PAPER, scenario, duration_s, out, [], [], plots=False,
                   sim_config=IMPAIRED if impaired else None)
    ff = flight_figures(out / "flight.mcap")
    vis = rep["visibility"]
    lv = rep["safety"]["steps_per_level"]
    hovers = [t for t in rep["safety"]["transitions"] if t["level"] != "tracking"]
    return {
        "max_corner_px": max(vis["max_abs_u_px"], vis["max_abs_n_px"]),
        "bound_px": vis["bound_px"],
        "frames_outside_bound": vis["frames_outside_bound"],
        "frames_target_lost": vis["frames_target_lost"],
        "steps": ff.steps, "sent": ff.sent, "levels": lv,
        "non_tracking_episodes": hovers[:20],
        "offboard_left": ff.offboard_left,
        "rms_se": rep["tracking"].get("rms_se"),
        "non_finite_commands": ff.non_finite_commands,
        "rejected": ff.rejected,
        "sim_rtf": rep.get("real_time_factor"),
        "impairment": _sim_impairment_counters(out / "sim.log") if impaired else {},
    }


def run_impaired(out: Path, duration_s: float = 251.0,
                 scenarios: tuple[str, ...] = ("paper", "edge")) -> ProbeResult:
    t_w, c0 = time.monotonic(), children_cpu_s()
    load0 = load_avg()
    rows: dict[str, Any] = {}
    for sc in scenarios:
        for imp in (False, True):
            rows[f"{sc}/{'impaired' if imp else 'clean'}"] = fly(
                out / f"{sc}-{'impaired' if imp else 'clean'}", sc, duration_s, imp)
    # in view: detected on every frame; the 500 px visible bound is reported beside it
    ok = all(r["frames_target_lost"] == 0 and r["offboard_left"] == 0
             and r["non_finite_commands"] == 0 for r in rows.values())
    parts = []
    for k, r in rows.items():
        nt = sum(v for lvl, v in r["levels"].items() if lvl != "tracking")
        parts.append(f"{k}: target lost {r['frames_target_lost']} frames, max corner "
                     f"{r['max_corner_px']:.0f}/{r['bound_px']:.0f} px ({r['frames_outside_bound']}"
                     f" frames beyond), offboard left {r['offboard_left']}x, non-tracking "
                     f"steps {nt}")
    lost = {k: f"{r['steps'] - r['sent']} steps without a command" for k, r in rows.items()}
    return ProbeResult(
        probe="impaired link (lockstep, paper + edge)",
        inputs=f"{len(rows)} flights of {duration_s:.0f} s; 20% loss, 10% dup, 5% reorder, "
               "50+-30 ms both directions (offboard + AGV links)",
        result="; ".join(parts),
        passed=ok,
        data_lost=", ".join(f"{k} {v}" for k, v in lost.items()),
        bad_commands=sum(r["non_finite_commands"] for r in rows.values()),
        figures={"flights": rows, "load_before": load0, "load_after": load_avg()},
        wall_s=time.monotonic() - t_w,
        cpu_s=children_cpu_s() - c0,
    )


if __name__ == "__main__":
    import argparse
    import json

    ap = argparse.ArgumentParser()
    ap.add_argument("--duration", type=float, default=251.0)
    ap.add_argument("--out", type=Path, default=Path("out/reliability/impaired"))
    a = ap.parse_args()
    print(json.dumps(run_impaired(a.out, a.duration).to_json(), indent=2, default=str))
