"""The perception stage of a replay reads only the ``input`` entry of each step record."""

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
