"""The RMPC solver process of :mod:`companion.control.solve_guard` (``rmpc.solve_isolation =
"process"``): what runs in the child, kept light so that starting one is cheap.

A child starts from a *recipe* per NLP (:class:`NlpRecipe`: the compiled library's path, the
solver and its options, the constraint bounds' template), which the parent takes from the
:class:`~companion.core.rmpc_nlp.NlpSolver` it has already built. Loading the library is then
all the child does (~3 ms of CPU): no expression graph is built and no cache key hashed (that
was ~0.45 s of CPU per child for the two NLPs, the larger part of a restart's cost). Without a
compiled library (``rmpc.jit = false``) the child builds the solvers itself as before.

The children are forked from a small server process started once with this module (and so
CasADi) imported (``multiprocessing``'s 'forkserver'): a fresh child costs a fork and the
library load instead of a Python start-up and the CasADi import (~0.45 s of CPU). The server
inherits nothing of the companion's event loop, threads or sockets, as 'spawn' did.

Protocol (a ``multiprocessing`` pipe): the child sends ``("ready", pid)`` (or ``("failed",
message)``), then answers each ``("solve", seq, kind, w0, p, lbx, ubx, hang, cpu_limit_s,
stall_s)`` with ``("ok", seq, evaluation, cpu_s)`` or ``("error", seq, message, cpu_s)``
(``cpu_s``: the child's CPU time so far). With ``cpu_limit_s > 0`` the solve runs under
``ITIMER_PROF``: after that much CPU the kernel's SIGPROF ends the process, also inside the C
call, so a solver that never returns cannot burn a core for long even when nobody waits for it.
"""

from __future__ import annotations

import contextlib
import ctypes
import multiprocessing.connection
import os
import signal
import time
from dataclasses import dataclass
from typing import Any

import casadi as ca
import numpy as np

from companion.core.nlp_buffer import NlpBuffer

__all__ = ["NlpRecipe", "child_main"]

_PR_SET_PDEATHSIG = 1


@dataclass(frozen=True)
class NlpRecipe:
    """What a child needs to load one compiled NLP: ``ca.nlpsol(name, solver, library,
    options)`` and the constraint bounds (``lbg``, ``ubg``) the parent's solver uses."""

    kind: str
    name: str
    solver: str
    library: str
    options: dict[str, Any]
    lbg: np.ndarray
    ubg: np.ndarray
    n_p: int


class LoadedNlp:
    """A compiled NLP loaded from its library, evaluated through CasADi's zero-copy buffer
    exactly as :meth:`companion.core.rmpc_nlp.NlpSolver.evaluate` does (same library, same
    options, same arrays: bit-identical results)."""

    def __init__(self, r: NlpRecipe) -> None:
        self.solver = ca.nlpsol(r.name, r.solver, r.library, r.options)
        self._lbg, self._ubg = np.array(r.lbg, dtype=float), np.array(r.ubg, dtype=float)
        self._buffer = NlpBuffer(self.solver, self._lbg, self._ubg)

    def evaluate(self, w0: np.ndarray, par: np.ndarray, lbx: np.ndarray,
                 ubx: np.ndarray) -> tuple[int, dict[str, Any], np.ndarray, float, np.ndarray]:
        return self._buffer.evaluate(w0, par, lbx, ubx)


def _die_with_parent() -> None:
    """Linux: the kernel sends the child SIGKILL when its parent (the fork server, which
    exits with the companion) dies, so a child stuck in a solve never outlives the companion.
    Best effort elsewhere."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(_PR_SET_PDEATHSIG, int(signal.SIGKILL), 0, 0, 0)
    except (OSError, AttributeError):  # pragma: no cover - not Linux
        pass


def _release_fork_server() -> None:
    """A forked child holds the fork server's keep-alive pipe, so the server would outlive
    the companion as long as a child lives (and the child's parent-death signal would never
    come): close the child's copy (it starts no processes itself)."""
    with contextlib.suppress(Exception):
        from multiprocessing import forkserver

        server: Any = forkserver._forkserver
        fd = getattr(server, "_forkserver_alive_fd", None)
        if fd is not None:
            os.close(fd)
            server._forkserver_alive_fd = None


def _load(recipes: dict[str, NlpRecipe | None], build_args: tuple[Any, ...],
          kinds: dict[str, tuple[bool, str]]) -> dict[str, Any]:
    """The solvers by kind: from the recipes' libraries, else built (``rmpc.jit = false``)."""
    out: dict[str, Any] = {}
    for kind, (soft, name) in kinds.items():
        recipe = recipes.get(kind)
        if recipe is not None:
            out[kind] = LoadedNlp(recipe)
        else:
            from companion.core.rmpc_nlp import NlpSolver  # builds the expression graph

            rmpc, camera, terminal = build_args
            out[kind] = NlpSolver(rmpc, camera, terminal, soft=soft, solver=name)
    return out


def child_main(conn: multiprocessing.connection.Connection,
               recipes: dict[str, NlpRecipe | None], build_args: tuple[Any, ...],
               kinds: dict[str, tuple[bool, str]]) -> None:
    """The solver process: load the solvers, then evaluate until told to stop (module
    docstring has the protocol)."""
    ppid = os.getppid()
    _die_with_parent()
    if os.getppid() != ppid:  # the parent died before prctl took effect
        return
    _release_fork_server()
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the parent's to handle
    signal.signal(signal.SIGPROF, signal.SIG_DFL)  # the CPU-time bound ends the process
    try:
        solvers = _load(recipes, build_args, kinds)
    except Exception as exc:  # reported to the parent, which raises RmpcBuildError
        conn.send(("failed", f"{type(exc).__name__}: {exc}"))
        return
    conn.send(("ready", os.getpid()))
    while True:
        try:
            msg = conn.recv()
        except (EOFError, OSError):  # the parent closed the pipe or died
            return
        if msg[0] != "solve":
            return
        conn.send(_solve(solvers, msg))


def _solve(solvers: dict[str, Any], msg: tuple[Any, ...]) -> tuple[str, int, Any, float]:
    _, seq, kind, w0, par, lbx, ubx, hang, cpu_limit_s, stall_s = msg
    reply: tuple[str, int, Any, float]
    if cpu_limit_s > 0.0:  # SIGPROF (default action: terminate) after that much CPU
        signal.setitimer(signal.ITIMER_PROF, cpu_limit_s)
    try:
        out: Any = solvers[kind].evaluate(w0, par, lbx, ubx)
        reply = ("ok", seq, out, time.process_time())
    except RuntimeError as exc:
        reply = ("error", seq, str(exc), time.process_time())
    if hang:  # test hook: a solver that never returns and ignores SIGTERM
        signal.signal(signal.SIGTERM, signal.SIG_IGN)
        while True:
            pass
    if stall_s > 0.0:  # test hook: a solve descheduled on a busy machine (no CPU used)
        time.sleep(stall_s)
    if cpu_limit_s > 0.0:
        signal.setitimer(signal.ITIMER_PROF, 0.0)
    return reply
