"""CPU of the companion's MAVLink receive path, its send path and its log writer, per message.

    python bench/link_log.py [--log FLIGHT.mcap] [--seconds 60] [--json]

The frames are real: the accepted MAVLink frames a flight logged (``/mavlink/in/*``, raw bytes)
and, since a flight never logs the streams the companion does not use, PX4's 50 Hz HIGHRES_IMU
built with pymavlink at its share of an onboard link (1 in 4 datagrams). Without ``--log`` a
short lockstep paper flight is flown first to get them (about a minute).

* **receive**: the frames go over a real UDP socket (a sender thread, one step's worth of
  datagrams at a time) to a :class:`MavlinkLink` wired as in a flight (``Vehicle.on_rx``:
  store, state machine, log record; the queue drained by a task). Figures: CPU of the event
  loop's thread per datagram (``time.thread_time``) and CPU of the MCAP writer thread per
  datagram (its own CPU clock), and how many were accepted, unused, rejected.
* **direct**: the link's own code alone (``_on_datagram`` called on the same datagrams, no
  socket, no event loop, no callback), per datagram.
* **send**: ``send_attitude_target`` (pack, sendto, the ``/mavlink/out`` record), per send.
* **crops**: the flight's ``/perception/input`` crops logged as PNG and as raw pixels (the
  MCAP chunk LZ4-compressed): writer-thread CPU per crop (encode, chunk compression, write,
  fsync), and bytes per crop in the file.

CPU figures hold on a loaded machine far better than wall figures; the load is printed.
"""

from __future__ import annotations

import argparse
import asyncio
import base64
import contextlib
import dataclasses
import json
import math
import multiprocessing
import os
import socket
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from pymavlink.dialects.v20 import common as mavlink2  # noqa: E402

from companion.config import load_config  # noqa: E402
from companion.control.recording import LogClock, RuntimeLog  # noqa: E402
from companion.control.timebase import TimeBase  # noqa: E402
from companion.control.vehicle import Vehicle  # noqa: E402
from companion.control.wiring import allow_rules  # noqa: E402
from companion.link import MavlinkLink  # noqa: E402
from companion.log.reader import LogReader  # noqa: E402
from companion.log.writer import McapLogger  # noqa: E402

STEP_DATAGRAMS = 10  # datagrams sent together


def flight_frames(log: Path) -> tuple[list[bytes], list[Any]]:
    """(received frames in order, the perception crops) of a flight log."""
    frames: list[bytes] = []
    crops: list[Any] = []
    with LogReader(log) as r:
        topics = [c.topic for c in r.channels if c.topic.startswith("/mavlink/in/")]
        for m in r.messages(topics):
            frames.append(base64.b64decode(m.data["raw_b64"]))
        for m in r.messages(["/perception/input"]):
            if m.image is not None:
                crops.append(m.image)
    return frames, crops


def with_unused(frames: list[bytes], sysid: int, compid: int) -> list[bytes]:
    """``frames`` with a HIGHRES_IMU after every third (PX4's onboard link: 50 of ~200 Hz)."""
    enc = mavlink2.MAVLink(None, srcSystem=sysid, srcComponent=compid)
    out: list[bytes] = []
    for i, f in enumerate(frames):
        out.append(f)
        if i % 3 == 2:
            m = enc.highres_imu_encode(i * 20_000, 0.1, -0.2, -9.81, 0.01, 0.02, 0.0,
                                       0.2, 0.0, 0.4, 1013.0, 0.1, 120.0, 25.0, 0x1FFF, 0)
            out.append(bytes(m.pack(enc)))
            enc.seq = (enc.seq + 1) % 256
    return out


class _NoLog:
    """Vehicle.records while the bench times the vehicle's own work (its log record is timed
    apart): every call is a no-op."""

    def __getattr__(self, name: str) -> Any:
        return lambda *a, **k: None


def _sender(conn: Any, frames: list[bytes]) -> None:
    """A separate process (no GIL shared with the link): one step's worth of datagrams every
    5 ms (2000 datagrams/s, ten times a flight's rate: the loop's idle cost stays small)."""
    addr = conn.recv()
    tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    tx.bind(("127.0.0.1", 0))
    tx.sendto(frames[0], addr)
    time.sleep(0.2)
    t = time.monotonic()
    for i in range(1, len(frames), STEP_DATAGRAMS):
        for d in frames[i:i + STEP_DATAGRAMS]:
            tx.sendto(d, addr)
        t += 0.005
        time.sleep(max(0.0, t - time.monotonic()))
    tx.close()


async def _receive(cfg: Any, frames: list[bytes], tmp: Path, conn: Any) -> dict[str, Any]:
    logger = McapLogger.from_config(cfg.logging, tmp / "rx.mcap")
    logger.open()
    records = RuntimeLog(logger, LogClock(cfg.logging.timestamps), cfg, "")
    vehicle = Vehicle(cfg, TimeBase(cfg.control.time_source, cfg.safety.max_frame_age_s))
    vehicle.records = records
    records.config()
    in_cb = [0.0, 0.0]  # CPU in Vehicle.on_rx (store, state machine, log record), its record

    def on_rx(rx: Any) -> None:
        t0 = time.thread_time()
        records.received(rx, rx.fields)
        t1 = time.thread_time()
        try:
            vehicle.records = _NoLog()  # type: ignore[assignment]
            vehicle.on_rx(rx)
        finally:
            vehicle.records = records
        t2 = time.thread_time()
        in_cb[0] += t1 - t0
        in_cb[1] += t2 - t1

    link = MavlinkLink.from_config(
        dataclasses.replace(cfg.mavlink, url="udpin:127.0.0.1:0"), cfg.target,
        allow=allow_rules(cfg), on_rx=on_rx, on_tx=records.sent,
        on_reject=records.rejected)
    vehicle.link = link
    await link.open()
    addr = link.local_address
    assert addr is not None

    async def drain() -> None:
        async for _ in link:
            pass

    drainer = asyncio.create_task(drain())
    conn.send(addr)  # the sender process starts
    while link.counters["rx_datagrams"] < 1:
        await asyncio.sleep(0.001)
    n0 = link.counters["rx_datagrams"]  # the first datagram taught the link its peer
    c0 = time.thread_time()
    in_cb[0] = in_cb[1] = 0.0
    t_end = time.monotonic() + 5.0 + len(frames) / 500.0
    while link.counters["rx_datagrams"] < len(frames) and time.monotonic() < t_end:
        await asyncio.sleep(0.05)
    c_rx = time.thread_time() - c0
    cb_log, cb_vehicle = in_cb
    n = link.counters["rx_datagrams"] - n0
    counters = dict(link.counters)
    # the send path: SET_ATTITUDE_TARGET as the controller sends it, with its log record
    n_tx = 2000
    c1 = time.thread_time()
    for i in range(n_tx):
        link.send_attitude_target((1.0, 0.0, 0.0, 0.0), 0.5 + 1e-4 * (i % 100))
    c_tx = time.thread_time() - c1
    logger.close()
    link.close()
    drainer.cancel()
    return {
        "datagrams": n, "counters": counters,
        "rx_loop_us_per_datagram": 1e6 * c_rx / max(n, 1),
        "rx_link_us_per_datagram": 1e6 * (c_rx - cb_log - cb_vehicle) / max(n, 1),
        "rx_record_us_per_accepted": 1e6 * cb_log / max(counters.get("rx_accepted", 1), 1),
        "rx_vehicle_us_per_accepted": 1e6 * cb_vehicle / max(counters.get("rx_accepted", 1), 1),
        "tx_us_per_send": 1e6 * c_tx / n_tx,
        "log_bytes": (tmp / "rx.mcap").stat().st_size,
    }


@contextlib.contextmanager
def _writer_cpu(cpu: dict[str, float]) -> Iterator[None]:
    """While inside: every McapLogger's writer thread records its whole life's CPU
    (``time.thread_time`` in it) in ``cpu["writer"]``."""
    orig_run = McapLogger._run

    def timed_run(self: McapLogger) -> None:
        t0 = time.thread_time()
        try:
            orig_run(self)
        finally:
            cpu["writer"] = time.thread_time() - t0

    McapLogger._run = timed_run  # type: ignore[method-assign]
    try:
        yield
    finally:
        McapLogger._run = orig_run  # type: ignore[method-assign]


def receive(cfg: Any, frames: list[bytes], tmp: Path) -> dict[str, Any]:
    """The receive and send figures; the writer thread's CPU (``time.thread_time`` in it) over
    its whole life, per record written."""
    cpu: dict[str, float] = {}
    with _writer_cpu(cpu):
        ctx = multiprocessing.get_context("fork")
        here, there = ctx.Pipe()
        proc = ctx.Process(target=_sender, args=(there, frames), daemon=True)
        proc.start()  # before any thread of ours exists
        res = asyncio.run(_receive(cfg, frames, tmp, here))
        proc.join(10.0)
    records = res["counters"].get("rx_accepted", 0) + res["counters"].get("tx_frames", 0)
    res["writer_us_per_record"] = 1e6 * cpu.get("writer", math.nan) / max(records, 1)
    res["writer_us_per_datagram_and_send"] = 1e6 * cpu.get("writer", math.nan) / max(
        res["datagrams"] + 2000, 1)
    return res


def direct(cfg: Any, frames: list[bytes]) -> float:
    """CPU per datagram of the link's own code called directly (no socket, no event loop, no
    callback): the read, checks and decode alone. A fresh link per pass (its duplicate window
    would refuse a second pass); best of three."""
    best = math.inf
    for _ in range(3):
        link = MavlinkLink.from_config(
            dataclasses.replace(cfg.mavlink, url="udpin:127.0.0.1:0"), cfg.target,
            allow=allow_rules(cfg))
        src = ("127.0.0.1", 40000)
        c0 = time.thread_time()
        for d in frames:
            link._on_datagram(d, src)
        best = min(best, time.thread_time() - c0)
    return 1e6 * best / max(len(frames), 1)


def crops(cfg: Any, images: list[Any], tmp: Path, encoding: str) -> dict[str, Any]:
    """Writer-thread CPU and file bytes per crop logged with ``encoding``."""
    cpu: dict[str, float] = {}
    path = tmp / f"crops-{encoding}.mcap"
    with _writer_cpu(cpu):
        lg = McapLogger.from_config(cfg.logging, path)
        lg.block_on_backlog = True
        with lg:
            for i, img in enumerate(images):
                lg.log_image("/perception/input", 1_000_000 + i * 50_000_000, img, encoding)
    n = max(len(images), 1)
    return {"encoding": encoding, "crops": len(images),
            "writer_us_per_crop": 1e6 * cpu["writer"] / n,
            "bytes_per_crop": path.stat().st_size / n,
            "pixels_per_crop": sum(int(i.size) for i in images) / n}


def fly(tmp: Path, seconds: float) -> Path:
    from companion.config import DEFAULT_CONFIG
    from companion.flight import run_demo

    out = tmp / "flight"
    run_demo(DEFAULT_CONFIG, "paper", seconds, out, (), (), plots=False)
    return out / "flight.mcap"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--log", type=Path, help="a flight log (default: fly 30 s first)")
    ap.add_argument("--seconds", type=float, default=30.0, help="flight length without --log")
    ap.add_argument("--repeat", type=int, default=2, help="frames sent this many times")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    cfg = load_config()
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        log = args.log or fly(tmp, args.seconds)
        frames, images = flight_frames(log)
        mix = with_unused(frames, cfg.mavlink.target_system, cfg.mavlink.target_component or 1)
        rx = receive(cfg, mix * args.repeat, tmp)
        rx["direct_link_us_per_datagram"] = direct(cfg, mix)
        cr = [crops(cfg, images, tmp, e) for e in ("png", "raw")]
    out = {"load": os.getloadavg(), "log": str(log), "receive": rx, "crops": cr}
    if args.json:
        print(json.dumps(out, indent=1, default=str))
        return
    c = rx["counters"]
    print(f"load {os.getloadavg()[0]:.2f}; frames from {log}")
    print(f"receive: {rx['datagrams']} datagrams over UDP ({c.get('rx_accepted', 0)} accepted, "
          f"{c.get('unused', 0)} unused, {c.get('rejected', 0)} rejected)")
    print(f"  event-loop thread CPU per datagram   {rx['rx_loop_us_per_datagram']:7.1f} us, "
          "of which")
    print(f"    the link (read, checks, decode)    {rx['rx_link_us_per_datagram']:7.1f} us")
    print(f"    its log record (enqueue), accepted {rx['rx_record_us_per_accepted']:7.1f} us")
    print(f"    Vehicle.on_rx (store, offboard)    {rx['rx_vehicle_us_per_accepted']:7.1f} us "
          "per accepted frame")
    print(f"  the link's code alone, called directly {rx['direct_link_us_per_datagram']:5.1f} us "
          "per datagram (no socket, no loop)")
    print(f"  writer thread CPU per record         {rx['writer_us_per_record']:7.1f} us "
          f"(in and out records)")
    print(f"send: SET_ATTITUDE_TARGET + its record {rx['tx_us_per_send']:7.1f} us (loop thread)")
    for r in cr:
        print(f"crops {r['encoding']:>4}: {r['crops']} crops of {r['pixels_per_crop']:.0f} px: "
              f"writer CPU {r['writer_us_per_crop']:7.1f} us, {r['bytes_per_crop'] / 1e3:6.1f} "
              f"kB a crop in the file")
    # a lockstep paper flight's step: 6.4 datagrams in (5.4 accepted), 1.7 frames out, one crop
    acc = c.get("rx_accepted", 0) / max(rx["datagrams"], 1)
    link = (6.4 * (rx["rx_link_us_per_datagram"] + acc * rx["rx_record_us_per_accepted"])
            + 1.7 * rx["tx_us_per_send"])
    writer = (6.4 * acc + 1.7) * rx["writer_us_per_record"] + cr[0]["writer_us_per_crop"]
    print(f"per step of a paper flight (6.4 datagrams in, 1.7 frames out, 1 png crop): link "
          f"and its records {link / 1e3:.2f} ms + writer {writer / 1e3:.2f} ms CPU "
          f"(Vehicle.on_rx apart: {6.4 * acc * rx['rx_vehicle_us_per_accepted'] / 1e3:.2f} ms)")


if __name__ == "__main__":
    main()
