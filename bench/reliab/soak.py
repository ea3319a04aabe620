"""Soak: hours of simulated flight in lockstep (the slowest, 20 Hz path), companion memory
growth per hour and command-rate steadiness.

RSS of the companion is sampled every ``sample_s`` of wall time (``/proc``); each sample is
mapped to simulated time through the log's control steps (same monotonic clock). Growth is the
least-squares slope of RSS over simulated time after a warm-up, per simulated hour (and per
wall hour). Command rate: SET_ATTITUDE_TARGET sent per simulated 10 s window (lockstep: should
be exactly 200), and the wall-clock gaps between consecutive steps.
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

import numpy as np

from bench.reliab.common import (
    ProbeResult,
    children_cpu_s,
    flight,
    load_avg,
    proc_cpu_s,
    rss_mb,
    wait_flight,
)
from companion.log.reader import LogReader

# The default log (lossless perception crops, a 5 Hz JPEG preview): ~3 GB per simulated hour.
SOAK_OVERRIDES: list[str] = []


def run_soak(out: Path, duration_s: float, sample_s: float = 5.0,
             warmup_s: float = 600.0) -> ProbeResult:
    t0, c0 = time.monotonic(), children_cpu_s()
    samples: list[tuple[int, float, float | None]] = []  # (monotonic ns, rss MB, cpu s)
    loads: list[str] = [load_avg()]
    rss_file = out / "rss.jsonl"
    out.mkdir(parents=True, exist_ok=True)
    with flight(out, duration_s=duration_s, overrides=SOAK_OVERRIDES) as f, \
            rss_file.open("w") as fh:
        last = [0.0]

        def sample() -> None:
            now = time.monotonic()
            if now - last[0] < sample_s:
                return
            last[0] = now
            r = rss_mb(f.comp.pid)
            if r is None:
                return
            c = proc_cpu_s(f.comp.pid)
            samples.append((time.monotonic_ns(), r, c))
            fh.write(json.dumps({"t_ns": samples[-1][0], "rss_mb": r, "cpu_s": c}) + "\n")
            fh.flush()
            if len(samples) % 60 == 0:
                loads.append(load_avg())

        sim_rc, comp_rc = wait_flight(f, 120.0 + 6.0 * duration_s, every=sample, period_s=0.5)
    wall = time.monotonic() - t0
    figs = soak_figures(out / "flight.mcap", samples, warmup_s)
    figs.update({"sim_rc": sim_rc, "comp_rc": comp_rc, "loads": loads})
    ok = (sim_rc == 0 and comp_rc == 0 and figs["bad_commands"] == 0
          and figs["sim_s"] >= 0.95 * duration_s)
    res = ProbeResult(
        probe="soak (lockstep, 20 Hz)",
        inputs=f"{figs['sim_s'] / 3600:.2f} h simulated, {figs['steps']} steps, "
               f"{len(samples)} RSS samples",
        result=_result(figs),
        passed=ok,
        data_lost=f"{figs['steps'] - figs['sent']} steps without a command",
        bad_commands=figs["bad_commands"],
        figures=figs,
        wall_s=wall,
        cpu_s=children_cpu_s() - c0,
    )
    (out / "soak.json").write_text(json.dumps(res.to_json(), indent=2, default=str))
    return res


def soak_partial(out: Path, warmup_s: float = 600.0) -> ProbeResult:
    """The figures of a soak still running in ``out`` (its log read up to the last chunk)."""
    samples = [(int(r["t_ns"]), float(r["rss_mb"]), r.get("cpu_s")) for r in
               map(json.loads, (out / "rss.jsonl").read_text().splitlines())]
    figs = soak_figures(out / "flight.mcap", samples, warmup_s)
    return ProbeResult(
        probe="soak (lockstep, 20 Hz) - PARTIAL, flight still running",
        inputs=f"{figs['sim_s'] / 3600:.2f} h simulated so far, {figs['steps']} steps, "
               f"{len(samples)} RSS samples",
        result=_result(figs),
        passed=figs["bad_commands"] == 0 and figs["steps"] == figs["sent"],
        data_lost=f"{figs['steps'] - figs['sent']} steps without a command",
        bad_commands=figs["bad_commands"], figures=figs)


def _result(figs: dict[str, Any]) -> str:
    """The probe's one-line result from :func:`soak_figures`."""
    return (f"RSS {figs['rss_start_mb']:.0f} -> {figs['rss_end_mb']:.0f} MB, "
            f"growth {figs['growth_mb_per_sim_h']:+.1f} MB/h simulated "
            f"({figs['growth_mb_per_wall_h']:+.1f} MB/h wall); commands per 10 s "
            f"min {figs['cmd_per_10s_min']} max {figs['cmd_per_10s_max']}; "
            f"{figs['real_time_factor']:.1f}x real time")


def soak_figures(log: Path, samples: list[tuple[int, float, float | None]],
                 warmup_s: float) -> dict[str, Any]:
    import math

    t_ns: list[int] = []
    t_sim: list[float] = []
    sent = 0
    bad = 0
    sent_sim: list[float] = []
    with LogReader(log) as r:
        for m in r.messages(topics=["/control/step", "/mavlink/out/SET_ATTITUDE_TARGET"]):
            d = m.data or {}
            if m.topic == "/control/step":
                t_ns.append(m.log_time_ns)
                t_sim.append(float(d["t_s"]))
                if d.get("sent"):
                    sent += 1
                    sent_sim.append(float(d["t_s"]))
            else:
                f = d["fields"]
                if not all(math.isfinite(v) for v in [*f["q"], f["thrust"]]):
                    bad += 1
    tn = np.asarray(t_ns, dtype=float)
    ts = np.asarray(t_sim)
    ts0 = ts[0] if ts.size else 0.0
    out: dict[str, Any] = {"steps": len(t_sim), "sent": sent, "bad_commands": bad,
                           "sim_s": float(ts[-1] - ts0) if ts.size else 0.0}
    wall_span = float(tn[-1] - tn[0]) * 1e-9 if tn.size > 1 else 0.0
    out["real_time_factor"] = out["sim_s"] / wall_span if wall_span > 0 else 0.0
    # command rate per simulated 10 s window
    if sent_sim:
        ss = np.asarray(sent_sim) - ts0
        nwin = int(out["sim_s"] // 10.0)
        counts = np.bincount(((ss + 1e-6) // 10.0).astype(int), minlength=nwin)[:nwin]
        # the first window holds the start-up, the last may be partial
        c = counts[1:] if counts.size > 2 else counts
        out["cmd_per_10s_min"] = int(c.min()) if c.size else 0
        out["cmd_per_10s_max"] = int(c.max()) if c.size else 0
    else:
        out["cmd_per_10s_min"] = out["cmd_per_10s_max"] = 0
    if tn.size > 1:
        gaps_ms = np.diff(tn) * 1e-6
        out["step_gap_wall_ms"] = {q: float(np.percentile(gaps_ms, p)) for q, p in
                                   (("p50", 50), ("p99", 99), ("p999", 99.9))}
        out["step_gap_wall_ms"]["max"] = float(gaps_ms.max())
    # RSS vs simulated time
    rs = [(float(np.interp(t, tn, ts)) - ts0, r) for t, r, _ in samples
          if tn.size and tn[0] <= t <= tn[-1]]
    out["rss_samples"] = len(rs)
    if rs:
        x = np.asarray([a for a, _ in rs])
        y = np.asarray([b for _, b in rs])
        out["rss_start_mb"], out["rss_end_mb"], out["rss_max_mb"] = (
            float(y[0]), float(y[-1]), float(y.max()))
        keep = x >= min(warmup_s, 0.25 * x.max())
        if keep.sum() >= 3:
            slope = float(np.polyfit(x[keep], y[keep], 1)[0])
            out["growth_mb_per_sim_h"] = slope * 3600.0
            out["growth_mb_per_wall_h"] = slope * 3600.0 * out["real_time_factor"]
            hours = {}
            for h in range(int(x.max() // 3600) + 1):
                sel = (x >= h * 3600) & (x < (h + 1) * 3600)
                if sel.any():
                    hours[f"h{h}"] = {"first_mb": float(y[sel][0]), "last_mb": float(y[sel][-1])}
            out["rss_by_sim_hour"] = hours
        else:
            out["growth_mb_per_sim_h"] = out["growth_mb_per_wall_h"] = float("nan")
    else:
        out["rss_start_mb"] = out["rss_end_mb"] = out["rss_max_mb"] = float("nan")
        out["growth_mb_per_sim_h"] = out["growth_mb_per_wall_h"] = float("nan")
    return out


if __name__ == "__main__":
    import argparse

    ap = argparse.ArgumentParser(description="soak probe alone")
    ap.add_argument("--duration", type=float, default=7200.0)
    ap.add_argument("--out", type=Path, default=Path("out/reliability/soak"))
    a = ap.parse_args()
    res = run_soak(a.out, a.duration)
    print(json.dumps(res.to_json(), indent=2, default=str))
