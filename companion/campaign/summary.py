"""A campaign's results: the table (``results.csv``), a Markdown summary and plots.

The table has one row per run (``companion/campaign/runner.py`` names the columns). The
summary counts, per controller and per scenario, the runs that lost corners, the centroid or
the target (from 1 s after OFFBOARD engaged, ground truth), and the plots show the rate of runs
with every corner in view against the AGV's peak speed, the distribution of the worst corner,
the recovery fraction, RMS errors and solve times per controller.
"""

from __future__ import annotations

import csv
import itertools
import math
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["read_table", "write_plots", "write_summary", "write_table"]

#: first columns of the table, in this order; any other column follows, sorted
LEAD_COLUMNS = ("run_id", "controller", "scenario", "seed", "status", "error", "path",
                "speed_scale", "corners_in_view", "centroid_in_view", "target_kept",
                "first_feasible", "corner_max_px", "centroid_max_px")


def write_table(rows: Sequence[Mapping[str, Any]], path: Path) -> None:
    """``rows`` as CSV (empty cells for missing values)."""
    cols = [c for c in LEAD_COLUMNS if any(c in r for r in rows)]
    cols += sorted({k for r in rows for k in r} - set(cols))
    with path.open("w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=cols, extrasaction="ignore")
        w.writeheader()
        for r in rows:
            w.writerow({k: ("" if r.get(k) is None else r.get(k)) for k in cols})


def _parse(v: str) -> Any:
    if v == "":
        return None
    if v in ("True", "False"):
        return v == "True"
    try:
        return int(v)
    except ValueError:
        pass
    try:
        return float(v)
    except ValueError:
        return v


def read_table(path: Path) -> list[dict[str, Any]]:
    """The rows of a ``results.csv`` with numbers and booleans parsed."""
    with path.open(newline="") as fh:
        return [{k: _parse(v) for k, v in r.items()} for r in csv.DictReader(fh)]


def _ok(rows: Iterable[Mapping[str, Any]]) -> list[Mapping[str, Any]]:
    return [r for r in rows if r.get("status") == "ok"]


def _vals(rows: Iterable[Mapping[str, Any]], key: str) -> np.ndarray:
    out = [r.get(key) for r in rows]
    return np.array([float(v) for v in out
                     if isinstance(v, (int, float)) and not isinstance(v, bool)
                     and math.isfinite(v)], dtype=float)


def _fmt(v: float | None, digits: int = 0) -> str:
    return "-" if v is None or not math.isfinite(v) else f"{v:.{digits}f}"


def _median(a: np.ndarray) -> float | None:
    return float(np.median(a)) if a.size else None


def _order(rows: Sequence[Mapping[str, Any]], key: str) -> list[str]:
    seen: dict[str, None] = {}
    for r in rows:
        seen.setdefault(str(r.get(key)), None)
    return list(seen)


def _losses(rows: Sequence[Mapping[str, Any]]) -> str:
    """``corners/centroid/target`` loss counts of ok runs, e.g. ``3/1/0 of 4``."""
    ok = _ok(rows)
    if not ok:
        n_err = len(rows)
        return f"{n_err} error{'s' if n_err != 1 else ''}" if n_err else "-"
    c = sum(1 for r in ok if r.get("corners_in_view") is not True)
    m = sum(1 for r in ok if r.get("centroid_in_view") is not True)
    t = sum(1 for r in ok if r.get("target_kept") is not True)
    err = len(rows) - len(ok)
    return f"{c}/{m}/{t} of {len(ok)}" + (f" (+{err} err)" if err else "")


def write_summary(rows: Sequence[Mapping[str, Any]], path: Path, title: str,
                  command: str = "", notes: Sequence[str] = ()) -> str:
    """The Markdown summary (also returned)."""
    ctrls = _order(rows, "controller")
    scens = _order(rows, "scenario")
    ok = _ok(rows)
    lines = [f"# {title}", ""]
    if command:
        lines += ["Regenerate (table, summary and plots) with:", "", "```bash", command, "```",
                  ""]
    lines += [f"{len(rows)} runs: {len(ok)} flown to the end, {len(rows) - len(ok)} errors. "
              "Visibility is judged on the emulator's ground truth from 1 s after OFFBOARD "
              "engaged; `corners` = every corner of the target inside the visible area on "
              "every frame, `centroid` = its centre, `target` = detected by the companion on "
              "every step.", "", *notes, "", "## Per controller", "",
              "| controller | runs | errors | every corner in view | centroid in view | "
              "target kept | first problem feasible | every corner in view, first problem "
              "feasible | first problem in OFFBOARD feasible | every corner in view, first "
              "problem in OFFBOARD feasible | worst corner (median / max px) | "
              "recovery steps (mean) | recovery steps in OFFBOARD (mean) | "
              "runs with a fallback | solve median / p95 (ms) | "
              "RMS horizontal / height error (m, median) |",
              "| --- | " + "--- | " * 15]
    for c in ctrls:
        rc = [r for r in rows if str(r.get("controller")) == c]
        ok_c = _ok(rc)
        n = len(ok_c)

        def rate(key: str, rs: Sequence[Mapping[str, Any]] = ok_c) -> str:
            known = [r for r in rs if r.get(key) is not None]
            k = sum(1 for r in known if r.get(key) is True)
            return f"{k}/{len(known)}" if known else "-"

        cm = _vals(ok_c, "corner_max_px")
        rf = _vals(ok_c, "recovery_fraction")
        rfe = _vals(ok_c, "recovery_fraction_engaged")
        first_eng = [r for r in ok_c if r.get("first_feasible_engaged") is True]
        fb = sum(1 for r in ok_c if (r.get("fallbacks") or 0) > 0)
        lines.append(
            f"| {c} | {len(rc)} | {len(rc) - n} | {rate('corners_in_view')} | "
            f"{rate('centroid_in_view')} | {rate('target_kept')} | {rate('first_feasible')} | "
            f"{rate('corners_in_view', [r for r in ok_c if r.get('first_feasible') is True])} | "
            f"{rate('first_feasible_engaged')} | {rate('corners_in_view', first_eng)} | "
            f"{_fmt(_median(cm))} / {_fmt(float(cm.max()) if cm.size else None)} | "
            f"{_fmt(100 * float(rf.mean()) if rf.size else None, 1)} % | "
            f"{_fmt(100 * float(rfe.mean()) if rfe.size else None, 1)} % | {fb} | "
            f"{_fmt(_median(_vals(ok_c, 'solve_median_ms')), 2)} / "
            f"{_fmt(_median(_vals(ok_c, 'solve_p95_ms')), 2)} | "
            f"{_fmt(_median(_vals(ok_c, 'rms_horizontal_error_m')), 3)} / "
            f"{_fmt(_median(_vals(ok_c, 'rms_height_error_m')), 3)} |")
    lines += ["", "## Where each controller loses corners / the centroid / the target", "",
              "Runs that lost corners / the centroid / the target, of the runs flown to the end "
              "(from 1 s after OFFBOARD engaged).", "",
              "| scenario | AGV peak speed (m/s) | heading rate (rad/s) | "
              + " | ".join(ctrls) + " |",
              "| --- | --- | --- | " + "--- | " * len(ctrls)]
    for s in scens:
        rs = [r for r in rows if str(r.get("scenario")) == s]
        v = _vals(rs, "nominal_peak_speed_m_s")
        w = _vals(rs, "nominal_peak_yaw_rate_rad_s")
        cells = [_losses([r for r in rs if str(r.get("controller")) == c]) for c in ctrls]
        lines.append(f"| {s} | {_fmt(float(v.max()) if v.size else None, 2)} | "
                     f"{_fmt(float(w.max()) if w.size else None, 2)} | " + " | ".join(cells)
                     + " |")
    errors = [r for r in rows if r.get("status") != "ok"]
    if errors:
        lines += ["", "## Errors", ""]
        by_msg: dict[str, list[str]] = {}
        for r in errors:
            by_msg.setdefault(str(r.get("error")), []).append(str(r.get("run_id")))
        for msg, ids in by_msg.items():
            lines.append(f"- {len(ids)} run(s), e.g. `{ids[0]}`: {msg}")
    lines += ["", "## Plots", "", "![in view vs speed](plots/in_view_vs_speed.png)",
              "![worst corner](plots/corner_max.png)",
              "![recovery](plots/recovery_fraction.png)", "![RMS errors](plots/rms_errors.png)",
              "![solve times](plots/solve_times.png)", ""]
    text = "\n".join(lines)
    path.write_text(text)
    return text


def write_plots(rows: Sequence[Mapping[str, Any]], out: Path) -> dict[str, Path]:
    """The campaign's plots (PNG) in ``out``; returns name -> file."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out.mkdir(parents=True, exist_ok=True)
    ok = _ok(rows)
    ctrls = _order(rows, "controller")
    by_c = {c: [r for r in ok if str(r.get("controller")) == c] for c in ctrls}
    files: dict[str, Path] = {}

    def save(fig: Any, name: str) -> None:
        fig.tight_layout()
        p = out / f"{name}.png"
        fig.savefig(p, dpi=90)
        plt.close(fig)
        files[name] = p

    # rate of runs with every corner in view vs the AGV's peak speed (binned)
    speeds = _vals(ok, "agv_max_speed_m_s")
    edges = np.unique(np.quantile(speeds, np.linspace(0, 1, 6))) if speeds.size else np.array(
        [0.0, 1.0])
    if edges.size < 2:
        edges = np.array([edges[0] - 0.05, edges[0] + 0.05])
    fig, ax = plt.subplots(figsize=(7, 4))
    width = float(edges[-1] - edges[0]) or 1.0
    styles = ("o-", "s--", "^-.", "D:", "v-", "P--")
    for i, (c, rs) in enumerate(by_c.items()):
        # controllers side by side within a bin (equal rates would hide each other)
        dx = (i - (len(by_c) - 1) / 2) * 0.012 * width
        xs, ys = [], []
        for lo, hi in itertools.pairwise(edges):
            sel = [r for r in rs if isinstance(r.get("agv_max_speed_m_s"), (int, float))
                   and lo <= r["agv_max_speed_m_s"] <= hi]
            if sel:
                xs.append((lo + hi) / 2 + dx)
                ys.append(100.0 * sum(r.get("corners_in_view") is True for r in sel) / len(sel))
        ax.plot(xs, ys, styles[i % len(styles)], label=c, alpha=0.85)
    ax.set_xlabel("AGV peak speed over the flight (m/s, bins of equal counts)")
    ax.set_ylabel("runs with every corner in view (%)")
    ax.set_ylim(-5, 105)
    ax.grid(alpha=0.3)
    ax.legend()
    save(fig, "in_view_vs_speed")

    def boxes(key: str, ylabel: str, name: str, scale: float = 1.0,
              line: float | None = None, log: bool = False) -> None:
        fig, ax = plt.subplots(figsize=(7, 4))
        data = [_vals(by_c[c], key) * scale for c in ctrls]
        pos = [i + 1 for i, d in enumerate(data) if d.size]
        if pos:
            ax.boxplot([d for d in data if d.size], positions=pos, widths=0.6)
            for p, d in zip(pos, [d for d in data if d.size], strict=True):
                ax.plot(np.full(d.size, p) + np.linspace(-0.15, 0.15, d.size), d, ".",
                        alpha=0.5)
        ax.set_xticks(range(1, len(ctrls) + 1), ctrls)
        ax.set_xlim(0.5, len(ctrls) + 0.5)
        if line is not None:
            ax.axhline(line, color="r", lw=1, ls="--")
        if log:
            ax.set_yscale("log")
        ax.set_ylabel(ylabel)
        ax.grid(alpha=0.3)
        save(fig, name)

    boxes("corner_max_px", "worst corner |u|, |n| over the flight (px; bound dashed)",
          "corner_max", line=500.0)
    boxes("recovery_fraction", "recovery steps (% of solves)", "recovery_fraction", 100.0)

    def pair(name: str, panels: tuple[tuple[str, str], tuple[str, str]]) -> None:
        """Two box plots side by side, one box per controller."""
        fig, axes = plt.subplots(1, 2, figsize=(9, 4))
        for ax, (key, label) in zip(axes, panels, strict=True):
            data = [_vals(by_c[c], key) for c in ctrls]
            pos = [i + 1 for i, d in enumerate(data) if d.size]
            if pos:
                ax.boxplot([d for d in data if d.size], positions=pos, widths=0.6)
            ax.set_xticks(range(1, len(ctrls) + 1), ctrls, rotation=20)
            ax.set_xlim(0.5, len(ctrls) + 0.5)
            ax.set_ylabel(label)
            ax.grid(alpha=0.3)
        save(fig, name)

    pair("rms_errors", (("rms_horizontal_error_m", "RMS horizontal error (m)"),
                        ("rms_height_error_m", "RMS height error (m)")))
    pair("solve_times", (("solve_median_ms", "solve time, median per run (ms)"),
                         ("solve_p95_ms", "solve time, p95 per run (ms)")))
    return files
