"""Logs a user keeps and replays: crops of what perception read, source-clock log times, exact
replay from the crops, replay from the recorded detections, sweeps, and logs written the old
way (every frame whole on /camera/image, receipt-time stamps) still replaying.

Two short lockstep flights (real UDP, real TCP frames, real CasADi, real MCAP files): one with
the default crops, one logging every frame whole, which :func:`to_old_format` rewrites the way
logs were written before crops existed.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap.writer import Writer

from companion.config import DEFAULT_CONFIG
from companion.flight import run_demo
from companion.log.reader import LogReader
from companion.replay import ReplayError, replay

pytestmark = pytest.mark.slow

DURATION_S = 6.0


@pytest.fixture(scope="module")
def crop_flight(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("crop")
    run_demo(DEFAULT_CONFIG, "paper", DURATION_S, out, [], [], plots=False)
    return out / "flight.mcap"


@pytest.fixture(scope="module")
def full_flight(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("full")
    run_demo(DEFAULT_CONFIG, "paper", DURATION_S, out, ['logging.perception_input="full"'], [],
             plots=False)
    return out / "flight.mcap"


def _steps(path: Path) -> list[tuple[int, dict]]:
    with LogReader(path) as r:
        return [(m.log_time_ns, m.data) for m in r.messages(topics=["/control/step"])]


def test_crops_are_what_perception_read_and_replay_exactly(crop_flight: Path,
                                                           tmp_path: Path) -> None:
    steps = _steps(crop_flight)
    with LogReader(crop_flight) as r:
        crops = {m.log_time_ns: m.image for m in r.messages(topics=["/perception/input"])}
        previews = [m.image for m in r.messages(topics=["/camera/image"])]
    inputs = [s["input"] for _, s in steps]
    assert all(i is not None for i in inputs)
    full = [i for i in inputs if (i["x1"] - i["x0"], i["y1"] - i["y0"]) == (1000, 1000)]
    # tracking: the detector read a region of interest, searched the whole frame at most a few
    # times (the first frame)
    assert 1 <= len(full) <= 3 and len(inputs) - len(full) > 0.9 * len(inputs)
    for i in inputs:
        img = crops[i["log_time_ns"]]
        assert img is not None and img.shape == (i["y1"] - i["y0"], i["x1"] - i["x0"])
    # the preview: decimated (2 Hz of 20 Hz) and half size, JPEG
    assert 0.08 * len(steps) <= len(previews) <= 0.12 * len(steps) + 1
    assert {p.shape for p in previews} == {(500, 500)}

    res = replay(crop_flight, tmp_path / "replay.mcap")
    s = res.summary()
    assert s["perception"] == "crop" and s["perception_outside_crop"] == 0
    assert s["frames_missing"] == 0 and s["input_encoding"] == "png"
    assert s["commands_compared"] == len(steps) and s["identical"], s


def test_replay_in_process_equals_the_worker(crop_flight: Path) -> None:
    a = replay(crop_flight, None, workers=0).summary()
    assert a["identical"] and a["commands_compared"] > 0


def test_from_detections_reproduces_every_command(crop_flight: Path, tmp_path: Path) -> None:
    res = replay(crop_flight, tmp_path / "replay.mcap", from_detections=True)
    s = res.summary()
    assert s["perception"] == "detections"
    assert s["commands_compared"] == len(_steps(crop_flight)) and s["identical"], s
    # and a changed controller setting does change them (the comparison can fail): a hover
    # thrust 10 % off, without PX4's own thrust to learn it from before OFFBOARD (with it, the
    # configured value hardly matters any more: docs/reference/estimator.md)
    changed = replay(crop_flight, None, from_detections=True,
                     overrides=["control.estimator.autopilot_thrust=false",
                                "control.hover_thrust=0.55"]).summary()
    assert not changed["identical"] and changed["max_thrust_diff"] > 1e-3


def test_without_out_the_replay_compares_and_writes_nothing(crop_flight: Path,
                                                            tmp_path: Path) -> None:
    """No ``--out``: every command still compared and the verdict printed, no log, no report
    (the replay's log is written only when asked for: ``--out``)."""
    p = subprocess.run([sys.executable, "-m", "companion", "replay", str(crop_flight),
                        "--from-detections"], capture_output=True, text=True, timeout=300,
                       cwd=tmp_path)
    assert p.returncode == 0, p.stdout + p.stderr
    n = len(_steps(crop_flight))
    assert f"PASS  commands reproduced: {n} of {n} identical" in p.stdout
    assert "report:" not in p.stdout
    assert list(tmp_path.iterdir()) == []


def test_sweep_gives_results_side_by_side(crop_flight: Path, tmp_path: Path) -> None:
    """Two keys swept: every combination. The hover thrust configured 10 % off changes the
    commands much more without PX4's thrust learnt before OFFBOARD than with it."""
    out = tmp_path / "sweep"
    ht = ["control.hover_thrust=0.5", "control.hover_thrust=0.55"]
    ap = ["control.estimator.autopilot_thrust=true", "control.estimator.autopilot_thrust=false"]
    p = subprocess.run(
        [sys.executable, "-m", "companion", "replay", str(crop_flight), "--from-detections",
         "--no-plots", "--out", str(out), *[a for o in ht + ap for a in ("--set", o)]],
        capture_output=True, text=True, timeout=600)
    assert p.returncode == 0, p.stdout + p.stderr
    variants = json.loads((out / "sweep.json").read_text())["variants"]
    assert [v["overrides"] for v in variants] == [[h, a] for h in ht for a in ap]
    recorded, learnt_off, wrong_learnt, wrong_off = variants
    assert recorded["identical"] and not wrong_off["identical"]
    assert wrong_off["max_thrust_diff"] > 1e-3
    assert wrong_off["max_thrust_diff"] > 5.0 * wrong_learnt["max_thrust_diff"]
    assert wrong_off["thrust_max"] > learnt_off["thrust_max"]
    head = next(ln for ln in p.stdout.splitlines() if "variant 1" in ln)
    assert "variant 4" in head
    row = next(ln for ln in p.stdout.splitlines() if ln.startswith("commands changed"))
    n = recorded["commands_compared"]
    assert f"0/{n}" in row and f"{wrong_off['commands_changed']}/{n}" in row
    assert wrong_off["commands_changed"] > 0
    for i in range(1, 5):
        assert (out / f"variant-{i}" / "report.json").exists()


def test_lockstep_log_times_are_simulated_time(crop_flight: Path) -> None:
    steps = _steps(crop_flight)
    t = np.array([lt for lt, _ in steps], dtype=np.int64)
    # stamped with the frames' capture times on the autopilot clock (boot offset 0 in the
    # paper config): 50 ms apart, not the wall-clock pace of the lockstep run
    assert [lt for lt, _ in steps] == [s["frame_t_us"] * 1000 for _, s in steps]
    assert np.median(np.diff(t)) == 50_000_000
    p = subprocess.run([sys.executable, "-m", "companion", "log", "info", str(crop_flight)],
                       capture_output=True, text=True, timeout=120)
    assert p.returncode == 0, p.stderr
    dur = float(next(ln for ln in p.stdout.splitlines() if ln.startswith("duration:")).split()[1])
    assert dur == pytest.approx(DURATION_S, abs=0.3)
    rate = float(next(ln for ln in p.stdout.splitlines() if "/perception/input" in ln).split()[2])
    assert rate == pytest.approx(20.0, rel=0.05)
    with open(crop_flight, "rb") as f:  # publish time = log time
        assert all(m.publish_time == m.log_time for _, _, m in make_reader(f).iter_messages())


def to_old_format(src: Path, dst: Path) -> None:
    """Rewrite a log that has every frame whole on /perception/input the way logs were written
    before crops: frames on /camera/image, step records without ``input``, everything stamped
    with its receipt time (steps and frames: the frame's ``t_rx_ns``)."""
    with open(src, "rb") as f:
        msgs = list(make_reader(f).iter_messages())
    frame_rx: dict[int, int] = {}
    for _, ch, m in msgs:
        if ch.topic == "/control/step":
            rec = json.loads(m.data)
            frame_rx[rec["input"]["log_time_ns"]] = rec["t_rx_ns"]
    out = []
    for order, (schema, ch, m) in enumerate(msgs):
        topic, data, t = ch.topic, m.data, m.log_time
        if topic == "/camera/image":
            continue  # the preview did not exist
        if topic == "/perception/input":
            topic, t = "/camera/image", frame_rx[m.log_time]
        elif topic == "/control/step":
            rec = json.loads(data)
            del rec["input"]
            data, t = json.dumps(rec).encode(), rec["t_rx_ns"]
        elif topic.startswith("/mavlink/in/"):
            t = json.loads(data)["t_rx_ns"]
        out.append((t, order, schema, topic, ch.message_encoding, data))
    out.sort(key=lambda x: (x[0], x[1]))
    with open(dst, "wb") as f:
        w = Writer(f)
        w.start()
        ids: dict[str, int] = {}
        schemas: dict[str, int] = {}
        for t, _, schema, topic, enc, data in out:
            if topic not in ids:
                if schema.name not in schemas:
                    schemas[schema.name] = w.register_schema(schema.name, schema.encoding,
                                                             schema.data)
                ids[topic] = w.register_channel(topic, enc, schemas[schema.name])
            w.add_message(ids[topic], t, data, t)
        w.finish()


def test_full_frames_and_an_old_format_log_replay_exactly(full_flight: Path,
                                                          tmp_path: Path) -> None:
    steps = _steps(full_flight)
    assert all((s["input"]["x1"], s["input"]["y1"]) == (1000, 1000) for _, s in steps)
    s = replay(full_flight, None).summary()
    assert s["perception"] == "crop" and s["identical"], s
    old = tmp_path / "old.mcap"
    to_old_format(full_flight, old)
    with LogReader(old) as r:
        topics = {c.topic for c in r.channels}
    assert "/perception/input" not in topics and "/camera/image" in topics
    s = replay(old, tmp_path / "replay.mcap").summary()
    assert s["perception"] == "frames" and s["frames_missing"] == 0
    assert s["commands_compared"] == len(steps) and s["identical"], s


def test_a_log_without_perception_input_names_the_way_out(tmp_path: Path) -> None:
    out = tmp_path / "none"
    run_demo(DEFAULT_CONFIG, "paper", 2.0, out, ['logging.perception_input="none"'], [],
             plots=False)
    with pytest.raises(ReplayError, match="--from-detections"):
        replay(out / "flight.mcap", None)
    s = replay(out / "flight.mcap", None, from_detections=True).summary()
    assert s["identical"], s


def test_a_jpeg_logged_flight_says_its_replay_is_approximate(tmp_path: Path) -> None:
    out = tmp_path / "jpeg"
    run_demo(DEFAULT_CONFIG, "paper", 2.0, out, ['logging.image_encoding="jpeg"'], [],
             plots=False)
    s = replay(out / "flight.mcap", None).summary()
    assert s["input_encoding"] == "jpeg" and s["commands_compared"] > 0
    # lossy crops: close to the flight, not bit-exact by construction
    assert s["max_quat_diff"] < 1e-2 and s["max_thrust_diff"] < 1e-2, s
