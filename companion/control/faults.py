"""Fault injection windows (``companion run --inject-fault KIND:T0:T1``), for tests and bench."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from companion import CompanionError

FAULT_KINDS = ("solver", "solver-hang")


@dataclass(frozen=True)
class FaultWindow:
    """Fault injection for tests and bench (like PX4's failure injection) during ``[t0_s,
    t1_s)`` after the first frame: ``kind`` is ``solver`` (every solve reported failed) or
    ``solver-hang`` (each step's solve never returns: the solver process's test hook, cut by
    ``rmpc.max_solve_time_s``; needs ``rmpc.solve_isolation = "process"``)."""

    kind: str
    t0_s: float
    t1_s: float

    @classmethod
    def parse(cls, text: str) -> FaultWindow:
        try:
            kind, t0, t1 = text.split(":")
            w = cls(kind, float(t0), float(t1))
        except ValueError:
            raise CompanionError(f"--inject-fault {text!r}: expected KIND:T0:T1") from None
        if w.kind not in FAULT_KINDS or not w.t1_s > w.t0_s:
            raise CompanionError(f"--inject-fault {text!r}: kind one of {FAULT_KINDS} and "
                                 "T1 > T0 only")
        return w


def check_faults(faults: Sequence[FaultWindow], controller: Any) -> None:
    """Refuse a window the controller cannot carry out (a hang needs the solver's process)."""
    if any(f.kind == "solver-hang" for f in faults) and not hasattr(
            getattr(controller, "backend", None), "hang_next_solve"):
        raise CompanionError("--inject-fault solver-hang: needs controller.kind an RMPC "
                             "with rmpc.solve_isolation = \"process\"")


def apply_faults(faults: Sequence[FaultWindow], pipeline: Any, elapsed_s: float) -> None:
    """Set the pipeline's faults for a step ``elapsed_s`` after the first frame: a failed
    solve inside a ``solver`` window; the solver process's hang hook inside a
    ``solver-hang`` window (withdrawn after it)."""
    pipeline.force_solver_failure = any(
        f.t0_s <= elapsed_s < f.t1_s for f in faults if f.kind == "solver")
    hang = [f.t0_s <= elapsed_s < f.t1_s for f in faults if f.kind == "solver-hang"]
    if hang:
        pipeline.rmpc.backend.hang_next_solve(any(hang))
        # rmpc.solver = "rti": the step must reach the NLP's child for the hook to bite
        pipeline.rmpc.force_nlp = any(hang)
