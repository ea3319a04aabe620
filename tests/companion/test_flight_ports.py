"""A flight's ports are chosen by the processes that bind them (companion/flight_ports.py).

Real sockets and a real child process: the frame server's listening socket is bound and held
by the orchestrator, a stranger cannot bind its port, and a child handed the socket serves a
client that connected before the child existed. The companion's ready file carries its ports.
"""

from __future__ import annotations

import errno
import socket
import subprocess
import sys
from pathlib import Path

import pytest

from companion import CompanionError
from companion.flight import emulator_command
from companion.flight_ports import FlightSockets, ReadyPorts, read_ready, write_ready

_CHILD = ("import socket, sys\n"
          "s = socket.socket(fileno=int(sys.argv[1]))\n"
          "c, _ = s.accept()\n"
          "c.sendall(c.recv(5).upper())\n")


def test_the_frame_port_is_held_until_the_child_serves_it() -> None:
    with FlightSockets() as held:
        port = held.frame_port
        # held: nobody else can bind it (a probed-and-closed port could be taken here)
        with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as stranger:
            with pytest.raises(OSError) as info:
                stranger.bind(("127.0.0.1", port))
            assert info.value.errno == errno.EADDRINUSE
        # a client (the companion's camera) may connect before the server process exists
        client = socket.create_connection(("127.0.0.1", port), timeout=30.0)
        child = subprocess.Popen([sys.executable, "-c", _CHILD, str(held.frame_fd)],
                                 pass_fds=(held.frame_fd,))
        held.frame.close()  # the child's now
        try:
            client.sendall(b"hello")
            assert client.recv(5) == b"HELLO"
            assert child.wait(timeout=30.0) == 0
        finally:
            client.close()
            if child.poll() is None:
                child.kill()
                child.wait()
        # the GCS sink is a bound UDP socket: datagrams to it are taken, not refused
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as tx:
            tx.sendto(b"x", ("127.0.0.1", held.gcs_sink_port))
        held.gcs_sink.settimeout(30.0)
        assert held.gcs_sink.recv(8) == b"x"


def test_two_flights_sockets_never_share_a_port() -> None:
    held = [FlightSockets() for _ in range(50)]
    try:
        ports = [h.frame_port for h in held]
        sinks = [h.gcs_sink_port for h in held]
        assert len(set(ports)) == 50 and len(set(sinks)) == 50
    finally:
        for h in held:
            h.close()


def test_the_ready_file_carries_the_bound_ports(tmp_path: Path) -> None:
    path = tmp_path / ".companion-ready"
    assert read_ready(path) is None
    write_ready(path, ("127.0.0.1", 40001), 40002)
    assert read_ready(path) == ReadyPorts(40001, 40002)
    assert path.read_text().splitlines()[0] == "ready"
    assert list(tmp_path.iterdir()) == [path]  # no temporary left behind
    write_ready(path, None, None)
    assert read_ready(path) == ReadyPorts(None, None)
    path.write_text("ready\nmavlink_port 70000\n")
    with pytest.raises(ValueError, match="mavlink_port 70000"):
        read_ready(path)


def test_the_emulator_command_gets_the_companions_ports() -> None:
    sim = ["sim", "--offboard-remote", "127.0.0.1:0", "--truth-remote", "127.0.0.1:0"]
    assert emulator_command(sim, ReadyPorts(5001, 5002)) == [
        "sim", "--offboard-remote", "127.0.0.1:5001", "--truth-remote", "127.0.0.1:5002"]
    with pytest.raises(CompanionError, match="names no ports"):
        emulator_command(sim, ReadyPorts(5001, None))
    with pytest.raises(CompanionError, match="names no ports"):
        emulator_command(sim, None)


def test_the_emulator_refuses_a_frame_fd_that_is_not_a_listener() -> None:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as udp:
        fd = udp.fileno()
        udp.set_inheritable(True)
        r = subprocess.run([sys.executable, "-m", "sim_bridge", "--lockstep", "--duration", "1",
                            "--bind", "127.0.0.1", "--frame-fd", str(fd)],
                           pass_fds=(fd,), capture_output=True, text=True, timeout=120.0)
    assert r.returncode == 2
    assert f"--frame-fd {fd}: not a listening TCP socket" in r.stderr + r.stdout
