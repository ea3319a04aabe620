"""Live view (companion.log.live) in process: a real foxglove-sdk server fed by a real MCAP
logger, a real WebSocket client speaking the Foxglove protocol; the client gets the bytes and
schemas the file gets. The whole flight with a live client is in tests/e2e/test_live.py."""

from __future__ import annotations

import asyncio
import json
import socket
import threading
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from companion.config import ConfigError, load_config
from companion.log.live import LiveServer, LiveViewError, start_live
from companion.log.reader import LogReader, decode_protobuf_image
from companion.log.writer import McapLogger
from tests.foxglove_ws import Capture, capture

pytest.importorskip("foxglove")


def _step(i: int) -> dict[str, Any]:
    return {"t_us": 1000 * i, "success": True, "status": "Solve_Succeeded", "k": i}


def test_client_gets_what_the_file_gets(tmp_path: Path) -> None:
    img = (np.arange(64 * 80) % 251).astype(np.uint8).reshape(64, 80)
    with LiveServer("127.0.0.1", 0) as live:
        lg = McapLogger(tmp_path / "a.mcap", flush_interval_s=0.05)
        lg.observer = live
        with lg:
            lg.log("/control/step", 1, _step(0), schema="companion.ControllerStep")
            lg.log_image("/camera/image", 2, img, "png")
            # the topics exist (advertised) before any client: subscribe, then stream
            result: list[Capture] = []

            def client() -> None:
                result.append(
                    asyncio.run(
                        capture(
                            live.url,
                            ["/control/step", "/camera/image"],
                            lambda c: (
                                c.count("/control/step") >= 20 and c.count("/camera/image") >= 3
                            ),
                            timeout_s=60.0,
                        )
                    )
                )

            th = threading.Thread(target=client)
            th.start()
            i = 1
            while th.is_alive() and i < 100_000:
                lg.log("/control/step", 10 + i, _step(i), schema="companion.ControllerStep")
                if i % 10 == 0:
                    lg.log_image("/camera/image", 10 + i, img, "png")
                i += 1
                th.join(0.01)
            th.join()
        stats = live.stats
    cap = result[0]
    with LogReader(tmp_path / "a.mcap") as r:
        file_chans = {c.topic: c for c in r.channels}
        file_msgs = {(m.topic, m.log_time_ns): m.raw for m in r.messages()}
    for topic in ("/control/step", "/camera/image"):
        ch = cap.channels[topic]
        assert ch["schemaName"] == file_chans[topic].schema_name
        assert ch["encoding"] == file_chans[topic].message_encoding
        for t_ns, _, payload in cap.messages[topic]:
            assert file_msgs[(topic, t_ns)] == payload  # the same bytes, the same log time
    steps = [json.loads(p) for _, _, p in cap.messages["/control/step"]]
    assert [s["k"] for s in steps] == sorted(s["k"] for s in steps)
    _, picture = decode_protobuf_image(
        "foxglove.CompressedImage", cap.messages["/camera/image"][0][2]
    )
    assert picture is not None and np.array_equal(picture, img)
    assert cap.channels["/camera/image"]["schemaEncoding"] == "protobuf"
    # before the client subscribed, messages were skipped, not queued
    assert stats.unsubscribed >= 2 and stats.published >= 23 and stats.dropped == 0


def test_a_late_client_gets_each_topic_s_newest_message(tmp_path: Path) -> None:
    """Topics written once or rarely (the initial safety state, the config) are latched."""
    with LiveServer("127.0.0.1", 0) as live:
        lg = McapLogger(tmp_path / "a.mcap", flush_interval_s=0.05)
        lg.observer = live
        with lg:
            lg.log_text("/control/safety", 5, "nominal: start", level="WARNING", name="safety")
            lg.log("/control/step", 6, _step(1), schema="companion.ControllerStep")
            lg.log("/control/step", 7, _step(2), schema="companion.ControllerStep")
            while live.stats.offered < 3:  # written by the writer thread
                threading.Event().wait(0.01)
            cap = asyncio.run(
                capture(
                    live.url,
                    None,
                    lambda c: c.count("/control/safety") >= 1 and c.count("/control/step") >= 1,
                    timeout_s=30.0,
                )
            )
    assert [t for t, _, _ in cap.messages["/control/safety"]] == [5]
    assert json.loads(cap.messages["/control/safety"][0][2])["message"] == "nominal: start"
    assert [json.loads(p)["k"] for _, _, p in cap.messages["/control/step"]] == [2]


class _Stuck:
    """A channel whose publishing blocks until released (a stalled SDK or network)."""

    def __init__(self) -> None:
        self.release = threading.Event()
        self.entered = threading.Event()
        self.got: list[int] = []

    def log(self, data: bytes, log_time: int) -> None:
        self.entered.set()
        self.release.wait(30.0)
        self.got.append(log_time)


def test_a_stalled_publisher_drops_the_oldest_and_never_blocks_the_writer() -> None:
    live = LiveServer("127.0.0.1", 0, queue_size=8).start()
    try:
        stuck = _Stuck()
        live._channels["/x"] = stuck  # white box: a channel that never returns
        live._subs["/x"] = 1
        live.message("/x", 0, b"{}")
        assert stuck.entered.wait(10.0)  # the publisher holds message 0
        for t in range(1, 101):  # returns every time although nothing is published
            live.message("/x", t, b"{}")
        s = live.stats
        assert s.dropped == 100 - 8 and s.queued == 101 and s.published == 0
        stuck.release.set()
        for _ in range(200):
            if live.stats.published == 9:
                break
            threading.Event().wait(0.05)
        assert stuck.got == [0, *range(93, 101)]  # the newest 8 survived, in order
    finally:
        stuck.release.set()
        live.close()


def test_taken_port_fails_clearly() -> None:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        port = s.getsockname()[1]
        with pytest.raises(LiveViewError, match=rf"127\.0\.0\.1:{port}.*port is taken"):
            LiveServer("127.0.0.1", port).start()


def test_config_off_by_default_and_validated() -> None:
    cfg = load_config()
    assert cfg.live.enabled is False and cfg.live.host == "127.0.0.1"
    assert start_live(cfg.live) is None
    with pytest.raises(ConfigError, match=r"live\.port"):
        load_config(overrides=["live.port=70000"])
    with pytest.raises(ConfigError, match=r"live\.queue_size"):
        load_config(overrides=["live.queue_size=0"])
    with pytest.raises(ConfigError, match=r"live\.enabled"):
        load_config(overrides=['live.enabled="yes"'])


class _Broken:
    def add_channel(self, *args: Any) -> None:
        pass

    def message(self, topic: str, log_time_ns: int, data: bytes) -> None:
        raise RuntimeError("live view gone")


def test_a_failing_observer_is_detached_and_the_log_keeps_everything(tmp_path: Path) -> None:
    lg = McapLogger(tmp_path / "a.mcap")
    lg.observer = _Broken()
    with lg:
        for i in range(50):
            lg.log("/control/step", i, _step(i), schema="companion.ControllerStep")
    assert lg.observer is None and lg.stats.written == 50 and lg.failure is None
    with LogReader(tmp_path / "a.mcap") as r:
        assert [json.loads(m.raw)["k"] for m in r.messages()] == list(range(50))
