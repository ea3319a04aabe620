"""docs/reference/reliability.md from the probes' results: the summary table, then each
probe's figures, then what the probes do and the configuration keys they exercise."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from bench.reliab.common import ProbeResult

INTRO = """\
# Reliability and security

> **Answers:** what does the companion do under a hostile or lossy link, a stalled or killed
> process and a full or slow disk, measured?

What the companion does under a hostile or lossy link, a stalled or killed process and a bad
disk, measured against the real emulator and companion processes on loopback (real UDP/TCP
sockets, real MCAP files). Written by `python bench/reliability.py` (this file is generated:
rerun it rather than editing the tables); the short versions of the same probes run as tests
in `tests/reliability/`. "Bad commands" counts commands built from bad data (an attacker's
frame that was accepted, a non-finite setpoint, a frame or telemetry older than the safety
limits): it must be 0.

Wall-clock figures on this 2-core machine shared with other jobs are noisy: the load average
is given with every run, and CPU time (`getrusage` of the child processes) beside wall time.
"""

STATIC = Path(__file__).with_name("static.md")


def _md(x: Any) -> str:
    return str(x).replace("|", "/").replace("\n", " ")


def write_report(doc: Path, results: list[ProbeResult], meta: dict[str, Any]) -> None:
    lines = [INTRO]
    lines.append(f"Run {meta['started']} to {meta['finished']} on {meta['machine']}; load "
                 f"average (1/5/15 min) {meta['load_before']} before, {meta['load_after']} "
                 f"after. Command: `{meta['command']}`.\n")
    lines.append("## Summary\n")
    lines.append("| probe | inputs tried | result | data lost | bad commands | pass | "
                 "wall s | CPU s |")
    lines.append("| --- | --- | --- | --- | --- | --- | --- | --- |")
    for r in results:
        lines.append(f"| {_md(r.probe)} | {_md(r.inputs)} | {_md(r.result)} | "
                     f"{_md(r.data_lost)} | {r.bad_commands} | "
                     f"{'yes' if r.passed else '**no**'} | {r.wall_s:.0f} | {r.cpu_s:.0f} |")
    lines.append("")
    lines.append("## Details\n")
    for r in results:
        lines.extend(_details(r))
    lines.append(STATIC.read_text().split("-->\n", 1)[1])
    doc.parent.mkdir(parents=True, exist_ok=True)
    doc.write_text("\n".join(lines))


def _details(r: ProbeResult) -> list[str]:
    f = r.figures
    out = [f"### {r.probe}\n"]
    if "flights" in f:  # impaired
        out.append("| flight | max corner px (bound) | frames outside | frames target lost "
                   "| steps per safety level | offboard left | RMS s_e | sim x real time |")
        out.append("| --- | --- | --- | --- | --- | --- | --- | --- |")
        for k, v in f["flights"].items():
            rtf = v.get("sim_rtf")
            rms = v.get("rms_se")
            rms_s = ("[" + ", ".join(f"{x:.3f}" for x in rms) + "]"
                     if isinstance(rms, list) else _md(rms))
            out.append(f"| {k} | {v['max_corner_px']:.0f} ({v['bound_px']:.0f}) | "
                       f"{v['frames_outside_bound']} | {v['frames_target_lost']} | "
                       f"{_md(v['levels'])} | {v['offboard_left']} | {rms_s} | "
                       f"{'-' if rtf is None else f'{rtf:.1f}'} |")
        out.append("")
        for k, v in f["flights"].items():
            eps = v.get("non_tracking_episodes") or []
            if eps:
                shown = "; ".join(f"{e['t_s']:.2f} s {e['level']} ({e['reason']})"
                                  for e in eps[:6])
                out.append(f"- {k}: first safety transitions away from tracking: {_md(shown)}")
            if v.get("impairment"):
                out.append(f"- {k}: emulator impairment counters: "
                           f"{_md(v['impairment'])}")
        out.append("")
    elif "runs" in f:  # kill -9
        out.append("| log | after ready s | messages | steps | lost s | replay identical |")
        out.append("| --- | --- | --- | --- | --- | --- |")
        for v in f["runs"]:
            lost = v.get("lost_s")
            out.append(f"| {v['log']} | {v['after_ready_s']:.2f} | {v.get('messages')} | "
                       f"{v.get('steps')} | {'-' if lost is None else f'{lost:.2f}'} | "
                       f"{v.get('replay_identical', v.get('replay_error', '-'))} |")
        out.append("")
    elif "policies" in f:
        out.append("| policy | fsyncs | total ms | ms each | log calls p50/p99/max ms | "
                   "loop period max ms |")
        out.append("| --- | --- | --- | --- | --- | --- |")
        for k, v in f["policies"].items():
            n = v["fsync_count"]
            each = v["fsync_time_s"] / n * 1e3 if n else 0.0
            lc = v["log_calls_ms"]
            out.append(f"| {k} | {n} | {v['fsync_time_s'] * 1e3:.0f} | {each:.1f} | "
                       f"{lc['p50']:.2f}/{lc['p99']:.2f}/{lc['max']:.2f} | "
                       f"{v['period_ms']['max']:.1f} |")
        out.append("")
    else:
        keep = {k: v for k, v in f.items() if k not in ("flight",)}
        if "flight" in f:
            fl = f["flight"]
            keep["flight"] = {k: fl[k] for k in ("steps", "sent", "levels", "offboard_left",
                                                   "frames_target_lost", "non_finite_commands")
                              if k in fl}
        if keep:
            out.append("```")
            out.append(_compact(keep))
            out.append("```")
            out.append("")
    return out


def _compact(d: Any, indent: int = 0) -> str:
    pad = "  " * indent
    if isinstance(d, dict):
        parts = []
        for k, v in d.items():
            if isinstance(v, dict) and v and any(isinstance(x, dict | list) for x in v.values()):
                parts.append(f"{pad}{k}:\n{_compact(v, indent + 1)}")
            else:
                parts.append(f"{pad}{k}: {_fmt(v)}")
        return "\n".join(parts)
    return pad + _fmt(d)


def _fmt(v: Any) -> str:
    if isinstance(v, float):
        return f"{v:.4g}"
    if isinstance(v, dict):
        return "{" + ", ".join(f"{k}: {_fmt(x)}" for k, x in v.items()) + "}"
    if isinstance(v, list | tuple):
        s = "[" + ", ".join(_fmt(x) for x in v[:12]) + (", ..." if len(v) > 12 else "") + "]"
        return s
    return str(v)
