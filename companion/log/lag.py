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
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from companion import CompanionError
from companion.log.reader import LogReader

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

#: fewest attitude samples the fit accepts (two seconds of PX4's slowest attitude stream)
MIN_SAMPLES = 40
#: smallest spread (std, rad) of the commanded tilt over the samples used: below it the
#: commands do not move (a vehicle holding still); how well what moves pins tau down is
#: reported (``tau_range_s``, ``variance_explained``) and warned about (:data:`WEAK_RANGE`)
MIN_EXCITATION_RAD = math.radians(0.02)
#: a backwards jump of time_boot_ms larger than this is a reboot: the stretch ends there
REBOOT_JUMP_S = 1.0

TAU_MIN_S, TAU_MAX_S = 0.005, 2.0
#: warn when the taus within 10 % of the best squared error span more than this fraction of
#: tau either way, or when less than WEAK_VARIANCE of the attitude's variance is explained
WEAK_RANGE = 0.25
WEAK_VARIANCE = 0.8


class LagFitError(CompanionError):
    """The log cannot give a lag: too few setpoints or attitude samples in offboard, no
    excitation, unusable data. The message says which."""


@dataclass(frozen=True)
class Series:
    """Commands and measurements on one clock (s). ``cmd_t`` sorted, ``cmd`` (n, 2) roll/pitch
    rad; ``att_t`` sorted, ``att`` (m, 2)."""

    cmd_t: np.ndarray
    cmd: np.ndarray
    att_t: np.ndarray
    att: np.ndarray


@dataclass
class LagFit:
    """Result of :func:`fit_lag`. ``rms_deg``: RMS residual over roll and pitch (deg);
    ``variance_explained``: 1 - SSE / (sum of squared deviations of the measured roll and pitch
    from their means); ``per_axis_tau_s``: tau fitted to roll and to pitch alone at the joint
    delay; ``tau_range_s``: the taus whose squared error is within 10 % of the best (at the best
    delay): how sharply the data pin tau down; ``warnings``: why the result may not be
    trusted (a bound of the searched range reached, tau weakly identified, a poor fit)."""

    tau_s: float
    delay_s: float
    rms_deg: float
    variance_explained: float
    samples: int
    per_axis_tau_s: tuple[float, float]
    tau_range_s: tuple[float, float]
    warnings: list[str] = field(default_factory=list)
    stretches: int = 0
    setpoints: int = 0
    offboard_s: float = 0.0
    dropped_nonfinite: int = 0
    attitude_topic: str = ""
    fit_delay: bool = True
    salvage_note: str = ""

    def to_dict(self) -> dict[str, Any]:
        return {
            "tau_s": self.tau_s, "delay_s": self.delay_s if self.fit_delay else None,
            "rms_deg": self.rms_deg, "variance_explained": self.variance_explained,
            "samples": self.samples, "per_axis_tau_s": {"roll": self.per_axis_tau_s[0],
                                                        "pitch": self.per_axis_tau_s[1]},
            "tau_range_s": list(self.tau_range_s), "warnings": self.warnings,
            "stretches": self.stretches, "setpoints": self.setpoints,
            "offboard_s": self.offboard_s, "dropped_nonfinite": self.dropped_nonfinite,
            "attitude_topic": self.attitude_topic, "damaged_log": self.salvage_note or None,
            # the lead inverts a lag alone: a tau fitted beside a delay is a diagnostic
            "config_line": None if self.fit_delay else config_line(self.tau_s),
        }


def config_line(tau_s: float) -> str:
    return f"control.lead.attitude_lag_s = {tau_s:.3f}"


def roll_pitch_from_quat(q_wxyz: np.ndarray) -> np.ndarray:
    """(n, 4) w,x,y,z quaternions -> (n, 2) ZYX roll, pitch (rad)."""
    q = np.asarray(q_wxyz, dtype=float)
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    w, x, y, z = q.T
    roll = np.arctan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y))
    pitch = np.arcsin(np.clip(2 * (w * y - z * x), -1.0, 1.0))
    return np.stack([roll, pitch], axis=1)


# -- the fit ---------------------------------------------------------------------------------


def _forced(cmd_t: np.ndarray, cmd: np.ndarray, taus: np.ndarray) -> np.ndarray:
    """G at each command time for every tau: the response from zero at ``cmd_t[0]`` to the
    held commands. Returns (n_cmd, n_tau, 2)."""
    n = cmd_t.size
    g = np.zeros((n, taus.size, cmd.shape[1]))
    dt = np.diff(cmd_t)
    for k in range(n - 1):
        a = np.exp(-dt[k] / taus)[:, None]
        g[k + 1] = cmd[k] + (g[k] - cmd[k]) * a
    return g


def _g_at(t: np.ndarray, cmd_t: np.ndarray, cmd: np.ndarray, g: np.ndarray,
          taus: np.ndarray) -> np.ndarray:
    """G at times ``t`` (each >= cmd_t[0]): (len(t), n_tau, 2)."""
    k = np.clip(np.searchsorted(cmd_t, t, side="right") - 1, 0, None)
    h = np.maximum(t - cmd_t[k], 0.0)[:, None, None]  # >= 0 up to rounding at cmd_t[0]
    u = cmd[k][:, None, :]
    out: np.ndarray = u + (g[k] - u) * np.exp(-h / taus[None, :, None])
    return out


def _simulate(s: Series, taus: np.ndarray, delay_s: float, g: np.ndarray,
              rows: slice) -> np.ndarray:
    """Simulated attitude at ``s.att_t[rows]`` (rows after the first sample, which starts the
    response at ``t0 = s.att_t[0]``) for every tau with the commands delayed by ``delay_s``:
    (n_rows, n_tau, 2)."""
    t0 = float(s.att_t[0])
    t = s.att_t[rows]
    e = np.exp(-(t - t0)[:, None, None] / taus[None, :, None])
    gt = _g_at(t - delay_s, s.cmd_t, s.cmd, g, taus)
    g0 = _g_at(np.array([t0 - delay_s]), s.cmd_t, s.cmd, g, taus)
    out: np.ndarray = s.att[0] * e + gt - e * g0
    return out


#: attitude samples simulated at once (bounds memory: rows x taus x 2 floats per array)
_CHUNK = 2048


def _sse_grid(series: Sequence[Series], taus: np.ndarray, delays: np.ndarray
              ) -> np.ndarray:
    """Squared error per (delay, tau, axis) summed over the stretches: (n_d, n_tau, 2)."""
    out = np.zeros((delays.size, taus.size, 2))
    for s in series:
        g = _forced(s.cmd_t, s.cmd, taus)
        for a in range(1, s.att_t.size, _CHUNK):
            rows = slice(a, min(a + _CHUNK, s.att_t.size))
            for i, d in enumerate(delays):
                r = _simulate(s, taus, float(d), g, rows) - s.att[rows, None, :]
                out[i] += np.sum(r * r, axis=0)
    return out


def _trim(series: Sequence[Series], max_delay_s: float) -> list[Series]:
    """Each stretch from the first attitude sample at which every candidate delay has a
    command: samples at or after ``cmd_t[0] + max_delay_s``."""
    out = []
    for s in series:
        keep = s.att_t >= s.cmd_t[0] + max_delay_s
        if np.count_nonzero(keep) >= 2:
            out.append(Series(s.cmd_t, s.cmd, s.att_t[keep], s.att[keep]))
    return out


def fit_lag(series: Sequence[Series], *, fit_delay: bool = True, max_delay_s: float = 0.2,
            tau_bounds_s: tuple[float, float] = (TAU_MIN_S, TAU_MAX_S),
            min_samples: int = MIN_SAMPLES) -> LagFit:
    """Least-squares first-order lag (and delay) from the stretches ``series``."""
    if not fit_delay:
        max_delay_s = 0.0
    used = _trim(series, max_delay_s)
    n = sum(s.att_t.size - 1 for s in used)
    if n < min_samples:
        raise LagFitError(
            f"only {n} attitude samples under offboard control with setpoints to compare "
            f"(at least {min_samples} needed): fly longer in OFFBOARD")
    cmd_held = np.concatenate([
        s.cmd[np.clip(np.searchsorted(s.cmd_t, s.att_t[1:], side="right") - 1, 0, None)]
        for s in used])
    spread = float(np.max(np.std(cmd_held, axis=0)))
    if spread < MIN_EXCITATION_RAD:
        raise LagFitError(
            f"the commanded roll/pitch hardly move (std {math.degrees(spread):.3f} deg < "
            f"{math.degrees(MIN_EXCITATION_RAD):.2f} deg): the lag cannot be seen; fly a "
            f"stretch with tilt changes (a moving target, or steps)")
    lo, hi = tau_bounds_s
    taus = np.geomspace(lo, hi, 64)
    delays = np.arange(0.0, max_delay_s + 1e-9, 0.005) if fit_delay else np.zeros(1)
    sse = _sse_grid(used, taus, delays).sum(axis=2)
    i, j = (int(v) for v in np.unravel_index(int(np.argmin(sse)), sse.shape))
    # refine: around the best grid point, one coarse step each way
    tau_f = np.linspace(taus[max(j - 1, 0)], taus[min(j + 1, taus.size - 1)], 41)
    if fit_delay:
        d_f = np.clip(np.linspace(delays[i] - 0.005, delays[i] + 0.005, 21), 0.0, max_delay_s)
        d_f = np.unique(d_f)
    else:
        d_f = np.zeros(1)
    sse_f = _sse_grid(used, tau_f, d_f)
    tot = sse_f.sum(axis=2)
    fi, fj = (int(v) for v in np.unravel_index(int(np.argmin(tot)), tot.shape))
    tau, delay = float(tau_f[fj]), float(d_f[fi])
    best = float(tot[fi, fj])
    warnings = []
    if j == 0 or j == taus.size - 1:
        warnings.append(f"tau at the edge of the searched {lo:g}..{hi:g} s: not identified")
    if fit_delay and i == delays.size - 1:
        warnings.append(f"delay at the edge of the searched 0..{max_delay_s:g} s: not "
                        "identified (a longer delay? --max-delay)")
    # per axis, and how sharply tau is pinned: a dense grid (3 % steps) at the best delay
    dense = np.geomspace(lo, hi, 200)
    rows = _sse_grid(used, dense, np.array([delay]))[0]
    per_axis = (float(dense[int(np.argmin(rows[:, 0]))]),
                float(dense[int(np.argmin(rows[:, 1]))]))
    within = dense[rows.sum(axis=1) <= 1.1 * best]
    rng = (min(float(within.min()), tau), max(float(within.max()), tau)) if within.size \
        else (tau, tau)
    y = np.concatenate([s.att[1:] for s in used])
    sst = float(np.sum((y - y.mean(axis=0)) ** 2))
    ve = 1.0 - best / sst if sst > 0 else math.nan
    if rng[0] < tau * (1 - WEAK_RANGE) or rng[1] > tau * (1 + WEAK_RANGE):
        warnings.append(f"tau weakly identified: {rng[0]:.3f}..{rng[1]:.3f} s fit within 10 % "
                        "of the best; fly a stretch with more tilt changes")
    if not ve >= WEAK_VARIANCE:
        warnings.append(f"the model explains only {ve * 100:.0f} % of the attitude's variance: "
                        "a first-order lag describes this vehicle poorly, or noise dominates")
    return LagFit(
        tau_s=tau, delay_s=delay, rms_deg=math.degrees(math.sqrt(best / (2 * n))),
        variance_explained=ve, samples=n,
        per_axis_tau_s=per_axis, tau_range_s=rng, warnings=warnings,
        stretches=len(used), fit_delay=fit_delay)


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
    # commands
    dropped = 0
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
    dropped += int(np.count_nonzero(~ok_c))
    cmd = np.full((cmd_t.size, 2), np.nan)
    cmd[ok_c] = roll_pitch_from_quat(qs[ok_c])
    # measurements: ATTITUDE, else ATTITUDE_QUATERNION, from the autopilot
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
    dropped += int(np.count_nonzero(~ok_a))
    att_log, att_boot, att = att_log[ok_a], att_boot[ok_a], att[ok_a]

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
        for run in runs:
            c_t, c = cmd_t[run], cmd[run]
            t_lo = max(a, c_t[0])
            t_hi = min(b, c_t[-1] + max_gap_s)
            m = (att_log >= t_lo) & (att_log < t_hi)
            if np.count_nonzero(m) < 2:
                continue
            # split at reboots (time_boot_ms going back)
            idx = np.nonzero(m)[0]
            cuts = np.nonzero(np.diff(att_boot[idx]) < -REBOOT_JUMP_S)[0]
            for part in np.split(idx, cuts + 1):
                if part.size < 2:
                    continue
                offset = float(np.min(att_log[part] - att_boot[part]))
                t_att = att_boot[part] + offset
                order = np.argsort(t_att, kind="stable")
                t_att, y = t_att[order], att[part][order]
                keep = (t_att >= t_lo) & (t_att < t_hi) & (t_att >= c_t[0])
                if np.count_nonzero(keep) < 2:
                    continue
                series.append(Series(c_t, c, t_att[keep], y[keep]))
            off_s += float(t_hi - t_lo)
            n_sp += int(np.count_nonzero((c_t >= t_lo) & (c_t < t_hi)))
    if not series:
        raise LagFitError(f"{path}: no stretch with both setpoints and attitude while the "
                          f"autopilot was in OFFBOARD ({len(raw.sat)} setpoints, {len(rows)} "
                          f"attitude samples in the log, {dropped} not finite){raw.salvage_note}")
    return LogSeries(series, n_sp, off_s, dropped, topic, raw.salvage_note)


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
