"""Live view end to end: a real Foxglove WebSocket client subscribes to a running companion in
a short lockstep flight (emulator and companion as processes on loopback, as ``companion demo
--live`` runs them) and receives the controller-step and image channels with payloads that
decode; the shipped layout's topics are served live with the schemas the MCAP file has."""

from __future__ import annotations

import asyncio
import json
import os
import re
import subprocess
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from companion.config import DEFAULT_CONFIG
from companion.flight import demo_commands, free_port
from companion.log.reader import LogReader, decode_protobuf_image
from tests.foxglove_ws import Capture, capture

pytestmark = pytest.mark.slow
pytest.importorskip("foxglove")

ROOT = Path(__file__).resolve().parents[2]
DURATION_S = 6.0


def _layout_topics() -> set[str]:
    text = (ROOT / "foxglove" / "layout.json").read_text()
    json.loads(text)
    return set(re.findall(r'"(/[a-z_/A-Z]+)', text))


@pytest.fixture(scope="module")
def live_flight(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Capture, str]:
    import socket

    out = tmp_path_factory.mktemp("live")
    port = free_port(socket.SOCK_STREAM)
    sim_cmd, comp_cmd = demo_commands(
        DEFAULT_CONFIG,
        "paper",
        DURATION_S,
        out,
        # buffers large enough that nothing is dropped for a slow client: the test is about
        # delivery and content (dropping is tested in tests/companion/test_live_view.py)
        [f"live.port={port}", "live.client_backlog=1000000", "live.queue_size=1000000"],
        [],
        live=True,
    )
    assert "--live" in comp_cmd
    env = dict(os.environ, PYTHONPATH=str(ROOT), PYTHONUNBUFFERED="1")
    caps: list[Capture] = []
    connected = threading.Event()

    def client() -> None:
        def done(c: Capture) -> bool:
            connected.set()
            return False  # until the companion closes the connection at its exit

        caps.append(
            asyncio.run(
                capture(
                    f"ws://127.0.0.1:{port}", None, done, timeout_s=300.0, connect_timeout_s=300.0
                )
            )
        )

    with open(out / "companion.log", "w") as clog, open(out / "sim.log", "w") as slog:
        comp = subprocess.Popen(comp_cmd, stdout=clog, stderr=subprocess.STDOUT, env=env)
        th = threading.Thread(target=client, daemon=True)
        sim = None
        try:
            ready = out / ".companion-ready"
            t0 = time.monotonic()
            while not ready.exists():
                assert comp.poll() is None, (out / "companion.log").read_text()[-3000:]
                assert time.monotonic() - t0 < 300.0, "companion did not start"
                time.sleep(0.05)
            th.start()
            assert connected.wait(60.0), "no live connection"
            sim = subprocess.Popen(sim_cmd, stdout=slog, stderr=subprocess.STDOUT, env=env)
            assert sim.wait(timeout=300.0) == 0, (out / "sim.log").read_text()[-3000:]
            assert comp.wait(timeout=60.0) == 0, (out / "companion.log").read_text()[-3000:]
            th.join(30.0)
        finally:
            for p in (sim, comp):
                if p is not None and p.poll() is None:
                    p.kill()
                    p.wait()
    assert caps, "client did not finish"
    return out, caps[0], (out / "companion.log").read_text()


def test_client_receives_decodable_step_and_image_channels(
    live_flight: tuple[Path, Capture, str],
) -> None:
    out, cap, _ = live_flight
    with LogReader(out / "flight.mcap") as r:
        file_steps = {m.log_time_ns: m.raw for m in r.messages(["/control/step"])}
        file_images = {m.log_time_ns: m.raw for m in r.messages(["/camera/image"], decode=False)}
    steps = cap.messages["/control/step"]
    # subscribed when the channel was advertised, i.e. after its first message
    assert len(file_steps) >= DURATION_S * 20 - 3 and len(steps) >= 20
    # in order and without gaps from the first one received (the server may cut the tail when
    # the companion exits); a latched copy of the newest message may repeat once at subscribe
    seqs = [json.loads(p)["frame_seq"] for _, _, p in steps]
    seqs = [q for i, q in enumerate(seqs) if i == 0 or q != seqs[i - 1]]
    assert seqs == list(range(seqs[0], seqs[0] + len(seqs)))
    for t_ns, _, payload in steps:
        rec = json.loads(payload)
        assert {"t_s", "eta_e", "rmpc", "setpoint", "timings_ms"} <= rec.keys()
        assert payload == file_steps[t_ns]
    solved = [json.loads(p)["rmpc"] for _, _, p in steps]
    assert sum(bool(r and r["success"]) for r in solved) >= len(steps) - 3
    images = cap.messages["/camera/image"]
    assert len(images) >= 10
    for t_ns, _, payload in images[:: max(1, len(images) // 10)]:
        assert payload == file_images[t_ns]
        _, picture = decode_protobuf_image(cap.channels["/camera/image"]["schemaName"], payload)
        assert picture is not None and picture.dtype == np.uint8 and min(picture.shape[:2]) >= 100


def test_layout_topics_are_served_live_and_in_the_file(
    live_flight: tuple[Path, Capture, str],
) -> None:
    out, cap, _ = live_flight
    wanted = _layout_topics()
    assert {"/camera/image", "/control/step", "/vehicle/pose", "/target/pose"} <= wanted
    with LogReader(out / "flight.mcap") as r:
        file_chans = {c.topic: c for c in r.channels}
    assert wanted <= set(file_chans), wanted - set(file_chans)
    assert wanted <= set(cap.channels), wanted - set(cap.channels)
    for topic in wanted:
        live = cap.channels[topic]
        assert live["schemaName"] == file_chans[topic].schema_name, topic
        assert live["encoding"] == file_chans[topic].message_encoding, topic
        assert cap.count(topic) > 0, topic


def test_live_view_counters_in_the_companion_log(live_flight: tuple[Path, Capture, str]) -> None:
    _, cap, text = live_flight
    m = re.search(r"live view closed: (\d+) messages published, (\d+) dropped", text)
    assert m is not None, text[-2000:]
    published = int(m[1])
    received = sum(len(v) for v in cap.messages.values())
    assert 0 < received <= published and int(m[2]) == 0  # nothing dropped from our queue
    rates = {t: len(v) / DURATION_S for t, v in sorted(cap.messages.items())}
    print("live messages per simulated second:", json.dumps(rates))
