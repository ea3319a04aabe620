"""``kill -9`` of the companion at random moments of a realtime flight, repeated: every log must
open and replay (commands identical) up to its last complete chunk. Data lost = time from the
last recovered message to the kill (the unfinished chunk; ``logging.flush_interval_s`` closes
one every second).

One realtime emulator runs throughout; each companion is started on the same port, flies for
a random 1.5-8 s after it is ready, and is killed with SIGKILL.
"""

from __future__ import annotations

import os
import random
import signal
import subprocess
import time
from pathlib import Path
from typing import Any

from bench.reliab.common import PAPER, ROOT, ProbeResult, children_cpu_s, load_avg
from companion.flight import demo_commands
from companion.log.reader import LogReader
from companion.replay import replay


def run_kill9(out: Path, kills: int = 20, seed: int = 9, replay_logs: bool = True,
              min_s: float = 1.5, max_s: float = 8.0) -> ProbeResult:
    t_w, c0 = time.monotonic(), children_cpu_s()
    load0 = load_avg()
    rng = random.Random(seed)
    out.mkdir(parents=True, exist_ok=True)
    sim_cmd, comp_cmd = demo_commands(PAPER, "paper", 3600.0, out, [], [])
    sim_cmd.remove("--lockstep")
    comp_cmd[comp_cmd.index('control.time_source="autopilot"')] = 'control.time_source="receipt"'
    comp_cmd[comp_cmd.index("logging.block_on_backlog=true")] = "logging.block_on_backlog=false"
    comp_cmd[comp_cmd.index('logging.timestamps="source"')] = 'logging.timestamps="receipt"'
    i_log, i_ready = comp_cmd.index("--log") + 1, comp_cmd.index("--ready-file") + 1
    env = dict(os.environ, PYTHONUNBUFFERED="1", PYTHONPATH=str(ROOT))
    runs: list[dict[str, Any]] = []
    sim: subprocess.Popen[bytes] | None = None
    sim_log = open(out / "sim.log", "w")  # noqa: SIM115
    try:
        # the vehicle runs throughout (realtime: it does not wait for anyone)
        sim = subprocess.Popen(sim_cmd, stdout=sim_log, stderr=subprocess.STDOUT, env=env)
        for k in range(kills):
            log = out / f"flight-{k:02d}.mcap"
            ready = out / f".ready-{k:02d}"
            cmd = list(comp_cmd)
            cmd[i_log], cmd[i_ready] = str(log), str(ready)
            with open(out / f"companion-{k:02d}.log", "w") as clog:
                comp = subprocess.Popen(cmd, stdout=clog, stderr=subprocess.STDOUT, env=env)
            t0 = time.monotonic()
            while not ready.exists() and comp.poll() is None and time.monotonic() - t0 < 300:
                time.sleep(0.05)
            wait = rng.uniform(min_s, max_s)
            time.sleep(wait)
            alive = comp.poll() is None
            kill_ns = time.monotonic_ns()
            comp.send_signal(signal.SIGKILL)
            comp.wait()
            runs.append({"log": log, "kill_ns": kill_ns, "after_ready_s": wait,
                         "alive_at_kill": alive})
    finally:
        if sim is not None:
            sim.terminate()
            try:
                sim.wait(timeout=20)
            except subprocess.TimeoutExpired:
                sim.kill()
        sim_log.close()
    rows = [check_log(r["log"], r["kill_ns"], out if replay_logs else None) | {
        "after_ready_s": r["after_ready_s"], "alive_at_kill": r["alive_at_kill"]} for r in runs]
    opened = sum(r["opened"] for r in rows)
    replayed = sum(bool(r.get("replay_identical")) for r in rows)
    losses = [r["lost_s"] for r in rows if r["lost_s"] is not None]
    ok = opened == kills and all(r["alive_at_kill"] for r in rows) and (
        not replay_logs or replayed == kills)
    return ProbeResult(
        probe="kill -9 (realtime flight)",
        inputs=f"{kills} kills, 1.5-8 s after start (seed {seed})",
        result=(f"{opened}/{kills} logs open, {replayed}/{kills} replay identically up to "
                f"their last chunk" + ("" if replay_logs else " (replay not run)")),
        passed=ok,
        data_lost=(f"last {min(losses):.2f}-{max(losses):.2f} s before the kill "
                   f"(median {sorted(losses)[len(losses) // 2]:.2f} s)" if losses else "-"),
        figures={"runs": rows, "load_before": load0, "load_after": load_avg()},
        wall_s=time.monotonic() - t_w,
        cpu_s=children_cpu_s() - c0,
    )


def check_log(log: Path, kill_ns: int, replay_dir: Path | None) -> dict[str, Any]:
    row: dict[str, Any] = {"log": log.name, "opened": False, "lost_s": None}
    try:
        with LogReader(log) as r:
            rec = r.recovery
            steps = sum(1 for _ in r.messages(topics=["/control/step"], decode=False))
        row.update(opened=True, messages=rec.messages, truncated=rec.truncated, steps=steps,
                   bytes=rec.bytes_total, stop_reason=rec.stop_reason,
                   lost_s=None if rec.last_log_time_ns is None
                   else (kill_ns - rec.last_log_time_ns) * 1e-9)
    except Exception as e:  # a log that does not open is the failure this probe looks for
        row["error"] = repr(e)
        return row
    if replay_dir is not None and steps > 0:
        try:
            s = replay(log, replay_dir / f"replay-{log.stem}.mcap").summary()
            row.update(replay_identical=bool(s["identical"]),
                       replay_compared=s["commands_compared"],
                       frames_missing=s["frames_missing"])
        except Exception as e:
            row["replay_error"] = repr(e)
    elif steps == 0:
        row["replay_identical"] = True  # nothing to replay: killed before the first step
    return row


if __name__ == "__main__":
    import argparse
    import json

    ap = argparse.ArgumentParser()
    ap.add_argument("--kills", type=int, default=20)
    ap.add_argument("--out", type=Path, default=Path("out/reliability/kill9"))
    a = ap.parse_args()
    print(json.dumps(run_kill9(a.out, a.kills).to_json(), indent=2, default=str))
