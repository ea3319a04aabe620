"""Cost of the solve time bound (``rmpc.solve_isolation``): the same closed loop solved in the
calling process ("none") and in the bounded child process ("process").

The paper closed loop (nominal model, |rho| <= 1e-4, seeded) with config/paper.toml, run with
each isolation in turn (alternating, ``--rounds``); per step: wall time around ``Rmpc.solve``
(perf_counter) and CPU time (this process's ``time.process_time`` plus the CPU the solver child
reported). Also checks that both give bit-identical inputs (the child evaluates the same
compiled solver on the same arrays), and the time to restart a killed child.

    python bench/solve_isolation.py [--json] [--steps 400] [--rounds 2]
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
from companion.control.solve_guard import ProcessSolveBackend, process_backend
from companion.core.design import design_terminal
from companion.core.rmpc import Rmpc, RmpcResult, TargetMotion
from companion.core.rmpc_scenario import closed_loop, initial_error

PAPER_POSE = ((-0.2, 0.4, -3.2), np.pi / 8)


def _loop(mpc: Rmpc, steps: int) -> tuple[dict[str, Any], np.ndarray]:
    wall: list[float] = []
    cpu: list[float] = []
    backend = mpc.backend

    def child_cpu() -> float:
        return backend.child_cpu_s if isinstance(backend, ProcessSolveBackend) else 0.0

    def timed(m: Rmpc, e: np.ndarray, tm: TargetMotion) -> RmpcResult:
        c0, t0 = time.process_time() + child_cpu(), time.perf_counter()
        r = m.solve(e, tm)
        wall.append(time.perf_counter() - t0)
        cpu.append(time.process_time() + child_cpu() - c0)
        return r

    mpc.reset()
    loop = closed_loop(mpc, initial_error(*PAPER_POSE), steps, 1e-4, seed=1, solve=timed)
    w, c = np.array(wall[1:]) * 1e3, np.array(cpu[1:]) * 1e3  # first step: page faults
    modes = [s.result.mode for s in loop]
    return {
        "wall_ms_mean": float(w.mean()), "wall_ms_p50": float(np.median(w)),
        "wall_ms_p95": float(np.percentile(w, 95)), "wall_ms_max": float(w.max()),
        "cpu_ms_mean": float(c.mean()), "cpu_ms_p95": float(np.percentile(c, 95)),
        "optimal": modes.count("optimal"), "steps": len(modes),
    }, np.array([s.result.u0 for s in loop])


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--steps", type=int, default=400)
    ap.add_argument("--rounds", type=int, default=2)
    args = ap.parse_args()
    cfg = load_config()
    design = design_terminal(cfg.rmpc, cfg.camera)
    none_p = dataclasses.replace(cfg.rmpc, solve_isolation="none")
    proc_p = dataclasses.replace(cfg.rmpc, solve_isolation="process")
    local = Rmpc(none_p, cfg.camera, design)
    t0 = time.perf_counter()
    isolated = Rmpc(proc_p, cfg.camera, design,
                    backend=process_backend(proc_p, cfg.camera, design))
    start_s = time.perf_counter() - t0
    out: dict[str, Any] = {"load_1min": os.getloadavg()[0], "build_with_child_s": start_s}
    rounds: dict[str, list[dict[str, Any]]] = {"none": [], "process": []}
    identical = True
    for _ in range(args.rounds):
        a, ua = _loop(local, args.steps)
        b, ub = _loop(isolated, args.steps)
        rounds["none"].append(a)
        rounds["process"].append(b)
        identical &= bool(np.array_equal(ua, ub))
    out["rounds"] = rounds
    out["bit_identical_u0"] = identical
    backend = isolated.backend
    assert isinstance(backend, ProcessSolveBackend)
    t0 = time.perf_counter()
    backend._restart("bench")  # what a timeout does
    backend.wait_ready(120.0)
    out["restart_to_ready_s"] = time.perf_counter() - t0
    out["load_1min_end"] = os.getloadavg()[0]
    isolated.close()
    if args.json:
        print(json.dumps(out, indent=2))
    else:
        print(f"load {out['load_1min']:.2f} -> {out['load_1min_end']:.2f}; first child ready "
              f"with the build in {start_s:.2f} s; restart to ready "
              f"{out['restart_to_ready_s']:.2f} s; u0 bit-identical: {identical}")
        for kind, rs in rounds.items():
            for r in rs:
                print(f"{kind:8s} wall mean {r['wall_ms_mean']:.3f} p50 {r['wall_ms_p50']:.3f} "
                      f"p95 {r['wall_ms_p95']:.3f} max {r['wall_ms_max']:.2f} ms; CPU mean "
                      f"{r['cpu_ms_mean']:.3f} p95 {r['cpu_ms_p95']:.3f} ms; optimal "
                      f"{r['optimal']}/{r['steps']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
