"""RMPC solve-time benchmark (spec section 6; targets in bench/README.md).

Closed loops on the nominal error model plus a random disturbance |rho| <= 1e-4 (seeded):
400 steps from the paper's initial state (all steps and the first 40 alone), and from the
`edge` initial state; then the same paper loop with a plain warm-started IPOPT of the same
problem (same compiled NLP functions) in the same process. Times are measured AROUND the
Python call ``Rmpc.solve`` (perf_counter), i.e. including the Python-side packing and checks;
the compiled solver's own evaluation time (``RmpcResult.solve_time_s``) is reported alongside as
``internal_*``.

    python bench/solver.py [--json] [--steps 400] [--seed 1]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from companion.config import load_config
from companion.core.design import design_terminal
from companion.core.rmpc import Rmpc, RmpcResult, TargetMotion
from companion.core.rmpc_scenario import closed_loop, initial_error

PAPER_POSE = ((-0.2, 0.4, -3.2), np.pi / 8)
EDGE_POSE = ((-1.0, 0.0, -3.2), np.pi / 4)
RHO = 1e-4


def _summary(times_s: list[float], results: list[RmpcResult]) -> dict[str, Any]:
    t = np.array(times_s) * 1e3
    modes = [r.mode for r in results]
    conv = np.array([ti for ti, m in zip(t, modes, strict=True) if m == "optimal"])
    internal = np.array([r.solve_time_s for r in results]) * 1e3
    iters = np.array([r.iterations for r in results])
    return {
        "steps": len(t),
        "median_ms": float(np.median(t)),
        "p95_ms": float(np.percentile(t, 95)),
        "max_ms": float(t.max()),
        "converged_median_ms": float(np.median(conv)) if conv.size else float("nan"),
        "converged_p95_ms": float(np.percentile(conv, 95)) if conv.size else float("nan"),
        "internal_median_ms": float(np.nanmedian(internal)),
        "iterations_median": float(np.median(iters)),
        "iterations_max": int(iters.max()),
        "failures": int(sum(m != "optimal" for m in modes)),
        "recovery": int(modes.count("recovery")),
        "fallback": int(modes.count("fallback")),
    }


def _run(mpc: Rmpc, eta0: np.ndarray, steps: int, seed: int) -> tuple[list[float], list[Any]]:
    times: list[float] = []

    def timed(m: Rmpc, e: np.ndarray, tm: TargetMotion) -> RmpcResult:
        t0 = time.perf_counter()
        r = m.solve(e, tm)
        times.append(time.perf_counter() - t0)
        return r

    mpc.reset()
    loop = closed_loop(mpc, eta0, steps, RHO, seed, solve=timed)
    return times, [s.result for s in loop]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", action="store_true", help="print one JSON object")
    ap.add_argument("--steps", type=int, default=400)
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args(argv)

    cfg = load_config()
    design = design_terminal(cfg.rmpc, cfg.camera)
    t0 = time.perf_counter()
    mpc = Rmpc(cfg.rmpc, cfg.camera, design, clock=time.perf_counter)
    build_s = time.perf_counter() - t0
    paper0 = initial_error(*PAPER_POSE)
    edge0 = initial_error(*EDGE_POSE)

    times, res = _run(mpc, paper0, args.steps, args.seed)
    paper = _summary(times, res)
    first = _summary(times[:40], res[:40])
    times_e, res_e = _run(mpc, edge0, args.steps, args.seed)
    edge = _summary(times_e, res_e)

    ipopt_cfg = dataclasses.replace(cfg.rmpc, solver="ipopt")
    t0 = time.perf_counter()
    ipopt = Rmpc(ipopt_cfg, cfg.camera, design, clock=time.perf_counter)
    ipopt_build_s = time.perf_counter() - t0
    times_i, res_i = _run(ipopt, paper0, args.steps, args.seed)
    ip = _summary(times_i, res_i)

    out: dict[str, Any] = {
        "solver": cfg.rmpc.solver,
        "median_ms": paper["median_ms"],
        "p95_ms": paper["p95_ms"],
        "max_ms": paper["max_ms"],
        "failures": paper["failures"],
        "ipopt_median_ms": ip["median_ms"],
        "ratio_ipopt_over_fatrop": ip["median_ms"] / paper["median_ms"],
        "paper": paper,
        "paper_first40": first,
        "edge": edge,
        "ipopt_paper": ip,
        "build_s": build_s,
        "ipopt_build_s": ipopt_build_s,
        "cache_hit": [c is not None and not c.compiled_now for c in mpc.compiled],
        "loadavg_1min": os.getloadavg()[0],
        "cpus": os.cpu_count(),
        "timing": "perf_counter around Rmpc.solve (Python call); internal_* = CasADi t_wall",
    }
    if args.json:
        print(json.dumps(out, indent=2))
        return 0
    print(f"RMPC solve time ({cfg.rmpc.solver}, N={cfg.rmpc.horizon}), measured around the "
          f"Python call; load avg {out['loadavg_1min']:.2f} on {out['cpus']} CPUs")
    print(f"build {build_s:.2f} s (cache hit: {out['cache_hit']})")
    rows = [("paper, all", paper), ("paper, first 40", first), ("edge, all", edge),
            ("paper, ipopt", ip)]
    print(f"{'run':<17}{'median':>9}{'p95':>9}{'max':>9}{'conv.med':>10}{'conv.p95':>10}"
          f"{'internal':>10}{'it.med':>8}{'it.max':>8}{'fail':>6}{'recov':>6}{'fallb':>6}")
    for name, s in rows:
        print(f"{name:<17}{s['median_ms']:>9.3f}{s['p95_ms']:>9.3f}{s['max_ms']:>9.3f}"
              f"{s['converged_median_ms']:>10.3f}{s['converged_p95_ms']:>10.3f}"
              f"{s['internal_median_ms']:>10.3f}{s['iterations_median']:>8.0f}"
              f"{s['iterations_max']:>8d}{s['failures']:>6d}{s['recovery']:>6d}"
              f"{s['fallback']:>6d}")
    print(f"ipopt / {cfg.rmpc.solver} median ratio: {out['ratio_ipopt_over_fatrop']:.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
