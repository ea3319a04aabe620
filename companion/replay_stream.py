"""A recorded flight's step inputs, read and decoded in the order a replay runs them.

:mod:`companion.replay` runs the controller; everything it needs from the log comes from here,
one :class:`StepInput` per step record: the MAVLink messages the live process had ingested
before that step (``rx_count``; decoded, only those the store reads, each with its time on the
flight's time base), the step's frame time, the step record's entries the replay reads, the
step's perception (:mod:`companion.replay_inputs`) and, when the replay writes a log, the
ground truth logged meanwhile. Reading, decompressing and decoding the log, the time base and
the detections' undistortion (~0.2 ms a step) then run beside the controller: in a child
process by default (:class:`StreamWorker`), so that the replay's process spends its time on
the controller. Between the processes a step is plain tuples, floats and strings (no class
instances: unpickling those cost the replay's process more than building them).
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
from companion.control.timebase import STAMPED_MESSAGES, TimeBase
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
#: the step record's entries a replay reads (the rest, ~6 kB of JSON a step, stays here;
#: of ``setpoint``, only the command: ``q_wxyz`` and ``thrust``)
STEP_KEYS = ("rx_count", "frame_t_us", "t_rx_ns", "fault_injected", "t_now_s", "in_control",
             "actuation_delay_s", "setpoint", "frame_seq", "offboard")
#: the messages the replay's store and time base read; the others are counted only
USED_MESSAGES = TelemetryStore.MESSAGES | STAMPED_MESSAGES
#: a step's raw, undistorted and metric corners (4 x (x, y) each, in that order, flat) and
#: the detection's quality
Measured = tuple[tuple[float, ...], float]
_BATCH = 64  # steps per message from the worker process
_PIPE_BYTES = 1 << 20  # the pipe to the replay (see _grow_pipe)
_FIRST_BATCH = 2  # ... but the first message, which the replay's first step waits for


class StepInput(NamedTuple):
    """One step's inputs. ``record``: the step record's :data:`STEP_KEYS` and its ``rmpc``
    mode (None: the end of the log, carrying the ground truth logged after the last step);
    ``messages``: ``(name, fields, sysid, t_s)`` to ingest first, in order (``t_s``: the
    message's time on the flight's time base, ``control.time_source``);
    ``perceived``: the step's perception (None when the replay supplies it);
    ``truth``: ``(log time ns, JSON bytes)`` of ``/truth`` read since the step before;
    ``measured``: when ``perceived`` has corners, its result's corners (``Perceived.result``:
    computed here, beside the controller's process); ``t_s``: the step's frame time on the
    time base (after its messages', as the live process stamped them);
    ``sat_count``, ``corrupt_chunks``: with the end marker, the SET_ATTITUDE_TARGET messages
    the flight sent and the damaged chunks reading skipped (CRC-checked as read)."""

    record: dict[str, Any] | None
    messages: tuple[tuple[str, dict[str, Any], int, float], ...]
    perceived: Perceived | None
    truth: tuple[tuple[int, bytes], ...] = ()
    measured: Measured | None = None
    sat_count: int = 0
    corrupt_chunks: int = 0
    t_s: float = 0.0


def _compact(rec: Mapping[str, Any]) -> dict[str, Any]:
    out = {k: rec.get(k) for k in STEP_KEYS if k in rec}
    sp = out.get("setpoint")
    if isinstance(sp, Mapping):
        out["setpoint"] = {k: sp.get(k) for k in ("q_wxyz", "thrust")}
    rmpc = rec.get("rmpc")
    if isinstance(rmpc, Mapping):
        out["rmpc"] = {"mode": rmpc.get("mode")}
    return out


def _frame_s(tb: TimeBase, rec: Mapping[str, Any]) -> float:
    """The step's frame time, as the live step stamped its frame."""
    try:
        return tb.frame_s(int(rec["frame_t_us"]), int(rec["t_rx_ns"]))
    except (KeyError, TypeError, ValueError):
        raise ReplayInputError(f"a step record without a usable frame_t_us / t_rx_ns: "
                               f"{ {k: rec.get(k) for k in ('frame_t_us', 't_rx_ns')} }"
                               ) from None


class _Messages:
    """The ``/mavlink/in/*`` messages read so far, handed to steps by count (``rx_count``),
    each stamped by the time base as the live process stamped it."""

    def __init__(self, tb: TimeBase) -> None:
        self.queue: deque[tuple[str, int, bytes]] = deque()
        self.seen = 0
        self.tb = tb
        self.parser: Any = None  # made when a logged message must be decoded from its bytes

    def _raw_parser(self) -> Any:
        if self.parser is None:  # (pymavlink's dialect: ~0.05-0.15 s to import)
            from pymavlink.dialects.v20 import common as mavlink2

            self.parser = mavlink2.MAVLink(None)
            self.parser.robust_parsing = True
        return self.parser

    def ready(self, rec: Mapping[str, Any]) -> bool:
        return self.seen + len(self.queue) >= int(rec.get("rx_count", 0))

    def take(self, rec: Mapping[str, Any]
             ) -> tuple[tuple[str, dict[str, Any], int, float], ...]:
        want = int(rec.get("rx_count", 0))
        out = []
        message_s = self.tb.message_s
        while self.seen < want and self.queue:
            self.seen += 1
            m = self._decode(*self.queue.popleft())
            if m is not None:
                name, fields, sysid, t_rx_ns = m
                out.append((name, fields, sysid, message_s(name, fields, t_rx_ns)))
        return tuple(out)

    def _decode(self, name: str, t_ns: int, raw_json: bytes
                ) -> tuple[str, dict[str, Any], int, int] | None:
        if name not in USED_MESSAGES:  # neither the store nor the time base reads it
            return None
        data = decode_json_object(raw_json) or {}
        fields, sysid = data.get("fields"), data.get("sysid")
        if (not isinstance(fields, dict) or not isinstance(sysid, int)
                or None in fields.values()):
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
            yield from _read(reader, topics, perception, seen, metric, cfg)
        finally:
            close = getattr(seen, "close", None)
            if close is not None:
                close()


def _read(reader: LogReader, topics: list[str], perception: str,
          seen: Iterator[Perceived] | None, metric: Perception, cfg: Config
          ) -> Iterator[StepInput]:
    """The stream of :func:`step_inputs`: a step is handed on once all of its ``rx_count``
    messages have been read (a step record is stamped with its frame's time, but the messages
    it saw may have arrived after that frame; log-time order keeps their order of arrival)."""
    tb = TimeBase(cfg.control.time_source, cfg.safety.max_frame_age_s)
    mav = _Messages(tb)
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
        messages = mav.take(rec)  # stamped before the frame, as the live process did
        out = StepInput(_compact(rec), messages, p, tuple(truth),
                        _measured(p, metric) if p is not None else None, t_s=_frame_s(tb, rec))
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


def _measured(p: Perceived, metric: Perception) -> Measured | None:
    """``p.result``'s corners as plain floats (exact; cheaper to send than arrays)."""
    if p.missing or p.corners_px is None:
        return None
    r = p.result(metric)
    if r is None or r.corners_undistorted_px is None or r.points_m is None:
        return None
    flat = np.concatenate([np.asarray(a, dtype=np.float64).reshape(-1) for a in
                           (r.corners_px, r.corners_undistorted_px, r.points_m)])
    if flat.size != 24:
        raise ReplayInputError(f"a detection of {flat.size // 6} corners: 4 expected")
    return tuple(flat.tolist()), float(r.quality)


def perception_result(s: StepInput, p: Perceived, metric: Perception
                      ) -> PerceptionResult | None:
    """The pipeline's perception input of step ``s`` whose perception is ``p``: the step's
    ``measured`` corners as the arrays :meth:`Perception.measured` gives (float64 (4, 2), the
    undistorted and metric ones read-only), else ``p.result(metric)`` computed here."""
    if s.measured is None:
        return p.result(metric)
    flat, quality = s.measured
    a = np.array(flat, dtype=np.float64).reshape(3, 4, 2)  # one array, three rows of it
    raw, undist, points = a[0], a[1], a[2]
    undist.setflags(write=False)
    points.setflags(write=False)
    return PerceptionResult("ok", "", raw, undist, points, quality)


#: a :class:`StepInput` between the processes: its fields, ``perceived`` as the tuple of its
#: fields (unpickling instances, by their classes' ``__new__`` and a state dict, cost the
#: replay's process ~10 us a step more than building them from tuples)
Wire = tuple[Any, ...]


def _wire(s: StepInput) -> Wire:
    p = s.perceived
    return (s.record, s.messages, None if p is None else (
        p.status, p.reason, p.corners_px, p.quality, p.missing, p.outside_crop),
        s.truth, s.measured, s.sat_count, s.corrupt_chunks, s.t_s)


def _unwire(w: Wire) -> StepInput:
    p = w[2]
    return StepInput(w[0], w[1], None if p is None else Perceived(*p), *w[3:])


def _worker_main(conn: Any, path: str, raw_cfg: dict[str, Any], source: str,
                 perception: str, truth: bool) -> None:
    try:
        cfg = config_from_dict(raw_cfg, source=source)
        batch: list[Wire] = []
        size = _FIRST_BATCH  # the first steps at once: the replay's first step waits for them
        for item in step_inputs(Path(path), cfg, perception, truth):
            batch.append(_wire(item))
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
            yield from map(_unwire, payload)


def _grow_pipe(conn: Any) -> None:
    """Let the worker run ~800 steps ahead (1 MB; a paper flight's step is ~1.2 kB pickled,
    the default pipe of 64 kB holds less than one batch): with a full pipe the worker waits for the
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
