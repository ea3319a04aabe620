"""A wall-time bound on the RMPC's solves: they run in a child process that is killed when a
step's solves exceed ``rmpc.max_solve_time_s`` (``rmpc.solve_isolation = "process"``).

Why a process: a compiled CasADi solver is one C call. A solver that never returns (seen:
fatrop's restoration phase looping at 100 % CPU, ``max_iter`` not bounding it) cannot be
interrupted from Python in the same process: signal handlers do not run inside the call, and a
worker thread (CasADi releases the GIL, so a thread would keep the loop alive) can be abandoned
but never stopped, so it would burn one of the companion computer's cores for good. A child
process can be killed (SIGKILL) and replaced. fatrop has no time option at all
(``max_wall_time``/``max_cpu_time`` are refused as unsupported options); ipopt has them but
they are checked only between iterations. docs/reference/reliability.md has the measurements.

Protocol (a ``multiprocessing`` pipe, 'spawn' start: nothing of the parent's event loop,
threads or sockets is inherited): the child builds the controller's compiled solvers from the
on-disk cache (:mod:`companion.core.rmpc_cache`: the parent compiled them, the child only loads
the libraries), sends ``("ready", pid)``, then answers each ``("solve", kind, w0, p, lbx, ubx,
hang)`` with ``("ok", evaluation, cpu_s)`` or ``("error", message, cpu_s)`` (CasADi raised;
``cpu_s``: the child's CPU time so far, so the companion's CPU figures include it). On a timeout the
parent kills the child, starts a fresh one in the background and the step flies the terminal
law (:class:`~companion.core.rmpc.SolveAborted` -> ``mode='fallback'``, status ``timeout:
...``); steps while the new child starts fly the fallback too (status ``solver restarting``).
The parent never blocks longer than the step's bound, so SIGTERM/SIGINT are served by the
event loop at the next step boundary.

``rmpc.solver_spare`` (a vehicle's default): a second child is started once the first is ready
and waits, loaded, beside it (~60 MB, ~0.7 s of CPU once). A timeout or a lost child then
promotes the spare, so the next step solves instead of flying the fallback for the ~0.6-1 s a
fresh child takes to load; a new spare is started once the promoted one answers.

``rmpc.solve_time_clock = "cpu"`` (what lockstep simulations use): the bound counts the solver
process's own CPU time instead, per solve. The child arms ``ITIMER_PROF`` with the bound before
each solve (SIGPROF's default action terminates the process, also inside the C call) and
disarms it after; the parent waits only up to a wall-time backstop
(:func:`cpu_clock_wall_backstop_s`) and reports a child killed by SIGPROF as a timeout. A
machine so busy that a 2 ms solve takes a second of wall time then no longer cuts it.
"""

from __future__ import annotations

import contextlib
import ctypes
import logging
import multiprocessing
import multiprocessing.connection
import os
import signal
import time
import weakref
from collections.abc import Callable
from multiprocessing.process import BaseProcess
from typing import Any

import numpy as np

from companion.core.params import CameraParams, RmpcParams
from companion.core.rmpc import Evaluation, Rmpc, RmpcBuildError, SolveAborted
from companion.core.terminal import TerminalDesign

__all__ = ["ProcessSolveBackend", "process_backend"]

log = logging.getLogger(__name__)

START_TIMEOUT_S = 120.0
"""How long the first child may take to load the solvers (a cold, loaded machine: import
CasADi, build the expression graphs, load two libraries; ~1-2 s measured idle)."""

_PR_SET_PDEATHSIG = 1


def _die_with_parent() -> None:
    """Linux: the kernel sends the child SIGKILL when the parent dies (even by SIGKILL), so a
    child stuck in a solve never outlives the companion. Best effort elsewhere."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(_PR_SET_PDEATHSIG, int(signal.SIGKILL), 0, 0, 0)
    except (OSError, AttributeError):  # pragma: no cover - not Linux
        pass


def _child_main(conn: multiprocessing.connection.Connection, rmpc: RmpcParams,
                camera: CameraParams, terminal: TerminalDesign,
                kinds: dict[str, tuple[bool, str]], parent_pid: int) -> None:
    """The solver process: load the compiled solvers, then evaluate until told to stop."""
    _die_with_parent()
    if os.getppid() != parent_pid:  # the parent died before prctl took effect
        return
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the parent's to handle
    signal.signal(signal.SIGPROF, signal.SIG_DFL)  # the CPU-time bound ends the process
    from companion.core.rmpc_nlp import NlpSolver  # the core's solver wrapper, same cache

    try:
        solvers = {kind: NlpSolver(rmpc, camera, terminal, soft=soft, solver=name)
                   for kind, (soft, name) in kinds.items()}
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
        _, kind, w0, par, lbx, ubx, hang, cpu_limit_s, stall_s = msg
        reply: tuple[str, Any, float]
        if cpu_limit_s > 0.0:  # SIGPROF (default action: terminate) after that much CPU
            signal.setitimer(signal.ITIMER_PROF, cpu_limit_s)
        try:
            out: Any = solvers[kind].evaluate(w0, par, lbx, ubx)
            reply = ("ok", out, time.process_time())
        except RuntimeError as exc:
            reply = ("error", str(exc), time.process_time())
        if hang:  # test hook: a solver that never returns and ignores SIGTERM
            signal.signal(signal.SIGTERM, signal.SIG_IGN)
            while True:
                pass
        if stall_s > 0.0:  # test hook: a solve descheduled on a busy machine (no CPU used)
            time.sleep(stall_s)
        if cpu_limit_s > 0.0:
            signal.setitimer(signal.ITIMER_PROF, 0.0)
        conn.send(reply)


def cpu_clock_wall_backstop_s(max_solve_time_s: float) -> float:
    """With ``solve_time_clock = "cpu"``: how long (wall) the parent waits for a step's solves
    before it kills the child anyway (a child that gets no CPU at all, or is stopped)."""
    return max(10.0, 20.0 * max_solve_time_s)


class ProcessSolveBackend:
    """Runs a :class:`~companion.core.rmpc.Rmpc`'s solves in a child process, each step's
    solves bounded by ``max_solve_time_s`` of wall time (module docstring).

    ``clock``: monotonic seconds (the step's deadline). The constructor blocks until the first
    child is ready (``start_timeout_s``), so the first step solves; it raises
    :class:`~companion.core.rmpc.RmpcBuildError` if the child cannot load the solvers. With
    ``defer_ready`` (what the companion uses) it returns at once and the first solve waits
    for the first child instead (raising the same error), so the child's ~1 s of loading
    overlaps the companion's connecting and waiting for its first frame.
    """

    def __init__(self, rmpc: RmpcParams, camera: CameraParams, terminal: TerminalDesign,
                 kinds: dict[str, tuple[bool, str]], max_solve_time_s: float,
                 clock: Callable[[], float] = time.monotonic,
                 start_timeout_s: float = START_TIMEOUT_S, defer_ready: bool = False,
                 time_clock: str = "wall", spare: bool = False) -> None:
        if not (np.isfinite(max_solve_time_s) and max_solve_time_s > 0):
            raise ValueError(f"max_solve_time_s: must be finite and > 0 (got {max_solve_time_s})")
        if time_clock not in ("wall", "cpu"):
            raise ValueError(f"time_clock: {time_clock!r} is not 'wall' or 'cpu'")
        self._args = (rmpc, camera, terminal, dict(kinds))
        self.max_solve_time_s = float(max_solve_time_s)
        self.time_clock = time_clock
        # the parent's wait per step: the bound itself (wall), or only a backstop (cpu)
        self._wait_s = (self.max_solve_time_s if time_clock == "wall"
                        else cpu_clock_wall_backstop_s(self.max_solve_time_s))
        self._stall_next_s = 0.0
        self._clock = clock
        self._ctx = multiprocessing.get_context("spawn")
        self._proc: BaseProcess | None = None
        self._conn: multiprocessing.connection.Connection | None = None
        self._ready = False
        self._use_spare = bool(spare)
        # the loaded stand-by child (started once the current one is ready) and its finalizer
        self._spare: tuple[BaseProcess, multiprocessing.connection.Connection] | None = None
        self._spare_finalizer: weakref.finalize[Any, Any] | None = None
        self.promotions = 0
        """Restarts served by the warm spare (a subset of :attr:`restarts`)."""
        self._deadline = 0.0
        self._hang_next = False
        self.restarts = 0
        """Children killed (timeout) or lost (died) and replaced since construction."""
        self.timeouts = 0
        self._cpu_dead_s = 0.0  # CPU last reported by the children already replaced
        self._cpu_live_s = 0.0  # CPU last reported by the current child
        self._start()
        self._finalizer = weakref.finalize(self, ProcessSolveBackend._stop_child, self._proc,
                                           self._conn)
        self._start_timeout_s = float(start_timeout_s)
        # defer_ready: the first child loads while the companion connects and waits for its
        # first frame (~1 s of imports and library loading); the first solve waits for it
        self._first_pending = bool(defer_ready)
        if not defer_ready:
            self._wait_first()

    def _wait_first(self) -> None:
        if not self.wait_ready(self._start_timeout_s):
            self.close()
            raise RmpcBuildError(f"solver process not ready within {self._start_timeout_s:g} s")

    # --- child lifecycle -------------------------------------------------------------------
    def _spawn(self, name: str) -> tuple[BaseProcess, multiprocessing.connection.Connection]:
        parent, child = self._ctx.Pipe(duplex=True)
        proc = self._ctx.Process(target=_child_main, args=(child, *self._args, os.getpid()),
                                 name=name, daemon=True)
        proc.start()
        child.close()
        return proc, parent

    def _start(self, promote: bool = False) -> None:
        if promote and self._spare is not None:  # the loaded spare takes over
            proc, parent = self._spare
            self._spare = None
            if self._spare_finalizer is not None:
                self._spare_finalizer.detach()
                self._spare_finalizer = None
            self.promotions += 1
        else:
            proc, parent = self._spawn("rmpc-solver")
        self._proc, self._conn, self._ready = proc, parent, False
        if hasattr(self, "_finalizer"):
            self._finalizer.detach()
            self._finalizer = weakref.finalize(self, ProcessSolveBackend._stop_child, proc,
                                               parent)

    @staticmethod
    def _stop_child(proc: BaseProcess | None,
                    conn: multiprocessing.connection.Connection | None) -> None:
        if conn is not None:
            with contextlib.suppress(OSError):
                conn.close()
        if proc is not None and proc.is_alive():
            proc.kill()
            proc.join(5.0)

    def _start_spare(self) -> None:
        if not self._use_spare or self._spare is not None:
            return
        self._spare = self._spawn("rmpc-solver-spare")
        self._spare_finalizer = weakref.finalize(self, ProcessSolveBackend._stop_child,
                                                 *self._spare)

    def _restart(self, why: str) -> None:
        log.error("RMPC solver process %s: killing pid %s and %s", why,
                  self._proc.pid if self._proc is not None else None,
                  f"promoting the spare (pid {self._spare[0].pid})" if self._spare is not None
                  else "starting a fresh one")
        self._stop_child(self._proc, self._conn)
        self.restarts += 1
        self._cpu_dead_s += self._cpu_live_s
        self._cpu_live_s = 0.0
        self._start(promote=True)  # the spare if there is one, else a fresh child

    @property
    def pid(self) -> int | None:
        """The current child's pid (None before start)."""
        return self._proc.pid if self._proc is not None else None

    @property
    def child_cpu_s(self) -> float:
        """CPU time (user + system, s) the solver children reported with their last results
        (a killed child's CPU after its last result is not included)."""
        return self._cpu_dead_s + self._cpu_live_s

    @property
    def ready(self) -> bool:
        return self._poll_ready(0.0)

    def _poll_ready(self, timeout_s: float) -> bool:
        if self._ready:
            return True
        assert self._conn is not None and self._proc is not None
        try:
            if not self._conn.poll(timeout_s):
                if not self._proc.is_alive():
                    raise EOFError
                return False
            msg = self._conn.recv()
        except (EOFError, OSError) as exc:
            raise RmpcBuildError(f"solver process exited while loading (code "
                                 f"{self._proc.exitcode})") from exc
        if msg[0] != "ready":
            raise RmpcBuildError(f"solver process could not load the solvers: {msg[1]}")
        self._ready = True
        log.info("RMPC solver process ready (pid %s)", msg[1])
        self._start_spare()  # the next one loads while this one solves
        return True

    def wait_ready(self, timeout_s: float) -> bool:
        """Block until the current child is ready (True) or ``timeout_s`` passed (False)."""
        end = self._clock() + timeout_s
        while True:
            if self._poll_ready(max(0.0, min(0.5, end - self._clock()))):
                return True
            if self._clock() >= end:
                return False

    def close(self) -> None:
        for conn in (self._conn, self._spare[1] if self._spare is not None else None):
            if conn is not None:
                with contextlib.suppress(OSError):
                    conn.send(("close",))
        self._finalizer()
        if self._spare_finalizer is not None:
            self._spare_finalizer()
        self._spare, self._spare_finalizer = None, None
        self._ready = False

    # --- SolveBackend ------------------------------------------------------------------------
    def start_step(self) -> None:
        self._deadline = self._clock() + self._wait_s

    def hang_next_solve(self, on: bool = True) -> None:
        """Test hook: the child's next solve (the next one sent to a ready child) computes its
        result and then never returns it (spinning at 100 % CPU with SIGTERM ignored), like the
        stuck fatrop solve. ``on=False`` withdraws a pending request."""
        self._hang_next = on

    def stall_next_solve(self, seconds: float) -> None:
        """Test hook: the child's next solve sleeps ``seconds`` (no CPU) before answering, as
        a solve descheduled on a busy machine."""
        self._stall_next_s = float(seconds)

    def evaluate(self, kind: str, w0: np.ndarray, par: np.ndarray, lbx: np.ndarray,
                 ubx: np.ndarray) -> Evaluation:
        if self._first_pending:  # the first child: wait for it (a failure is a start failure)
            self._first_pending = False
            self._wait_first()
            self._deadline = self._clock() + self._wait_s
        try:
            ready = self._poll_ready(0.0)
        except RmpcBuildError as exc:  # the new child failed: try again next step
            self._restart(f"failed to start ({exc})")
            raise SolveAborted(f"solver restarting: {exc}") from exc
        if not ready:
            raise SolveAborted("solver restarting (after a timeout): terminal law meanwhile")
        remaining = self._deadline - self._clock()
        if remaining <= 0.0:
            self.timeouts += 1
            raise SolveAborted(f"timeout: no time left for the {kind} solve within "
                               f"rmpc.max_solve_time_s = {self.max_solve_time_s:g} s")
        assert self._conn is not None
        hang, self._hang_next = self._hang_next, False
        stall, self._stall_next_s = self._stall_next_s, 0.0
        cpu_limit = self.max_solve_time_s if self.time_clock == "cpu" else 0.0
        try:
            self._conn.send(("solve", kind, w0, par, lbx, ubx, hang, cpu_limit, stall))
            if not self._conn.poll(remaining):
                self.timeouts += 1
                what = ("s" if self.time_clock == "wall" else
                        f"s of CPU: no answer within the {self._wait_s:g} s wall backstop")
                self._restart(f"{kind} solve exceeded {self.max_solve_time_s:g} {what}")
                raise SolveAborted(f"timeout: {kind} solve exceeded rmpc.max_solve_time_s = "
                                   f"{self.max_solve_time_s:g} {what} (solver process restarted)")
            status, payload, self._cpu_live_s = self._conn.recv()
        except (EOFError, OSError) as exc:
            assert self._proc is not None
            self._proc.join(1.0)  # the exit code says whether the CPU-time bound ended it
            code = self._proc.exitcode
            if self.time_clock == "cpu" and code == -signal.SIGPROF:
                self.timeouts += 1
                self._restart(f"{kind} solve exceeded {self.max_solve_time_s:g} s of CPU")
                raise SolveAborted(f"timeout: {kind} solve exceeded rmpc.max_solve_time_s = "
                                   f"{self.max_solve_time_s:g} s of CPU (solver process "
                                   "restarted)") from exc
            self._restart(f"lost (exit code {code})")
            raise SolveAborted(f"solver process lost during the {kind} solve (exit code "
                               f"{code}; restarted)") from exc
        if status == "error":
            raise RuntimeError(payload)
        flag, stats, x, f, g = payload
        return int(flag), dict(stats), np.asarray(x, dtype=float), float(f), \
            np.asarray(g, dtype=float)


def process_backend(rmpc: RmpcParams, camera: CameraParams,
                    terminal: TerminalDesign) -> Callable[[Rmpc], ProcessSolveBackend]:
    """The ``backend`` argument of :class:`~companion.core.rmpc.Rmpc` for
    ``rmpc.solve_isolation = "process"`` (the child loads what the parent compiled)."""

    def make(mpc: Rmpc) -> ProcessSolveBackend:
        return ProcessSolveBackend(rmpc, camera, terminal, mpc.solver_kinds(),
                                   rmpc.max_solve_time_s, defer_ready=True,
                                   time_clock=rmpc.solve_time_clock,
                                   spare=rmpc.solver_spare)

    return make
