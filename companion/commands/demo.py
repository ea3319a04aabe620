"""``companion demo``: the emulator and the companion as two processes on loopback, in lockstep.

They meet only on sockets (docs/reference/wire.md), exactly as the companion meets a real PX4. The
demo merges the config file and every ``--set`` override into ``DIR/config.toml`` (so an override
reaches both processes, ``sim.*`` keys the emulator and shared ``camera.*``/``target.*`` keys
both), has both programs validate it (``sim-bridge --check-config``; a key neither knows is
refused before anything flies), picks free ports, starts ``python -m sim_bridge --lockstep`` and
``python -m companion run`` on that file, waits for the flight, then scores it from the log
(ground truth recorded on ``/truth``) into ``DIR/report.json`` and the report figures.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import resource
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

from companion import CompanionError, ConfigError
from companion.config import DEFAULT_CONFIG, Config, config_from_dict, read_document
from companion.config_file import absolutize_paths, dump_toml, merged_document
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
                   help="config override for both processes, e.g. sim.agv.speed_scale=3 "
                        "(repeatable; a key neither program knows is refused)")
    p.add_argument("--inject-fault", action="append", default=[], metavar="KIND:T0:T1")
    p.add_argument("--out", type=Path, default=None, help="output dir (default out/SCENARIO)")
    p.add_argument("--no-plots", action="store_true", help="report.json only")
    p.add_argument("--live", action="store_true",
                   help="serve the flight live to Foxglove (ws://live.host:live.port)")
    p.set_defaults(func=_run)


def free_port(kind: int = socket.SOCK_DGRAM) -> int:
    return free_ports(1, kind)[0]


def free_ports(n: int, kind: int = socket.SOCK_DGRAM) -> list[int]:
    """``n`` distinct free loopback ports: every socket stays bound until all are chosen (the
    kernel picks ephemeral ports at random and may hand a just-closed one out again: picked one
    at a time, two of a flight's six ports coincide in ~1 flight of 2,000 (15 pairs of ~28,000
    ports), a campaign-sized risk).
    Another process may still take one before the flight binds it."""
    socks = [socket.socket(socket.AF_INET, kind) for _ in range(n)]
    try:
        for s in socks:
            s.bind(("127.0.0.1", 0))
        return [int(s.getsockname()[1]) for s in socks]
    finally:
        for s in socks:
            s.close()


def demo_commands(config: Path, scenario: str, duration_s: float, out: Path,
                  overrides: Sequence[str], faults: Sequence[str],
                  live: bool = False) -> tuple[list[str], list[str]]:
    """The two command lines (emulator, companion) of a lockstep flight on free ports, both
    reading ``config`` (the merged file); ``overrides`` go to the companion only (the demo's
    own lockstep settings)."""
    p_sim, p_comp, p_gcs, p_gcs_remote, p_agv, p_truth = free_ports(6)
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
        # lockstep: the emulator waits for every command, so the solve-time bound only has to
        # catch a solver that never returns: 1 s of the solver's own CPU time, so that a busy
        # machine (CI, a campaign beside it) never cuts a slow but finite solve (at load 8-15 a
        # 1 s wall bound did). A user's --set still wins.
        "--set", "rmpc.max_solve_time_s=1.0", "--set", 'rmpc.solve_time_clock="cpu"',
        # ... which then cuts only a solver that never returns: no stand-by solver process
        # (its ~0.7 s of CPU per flight adds up over a campaign or the test suite)
        "--set", "rmpc.solver_spare=false",
        *[a for o in overrides for a in ("--set", o)],
        *[a for f in faults for a in ("--inject-fault", f)],
        "--mavlink", f"udpin:127.0.0.1:{p_comp}", "--camera", f"tcp://127.0.0.1:{p_frame}",
        "--log", str(out / "flight.mcap"), "--truth-port", str(p_truth),
        "--duration", f"{duration_s}", "--ready-file", str(out / ".companion-ready"),
        "--progress-file", str(out / ".companion-progress"),
        *(["--live"] if live else []),
    ]
    return sim, comp


def write_merged_config(config: Path, overrides: Sequence[str], path: Path) -> dict[str, Any]:
    """``config`` (its base chain merged) with ``overrides`` applied, written to ``path`` as one
    self-contained TOML file (file paths made absolute); returns the document."""
    doc = merged_document(read_document(config), overrides)
    absolutize_paths(doc, config)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(f"# {config} with --set {' '.join(overrides) or '(none)'}\n"
                    + dump_toml(doc))
    return doc


def check_emulator_config(path: Path, scenario: str, env: Mapping[str, str]) -> None:
    """Have the emulator validate ``path`` (``sim-bridge --check-config``); raise
    :class:`ConfigError` with its message if it refuses."""
    r = subprocess.run([sys.executable, "-m", "sim_bridge", "--check-config", "--config",
                        str(path), "--scenario", scenario, "--log-level", "ERROR"],
                       capture_output=True, text=True, env=dict(env), timeout=120.0)
    if r.returncode != 0:
        lines = [ln for ln in (r.stderr + r.stdout).splitlines() if ln.strip()]
        msg = lines[-1] if lines else f"exit {r.returncode}"
        raise ConfigError(f"the emulator refuses the config: {msg.split(': ', 1)[-1]}")


def prepare_configs(config: Path, scenario: str, overrides: Sequence[str], out: Path,
                    env: Mapping[str, str], sim_config: Path | None = None,
                    ) -> tuple[Config, Path, Path, dict[str, Any]]:
    """Merge and validate the flight's config for both programs: ``(companion config,
    companion file, emulator file, emulator document)``. Raises :class:`ConfigError` naming
    the key either program refuses."""
    comp_path = out / "config.toml"
    doc = write_merged_config(config, overrides, comp_path)
    cfg = config_from_dict(doc, source=str(comp_path))  # the companion's validation
    sim_path, sim_doc = comp_path, doc
    if sim_config is not None:  # the emulator reads another file (plus the same overrides)
        sim_path = out / "sim-config.toml"
        sim_doc = write_merged_config(sim_config, overrides, sim_path)
    check_emulator_config(sim_path, scenario, env)
    return cfg, comp_path, sim_path, sim_doc


def run_demo(config: Path, scenario: str, duration_s: float | None, out: Path,
             overrides: Sequence[str], faults: Sequence[str], plots: bool = True,
             monitor: Callable[[subprocess.Popen[bytes]], None] | None = None,
             sim_config: Path | None = None, budget_s: float | None = None,
             live: bool = False, show_progress: bool = False) -> dict[str, Any]:
    """Fly a scenario; ``overrides`` reach both processes (``OUT/config.toml``).
    ``budget_s``: wall time allowed for the flight (default 120 s + 4 times the flight).
    ``monitor(companion_process)`` is called every 50 ms during the flight (benchmarks sample
    its memory); ``sim_config`` gives the emulator a different file (e.g. with fault
    injection) than the companion's ``config``, with the same overrides; with ``live`` the
    companion serves its channels to Foxglove while it flies (``[live]`` config)."""
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    out.mkdir(parents=True, exist_ok=True)
    # fail early, before anything starts, on a key either program refuses
    cfg, comp_path, sim_path, sim_doc = prepare_configs(config, scenario, overrides, out, env,
                                                        sim_config)
    if duration_s is None:
        duration_s = float(sim_doc.get("sim", {}).get("duration_s", 251.0))
    sim_cmd, comp_cmd = demo_commands(comp_path, scenario, duration_s, out, [], faults,
                                      live=live)
    sim_cmd[sim_cmd.index("--config") + 1] = str(sim_path)
    t0 = time.monotonic()
    with open(out / "companion.log", "w") as comp_log, open(out / "sim.log", "w") as sim_log:
        startup_s = 300.0 if budget_s is None else max(300.0, budget_s)
        ready = out / ".companion-ready"
        ready.unlink(missing_ok=True)
        comp = subprocess.Popen(comp_cmd, stdout=comp_log, stderr=subprocess.STDOUT, env=env)
        # The vehicle starts talking only once the companion listens (first start compiles
        # the solver: allow for it).
        while not ready.exists():
            if comp.poll() is not None or time.monotonic() - t0 > startup_s:
                comp.kill()
                comp.wait()
                raise CompanionError(f"demo: the companion did not start within "
                                     f"{time.monotonic() - t0:.0f} s (see {out}/companion.log)")
            time.sleep(0.05)
        t0 = time.monotonic()
        progress_file = out / ".companion-progress"
        progress_file.unlink(missing_ok=True)
        bar = bar_for(duration_s, show_progress)
        # the emulator's CPU: what this process's reaped children used from its start until it
        # is reaped (the companion is reaped after it)
        children0 = _children_cpu_s()
        emulator_cpu_s: float | None = None
        sim = subprocess.Popen(sim_cmd, stdout=sim_log, stderr=subprocess.STDOUT, env=env)
        budget = budget_s if budget_s is not None else 120.0 + 4.0 * duration_s
        sim_rc = comp_rc = None
        wall = 0.0
        try:
            while time.monotonic() - t0 < budget:
                sim_rc = sim.poll()
                comp_rc = comp.poll() if sim_rc is None else None
                if sim_rc is not None:
                    wall = time.monotonic() - t0
                    emulator_cpu_s = _children_cpu_s() - children0
                    # the flight is over: the companion stops at once (it would otherwise
                    # wait for frames that will not come)
                    if sim_rc == 0 and comp.poll() is None:
                        comp.send_signal(signal.SIGTERM)
                    comp_rc = comp.wait(timeout=30.0)
                    break
                if comp_rc is not None:  # the companion stopped: at the end, or early?
                    try:
                        sim_rc = sim.wait(timeout=5.0)
                        wall = time.monotonic() - t0
                        break
                    except subprocess.TimeoutExpired:
                        pass
                    sim.terminate()
                    sim.wait(timeout=10.0)
                    raise CompanionError(
                        f"demo: the companion exited ({comp_rc}) before the flight's end "
                        f"(see {out}/companion.log)")
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
    steps = round(duration_s / _step_s(sim_doc))
    report["emulator_cpu_ms_per_step"] = (
        emulator_cpu_s * 1e3 / steps if emulator_cpu_s is not None and steps > 0 else None)
    report["load_1min"] = os.getloadavg()[0]
    report["scenario"] = scenario
    report["overrides"] = list(overrides)
    report["config_file"] = str(comp_path)
    (out / "report.json").write_text(json.dumps(report, indent=2))
    return report


def _children_cpu_s() -> float:
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def _step_s(sim_doc: Mapping[str, Any]) -> float:
    """The lockstep step (one camera frame): ``sim.step_dt_s``, default 50 ms."""
    try:
        return float(sim_doc.get("sim", {}).get("step_dt_s", 0.05)) or 0.05
    except (TypeError, ValueError, AttributeError):
        return 0.05


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
        lc = config_from_dict(merged_document(read_document(args.config), overrides)).live
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
    emu = rep.get("emulator_cpu_ms_per_step")
    print(f"CPU per step (getrusage): companion {'-' if cpu is None else f'{cpu:.2f} ms'} (all "
          f"its threads and solver process, first frame to exit), emulator "
          f"{'-' if emu is None else f'{emu:.2f} ms'}"
          f" (start to exit); load average {rep.get('load_1min', 0.0):.1f}")
    print(f"report: {out / 'report.json'}")
    return 0
