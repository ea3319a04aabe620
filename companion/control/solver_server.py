"""The server the RMPC's solver processes are forked from (``multiprocessing``'s 'forkserver',
with :mod:`companion.control.solver_child` and so CasADi imported once): its context for
:mod:`companion.control.solve_guard`, and :func:`start_server` to start it early."""

from __future__ import annotations

import logging
import multiprocessing
from typing import Any

log = logging.getLogger(__name__)


def solver_context() -> Any:
    """'forkserver' (children forked from a clean server with CasADi imported: cheap starts,
    nothing of the companion's loop, threads or sockets inherited), else 'spawn'."""
    if "forkserver" in multiprocessing.get_all_start_methods():
        ctx = multiprocessing.get_context("forkserver")
        ctx.set_forkserver_preload(["companion.control.solver_child"])
        return ctx
    return multiprocessing.get_context("spawn")  # pragma: no cover - not POSIX


def start_server() -> None:
    """Start the solver processes' server now, not at the first child's start: the server
    imports CasADi (~0.45 s of CPU) while the caller waits for something else (the companion
    for the autopilot's limits, which its controller is built from; on a small computer that
    import was ~1.5 s of the wait between the limits' arrival and the first step). Returns at
    once (the server imports in its own process); a no-op where there is no 'forkserver'. An
    OS error (no file descriptor or process left) is logged, not raised: the first child's start
    meets it again and reports it as the controller's build error, as before."""
    ctx = solver_context()
    if ctx.get_start_method() == "forkserver":
        from multiprocessing import forkserver

        try:
            forkserver.ensure_running()
        except OSError as exc:
            log.warning("RMPC solver server not started early: %s", exc)
