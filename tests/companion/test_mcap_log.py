"""McapLogger on real files (and a real FIFO to stall the writer), read back with mcap's own
reader and with companion.log.reader."""

from __future__ import annotations

import base64
import json
import math
import os
import shutil
import threading
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from mcap.reader import make_reader
from pymavlink.dialects.v20 import common as mavlink2

from companion.link import Received, Sent
from companion.log import McapLogError
from companion.log import schemas as sch
from companion.log.encode import encode_json
from companion.log.reader import LogReader
from companion.log.writer import McapLogger

ROOT = Path(__file__).resolve().parents[2]


def _image(h: int = 60, w: int = 80) -> np.ndarray:
    """A smooth BGR test picture (JPEG-friendly) with a sharp-edged square."""
    yy, xx = np.mgrid[0:h, 0:w]
    img = np.stack([xx * 255 // w, yy * 255 // h, (xx + yy) * 255 // (w + h)], axis=-1)
    img = img.astype(np.uint8)
    img[20:40, 30:50] = (255, 255, 255)
    return img


def _mavlink_items() -> tuple[Received, Sent]:
    ap = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
    raw_in = bytes(ap.attitude_quaternion_encode(5, 1.0, 0.0, 0.0, 0.0, 0.1, 0.2, 0.3).pack(ap))
    msg_in = mavlink2.MAVLink(None).parse_buffer(raw_in)[0]
    rx = Received(msg_in, raw_in, 123, 1, 1, 31, "ATTITUDE_QUATERNION", 0, False)
    me = mavlink2.MAVLink(None, srcSystem=1, srcComponent=191)
    out = me.command_long_encode(1, 1, 176, 0, 1, 6, 0, 0, 0, 0, math.nan)
    raw_out = bytes(out.pack(me))
    tx = Sent(out, raw_out, 456, 76, "COMMAND_LONG")
    return rx, tx


def test_roundtrip_all_channel_kinds(tmp_path: Path) -> None:
    path = tmp_path / "run.mcap"
    img = _image()
    gray = img[:, :, 1].copy()
    rx, tx = _mavlink_items()
    steps: list[dict[str, Any]] = []
    with McapLogger(path, chunk_size=2048, flush_interval_s=0.05, queue_size=10_000) as lg:
        lg.log_config(0, "[control]\nrate_hz = 20.0\n", {"control": {"rate_hz": 20.0}}, "x.toml")
        for k in range(200):
            step = {
                "t_us": 50_000 * k, "success": k % 7 != 0, "status": "Solve_Succeeded",
                "u": np.array([0.1 * k, -0.2, math.nan, math.inf]), "k": np.int64(k),
            }  # fmt: skip
            steps.append(step)
            assert lg.log("/control/step", 50_000_000 * k + 10, step, schema=sch.CONTROLLER_STEP)
        for k in range(20):
            # images logged later in the queue but stamped earlier: readers must re-order
            assert lg.log_image("/camera/jpeg", 50_000_000 * k, img, "jpeg")
            assert lg.log_image("/camera/raw", 50_000_000 * k + 1, gray, "raw")
        assert lg.log_image("/camera/png", 7, img, "png")
        assert lg.log_text("/log", 11, "offboard engaged", "WARNING", "safety")
        assert lg.log_pose("/uav/pose", 12, "ned", [1.0, 2.0, -3.0], [0.5, 0.5, 0.5, 0.5])
        assert lg.log_transform("/tf", 13, "ned", "uav", [1, 2, 3], [1, 0, 0, 0])
        assert lg.log_mavlink("in", rx)
        assert lg.log_mavlink("out", tx, log_time_ns=999)
        assert lg.log("/pre", 14, b'{"already":"json"}', schema=sch.JSON)
        assert lg.log_rejected("bad_signature", b"\xfd\x00", 15)
    st = lg.stats
    total = 1 + 200 + 40 + 1 + 7
    assert (st.enqueued, st.written, st.flushed, st.dropped, st.errors) == (total,) * 3 + (0, 0)

    # --- mcap's own reader: counts, schemas, encodings, JSON -----------------------------------
    with open(path, "rb") as f:
        reader = make_reader(f, validate_crcs=True)
        summary = reader.get_summary()
        assert summary is not None and summary.statistics is not None
        assert summary.statistics.message_count == total
        by_topic = {c.topic: c for c in summary.channels.values()}
        counts = summary.statistics.channel_message_counts
        assert counts[by_topic["/control/step"].id] == 200
        assert counts[by_topic["/camera/jpeg"].id] == 20
        expect_schema = {
            "/config": sch.CONFIG, "/control/step": sch.CONTROLLER_STEP,
            "/camera/jpeg": sch.COMPRESSED_IMAGE, "/camera/raw": sch.RAW_IMAGE,
            "/camera/png": sch.COMPRESSED_IMAGE, "/log": sch.LOG, "/uav/pose": sch.POSE_IN_FRAME,
            "/tf": sch.FRAME_TRANSFORM, "/mavlink/in/ATTITUDE_QUATERNION":
            "companion.mavlink.ATTITUDE_QUATERNION", "/mavlink/out/COMMAND_LONG":
            "companion.mavlink.COMMAND_LONG", "/pre": sch.JSON,
            "/mavlink/rejected": sch.MAVLINK_REJECTED,
        }  # fmt: skip
        assert set(by_topic) == set(expect_schema)
        pb_classes = {}
        for topic, ch in by_topic.items():
            schema = summary.schemas[ch.schema_id]
            assert schema.name == expect_schema[topic]
            if topic.startswith("/camera/"):
                # frames are protobuf, self-described by the FileDescriptorSet in the file
                assert ch.message_encoding == "protobuf" and schema.encoding == "protobuf"
                pb_classes[topic] = _class_from_file_descriptor_set(schema.data, schema.name)
                continue
            assert ch.message_encoding == "json" and schema.encoding == "jsonschema"
            assert json.loads(schema.data)["title"] == schema.name
        mine = [
            (ch.topic, m.log_time, _pb_to_dict(pb_classes[ch.topic], m.data)
             if ch.topic in pb_classes else json.loads(m.data))
            for _, ch, m in reader.iter_messages(log_time_order=True)
        ]
    times = [t for _, t, _ in mine]
    assert times == sorted(times)
    ctrl = [d for topic, _, d in mine if topic == "/control/step"]
    assert ctrl[3] == {
        "t_us": 150_000, "success": True, "status": "Solve_Succeeded",
        "u": [0.30000000000000004, -0.2, None, None], "k": 3,
    }  # fmt: skip
    assert [d["t_us"] for d in ctrl] == [s["t_us"] for s in steps]
    jpeg = next(d for topic, _, d in mine if topic == "/camera/jpeg")
    assert jpeg["format"] == "jpeg" and jpeg["timestamp"] == {"sec": 0, "nsec": 0}
    dec = cv2.imdecode(np.frombuffer(jpeg["data"], np.uint8), cv2.IMREAD_COLOR)
    assert dec.shape == img.shape and np.abs(dec.astype(int) - img).mean() < 3.0
    raw = [d for topic, _, d in mine if topic == "/camera/raw"]
    assert raw[1]["timestamp"] == {"sec": 0, "nsec": 50_000_001}
    assert (raw[1]["width"], raw[1]["height"], raw[1]["encoding"], raw[1]["step"]) == (
        gray.shape[1], gray.shape[0], "mono8", gray.shape[1])
    assert np.array_equal(np.frombuffer(raw[1]["data"], np.uint8).reshape(gray.shape), gray)
    mav_in = next(d for topic, _, d in mine if topic.startswith("/mavlink/in/"))
    assert base64.b64decode(mav_in["raw_b64"]) == rx.raw
    assert mav_in["t_rx_ns"] == 123 and mav_in["sysid"] == 1
    assert mav_in["fields"]["rollspeed"] == pytest.approx(0.1)
    reparsed = mavlink2.MAVLink(None).parse_buffer(base64.b64decode(mav_in["raw_b64"]))[0]
    assert reparsed.q1 == 1.0
    mav_out = next((t, d) for topic, t, d in mine if topic.startswith("/mavlink/out/"))
    assert mav_out[0] == 999 and mav_out[1]["fields"]["param7"] is None  # NaN -> null
    assert mav_out[1]["t_tx_ns"] == 456
    pose = next(d for topic, _, d in mine if topic == "/uav/pose")
    assert pose["pose"]["orientation"] == {"x": 0.5, "y": 0.5, "z": 0.5, "w": 0.5}
    rej = next(d for topic, _, d in mine if topic == "/mavlink/rejected")
    assert rej == {"reason": "bad_signature", "raw_b64": "/QA=", "t_rx_ns": 15}
    log_msg = next(d for topic, _, d in mine if topic == "/log")
    assert (log_msg["level"], log_msg["name"]) == (3, "safety")

    # --- our reader: same messages in the same order, images decoded ---------------------------
    with LogReader(path) as r:
        assert not r.recovery.salvaged and not r.recovery.truncated
        assert r.recovery.messages == total
        ours = list(r.messages())
    assert [(m.topic, m.log_time_ns) for m in ours] == [(t, lt) for t, lt, _ in mine]
    assert [m.data for m in ours if m.topic == "/control/step"] == ctrl
    raw_imgs = [m.image for m in ours if m.topic == "/camera/raw"]
    assert len(raw_imgs) == 20 and all(np.array_equal(i, gray) for i in raw_imgs)
    png = next(m for m in ours if m.topic == "/camera/png")
    assert np.array_equal(png.image, img) and png.data is not None and "data" not in png.data
    jp = next(m for m in ours if m.topic == "/camera/jpeg")
    assert jp.image is not None and np.abs(jp.image.astype(int) - img).mean() < 3.0


def test_from_config_uses_the_logging_table(tmp_path: Path) -> None:
    from companion.config import load_config

    cfg = load_config(ROOT / "config" / "paper.toml").logging
    lg = McapLogger.from_config(cfg, tmp_path / "c.mcap")
    assert (lg.chunk_size, lg.flush_interval_s, lg.queue_size) == (
        cfg.chunk_size_bytes, cfg.flush_interval_s, cfg.queue_size,
    )  # fmt: skip


def test_misuse_is_a_clear_error(tmp_path: Path) -> None:
    with pytest.raises(McapLogError, match="cannot open"):
        McapLogger(tmp_path / "no" / "such" / "dir.mcap").open()
    with pytest.raises(McapLogError):
        McapLogger(tmp_path / "x.mcap", chunk_size=0)
    with McapLogger(tmp_path / "x.mcap") as lg:
        with pytest.raises(McapLogError, match="unknown schema"):
            lg.log("/a", 1, {}, schema="nope.Nope")
        with pytest.raises(McapLogError, match="give its schema"):
            lg.log("/b", 1, {})
        lg.log("/c", 1, {}, schema=sch.JSON)
        with pytest.raises(McapLogError, match="already uses"):
            lg.log("/c", 2, {}, schema=sch.PERCEPTION)
        lg.log("/c", 3, {"ok": True})  # schema known from the first use
        with pytest.raises(McapLogError, match="non-negative"):
            lg.log("/c", -1, {})
        with pytest.raises(McapLogError, match="encoding"):
            lg.log_image("/img", 1, _image(), "gif")
        # a bad image or a non-serialisable payload is counted, the logger keeps going
        assert lg.log_image("/img", 2, np.zeros((4, 4), np.float32))
        assert lg.log("/c", 4, {"bad": object()})
        assert lg.log("/c", 5, {"after": 1})
    assert (lg.stats.errors, lg.stats.written) == (2, 3)
    assert not lg.log("/c", 6, {})  # closed: dropped
    assert lg.dropped == 1


def test_encode_json_handles_numpy_and_non_finite() -> None:
    out = json.loads(encode_json({"a": np.float32(1.5), "b": [math.nan, 1.0], "c": b"\x00\x01"}))
    assert out == {"a": 1.5, "b": [None, 1.0], "c": "AAE="}


def test_full_queue_drops_and_counts_without_blocking(tmp_path: Path) -> None:
    """The writer is stalled on purpose: it writes into a FIFO nobody reads (yet)."""
    fifo = tmp_path / "stall.mcap"
    os.mkfifo(fifo)
    rfd = os.open(fifo, os.O_RDONLY | os.O_NONBLOCK)  # a reader exists but does not read
    pad = base64.b64encode(os.urandom(3000)).decode()
    lg = McapLogger(fifo, chunk_size=512, flush_interval_s=0.05, queue_size=16, compression="none")
    lg.open()
    attempts = 0
    t0 = time.monotonic()
    while lg.dropped < 100 and attempts < 20_000:
        lg.log("/pad", attempts, {"i": attempts, "pad": pad}, schema=sch.JSON)
        attempts += 1
    elapsed = time.monotonic() - t0
    st = lg.stats
    assert st.dropped >= 100, "the stalled writer never filled the queue"
    assert st.enqueued + st.dropped == attempts
    assert st.written < st.enqueued  # the writer is stuck in a write
    assert elapsed < 10.0  # every call returned although the writer is blocked

    got = bytearray()

    def drain() -> None:
        os.set_blocking(rfd, True)
        while chunk := os.read(rfd, 1 << 16):
            got.extend(chunk)

    reader = threading.Thread(target=drain)
    reader.start()
    lg.close()
    reader.join(10.0)
    os.close(rfd)
    out = tmp_path / "drained.mcap"
    out.write_bytes(bytes(got))
    with LogReader(out) as r:
        assert not r.recovery.truncated
        idx = [m.data["i"] for m in r.messages() if m.data is not None]
    assert lg.stats.written == lg.stats.enqueued == len(idx)
    assert idx == sorted(idx) and len(set(idx)) == len(idx)


def test_flushed_data_is_readable_while_the_logger_is_still_open(tmp_path: Path) -> None:
    path = tmp_path / "live.mcap"
    with McapLogger(path, chunk_size=1 << 20, flush_interval_s=0.05) as lg:
        for i in range(300):
            lg.log("/seq", i, {"i": i}, schema=sch.JSON)
        deadline = time.monotonic() + 5.0
        while lg.stats.flushed < 300 and time.monotonic() < deadline:
            time.sleep(0.01)
        assert lg.stats.flushed == 300
        snap = tmp_path / "snapshot.mcap"
        shutil.copyfile(path, snap)  # what a power cut right now would leave
        with LogReader(snap) as r:
            rec = r.recovery
            seq = [m.data["i"] for m in r.messages() if m.data is not None]
    assert rec.truncated and rec.salvaged and rec.messages == 300
    assert seq == list(range(300))


def test_writer_failure_stops_logging_not_the_caller(tmp_path: Path) -> None:
    lg = McapLogger("/dev/full", chunk_size=256, flush_interval_s=0.01)
    lg.open()
    deadline = time.monotonic() + 5.0
    i = 0
    while lg.failure is None and time.monotonic() < deadline:
        lg.log("/x", i, {"i": i}, schema=sch.JSON)
        i += 1
        time.sleep(0.001)
    assert isinstance(lg.failure, OSError)
    assert not lg.log("/x", i, {"i": i}, schema=sch.JSON)  # dropped, no exception
    with pytest.raises(McapLogError, match="writer failed"):
        lg.close()


def test_image_backlog_is_bounded_in_bytes_drop_or_wait(tmp_path: Path) -> None:
    """Frames waiting for (slow, PNG) encoding are bounded in bytes: dropped and counted by
    default; with ``block_on_backlog`` (lockstep) the caller waits and nothing is lost."""
    import numpy as np

    from companion.log.reader import LogReader
    from companion.log.writer import McapLogger

    rng = np.random.default_rng(0)
    imgs = [rng.integers(0, 255, (1000, 1000), dtype=np.uint8) for _ in range(3)]
    budget = int(2.5 * imgs[0].nbytes)
    n = 12
    for block in (False, True):
        path = tmp_path / f"b{block}.mcap"
        with McapLogger(path, max_pending_image_bytes=budget, block_on_backlog=block) as lg:
            accepted = sum(lg.log_image("/cam", i, imgs[i % 3], "png") for i in range(n))
            dropped = lg.images_dropped
        with LogReader(path) as r:
            logged = sum(1 for _ in r.messages(topics=["/cam"], decode=False))
        assert logged == accepted
        if block:
            assert accepted == n and dropped == 0
        else:
            assert 2 <= accepted < n and dropped == n - accepted


def _class_from_file_descriptor_set(data: bytes, full_name: str) -> Any:
    """The message class described by an MCAP protobuf schema, built with protobuf's own
    descriptor pool (what Foxglove does), not with the generated module the writer used."""
    from google.protobuf import descriptor_pool, message_factory
    from google.protobuf.descriptor_pb2 import FileDescriptorSet

    fds = FileDescriptorSet.FromString(data)
    assert [f.name for f in fds.file][-1].endswith(full_name.split(".")[-1] + ".proto")
    pool = descriptor_pool.DescriptorPool()
    for f in fds.file:
        pool.Add(f)
    return message_factory.GetMessageClass(pool.FindMessageTypeByName(full_name))


def _pb_to_dict(cls: Any, data: bytes) -> dict[str, Any]:
    msg = cls.FromString(data)
    out = {f.name: v for f, v in msg.ListFields()}
    out["timestamp"] = {"sec": msg.timestamp.seconds, "nsec": msg.timestamp.nanos}
    return out


@pytest.mark.parametrize("compression", ["lz4", "zstd", "none"])
def test_chunk_compression_from_config(tmp_path: Path, compression: str) -> None:
    """``logging.compression`` reaches the file's chunk records, and every kind reads back."""
    from mcap.records import Chunk
    from mcap.stream_reader import StreamReader

    from companion.config import load_config
    from companion.log.reader import read_log

    cfg = load_config(None, [f'logging.compression="{compression}"'])
    path = tmp_path / f"{compression}.mcap"
    gray = np.random.default_rng(1).integers(0, 255, (64, 80), dtype=np.uint8)
    with McapLogger.from_config(cfg.logging, path) as lg:
        for k in range(5):
            assert lg.log_image("/camera/image", k, gray, "raw")
            assert lg.log("/x", k, {"k": k}, schema=sch.JSON)
    with open(path, "rb") as f:
        kinds = {r.compression for r in StreamReader(f, emit_chunks=True).records
                 if isinstance(r, Chunk)}
    assert kinds == {"" if compression == "none" else compression}
    rec, msgs = read_log(path)
    assert rec.messages == 10 and not rec.salvaged
    assert all(np.array_equal(m.image, gray) for m in msgs if m.topic == "/camera/image")


def test_a_held_writer_waits_for_release_and_loses_nothing(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The control step holds the writer thread off the GIL (McapLogger.hold); messages logged
    meanwhile wait in the queue and are all written once released, in order; a hold never
    outlives its cap (close does not hang on a logger left held)."""
    import companion.log.writer_thread as writer_thread

    monkeypatch.setattr(writer_thread, "MAX_HOLD_S", 30.0)
    path = tmp_path / "held.mcap"
    with McapLogger(path, chunk_size=1 << 20, flush_interval_s=0.05) as lg:
        lg.hold()
        for i in range(20):
            lg.log("/seq", i, {"i": i}, schema=sch.JSON)
        time.sleep(0.2)
        assert lg.stats.written == 0  # held: nothing written (the cap is 30 s here)
        lg.release()
        deadline = time.monotonic() + 5.0
        while lg.stats.written < 20 and time.monotonic() < deadline:
            time.sleep(0.01)
        assert lg.stats.written == 20
    with LogReader(path) as r:
        assert [m.data["i"] for m in r.messages() if m.data is not None] == list(range(20))

    monkeypatch.setattr(writer_thread, "MAX_HOLD_S", 0.01)
    path2 = tmp_path / "left-held.mcap"
    with McapLogger(path2, chunk_size=1 << 20, flush_interval_s=0.05) as lg:
        lg.hold()  # never released: each message waits at most the cap
        for i in range(5):
            lg.log("/seq", i, {"i": i}, schema=sch.JSON)
    with LogReader(path2) as r:
        assert [m.data["i"] for m in r.messages() if m.data is not None] == list(range(5))


@pytest.mark.parametrize("shape", [(1, 1), (7, 5), (241, 333), (16, 9, 3), (1, 4, 3)])
def test_png_bytes_is_a_lossless_standard_png(shape: tuple[int, ...]) -> None:
    """The logged crops' PNG writer (ISA-L deflate, UP filter): OpenCV and Pillow, two
    independent decoders, both give back every pixel (BGR in, BGR back from OpenCV)."""
    import io

    from PIL import Image

    from companion.log.encode import png_bytes

    rng = np.random.default_rng(sum(shape))
    img = rng.integers(0, 256, shape, dtype=np.uint8)
    data = png_bytes(img)
    back = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    assert back is not None and np.array_equal(back, img)
    pil = np.asarray(Image.open(io.BytesIO(data)))  # Pillow checks every chunk's CRC
    assert np.array_equal(pil, img if img.ndim == 2 else img[:, :, ::-1])
    # a non-contiguous view (a crop of a frame) is what the recorder hands over
    frame = rng.integers(0, 256, (50, 60), dtype=np.uint8)
    crop = frame[10:40, 5:45]
    back = cv2.imdecode(np.frombuffer(png_bytes(crop), np.uint8), cv2.IMREAD_UNCHANGED)
    assert np.array_equal(back, crop)


def test_encode_json_values_match_the_json_module() -> None:
    """encode_json (orjson) reads back to the same values as the json module's encoding,
    NaN/inf as null, numpy float32 at float64 precision, bytes as base64, int keys as text."""
    payload: dict[Any, Any] = {
        "f": [0.1, 1e-5, 1e16, -0.0, 123456.789, float("nan"), float("inf")],
        "np": np.array([[1.5, np.nan], [np.float32(0.1), -np.inf]]),
        "f32": np.float32(0.1), "i64": np.int64(-7), "b": b"\x00\xff", "t": (1, 2),
        "nested": {"x": [{"y": float("-inf")}]}, 3: "int key", "big": 2**70,
    }
    reference = json.dumps(_nulled(payload), allow_nan=False, default=_plain)
    assert json.loads(encode_json(payload)) == json.loads(reference)
    small = {k: v for k, v in payload.items() if k != "big"}  # orjson's own path, not the fallback
    assert json.loads(encode_json(small)) == json.loads(
        json.dumps(_nulled(small), allow_nan=False, default=_plain))


def _plain(o: Any) -> Any:
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, bytes):
        return base64.b64encode(o).decode()
    raise TypeError(type(o))


def _nulled(o: Any) -> Any:
    if isinstance(o, np.ndarray | np.generic):
        o = o.tolist()
    if isinstance(o, float):
        return o if math.isfinite(o) else None
    if isinstance(o, dict):
        return {str(k): _nulled(v) for k, v in o.items()}
    if isinstance(o, list | tuple):
        return [_nulled(v) for v in o]
    return o


def test_decode_json_reads_what_either_encoder_wrote() -> None:
    """Logs written before orjson (json module, compact) and text orjson refuses (NaN
    literals, integers beyond 64 bits) decode to the same values."""
    from companion.log.encode import decode_json

    payload = {"a": [0.1, 1e-05, 2.5e16], "b": {"c": None, "d": True}, "e": "x"}
    old = json.dumps(payload, separators=(",", ":")).encode()
    assert decode_json(old) == payload == decode_json(encode_json(payload))
    odd = decode_json(b'{"n": NaN, "big": 1180591620717411303424}')
    assert math.isnan(odd["n"]) and odd["big"] == 2**70
    with pytest.raises(ValueError):
        decode_json(b'{"cut": ')


def test_a_held_writer_is_let_go_before_the_log_would_wait_or_drop(tmp_path: Path) -> None:
    """The step holds the writer; if the step's own logging then waits for the writer (an
    image backlog with block_on_backlog) or the queue is half full, the hold ends at once:
    otherwise the step would wait for a writer that waits for the step (MAX_HOLD_S a
    message), the backlog would never clear and the queue would drop records."""
    with McapLogger(tmp_path / "a.mcap", compression="none", queue_size=64) as lg:
        lg.hold()
        for i in range(31):
            lg.log("/x", 1_000 + i, {"i": i}, schema=sch.JSON)
        assert not lg._may_write.is_set()  # below half: still held
        lg.hold()
        for i in range(40):
            lg.log("/x", 2_000 + i, {"i": i}, schema=sch.JSON)
        assert lg._may_write.is_set()  # half full: let go
        lg.release()
    img = np.zeros((100, 100), np.uint8)
    with McapLogger(tmp_path / "b.mcap", compression="none", block_on_backlog=True,
                    max_pending_image_bytes=3 * img.nbytes) as lg:
        lg.hold()
        for i in range(3):
            assert lg.log_image("/img", 1_000 + i, img, "png")
        lg.hold()
        assert lg.log_image("/img", 2_000, img, "png")  # over the budget: waits for the writer
        assert lg._may_write.is_set()
        lg.release()
    with LogReader(tmp_path / "b.mcap") as r:
        assert len(list(r.messages(["/img"]))) == 4
