"""``companion demo``: the emulator and the companion as two processes on loopback, in lockstep.

They meet only on sockets (docs/wire.md), exactly as the companion meets a real PX4. The demo
picks free ports, starts ``python -m sim_bridge --lockstep`` and ``python -m companion run``,
waits for the flight, then scores it from the log (ground truth recorded on ``/truth``) into
``DIR/report.json`` and the report figures.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import socket
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from companion import CompanionError
from companion.config import DEFAULT_CONFIG, load_config, read_document
from companion.report.files import build_report

log = logging.getLogger(__name__)


def add_parser(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = sub.add_parser("demo", help="fly a scenario: emulator + companion in lockstep")
    p.add_argument("--scenario", default="paper",
                   help="[sim.scenarios.NAME] of the config: paper, edge, yaw-offset, ...")
    p.add_argument("--duration", type=float, default=None,
                   help="simulated seconds (default: sim.duration_s, one AGV period)")
    p.add_argument("--no-visibility", action="store_true",
                   help="switch the RMPC's visibility constraints off (for comparison)")
    p.add_argument("--config", type=Path, default=DEFAULT_CONFIG)
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="companion config override (repeatable)")
    p.add_argument("--inject-fault", action="append", default=[], metavar="KIND:T0:T1")
    p.add_argument("--out", type=Path, default=None, help="output dir (default out/SCENARIO)")
    p.add_argument("--no-plots", action="store_true", help="report.json only")
    p.add_argument("--live", action="store_true",
                   help="serve the flight live to Foxglove (ws://live.host:live.port)")
    p.set_defaults(func=_run)


def free_port(kind: int = socket.SOCK_DGRAM) -> int:
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def demo_commands(config: Path, scenario: str, duration_s: float, out: Path,
                  overrides: list[str], faults: list[str],
                  live: bool = False) -> tuple[list[str], list[str]]:
    """The two command lines (emulator, companion) of a lockstep flight on free ports."""
    p_sim, p_comp, p_gcs, p_gcs_remote, p_agv, p_truth = (free_port() for _ in range(6))
    p_frame = free_port(socket.SOCK_STREAM)
    sim = [
        sys.executable, "-m", "sim_bridge", "--config", str(config), "--scenario", scenario,
        "--lockstep", "--duration", f"{duration_s}", "--bind", "127.0.0.1",
        "--offboard-port", str(p_sim), "--offboard-remote", f"127.0.0.1:{p_comp}",
        "--gcs-port", str(p_gcs), "--gcs-remote", f"127.0.0.1:{p_gcs_remote}",
        "--agv-port", str(p_agv), "--frame-port", str(p_frame),
        "--truth-remote", f"127.0.0.1:{p_truth}",
    ]
    comp = [
        sys.executable, "-m", "companion", "run", "--config", str(config),
        "--set", 'control.time_source="autopilot"', "--set", "offboard.arm=true",
        "--set", "offboard.reengage=true", "--set", "logging.block_on_backlog=true",
        "--set", 'logging.timestamps="source"',
        *[a for o in overrides for a in ("--set", o)],
        *[a for f in faults for a in ("--inject-fault", f)],
        "--mavlink", f"udpin:127.0.0.1:{p_comp}", "--camera", f"tcp://127.0.0.1:{p_frame}",
        "--log", str(out / "flight.mcap"), "--truth-port", str(p_truth),
        "--duration", f"{duration_s}", "--ready-file", str(out / ".companion-ready"),
        "--progress-file", str(out / ".companion-progress"),
        *(["--live"] if live else []),
    ]
    return sim, comp


def run_demo(config: Path, scenario: str, duration_s: float | None, out: Path,
             overrides: list[str], faults: list[str], plots: bool = True,
             monitor: Callable[[subprocess.Popen[bytes]], None] | None = None,
             sim_config: Path | None = None, live: bool = False,
             show_progress: bool = False) -> dict[str, Any]:
    """Fly a scenario; ``monitor(companion_process)`` is called every 50 ms during the flight
    (benchmarks sample its memory); ``sim_config`` gives the emulator a different file (e.g.
    with fault injection) than the companion's ``config``; with ``live`` the companion serves
    its channels to Foxglove while it flies (``[live]`` config)."""
    cfg = load_config(config, overrides)  # fail early, in this process, on a bad config
    if duration_s is None:
        # the emulator's own setting, through the file's base chain
        duration_s = float(read_document(config).get("sim", {}).get("duration_s", 251.0))
    out.mkdir(parents=True, exist_ok=True)
    sim_cmd, comp_cmd = demo_commands(config, scenario, duration_s, out, overrides, faults,
                                      live=live)
    if sim_config is not None:
        sim_cmd[sim_cmd.index("--config") + 1] = str(sim_config)
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    t0 = time.monotonic()
    with open(out / "companion.log", "w") as comp_log, open(out / "sim.log", "w") as sim_log:
        ready = out / ".companion-ready"
        ready.unlink(missing_ok=True)
        comp = subprocess.Popen(comp_cmd, stdout=comp_log, stderr=subprocess.STDOUT, env=env)
        # The vehicle starts talking only once the companion listens (first start compiles
        # the solver: allow for it).
        while not ready.exists():
            if comp.poll() is not None or time.monotonic() - t0 > 300.0:
                comp.kill()
                raise CompanionError(f"demo: the companion did not start (see {out}/companion.log)")
            time.sleep(0.05)
        t0 = time.monotonic()
        progress_file = out / ".companion-progress"
        progress_file.unlink(missing_ok=True)
        bar = bar_for(duration_s, show_progress)
        sim = subprocess.Popen(sim_cmd, stdout=sim_log, stderr=subprocess.STDOUT, env=env)
        budget = 120.0 + 4.0 * duration_s  # lockstep: a loaded machine runs below real time
        sim_rc = comp_rc = None
        wall = 0.0
        try:
            while time.monotonic() - t0 < budget:
                sim_rc, comp_rc = sim.poll(), comp.poll()
                if sim_rc is not None:
                    wall = time.monotonic() - t0
                    comp_rc = comp.wait(timeout=30.0)
                    break
                if comp_rc is not None:  # the companion died: no point flying on
                    sim.terminate()
                    sim_rc = sim.wait(timeout=10.0)
                    break
                if monitor is not None:
                    monitor(comp)
                if bar is not None:
                    elapsed = read_progress(progress_file)[0]
                    bar.update(max(round(elapsed, 1) - bar.n, 0.0))
                time.sleep(0.05)
            else:
                raise CompanionError(f"demo: flight did not finish within {budget:.0f} s "
                                     f"(see {out}/sim.log, {out}/companion.log)")
        except subprocess.TimeoutExpired:
            raise CompanionError(f"demo: a process did not exit (see {out}/sim.log, "
                                 f"{out}/companion.log)") from None
        finally:
            if bar is not None:
                bar.close()
            for p in (sim, comp):
                if p.poll() is None:
                    p.kill()
                    p.wait()
    if sim_rc != 0 or comp_rc != 0:
        raise CompanionError(f"demo: emulator exited {sim_rc}, companion exited {comp_rc} "
                             f"(see {out}/sim.log, {out}/companion.log)")
    rbar, cb = (None, None)
    if show_progress:
        from companion.progress import step_callback

        rbar, cb = step_callback("report", unit="msg")
    try:
        report = build_report(out / "flight.mcap", cfg, out, plots=plots, progress=cb)
    finally:
        if rbar is not None:
            rbar.close()
    report["wall_time_s"] = wall
    report["real_time_factor"] = report["sim_time_s"] / wall if wall > 0 else None
    report["companion_cpu_ms_per_step"] = read_progress(progress_file)[2]
    report["scenario"] = scenario
    report["overrides"] = overrides
    (out / "report.json").write_text(json.dumps(report, indent=2))
    return report


def bar_for(duration_s: float, show: bool) -> Any:
    if not show:
        return None
    from companion.progress import bar

    return bar(round(duration_s, 1), "demo", unit="sim s",
               bar_format="{l_bar}{bar}| {n:.1f}/{total:.1f} sim s [{elapsed}<{remaining}]")


def read_progress(path: Path) -> tuple[float, int, float | None]:
    """(simulated seconds since the first frame, steps, CPU ms per step at the end) from the
    companion's ``--progress-file`` (zeros while it has none)."""
    try:
        parts = path.read_text().split()
        return float(parts[0]), int(parts[1]), float(parts[2]) if len(parts) > 2 else None
    except (OSError, ValueError, IndexError):
        return 0.0, 0, None


def _run(args: argparse.Namespace) -> int:
    overrides = list(args.set)
    if args.no_visibility:
        overrides.append("rmpc.enable_visibility=false")
    out = args.out or Path("out") / (args.scenario + ("-novis" if args.no_visibility else ""))
    if args.live:
        lc = load_config(args.config, overrides).live
        where = f"ws://{lc.host}:{lc.port}" if lc.port else f"a free port ({out}/companion.log)"
        print(f"live view: {where} (Foxglove: Open connection, Foxglove WebSocket; layout "
              "foxglove/layout.json)", flush=True)
    rep = run_demo(args.config, args.scenario, args.duration, out, overrides,
                   args.inject_fault, plots=not args.no_plots, live=args.live,
                   show_progress=True)
    vis = rep["visibility"]
    trk = rep["tracking"]
    print(f"scenario {args.scenario}: {rep['sim_time_s']:.1f} s simulated in "
          f"{rep['wall_time_s']:.1f} s ({rep['real_time_factor']:.1f}x real time)")
    print(f"visibility: max |u| {vis['max_abs_u_px']:.1f} px, max |n| {vis['max_abs_n_px']:.1f}"
          f" px (bound {vis['bound_px']:.0f}), frames target lost {vis['frames_target_lost']}")
    eng = rep.get("engaged") or {}
    if eng.get("t_engaged_s") is not None:
        print(f"after OFFBOARD (+1 s, controller {rep.get('controller')}): worst corner "
              f"{eng['corner_max_px']:.1f} px, {eng['frames_outside_bound']} frames out, "
              f"recovery {100 * (eng['recovery_fraction'] or 0):.1f} %, "
              f"{eng['fallbacks']} fallbacks")
    print(f"tracking: rms s_e {trk['rms_se']}, final s_e {trk['final_se']}")
    print(f"solver: {rep['solver']}")
    cpu = rep.get("companion_cpu_ms_per_step")
    print(f"companion CPU per step: {'-' if cpu is None else f'{cpu:.2f} ms'} (getrusage: "
          f"all its threads, first frame to exit)")
    print(f"report: {out / 'report.json'}")
    return 0
