"""The log's channel names a replay reads, without the recording module (which loads the MCAP
writer and its dependencies: ~0.05-0.2 s of a replay's start-up that writes no log). The
recording (:mod:`companion.control.recording`) writes the same names
(tests/companion/test_replay_step_input.py checks that they agree)."""

from __future__ import annotations

TOPIC_INPUT = "/perception/input"
TOPIC_FRAME = "/camera/image"  # an old log's full frames (the preview channel today)
TOPIC_STEP = "/control/step"
TOPIC_TRUTH = "/truth"

__all__ = ["TOPIC_FRAME", "TOPIC_INPUT", "TOPIC_STEP", "TOPIC_TRUTH"]
