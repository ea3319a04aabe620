"""Flight reports from a log: ``report.json`` figures, PNG plots and an HTML summary."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

from companion.config import Config
from companion.log.reader import LogReader
from companion.report.figures import (
    TOPIC_OUTRUN,
    TOPIC_STEP,
    TOPIC_TRUTH,
    ReportSettings,
    compute_report,
)

SCORED_TOPICS = (TOPIC_TRUTH, TOPIC_STEP, "/mavlink/out/SET_ATTITUDE_TARGET", TOPIC_OUTRUN)


def report_settings(cfg: Config) -> ReportSettings:
    c = cfg.camera
    return ReportSettings(
        width_px=c.width_px, height_px=c.height_px, pixel_size_m=c.pixel_size_m,
        report_pixel_size_m=c.report_pixel_size_m,
        visible_bound_report_px=c.visible_bound_report_px,
        desired_depth_m=cfg.rmpc.desired_depth_m,
        hover_thrust=cfg.control.hover_thrust, g_m_s2=cfg.rmpc.g_m_s2,
    )


def load_scored_messages(
    log_path: Path, progress: Callable[[int, int], None] | None = None
) -> tuple[list[tuple[str, int, Any]], dict[str, Any]]:
    """The messages the report uses, decoded, and what the reader recovered;
    ``progress(done, total)`` is told every 500 messages."""
    with LogReader(log_path, verify=False) as reader:  # one pass; chunks CRC-checked as read
        total = sum(c.count for c in reader.channels if c.topic in SCORED_TOPICS)
        msgs: list[tuple[str, int, Any]] = []
        for m in reader.messages(topics=SCORED_TOPICS):
            msgs.append((m.topic, m.log_time_ns, m.data or {}))
            if progress is not None and len(msgs) % 500 == 0:
                progress(len(msgs), total)
        if progress is not None:
            progress(len(msgs), max(total, len(msgs)))
        rec = reader.recovery
    return msgs, {"truncated": rec.truncated, "messages": rec.messages,
                  "salvaged": rec.salvaged, "corrupt_chunks": rec.corrupt_chunks}


def build_report(log_path: Path, cfg: Config, out: Path, plots: bool = True,
                 progress: Callable[[int, int], None] | None = None) -> dict[str, Any]:
    msgs, recovery = load_scored_messages(log_path, progress)
    st = report_settings(cfg)
    report = compute_report(msgs, st)
    report["log"] = {"path": str(log_path), **recovery}
    kind = report["controller"] = cfg.controller.kind
    if kind != "ibvs-pd":  # the rows the kind flies with (companion/control/factory.py)
        vis = {"rmpc-centroid": "centroid", "mpc-novis": "none"}.get(kind, cfg.rmpc.visibility)
        if not cfg.rmpc.enable_visibility:
            vis = "none"
        report["controller_rmpc"] = {"visibility": vis,
                                     "heading": cfg.rmpc.heading,
                                     "target_motion": cfg.rmpc.target_motion}
    if plots:
        from companion.report.plots import write_figures, write_html

        figs = write_figures(msgs, st, out)
        report["figures"] = {k: p.name for k, p in figs.items()}
        write_html(report, figs, out / "report.html", title=f"Flight report: {log_path.name}")
    (out / "report.json").write_text(json.dumps(report, indent=2))
    return report
