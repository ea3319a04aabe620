"""The tilt-lag model and its fit (:mod:`companion.log.lag` reads the log and calls it).

Model: the measured roll and pitch follow the commanded ones through a first-order lag with time
constant ``tau`` after a pure delay ``delay`` (``tau * dy/dt = u(t - delay) - y(t)``), simulated
exactly (piecewise-exponential between setpoints, started from the measured attitude) for a
grid of ``tau`` and ``delay``, refined around the best.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from companion import CompanionError

#: fewest attitude samples the fit accepts (two seconds of PX4's slowest attitude stream)
MIN_SAMPLES = 40
#: smallest spread (std, rad) of the commanded tilt over the samples used: below it the
#: commands do not move (a vehicle holding still); how well what moves pins tau down is
#: reported (``tau_range_s``, ``variance_explained``) and warned about (:data:`WEAK_RANGE`)
MIN_EXCITATION_RAD = math.radians(0.02)

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
