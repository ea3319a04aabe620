"""What the live view costs the companion (issue #14 item 4).

    python bench/live.py [--duration 30] [--repeat 2] [--json]

1. Writer level, in this process: the messages of a recorded flight (``--log``, else the one
   flown in step 2's first run) are written again through ``McapLogger`` three ways: no live
   view; live view with no client; live view with one client subscribed to every channel (the
   client is another process, so its CPU is not counted). CPU from ``getrusage(RUSAGE_SELF)``
   (every thread: writer, live publisher, the SDK's server threads) per control step.
2. Flight level: ``companion demo`` flights (lockstep, separate processes) with the live view
   off, on without a client, and on with a client; the companion process's CPU (utime + stime
   from /proc, sampled every 50 ms until it exits) per control step, and the message rates
   the client saw (per simulated second: at lockstep speed the wall rates are higher).

The control loop never calls the live view (the MCAP writer thread feeds it), so its cost
shows as CPU of other threads, not as latency of a step. Wall figures are noisy on a loaded
machine: ``uptime`` is printed.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import resource
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from companion.config import DEFAULT_CONFIG  # noqa: E402
from companion.flight import free_port, run_demo  # noqa: E402
from companion.log.live import LiveServer  # noqa: E402
from companion.log.reader import LogReader  # noqa: E402
from companion.log.writer import McapLogger  # noqa: E402

TICK_S = 1.0 / os.sysconf("SC_CLK_TCK")


def _cpu_s() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def _proc_cpu_s(pid: int) -> float | None:
    try:
        f = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return None
    return (int(f[11]) + int(f[12])) * TICK_S  # utime, stime (fields 14, 15)


def _client_proc(url: str, until_closed: bool, seconds: float) -> subprocess.Popen[str]:
    args = [sys.executable, __file__, "--client", url, "--client-seconds", str(seconds)]
    if until_closed:
        args.append("--until-closed")
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    return subprocess.Popen(args, stdout=subprocess.PIPE, text=True, env=env)


def _client_main(url: str, seconds: float, until_closed: bool) -> int:
    from tests.foxglove_ws import capture

    cap = asyncio.run(
        capture(url, None, lambda c: False, timeout_s=seconds, connect_timeout_s=300.0)
    )
    out: dict[str, Any] = {
        "counts": {t: len(v) for t, v in sorted(cap.messages.items())},
        "refused_subscriptions": cap.refused,
        "bytes": sum(len(p) for v in cap.messages.values() for _, _, p in v),
    }
    print(json.dumps(out))
    return 0


def _writer_pass(recs: list[Any], mode: str, path: Path, speed: float) -> dict[str, Any]:
    """One paced pass of ``recs`` through a McapLogger with the live view ``mode``."""
    live = None if mode == "off" else LiveServer("127.0.0.1", 0).start()
    client = None
    lg = McapLogger(path, queue_size=1 << 16)
    lg.observer = live
    with lg:
        if live is not None and mode == "on-client":
            # advertise every topic first (one message each), then let the client subscribe
            first = {r[0]: r for r in reversed(recs)}
            for topic, schema, t, raw in first.values():
                lg.log(topic, t, raw, schema=schema)
            while len(live._channels) < len(first):
                time.sleep(0.01)
            client = _client_proc(live.url, until_closed=True, seconds=600.0)
            while live.stats.subscriptions < len(first):
                time.sleep(0.05)
        t_first = recs[0][2]
        c0, w0 = _cpu_s(), time.perf_counter()
        for topic, schema, t, raw in recs:
            lag = (t - t_first) * 1e-9 / speed - (time.perf_counter() - w0)
            if lag > 0.0005:
                time.sleep(lag)  # paced like a flight at `speed` x real time
            lg.log(topic, t, raw, schema=schema)
        while lg.stats.written + lg.stats.dropped < lg.stats.enqueued:
            time.sleep(0.005)
        if live is not None:
            while live.stats.published + live.stats.dropped < live.stats.queued:
                time.sleep(0.005)
        c1, w1 = _cpu_s(), time.perf_counter()
    res: dict[str, Any] = {"cpu_s": c1 - c0, "wall_s": w1 - w0}
    if live is not None:
        s = live.stats
        res.update(published=s.published, dropped=s.dropped, unsubscribed=s.unsubscribed)
        live.close()
    if client is not None:
        text, _ = client.communicate(timeout=60)
        got = json.loads(text.strip().splitlines()[-1])
        res["client_received"] = sum(got["counts"].values())
        res["client_refused_subscriptions"] = got["refused_subscriptions"]
    return res


def writer_level(log_path: Path, speed: float, repeat: int) -> dict[str, Any]:
    """CPU per control step of re-writing ``log_path`` through McapLogger three ways, paced at
    ``speed`` x real time, the modes interleaved ``repeat`` times."""
    with LogReader(log_path) as r:
        recs = [(m.topic, m.schema_name, m.log_time_ns, m.raw) for m in r.messages(decode=False)]
    steps = sum(1 for t, *_ in recs if t == "/control/step")
    out: dict[str, Any] = {"messages": len(recs), "steps": steps, "speed": speed}
    with tempfile.TemporaryDirectory() as d:
        for i in range(repeat):
            for mode in ("off", "on-no-client", "on-client"):
                res = _writer_pass(recs, mode, Path(d) / f"{mode}-{i}.mcap", speed)
                res["cpu_ms_per_step"] = res["cpu_s"] * 1e3 / max(steps, 1)
                out.setdefault(mode, []).append(res)
                print(f"writer {mode} #{i}: {json.dumps(res)}", file=sys.stderr, flush=True)
    return out


def flight_level(duration_s: float, out_dir: Path, mode: str) -> dict[str, Any]:
    port = free_port(socket.SOCK_STREAM)
    last: dict[str, float] = {}

    def monitor(p: subprocess.Popen[bytes]) -> None:
        c = _proc_cpu_s(p.pid)
        if c is not None:
            last.setdefault("start_cpu_s", c)  # ready and waiting: start-up excluded
            last["cpu_s"] = c

    client = None
    if mode == "on-client":
        client = _client_proc(f"ws://127.0.0.1:{port}", until_closed=True, seconds=3600.0)
    rep = run_demo(
        DEFAULT_CONFIG,
        "paper",
        duration_s,
        out_dir,
        [f"live.port={port}"],
        [],
        plots=False,
        monitor=monitor,
        live=mode != "off",
    )
    res: dict[str, Any] = {
        "steps": rep["steps"],
        "wall_s": rep["wall_time_s"],
        "real_time_factor": rep["real_time_factor"],
        "latency": rep.get("latency"),
        "companion_cpu_ms_per_step": (last.get("cpu_s", float("nan")) - last["start_cpu_s"])
        * 1e3
        / rep["steps"],
    }
    if client is not None:
        text, _ = client.communicate(timeout=120)
        got = json.loads(text.strip().splitlines()[-1])
        res["client_rates_per_sim_s"] = {t: n / duration_s for t, n in got["counts"].items()}
        res["client_mb_per_sim_s"] = got["bytes"] / duration_s / 1e6
        res["client_refused_subscriptions"] = got["refused_subscriptions"]
    return res


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=30.0, help="simulated s per flight")
    ap.add_argument("--repeat", type=int, default=2, help="flights per mode")
    ap.add_argument("--log", type=Path, default=None, help="flight log for the writer level")
    ap.add_argument("--writer-speed", type=float, default=2.0, help="x real time")
    ap.add_argument("--writer-repeat", type=int, default=3)
    ap.add_argument(
        "--flights",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="fly (part 2); --no-flights needs --log",
    )
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--client", default=None, help=argparse.SUPPRESS)
    ap.add_argument("--client-seconds", type=float, default=60.0, help=argparse.SUPPRESS)
    ap.add_argument("--until-closed", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.client:
        return _client_main(args.client, args.client_seconds, args.until_closed)
    load = os.getloadavg()
    result: dict[str, Any] = {"load_avg": load, "flights": {}}
    with tempfile.TemporaryDirectory() as d:
        for i in range(args.repeat if args.flights else 0):
            for mode in ("off", "on-no-client", "on-client"):
                r = flight_level(args.duration, Path(d) / f"{mode}-{i}", mode)
                result["flights"].setdefault(mode, []).append(r)
                print(f"flight {mode} #{i}: {json.dumps(r)}", file=sys.stderr, flush=True)
        log_path = args.log or Path(d) / "off-0" / "flight.mcap"
        result["writer"] = writer_level(log_path, args.writer_speed, args.writer_repeat)
    result["load_avg_end"] = os.getloadavg()
    if args.json:
        print(json.dumps(result, indent=2))
        return 0
    print(f"load average at start {load[0]:.1f}, at end {result['load_avg_end'][0]:.1f}")
    w = result["writer"]
    print(f"writer level ({w['messages']} messages, {w['steps']} steps, {w['speed']}x real time):")
    for mode in ("off", "on-no-client", "on-client"):
        runs = w[mode]
        cpus = ", ".join(f"{r['cpu_ms_per_step']:.3f}" for r in runs)
        extra = {
            k: runs[-1][k] for k in ("published", "dropped", "client_received") if k in runs[-1]
        }
        print(f"  {mode:<13} CPU/step ms: {cpus}  {json.dumps(extra)}")
    print("flight level (companion CPU per step, ms):")
    for mode, runs in result["flights"].items():
        cpu = [f"{r['companion_cpu_ms_per_step']:.2f}" for r in runs]
        rtf = [f"{r['real_time_factor']:.1f}x" for r in runs]
        lat = [
            f"{(r['latency'] or {}).get('frame_to_command_median_ms', float('nan')):.1f}"
            for r in runs
        ]
        print(
            f"  {mode:<13} {', '.join(cpu)}  (speed {', '.join(rtf)}; frame -> command "
            f"median ms {', '.join(lat)})"
        )
    for r in result["flights"].get("on-client", []):
        rates = r["client_rates_per_sim_s"]
        print(
            f"  client saw {sum(rates.values()):.0f} msg per simulated s "
            f"({r['client_mb_per_sim_s']:.1f} MB): "
            + ", ".join(f"{t} {v:.1f}" for t, v in rates.items() if v >= 1.0)
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
