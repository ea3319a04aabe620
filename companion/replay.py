"""Offline replay: a recorded flight through the same perception and controller code.

Accepted MAVLink messages (``/mavlink/in/*``, re-decoded from their raw bytes, so the store sees
exactly what the live process saw) are fed in the order the live process consumed them: before
step k, exactly the ``rx_count`` messages that had been ingested live. Every recomputed command
is compared with the recorded one.

Reading the log and perception run as their own stage (:mod:`companion.replay_stream`), in a
child process by default so that they and the controller use two cores: perception from the
logged perception inputs (crops, or an old log's full frames, :mod:`companion.replay_inputs`);
or, with ``from_detections``, not at all: the controller is fed the corners each step recorded
(tuning the controller: solver-bound). This process runs the controller, compares and writes.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import typing
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from companion import CompanionError, ConfigError
from companion.config import Config, config_from_dict, load_config, with_overrides
from companion.control.topics import TOPIC_FRAME, TOPIC_INPUT, TOPIC_STEP, TOPIC_TRUTH
from companion.control.wiring import new_pipeline, new_store
from companion.log import schemas as sch
from companion.log.encode import decode_json_object
from companion.log.reader import LogReader
from companion.perception import Perception, PerceptionResult
from companion.replay_inputs import Perceived, ReplayInputError, input_mode
from companion.replay_stream import StepInput, StreamWorker, perception_result, step_inputs

if TYPE_CHECKING:  # (loaded when a replay writes its log: the MCAP writer's imports)
    from companion.log.writer import McapLogger

log = logging.getLogger(__name__)



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
    outside_crop: int = 0
    recorded_wire_commands: int = 0
    recovery: dict[str, Any] = field(default_factory=dict)
    config_source: str = ""
    perception: str = ""  # "crop", "frames" (old full-frame log) or "detections"
    input_encoding: str = ""  # of the logged crops: "png" / "raw" (lossless) or "jpeg"
    commands_changed: int = 0
    modes: dict[str, int] = field(default_factory=dict)
    solve_ms: list[float] = field(default_factory=list, repr=False)
    costs: list[float] = field(default_factory=list, repr=False)
    thrust: list[float] = field(default_factory=list, repr=False)

    def summary(self, tol: float = 1e-6) -> dict[str, Any]:
        solve = np.asarray(self.solve_ms, dtype=float)
        cost = np.asarray(self.costs, dtype=float)
        return {
            "steps": self.steps,
            "commands_compared": self.commands_compared,
            "max_quat_diff": self.max_quat_diff,
            "max_thrust_diff": self.max_thrust_diff,
            "identical": self.commands_compared > 0 and self.max_quat_diff <= tol
            and self.max_thrust_diff <= tol and self.mode_mismatches == 0,
            "tolerance": tol,
            "commands_changed": self.commands_changed,
            "mode_mismatches": self.mode_mismatches,
            "first_difference_t_s": self.first_difference_t_s,
            "frames_missing": self.frames_missing,
            "perception": self.perception,
            "perception_outside_crop": self.outside_crop,
            "input_encoding": self.input_encoding,
            "recorded_wire_commands": self.recorded_wire_commands,
            "solver_modes": dict(self.modes),
            "solve_ms_median": float(np.median(solve)) if solve.size else None,
            "solve_ms_p95": float(np.percentile(solve, 95)) if solve.size else None,
            "mean_cost": float(np.mean(cost)) if cost.size else None,
            "thrust_min": min(self.thrust) if self.thrust else None,
            "thrust_max": max(self.thrust) if self.thrust else None,
            "config": self.config_source,
            "log": self.recovery,
        }


def replay_config(reader: LogReader, config: Path | None, overrides: list[str]) -> Config:
    """``--config`` if given, else the config recorded on ``/config``; overrides applied."""
    if config is not None:
        return load_config(config, overrides)
    # the bounds the flight built from the autopilot's limits (companion/control/vehicle_limits)
    flown = [str(o) for m in reader.messages(topics=["/control/vehicle_limits"])
             if m.data for o in m.data.get("overrides") or []]
    for m in reader.messages(topics=["/config"]):
        if m.data and isinstance(m.data.get("config"), dict):
            recorded = with_overrides(_as_flown(m.data["config"]), flown)
            return config_from_dict(with_known_keys(recorded, overrides),
                                    source=f"{m.data.get('source', '')} (recorded)")
    raise ReplayError("the log has no /config channel: pass --config FILE")


def schema_refuses(key: str) -> str | None:
    """Why the companion's config schema (today's :class:`Config`) has no dotted ``key``, or
    ``None`` when it has it (a value, or a table)."""
    cls: Any = Config
    parts = key.split(".")
    for i, part in enumerate(parts):
        names = [f.name for f in dataclasses.fields(cls) if f.name not in ("source", "raw")]
        where = ".".join(parts[:i + 1])
        if part not in names:
            table = ".".join(parts[:i]) or "the config"
            return f"{where}: no such key in {table} (it has {', '.join(sorted(names))})"
        if i == len(parts) - 1:
            return None
        tp = typing.get_type_hints(cls)[part]
        inner = [t for t in (typing.get_args(tp) or (tp,)) if dataclasses.is_dataclass(t)]
        if not inner:
            return f"{where}: a value, not a table"
        cls = inner[0]
    return None


def _has_key(doc: Mapping[str, Any], key: str) -> bool:
    node: Any = doc
    for part in key.split("."):
        if not isinstance(node, Mapping) or part not in node:
            return False
        node = node[part]
    return True


def with_known_keys(doc: Mapping[str, Any], overrides: Sequence[str]) -> dict[str, Any]:
    """``doc`` (a recorded config) with ``--set`` ``overrides`` applied; a key the recording
    lacks (one added to the companion after the log was written) is added when today's config
    schema knows it (:func:`schema_refuses`), with its tables; any other key is refused with a
    :class:`ConfigError` naming it."""
    out = with_overrides(doc, [])
    for text in overrides:
        key = text.partition("=")[0].strip()
        if "=" not in text or not key:
            raise ConfigError(f"--set {text!r}: expected KEY=VALUE")
        if not _has_key(out, key):  # as recorded: replaced (also a foreign table's key)
            why = schema_refuses(key)
            if why is not None:
                raise ConfigError(f"--set {key}: unknown key: {why}")
            log.info("--set %s: not in the recorded config (a key newer than the log): added",
                     key)
            node = out
            *tables, leaf = key.split(".")
            for part in tables:
                node = node.setdefault(part, {})
            node[leaf] = None  # a place for the override (replaced just below)
        out = with_overrides(out, [text])
    return out


#: ``[control.*]`` features newer than some logs: a log whose config has no such table was flown
#: without the feature, so its replay keeps it off (the defaults would switch it on)
_ADDED_LATER = ("estimator", "latency")


#: ``[perception]`` keys newer than some logs, with the value every log recorded before the key
#: existed was flown with (such a log's config has no such key)
_PERCEPTION_BEFORE = {"rectangle_edges": "profiles"}


def _as_flown(cfg: dict[str, Any]) -> dict[str, Any]:
    perception = cfg.get("perception")
    table = dict(perception) if isinstance(perception, dict) else {}
    if any(k not in table for k in _PERCEPTION_BEFORE):
        cfg = {**cfg, "perception": {**_PERCEPTION_BEFORE, **table}}
    control = cfg.get("control")
    if not isinstance(control, dict) or all(k in control for k in _ADDED_LATER):
        return cfg
    control = dict(control)
    for key in _ADDED_LATER:
        control.setdefault(key, {"enabled": False})
    return {**cfg, "control": control}


def replay(log_path: Path, out_path: Path | None, config: Path | None = None,
           overrides: list[str] | None = None,
           progress: Callable[[int, int], None] | None = None,
           timer: Callable[[], float] | None = None, *,
           from_detections: bool = False, workers: int = 1,
           perceived: list[Perceived] | None = None) -> ReplayResult:
    """Replay ``log_path``; ``timer`` (e.g. time.perf_counter) records stage timings in the
    recomputed step records (measurement only: results are the same without it).

    ``from_detections``: feed the controller the recorded detections instead of running
    perception. ``workers``: 1 runs perception in a child process (two cores), 0 in this
    one. ``perceived``: perception results of this log computed before (a sweep reuses them);
    when it is an empty list, this replay's are appended to it."""
    with LogReader(log_path, verify=False) as reader:  # one pass: chunks are CRC-checked as read
        return _replay(reader, log_path, out_path, config, overrides, progress, timer,
                       from_detections, workers, perceived)


def _input_stage(log_path: Path, cfg: Config, mode: str, workers: int, truth: bool,
                 perceived: list[Perceived] | None
                 ) -> tuple[Iterator[StepInput], Iterator[Perceived] | None, Callable[[], None]]:
    """The step inputs in step order, the perception results when the caller has them
    (a sweep's earlier variant; else None: they come with the step inputs) and what ends
    the stage (the worker process, if one was started: it is, at once)."""
    given = iter(perceived) if perceived else None
    kind = "given" if given is not None else mode
    close: Callable[[], None] = lambda: None  # noqa: E731
    if workers > 0:
        worker = StreamWorker(log_path, cfg, kind, truth)
        it: Iterator[StepInput] = iter(worker)
        close = worker.close
    else:
        gen = step_inputs(log_path, cfg, kind, truth)
        it, close = gen, gen.close  # type: ignore[attr-defined]
    if perceived is None or given is not None or mode == "detections":
        return it, given, close

    def keep() -> Iterator[StepInput]:  # a sweep's first variant: keep what perception saw
        for s in it:
            if s.perceived is not None:
                perceived.append(s.perceived)
            yield s
    return keep(), None, close


def _replay(reader: LogReader, log_path: Path, out_path: Path | None, config: Path | None,
            overrides: list[str] | None,
            progress: Callable[[int, int], None] | None,
            timer: Callable[[], float] | None, from_detections: bool, workers: int,
            perceived: list[Perceived] | None) -> ReplayResult:
    counts = {c.topic: c.count for c in reader.channels}
    if TOPIC_STEP not in counts:
        raise ReplayError(f"{log_path}: missing channel {TOPIC_STEP}: cannot replay "
                          f"(present: {', '.join(sorted(counts)) or 'none'})")
    cfg = _in_process_solves(replay_config(reader, config, list(overrides or [])))
    mode = "detections" if from_detections else _input_mode(reader, log_path, counts)
    res = _new_result(reader, log_path, cfg, mode)
    # The input worker first: forked before this process starts any thread (the writer's),
    # its start-up (reading the log, the first frames) overlaps the controller's build on
    # the other core; the first step waits for both.
    stage, given, close_stage = _input_stage(log_path, cfg, mode, workers,
                                             out_path is not None, perceived)
    writer = None
    try:
        rp = _Replayer(cfg, log_path, res, timer, progress, counts.get(TOPIC_STEP, 0))
        if out_path is not None:
            from companion.log.writer import McapLogger

            writer = McapLogger(out_path, flush_interval_s=5.0, queue_size=1 << 16)
            writer.open()
            writer.log_config(0, "", dict(cfg.raw), cfg.source)
        rp.given, rp.writer = given, writer
        rp.feed(stage)
    except ReplayInputError as exc:
        raise ReplayError(str(exc)) from exc
    finally:
        close_stage()
        if writer is not None:
            writer.close()
    # chunks are CRC-checked as they are read: by the input stage (a damaged one is skipped
    # and counted there), and here, the few the config and the first step were read from
    res.recovery["corrupt_chunks"] = max(reader.recovery.corrupt_chunks, rp.corrupt_chunks)
    res.recorded_wire_commands = rp.recorded_sat
    return res


def _input_mode(reader: LogReader, log_path: Path, counts: dict[str, int]) -> str:
    """What perception replays from: "crop" or "frames"; a clear error when neither is
    logged."""
    steps = reader.messages(topics=[TOPIC_STEP], decode=False)
    first = next((decode_json_object(m.raw) for m in steps), None)
    mode = input_mode(counts, first)
    if mode == "none":
        want = TOPIC_FRAME if first is None or "input" not in first else TOPIC_INPUT
        raise ReplayError(f"{log_path}: missing channel {want}: no perception input to "
                          "replay; --from-detections replays the controller from the "
                          "recorded detections")
    return mode


def _new_result(reader: LogReader, log_path: Path, cfg: Config, mode: str) -> ReplayResult:
    res = ReplayResult(config_source=cfg.source, perception=mode)
    if mode == "crop":
        try:  # how the flight logged what perception read (a JPEG crop replays approximately)
            res.input_encoding = replay_config(reader, None, []).logging.image_encoding
        except (ReplayError, ConfigError):
            res.input_encoding = ""
    rec = reader.recovery
    res.recovery = {"truncated": rec.truncated, "messages_recovered": rec.messages,
                    "salvaged": rec.salvaged, "bytes_used": rec.bytes_used,
                    "bytes_total": rec.bytes_total}
    if rec.truncated:
        log.warning("%s is cut short: replaying the %d messages recovered up to %.1f s",
                    log_path, rec.messages,
                    ((rec.last_log_time_ns or 0) - (rec.first_log_time_ns or 0)) * 1e-9)
    return res


class _Replayer:
    """The live process's order, rebuilt: before step k, exactly the messages the live
    process had ingested (:mod:`companion.replay_stream` counts them) go into the store;
    then the step runs and is compared."""

    def __init__(self, cfg: Config, log_path: Path, res: ReplayResult,
                 timer: Callable[[], float] | None,
                 progress: Callable[[int, int], None] | None, total_steps: int) -> None:
        self.cfg, self.log_path, self.res = cfg, log_path, res
        self.progress, self.total_steps = progress, total_steps
        #: the perception results when not in the step inputs (a sweep's), the output log
        self.given: Iterator[Perceived] | None = None
        self.writer: McapLogger | None = None
        self.pipeline = new_pipeline(cfg, timer=timer)
        # undistortion + metric of detections
        self.perception = Perception(cfg.camera, cfg.target, perception=cfg.perception)
        self.store = new_store(cfg)  # (the time base is the input stage's: the times come stamped)
        self.auto_delay = cfg.control.latency.auto_delay
        self.recorded_sat = self.corrupt_chunks = 0

    def feed(self, stage: Iterable[StepInput]) -> None:
        """Every step, in order, each after the messages it saw."""
        writer, ingest = self.writer, self.store.ingest
        for s in stage:
            if writer is not None:
                for t_ns, raw in s.truth:
                    writer.log(TOPIC_TRUTH, t_ns, raw, schema=sch.JSON)
            for name, fields, sysid, t_s in s.messages:
                ingest(name, fields, t_s, sysid)
            if s.record is None:  # the end
                self.recorded_sat, self.corrupt_chunks = s.sat_count, s.corrupt_chunks
                return
            p = self._perceived(s)
            self.run_step(s.record, p, perception_result(s, p, self.perception), s.t_s)
        raise ReplayError(f"{self.log_path}: the replay's inputs ended early")

    def _perceived(self, s: StepInput) -> Perceived:
        if s.perceived is not None:
            return s.perceived
        nxt = None if self.given is None else next(self.given, None)
        if nxt is None:
            raise ReplayError(f"{self.log_path}: perception ended before the step records")
        return nxt

    def run_step(self, rec_step: dict[str, Any], p: Perceived,
                 seen: PerceptionResult | None, t_s: float) -> None:
        """Step ``rec_step`` (its frame at ``t_s`` on the time base) and compare."""
        res = self.res
        res.frames_missing += p.missing
        res.outside_crop += p.outside_crop
        self.pipeline.force_solver_failure = bool(rec_step.get("fault_injected", False))
        t_now = rec_step.get("t_now_s")  # the live step's "now" (latency compensation)
        ic = rec_step.get("in_control")
        ad = rec_step.get("actuation_delay_s")  # the delay the live step used (auto_delay)
        out = self.pipeline.step(None, t_s, self.store,
                                 t_now_s=float(t_now) if isinstance(t_now, (int, float)) else None,
                                 in_control=ic if isinstance(ic, bool) else None,
                                 perceived=seen,
                                 actuation_delay_s=float(ad) if isinstance(ad, (int, float))
                                 and self.auto_delay else None)
        res.steps += 1
        if self.writer is not None:
            new = out.to_record()
            new.update({k: rec_step.get(k) for k in ("frame_seq", "frame_t_us", "t_rx_ns",
                                                     "rx_count", "offboard")})
            self.writer.log(TOPIC_STEP, int(rec_step["t_rx_ns"]), new,
                            schema=sch.CONTROLLER_STEP)
        _compare(res, rec_step, out, t_s)
        if self.progress is not None:
            self.progress(res.steps, self.total_steps)


def _in_process_solves(cfg: Config) -> Config:
    """The config with the RMPC solved in this process (``rmpc.solve_isolation = "none"``).

    A replay has no deadline to protect, and the child process of a flight solves the same
    compiled problem, so the commands are the same; in-process a replay saves the child's
    start-up (loading the solver a second time) and a pipe round trip per solve."""
    if cfg.rmpc.solve_isolation == "none":
        return cfg
    return dataclasses.replace(cfg, rmpc=dataclasses.replace(cfg.rmpc, solve_isolation="none"))


def _quat_diff(q_rec: Any, q_new: Any) -> float:
    """Largest component difference of two quaternions, up to sign (q and -q are one
    attitude); plain floats: numpy's per-call overhead was most of a step's comparison."""
    a = [float(v) for v in q_rec]
    b = q_new.tolist() if isinstance(q_new, np.ndarray) else [float(v) for v in q_new]
    if len(a) != 4 or len(b) != 4:
        raise ReplayError(f"a quaternion of {len(a)} and one of {len(b)} components")
    a0, a1, a2, a3 = a
    b0, b1, b2, b3 = b
    # one sum is finite when every term is (a NaN or infinity anywhere makes it not); the
    # one-by-one test only for what it rejects (a sum can also overflow)
    if not math.isfinite(a0 + a1 + a2 + a3 + b0 + b1 + b2 + b3) and not all(
            map(math.isfinite, a + b)):
        return math.inf  # a non-finite command is never "identical"
    return min(max(abs(a0 - b0), abs(a1 - b1), abs(a2 - b2), abs(a3 - b3)),
               max(abs(a0 + b0), abs(a1 + b1), abs(a2 + b2), abs(a3 + b3)))


def _compare(res: ReplayResult, rec_step: dict[str, Any], out: Any, t_s: float) -> None:
    rec_sp = rec_step.get("setpoint")
    new_sp = out.setpoint
    r = out.rmpc
    if r is not None:
        res.modes[r.mode] = res.modes.get(r.mode, 0) + 1
        if math.isfinite(r.solve_time_s):
            res.solve_ms.append(r.solve_time_s * 1e3)
        if math.isfinite(r.cost):
            res.costs.append(float(r.cost))
    if new_sp is not None:
        res.thrust.append(float(new_sp.thrust_norm))
    if rec_sp is None and new_sp is None:
        return
    res.commands_compared += 1
    if rec_sp is None or new_sp is None:
        res.max_quat_diff = math.inf
        res.max_thrust_diff = math.inf
        res.commands_changed += 1
        res.first_difference_t_s = res.first_difference_t_s or t_s
        return
    dq = _quat_diff(rec_sp["q_wxyz"], new_sp.q_wxyz)
    dt = abs(float(rec_sp["thrust"]) - float(new_sp.thrust_norm))
    if dq > 1e-6 or dt > 1e-6:
        res.commands_changed += 1
        if res.first_difference_t_s is None:
            res.first_difference_t_s = t_s
    res.max_quat_diff = max(res.max_quat_diff, dq)
    res.max_thrust_diff = max(res.max_thrust_diff, dt)
    rec_mode = (rec_step.get("rmpc") or {}).get("mode")
    new_mode = out.rmpc.mode if out.rmpc is not None else None
    if rec_mode != new_mode:
        res.mode_mismatches += 1
