"""How long a timed-out solve leaves the companion without the RMPC, with and without the
stand-by solver process (``rmpc.solver_spare``).

A real compiled solver in a real child process (``rmpc.solve_isolation = "process"``, the
paper config, wall-clock bound 0.25 s); the stuck solve is the child's test hook (it spins at
100 % CPU, SIGTERM ignored). After each timeout the controller keeps stepping at 20 Hz; printed:
the wall time to the next optimal step and the fallback steps flown meanwhile, five times each.

    python bench/solver_spare.py
"""

from __future__ import annotations

import dataclasses
import logging
import os
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
import numpy as np

from companion.config import load_config
from companion.control.solve_guard import process_backend
from companion.core.design import design_terminal
from companion.core.rmpc import Rmpc, TargetMotion

ETA0 = np.array([0.0159, -0.2230, 0.6, 0.3927, -0.1307, -0.0541, 0.0])


def main() -> int:
    logging.basicConfig(level=logging.CRITICAL)
    cfg = load_config()
    d = design_terminal(cfg.rmpc, cfg.camera)
    tm = TargetMotion.constant([0.1, 0.0], [0.0, 0.0], 0.0, cfg.rmpc.horizon)
    for spare in (False, True):
        p = dataclasses.replace(cfg.rmpc, solve_isolation="process", solver_spare=spare)
        m = Rmpc(p, cfg.camera, d, backend=process_backend(p, cfg.camera, d))
        b = m.backend
        assert b is not None
        b.wait_ready(60)
        m.solve(ETA0, tm)
        time.sleep(3.0)  # the spare loads
        gaps = []
        for _ in range(5):
            b.hang_next_solve()
            m.solve(ETA0, tm)  # the stuck solve: cut after 0.25 s
            t0, n = time.monotonic(), 0
            while m.solve(ETA0, tm).mode != "optimal":
                n += 1
                time.sleep(0.05)  # a 20 Hz loop
            gaps.append((time.monotonic() - t0, n))
            time.sleep(3.0)
        print(f"{'with' if spare else 'without'} the spare: wall time to the next optimal step "
              f"after a timeout (s, fallback steps): {[(round(g, 3), n) for g, n in gaps]}; "
              f"load {os.getloadavg()[0]:.1f}", flush=True)
        m.close()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
