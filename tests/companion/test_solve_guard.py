"""The solve time bound (``rmpc.solve_isolation = "process"``, companion.control.solve_guard):
a solve that never returns is abandoned, its child process killed and replaced, the step flies
the finite terminal-law fallback with a 'timeout' status and the steps after the restart solve
again; SIGTERM stops a companion whose solver is stuck. Real CasADi in a real child process
(the compiled libraries come from the cache); the stuck solver is the child's own test hook
(it solves, then spins at 100 % CPU ignoring SIGTERM, like the fatrop restoration loop)."""

from __future__ import annotations

import contextlib
import dataclasses
import os
import signal
import subprocess
import sys
import textwrap
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from companion import ConfigError
from companion.config import Config, load_config
from companion.control.factory import build_controller
from companion.control.solve_guard import (
    ProcessSolveBackend,
    cpu_clock_wall_backstop_s,
    process_backend,
)
from companion.core.errors import ParamError
from companion.core.rmpc import Rmpc, RmpcResult, TargetMotion
from companion.core.terminal import TerminalDesign

ROOT = Path(__file__).resolve().parents[2]
ETA0 = np.array([0.0159, -0.2230, 0.6, 0.3927, -0.1307, -0.0541, 0.0])
READY_S = 120.0  # generous: a cold child on a loaded machine


@pytest.fixture(scope="module")
def mpc(cfg: Config, design: TerminalDesign) -> Iterator[Rmpc]:
    """Without the stand-by process: a restart loads a fresh child."""
    p = dataclasses.replace(cfg.rmpc, solver="nlp", solve_isolation="process", solver_spare=False)
    m = Rmpc(p, cfg.camera, design, backend=process_backend(p, cfg.camera, design))
    yield m
    m.close()


def _backend(m: Rmpc) -> ProcessSolveBackend:
    b = m.backend
    assert isinstance(b, ProcessSolveBackend)
    assert b.wait_ready(READY_S)
    return b


def _motion(cfg: Config) -> TargetMotion:
    return TargetMotion.constant([0.1, 0.0], [0.0, 0.0], 0.0, cfg.rmpc.horizon)


def _finite_fallback(res: RmpcResult, cfg: Config) -> None:
    assert res.mode == "fallback" and not res.success
    for a in (res.u0, res.eta_pred, res.u_pred):
        assert np.all(np.isfinite(a))
    assert np.isfinite(res.cost)
    assert np.all(np.abs(res.u0) <= np.asarray(cfg.rmpc.u_max) + 1e-12)


def test_isolated_solve_equals_the_in_process_one(mpc: Rmpc, cfg: Config,
                                                  design: TerminalDesign) -> None:
    """Same compiled solver, same arrays: the child's answer is bit-identical."""
    _backend(mpc)
    local = Rmpc(dataclasses.replace(cfg.rmpc, solver="nlp", solve_isolation="none"), cfg.camera,
                 design)
    assert local.backend is None
    mpc.reset()
    a, b = mpc.solve(ETA0, _motion(cfg)), local.solve(ETA0, _motion(cfg))
    assert a.mode == b.mode == "optimal"
    assert np.array_equal(a.u_pred, b.u_pred) and a.status == b.status


def _ended(proc: object) -> None:
    """A stuck child is gone: killed by the guard (SIGKILL) or ended by its own CPU-time bound
    (SIGPROF), whichever came first on this machine."""
    assert getattr(proc, "exitcode", None) in (-signal.SIGKILL, -signal.SIGPROF), proc


def test_a_stuck_solve_times_out_to_the_fallback_and_the_restarted_child_solves(
        mpc: Rmpc, cfg: Config) -> None:
    backend = _backend(mpc)
    mpc.reset()
    assert mpc.solve(ETA0, _motion(cfg)).mode == "optimal"
    stuck = backend._proc
    assert stuck is not None
    restarts = backend.restarts
    backend.hang_next_solve()
    res = mpc.solve(ETA0, _motion(cfg))
    _finite_fallback(res, cfg)
    assert res.status.startswith("timeout: hard solve exceeded rmpc.max_solve_time_s")
    assert res.hard_status == res.status
    # the stuck child (SIGTERM ignored) is killed at the deadline when it had the CPU, else
    # ended by its CPU-time bound once it has used it; either way it is replaced
    assert backend.settle(READY_S)
    stuck.join(READY_S)
    _ended(stuck)
    assert backend.restarts == restarts + 1 and backend.pid != stuck.pid
    assert backend.wait_ready(READY_S)
    again = mpc.solve(ETA0, _motion(cfg))
    assert again.mode == "optimal" and again.success
    assert np.all(np.isfinite(again.u_pred))


def test_a_starved_solve_flies_the_fallback_but_keeps_its_child(mpc: Rmpc, cfg: Config) -> None:
    """A solve that waits 0.5 s without using CPU (a companion computer short of CPU) misses
    the 0.25 s wall deadline: the step flies the fallback, but the child is not killed (a
    restart costs CPU exactly when there is none); its late answer is discarded."""
    assert cfg.rmpc.max_solve_time_s < 0.5
    backend = _backend(mpc)
    mpc.reset()
    assert mpc.solve(ETA0, _motion(cfg)).mode == "optimal"
    pid, restarts, late = backend.pid, backend.restarts, backend.late_answers
    backend.stall_next_solve(0.5)
    res = mpc.solve(ETA0, _motion(cfg))
    _finite_fallback(res, cfg)
    assert res.status.startswith("timeout: hard solve exceeded rmpc.max_solve_time_s")
    assert "starved: solver process kept" in res.status
    assert backend.pid == pid and backend.restarts == restarts and backend.starved >= 1
    assert backend.busy
    assert backend.settle(READY_S)
    assert backend.late_answers == late + 1 and backend.pid == pid
    assert mpc.solve(ETA0, _motion(cfg)).mode == "optimal"
    assert backend.pid == pid and backend.restarts == restarts


def test_a_late_answer_is_never_taken_for_the_next_steps(cfg: Config,
                                                         design: TerminalDesign) -> None:
    """The next step's solve queues behind the abandoned one in the same child: the answer it
    gets is its own (the late one, for another state, is discarded), bit-identical to the
    in-process solve of its own state."""
    p = dataclasses.replace(cfg.rmpc, solver="nlp", solve_isolation="process",
                            solver_spare=False, max_solve_time_s=1.0)
    m = Rmpc(p, cfg.camera, design, backend=process_backend(p, cfg.camera, design))
    local = Rmpc(dataclasses.replace(p, solve_isolation="none"), cfg.camera, design)
    eta1 = ETA0 + np.array([0.05, 0.05, 0.1, 0.0, 0.0, 0.0, 0.0])
    try:
        backend = _backend(m)
        backend.stall_next_solve(1.5)
        first = m.solve(ETA0, _motion(cfg))
        assert first.mode == "fallback" and "starved" in first.status
        pid = backend.pid
        for _ in range(20):  # each attempt: its own answer, or (a loaded machine) a fallback
            m.reset()
            res = m.solve(eta1, _motion(cfg))
            if res.mode == "optimal":
                break
        assert res.mode == "optimal", res.status
        assert backend.late_answers >= 1 and backend.pid == pid and backend.restarts == 0
        local.reset()
        want = local.solve(eta1, _motion(cfg))
        assert np.array_equal(res.u_pred, want.u_pred)
    finally:
        m.close()


def test_steps_while_the_child_restarts_fly_the_fallback(mpc: Rmpc, cfg: Config) -> None:
    backend = _backend(mpc)
    backend._restart("test")
    # stopped before it can have imported CasADi: it cannot be ready yet
    pid = backend.pid
    assert pid is not None
    os.kill(pid, signal.SIGSTOP)
    try:
        assert not backend.ready
        res = mpc.solve(ETA0, _motion(cfg))
        _finite_fallback(res, cfg)
        assert res.status.startswith("solver restarting")
    finally:
        os.kill(pid, signal.SIGCONT)
    assert backend.wait_ready(READY_S)
    assert mpc.solve(ETA0, _motion(cfg)).mode == "optimal"


def test_a_child_that_died_is_replaced(mpc: Rmpc, cfg: Config) -> None:
    backend = _backend(mpc)
    dead = backend._proc
    assert dead is not None
    os.kill(dead.pid, signal.SIGKILL)  # type: ignore[arg-type]
    dead.join(READY_S)
    res = mpc.solve(ETA0, _motion(cfg))
    _finite_fallback(res, cfg)
    assert res.status.startswith("solver process lost during the hard solve")
    assert backend.pid != dead.pid and backend.wait_ready(READY_S)
    assert mpc.solve(ETA0, _motion(cfg)).mode == "optimal"


@pytest.fixture(scope="module")
def mpc_spare(cfg: Config, design: TerminalDesign) -> Iterator[Rmpc]:
    """config/paper.toml's default: a loaded stand-by process beside the solving one."""
    assert cfg.rmpc.solver_spare
    p = dataclasses.replace(cfg.rmpc, solver="nlp", solve_isolation="process")
    m = Rmpc(p, cfg.camera, design, backend=process_backend(p, cfg.camera, design))
    yield m
    m.close()


def _spare_ready(backend: ProcessSolveBackend) -> int:
    """Wait until the stand-by child exists and has loaded; its pid."""
    import time

    end = time.monotonic() + READY_S
    while backend._spare is None and time.monotonic() < end:
        time.sleep(0.05)
    assert backend._spare is not None, "no spare started"
    proc, conn = backend._spare
    assert conn.poll(READY_S), "the spare never loaded"
    assert proc.pid is not None
    return proc.pid


def test_a_stuck_solve_promotes_the_loaded_spare_and_the_next_step_solves(
        mpc_spare: Rmpc, cfg: Config) -> None:
    """With the spare the step after a timeout solves (no 'solver restarting' steps), and a
    new spare is started behind the promoted one; stuck and stand-by processes are distinct."""
    backend = _backend(mpc_spare)
    mpc_spare.reset()
    assert mpc_spare.solve(ETA0, _motion(cfg)).mode == "optimal"
    spare_pid = _spare_ready(backend)
    stuck = backend._proc
    assert stuck is not None and stuck.pid != spare_pid
    promotions = backend.promotions
    backend.hang_next_solve()
    res = mpc_spare.solve(ETA0, _motion(cfg))
    _finite_fallback(res, cfg)
    assert res.status.startswith("timeout: hard solve exceeded rmpc.max_solve_time_s")
    assert backend.settle(READY_S)  # killed at once, or ended by its CPU-time bound
    stuck.join(READY_S)
    _ended(stuck)
    assert backend.pid == spare_pid and backend.promotions == promotions + 1
    # at once: no wait for a fresh child to load
    again = mpc_spare.solve(ETA0, _motion(cfg))
    assert again.mode == "optimal" and again.success, again.status
    new_spare = _spare_ready(backend)
    assert new_spare not in (spare_pid, stuck.pid)
    # a lost child is replaced by the spare the same way
    os.kill(spare_pid, signal.SIGKILL)
    lost = mpc_spare.solve(ETA0, _motion(cfg))
    assert lost.status.startswith("solver process lost during the hard solve")
    assert backend.pid == new_spare
    assert mpc_spare.solve(ETA0, _motion(cfg)).mode == "optimal"


def test_closing_stops_the_spare_too(cfg: Config, design: TerminalDesign) -> None:
    p = dataclasses.replace(cfg.rmpc, solver="nlp", solve_isolation="process")
    m = Rmpc(p, cfg.camera, design, backend=process_backend(p, cfg.camera, design))
    backend = _backend(m)
    assert m.solve(ETA0, _motion(cfg)).mode == "optimal"
    pids = (backend.pid, _spare_ready(backend))
    m.close()
    for pid in pids:
        assert pid is not None and _gone(pid), pid


@pytest.fixture(scope="module")
def mpc_cpu(cfg: Config, design: TerminalDesign) -> Iterator[Rmpc]:
    """The lockstep flavour: the bound counts the solver process's CPU time (0.25 s)."""
    p = dataclasses.replace(cfg.rmpc, solver="nlp", solve_isolation="process",
                            solve_time_clock="cpu")
    m = Rmpc(p, cfg.camera, design, backend=process_backend(p, cfg.camera, design))
    yield m
    m.close()


def test_a_descheduled_solve_is_cut_by_wall_time_but_not_by_cpu_time(
        mpc: Rmpc, mpc_cpu: Rmpc, cfg: Config) -> None:
    """A solve that waits 0.5 s without using CPU (a busy machine): past the 0.25 s wall bound
    the step is abandoned (its child kept); with the CPU-time clock it is a normal, optimal
    solve."""
    assert cfg.rmpc.max_solve_time_s < 0.5
    wall, cpu = _backend(mpc), _backend(mpc_cpu)
    assert (wall.time_clock, cpu.time_clock) == ("wall", "cpu")
    mpc.reset()
    wall.stall_next_solve(0.5)
    res = mpc.solve(ETA0, _motion(cfg))
    _finite_fallback(res, cfg)
    assert res.status.startswith("timeout: hard solve exceeded")
    assert wall.settle(READY_S)
    mpc_cpu.reset()
    restarts = cpu.restarts
    cpu.stall_next_solve(0.5)
    res = mpc_cpu.solve(ETA0, _motion(cfg))
    assert res.mode == "optimal" and res.success, res.status
    assert cpu.restarts == restarts and cpu.timeouts == 0


def test_with_the_cpu_clock_a_stuck_solve_is_ended_by_its_cpu_time(
        mpc_cpu: Rmpc, cfg: Config) -> None:
    """The stuck child (100 % CPU, SIGTERM ignored) is ended by its own CPU-time bound (SIGPROF)
    well before the wall backstop; the step flies the fallback with a 'timeout' status and the
    restarted child solves again."""
    backend = _backend(mpc_cpu)
    assert cpu_clock_wall_backstop_s(cfg.rmpc.max_solve_time_s) >= 10.0
    mpc_cpu.reset()
    assert mpc_cpu.solve(ETA0, _motion(cfg)).mode == "optimal"
    stuck = backend._proc
    assert stuck is not None
    backend.hang_next_solve()
    res = mpc_cpu.solve(ETA0, _motion(cfg))
    _finite_fallback(res, cfg)
    assert res.status.startswith("timeout: hard solve exceeded rmpc.max_solve_time_s")
    assert "of CPU" in res.status
    assert stuck.exitcode == -signal.SIGPROF
    assert backend.timeouts == 1 and backend.pid != stuck.pid
    assert backend.wait_ready(READY_S)
    assert mpc_cpu.solve(ETA0, _motion(cfg)).mode == "optimal"


def test_the_factory_follows_rmpc_solve_isolation(cfg: Config,
                                                  design: TerminalDesign) -> None:
    assert cfg.rmpc.solve_isolation == "process"  # config/paper.toml
    ctrl = build_controller(load_config(overrides=['rmpc.solve_isolation="none"']), design)
    assert isinstance(ctrl, Rmpc) and ctrl.backend is None
    ctrl = build_controller(cfg, design)
    try:
        assert isinstance(ctrl, Rmpc) and isinstance(ctrl.backend, ProcessSolveBackend)
        assert ctrl.backend.max_solve_time_s == cfg.rmpc.max_solve_time_s
    finally:
        assert isinstance(ctrl, Rmpc)
        ctrl.close()


@pytest.mark.parametrize("bad", ['rmpc.solve_isolation="thread"', "rmpc.max_solve_time_s=0",
                                 'rmpc.solve_time_clock="gpu"',
                                 "rmpc.max_solve_time_s=-0.1", "rmpc.max_solve_time_s=inf"])
def test_bad_settings_are_refused(bad: str) -> None:
    with pytest.raises((ConfigError, ParamError),
                       match=r"solve_isolation|max_solve_time_s|solve_time_clock"):
        load_config(overrides=[bad])


SCRIPT = textwrap.dedent("""
    import asyncio, dataclasses, signal, sys
    import numpy as np
    from companion.config import load_config
    from companion.control.solve_guard import process_backend
    from companion.core.design import design_terminal
    from companion.core.rmpc import Rmpc, TargetMotion

    async def main():
        cfg = load_config()
        p = dataclasses.replace(cfg.rmpc, solver="nlp", solve_isolation="process",
                                max_solve_time_s=3.0)
        d = design_terminal(p, cfg.camera)
        m = Rmpc(p, cfg.camera, d, backend=process_backend(p, cfg.camera, d))
        stop = asyncio.Event()
        asyncio.get_running_loop().add_signal_handler(signal.SIGTERM, stop.set)
        eta0 = np.array([0.0159, -0.2230, 0.6, 0.3927, -0.1307, -0.0541, 0.0])
        tm = TargetMotion.constant([0.1, 0.0], [0.0, 0.0], 0.0, p.horizon)
        print("first", m.solve(eta0, tm).mode, flush=True)
        m.backend.hang_next_solve()
        print("hanging", m.backend.pid, flush=True)
        while not stop.is_set():
            res = m.solve(eta0, tm)
            print("step", res.mode, res.status, m.backend.pid, flush=True)
            await asyncio.sleep(0.05)
        print("stopped", flush=True)
        m.close()

    asyncio.run(main())
""")


def _gone(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except (OSError, IndexError):
        return True
    return state in ("Z", "X")


def test_sigterm_stops_a_companion_whose_solve_is_stuck() -> None:
    """An asyncio loop (as the runtime's) serves SIGTERM although the solve it ran was stuck:
    the parent waits at most the bound, the stuck child is killed, nothing is left behind."""
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    proc = subprocess.Popen([sys.executable, "-c", SCRIPT], cwd=ROOT, env=env, text=True,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    assert proc.stdout is not None
    lines = []
    for line in proc.stdout:
        lines.append(line.split())
        if line.startswith("hanging"):
            proc.send_signal(signal.SIGTERM)  # while the stuck solve runs
            break
    out, err = proc.communicate(timeout=300)
    lines += [ln.split() for ln in out.splitlines()]
    assert proc.returncode == 0, err
    assert lines[0] == ["first", "optimal"]
    stuck = int(lines[1][1])
    steps = [ln for ln in lines if ln[0] == "step"]
    assert steps and steps[0][1] == "fallback" and steps[0][2] == "timeout:"
    assert lines[-1] == ["stopped"]
    assert _gone(stuck)
    assert all(_gone(int(s[-1])) for s in steps)


KILL_SCRIPT = textwrap.dedent("""
    import dataclasses, os, time
    import numpy as np
    from companion.config import load_config
    from companion.control.solve_guard import process_backend
    from companion.core.design import design_terminal
    from companion.core.rmpc import Rmpc, TargetMotion

    cfg = load_config()
    # a CPU-time bound the stuck solve will not reach: only the companion's death can end it
    p = dataclasses.replace(cfg.rmpc, solver="nlp", solve_isolation="process", solver_spare=True,
                            max_solve_time_s=600.0)
    d = design_terminal(p, cfg.camera)
    m = Rmpc(p, cfg.camera, d, backend=process_backend(p, cfg.camera, d))
    b = m.backend
    assert b.wait_ready(120.0) and b._spare[1].poll(120.0)
    eta0 = np.array([0.0159, -0.2230, 0.6, 0.3927, -0.1307, -0.0541, 0.0])
    tm = TargetMotion.constant([0.1, 0.0], [0.0, 0.0], 0.0, p.horizon)
    lbx, ubx = m._hard.bounds(eta0, tm)
    b.hang_next_solve()  # sent, not waited for: the child solves, then spins
    b._send("hard", np.zeros(len(lbx)), np.append(tm.packed(), eta0[3]), lbx, ubx)
    kids = [int(x) for x in os.popen(f"pgrep -P {os.getpid()}").read().split()]
    print("pids", b.pid, b._spare[0].pid, *kids, flush=True)
    time.sleep(600)
""")


def test_no_solver_process_outlives_a_killed_companion() -> None:
    """The children are forked from a fork server: when the companion is SIGKILLed the server
    sees its end of the keep-alive pipe close and exits, and the children's parent-death
    signal ends them, a child stuck in a solve (reading no pipe) too (a child holding the
    server's pipe would keep both alive)."""
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    proc = subprocess.Popen([sys.executable, "-c", KILL_SCRIPT], cwd=ROOT, env=env, text=True,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    assert proc.stdout is not None
    line = proc.stdout.readline().split()
    assert line and line[0] == "pids", proc.stderr.read() if proc.stderr else ""
    pids = [int(x) for x in line[1:]]
    assert len(set(pids)) >= 3  # the solver, the spare, the fork server (and its tracker)
    proc.kill()
    proc.communicate(timeout=60)  # (and closes the pipes)
    import time

    end = time.monotonic() + READY_S
    while time.monotonic() < end and not all(_gone(p) for p in pids):
        time.sleep(0.1)
    left = [p for p in pids if not _gone(p)]
    for p in left:  # a failure leaves nothing spinning behind
        with contextlib.suppress(OSError):
            os.kill(p, signal.SIGKILL)
    assert left == []


def test_a_child_that_gets_no_cpu_at_all_is_replaced_after_the_backstop(
        cfg: Config, design: TerminalDesign) -> None:
    """A stopped child (SIGSTOP: no CPU at all, as a solver that is never scheduled) looks
    starved at the deadline and is kept; once its answer has been outstanding for the wall
    backstop it is killed and replaced. The backstop is reached on the backend's own clock
    (advanced here), not waited for."""
    from companion.control.solve_guard import nlp_recipes

    now = [1000.0]
    p = dataclasses.replace(cfg.rmpc, solver="nlp", solve_isolation="process",
                            solver_spare=False)

    def make(m: Rmpc) -> ProcessSolveBackend:
        return ProcessSolveBackend(p, cfg.camera, design, m.solver_kinds(),
                                   p.max_solve_time_s, clock=lambda: now[0],
                                   recipes=nlp_recipes(m))

    m = Rmpc(p, cfg.camera, design, backend=make)
    try:
        backend = _backend(m)
        assert m.solve(ETA0, _motion(cfg)).mode == "optimal"
        stopped = backend._proc
        assert stopped is not None and stopped.pid is not None
        os.kill(stopped.pid, signal.SIGSTOP)
        res = m.solve(ETA0, _motion(cfg))  # the frozen clock: the poll waits the bound once
        _finite_fallback(res, cfg)
        assert "starved: solver process kept" in res.status
        assert backend.pid == stopped.pid and backend.restarts == 0
        now[0] += backend.backstop_s
        res = m.solve(ETA0, _motion(cfg))
        _finite_fallback(res, cfg)
        assert res.status.startswith("timeout: an abandoned solve still running after")
        stopped.join(READY_S)
        assert stopped.exitcode == -signal.SIGKILL
        assert backend.restarts == 1 and backend.pid != stopped.pid
        assert backend.wait_ready(READY_S)
        assert m.solve(ETA0, _motion(cfg)).mode == "optimal"
    finally:
        m.close()
