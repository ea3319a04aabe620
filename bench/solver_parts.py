"""Where one RTI step's time goes, on a flight's recorded closed-loop sequence of solves
(``python bench/solver.py --log FLIGHT.mcap``).

The log is replayed in this process (its recorded config; the commands are compared as
``companion replay`` does) with :meth:`Rmpc.solve` wrapped to record each call's ``(eta0,
target)`` (and each ``reset``). A fresh controller then solves the same sequence twice: once
plain (the total per step, wall and this thread's CPU time), once with the parts wrapped by
timers (exclusive CPU time of each part: the guess, the infeasibility certificate, the state
box, the compiled linearisation, DAQP, the QP's numpy glue, the compiled check, the step's
glue, and the rest of ``Rmpc.solve``; with the C step, ``rti_qp``, one call for a QP's
linearisation, DAQP, glue and check, which are then not timed apart). The timers add ~1 us
per wrapped call; the plain run is the figure to compare with the target, the parts say
where it goes.
"""

from __future__ import annotations

import contextlib
import dataclasses
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np

from companion.core import rmpc as rmpc_mod
from companion.core.design import design_terminal
from companion.core.rmpc import Rmpc

Call = tuple[str, Any]
_EVICT = np.zeros(0)


@contextlib.contextmanager
def linearisation(form: str | None) -> Iterator[None]:
    """Every controller built inside flies ``rmpc.rti_linearisation = form`` (None: the
    log's), whatever the log recorded (a log recorded before the key cannot be overridden
    by ``replay --set``)."""
    if form is None:
        yield
        return
    init = rmpc_mod.Rmpc.__init__

    def patched(self: Rmpc, rmpc: Any, *a: Any, **k: Any) -> None:
        init(self, dataclasses.replace(rmpc, rti_linearisation=form), *a, **k)

    rmpc_mod.Rmpc.__init__ = patched  # type: ignore[method-assign]
    try:
        yield
    finally:
        rmpc_mod.Rmpc.__init__ = init  # type: ignore[method-assign]


def capture(log: Path) -> tuple[list[Call], Any, dict[str, Any]]:
    """The solve/reset calls of a replay of ``log``, its config and the replay's summary."""
    from companion.log.reader import LogReader
    from companion.replay import replay, replay_config  # the replay's imports: only here

    calls: list[Call] = []
    solve, reset = rmpc_mod.Rmpc.solve, rmpc_mod.Rmpc.reset

    def rec_solve(self: Rmpc, eta0: Any, target: Any) -> Any:
        if not self.force_nlp:
            calls.append(("solve", (np.array(eta0, dtype=float), target)))
        return solve(self, eta0, target)

    def rec_reset(self: Rmpc) -> None:
        calls.append(("reset", None))
        reset(self)

    rmpc_mod.Rmpc.solve, rmpc_mod.Rmpc.reset = rec_solve, rec_reset  # type: ignore[method-assign]
    try:
        summary = replay(log, None, workers=1).summary()
    finally:
        rmpc_mod.Rmpc.solve, rmpc_mod.Rmpc.reset = solve, reset  # type: ignore[method-assign]
    with LogReader(log, verify=False) as reader:
        cfg = replay_config(reader, None, [])
    return calls, cfg, summary


class _Timers:
    """Exclusive thread-CPU time per label of nested wrapped calls, one list per step."""

    def __init__(self) -> None:
        self.stack: list[list[float]] = []  # [start, time spent in children]
        self.step: dict[str, float] = {}
        self.steps: list[dict[str, float]] = []

    def wrap(self, fn: Callable[..., Any], label: str) -> Callable[..., Any]:
        def timed(*a: Any, **k: Any) -> Any:
            frame = [time.thread_time(), 0.0]
            self.stack.append(frame)
            try:
                return fn(*a, **k)
            finally:
                total = time.thread_time() - frame[0]
                self.stack.pop()
                self.step[label] = self.step.get(label, 0.0) + total - frame[1]
                if self.stack:
                    self.stack[-1][1] += total
        return timed


PARTS = ("Rmpc wrapper", "guess", "certificate", "state box", "linearisation (rti_lin)",
         "DAQP", "QP glue (numpy)", "check (rti_val)", "step glue", "C QP (rti_qp)")


def _instrument(mpc: Rmpc, t: _Timers) -> None:
    """Wrap the parts of this controller (instance attributes: nothing global changes)."""
    rti: Any = mpc._rti
    m: Any = mpc
    m.solve = t.wrap(mpc.solve, "Rmpc wrapper")
    for attr in ("_guess", "_guess_inputs", "_guess_states"):  # (older trees: _guess)
        if hasattr(mpc, attr):
            setattr(m, attr, t.wrap(getattr(mpc, attr), "guess"))
    m._infeasibility_certificate = t.wrap(mpc._infeasibility_certificate, "certificate")
    m._state_box = t.wrap(mpc._state_box, "state box")
    rti.step = t.wrap(rti.step, "step glue")
    rti._qp = t.wrap(rti._qp, "QP glue (numpy)")
    rti._daqp = t.wrap(rti._daqp, "DAQP")
    cstep = getattr(rti, "_cstep", None)  # (one QP in one foreign call: its parts untimed)
    if cstep is not None:
        cstep.run = t.wrap(cstep.run, "C QP (rti_qp)")
    for attr, label in (("_lin", "linearisation (rti_lin)"), ("_val", "check (rti_val)")):
        if hasattr(rti, attr):
            setattr(rti, attr, t.wrap(getattr(rti, attr), label))


def _play(mpc: Rmpc, calls: list[Call], after: Callable[[], None] | None = None
          ) -> tuple[list[tuple[float, float]], list[Any]]:
    times, results = [], []
    mpc.reset()
    for kind, arg in calls:
        if kind == "reset":
            mpc.reset()
            continue
        if _EVICT.size:  # a flight's step in between: its data evicts the solver's code
            np.add(_EVICT, 1.0, out=_EVICT)
        c0, t0 = time.thread_time(), time.perf_counter()
        r = mpc.solve(*arg)
        times.append((time.perf_counter() - t0, time.thread_time() - c0))
        results.append(r)
        if after is not None:
            after()
    return times, results


def measure(log: Path, evict_mb: float = 0.0) -> dict[str, Any]:
    """The plain and the per-part figures of the RTI steps of ``log``'s sequence (module
    docstring). Only the steps whose plan the RTI flew (no full NLP) are counted.
    ``evict_mb``: an array of that size written between two solves (a flight's step in
    between evicts the caches: the solve's code and data are fetched from memory again, as
    in flight; 0: back-to-back solves, warm caches)."""
    global _EVICT
    _EVICT = np.zeros(int(evict_mb * 1e6 / 8))
    calls, cfg, summary = capture(log)
    design = design_terminal(cfg.rmpc, cfg.camera)
    mpc = Rmpc(cfg.rmpc, cfg.camera, design, clock=time.perf_counter)
    form = mpc.cfg.rti_linearisation
    _play(mpc, calls)  # warm the caches once
    times, results = _play(mpc, calls)
    rti = np.array([r.status.startswith("rti:") and "nlp: " not in r.status for r in results])
    wall = np.array([w for w, _ in times])[rti] * 1e6
    cpu = np.array([c for _, c in times])[rti] * 1e6
    timers = _Timers()
    _instrument(mpc, timers)

    def close_step() -> None:
        timers.steps.append(timers.step)
        timers.step = {}

    _, results_i = _play(mpc, calls, close_step)
    parts = {p: np.array([s.get(p, 0.0) for s in timers.steps])[rti] * 1e6 for p in PARTS}
    same = all(np.array_equal(a.u0, b.u0) for a, b in zip(results, results_i, strict=True))
    return {"log": str(log), "replay": summary, "evict_mb": evict_mb, "solves": len(results),
            "linearisation": form,
            "rti_steps": int(rti.sum()), "nlp_steps": int((~rti).sum()),
            "wall_us": wall, "cpu_us": cpu, "parts_us": parts, "deterministic": same}


def report(m: dict[str, Any], load: float) -> None:
    """The table of :func:`measure`'s figures (us)."""
    def q(a: np.ndarray) -> str:
        return f"{np.median(a):>8.1f}{np.percentile(a, 95):>8.1f}{np.mean(a):>8.1f}"
    rep = m["replay"]
    print(f"RTI step parts on {m['log']} (rti_linearisation {m['linearisation']!r}; load avg "
          f"{load:.2f}; {m['evict_mb']:g} MB written "
          f"between two solves): {m['solves']} solves, "
          f"{m['rti_steps']} flew the RTI, {m['nlp_steps']} the full NLP; replay "
          f"{rep['commands_compared']} commands, max |dq| {rep['max_quat_diff']:.2g}; "
          f"instrumented run same u0: {m['deterministic']}")
    print(f"{'us per RTI step':<26}{'median':>8}{'p95':>8}{'mean':>8}")
    print(f"{'total, wall':<26}{q(m['wall_us'])}")
    print(f"{'total, thread CPU':<26}{q(m['cpu_us'])}")
    for p, a in m["parts_us"].items():
        print(f"  {p:<24}{q(a)}")
    s = sum(m["parts_us"].values())
    print(f"{'  sum of parts (timed)':<26}{q(s)}")


def in_flight(log: Path) -> dict[str, Any]:
    """The parts of the RTI steps of a replay of ``log`` itself (perception in its child
    process, the pipeline around each solve, as in flight: the caches as a flight's step
    leaves them), timed by the same wrappers, on the controller the replay builds."""
    from companion.replay import replay  # the replay's imports: only here

    timers = _Timers()
    init, solve = rmpc_mod.Rmpc.__init__, rmpc_mod.Rmpc.solve
    flown: list[bool] = []

    def rec_init(self: Rmpc, *a: Any, **k: Any) -> None:
        init(self, *a, **k)
        if self._rti is not None:
            _instrument(self, timers)

    def rec_solve(self: Rmpc, eta0: Any, target: Any) -> Any:
        r = solve(self, eta0, target)
        flown.append(r.status.startswith("rti:") and "nlp: " not in r.status)
        timers.steps.append(timers.step)
        timers.step = {}
        return r

    rmpc_mod.Rmpc.__init__, rmpc_mod.Rmpc.solve = rec_init, rec_solve  # type: ignore[method-assign]
    try:
        summary = replay(log, None, workers=1).summary()
    finally:
        rmpc_mod.Rmpc.__init__, rmpc_mod.Rmpc.solve = init, solve  # type: ignore[method-assign]
    rti = np.array(flown)
    parts = {p: np.array([s.get(p, 0.0) for s in timers.steps])[rti] * 1e6 for p in PARTS}
    return {"replay": summary, "rti_steps": int(rti.sum()), "nlp_steps": int((~rti).sum()),
            "parts_us": parts}


def report_in_flight(m: dict[str, Any], load: float) -> None:
    """The table of :func:`in_flight`'s figures (us of thread CPU)."""
    rep = m["replay"]
    print(f"in the replay itself (load avg {load:.2f}): {m['rti_steps']} RTI steps, "
          f"{m['nlp_steps']} full NLP; solve time (wall, RTI + NLP) median "
          f"{rep['solve_ms_median']:.3f} ms; max |dq| {rep['max_quat_diff']:.2g}")
    print(f"{'us per RTI step (CPU)':<26}{'median':>8}{'p95':>8}{'mean':>8}")
    for p, a in m["parts_us"].items():
        print(f"  {p:<24}{np.median(a):>8.1f}{np.percentile(a, 95):>8.1f}{np.mean(a):>8.1f}")
    s = sum(m["parts_us"].values())
    print(f"{'  sum of parts':<26}{np.median(s):>8.1f}{np.percentile(s, 95):>8.1f}"
          f"{np.mean(s):>8.1f}")
    step = sum(m["parts_us"][p] for p in PARTS[4:])
    print(f"{'  of which RtiSolver.step':<26}{np.median(step):>8.1f}"
          f"{np.percentile(step, 95):>8.1f}{np.mean(step):>8.1f}")
