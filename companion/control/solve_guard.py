"""A time bound on the RMPC's solves: they run in a child process, a step whose solves overrun
``rmpc.max_solve_time_s`` flies the terminal law, and a child that is *stuck* is killed and
replaced (``rmpc.solve_isolation = "process"``).

Why a process: a compiled CasADi solver is one C call. A solver that never returns (seen:
fatrop's restoration phase looping at 100 % CPU, ``max_iter`` not bounding it) cannot be
interrupted from Python in the same process (no signal handler runs inside the call; a worker
thread can be abandoned, never stopped); a child process can be killed and replaced. fatrop has
no time option; ipopt's are checked only between iterations (docs/reference/reliability.md).

The child (:mod:`companion.control.solver_child`, forked from a server process that has
CasADi loaded) loads the compiled libraries the parent built and answers each solve over a
pipe; its answers are bit-identical to an in-process solve.

**A stuck solver is not a starved one.** With ``rmpc.solve_time_clock = "wall"`` (a vehicle)
the parent waits for a step's solves until ``max_solve_time_s`` of wall time after the step
began; then the step flies the terminal law (:class:`~companion.core.rmpc.SolveAborted` ->
``mode='fallback'``, status ``timeout: ...``). Whether the child is killed depends on the CPU
it used for the solve (``/proc/<pid>/stat``): at least half the bound (``HUNG_CPU_SHARE``)
means it was running and did not finish: stuck, killed and replaced. Less means it was waiting
for a CPU (a companion computer short of CPU, a busy machine): it is kept, its late answer is
discarded when it comes, and the next step's solve queues behind it, so a small CPU budget no
longer turns into a spiral of restarts (each of which cost ~0.9 s of CPU before the fork
server). Every solve also runs under the child's own CPU-time bound (``ITIMER_PROF`` =
``max_solve_time_s``: SIGPROF ends the process, also inside the C call), so a stuck solve that
is waited for by nobody still ends, and an answer outstanding longer than a wall backstop
(:func:`cpu_clock_wall_backstop_s`: a child that gets no CPU at all, or is stopped) ends it too.

``rmpc.solve_time_clock = "cpu"`` (what lockstep simulations use): the parent waits up to the
backstop only; the CPU-time bound alone decides (a machine so busy that a 2 ms solve takes a
second of wall time then no longer cuts it); the step flies the terminal law only when the child
was ended.

``rmpc.solver_spare`` (a vehicle's default): a second child is started beside the first and
waits, loaded; a killed or lost child is replaced by it, so the next step solves instead of
flying the fallback while a fresh child loads; a new spare is started once the promoted one is
ready.

The parent never blocks longer than the step's bound (wall) or the backstop (cpu).
"""

from __future__ import annotations

import contextlib
import logging
import multiprocessing
import multiprocessing.connection
import os
import signal
import time
import weakref
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from multiprocessing.process import BaseProcess
from typing import Any

import numpy as np

from companion.control.solver_child import NlpRecipe, child_main
from companion.control.solver_server import solver_context
from companion.core.params import CameraParams, RmpcParams
from companion.core.rmpc import Evaluation, Rmpc, RmpcBuildError, SolveAborted
from companion.core.terminal import TerminalDesign

__all__ = ["HUNG_CPU_SHARE", "ProcessSolveBackend", "nlp_recipes", "process_backend"]

log = logging.getLogger(__name__)

START_TIMEOUT_S = 120.0
"""How long the first child may take to load the solvers (a cold, loaded machine: the fork
server's CasADi import, two libraries; ~0.5-1 s measured idle)."""

HUNG_CPU_SHARE = 0.5
"""A solve still running at its wall deadline is stuck (killed) when it used at least this
share of ``max_solve_time_s`` as CPU; below, it waited for a CPU and is kept."""

_CLK_TCK = os.sysconf("SC_CLK_TCK") if hasattr(os, "sysconf") else 100


def _proc_cpu_s(pid: int | None) -> float | None:
    """The CPU time (user + system, s) process ``pid`` used so far, from /proc (10 ms
    resolution); None when it cannot be read (not Linux, the process is gone)."""
    if pid is None:
        return None
    try:
        with open(f"/proc/{pid}/stat", "rb") as f:
            fields = f.read().rsplit(b")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / _CLK_TCK
    except (OSError, IndexError, ValueError):
        return None


def cpu_clock_wall_backstop_s(max_solve_time_s: float) -> float:
    """How long (wall) an answer may be outstanding before the child is killed anyway (a
    child that gets no CPU at all, or is stopped); with ``solve_time_clock = "cpu"`` also how
    long the parent waits for a step's solves."""
    return max(10.0, 20.0 * max_solve_time_s)


@dataclass(frozen=True)
class _Request:
    seq: int
    sent_s: float  # clock
    cpu0_s: float | None  # the child's CPU time when it was sent (/proc)


_Child = tuple[BaseProcess, multiprocessing.connection.Connection]


class ProcessSolveBackend:
    """Runs a :class:`~companion.core.rmpc.Rmpc`'s solves in a child process, each step's
    solves bounded by ``max_solve_time_s`` (module docstring).

    ``recipes``: per NLP kind, what a child loads (:func:`nlp_recipes`; a kind without one is
    built in the child). ``clock``: monotonic seconds (the step's deadline). The constructor
    blocks until the first child is ready (``start_timeout_s``), so the first step solves; it
    raises :class:`~companion.core.rmpc.RmpcBuildError` if the child cannot load the solvers.
    With ``defer_ready`` (what the companion uses) it returns at once and the first solve
    waits for the first child instead (raising the same error).
    """

    def __init__(self, rmpc: RmpcParams, camera: CameraParams, terminal: TerminalDesign,
                 kinds: dict[str, tuple[bool, str]], max_solve_time_s: float,
                 clock: Callable[[], float] = time.monotonic,
                 start_timeout_s: float = START_TIMEOUT_S, defer_ready: bool = False,
                 time_clock: str = "wall", spare: bool = False,
                 recipes: dict[str, NlpRecipe | None] | None = None) -> None:
        if not (np.isfinite(max_solve_time_s) and max_solve_time_s > 0):
            raise ValueError(f"max_solve_time_s: must be finite and > 0 (got {max_solve_time_s})")
        if time_clock not in ("wall", "cpu"):
            raise ValueError(f"time_clock: {time_clock!r} is not 'wall' or 'cpu'")
        self._args = (dict(recipes or {}), (rmpc, camera, terminal), dict(kinds))
        self.max_solve_time_s = float(max_solve_time_s)
        self.time_clock = time_clock
        self.backstop_s = cpu_clock_wall_backstop_s(self.max_solve_time_s)
        # the parent's wait per step: the bound itself (wall), or only the backstop (cpu)
        self._wait_s = self.max_solve_time_s if time_clock == "wall" else self.backstop_s
        self._stall_next_s = 0.0
        self._clock = clock
        self._ctx = solver_context()
        self._proc: BaseProcess | None = None
        self._conn: multiprocessing.connection.Connection | None = None
        self._ready = False
        self._use_spare = bool(spare)
        self._spare: _Child | None = None  # the loaded stand-by child and its finalizer
        self._spare_finalizer: weakref.finalize[Any, Any] | None = None
        self._inflight: deque[_Request] = deque()  # sent, not answered yet (oldest first)
        self._seq = 0
        self.promotions = 0
        """Restarts served by the warm spare (a subset of :attr:`restarts`)."""
        self._deadline = 0.0
        self._hang_next = False
        self.restarts = 0
        """Children killed (stuck) or lost (died) and replaced since construction."""
        self.timeouts = 0
        """Solves abandoned at the deadline (stuck or starved)."""
        self.starved = 0
        """Of :attr:`timeouts`: solves that waited for a CPU; their child was kept."""
        self.late_answers = 0
        """Answers that came after their step had flown the fallback (discarded)."""
        self._cpu_dead_s = 0.0  # CPU of the children already replaced
        self._cpu_live_s = 0.0  # CPU last reported by the current child
        self._start()
        self._finalizer = weakref.finalize(self, ProcessSolveBackend._stop_child, self._proc,
                                           self._conn)
        self._start_spare()  # forked beside the first: it loads before the flight
        self._start_timeout_s = float(start_timeout_s)
        self._first_pending = bool(defer_ready)
        if not defer_ready:
            self._wait_first()

    def _wait_first(self) -> None:
        if not self.wait_ready(self._start_timeout_s):
            self.close()
            raise RmpcBuildError(f"solver process not ready within {self._start_timeout_s:g} s")

    # --- child lifecycle -------------------------------------------------------------------
    def _spawn(self, name: str) -> _Child:
        parent, child = self._ctx.Pipe(duplex=True)
        proc = self._ctx.Process(target=child_main, args=(child, *self._args), name=name,
                                 daemon=True)
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
        self._inflight.clear()
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
        last = _proc_cpu_s(self.pid)  # its CPU since its last answer counts too
        self._stop_child(self._proc, self._conn)
        self.restarts += 1
        self._cpu_dead_s += max(self._cpu_live_s, last or 0.0)
        self._cpu_live_s = 0.0
        self._start(promote=True)  # the spare if there is one, else a fresh child

    @property
    def pid(self) -> int | None:
        """The current child's pid (None before start)."""
        return self._proc.pid if self._proc is not None else None

    @property
    def child_cpu_s(self) -> float:
        """CPU time (user + system, s) of the solver children: as they reported with their
        last answers, and for a killed child up to its kill."""
        return self._cpu_dead_s + self._cpu_live_s

    @property
    def busy(self) -> bool:
        """An abandoned solve is still running in the child (its answer will be discarded)."""
        return bool(self._inflight)

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

    def settle(self, timeout_s: float) -> bool:
        """Block until no abandoned solve is outstanding (its late answer taken, or the child
        ended by its CPU-time bound and replaced): True, or False after ``timeout_s``."""
        end = self._clock() + timeout_s
        while self._inflight:
            assert self._conn is not None
            try:
                if self._conn.poll(max(0.0, min(0.5, end - self._clock()))):
                    self._take(self._conn.recv())
                    self.late_answers += 1
            except (EOFError, OSError):
                self._lost("settle")
                return True
            if self._inflight and self._clock() >= end:
                return False
        return True

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
        a solve waiting for a CPU on a machine short of it."""
        self._stall_next_s = float(seconds)

    def evaluate(self, kind: str, w0: np.ndarray, par: np.ndarray, lbx: np.ndarray,
                 ubx: np.ndarray) -> Evaluation:
        self._check_ready()
        assert self._conn is not None
        try:
            self._collect()
            self._check_stuck(kind)
            remaining = self._deadline - self._clock()
            if remaining <= 0.0:
                self.timeouts += 1
                raise SolveAborted(f"timeout: no time left for the {kind} solve within "
                                   f"rmpc.max_solve_time_s = {self.max_solve_time_s:g} s")
            seq = self._send(kind, w0, par, lbx, ubx)
            msg = self._await(seq)
        except (EOFError, OSError) as exc:
            raise self._lost(kind) from exc
        if msg is None:
            raise self._overrun(kind)
        status, _, payload, _ = msg
        if status == "error":
            raise RuntimeError(payload)
        flag, stats, x, f, g = payload
        return int(flag), dict(stats), np.asarray(x, dtype=float), float(f), \
            np.asarray(g, dtype=float)

    # --- the parts of a solve -------------------------------------------------------------
    def _check_ready(self) -> None:
        """The first child (a failure is a start failure), or a restarted one (its steps fly
        the fallback until it is ready)."""
        if self._first_pending:
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

    def _take(self, msg: tuple[Any, ...]) -> tuple[Any, ...]:
        """Book an answer: the oldest request is done; its child's CPU so far."""
        while self._inflight and self._inflight[0].seq != msg[1]:
            self._inflight.popleft()  # (answers come in order: nothing is skipped)
        if self._inflight:
            self._inflight.popleft()
        self._cpu_live_s = float(msg[3])
        return msg

    def _collect(self) -> None:
        """Take the late answers that have arrived for abandoned solves (no wait)."""
        assert self._conn is not None
        while self._inflight and self._conn.poll(0.0):
            self._take(self._conn.recv())
            self.late_answers += 1

    def _check_stuck(self, kind: str) -> None:
        """An abandoned solve still running past the CPU-time bound or the wall backstop: the
        child is stuck (or stopped): replace it; this step flies the fallback."""
        if not self._inflight:
            return
        req = self._inflight[0]
        cpu = _proc_cpu_s(self.pid)
        used = None if cpu is None or req.cpu0_s is None else cpu - req.cpu0_s
        waited = self._clock() - req.sent_s
        if waited >= self.backstop_s or (used is not None and used >= self.max_solve_time_s):
            self.timeouts += 1
            why = (f"an abandoned solve still running after {waited:.1f} s ("
                   f"{'?' if used is None else f'{used:.2f}'} s of CPU)")
            self._restart(why)
            raise SolveAborted(f"timeout: {why} (solver process restarted; {kind} solve not "
                               "sent)")

    def _send(self, kind: str, w0: np.ndarray, par: np.ndarray, lbx: np.ndarray,
              ubx: np.ndarray) -> int:
        assert self._conn is not None
        hang, self._hang_next = self._hang_next, False
        stall, self._stall_next_s = self._stall_next_s, 0.0
        self._seq += 1
        self._inflight.append(_Request(self._seq, self._clock(), _proc_cpu_s(self.pid)))
        self._conn.send(("solve", self._seq, kind, w0, par, lbx, ubx, hang,
                         self.max_solve_time_s, stall))
        return self._seq

    def _await(self, seq: int) -> tuple[Any, ...] | None:
        """The answer to request ``seq`` by the step's deadline (earlier requests' late
        answers are taken and discarded on the way), else None."""
        assert self._conn is not None
        while True:
            remaining = self._deadline - self._clock()
            if remaining <= 0.0 or not self._conn.poll(remaining):
                return None
            msg = self._take(self._conn.recv())
            if msg[1] == seq:
                return msg
            self.late_answers += 1

    def _overrun(self, kind: str) -> SolveAborted:
        """No answer by the deadline: stuck (killed, replaced) or starved (kept)."""
        self.timeouts += 1
        bound = f"rmpc.max_solve_time_s = {self.max_solve_time_s:g} s"
        if self.time_clock == "cpu":  # the backstop passed: no CPU at all, or stopped
            self._restart(f"{kind} solve: no answer within the {self._wait_s:g} s wall backstop")
            return SolveAborted(f"timeout: {kind} solve exceeded {bound} of CPU: no answer "
                                f"within the {self._wait_s:g} s wall backstop (solver process "
                                "restarted)")
        req = self._inflight[0]
        cpu = _proc_cpu_s(self.pid)
        used = None if cpu is None or req.cpu0_s is None else cpu - req.cpu0_s
        if used is None or used >= HUNG_CPU_SHARE * self.max_solve_time_s:
            self._restart(f"{kind} solve exceeded {self.max_solve_time_s:g} s")
            return SolveAborted(f"timeout: {kind} solve exceeded {bound} (solver process "
                                "restarted)")
        self.starved += 1
        log.warning("RMPC %s solve not answered within %s, %.3f s of CPU used: waiting for a "
                    "CPU, solver process kept (its answer will be discarded)", kind, bound, used)
        return SolveAborted(f"timeout: {kind} solve exceeded {bound} with {used:.3f} s of CPU "
                            "(starved: solver process kept)")

    def _lost(self, kind: str) -> SolveAborted:
        """The child's pipe ended: ended by its CPU-time bound (stuck) or died otherwise."""
        assert self._proc is not None
        self._proc.join(1.0)  # the exit code says whether the CPU-time bound ended it
        code = self._proc.exitcode
        if code == -signal.SIGPROF:
            self.timeouts += 1
            self._restart(f"{kind} solve exceeded {self.max_solve_time_s:g} s of CPU")
            return SolveAborted(f"timeout: {kind} solve exceeded rmpc.max_solve_time_s = "
                                f"{self.max_solve_time_s:g} s of CPU (solver process "
                                "restarted)")
        self._restart(f"lost (exit code {code})")
        return SolveAborted(f"solver process lost during the {kind} solve (exit code {code}; "
                            "restarted)")


def nlp_recipes(mpc: Rmpc) -> dict[str, NlpRecipe | None]:
    """Per NLP kind of ``mpc``, what a solver process loads: the compiled library the parent
    built and its options (None: not compiled, ``rmpc.jit = false``; the child builds it)."""
    out: dict[str, NlpRecipe | None] = {}
    # the controller's compiled NLPs (hard, and the soft copy when there is one)
    for nlp in mpc.nlps():
        opts = getattr(nlp, "options", None)
        if nlp.compiled is None or opts is None:
            out[nlp.kind] = None
            continue
        out[nlp.kind] = NlpRecipe(nlp.kind, f"rmpc_{nlp.kind}", nlp.solver_name,
                                  str(nlp.compiled.library), dict(opts), nlp.lbg.copy(),
                                  nlp.ubg.copy(), int(nlp.solver.nnz_in(1)))
    return out


def process_backend(rmpc: RmpcParams, camera: CameraParams,
                    terminal: TerminalDesign) -> Callable[[Rmpc], ProcessSolveBackend]:
    """The ``backend`` argument of :class:`~companion.core.rmpc.Rmpc` for
    ``rmpc.solve_isolation = "process"`` (the child loads what the parent compiled)."""

    def make(mpc: Rmpc) -> ProcessSolveBackend:
        return ProcessSolveBackend(rmpc, camera, terminal, mpc.solver_kinds(),
                                   rmpc.max_solve_time_s, defer_ready=True,
                                   time_clock=rmpc.solve_time_clock,
                                   spare=rmpc.solver_spare, recipes=nlp_recipes(mpc))

    return make
