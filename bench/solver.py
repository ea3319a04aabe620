"""RMPC solve-time benchmark (spec section 6; targets in bench/README.md).

Closed loops on the nominal error model plus a random disturbance |rho| <= 1e-4 (seeded):
400 steps from the paper's initial state (all steps and the first 40 alone), and from the
`edge` initial state; then the same paper loop with a plain warm-started IPOPT of the same
problem (same compiled NLP functions) in the same process; then the same paper and edge loops
with the real-time iteration (``rmpc.solver = "rti"``: linearisation + DAQP QP + nonlinear
check, the full NLP behind it when the check rejects). Times are measured AROUND the Python
call ``Rmpc.solve`` (perf_counter, and ``cpu_*``: this process's CPU time, process_time, which
a busy machine inflates less), i.e. including the Python-side packing and checks; the solver's
own time (``RmpcResult.solve_time_s``: the compiled NLP's evaluation, or the RTI's
linearisation + QP + check) is reported alongside as ``internal_*``.

    python bench/solver.py [--json] [--steps 400] [--seed 1] [--rti-only]

``--rti-only`` runs only the real-time iteration's loops (and the paper loop of the full NLP
they are compared with), skipping the edge and IPOPT loops of the full NLP.

    python bench/solver.py --log FLIGHT.mcap [--evict-mb 0] [--linearisation loops]

instead prints where an RTI step's CPU time goes (guess, certificate, state box, compiled
linearisation, DAQP, numpy glue, compiled check, the rest of ``Rmpc.solve``), in a replay of
the flight itself (in-flight caches) and on the flight's sequence of solves repeated back to
back (warm caches, or with ``--evict-mb`` written between two solves): bench/solver_parts.py.
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


def _summary(times_s: list[tuple[float, float]], results: list[RmpcResult]) -> dict[str, Any]:
    t = np.array([w for w, _ in times_s]) * 1e3
    cpu = np.array([c for _, c in times_s]) * 1e3
    modes = [r.mode for r in results]
    conv = np.array([ti for ti, m in zip(t, modes, strict=True) if m == "optimal"])
    internal = np.array([r.solve_time_s for r in results]) * 1e3
    iters = np.array([r.iterations for r in results])
    return {
        "steps": len(t),
        "median_ms": float(np.median(t)),
        "p95_ms": float(np.percentile(t, 95)),
        "max_ms": float(t.max()),
        "cpu_median_ms": float(np.median(cpu)),
        "cpu_p95_ms": float(np.percentile(cpu, 95)),
        "cpu_mean_ms": float(np.mean(cpu)),
        "rti_flown": int(sum(r.status.startswith("rti:") and "nlp: " not in r.status
                             for r in results)),
        "converged_median_ms": float(np.median(conv)) if conv.size else float("nan"),
        "converged_p95_ms": float(np.percentile(conv, 95)) if conv.size else float("nan"),
        "internal_median_ms": float(np.nanmedian(internal)),
        "internal_p95_ms": float(np.nanpercentile(internal, 95)),
        "iterations_median": float(np.median(iters)),
        "iterations_max": int(iters.max()),
        "failures": int(sum(m != "optimal" for m in modes)),
        "recovery": int(modes.count("recovery")),
        "fallback": int(modes.count("fallback")),
    }


def _run(mpc: Rmpc, eta0: np.ndarray, steps: int,
         seed: int) -> tuple[list[tuple[float, float]], list[Any]]:
    times: list[tuple[float, float]] = []

    def timed(m: Rmpc, e: np.ndarray, tm: TargetMotion) -> RmpcResult:
        c0, t0 = time.process_time(), time.perf_counter()
        r = m.solve(e, tm)
        times.append((time.perf_counter() - t0, time.process_time() - c0))
        return r

    mpc.reset()
    loop = closed_loop(mpc, eta0, steps, RHO, seed, solve=timed)
    return times, [s.result for s in loop]


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", action="store_true", help="print one JSON object")
    ap.add_argument("--steps", type=int, default=400)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--rti-only", action="store_true",
                    help="only the RTI loops and the full NLP's paper loop")
    ap.add_argument("--log", type=Path, default=None,
                    help="instead: the RTI step's parts on this flight log's sequence of "
                         "solves (bench/solver_parts.py)")
    ap.add_argument("--evict-mb", type=float, default=0.0,
                    help="with --log: MB written between two solves (default 0: warm caches)")
    ap.add_argument("--linearisation", choices=("recursion", "loops", "graph", "scalar"),
                    default=None,
                    help="with --log: fly this rmpc.rti_linearisation (default: the log's)")
    return ap.parse_args(argv)


def _build(rmpc_cfg: Any, cfg: Any, design: Any) -> tuple[Rmpc, float]:
    """An Rmpc of ``rmpc_cfg`` and its build time (s, perf_counter; compile or cache load)."""
    t0 = time.perf_counter()
    mpc = Rmpc(rmpc_cfg, cfg.camera, design, clock=time.perf_counter)
    return mpc, time.perf_counter() - t0


def _measure(args: argparse.Namespace, cfg: Any) -> dict[str, Any]:
    """Every loop, in this order: the full NLP on paper (and edge), the RTI on paper and edge,
    IPOPT on paper (not with ``--rti-only``)."""
    design = design_terminal(cfg.rmpc, cfg.camera)
    mpc, build_s = _build(dataclasses.replace(cfg.rmpc, solver="nlp"), cfg, design)
    paper0 = initial_error(*PAPER_POSE)
    edge0 = initial_error(*EDGE_POSE)

    times, res = _run(mpc, paper0, args.steps, args.seed)
    m: dict[str, Any] = {"mpc": mpc, "build_s": build_s, "paper": _summary(times, res),
                         "paper_first40": _summary(times[:40], res[:40]), "edge": {}}
    if not args.rti_only:
        m["edge"] = _summary(*_run(mpc, edge0, args.steps, args.seed))

    m["rti_cfg"] = dataclasses.replace(cfg.rmpc, solver="rti")
    m["rti"], m["rti_build_s"] = _build(m["rti_cfg"], cfg, design)
    times_r, res_r = _run(m["rti"], paper0, args.steps, args.seed)
    m["rti_paper"] = _summary(times_r, res_r)
    m["rti_paper_first40"] = _summary(times_r[:40], res_r[:40])
    m["rti_edge"] = _summary(*_run(m["rti"], edge0, args.steps, args.seed))
    u_nlp = np.array([r.u0 for r in res])
    u_rti = np.array([r.u0 for r in res_r])
    m["rti_vs_nlp_max_abs_u0_paper"] = float(np.max(np.abs(u_rti - u_nlp)))

    m["ipopt_paper"] = {"median_ms": float("nan")}
    m["ipopt_build_s"] = float("nan")
    if not args.rti_only:
        ipopt_cfg = dataclasses.replace(cfg.rmpc, solver="nlp", nlp_solver="ipopt")
        ipopt, m["ipopt_build_s"] = _build(ipopt_cfg, cfg, design)
        m["ipopt_paper"] = _summary(*_run(ipopt, paper0, args.steps, args.seed))
    return m


def _result(cfg: Any, m: dict[str, Any]) -> dict[str, Any]:
    paper, ip = m["paper"], m["ipopt_paper"]
    return {
        "solver": cfg.rmpc.solver,
        "nlp_solver": cfg.rmpc.nlp_solver,
        "median_ms": paper["median_ms"],
        "p95_ms": paper["p95_ms"],
        "max_ms": paper["max_ms"],
        "failures": paper["failures"],
        "ipopt_median_ms": ip["median_ms"],
        "ratio_ipopt_over_fatrop": ip["median_ms"] / paper["median_ms"],
        "paper": paper,
        "paper_first40": m["paper_first40"],
        "edge": m["edge"],
        "ipopt_paper": ip,
        "build_s": m["build_s"],
        "ipopt_build_s": m["ipopt_build_s"],
        "rti_paper": m["rti_paper"],
        "rti_paper_first40": m["rti_paper_first40"],
        "rti_edge": m["rti_edge"],
        "rti_build_s": m["rti_build_s"],
        "rti_vs_nlp_max_abs_u0_paper": m["rti_vs_nlp_max_abs_u0_paper"],
        "rti_max_qp": m["rti_cfg"].rti_max_qp,
        "rti_qps": m["rti"].rti_qps,
        "rti_to_nlp": m["rti"].rti_rejected,
        "cache_hit": [c is not None and not c.compiled_now for c in m["mpc"].compiled],
        "loadavg_1min": os.getloadavg()[0],
        "cpus": os.cpu_count(),
        "timing": "perf_counter around Rmpc.solve (Python call); internal_* = CasADi t_wall",
    }


def _print(out: dict[str, Any], horizon: int, steps: int) -> None:
    print(f"RMPC solve time (N={horizon}), measured around the "
          f"Python call; load avg {out['loadavg_1min']:.2f} on {out['cpus']} CPUs")
    print(f"build {out['build_s']:.2f} s (cache hit: {out['cache_hit']})")
    rows = [("nlp paper, all", out["paper"]), ("nlp paper, 1st 40", out["paper_first40"]),
            ("nlp edge, all", out["edge"]), ("ipopt paper", out["ipopt_paper"]),
            ("rti paper, all", out["rti_paper"]),
            ("rti paper, 1st 40", out["rti_paper_first40"]), ("rti edge, all", out["rti_edge"])]
    rows = [(name, s) for name, s in rows if "steps" in s]
    print(f"{'run':<19}{'median':>8}{'p95':>8}{'max':>8}{'cpu.med':>8}{'cpu.p95':>8}"
          f"{'intern':>8}{'it.med':>7}{'it.max':>7}{'fail':>5}{'recov':>6}{'fallb':>6}"
          f"{'rti':>5}")
    for name, s in rows:
        print(f"{name:<19}{s['median_ms']:>8.3f}{s['p95_ms']:>8.3f}{s['max_ms']:>8.2f}"
              f"{s['cpu_median_ms']:>8.3f}{s['cpu_p95_ms']:>8.3f}"
              f"{s['internal_median_ms']:>8.3f}{s['iterations_median']:>7.0f}"
              f"{s['iterations_max']:>7d}{s['failures']:>5d}{s['recovery']:>6d}"
              f"{s['fallback']:>6d}{s['rti_flown']:>5d}")
    print("(ms; rti: steps that flew the RTI's plan; the others solved the full NLP)")
    rti_paper, rti_edge = out["rti_paper"], out["rti_edge"]
    print(f"rti (rmpc.rti_max_qp = {out['rti_max_qp']}): {out['rti_qps']} QPs in "
          f"{2 * steps} steps, {out['rti_to_nlp']} steps to the full NLP; internal "
          f"(linearisation + QP + check) median / p95 ms: paper "
          f"{rti_paper['internal_median_ms']:.3f} / {rti_paper['internal_p95_ms']:.3f}, edge "
          f"{rti_edge['internal_median_ms']:.3f} / {rti_edge['internal_p95_ms']:.3f}")
    print(f"ipopt / fatrop median ratio: {out['ratio_ipopt_over_fatrop']:.2f}; rti vs nlp, "
          f"paper loop: max |u0 difference| {out['rti_vs_nlp_max_abs_u0_paper']:.2e}")


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    if args.log is not None:
        import solver_parts as sp  # bench/ is on the path as the script's dir
        with sp.linearisation(args.linearisation):
            sp.report_in_flight(sp.in_flight(args.log), os.getloadavg()[0])
            sp.report(sp.measure(args.log, args.evict_mb), os.getloadavg()[0])
        return 0
    cfg = load_config()
    out = _result(cfg, _measure(args, cfg))
    if args.json:
        print(json.dumps(out, indent=2))
        return 0
    _print(out, cfg.rmpc.horizon, args.steps)
    return 0

if __name__ == "__main__":
    raise SystemExit(main())
