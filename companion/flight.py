"""A lockstep flight as a library call: the emulator and the companion as two processes.

:func:`fly` is what ``companion demo``, the campaign runner (``companion/campaign/runner.py``)
and the benches call. The two programs meet only on loopback sockets (docs/reference/wire.md),
exactly as
the companion meets a real PX4: this module starts ``python -m sim_bridge --lockstep`` as a
subprocess and never imports it. It merges the config file and every ``--set`` override into
``DIR/config.toml`` (so an override reaches both processes, ``sim.*`` keys the emulator and
shared ``camera.*``/``target.*`` keys both), has both programs validate it (``sim-bridge
--check-config``; a key neither knows is refused before anything flies), starts both on that
file on ports the binding processes choose (companion/flight_ports.py: nothing is probed, so
two flights started at once cannot be handed the same port), waits for the flight, then
scores it from the log (ground truth recorded on ``/truth``) into ``DIR/report.json`` and the
report figures.

The flight's folder ``DIR`` then holds ``flight.mcap``, ``report.json``, ``config.toml`` and the
two processes' output (``companion.log``, ``sim.log``).
"""

from __future__ import annotations

import dataclasses
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
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from companion import CompanionError, ConfigError
from companion.config import Config, config_from_dict, read_document
from companion.config_file import absolutize_paths, dump_toml, merged_document
from companion.control.knobs import warn_ineffective_knobs
from companion.flight_ports import FlightSockets, ReadyPorts, read_ready
from companion.report.files import build_report

log = logging.getLogger(__name__)

__all__ = ["Flight", "build_flight_report", "check_emulator_config", "demo_commands",
           "emulator_command", "fly", "free_port", "free_ports", "prepare_configs",
           "read_progress", "run_demo", "write_merged_config"]

READY_FILE = ".companion-ready"
PROGRESS_FILE = ".companion-progress"
#: wall time the companion may take to open its sockets (its first start compiles the solver)
STARTUP_S = 300.0


@dataclass(frozen=True)
class Flight:
    """A flown flight: its ``folder`` (``flight.mcap``, ``report.json``, ``config.toml``, the
    processes' logs) and the scored ``report`` (the dict written to ``report.json``)."""

    folder: Path
    report: dict[str, Any]

    @property
    def log_path(self) -> Path:
        return self.folder / "flight.mcap"


@dataclass(frozen=True)
class _Ended:
    """How the two processes ended: exit codes, wall time of the flight (s, emulator start to
    its exit), the emulator's CPU time (s, ``None`` when not measured) and how much of it was
    spent before the companion's first step (its start-up, s; ``None`` when not sampled)."""

    sim_rc: int | None
    comp_rc: int | None
    wall_s: float
    emulator_cpu_s: float | None
    emulator_startup_cpu_s: float | None = None


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
                  live: bool = False, sockets: FlightSockets | None = None,
                  ) -> tuple[list[str], list[str]]:
    """The two command lines (emulator, companion) of a lockstep flight, both reading
    ``config`` (the merged file); ``overrides`` go to the companion only (the demo's own
    lockstep settings).

    With ``sockets`` (what :func:`fly` does) no port is probed (companion/flight_ports.py):
    the companion binds port 0 and reports its ports in its ready file, which
    :func:`emulator_command` then writes into the emulator's line; the emulator serves the
    frames on ``sockets.frame`` (start it with ``pass_fds=(sockets.frame_fd,)``). Without,
    probed free ports (:func:`free_ports`: another process may take one before the child
    binds it; for tools that start the two processes on their own)."""
    if sockets is None:
        p_sim, p_comp, p_gcs, p_gcs_remote, p_agv, p_truth = free_ports(6)
        p_frame = free_port(socket.SOCK_STREAM)
        frame = ["--frame-port", str(p_frame)]
    else:  # 0: the binding process picks; the remotes are filled in by emulator_command
        p_sim = p_comp = p_gcs = p_agv = p_truth = 0
        p_gcs_remote, p_frame = sockets.gcs_sink_port, sockets.frame_port
        frame = ["--frame-fd", str(sockets.frame_fd)]
    sim = [
        sys.executable, "-m", "sim_bridge", "--config", str(config), "--scenario", scenario,
        "--lockstep", "--duration", f"{duration_s}", "--bind", "127.0.0.1",
        "--offboard-port", str(p_sim), "--offboard-remote", f"127.0.0.1:{p_comp}",
        "--gcs-port", str(p_gcs), "--gcs-remote", f"127.0.0.1:{p_gcs_remote}",
        "--agv-port", str(p_agv), *frame,
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
        "--mavlink", f"udpin:127.0.0.1:{p_comp}", "--camera",
        # every frame answered in turn (the flights as flown before, one step per frame); a
        # client on the default intake (?frames=newest, realtime) also keeps lockstep: the
        # emulator takes an answer stamped with the newest frame's time for every frame before it;
        # the frames through the emulator's shared memory (both run here: no 1 MB loopback
        # write and read a frame, docs/reference/wire.md)
        f"tcp://127.0.0.1:{p_frame}?frames=all&transport=shm",
        "--log", str(out / "flight.mcap"), "--truth-port", str(p_truth),
        "--duration", f"{duration_s}", "--ready-file", str(out / READY_FILE),
        "--progress-file", str(out / PROGRESS_FILE),
        "--camera-timeout", f"{camera_timeout_s(config)}",
        *(["--live"] if live else []),
    ]
    return sim, comp


def emulator_command(sim_cmd: Sequence[str], ready: ReadyPorts | None) -> list[str]:
    """``sim_cmd`` sending to the ports the companion's ready file names (its MAVLink and
    ground-truth sockets); a clear error if it names none."""
    if ready is None or ready.mavlink_port is None or ready.truth_port is None:
        raise CompanionError(f"demo: the companion's ready file names no ports ({ready})")
    cmd = list(sim_cmd)
    cmd[cmd.index("--offboard-remote") + 1] = f"127.0.0.1:{ready.mavlink_port}"
    cmd[cmd.index("--truth-remote") + 1] = f"127.0.0.1:{ready.truth_port}"
    return cmd


def positive_seconds(text: str) -> float:
    """A finite number of seconds > 0 (an ``argparse`` type: ``companion run
    --camera-timeout``)."""
    import argparse

    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number of seconds: {text!r}") from None
    if not (value > 0.0 and value < float("inf")):
        raise argparse.ArgumentTypeError(f"must be a finite number of seconds > 0: {text!r}")
    return value


CAMERA_TIMEOUT_MARGIN_S = 5.0
"""How much longer than the emulator's lockstep timeout the companion waits for a frame."""


def camera_timeout_s(config: Path) -> float:
    """The companion's "no camera frame" stop for a lockstep flight on ``config``: longer than
    the emulator's ``sim.lockstep_timeout_s`` by :data:`CAMERA_TIMEOUT_MARGIN_S`, so that a
    setpoint lost or late under load makes the emulator step on (and count a lockstep
    timeout) before the companion would take the silence for a dead camera and end the
    flight; never below ``companion run``'s own 5 s default."""
    sim = read_document(config).get("sim", {})
    lockstep_s = sim.get("lockstep_timeout_s", 0.0) if isinstance(sim, dict) else 0.0
    if isinstance(lockstep_s, bool) or not isinstance(lockstep_s, (int, float)):
        lockstep_s = 0.0  # the emulator's --check-config refuses such a file by name
    return max(5.0, float(lockstep_s) + CAMERA_TIMEOUT_MARGIN_S)


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
    """Have the emulator validate ``path`` for a lockstep flight (``sim-bridge --check-config
    --lockstep``: a knob with no effect in lockstep is refused by name); raise
    :class:`ConfigError` with its message if it refuses."""
    r = subprocess.run([sys.executable, "-m", "sim_bridge", "--check-config", "--lockstep",
                        "--config", str(path), "--scenario", scenario, "--log-level", "ERROR"],
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


def fly(config: Path, scenario: str, duration_s: float | None, out: Path,
        overrides: Sequence[str], faults: Sequence[str], plots: bool = True,
        monitor: Callable[[subprocess.Popen[bytes]], None] | None = None,
        sim_config: Path | None = None, budget_s: float | None = None,
        live: bool = False, show_progress: bool = False) -> Flight:
    """Fly a scenario into the folder ``out``; ``overrides`` reach both processes
    (``OUT/config.toml``). ``budget_s``: wall time allowed for the flight (default 120 s + 4
    times the flight). ``monitor(companion_process)`` is called every 50 ms during the flight
    (benchmarks sample its memory); ``sim_config`` gives the emulator a different file (e.g.
    with fault injection) than the companion's ``config``, with the same overrides; with
    ``live`` the companion serves its channels to Foxglove while it flies (``[live]``
    config). Raises :class:`CompanionError` when a process fails or the flight does not end,
    :class:`ConfigError` on a key either program refuses (before anything starts)."""
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    out.mkdir(parents=True, exist_ok=True)
    # fail early, before anything starts, on a key either program refuses
    cfg, comp_path, sim_path, sim_doc = prepare_configs(config, scenario, overrides, out, env,
                                                        sim_config)
    # said here too, where the user reads (the companion's own warning is in companion.log)
    warn_ineffective_knobs(dataclasses.replace(cfg, live=dataclasses.replace(
        cfg.live, enabled=True)) if live else cfg)
    if duration_s is None:
        duration_s = float(sim_doc.get("sim", {}).get("duration_s", 251.0))
    budget = budget_s if budget_s is not None else 120.0 + 4.0 * duration_s
    progress_file = out / PROGRESS_FILE
    with (FlightSockets() as sockets, open(out / "companion.log", "w") as comp_log,
          open(out / "sim.log", "w") as sim_log):
        sim_cmd, comp_cmd = demo_commands(comp_path, scenario, duration_s, out, [], faults,
                                          live=live, sockets=sockets)
        sim_cmd[sim_cmd.index("--config") + 1] = str(sim_path)
        comp = _start_companion(comp_cmd, comp_log, env, out,
                                STARTUP_S if budget_s is None else max(STARTUP_S, budget_s))
        try:
            sim_cmd = emulator_command(sim_cmd, read_ready(out / READY_FILE))
        except (CompanionError, ValueError):
            comp.kill()
            comp.wait()
            raise
        progress_file.unlink(missing_ok=True)
        bar = _bar_for(duration_s, show_progress)
        try:
            ended = _supervise(sim_cmd, sim_log, comp, env, out, budget, monitor,
                               lambda: _advance(bar, progress_file), sockets,
                               lambda: read_progress(progress_file)[1] > 0)
        finally:
            if bar is not None:
                bar.close()
    if ended.sim_rc != 0 or ended.comp_rc != 0:
        raise CompanionError(f"demo: emulator exited {ended.sim_rc}, companion exited "
                             f"{ended.comp_rc} (see {out}/sim.log, {out}/companion.log)")
    report = build_flight_report(out, cfg, plots, show_progress)
    report["wall_time_s"] = ended.wall_s
    report["real_time_factor"] = (report["sim_time_s"] / ended.wall_s if ended.wall_s > 0
                                  else None)
    report["companion_cpu_ms_per_step"] = read_progress(progress_file)[2]
    steps = round(duration_s / _step_s(sim_doc))
    report.update(emulator_cpu_figures(ended.emulator_cpu_s, ended.emulator_startup_cpu_s,
                                       steps))
    report["load_1min"] = os.getloadavg()[0]
    report["scenario"] = scenario
    report["overrides"] = list(overrides)
    report["config_file"] = str(comp_path)
    (out / "report.json").write_text(json.dumps(report, indent=2))
    return Flight(out, report)


def run_demo(config: Path, scenario: str, duration_s: float | None, out: Path,
             overrides: Sequence[str], faults: Sequence[str], plots: bool = True,
             monitor: Callable[[subprocess.Popen[bytes]], None] | None = None,
             sim_config: Path | None = None, budget_s: float | None = None,
             live: bool = False, show_progress: bool = False) -> dict[str, Any]:
    """:func:`fly`, returning only the report (what ``OUT/report.json`` holds)."""
    return fly(config, scenario, duration_s, out, overrides, faults, plots=plots,
               monitor=monitor, sim_config=sim_config, budget_s=budget_s, live=live,
               show_progress=show_progress).report


def _start_companion(cmd: list[str], output: Any, env: Mapping[str, str], out: Path,
                     startup_s: float) -> subprocess.Popen[bytes]:
    """Start the companion and wait until it listens (its ready file): the vehicle starts
    talking only then (a first start compiles the solver: allow for it)."""
    t0 = time.monotonic()
    ready = out / READY_FILE
    ready.unlink(missing_ok=True)
    comp = subprocess.Popen(cmd, stdout=output, stderr=subprocess.STDOUT, env=dict(env))
    while not ready.exists():
        if comp.poll() is not None or time.monotonic() - t0 > startup_s:
            comp.kill()
            comp.wait()
            raise CompanionError(f"demo: the companion did not start within "
                                 f"{time.monotonic() - t0:.0f} s (see {out}/companion.log)")
        time.sleep(0.05)
    return comp


def _supervise(sim_cmd: list[str], output: Any, comp: subprocess.Popen[bytes],
               env: Mapping[str, str], out: Path, budget_s: float,
               monitor: Callable[[subprocess.Popen[bytes]], None] | None,
               tick: Callable[[], None], sockets: FlightSockets,
               first_step: Callable[[], bool] = lambda: False) -> _Ended:
    """Start the emulator (handing it the frame server's socket) and wait for the flight's
    end (the emulator exits after its duration, then the companion is told to stop); both
    processes are gone on return."""
    t0 = time.monotonic()
    # the emulator's CPU: what this process's reaped children used from its start until it
    # is reaped (the companion is reaped after it)
    children0 = _children_cpu_s()
    sim = subprocess.Popen(sim_cmd, stdout=output, stderr=subprocess.STDOUT, env=dict(env),
                           pass_fds=(sockets.frame_fd,))
    sockets.frame.close()  # the emulator's now: its port stays held until the emulator exits
    startup_cpu_s: float | None = None
    sampled = False  # the start-up sample taken (or tried: no /proc), once
    try:
        while time.monotonic() - t0 < budget_s:
            sim_rc = sim.poll()
            comp_rc = comp.poll() if sim_rc is None else None
            if sim_rc is not None:
                wall = time.monotonic() - t0
                emulator_cpu_s = _children_cpu_s() - children0
                # the flight is over, ended or failed: the companion stops at once (it would
                # otherwise wait for frames that will not come)
                if comp.poll() is None:
                    comp.send_signal(signal.SIGTERM)
                return _Ended(sim_rc, comp.wait(timeout=30.0), wall, emulator_cpu_s,
                              startup_cpu_s)
            if not sampled and first_step():
                # the emulator's start-up (imports, kernels' checks, first frames) ends where
                # the companion's per-step figure begins: its first step
                startup_cpu_s, sampled = proc_cpu_s(sim.pid), True
            if comp_rc is not None:  # the companion stopped: at the end, or early?
                try:
                    sim_rc = sim.wait(timeout=5.0)
                    return _Ended(sim_rc, comp_rc, time.monotonic() - t0, None)
                except subprocess.TimeoutExpired:
                    pass
                sim.terminate()
                sim.wait(timeout=10.0)
                raise CompanionError(
                    f"demo: the companion exited ({comp_rc}) before the flight's end "
                    f"(see {out}/companion.log)")
            if monitor is not None:
                monitor(comp)
            tick()
            time.sleep(0.05)
        raise CompanionError(f"demo: flight did not finish within {budget_s:.0f} s "
                             f"(see {out}/sim.log, {out}/companion.log)")
    except subprocess.TimeoutExpired:
        raise CompanionError(f"demo: a process did not exit (see {out}/sim.log, "
                             f"{out}/companion.log)") from None
    finally:
        for p in (sim, comp):
            if p.poll() is None:
                p.kill()
                p.wait()


def build_flight_report(out: Path, cfg: Config, plots: bool,
                        show_progress: bool) -> dict[str, Any]:
    """Score ``OUT/flight.mcap`` (report figures and, with ``plots``, the plots)."""
    rbar, cb = (None, None)
    if show_progress:
        from companion.progress import step_callback

        rbar, cb = step_callback("report", unit="msg")
    try:
        return build_report(out / "flight.mcap", cfg, out, plots=plots, progress=cb)
    finally:
        if rbar is not None:
            rbar.close()


def emulator_cpu_figures(total_s: float | None, startup_s: float | None,
                         steps: int) -> dict[str, float | None]:
    """The emulator's CPU a step as the companion's is counted, from the companion's first
    step to the exit (``emulator_cpu_ms_per_step``), beside its start-up (s) and the whole
    process's figure (start-up included, ``emulator_cpu_ms_per_step_all``). Without a
    start-up sample (no ``/proc``, or the companion never stepped) the per-step figure is the
    whole process's."""
    if total_s is None or steps <= 0:
        return {"emulator_cpu_ms_per_step": None, "emulator_cpu_ms_per_step_all": None,
                "emulator_startup_cpu_s": None}
    whole = total_s * 1e3 / steps
    if startup_s is None or not 0.0 <= startup_s <= total_s:
        return {"emulator_cpu_ms_per_step": whole, "emulator_cpu_ms_per_step_all": whole,
                "emulator_startup_cpu_s": None}
    return {"emulator_cpu_ms_per_step": (total_s - startup_s) * 1e3 / steps,
            "emulator_cpu_ms_per_step_all": whole, "emulator_startup_cpu_s": startup_s}


def proc_cpu_s(pid: int) -> float | None:
    """CPU seconds (user + system, its threads and reaped children) of a running process from
    ``/proc/PID/stat``; ``None`` where there is no such file (not Linux, already gone)."""
    try:
        with open(f"/proc/{pid}/stat", "rb") as f:
            fields = f.read().rsplit(b")", 1)[1].split()
        # after the ")": state is field 3, utime..cstime are fields 14..17
        ticks = sum(int(v) for v in fields[11:15])
        return ticks / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError):
        return None


def _children_cpu_s() -> float:
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def _step_s(sim_doc: Mapping[str, Any]) -> float:
    """The lockstep step (one camera frame): ``sim.step_dt_s``, default 50 ms."""
    try:
        return float(sim_doc.get("sim", {}).get("step_dt_s", 0.05)) or 0.05
    except (TypeError, ValueError, AttributeError):
        return 0.05


def _bar_for(duration_s: float, show: bool) -> Any:
    if not show:
        return None
    from companion.progress import bar

    return bar(round(duration_s, 1), "demo", unit="sim s",
               bar_format="{l_bar}{bar}| {n:.1f}/{total:.1f} sim s [{elapsed}<{remaining}]")


def _advance(bar: Any, progress_file: Path) -> None:
    if bar is not None:
        elapsed = read_progress(progress_file)[0]
        bar.update(max(round(elapsed, 1) - bar.n, 0.0))


def read_progress(path: Path) -> tuple[float, int, float | None]:
    """(simulated seconds since the first frame, steps, CPU ms per step at the end) from the
    companion's ``--progress-file`` (zeros while it has none)."""
    try:
        parts = path.read_text().split()
        return float(parts[0]), int(parts[1]), float(parts[2]) if len(parts) > 2 else None
    except (OSError, ValueError, IndexError):
        return 0.0, 0, None
