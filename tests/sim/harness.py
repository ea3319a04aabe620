"""Shared harness of the emulator tests: the real emulator on 127.0.0.1 with ephemeral ports,
in a background thread with its own event loop, and a plain-socket pymavlink client."""

from __future__ import annotations

import asyncio
import contextlib
import json
import socket
import struct
import threading
import time
import zlib
from collections.abc import Callable, Iterator
from typing import Any

from pymavlink.dialects.v20 import common as mavlink2

from sim_bridge.app import SimBridge
from sim_bridge.config import EmulatorConfig, load_config, with_link, with_sim


class MavClient:
    """A MAVLink 2 peer on a UDP socket: sends to the emulator, parses every datagram it gets
    with a fresh parser."""

    def __init__(self, sysid: int = 1, compid: int = 191) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.port = self.sock.getsockname()[1]
        self.target: tuple[str, int] | None = None
        self.mav = mavlink2.MAVLink(self, srcSystem=sysid, srcComponent=compid)
        self._out: list[bytes] = []

    def write(self, b: bytes) -> None:  # pymavlink "file"
        self._out.append(bytes(b))

    def send(self, msg: Any) -> None:
        self.mav.send(msg)
        assert self.target is not None
        for b in self._out:
            self.sock.sendto(b, self.target)
        self._out.clear()

    def send_raw(self, data: bytes) -> None:
        assert self.target is not None
        self.sock.sendto(data, self.target)

    def recv(self, timeout_s: float) -> list[Any]:
        """Messages from one datagram (possibly none), or [] on timeout."""
        self.sock.settimeout(max(1e-4, timeout_s))
        try:
            data, _ = self.sock.recvfrom(65536)
        except (TimeoutError, BlockingIOError):
            return []
        p = mavlink2.MAVLink(None)
        p.robust_parsing = True
        return [m for m in (p.parse_buffer(data) or []) if not m.get_type().startswith(
            ("BAD_DATA", "UNKNOWN"))]

    def wait_for(self, pred: Callable[[Any], bool], timeout_s: float) -> Any | None:
        end = time.monotonic() + timeout_s
        while (left := end - time.monotonic()) > 0:
            for m in self.recv(left):
                if pred(m):
                    return m
        return None

    def collect(self, duration_s: float) -> list[Any]:
        end = time.monotonic() + duration_s
        out: list[Any] = []
        while (left := end - time.monotonic()) > 0:
            out.extend(self.recv(left))
        return out

    def drain(self) -> None:
        self.sock.setblocking(False)
        with contextlib.suppress(BlockingIOError):
            while True:
                self.sock.recvfrom(65536)
        self.sock.setblocking(True)

    def command(self, command: int, *params: float, target: tuple[int, int] = (1, 1)) -> None:
        p = [*params, *([0.0] * (7 - len(params)))]
        self.send(self.mav.command_long_encode(target[0], target[1], command, 0, *p))

    def ack(self, command: int, timeout_s: float = 1.0) -> Any | None:
        return self.wait_for(lambda m: m.get_type() == "COMMAND_ACK" and m.command == command,
                             timeout_s)

    def close(self) -> None:
        self.sock.close()


class RunningSim:
    def __init__(self, sim: SimBridge, loop: asyncio.AbstractEventLoop,
                 thread: threading.Thread, task_box: dict[str, Any]) -> None:
        self.sim = sim
        self.loop = loop
        self.thread = thread
        self._box = task_box

    @property
    def ports(self) -> dict[str, int]:
        return self.sim.ports

    def call(self, fn: Callable[[], Any]) -> Any:
        """Run ``fn`` on the emulator's loop thread and return its result."""
        fut: Any = asyncio.run_coroutine_threadsafe(_acall(fn), self.loop)
        return fut.result(5.0)

    def stop(self) -> Any:
        task = self._box.get("task")
        if task is not None and not task.done():
            self.loop.call_soon_threadsafe(task.cancel)
        self.thread.join(10.0)
        assert not self.thread.is_alive(), "emulator thread did not stop"
        if "error" in self._box:
            raise self._box["error"]
        return self._box.get("stats")


async def _acall(fn: Callable[[], Any]) -> Any:
    return fn()


def make_config(**sim_changes: Any) -> EmulatorConfig:
    cfg = load_config()
    cfg = with_link(cfg, offboard_local_port=0, gcs_local_port=0, agv_local_port=0,
                    frame_port=0)
    return with_sim(cfg, **sim_changes) if sim_changes else cfg


@contextlib.contextmanager
def run_sim(cfg: EmulatorConfig, duration_s: float = 600.0) -> Iterator[RunningSim]:
    """Start the emulator in a thread; stop it (cancel) when the block exits."""
    box: dict[str, Any] = {}
    ready = threading.Event()
    sim = SimBridge(cfg, bind_host="127.0.0.1")

    async def main() -> None:
        box["task"] = asyncio.current_task()
        box["loop"] = asyncio.get_running_loop()
        try:
            async with sim:
                ready.set()
                box["stats"] = await sim.run(duration_s)
        except asyncio.CancelledError:
            box["stats"] = sim.stats() if sim.links else None
        except BaseException as e:
            box["error"] = e
        finally:
            ready.set()

    thread = threading.Thread(target=lambda: asyncio.run(main()), daemon=True)
    thread.start()
    assert ready.wait(10.0), "emulator did not start"
    if "error" in box:
        raise box["error"]
    rs = RunningSim(sim, box["loop"], thread, box)
    try:
        yield rs
    finally:
        rs.stop()


def sim_with_client(c: MavClient, **sim_changes: Any) -> contextlib.AbstractContextManager[
        RunningSim]:
    """An emulator whose offboard link sends to ``c`` (and ``c`` targets it)."""
    cfg = with_link(make_config(**sim_changes), offboard_remote=f"127.0.0.1:{c.port}")
    cm = run_sim(cfg)

    @contextlib.contextmanager
    def wrapped() -> Iterator[RunningSim]:
        with cm as rs:
            c.target = ("127.0.0.1", rs.ports["offboard"])
            yield rs

    return wrapped()


HEADER = struct.Struct("<4sBBHIQHHII")


def read_exact(sock: socket.socket, n: int) -> bytes:
    buf = bytearray()
    while len(buf) < n:
        chunk = sock.recv(n - len(buf))
        if not chunk:
            raise ConnectionError("frame server closed the connection")
        buf += chunk
    return bytes(buf)


def read_frame(sock: socket.socket) -> tuple[dict[str, Any], bytes]:
    """One camera frame record (docs/reference/wire.md), header checked, CRC verified."""
    magic, ver, enc, _res, seq, t_us, w, h, n, crc = HEADER.unpack(
        read_exact(sock, HEADER.size))
    payload = read_exact(sock, n)
    assert magic == b"IBVF" and ver == 1
    assert zlib.crc32(payload) == crc
    return {"seq": seq, "t_us": t_us, "w": w, "h": h, "enc": enc}, payload


def drain_truth(sock: socket.socket, quiet_s: float = 0.3) -> list[dict[str, Any]]:
    """Every ground-truth record (one JSON datagram each) waiting on ``sock``, until none
    arrives for ``quiet_s``."""
    sock.settimeout(quiet_s)
    records = []
    while True:
        try:
            records.append(json.loads(sock.recv(65536)))
        except TimeoutError:
            return records
