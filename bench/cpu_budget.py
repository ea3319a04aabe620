"""The companion on a CPU budget: a realtime flight with the companion confined to a fraction of
one CPU core by a Linux cgroup quota (issue #24 item 3; docs/guides/sizing.md).

    python bench/cpu_budget.py [--fraction 1.0 0.5 0.3 0.15] [--duration 60] [--rate HZ]
                               [--config FILE] [--scenario paper] [--set KEY=VALUE ...]
                               [--out DIR] [--period-us 10000] [--weight 16]
                               [--cgroup-dir DIR] [--json] [--markdown]
    python bench/cpu_budget.py --from-summary OUT/summary.json [--markdown]

Per fraction: ``sim-bridge --realtime`` (the emulator, unconfined, on the wall clock) and
``companion run`` against it, the companion process and every child it starts (the solver
processes) in a cgroup limited to ``fraction`` x ``--period-us`` of CPU time per period
(10 ms: cgroup v1 ``cpu.cfs_quota_us`` / ``cpu.cfs_period_us``, v2 ``cpu.max``). The companion
flies the product's settings (``--config``, default config/paper.toml) with
``offboard.arm = true`` (the emulator starts disarmed in the air) and the ``--set`` overrides;
``--rate HZ`` sets the camera rate (``sim.camera.rate_hz``) and the controller's interval to
match (``rmpc.dt_s = 1/HZ``, ``control.rate_hz``). Everything goes into one variant file
(``OUT/f<fraction>/config.toml``, ``base`` = the config) which both programs read.

Printed per fraction, from the emulator's own count of frames rendered, the companion's
``report.json`` (``companion report`` on the flight's MCAP log) and the cgroup's counters:
frames answered with a command, frame -> command latency (the report's headline figures),
safety transitions, steps per safety level, fallbacks and recovery solves, the worst true
corner from 1 s after OFFBOARD, the companion's CPU per step, how often the quota throttled it,
and the verdict against issue #24's targets (0.3 core: >= 98 % answered, 0 fallbacks, 0 hover
steps, p95 <= 25 ms, every corner in view; 0.15 core: the target kept, no hover).

Exit status: 0 the flights ran (the targets are printed, not enforced), 1 a flight failed (a
process crashed or never started), 2 bad arguments or a config a program refused, 3 no cgroup
CPU quota can be set on this machine (the reason is printed).

The emulator is not confined (its group has no quota). Both groups get ``--weight`` x the
default scheduling weight, so that on a loaded machine the quota, not the competition with other
jobs, limits the companion; frames the emulator renders late still count against the companion.
The load average is printed before and after each flight. docs/guides/sizing.md reads the
figures.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import resource
import signal
import subprocess
import sys
import time
import tomllib
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from bench.budget_figures import (  # noqa: E402
    EXIT_FLIGHT_FAILED,
    BenchError,
    Flown,
    _fmt,
    _load,
    companion_report,
    emulator_figures,
    judge,
    print_markdown,
    print_table,
    stale_frames,
    summarize,
)
from bench.cgroup_quota import CgroupUnavailable, CpuQuota, create_quota  # noqa: E402
from companion.flight_ports import FlightSockets, ReadyPorts, read_ready  # noqa: E402

PAPER = ROOT / "config" / "paper.toml"
EXIT_BAD_INPUT = 2
EXIT_NO_CGROUP = 3

def _toml_value(text: str) -> str:
    """A ``--set`` value as a TOML literal: as given when it parses, else a quoted string (as
    ``companion run --set`` reads a bare word)."""
    try:
        tomllib.loads(f"v = {text}")
        return text.strip()
    except tomllib.TOMLDecodeError:
        return json.dumps(text.strip())


def variant_settings(rate_hz: float | None, overrides: list[str]) -> dict[str, str]:
    """The keys the variant file sets (dotted key -> TOML literal), in order: the emulator's
    arming, the rate, then ``overrides`` (later wins)."""
    keys: dict[str, str] = {"offboard.arm": "true"}
    if rate_hz is not None:
        if not (math.isfinite(rate_hz) and 1.0 <= rate_hz <= 100.0):
            raise BenchError(f"--rate {rate_hz}: must be in [1, 100] Hz", EXIT_BAD_INPUT)
        keys["sim.camera.rate_hz"] = repr(float(rate_hz))
        keys["control.rate_hz"] = repr(float(rate_hz))
        keys["rmpc.dt_s"] = repr(1.0 / rate_hz)
    for ov in overrides:
        key, sep, value = ov.partition("=")
        key = key.strip()
        if not sep or not key or any(not p.strip() for p in key.split(".")):
            raise BenchError(f"--set {ov!r}: expected KEY=VALUE, e.g. logging.preview_rate_hz=0",
                             EXIT_BAD_INPUT)
        keys[key] = _toml_value(value)
    return keys


def write_variant(config: Path, keys: dict[str, str], path: Path) -> None:
    """One TOML file both programs read: ``base`` = ``config`` (absolute) and ``keys`` as
    top-level dotted keys (deep-merged over the base by each program's own loader)."""
    lines = [f"# bench/cpu_budget.py: {config} with these keys",
             f"base = {json.dumps(str(config))}"]
    lines += [f"{k} = {v}" for k, v in keys.items()]
    text = "\n".join(lines) + "\n"
    try:
        tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise BenchError(f"the overrides do not make a valid TOML file: {e}", EXIT_BAD_INPUT) from e
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)


def check_emulator_config(variant: Path, scenario: str, env: dict[str, str]) -> None:
    """``sim-bridge --check-config``: the emulator's own verdict on the file."""
    r = subprocess.run([sys.executable, "-m", "sim_bridge", "--check-config", "--config",
                        str(variant), "--scenario", scenario, "--log-level", "ERROR"],
                       capture_output=True, text=True, env=env, timeout=300)
    if r.returncode != 0:
        lines = [ln for ln in (r.stderr + r.stdout).splitlines() if ln.strip()]
        raise BenchError(f"the emulator refuses the config: {lines[-1] if lines else r.returncode}",
                         EXIT_BAD_INPUT)


def companion_cmd(variant: Path, frame_port: int, out: Path, duration_s: float) -> list[str]:
    """The companion's line: it binds its MAVLink and ground-truth ports itself (port 0) and
    names them in its ready file (companion/flight_ports.py: nothing probed, nothing raced)."""
    return [sys.executable, "-m", "companion", "run", "--config", str(variant),
            "--mavlink", "udpin:127.0.0.1:0",
            "--camera", f"tcp://127.0.0.1:{frame_port}",
            "--log", str(out / "flight.mcap"), "--truth-port", "0",
            "--duration", f"{duration_s}", "--ready-file", str(out / ".companion-ready"),
            "--progress-file", str(out / ".companion-progress")]


def emulator_cmd(variant: Path, scenario: str, sockets: FlightSockets, ready: ReadyPorts | None,
                 duration_s: float) -> list[str]:
    """The emulator's line: its own links on ports it picks, the frames on the listening
    socket this process holds (``--frame-fd``: start it with ``pass_fds``), sending to the
    ports the companion's ready file names."""
    if ready is None or ready.mavlink_port is None or ready.truth_port is None:
        raise BenchError(f"the companion's ready file names no ports ({ready})")
    return [sys.executable, "-m", "sim_bridge", "--config", str(variant), "--scenario", scenario,
            "--realtime", "--duration", f"{duration_s}", "--bind", "127.0.0.1",
            "--offboard-port", "0", "--offboard-remote", f"127.0.0.1:{ready.mavlink_port}",
            "--gcs-port", "0", "--gcs-remote", f"127.0.0.1:{sockets.gcs_sink_port}",
            "--agv-port", "0", "--frame-fd", str(sockets.frame_fd),
            "--truth-remote", f"127.0.0.1:{ready.truth_port}"]


def _children_cpu_s() -> float:
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def _stop(p: subprocess.Popen[bytes], timeout_s: float) -> int:
    """SIGTERM (the programs' clean stop: the log is closed), SIGKILL after ``timeout_s``."""
    if p.poll() is None:
        with contextlib.suppress(ProcessLookupError):
            p.send_signal(signal.SIGTERM)
        try:
            p.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait()
    return int(p.returncode)


def _wait_ready(comp: subprocess.Popen[bytes], ready: Path, budget_s: float, out: Path) -> None:
    t0 = time.monotonic()
    while not ready.exists():
        if comp.poll() is not None:
            status = EXIT_BAD_INPUT if comp.returncode == 2 else EXIT_FLIGHT_FAILED
            raise BenchError(f"the companion exited ({comp.returncode}) before it was ready: "
                             f"{_tail(out / 'companion.log')}", status)
        if time.monotonic() - t0 > budget_s:
            raise BenchError(f"the companion was not ready after {budget_s:.0f} s: "
                             f"see {out / 'companion.log'}")
        time.sleep(0.05)


def _wait_idle(quota: CpuQuota, comp: subprocess.Popen[bytes], budget_s: float,
               window_s: float = 1.0, idle_cores: float = 0.02) -> float | None:
    """Wait until the companion's group uses less than ``idle_cores`` (or a fifth of its
    quota if less) over ``window_s``: its start-up is over (imports and the solver process
    loading its libraries, ~3 s of CPU, then ~0.002 core measured while it waits for the
    vehicle; the ready file only says its sockets are open). The flight then starts from a
    loaded companion, as on a vehicle, where it starts before the pilot hands it the vehicle.
    The stand-by solver process (``rmpc.solver_spare``) is forked beside the first one, so it
    has loaded by then too, as on a vehicle. Returns the idle use (cores), None when
    ``budget_s`` passed first or usage cannot be read."""
    assert quota.fraction is not None
    t_end = time.monotonic() + budget_s
    samples: list[tuple[float, float]] = []
    while time.monotonic() < t_end and comp.poll() is None:
        u = quota.usage_s()
        if u is None:
            return None
        now = time.monotonic()
        samples.append((now, u))
        old = [x for x in samples if x[0] <= now - window_s]
        if old:
            t_a, u_a = old[-1]
            if (u - u_a) / (now - t_a) < min(idle_cores, 0.2 * quota.fraction):
                return (u - u_a) / (now - t_a)
        time.sleep(0.1)
    return None


def _tail(path: Path, n: int = 3) -> str:
    with contextlib.suppress(OSError):
        return " | ".join(path.read_text(errors="replace").strip().splitlines()[-n:])
    return "(no output)"


def fly(quota: CpuQuota, sim_group: CpuQuota | None, variant: Path, scenario: str,
        duration_s: float, out: Path) -> Flown:
    """One realtime flight: the companion (in ``quota``'s group) started first and waited for
    (its sockets open), then the emulator (in ``sim_group``, no quota, when given); both
    stopped at the end of ``duration_s``."""
    assert quota.fraction is not None
    env = dict(os.environ, PYTHONUNBUFFERED="1", PYTHONPATH=str(ROOT))
    f = Flown(out, quota.fraction, quota={"cgroup": f"v{quota.controller.version}",
                                          "group": str(quota.cpu_group),
                                          "quota_us": quota.quota_us,
                                          "period_us": quota.period_us})
    f.load.append(_load())
    (out / ".companion-ready").unlink(missing_ok=True)
    with (FlightSockets() as sockets, open(out / "companion.log", "w") as clog,
          open(out / "sim.log", "w") as slog):
        t0 = time.monotonic()
        cpu0 = _children_cpu_s()
        comp = subprocess.Popen(companion_cmd(variant, sockets.frame_port, out, duration_s),
                                stdout=clog,
                                stderr=subprocess.STDOUT, env=env,
                                preexec_fn=quota.enter_self)  # before exec: its children inherit
        sim: subprocess.Popen[bytes] | None = None
        try:
            # start-up is ~1-3 s of CPU (imports, the solver libraries): scaled by the quota
            _wait_ready(comp, out / ".companion-ready", 120.0 + 60.0 / quota.fraction, out)
            f.idle = _wait_idle(quota, comp, 30.0 + 30.0 / quota.fraction)
            f.start_wall_s = time.monotonic() - t0
            f.cg_usage_start_s = quota.usage_s()
            sim_cmd = emulator_cmd(variant, scenario, sockets,
                                   read_ready(out / ".companion-ready"), duration_s)
            sim = subprocess.Popen(sim_cmd, stdout=slog, stderr=subprocess.STDOUT, env=env,
                                   pass_fds=(sockets.frame_fd,),
                                   preexec_fn=None if sim_group is None else sim_group.enter_self)
            sockets.frame.close()  # the emulator's now (held until it exits)
            t_fly = time.monotonic()
            try:
                f.sim_rc = sim.wait(timeout=duration_s + 120.0)
            except subprocess.TimeoutExpired:
                f.sim_rc = _stop(sim, 20.0)
            f.wall_s = time.monotonic() - t_fly
            f.cg_usage_flight_end_s = quota.usage_s()
            cpu1 = _children_cpu_s()  # the emulator reaped, the companion not yet
            f.rusage_sim_s = cpu1 - cpu0
            # the companion stops by itself duration_s after its first frame; else SIGTERM
            with contextlib.suppress(subprocess.TimeoutExpired):
                comp.wait(timeout=10.0)
            f.comp_rc = _stop(comp, 60.0 + 30.0 / quota.fraction)
            f.window_s = time.monotonic() - t_fly
            # getrusage of the companion and the children it reaped (its solver processes)
            f.rusage_comp_s = _children_cpu_s() - cpu1
        finally:
            for p in (sim, comp):
                if p is not None:
                    _stop(p, 20.0)
    f.cg_usage_end_s = quota.usage_s()
    f.cg_stat = quota.stat()
    f.cg_throttled_s = quota.throttled_s()
    f.load.append(_load())
    return f


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--fraction", type=float, nargs="+", default=[1.0, 0.5, 0.3, 0.15],
                    help="CPU budgets to fly, in cores (default: 1.0 0.5 0.3 0.15)")
    ap.add_argument("--duration", type=float, default=60.0, help="seconds per flight (60)")
    ap.add_argument("--rate", type=float, default=None,
                    help="camera and control rate, Hz (default: the config's, 20)")
    ap.add_argument("--config", type=Path, default=PAPER, help="config file (config/paper.toml)")
    ap.add_argument("--scenario", default="paper", help="emulator scenario (paper)")
    ap.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                    help="a config key for both programs, e.g. logging.preview_rate_hz=0")
    ap.add_argument("--out", type=Path, default=ROOT / "out" / "cpu-budget",
                    help="where the flights' logs, reports and summary.json go")
    ap.add_argument("--period-us", type=int, default=10_000, help="quota period (10000 us)")
    ap.add_argument("--weight", type=float, default=16.0,
                    help="scheduling weight of the companion's and the emulator's groups, x "
                         "the default (16: on a busy machine the quota, not the competition "
                         "with other jobs, limits the companion; 1: fair share)")
    ap.add_argument("--cgroup-dir", type=Path, default=None,
                    help="make the groups under this cgroup directory (a subtree delegated to "
                         "you; default: the cpu hierarchy in /proc/mounts)")
    ap.add_argument("--json", action="store_true", help="print the rows as JSON")
    ap.add_argument("--markdown", action="store_true",
                    help="print a compact Markdown table (after the full one)")
    ap.add_argument("--from-summary", type=Path, default=None, metavar="SUMMARY.json",
                    help="fly nothing: print the tables of an earlier run's summary.json")
    a = ap.parse_args(argv)
    if not (math.isfinite(a.duration) and 5.0 <= a.duration <= 3600.0):
        ap.error("--duration: must be in [5, 3600] s")
    if any(not (math.isfinite(x) and 0.01 <= x <= 64.0) for x in a.fraction):
        ap.error("--fraction: each must be in [0.01, 64] cores")
    if not a.config.is_file():
        ap.error(f"--config {a.config}: no such file")
    if not 1000 <= a.period_us <= 1_000_000:
        ap.error("--period-us: must be in [1000, 1000000] (the kernel's bounds)")
    if not (math.isfinite(a.weight) and 0.01 <= a.weight <= 100.0):
        ap.error("--weight: must be in [0.01, 100]")
    return a


def fly_budget(fraction: float, variant: Path, scenario: str, duration_s: float, out: Path,
               period_us: int = 10_000, weight: float = 16.0,
               cgroup_dir: Path | None = None) -> dict[str, Any]:
    """One flight under a ``fraction``-of-a-core quota, reported and judged (the row)."""
    tag = f"rmpc-budget-{os.getpid()}-{fraction:g}"
    out.mkdir(parents=True, exist_ok=True)
    quota = create_quota(fraction, tag, period_us, weight, cgroup_dir)
    sim_group: CpuQuota | None = None
    try:
        sim_group = create_quota(None, tag + "-emulator", period_us, weight, cgroup_dir)
        flown = fly(quota, sim_group, variant, scenario, duration_s, out)
    finally:
        quota.remove()
        if sim_group is not None:
            sim_group.remove()
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    rep = companion_report(out / "flight.mcap", out / "report", env)
    row = summarize(flown, rep, emulator_figures(out / "sim.log"), stale_frames(
        out / "flight.mcap"))
    row["verdict"] = judge(row)
    return row


def _print_rows(rows: list[dict[str, Any]], a: argparse.Namespace) -> int:
    if a.json:
        print(json.dumps(rows, indent=2, default=str))
        return 0
    print_table(rows)
    if a.markdown:
        print()
        print_markdown(rows)
    return 0


def main(argv: list[str] | None = None) -> int:
    a = parse_args(argv)
    if a.from_summary is not None:
        return _print_rows(json.loads(a.from_summary.read_text())["rows"], a)
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    rows: list[dict[str, Any]] = []
    try:
        # can a quota be set at all? (first: before anything else is started)
        create_quota(a.fraction[0], f"rmpc-budget-{os.getpid()}-probe", a.period_us,
                     parent=a.cgroup_dir).remove()
        keys = variant_settings(a.rate, a.overrides)
        a.out.mkdir(parents=True, exist_ok=True)
        variant = a.out / "config.toml"
        write_variant(a.config.resolve(), keys, variant)
        check_emulator_config(variant, a.scenario, env)
        print(f"cpu_budget: {a.scenario}, {a.duration:g} s realtime per flight, config {variant}"
              f" ({', '.join(f'{k}={v}' for k, v in keys.items())}); uptime load "
              f"{_load()}", flush=True)
        for fr in a.fraction:
            rows.append(fly_budget(fr, variant, a.scenario, a.duration, a.out / f"f{fr:g}",
                                   a.period_us, a.weight, a.cgroup_dir))
            r = rows[-1]
            print(f"  {fr:g} core: {r['commands_sent']}/{r['frames_offered']} frames answered,"
                  f" p95 {_fmt(r['latency_p95_ms'])} ms, {r['fallbacks']} fallbacks, "
                  f"{r['hover_steps']} hover; load {r['load'][-1]}", flush=True)
    except CgroupUnavailable as e:
        print(f"cpu_budget: no CPU quota can be set on this machine: {e}", file=sys.stderr)
        return EXIT_NO_CGROUP
    except BenchError as e:
        print(f"cpu_budget: {e}", file=sys.stderr)
        return e.status
    finally:
        if rows:
            (a.out / "summary.json").write_text(json.dumps(
                {"argv": sys.argv[1:] if argv is None else argv, "rows": rows}, indent=2,
                default=str))
    _print_rows(rows, a)
    crashed = [r["fraction"] for r in rows if r["rc"]["companion"] not in (0,)]
    if crashed:
        print(f"cpu_budget: the companion exited with an error at {crashed} core", file=sys.stderr)
        return EXIT_FLIGHT_FAILED
    return 0


if __name__ == "__main__":
    sys.exit(main())
