"""Offline replay: a recorded flight through the same perception and controller code.

Frames (``/camera/image``) and accepted MAVLink messages (``/mavlink/in/*``, re-decoded from
their raw bytes, so the store sees exactly what the live process saw) are fed in the order the
live process consumed them: before step k, exactly the ``rx_count`` messages that had been
ingested live. Every recomputed command is compared with the recorded one.
"""

from __future__ import annotations

import base64
import json
import logging
import math
import sys
from collections import deque
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from pymavlink.dialects.v20 import common as mavlink2

from companion import CompanionError
from companion.config import Config, config_from_dict, load_config, with_overrides
from companion.control.runtime import (
    TOPIC_FRAME,
    TOPIC_STEP,
    TOPIC_TRUTH,
    TimeBase,
    new_pipeline,
    new_store,
)
from companion.log import schemas as sch
from companion.log.reader import LogMessage, LogReader, image_from_raw
from companion.log.writer import McapLogger

log = logging.getLogger(__name__)

TOPIC_SAT = "/mavlink/out/SET_ATTITUDE_TARGET"
REQUIRED = (TOPIC_FRAME, TOPIC_STEP)


class ReplayError(CompanionError):
    """The log cannot be replayed (missing channels, no config); the message says which."""


@dataclass
class ReplayResult:
    steps: int = 0
    commands_compared: int = 0
    max_quat_diff: float = 0.0
    max_thrust_diff: float = 0.0
    mode_mismatches: int = 0
    first_difference_t_s: float | None = None
    frames_missing: int = 0
    recorded_wire_commands: int = 0
    recovery: dict[str, Any] = field(default_factory=dict)
    config_source: str = ""

    def summary(self, tol: float = 1e-6) -> dict[str, Any]:
        return {
            "steps": self.steps,
            "commands_compared": self.commands_compared,
            "max_quat_diff": self.max_quat_diff,
            "max_thrust_diff": self.max_thrust_diff,
            "identical": self.commands_compared > 0 and self.max_quat_diff <= tol
            and self.max_thrust_diff <= tol and self.mode_mismatches == 0,
            "tolerance": tol,
            "mode_mismatches": self.mode_mismatches,
            "first_difference_t_s": self.first_difference_t_s,
            "frames_missing": self.frames_missing,
            "recorded_wire_commands": self.recorded_wire_commands,
            "config": self.config_source,
            "log": self.recovery,
        }


def replay_config(reader: LogReader, config: Path | None, overrides: list[str]) -> Config:
    """``--config`` if given, else the config recorded on ``/config``; overrides applied."""
    if config is not None:
        return load_config(config, overrides)
    for m in reader.messages(topics=["/config"]):
        if m.data and isinstance(m.data.get("config"), dict):
            return config_from_dict(with_overrides(m.data["config"], overrides),
                                    source=f"{m.data.get('source', '')} (recorded)")
    raise ReplayError("the log has no /config channel: pass --config FILE")


def replay(log_path: Path, out_path: Path | None, config: Path | None = None,
           overrides: list[str] | None = None,
           progress: Callable[[int, int], None] | None = None,
           timer: Callable[[], float] | None = None) -> ReplayResult:
    """Replay ``log_path``; ``timer`` (e.g. time.perf_counter) records stage timings in the
    recomputed step records (measurement only: results are the same without it)."""
    with LogReader(log_path, verify=False) as reader:  # one pass: chunks are CRC-checked as read
        return _replay(reader, log_path, out_path, config, overrides, progress, timer)


def _replay(reader: LogReader, log_path: Path, out_path: Path | None, config: Path | None,
            overrides: list[str] | None,
            progress: Callable[[int, int], None] | None,
            timer: Callable[[], float] | None) -> ReplayResult:
    counts = {c.topic: c.count for c in reader.channels}
    missing = [t for t in REQUIRED if t not in counts]
    if missing:
        raise ReplayError(f"{log_path}: missing channel(s) {', '.join(missing)}: cannot replay "
                          f"(present: {', '.join(sorted(counts)) or 'none'})")
    cfg = replay_config(reader, config, list(overrides or []))
    res = ReplayResult(config_source=cfg.source)
    rec = reader.recovery
    res.recovery = {"truncated": rec.truncated, "messages_recovered": rec.messages,
                    "salvaged": rec.salvaged, "bytes_used": rec.bytes_used,
                    "bytes_total": rec.bytes_total}
    if rec.truncated:
        log.warning("%s is cut short: replaying the %d messages recovered up to %.1f s",
                    log_path, rec.messages,
                    ((rec.last_log_time_ns or 0) - (rec.first_log_time_ns or 0)) * 1e-9)
    pipeline = new_pipeline(cfg, timer=timer)
    store = new_store(cfg)
    tb = TimeBase(cfg.control.time_source, cfg.safety.max_frame_age_s)
    parser = mavlink2.MAVLink(None)
    parser.robust_parsing = True
    total_steps = counts.get(TOPIC_STEP, 0)

    rx_seen = 0
    frames: dict[int, Future[np.ndarray | None]] = {}
    recorded_sat: list[dict[str, Any]] = []
    pending_steps: list[dict[str, Any]] = []
    mav_in: deque[LogMessage] = deque()
    writer = None
    if out_path is not None:
        writer = McapLogger(out_path, flush_interval_s=5.0, queue_size=1 << 16)
        writer.open()
        writer.log_config(0, "", dict(cfg.raw), cfg.source)

    def ingest(m: LogMessage) -> None:
        nonlocal rx_seen
        raw = base64.b64decode((m.data or {}).get("raw_b64", ""))
        msg = _decode(parser, raw)
        if msg is None:
            return
        fields = msg.to_dict()
        name = msg.get_type()
        t_s = tb.message_s(name, fields, int((m.data or {}).get("t_rx_ns", m.log_time_ns)))
        store.ingest(name, fields, t_s, msg.get_srcSystem())
        rx_seen += 1

    def run_step(rec_step: dict[str, Any]) -> None:
        want = int(rec_step.get("rx_count", 0))
        while rx_seen < want and mav_in:
            ingest(mav_in.popleft())
        fut = frames.pop(int(rec_step["t_rx_ns"]), None)
        img = fut.result() if fut is not None else None
        if img is None:
            res.frames_missing += 1
        t_s = tb.frame_s(int(rec_step["frame_t_us"]), int(rec_step["t_rx_ns"]))
        pipeline.force_solver_failure = bool(rec_step.get("fault_injected", False))
        out = pipeline.step(img, t_s, store)
        res.steps += 1
        new = out.to_record()
        new.update({k: rec_step.get(k) for k in ("frame_seq", "frame_t_us", "t_rx_ns",
                                                 "rx_count", "offboard")})
        if writer is not None:
            writer.log(TOPIC_STEP, int(rec_step["t_rx_ns"]), new, schema=sch.CONTROLLER_STEP)
        _compare(res, rec_step, out, t_s)
        if progress is not None:
            progress(res.steps, total_steps)

    def ready(step: dict[str, Any]) -> bool:
        return rx_seen + len(mav_in) >= int(step.get("rx_count", 0))

    # Frames are decoded (PNG: ~6.6 ms at 1000 x 1000; raw: a copy) in worker threads a few
    # frames ahead of the step that uses them: cv2.imdecode releases the GIL, so decoding
    # overlaps the pipeline. Same frames, same order, same results.
    pool = ThreadPoolExecutor(max_workers=2, thread_name_prefix="replay-decode")
    try:
        # A step record is stamped with its frame's receipt time, but the messages it saw may
        # have arrived after that frame: run a step once all of its ``rx_count`` messages have
        # been read (log-time order preserves their order of arrival).
        for m in reader.messages(topics=None, decode=False):
            if m.topic == TOPIC_FRAME:
                frames[m.log_time_ns] = pool.submit(image_from_raw, m.schema_name,
                                                     m.message_encoding, m.raw)
                continue
            data = _json(m.raw)
            if m.topic.startswith("/mavlink/in/"):
                mav_in.append(LogMessage(m.topic, m.log_time_ns, m.publish_time_ns,
                                         m.schema_name, data, None, m.raw))
            elif m.topic == TOPIC_SAT and data:
                recorded_sat.append(data.get("fields", {}))
            elif m.topic == TOPIC_STEP and data:
                pending_steps.append(data)
            elif m.topic == TOPIC_TRUTH and writer is not None and data:
                writer.log(TOPIC_TRUTH, m.log_time_ns, data, schema=sch.JSON)
            while pending_steps and ready(pending_steps[0]) and len(frames) > LOOKAHEAD:
                run_step(pending_steps.pop(0))
        while pending_steps:  # end of the log (or a log cut short): run what is left
            run_step(pending_steps.pop(0))
    finally:
        pool.shutdown(wait=True, cancel_futures=True)
        if writer is not None:
            writer.close()
    res.recovery["corrupt_chunks"] = reader.recovery.corrupt_chunks  # found while reading
    res.recorded_wire_commands = len(recorded_sat)
    return res


LOOKAHEAD = 3  # frames decoded ahead of the step that uses them


def _json(raw: bytes) -> dict[str, Any] | None:
    try:
        out = json.loads(raw)
    except ValueError:
        return None
    return out if isinstance(out, dict) else None


def _decode(parser: Any, raw: bytes) -> Any:
    parser.buf = bytearray()
    parser.buf_index = 0
    try:
        msgs = parser.parse_buffer(raw) or []
    except Exception:
        return None
    for msg in msgs:
        if msg.get_type() not in ("BAD_DATA",) and not msg.get_type().startswith("UNKNOWN"):
            return msg
    return None


def _compare(res: ReplayResult, rec_step: dict[str, Any], out: Any, t_s: float) -> None:
    rec_sp = rec_step.get("setpoint")
    new_sp = out.setpoint
    if rec_sp is None and new_sp is None:
        return
    res.commands_compared += 1
    if rec_sp is None or new_sp is None:
        res.max_quat_diff = math.inf
        res.max_thrust_diff = math.inf
        res.first_difference_t_s = res.first_difference_t_s or t_s
        return
    q_rec = np.asarray(rec_sp["q_wxyz"], dtype=float)
    q_new = np.asarray(new_sp.q_wxyz, dtype=float)
    dq = float(min(np.max(np.abs(q_rec - q_new)), np.max(np.abs(q_rec + q_new))))
    dt = abs(float(rec_sp["thrust"]) - float(new_sp.thrust_norm))
    if (dq > 1e-6 or dt > 1e-6) and res.first_difference_t_s is None:
        res.first_difference_t_s = t_s
    res.max_quat_diff = max(res.max_quat_diff, dq)
    res.max_thrust_diff = max(res.max_thrust_diff, dt)
    rec_mode = (rec_step.get("rmpc") or {}).get("mode")
    new_mode = out.rmpc.mode if out.rmpc is not None else None
    if rec_mode != new_mode:
        res.mode_mismatches += 1


def terminal_progress() -> Callable[[int, int], None] | None:
    """A one-line progress bar on stderr when it is a terminal, else None (quiet)."""
    if not sys.stderr.isatty():
        return None

    def show(done: int, total: int) -> None:
        if done % 20 and done != total:
            return
        frac = done / total if total else 1.0
        bar = "#" * int(30 * frac)
        sys.stderr.write(f"\rreplay [{bar:<30}] {done}/{total}")
        if done >= total:
            sys.stderr.write("\n")
        sys.stderr.flush()

    return show

