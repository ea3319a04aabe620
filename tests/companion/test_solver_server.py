"""The solver processes' server can be started before the first solver process is needed:
while the companion waits for the autopilot's limits, the server's CasADi import runs, so the
controller built once they arrive gets its child by a fork."""

from __future__ import annotations

import multiprocessing
import os
import subprocess
import sys

import pytest

from companion.control.solver_server import solver_context, start_server

pytestmark = pytest.mark.skipif("forkserver" not in multiprocessing.get_all_start_methods(),
                                reason="no 'forkserver' on this platform: nothing to start")


def test_start_server_starts_the_server() -> None:
    # in a fresh interpreter: this test process may have started the server already
    code = (
        "from multiprocessing import forkserver\n"
        "from companion.control.solver_server import start_server\n"
        "assert forkserver._forkserver._forkserver_pid is None\n"
        "start_server()\n"
        "pid = forkserver._forkserver._forkserver_pid\n"
        "import os; os.kill(pid, 0)\n"
        "print(pid)\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True, timeout=60).stdout.split()
    assert int(out[0]) > 0  # the server runs (a child's fork waits only for its import)


def test_a_child_forks_from_the_started_server() -> None:
    start_server()
    from multiprocessing import forkserver

    pid = forkserver._forkserver._forkserver_pid  # type: ignore[attr-defined]
    assert pid is not None
    os.kill(pid, 0)  # alive
    ctx = solver_context()
    p = ctx.Process(target=os.getpid)
    p.start()
    p.join(30)
    assert p.exitcode == 0
    assert forkserver._forkserver._forkserver_pid == pid  # type: ignore[attr-defined]


def test_an_os_error_starting_the_server_is_logged_not_raised(
        monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture) -> None:
    from multiprocessing import forkserver

    def no_fds() -> None:
        raise OSError(24, "Too many open files")

    monkeypatch.setattr(forkserver, "ensure_running", no_fds)
    start_server()  # the companion goes on reading the limits; the first child reports it
    assert "not started early" in caplog.text and "Too many open files" in caplog.text
