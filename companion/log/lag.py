"""Measure the vehicle's tilt lag from a flight log (``companion log lag LOG.mcap``).

Model: the measured roll and pitch follow the commanded ones through a first-order lag with time
constant ``tau`` after a pure delay ``delay``::

    tau * dy/dt = u(t - delay) - y(t)

``u`` is the roll/pitch of the attitude setpoints the companion sent (SET_ATTITUDE_TARGET's
quaternion), held from one setpoint to the next as the autopilot holds it; ``y`` is the
autopilot's ATTITUDE (or ATTITUDE_QUATERNION) at its own ``time_boot_ms`` stamps. The fit
simulates the response exactly (piecewise-exponential between setpoints, started from the
measured attitude) for a grid of ``tau`` and ``delay``, refines around the best, and keeps the
pair with the least squared error over roll and pitch together.

Only stretches the vehicle flew our setpoints are used: the autopilot's HEARTBEAT says OFFBOARD
(a mode change is placed at the COMMAND_ACK of our own accepted DO_SET_MODE when there is one,
else the heartbeat period around it is left out), and setpoints arrive without a gap longer than
``max_gap_s``.

Clocks: every time is taken on the log's clock. Attitude samples are placed by their
``time_boot_ms`` plus the smallest ``log time - time_boot_ms`` of the stretch (the autopilot's
clock offset plus the link's smallest transport delay; 0 on a log written with
``logging.timestamps = "source"``), so receipt jitter does not enter; setpoints are placed at
their log time (when they were sent). What remains between sending and the autopilot acting on
a setpoint (the link, the autopilot's loop) is the fitted ``delay``.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from companion.log.lag_fit import (
    LagFit,
    LagFitError,
    Series,
    config_line,
    fit_lag,
    roll_pitch_from_quat,
)
from companion.log.reader import LogReader

__all__ = [
    "LagFit", "LagFitError", "LogSeries", "Series", "config_line", "fit_lag", "measure_lag",
    "roll_pitch_from_quat", "series_from_log",
]

TOPIC_SAT = "/mavlink/out/SET_ATTITUDE_TARGET"
TOPIC_ATTITUDE = "/mavlink/in/ATTITUDE"
TOPIC_ATTITUDE_Q = "/mavlink/in/ATTITUDE_QUATERNION"
TOPIC_HEARTBEAT = "/mavlink/in/HEARTBEAT"
TOPIC_ACK = "/mavlink/in/COMMAND_ACK"
TOPICS_COMMAND_OUT = ("/mavlink/out/COMMAND_LONG", "/mavlink/out/COMMAND_INT")

PX4_MAIN_OFFBOARD = 6
MAV_CMD_DO_SET_MODE = 176
MAV_RESULT_ACCEPTED = 0
MAV_AUTOPILOT_INVALID = 8

#: a backwards jump of time_boot_ms larger than this is a reboot: the stretch ends there
REBOOT_JUMP_S = 1.0



# -- reading the log ---------------------------------------------------------------------------


@dataclass
class _Raw:
    sat: list[tuple[int, dict[str, Any]]] = field(default_factory=list)
    att: list[tuple[int, dict[str, Any], int | None]] = field(default_factory=list)
    att_q: list[tuple[int, dict[str, Any], int | None]] = field(default_factory=list)
    hb: list[tuple[int, dict[str, Any], int | None, int | None]] = field(default_factory=list)
    ack: list[tuple[int, dict[str, Any]]] = field(default_factory=list)
    cmd_out: list[tuple[int, dict[str, Any]]] = field(default_factory=list)
    #: "" for a complete log, else what the reader salvaged (appended to errors)
    salvage_note: str = ""


def _read(path: Path) -> _Raw:
    raw = _Raw()
    topics = [TOPIC_SAT, TOPIC_ATTITUDE, TOPIC_ATTITUDE_Q, TOPIC_HEARTBEAT, TOPIC_ACK,
              *TOPICS_COMMAND_OUT]
    with LogReader(path) as r:
        rec = r.recovery
        if rec.truncated or rec.corrupt_chunks:
            raw.salvage_note = (
                f" (the log is damaged: {rec.messages} messages readable in its first "
                f"{rec.bytes_used} of {rec.bytes_total} bytes, {rec.corrupt_chunks} damaged "
                "chunk(s) skipped)")
        for m in r.messages(topics):
            d = m.data
            if d is None or not isinstance(d.get("fields"), dict):
                continue
            f = d["fields"]
            if m.topic == TOPIC_SAT:
                raw.sat.append((m.log_time_ns, f))
            elif m.topic == TOPIC_ATTITUDE:
                raw.att.append((m.log_time_ns, f, d.get("sysid")))
            elif m.topic == TOPIC_ATTITUDE_Q:
                raw.att_q.append((m.log_time_ns, f, d.get("sysid")))
            elif m.topic == TOPIC_HEARTBEAT:
                raw.hb.append((m.log_time_ns, f, d.get("sysid"), d.get("compid")))
            elif m.topic == TOPIC_ACK:
                raw.ack.append((m.log_time_ns, f))
            else:
                raw.cmd_out.append((m.log_time_ns, f))
    return raw


def _num(v: Any) -> float:
    """A logged number (NaN/inf are logged as null) as a float; NaN when missing."""
    return float(v) if isinstance(v, int | float) and not isinstance(v, bool) else math.nan


def offboard_intervals(raw: _Raw, sysid: int, compid: int) -> tuple[list[tuple[float, float]],
                                                                    int]:
    """Log-time intervals (s) the autopilot ``sysid``/``compid`` was in OFFBOARD, and how many
    of its heartbeats were seen. Between two heartbeats in the same mode the mode held; a
    change between heartbeats is placed at the COMMAND_ACK accepting our DO_SET_MODE to the new
    mode when there is one, else the interval between them is left out; after the last
    heartbeat its mode holds for one heartbeat period."""
    hbs = [(t * 1e-9, ((int(f.get("custom_mode", 0)) >> 16) & 0xFF) == PX4_MAIN_OFFBOARD)
           for t, f, s, c in raw.hb
           if s == sysid and (compid == 0 or c == compid)
           and f.get("autopilot") != MAV_AUTOPILOT_INVALID]
    if not hbs:
        return [], 0
    # our accepted mode requests: (time of the ACK, whether it asked for OFFBOARD)
    reqs = [(t * 1e-9, f) for t, f in sorted(raw.cmd_out, key=lambda r: r[0])
            if f.get("command") == MAV_CMD_DO_SET_MODE]
    changes: list[tuple[float, bool]] = []
    for t, f in raw.ack:
        if f.get("command") != MAV_CMD_DO_SET_MODE or f.get("result") != MAV_RESULT_ACCEPTED:
            continue
        before = [q for tq, q in reqs if tq <= t * 1e-9]
        if before:
            main = _num(before[-1].get("param2"))
            changes.append((t * 1e-9, math.isfinite(main) and int(main) == PX4_MAIN_OFFBOARD))
    hb_t = np.array([t for t, _ in hbs])
    period = float(np.median(np.diff(hb_t))) if hb_t.size > 1 else 1.0
    # timeline points: (time, offboard, kind)
    pts = sorted([(t, o, "hb") for t, o in hbs] + [(t, o, "ack") for t, o in changes])
    out: list[tuple[float, float]] = []
    for (t_a, o_a, _), (t_b, o_b, k_b) in itertools.pairwise(pts):
        if o_a and (o_b or k_b == "ack"):
            out.append((t_a, t_b))  # held, or left exactly at our accepted request
    t_last, o_last, _ = pts[-1]
    if o_last:
        out.append((t_last, t_last + period))
    merged: list[tuple[float, float]] = []
    for a, b in out:
        if merged and a <= merged[-1][1] + 1e-9:
            merged[-1] = (merged[-1][0], max(merged[-1][1], b))
        else:
            merged.append((a, b))
    return merged, len(hbs)


@dataclass
class LogSeries:
    series: list[Series]
    setpoints: int
    offboard_s: float
    dropped_nonfinite: int
    attitude_topic: str
    salvage_note: str = ""


def _commands(raw: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """The attitude setpoints' times (s), roll/pitch (rad; NaN where unusable), usable mask
    and the count of unusable ones (body-rate setpoints are left out)."""
    cmd_t_l, q_l = [], []
    for t, f in raw.sat:
        q = f.get("q")
        mask = f.get("type_mask")
        if isinstance(mask, int) and mask & 128:  # attitude ignored: a body-rate setpoint
            continue
        qa = [_num(v) for v in q] if isinstance(q, list) and len(q) == 4 else [math.nan] * 4
        cmd_t_l.append(t * 1e-9)
        q_l.append(qa)
    cmd_t = np.array(cmd_t_l)
    qs = np.array(q_l, dtype=float).reshape(-1, 4)
    ok_c = np.all(np.isfinite(qs), axis=1) & (np.linalg.norm(qs, axis=1) > 0.5)
    cmd = np.full((cmd_t.size, 2), np.nan)
    cmd[ok_c] = roll_pitch_from_quat(qs[ok_c])
    return cmd_t, cmd, ok_c, int(np.count_nonzero(~ok_c))


@dataclass
class _Attitude:
    topic: str
    t_log_s: np.ndarray
    t_boot_s: np.ndarray
    roll_pitch: np.ndarray
    samples: int  # in the log, before the unusable ones were dropped
    dropped: int


def _attitude(raw: Any, sysid: int, path: str | Path) -> _Attitude:
    """The autopilot's measured roll/pitch: ATTITUDE, else ATTITUDE_QUATERNION."""
    topic = TOPIC_ATTITUDE
    rows = [(t, f) for t, f, s in raw.att if s == sysid]
    if not rows:
        topic = TOPIC_ATTITUDE_Q
        rows = [(t, f) for t, f, s in raw.att_q if s == sysid]
    if not rows:
        raise LagFitError(f"{path}: no attitude from the autopilot (sysid {sysid}) on "
                          f"{TOPIC_ATTITUDE} or {TOPIC_ATTITUDE_Q}{raw.salvage_note}")
    att_log = np.array([t * 1e-9 for t, _ in rows])
    att_boot = np.array([_num(f.get("time_boot_ms")) * 1e-3 for _, f in rows])
    if topic == TOPIC_ATTITUDE:
        att = np.array([[_num(f.get("roll")), _num(f.get("pitch"))] for _, f in rows])
    else:
        qs_m = np.array([[_num(f.get(k)) for k in ("q1", "q2", "q3", "q4")] for _, f in rows])
        att = np.full((qs_m.shape[0], 2), np.nan)
        good = np.all(np.isfinite(qs_m), axis=1) & (np.linalg.norm(qs_m, axis=1) > 0.5)
        att[good] = roll_pitch_from_quat(qs_m[good])
    ok_a = np.all(np.isfinite(att), axis=1) & np.isfinite(att_boot)
    return _Attitude(topic, att_log[ok_a], att_boot[ok_a], att[ok_a], len(rows),
                     int(np.count_nonzero(~ok_a)))


def _setpoint_runs(sel: np.ndarray, ok_c: np.ndarray, cmd_t: np.ndarray,
                   max_gap_s: float) -> list[np.ndarray]:
    """``sel``'s setpoints split at gaps longer than ``max_gap_s`` and at unusable ones; runs
    of at least 2."""
    runs: list[np.ndarray] = []
    cur: list[int] = []
    for k in sel:
        if not ok_c[k] or (cur and cmd_t[k] - cmd_t[cur[-1]] > max_gap_s):
            if len(cur) >= 2:
                runs.append(np.array(cur))
            cur = [] if not ok_c[k] else [int(k)]
            continue
        cur.append(int(k))
    if len(cur) >= 2:
        runs.append(np.array(cur))
    return runs


def _run_series(c_t: np.ndarray, c: np.ndarray, att: _Attitude, t_lo: float,
                t_hi: float) -> list[Series]:
    """One setpoint run's :class:`Series` over [t_lo, t_hi), split at autopilot reboots
    (time_boot_ms going back)."""
    out: list[Series] = []
    m = (att.t_log_s >= t_lo) & (att.t_log_s < t_hi)
    if np.count_nonzero(m) < 2:
        return out
    idx = np.nonzero(m)[0]
    cuts = np.nonzero(np.diff(att.t_boot_s[idx]) < -REBOOT_JUMP_S)[0]
    for part in np.split(idx, cuts + 1):
        if part.size < 2:
            continue
        offset = float(np.min(att.t_log_s[part] - att.t_boot_s[part]))
        t_att = att.t_boot_s[part] + offset
        order = np.argsort(t_att, kind="stable")
        t_att, y = t_att[order], att.roll_pitch[part][order]
        keep = (t_att >= t_lo) & (t_att < t_hi) & (t_att >= c_t[0])
        if np.count_nonzero(keep) < 2:
            continue
        out.append(Series(c_t, c, t_att[keep], y[keep]))
    return out


def series_from_log(path: str | Path, *, max_gap_s: float = 0.5) -> LogSeries:
    """The offboard stretches of a companion log as :class:`Series` (see the module doc)."""
    raw = _read(Path(path))
    if not raw.sat:
        why = raw.salvage_note or ": it is not a log of a flight the companion flew"
        raise LagFitError(f"{path}: no attitude setpoints ({TOPIC_SAT}) in the log{why}")
    f0 = raw.sat[0][1]
    sysid, compid = f0.get("target_system"), f0.get("target_component")
    if not (isinstance(sysid, int) and isinstance(compid, int)):
        raise LagFitError(f"{path}: the setpoints carry no target system/component")
    cmd_t, cmd, ok_c, dropped = _commands(raw)
    att = _attitude(raw, sysid, path)
    dropped += att.dropped
    intervals, n_hb = offboard_intervals(raw, sysid, compid)
    if n_hb == 0:
        raise LagFitError(f"{path}: no HEARTBEAT from the autopilot (sysid {sysid}): cannot "
                          f"tell when the vehicle flew the setpoints (OFFBOARD){raw.salvage_note}")
    if not intervals:
        raise LagFitError(f"{path}: the autopilot's HEARTBEAT never reports OFFBOARD: the "
                          f"setpoints were never flown{raw.salvage_note}")
    series: list[Series] = []
    off_s = 0.0
    n_sp = 0
    for a, b in intervals:
        # setpoint runs inside (a, b), split at gaps and at unusable setpoints. A setpoint
        # sent before the stretch began is left out even if it was still in force: PX4 takes
        # attitude setpoints only while in OFFBOARD (mavlink_receiver), so on engaging it
        # flies the first one received after the switch; before that, its previous mode's.
        # The fit then starts max_delay_s after the first setpoint kept (_trim).
        sel = np.nonzero((cmd_t > a) & (cmd_t < b))[0]
        for run in _setpoint_runs(sel, ok_c, cmd_t, max_gap_s):
            c_t, c = cmd_t[run], cmd[run]
            t_lo = max(a, c_t[0])
            t_hi = min(b, c_t[-1] + max_gap_s)
            if np.count_nonzero((att.t_log_s >= t_lo) & (att.t_log_s < t_hi)) < 2:
                continue
            series += _run_series(c_t, c, att, t_lo, t_hi)
            off_s += float(t_hi - t_lo)
            n_sp += int(np.count_nonzero((c_t >= t_lo) & (c_t < t_hi)))
    if not series:
        raise LagFitError(f"{path}: no stretch with both setpoints and attitude while the "
                          f"autopilot was in OFFBOARD ({len(raw.sat)} setpoints, {att.samples} "
                          f"attitude samples in the log, {dropped} not finite){raw.salvage_note}")
    return LogSeries(series, n_sp, off_s, dropped, att.topic, raw.salvage_note)


def measure_lag(path: str | Path, *, fit_delay: bool = False, max_delay_s: float = 0.2,
                max_gap_s: float = 0.5) -> LagFit:
    """Read ``path`` and fit the lag; raises :class:`LagFitError` with the reason when the log
    cannot give one."""
    ls = series_from_log(path, max_gap_s=max_gap_s)
    try:
        res = fit_lag(ls.series, fit_delay=fit_delay, max_delay_s=max_delay_s)
    except LagFitError as e:
        extra = f" ({ls.dropped_nonfinite} non-finite samples dropped)" \
            if ls.dropped_nonfinite else ""
        raise LagFitError(f"{path}: {e}{extra}{ls.salvage_note}") from None
    res.setpoints, res.offboard_s = ls.setpoints, ls.offboard_s
    res.dropped_nonfinite, res.attitude_topic = ls.dropped_nonfinite, ls.attitude_topic
    res.salvage_note = ls.salvage_note.strip(" ()")
    return res
