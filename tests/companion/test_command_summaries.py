"""What ``companion replay`` prints at its end: rounded, with units and a verdict (issue 25)."""

from __future__ import annotations

from typing import Any

from companion.report.text import replay_summary


def _summary(**over: Any) -> dict[str, Any]:
    s: dict[str, Any] = {
        "steps": 1197, "commands_compared": 1197, "commands_changed": 0,
        "max_quat_diff": 0.0, "max_thrust_diff": 0.0, "identical": True, "tolerance": 1e-6,
        "first_difference_t_s": None, "perception": "crop", "perception_outside_crop": 0,
        "input_encoding": "png", "solver_modes": {"optimal": 1190, "recovery": 7},
        "solve_ms_median": 3.0245570000033695, "solve_ms_p95": 20.680754400007135,
        "wall_time_s": 136.0987, "cpu_time_s": 17.41234, "cpu_ms_per_step": 14.5466,
        "speed_vs_real_time": 0.44051, "load_1min": 20.8125, "log": {"truncated": False},
    }
    s.update(over)
    return s


def test_replay_summary_is_rounded_with_a_verdict() -> None:
    text = "\n".join(replay_summary(_summary()))
    assert "PASS  commands reproduced: 1197 of 1197 identical" in text and "tolerance 1e-6)" in text
    assert "1190 optimal, 7 recovery" in text and "median 3.0 ms, p95 20.7 ms" in text
    for raw in ("{", "[", "3.02455", "14.5466", "136.0987"):
        assert raw not in text, raw
    bad = "\n".join(replay_summary(_summary(identical=False, commands_changed=3,
                                            max_quat_diff=0.0123456, first_difference_t_s=4.25)))
    assert "MISS  commands reproduced: 1194 of 1197 identical (max |dq| 0.0123" in bad
    assert "first difference at t = 4.25 s" in bad


def test_replay_summary_says_the_start_up_beside_the_rate() -> None:
    text = "\n".join(replay_summary(_summary(startup_s=0.6412)))
    assert "(0.4x real time, start-up 0.6 s included)" in text
    assert "(0.4x real time)" in "\n".join(replay_summary(_summary()))  # one from before
