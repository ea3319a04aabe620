"""A recorded flight's step inputs, read and decoded in the order a replay runs them.

:mod:`companion.replay` runs the controller; everything it needs from the log comes from here,
one :class:`StepInput` per step record: the MAVLink messages the live process had ingested
before that step (``rx_count``; decoded, only those the store or the time base reads), the
step record's entries the replay reads, the step's perception (:mod:`companion.replay_inputs`)
and, when the replay writes a log, the ground truth logged meanwhile. Reading, decompressing
and decoding the log (~0.3 ms a step) then run beside the controller: in a child process by
default (:class:`StreamWorker`), so that the replay's process spends its time on the controller.
"""

from __future__ import annotations

import base64
import multiprocessing as mp
import traceback
from collections import deque
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from companion import CompanionError
from companion.config import Config, config_from_dict
from companion.control.telemetry import TelemetryStore
from companion.control.timebase import STAMPED_MESSAGES
from companion.control.topics import TOPIC_STEP, TOPIC_TRUTH
from companion.log.encode import decode_json_object
from companion.log.reader import LogReader
from companion.perception import Perception, PerceptionResult
from companion.replay_inputs import (
    Perceived,
    ReplayInputError,
    perceive_log,
    perceived_from_record,
)

TOPIC_SAT = "/mavlink/out/SET_ATTITUDE_TARGET"
_MAV_IN = "/mavlink/in/"
#: the step record's entries a replay reads (the rest, ~6 kB of JSON a step, stays here)
STEP_KEYS = ("rx_count", "frame_t_us", "t_rx_ns", "fault_injected", "t_now_s", "in_control",
             "actuation_delay_s", "setpoint", "frame_seq", "offboard")
#: the messages the replay's store and time base read; the others are counted only
USED_MESSAGES = TelemetryStore.MESSAGES | STAMPED_MESSAGES
Corners = tuple[tuple[float, float], ...]
_BATCH = 64  # steps per message from the worker process
_PIPE_BYTES = 1 << 20  # the pipe to the replay (see _grow_pipe)
_FIRST_BATCH = 2  # ... but the first message, which the replay's first step waits for


class StepInput(NamedTuple):
    """One step's inputs. ``record``: the step record's :data:`STEP_KEYS` and its ``rmpc``
    mode (None: the end of the log, carrying the ground truth logged after the last step);
    ``messages``: ``(name, fields, sysid, t_rx_ns)`` to ingest first, in order;
    ``perceived``: the step's perception (None when the replay supplies it);
    ``truth``: ``(log time ns, JSON bytes)`` of ``/truth`` read since the step before;
    ``measured``: when ``perceived`` has corners, its result's raw, undistorted and metric
    corners (``Perceived.result``: computed here, beside the controller's process);
    ``sat_count``, ``corrupt_chunks``: with the end marker, the SET_ATTITUDE_TARGET messages
    the flight sent and the damaged chunks reading skipped (CRC-checked as read)."""

    record: dict[str, Any] | None
    messages: tuple[tuple[str, dict[str, Any], int, int], ...]
    perceived: Perceived | None
    truth: tuple[tuple[int, bytes], ...] = ()
    measured: tuple[Corners, Corners, Corners, float] | None = None
    sat_count: int = 0
    corrupt_chunks: int = 0


def _compact(rec: Mapping[str, Any]) -> dict[str, Any]:
    out = {k: rec.get(k) for k in STEP_KEYS if k in rec}
    rmpc = rec.get("rmpc")
    if isinstance(rmpc, Mapping):
        out["rmpc"] = {"mode": rmpc.get("mode")}
    return out


class _Messages:
    """The ``/mavlink/in/*`` messages read so far, handed to steps by count (``rx_count``)."""

    def __init__(self) -> None:
        self.queue: deque[tuple[str, int, bytes]] = deque()
        self.seen = 0
        self.parser: Any = None  # made when a logged message must be decoded from its bytes

    def _raw_parser(self) -> Any:
        if self.parser is None:  # (pymavlink's dialect: ~0.05-0.15 s to import)
            from pymavlink.dialects.v20 import common as mavlink2

            self.parser = mavlink2.MAVLink(None)
            self.parser.robust_parsing = True
        return self.parser

    def ready(self, rec: Mapping[str, Any]) -> bool:
        return self.seen + len(self.queue) >= int(rec.get("rx_count", 0))

    def take(self, rec: Mapping[str, Any]) -> tuple[tuple[str, dict[str, Any], int, int], ...]:
        want = int(rec.get("rx_count", 0))
        out = []
        while self.seen < want and self.queue:
            self.seen += 1
            m = self._decode(*self.queue.popleft())
            if m is not None:
                out.append(m)
        return tuple(out)

    def _decode(self, name: str, t_ns: int, raw_json: bytes
                ) -> tuple[str, dict[str, Any], int, int] | None:
        if name not in USED_MESSAGES:  # neither the store nor the time base reads it
            return None
        data = decode_json_object(raw_json) or {}
        fields, sysid = data.get("fields"), data.get("sysid")
        if (not isinstance(fields, dict) or not isinstance(sysid, int)
                or any(v is None for v in fields.values())):
            # the logged fields lost something (JSON has no NaN): decode the raw bytes
            msg = _decode_raw(self._raw_parser(), base64.b64decode(data.get("raw_b64", "")))
            if msg is None:
                return None
            fields, name, sysid = msg.to_dict(), msg.get_type(), msg.get_srcSystem()
        # logged fields are the decoded values (floats round-trip JSON exactly)
        return name, fields, sysid, int(data.get("t_rx_ns", t_ns))


def _decode_raw(parser: Any, raw: bytes) -> Any:
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


def step_inputs(path: Path, cfg: Config, perception: str, truth: bool) -> Iterator[StepInput]:
    """The :class:`StepInput` of every step record of the log at ``path``, in log order,
    then the end marker. ``perception``: "crop" / "frames" (run perception on the logged
    inputs), "detections" (the records' own) or "given" (none: the caller has it);
    ``truth``: carry ``/truth`` (for a replay that writes a log)."""
    with LogReader(path, verify=False) as reader:
        topics = [c.topic for c in reader.channels if c.topic.startswith(_MAV_IN)]
        topics += [TOPIC_SAT, TOPIC_STEP] + ([TOPIC_TRUTH] if truth else [])
        seen: Iterator[Perceived] | None = None
        if perception in ("crop", "frames"):
            seen = perceive_log(path, cfg)
        try:
            metric = Perception(cfg.camera, cfg.target, perception=cfg.perception)
            yield from _read(reader, topics, perception, seen, metric)
        finally:
            close = getattr(seen, "close", None)
            if close is not None:
                close()


def _read(reader: LogReader, topics: list[str], perception: str,
          seen: Iterator[Perceived] | None, metric: Perception) -> Iterator[StepInput]:
    """The stream of :func:`step_inputs`: a step is handed on once all of its ``rx_count``
    messages have been read (a step record is stamped with its frame's time, but the messages
    it saw may have arrived after that frame; log-time order keeps their order of arrival)."""
    mav = _Messages()
    pending: deque[dict[str, Any]] = deque()
    truth: list[tuple[int, bytes]] = []
    sat = 0

    def emit(rec: dict[str, Any]) -> StepInput:
        if seen is not None:
            p = next(seen, None)
            if p is None:
                raise ReplayInputError("perception ended before the step records")
        else:
            p = perceived_from_record(rec) if perception == "detections" else None
        out = StepInput(_compact(rec), mav.take(rec), p, tuple(truth),
                        _measured(p, metric) if p is not None else None)
        truth.clear()
        return out

    for topic, t_ns, raw in reader.raw_messages(topics):
        if topic == TOPIC_STEP:
            data = decode_json_object(raw)
            if data:
                pending.append(data)
        elif topic == TOPIC_SAT:
            sat += 1
        elif topic == TOPIC_TRUTH:
            truth.append((t_ns, raw))
            continue
        else:
            mav.queue.append((topic[len(_MAV_IN):], t_ns, raw))
            if not pending:
                continue
        while pending and mav.ready(pending[0]):
            yield emit(pending.popleft())
    while pending:  # end of the log (or a log cut short): hand on what is left
        yield emit(pending.popleft())
    yield StepInput(None, (), None, tuple(truth), None, sat, reader.recovery.corrupt_chunks)


def _measured(p: Perceived, metric: Perception
              ) -> tuple[Corners, Corners, Corners, float] | None:
    """``p.result``'s corners as plain floats (exact; cheaper to send than arrays)."""
    if p.missing or p.corners_px is None:
        return None
    r = p.result(metric)
    if r is None or r.corners_undistorted_px is None or r.points_m is None:
        return None
    return (_rows(r.corners_px), _rows(r.corners_undistorted_px), _rows(r.points_m),
            r.quality)


def _rows(a: Any) -> Corners:
    return tuple((float(x), float(y)) for x, y in a.tolist())


def perception_result(s: StepInput, p: Perceived, metric: Perception
                      ) -> PerceptionResult | None:
    """The pipeline's perception input of step ``s`` whose perception is ``p``: the step's
    ``measured`` corners as the arrays :meth:`Perception.measured` gives (float64, the
    undistorted and metric ones read-only), else ``p.result(metric)`` computed here."""
    if s.measured is None:
        return p.result(metric)
    raw, undist, points, quality = s.measured
    arrays = [np.array(v, dtype=np.float64) for v in (raw, undist, points)]
    for a in arrays[1:]:
        a.setflags(write=False)
    return PerceptionResult("ok", "", arrays[0], arrays[1], arrays[2], quality)


def _worker_main(conn: Any, path: str, raw_cfg: dict[str, Any], source: str,
                 perception: str, truth: bool) -> None:
    try:
        cfg = config_from_dict(raw_cfg, source=source)
        batch: list[StepInput] = []
        size = _FIRST_BATCH  # the first steps at once: the replay's first step waits for them
        for item in step_inputs(Path(path), cfg, perception, truth):
            batch.append(item)
            if len(batch) >= size:
                conn.send(("ok", batch))
                batch, size = [], _BATCH
        conn.send(("ok", batch))
        conn.send(("done", None))
    except CompanionError as exc:
        conn.send(("error", str(exc)))
    except BaseException:  # reported to the parent, which raises
        conn.send(("error", traceback.format_exc()))
    finally:
        conn.close()


class StreamWorker:
    """:func:`step_inputs` in a child process; iterate for the items, in order.
    ``with StreamWorker(path, cfg, "crop", False) as w: for s in w: ...``"""

    def __init__(self, path: Path, cfg: Config, perception: str, truth: bool) -> None:
        # fork (fast: nothing to import again) when available; create the worker before the
        # parent starts threads
        methods = mp.get_all_start_methods()
        ctx: Any = mp.get_context("fork" if "fork" in methods else "spawn")
        self._conn, child = ctx.Pipe(duplex=False)
        _grow_pipe(child)
        self._proc = ctx.Process(
            target=_worker_main,
            args=(child, str(path), _plain(cfg.raw), cfg.source, perception, truth),
            name="replay-inputs", daemon=True)
        self._proc.start()
        child.close()

    def __enter__(self) -> StreamWorker:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        if self._proc.is_alive():
            self._proc.terminate()
        self._proc.join(timeout=5.0)
        self._conn.close()

    def __iter__(self) -> Iterator[StepInput]:
        while True:
            try:
                kind, payload = self._conn.recv()
            except EOFError:
                raise ReplayInputError("the replay's input process stopped unexpectedly"
                                       ) from None
            if kind == "done":
                return
            if kind == "error":
                raise ReplayInputError(f"replay input process: {payload}")
            yield from payload


def _grow_pipe(conn: Any) -> None:
    """Let the worker run ~450 steps ahead (1 MB; a step is ~2.3 kB pickled, the default
    pipe of 64 kB holds less than one batch): with a full pipe the worker waits for the
    replay to read, and on a loaded machine the replay then waits for the worker to be
    scheduled again, batch after batch. Best effort (Linux; the default size still works)."""
    try:
        import fcntl

        fcntl.fcntl(conn.fileno(), fcntl.F_SETPIPE_SZ, _PIPE_BYTES)
    except (ImportError, AttributeError, OSError):
        pass


def _plain(v: Any) -> Any:
    if isinstance(v, Mapping):
        return {k: _plain(x) for k, x in v.items()}
    if isinstance(v, list | tuple):
        return [_plain(x) for x in v]
    return v


__all__ = ["STEP_KEYS", "USED_MESSAGES", "StepInput", "StreamWorker", "perception_result",
           "step_inputs"]
