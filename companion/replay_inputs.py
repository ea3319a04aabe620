"""What perception saw in a recorded flight, step by step, for :mod:`companion.replay`.

Perception depends only on the frames (and its own earlier results), never on the controller,
so a replay runs it as a separate stage: :func:`perceive_log` reads a log's perception inputs
and ``/control/step`` records and yields one :class:`Perceived` per step record, in log order;
:mod:`companion.replay_stream` runs that in a child process (with the rest of the log's
reading) so perception and the controller use two cores. Inputs, newest format first:

- ``/perception/input`` (``logging.perception_input = "crop"`` or ``"full"``): what the detector
  read, with its place in the frame in the step record's ``input`` entry. The crop is pasted
  into an empty frame: the detector reads only that region again, so the result is the live one
  (a replay whose perception wants pixels outside the crop counts them in ``outside_crop``);
- ``/camera/image`` of logs written before crops (every frame whole, keyed by the step's
  ``t_rx_ns``);
- the step records' own detections (:func:`perceived_from_record`, ``--from-detections``).
"""

from __future__ import annotations

import json
import logging
from collections import deque
from collections.abc import Iterator, Mapping
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from companion import CompanionError
from companion.config import Config
from companion.control.topics import TOPIC_FRAME, TOPIC_INPUT, TOPIC_STEP
from companion.log.encode import decode_json_object
from companion.log.reader import LogReader, image_from_raw
from companion.perception import Perception, PerceptionResult

log = logging.getLogger(__name__)

LOOKAHEAD = 3  # frames decoded ahead of the step that uses them


class ReplayInputError(CompanionError):
    """A log's perception inputs cannot be replayed; the message says why."""


@dataclass(frozen=True)
class Perceived:
    """One step's perception, as plain values (cheap to send between processes).

    ``missing``: the step's frame is not in the log (the step runs as "no image").
    ``corners_px``: raw pixel corners (4 x (col, row)) when the target was detected.
    ``outside_crop``: perception read pixels the log did not keep (replay not exact)."""

    status: str
    reason: str
    corners_px: tuple[tuple[float, float], ...] | None
    quality: float = 0.0
    missing: bool = False
    outside_crop: bool = False

    def result(self, perception: Perception) -> PerceptionResult | None:
        """The pipeline's input for this step (None: no image), through the same
        undistortion and metric conversion as a live detection."""
        if self.missing:
            return None
        if self.corners_px is not None:
            return perception.measured(np.array(self.corners_px, dtype=np.float64),
                                       self.quality)
        return PerceptionResult(self.status, self.reason)  # type: ignore[arg-type]


def input_mode(channels: Mapping[str, int], first_step: Mapping[str, Any] | None) -> str:
    """``"crop"`` (``/perception/input``), ``"frames"`` (an old log's full frames) or
    ``"none"``; ``first_step`` is a step record of the log (new logs carry an ``input``)."""
    if channels.get(TOPIC_INPUT):
        return "crop"
    if channels.get(TOPIC_FRAME) and (first_step is None or "input" not in first_step):
        return "frames"
    return "none"


def perceived_from_record(rec: Mapping[str, Any]) -> Perceived:
    """A step's perception from its own record (``--from-detections``): the corners it
    detected (recorded only when detected), else its status and reason."""
    p = rec.get("perception") or {}
    corners = p.get("corners_px")
    if corners is not None:
        return Perceived("ok", "", tuple((float(c), float(r)) for c, r in corners))
    status, reason = str(p.get("status", "lost")), str(p.get("reason", ""))
    return Perceived(status, reason, None, missing=reason == "no image")


_DECODER = json.JSONDecoder()
_INPUT_KEY = '"input":'


def _step_input(raw: bytes) -> dict[str, Any] | None:
    """The ``input`` entry of a step record, without parsing the rest of it (a step record
    is ~7 kB of JSON; perception needs only this entry): the runtime writes it as the record's
    last key. Falls back to the whole record when the shortcut does not give a dict with the
    crop's keys (the same value either way). The log's chunks are CRC-checked as they are
    read, so a record is either what the runtime wrote (valid JSON) or not read at all."""
    try:
        text = raw.decode()
        at = text.rfind(_INPUT_KEY)
        if at > 0 and text[at - 1] in ",{" and text.startswith("{"):
            value, end = _DECODER.raw_decode(text, at + len(_INPUT_KEY))
            if (isinstance(value, dict) and text[end:].strip() == "}"
                    and {"log_time_ns", "x0", "y0", "x1", "y1", "width", "height"} <= value.keys()):
                return value
    except (UnicodeDecodeError, ValueError):
        pass
    rec = decode_json_object(raw)
    inp = rec.get("input") if rec is not None else None
    return inp if isinstance(inp, dict) else None


class _Canvas:
    """Full frames to paste crops into; only the last crop's area is ever non-zero."""

    def __init__(self) -> None:
        self._frames: dict[tuple[int, ...], np.ndarray] = {}
        self._last: dict[tuple[int, ...], tuple[int, int, int, int]] = {}

    def paste(self, crop: np.ndarray, x0: int, y0: int, width: int, height: int) -> np.ndarray:
        shape = (height, width, *crop.shape[2:])
        frame = self._frames.get(shape)
        if frame is None:
            frame = self._frames[shape] = np.zeros(shape, np.uint8)
        else:
            a0, b0, a1, b1 = self._last[shape]
            frame[b0:b1, a0:a1] = 0
        h, w = crop.shape[:2]
        if x0 < 0 or y0 < 0 or x0 + w > width or y0 + h > height:
            raise ReplayInputError(f"crop at ({x0}, {y0}) of {w}x{h} px is outside the "
                                   f"{width}x{height} frame")
        frame[y0:y0 + h, x0:x0 + w] = crop
        self._last[shape] = (x0, y0, x0 + w, y0 + h)
        return frame


def perceive_log(path: Path, cfg: Config) -> Iterator[Perceived]:
    """Perception of every step record of the log at ``path``, in log order (see module)."""
    with LogReader(path, verify=False) as reader:
        counts = {c.topic: c.count for c in reader.channels}
        steps = reader.messages(topics=[TOPIC_STEP], decode=False)
        first = next((decode_json_object(m.raw) for m in steps), None)
        mode = input_mode(counts, first)
        if mode == "none":
            raise ReplayInputError(
                f"{path}: no perception input logged (logging.perception_input = \"none\"): "
                "replay it with --from-detections")
        topic = TOPIC_INPUT if mode == "crop" else TOPIC_FRAME
        perception = Perception(cfg.camera, cfg.target, perception=cfg.perception)
        canvas = _Canvas()
        frames: dict[int, deque[Future[np.ndarray | None]]] = {}
        pending: deque[tuple[dict[str, Any], Future[np.ndarray | None] | None]] = deque()
        pool = ThreadPoolExecutor(max_workers=2, thread_name_prefix="replay-decode")

        def run(rec: dict[str, Any], fut: Future[np.ndarray | None] | None) -> Perceived:
            img = fut.result() if fut is not None else None
            if img is None:
                return Perceived("lost", "no image", None, missing=True)
            region = None
            if mode == "crop":
                inp = rec["input"]
                region = (int(inp["x0"]), int(inp["y0"]), int(inp["x1"]), int(inp["y1"]))
                img = canvas.paste(img, region[0], region[1], int(inp["width"]),
                                   int(inp["height"]))
            pr = perception.process(img)
            outside = False
            if region is not None and perception.last_region is not None:
                a0, b0, a1, b1 = perception.last_region
                outside = not (a0 >= region[0] and b0 >= region[1] and a1 <= region[2]
                               and b1 <= region[3])
            corners = None
            if pr.status == "ok" and pr.corners_px is not None:
                corners = tuple((float(c), float(r)) for c, r in pr.corners_px)
            return Perceived(pr.status, pr.reason, corners, pr.quality, False, outside)

        try:
            for m in reader.messages(topics=[topic, TOPIC_STEP], decode=False):
                if m.topic == topic:
                    frames.setdefault(m.log_time_ns, deque()).append(
                        pool.submit(image_from_raw, m.schema_name, m.message_encoding, m.raw))
                    continue
                if mode == "crop":
                    inp = _step_input(m.raw)
                    if inp is None and decode_json_object(m.raw) is None:
                        continue
                    rec: dict[str, Any] = {"input": inp}
                    key = int(inp["log_time_ns"]) if inp is not None else None
                else:
                    whole = decode_json_object(m.raw)
                    if whole is None:
                        continue
                    rec = whole
                    key = int(rec.get("t_rx_ns", -1))
                queue = frames.get(key) if key is not None else None
                fut = queue.popleft() if queue else None
                if queue is not None and not queue:
                    del frames[key]  # type: ignore[arg-type]
                if key is not None:  # frames of steps that were never recorded: forget
                    for k in [k for k in frames if k < key]:
                        del frames[k]
                pending.append((rec, fut))
                while len(pending) > LOOKAHEAD:
                    yield run(*pending.popleft())
            while pending:
                yield run(*pending.popleft())
        finally:
            pool.shutdown(wait=True, cancel_futures=True)
