"""Replay speed against the flight's own duration (issue: offline replay).

    python bench/replay.py [LOG.mcap] [--duration 60] [--json]

Without a log it first flies the paper scenario for ``--duration`` simulated seconds (lockstep,
the config's frame encoding, PNG by default; ``--set logging.image_encoding=\"raw\"`` for raw)
and replays that. Prints the replay's wall time, the flight's simulated time, the
ratio (target >= 20x real time) and the per-step cost breakdown: reading and decoding the log
(frames decoded), perception, and the controller.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from companion.commands.demo import run_demo  # noqa: E402
from companion.config import DEFAULT_CONFIG  # noqa: E402
from companion.log.reader import LogReader  # noqa: E402
from companion.replay import replay  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("log", type=Path, nargs="?")
    ap.add_argument("--duration", type=float, default=60.0)
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="config override for the flight (when no LOG is given)")
    args = ap.parse_args()
    tmp = Path(tempfile.mkdtemp(prefix="bench-replay-"))
    log = args.log
    if log is None:
        run_demo(DEFAULT_CONFIG, "paper", args.duration, tmp, args.set, [], plots=False)
        log = tmp / "flight.mcap"
    # reading + decoding alone (one pass, as replay reads; frames decoded), to split the cost
    t0 = time.perf_counter()
    n_frames = 0
    steps = []
    with LogReader(log, verify=False) as r:
        for m in r.messages():
            if m.topic == "/camera/image":
                n_frames += m.image is not None
            elif m.topic == "/control/step" and m.data:
                steps.append(m.data)
    t_read = time.perf_counter() - t0
    t0 = time.perf_counter()
    res = replay(log, tmp / "replay.mcap", timer=time.perf_counter)
    t_replay = time.perf_counter() - t0
    sim_s = (steps[-1]["t_s"] - steps[0]["t_s"]) if len(steps) > 1 else 0.0
    with LogReader(tmp / "replay.mcap") as r:
        timings = [m.data.get("timings_ms") or {} for m in r.messages(topics=["/control/step"])]
    stage = {k: float(np.median([t[k] for t in timings if k in t]))
             for k in ("detect", "moments", "solve", "command")}
    out = {
        "steps": res.steps,
        "identical": res.summary()["identical"],
        "flight_sim_time_s": sim_s,
        "replay_wall_s": t_replay,
        "speed_vs_real_time": sim_s / t_replay if t_replay > 0 else None,
        "read_decode_wall_s": t_read,
        "read_decode_ms_per_frame": 1e3 * t_read / max(n_frames, 1),
        "pipeline_stage_median_ms": stage,
        "target_speed": 20.0,
    }
    if args.json:
        print(json.dumps(out, indent=2))
    else:
        print(f"replayed {out['steps']} steps ({sim_s:.1f} s of flight) in {t_replay:.1f} s: "
              f"{out['speed_vs_real_time']:.1f}x real time (target 20x); identical: "
              f"{out['identical']}")
        print(f"  reading + decoding the log alone (one thread): "
              f"{out['read_decode_ms_per_frame']:.2f} ms/frame")
        print("  pipeline stages (median ms): " +
              ", ".join(f"{k} {v:.2f}" for k, v in stage.items()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
