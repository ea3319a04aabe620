"""What a replay reads of each step record, and what of it crosses between its two processes."""

from __future__ import annotations

import json

from companion.replay_inputs import _step_input

INPUT = {"log_time_ns": 5050000000, "x0": 334, "y0": 313, "x1": 623, "y1": 662,
         "width": 1000, "height": 1000}


def _record(**extra: object) -> dict[str, object]:
    # what the runtime writes: the step's own record, then the runtime's keys, "input" last
    rec: dict[str, object] = {"t_s": 5.05, "perception": {"status": "ok", "reason": "",
                                                        "corners_px": [[1.0, 2.0]] * 4},
                              "notes": ['a note with "input": {"x0": 1} in it'],
                              "estimator": {"input": [0.1, 0.2]}, "rx_count": 452}
    rec.update(extra)
    return rec


def test_the_shortcut_gives_what_parsing_the_whole_record_gives() -> None:
    raw = json.dumps(_record(input=INPUT), separators=(",", ":")).encode()
    assert _step_input(raw) == json.loads(raw)["input"] == INPUT
    spaced = json.dumps(_record(input=INPUT)).encode()  # other separators
    assert _step_input(spaced) == INPUT


def test_records_the_shortcut_cannot_read_fall_back_to_the_whole_record() -> None:
    # "input" not last: the whole record is parsed
    rec = {"input": INPUT, **_record()}
    assert _step_input(json.dumps(rec).encode()) == INPUT
    # a record without an input, or with an input that is not a crop's
    assert _step_input(json.dumps(_record()).encode()) is None
    assert _step_input(json.dumps(_record(input=None)).encode()) is None
    partial = {k: v for k, v in INPUT.items() if k != "x1"}
    assert _step_input(json.dumps(_record(input=partial)).encode()) == partial
    # not JSON at all
    assert _step_input(b'{"t_s": 1, "input": {"x0": ') is None
    assert _step_input(b"\xff\xfe") is None


def test_the_replay_reads_the_channels_the_recording_writes() -> None:
    from companion.control import recording, topics

    for name in topics.__all__:
        assert getattr(topics, name) == getattr(recording, name), name


def test_a_step_crosses_between_the_processes_unchanged() -> None:
    import pickle

    from companion.replay_inputs import Perceived
    from companion.replay_stream import StepInput, _unwire, _wire

    p = Perceived("ok", "", ((1.5, 2.0), (3.0, 4.25), (5.0, 6.0), (7.0, 8.0)), 0.75,
                  False, True)
    s = StepInput({"rx_count": 3, "setpoint": {"q_wxyz": [1.0, 0.0, 0.0, 0.0],
                                               "thrust": 0.5}},
                  (("ATTITUDE", {"roll": 0.1}, 1, 2.5),), p, ((7, b"{}"),),
                  (tuple(float(i) for i in range(24)), 0.75), 4, 1, 5.05)
    back = _unwire(pickle.loads(pickle.dumps(_wire(s))))
    assert back == s and back.perceived == p
    none = s._replace(perceived=None, measured=None)
    assert _unwire(pickle.loads(pickle.dumps(_wire(none)))) == none


def test_the_corners_sent_give_the_arrays_perception_gives() -> None:
    import numpy as np

    from companion.config import load_config
    from companion.perception import Perception
    from companion.replay_inputs import Perceived
    from companion.replay_stream import StepInput, _measured, perception_result

    cfg = load_config()
    metric = Perception(cfg.camera, cfg.target, perception=cfg.perception)
    p = Perceived("ok", "", ((512.3, 401.7), (610.25, 405.5), (606.0, 470.125),
                             (509.0, 466.0)), 0.9)
    want = p.result(metric)
    got = perception_result(StepInput({}, (), p, measured=_measured(p, metric)), p, metric)
    assert want is not None and got is not None and got.status == "ok"
    assert got.quality == want.quality
    for a, b in ((got.corners_px, want.corners_px),
                 (got.corners_undistorted_px, want.corners_undistorted_px),
                 (got.points_m, want.points_m)):
        assert a is not None and b is not None
        assert a.dtype == b.dtype and a.shape == b.shape == (4, 2)
        assert np.array_equal(a, b)  # bit for bit: the replay stays exact
        assert a.flags.writeable == b.flags.writeable
