"""What replacing the RMPC's solver process costs: wall time from a restart to the new child
being ready, and the CPU the child used to get there (its ``/proc`` times), five times.

A real compiled solver (the paper config, ``rmpc.solve_isolation = "process"``, no stand-by
process, so every restart starts a fresh child). The companion's CPU-budget behaviour depends
on it: a restart that costs a second of CPU on a small budget delays every step after it
(docs/guides/sizing.md, docs/reference/reliability.md "Solve time bound").

    python bench/solver_restart.py
"""

from __future__ import annotations

import dataclasses
import logging
import os
import sys
import time
from pathlib import Path

if __name__ == "__main__":  # the solver processes re-import the main script: keep it light
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent))


def _cpu_s(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_bytes().rsplit(b")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def main() -> int:
    from companion.config import load_config
    from companion.control.solve_guard import ProcessSolveBackend, process_backend
    from companion.core.design import design_terminal
    from companion.core.rmpc import Rmpc

    logging.basicConfig(level=logging.CRITICAL)
    cfg = load_config()
    d = design_terminal(cfg.rmpc, cfg.camera)
    p = dataclasses.replace(cfg.rmpc, solve_isolation="process", solver_spare=False)
    m = Rmpc(p, cfg.camera, d, backend=process_backend(p, cfg.camera, d))
    b = m.backend
    assert isinstance(b, ProcessSolveBackend) and b.wait_ready(120.0)
    rows = []
    for _ in range(5):
        t0 = time.monotonic()
        b._restart("bench")  # what a stuck solve does
        assert b.wait_ready(120.0) and b.pid is not None
        rows.append((round(time.monotonic() - t0, 3), _cpu_s(b.pid)))
    m.close()
    print(f"restart -> ready (wall s, child CPU s at ready): {rows}; load "
          f"{os.getloadavg()[0]:.1f}", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
