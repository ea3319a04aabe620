"""Flight report figures (the paper's Fig. 2 and more) and a one-page HTML summary.

Input: decoded log messages ``(topic, log_time_ns, payload)`` as for
:func:`companion.report.figures.compute_report`. Matplotlib with the non-interactive Agg backend.
"""

from __future__ import annotations

import html
import json
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from matplotlib.patches import Rectangle

from companion.report.figures import (
    TOPIC_STEP,
    TOPIC_TRUTH,
    ReportSettings,
    true_features,
)
from companion.report.headline import headline

LEVELS = ("tracking", "reacquire", "terminal", "hover", "silent")


def write_figures(
    messages: Iterable[tuple[str, int, Mapping[str, Any]]], st: ReportSettings, out_dir: Path
) -> dict[str, Path]:
    """Write the PNG figures; returns name -> path (only figures that have data)."""
    out_dir.mkdir(parents=True, exist_ok=True)
    truth: list[Mapping[str, Any]] = []
    steps: list[Mapping[str, Any]] = []
    for topic, _t, payload in messages:
        if topic == TOPIC_TRUTH:
            truth.append(payload)
        elif topic == TOPIC_STEP:
            steps.append(payload)
    truth.sort(key=lambda r: r["t_us"])
    steps.sort(key=lambda r: r["t_s"])
    figs: dict[str, Path] = {}
    if truth:
        figs["paths_3d"] = _paths_3d(truth, out_dir / "paths_3d.png")
        figs["pixels"] = _pixels(truth, st, out_dir / "pixels.png")
        figs["moment_errors"] = _moment_errors(truth, steps, st, out_dir / "moment_errors.png")
    if steps:
        figs["solver"] = _solver(steps, out_dir / "solver.png")
        figs["safety"] = _safety(steps, out_dir / "safety.png")
        figs["latency"] = _latency(steps, out_dir / "latency.png")
    if truth and steps:
        figs["command_vs_achieved"] = _command_vs_achieved(
            truth, steps, st, out_dir / "command_vs_achieved.png")
    return figs


def _paths_3d(truth: list[Mapping[str, Any]], path: Path) -> Path:
    q = np.array([r["uav"]["pos_ned_m"] for r in truth])
    a = np.array([r["agv"]["pos_ned_m"] for r in truth])
    fig = plt.figure(figsize=(7, 5.5))
    ax = fig.add_subplot(projection="3d")
    # plot in a right-handed "north, east, up" view
    ax.plot(q[:, 0], q[:, 1], -q[:, 2], label="UAV", color="tab:blue")
    ax.plot(a[:, 0], a[:, 1], -a[:, 2], label="AGV top", color="tab:orange")
    ax.scatter(q[0, 0], q[0, 1], -q[0, 2], color="tab:blue", marker="o")
    ax.scatter(a[0, 0], a[0, 1], -a[0, 2], color="tab:orange", marker="o")
    ax.set_xlabel("north (m)")
    ax.set_ylabel("east (m)")
    ax.set_zlabel("up (m)")
    ax.set_title("Trajectories (ground truth)")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def corner_report_pixels(truth: list[Mapping[str, Any]], st: ReportSettings) -> np.ndarray:
    """(F, 4, 2) true corner positions ``(n_px, u_px)`` in report pixels (NaN where absent)."""
    scale = st.pixel_size_m / st.report_pixel_size_m
    cx, cy = (st.width_px - 1) / 2.0, (st.height_px - 1) / 2.0
    out = np.full((len(truth), 4, 2), np.nan)
    for i, r in enumerate(truth):
        c = np.asarray(r.get("corners_px") or [], dtype=float)
        if c.shape == (4, 2):
            out[i, :, 0] = (c[:, 0] - cx) * scale
            out[i, :, 1] = -(c[:, 1] - cy) * scale
    return out


def _pixels(truth: list[Mapping[str, Any]], st: ReportSettings, path: Path) -> Path:
    px = corner_report_pixels(truth, st)
    b = st.visible_bound_report_px
    half = st.width_px * st.pixel_size_m / st.report_pixel_size_m / 2.0
    fig, ax = plt.subplots(figsize=(6, 6))
    ax.add_patch(Rectangle((-half, -half), 2 * half, 2 * half, fill=False, color="0.6",
                               label="image"))
    ax.add_patch(Rectangle((-b, -b), 2 * b, 2 * b, fill=False, color="tab:red", lw=2,
                               label=f"visible area (|px| <= {b:.0f})"))
    for k in range(4):
        ax.plot(px[:, k, 0], px[:, k, 1], lw=0.8, label=f"corner {k + 1}")
    ax.plot(np.nanmean(px[:, :, 0], axis=1), np.nanmean(px[:, :, 1], axis=1), "k--", lw=0.8,
            label="centroid")
    ax.set_xlabel("n (px, right)")
    ax.set_ylabel("u (px, forward)")
    ax.set_aspect("equal")
    lim = max(half, float(np.nanmax(np.abs(px))) if np.isfinite(px).any() else half) * 1.05
    ax.set_xlim(-lim, lim)
    ax.set_ylim(-lim, lim)
    ax.set_title("Target corners in the real image (ground truth, paper pixels)")
    ax.legend(fontsize=7, loc="upper right")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def _moment_errors(truth: list[Mapping[str, Any]], steps: list[Mapping[str, Any]],
                   st: ReportSettings, path: Path) -> Path:
    t = np.array([r["t_us"] * 1e-6 for r in truth])
    se = np.array([true_features(r, st.desired_depth_m) for r in truth])
    fig, axes = plt.subplots(2, 1, figsize=(8, 6), sharex=True)
    for i, name in enumerate(("s_e1", "s_e2", "s_e3", "s_e4")):
        axes[0].plot(t, se[:, i], label=f"{name} (truth)")
    meas = [(s["t_s"], s["eta_e"]) for s in steps if s.get("eta_e")]
    if meas:
        tm = np.array([m[0] for m in meas])
        em = np.array([m[1] for m in meas])
        for i in range(4):
            axes[1].plot(tm, em[:, i], label=f"s_e{i + 1} (measured)")
    axes[0].set_ylabel("image-moment error")
    axes[1].set_ylabel("image-moment error")
    axes[1].set_xlabel("time (s)")
    for ax in axes:
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, ncol=4)
    axes[0].set_title("Image-moment errors")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def _solver(steps: list[Mapping[str, Any]], path: Path) -> Path:
    rec = [(s["t_s"], s["rmpc"]) for s in steps if s.get("rmpc")]
    fig, axes = plt.subplots(2, 1, figsize=(8, 5), sharex=True)
    if rec:
        t = np.array([r[0] for r in rec])
        ms = np.array([(r[1]["solve_time_s"] or np.nan) * 1e3 for r in rec])
        it = np.array([r[1]["iterations"] for r in rec])
        modes = [r[1]["mode"] for r in rec]
        colors = {"optimal": "tab:green", "recovery": "tab:orange", "fallback": "tab:red"}
        for m, c in colors.items():
            sel = np.array([x == m for x in modes])
            if sel.any():
                axes[0].scatter(t[sel], ms[sel], s=3, color=c, label=m)
        axes[1].plot(t, it, lw=0.8)
        axes[0].legend(fontsize=7)
    axes[0].set_ylabel("solve time (ms)")
    axes[1].set_ylabel("iterations")
    axes[1].set_xlabel("time (s)")
    axes[0].set_title("RMPC solver")
    for ax in axes:
        ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def _safety(steps: list[Mapping[str, Any]], path: Path) -> Path:
    t = np.array([s["t_s"] for s in steps])
    lv = np.array([LEVELS.index((s.get("safety") or {}).get("level", "silent"))
                   if (s.get("safety") or {}).get("level") in LEVELS else len(LEVELS) - 1
                   for s in steps])
    fig, ax = plt.subplots(figsize=(8, 2.8))
    ax.step(t, lv, where="post")
    ax.set_yticks(range(len(LEVELS)), LEVELS)
    ax.set_xlabel("time (s)")
    ax.set_title("Safety level")
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def _latency(steps: list[Mapping[str, Any]], path: Path) -> Path:
    rec = [(s["t_s"], s["latency_ms"], s.get("timings_ms") or {}) for s in steps
           if s.get("latency_ms") is not None]
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.2), gridspec_kw={"width_ratios": [2, 1]})
    if rec:
        t = np.array([r[0] for r in rec])
        lat = np.array([r[1] for r in rec], dtype=float)
        axes[0].plot(t, lat, lw=0.6, color="tab:blue", label="frame -> command")
        stages = sorted({k for r in rec for k in r[2]})
        med = [float(np.median([r[2].get(k, np.nan) for r in rec])) for k in stages]
        axes[1].barh(stages, med, color="tab:gray")
        axes[1].set_xlabel("median (ms)")
        axes[1].set_title("stages")
        axes[0].axhline(float(np.median(lat)), color="k", lw=0.8, ls="--", label="median")
        axes[0].legend(fontsize=7)
    axes[0].set_xlabel("time (s)")
    axes[0].set_ylabel("latency (ms)")
    axes[0].set_title("Frame receipt -> SET_ATTITUDE_TARGET sent")
    axes[0].grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def _euler_zyx(q: np.ndarray) -> np.ndarray:
    """(N, 4) w, x, y, z quaternions -> (N, 3) roll, pitch, yaw (rad), ZYX."""
    w, x, y, z = q.T
    roll = np.arctan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y))
    pitch = np.arcsin(np.clip(2 * (w * y - z * x), -1.0, 1.0))
    yaw = np.arctan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
    return np.column_stack([roll, pitch, yaw])


def _command_vs_achieved(truth: list[Mapping[str, Any]], steps: list[Mapping[str, Any]],
                         st: ReportSettings, path: Path) -> Path:
    """Commanded attitude and collective thrust (the setpoints sent) against what the vehicle
    achieved (ground truth). Thrust is shown as specific force in g: commanded
    ``thrust / hover_thrust`` (the companion's model) against the achieved
    ``|a - g - d| / g`` from the true acceleration and disturbance."""
    cmd = [(s["t_s"], s["setpoint"]) for s in steps if s.get("setpoint") and s.get("sent", True)]
    tt = np.array([r["t_us"] for r in truth], dtype=float) * 1e-6
    q = np.array([r["uav"]["q_wxyz"] for r in truth], dtype=float)
    v = np.array([r["uav"]["vel_ned_m_s"] for r in truth], dtype=float)
    d = np.array([r.get("disturbance_accel_ned_m_s2") or [0.0, 0.0, 0.0] for r in truth],
                 dtype=float)
    ach = _euler_zyx(q)
    fig, axes = plt.subplots(4, 1, figsize=(9, 8), sharex=True)
    names = ("roll (deg)", "pitch (deg)", "yaw (deg)")
    for i, name in enumerate(names):
        axes[i].plot(tt, np.degrees(np.unwrap(ach[:, i])), lw=0.8, label="achieved")
        if cmd:
            tc = np.array([c[0] for c in cmd])
            key = ("roll_rad", "pitch_rad", "yaw_rad")[i]
            vc = np.array([c[1].get(key, np.nan) for c in cmd], dtype=float)
            axes[i].plot(tc, np.degrees(np.unwrap(vc)), lw=0.8, ls="--", label="commanded")
        axes[i].set_ylabel(name)
    if len(tt) > 2:
        acc = np.gradient(v, tt, axis=0)
        f = acc - np.array([0.0, 0.0, st.g_m_s2]) - d
        axes[3].plot(tt, np.linalg.norm(f, axis=1) / st.g_m_s2, lw=0.8, label="achieved")
    if cmd:
        tc = np.array([c[0] for c in cmd])
        th = np.array([c[1].get("thrust", np.nan) for c in cmd], dtype=float)
        axes[3].plot(tc, th / st.hover_thrust, lw=0.8, ls="--", label="commanded")
    axes[3].set_ylabel("thrust (g)")
    axes[3].set_xlabel("time (s)")
    axes[0].set_title("Commanded vs achieved attitude and collective thrust")
    for ax in axes:
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, loc="upper right")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def write_html(report: Mapping[str, Any], figs: Mapping[str, Path], out: Path,
               title: str = "Flight report") -> Path:
    """A one-page HTML report: the headline verdicts first (each against its target), then
    the figures, then every number of ``report.json`` folded away. Each headline row carries
    ``data-key`` and ``data-verdict`` so a machine can read the page back."""
    rows = headline(report)
    n_miss = sum(r.verdict == "miss" for r in rows)
    summary = ("every headline target met" if n_miss == 0 else
               f"{n_miss} of {sum(r.verdict != 'n/a' for r in rows)} headline targets missed")
    head = "\n".join(
        f'<tr class="{r.verdict.replace("/", "")}" data-key="{html.escape(r.key)}" '
        f'data-verdict="{html.escape(r.verdict)}"><td>{html.escape(r.label)}</td>'
        f"<td><b>{html.escape(r.figure)}</b></td><td>{html.escape(r.target)}</td>"
        f'<td class="v">{html.escape(r.verdict.upper())}</td></tr>'
        for r in rows)
    context = []
    for k in ("scenario", "sim_time_s", "real_time_factor", "overrides"):
        if k in report:
            context.append(f"{k.replace('_', ' ')}: {html.escape(_fmt(report[k]))}")
    details = []
    for section, vals in report.items():
        if isinstance(vals, Mapping):
            for k, v in vals.items():
                if f"{section}.{k}" != "safety.transitions":
                    details.append((f"{section}.{k}", v))
        else:
            details.append((section, vals))
    table = "\n".join(
        f"<tr><td>{html.escape(k)}</td><td><code>{html.escape(_fmt(v))}</code></td></tr>"
        for k, v in details)
    imgs = "\n".join(
        f'<figure><img src="{html.escape(p.name)}" alt="{html.escape(n)}">'
        f"<figcaption>{html.escape(n.replace('_', ' '))}</figcaption></figure>"
        for n, p in figs.items()
    )
    doc = f"""<!doctype html>
<html><head><meta charset="utf-8"><title>{html.escape(title)}</title>
<style>body{{font-family:sans-serif;max-width:1100px;margin:auto;color:#222}}
table.headline{{border-collapse:collapse;margin:12px 0;font-size:15px}}
table.headline td,table.headline th{{padding:6px 12px;border-bottom:1px solid #ddd;text-align:left}}
tr.pass td.v{{color:#fff;background:#2e7d32}} tr.miss td.v{{color:#fff;background:#c62828}}
tr.na td.v{{color:#fff;background:#888}} td.v{{font-weight:bold;text-align:center}}
p.summary{{font-size:18px}} .context{{color:#666}}
details td{{padding:2px 8px;border-bottom:1px solid #eee;font-size:13px}}
img{{max-width:540px}} figure{{display:inline-block;margin:6px;vertical-align:top}}</style>
</head>
<body><h1>{html.escape(title)}</h1>
<p class="context">{" &middot; ".join(context)}</p>
<p class="summary" id="summary">{html.escape(summary)}</p>
<table class="headline" id="headline">
<tr><th>what</th><th>figure</th><th>target</th><th>verdict</th></tr>
{head}
</table>
<h2>Figures</h2>
{imgs}
<details><summary>All figures of report.json</summary><table>{table}</table></details>
</body></html>
"""
    out.write_text(doc)
    return out


def _fmt(v: Any) -> str:
    if isinstance(v, float):
        return f"{v:.4g}"
    if isinstance(v, list) and v and all(isinstance(x, float) for x in v):
        return "[" + ", ".join(f"{x:.3g}" for x in v) + "]"
    return json.dumps(v) if not isinstance(v, str) else v
