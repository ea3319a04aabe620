"""Replay speed against the flight's own duration (issue: logs a user can keep and replay).

    python bench/replay.py [LOG.mcap] [--duration 60] [--json] [--write-log]

Without a log it first flies the paper scenario for ``--duration`` simulated seconds (lockstep,
the config's logging: crops of what perception read by default) and replays that. Three ways:
exact (perception in a second process, the default of ``companion replay``), exact in one
process, and ``--from-detections`` (controller only), comparing only as ``companion replay``
does without ``--out`` (``--write-log``: writing the replay's log too, as with it). For each:
wall time, CPU time (this process and the perception worker, getrusage), steady CPU per step,
the ratio to the flight's
duration (targets: exact >= 20x, from detections >= 100x), the start-up (the call to the first
step: reading the config, the terminal design, the NLP build or solver load, the perception
worker) and whether every command matched. CPU of a child process (the perception worker, a
solver child) counts once it has exited: in the totals, not in the steady figures.
Wall figures depend on the machine's load (printed); CPU figures much less. The replay's own
thread is the critical path: its CPU per step (and the start-up's), or half the total CPU when
that is more, give the rate two idle cores would reach ("on two idle cores"), a figure a loaded
machine can still measure. The controller's own step (``ControlPipeline.step``, thread CPU) is
timed apart: the replay cannot run faster than the flight's steps one after the other
("the step alone"); the rest of the replay's thread is feeding it (the store's ingest of the
messages, receiving the inputs, comparing).
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

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from companion.config import DEFAULT_CONFIG  # noqa: E402
from companion.control.pipeline import ControlPipeline  # noqa: E402
from companion.flight import run_demo  # noqa: E402
from companion.log.reader import LogReader  # noqa: E402
from companion.replay import replay  # noqa: E402


def _cpu() -> float:
    s = resource.getrusage(resource.RUSAGE_SELF)
    c = resource.getrusage(resource.RUSAGE_CHILDREN)
    return s.ru_utime + s.ru_stime + c.ru_utime + c.ru_stime


def measure(log: Path, flight_s: float, out: Path | None = None, **kw: Any) -> dict[str, Any]:
    marks: dict[str, tuple[float, float, int, float]] = {}

    def prog(done: int, total: int) -> None:  # called on the replay's (main) thread
        now = (time.perf_counter(), _cpu(), done, time.thread_time())
        if done == 1:
            marks["first"] = now
        if done == 100:
            marks["a"] = now
        marks["b"] = now

    step_cpu = [0.0]
    plain = ControlPipeline.step

    def timed_step(self: ControlPipeline, *a: Any, **k: Any) -> Any:
        t = time.thread_time()
        try:
            return plain(self, *a, **k)
        finally:
            step_cpu[0] += time.thread_time() - t

    ControlPipeline.step = timed_step  # type: ignore[method-assign]
    t0, c0, m0 = time.perf_counter(), _cpu(), time.thread_time()
    try:
        res = replay(log, out, progress=prog, **kw)
    finally:
        ControlPipeline.step = plain  # type: ignore[method-assign]
    wall, cpu = time.perf_counter() - t0, _cpu() - c0
    a, b = marks.get("a"), marks.get("b")
    steady = None
    if a and b and b[2] > a[2]:
        n = b[2] - a[2]
        steady = {"wall_ms_per_step": 1e3 * (b[0] - a[0]) / n,
                  "cpu_ms_per_step": 1e3 * (b[1] - a[1]) / n,
                  "main_thread_ms_per_step": 1e3 * (b[3] - a[3]) / n}
    first = marks.get("first")
    startup = None if first is None else {"wall_s": first[0] - t0, "cpu_s": first[1] - c0,
                                          "main_thread_s": first[3] - m0}
    bound = None
    if steady and startup and res.steps:
        # on two idle cores: the replay's thread (the critical path) or, when the rest (the
        # input process with perception, the writer's compression) is heavier, half the CPU
        busy_s = startup["main_thread_s"] + res.steps * steady["main_thread_ms_per_step"] * 1e-3
        bound = flight_s / max(busy_s, cpu / 2)
    step_ms = step_cpu[0] * 1e3 / res.steps if res.steps else None
    return {"steps": res.steps, "identical": res.summary()["identical"], "wall_s": wall,
            "controller_step_ms": step_ms,
            "step_alone_bound": flight_s / (step_cpu[0]) if step_cpu[0] > 0 else None,
            "startup": startup,
            "cpu_s": cpu, "speed_vs_real_time": flight_s / wall if wall > 0 else None,
            "steady": steady, "idle_two_core_bound": bound}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("log", type=Path, nargs="?")
    ap.add_argument("--duration", type=float, default=60.0)
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--write-log", action="store_true",
                    help="write the replay's log, as `companion replay --out DIR` does")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="config override for the flight (when no LOG is given)")
    args = ap.parse_args()
    tmp = Path(tempfile.mkdtemp(prefix="bench-replay-"))
    log = args.log
    if log is None:
        run_demo(DEFAULT_CONFIG, "paper", args.duration, tmp, args.set, [], plots=False)
        log = tmp / "flight.mcap"
    with LogReader(log, verify=False) as r:
        ch = next(c for c in r.channels if c.topic == "/control/step")
    flight_s = ((ch.last_log_time_ns or 0) - (ch.first_log_time_ns or 0)) * 1e-9
    out: dict[str, Any] = {"log": str(log), "log_bytes": log.stat().st_size,
                           "flight_s": flight_s, "load_1min_before": os.getloadavg()[0]}
    # as `companion replay` runs: without --out, comparing only; with it (--write-log here)
    # writing the replay's log too (its report reads it)
    def log_to(name: str) -> Path | None:
        return tmp / name if args.write_log else None

    out["writes_log"] = args.write_log
    out["exact_worker"] = measure(log, flight_s, log_to("exact.mcap"), workers=1)
    out["exact_in_process"] = measure(log, flight_s, log_to("one.mcap"), workers=0)
    out["from_detections"] = measure(log, flight_s, log_to("fd.mcap"), from_detections=True)
    out["load_1min_after"] = os.getloadavg()[0]
    out["targets"] = {"exact": 20.0, "from_detections": 100.0}
    if args.json:
        print(json.dumps(out, indent=2))
        return 0
    print(f"{log} ({out['log_bytes'] / 1e6:.0f} MB, {flight_s:.1f} s of flight); load "
          f"{out['load_1min_before']:.1f} -> {out['load_1min_after']:.1f}")
    for name, target in (("exact_worker", 20), ("exact_in_process", 20),
                         ("from_detections", 100)):
        m = out[name]
        st = m["steady"] or {}
        print(f"  {name:>16}: {m['wall_s']:.1f} s wall = {m['speed_vs_real_time']:.1f}x real "
              f"time (target {target}x), CPU {m['cpu_s']:.1f} s; steady "
              f"{st.get('wall_ms_per_step', float('nan')):.2f} ms wall, "
              f"{st.get('cpu_ms_per_step', float('nan')):.2f} ms CPU per step; identical: "
              f"{m['identical']}")
        bound = m.get("idle_two_core_bound")
        print(f"  {'':>16}  replay thread (the critical path): "
              f"{st.get('main_thread_ms_per_step', float('nan')):.2f} ms CPU per step; on two "
              f"idle cores ~{float('nan') if bound is None else bound:.0f}x")
        print(f"  {'':>16}  of which the controller's step (ControlPipeline.step): "
              f"{m['controller_step_ms'] or float('nan'):.2f} ms CPU a step; the steps "
              f"alone, one after the other: ~{m['step_alone_bound'] or float('nan'):.0f}x")
        su = m["startup"] or {}
        print(f"  {'':>16}  start-up (call -> first step): {su.get('wall_s', float('nan')):.2f} s "
              f"wall, {su.get('cpu_s', float('nan')):.2f} s CPU (this process; the import of "
              "the companion's modules before the call is not counted)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
