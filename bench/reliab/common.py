"""What every probe shares: the result row, lockstep/realtime flights of the real emulator and
companion processes on loopback, memory sampling, and figures read back from the flight log."""

from __future__ import annotations

import contextlib
import json
import os
import resource
import signal
import subprocess
import time
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from companion.commands.demo import demo_commands
from companion.log.reader import LogReader

ROOT = Path(__file__).resolve().parents[2]
PAPER = ROOT / "config" / "paper.toml"


@dataclass
class ProbeResult:
    """One row of docs/reference/reliability.md. ``bad_commands``: commands built from bad data
    (must be 0); ``data_lost``: what the probe lost, in words with figures."""

    probe: str
    inputs: str
    result: str
    passed: bool
    data_lost: str = "-"
    bad_commands: int = 0
    figures: dict[str, Any] = field(default_factory=dict)
    wall_s: float = 0.0
    cpu_s: float = 0.0

    def to_json(self) -> dict[str, Any]:
        return asdict(self)


def rss_mb(pid: int) -> float | None:
    """Resident set size of a process (MB), None once it is gone."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    except OSError:
        return None
    return None


def proc_cpu_s(pid: int) -> float | None:
    """User + system CPU seconds of a running process."""
    try:
        parts = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        return (int(parts[11]) + int(parts[12])) / os.sysconf("SC_CLK_TCK")
    except (OSError, IndexError, ValueError):
        return None


def udp_socket_drops(port: int) -> dict[str, int]:
    """Datagrams the kernel dropped (receive buffer full) on the UDP sockets bound to ``port``,
    from /proc/net/udp: ``bound`` (unconnected: unknown senders) and ``connected`` (the
    companion's per-source sockets)."""
    out = {"bound": 0, "connected": 0}
    try:
        lines = Path("/proc/net/udp").read_text().splitlines()[1:]
    except OSError:
        return out
    want = f":{port:04X}"
    for ln in lines:
        cols = ln.split()
        if len(cols) > 12 and cols[1].endswith(want):
            kind = "bound" if cols[2].endswith(":0000") else "connected"
            out[kind] += int(cols[-1])
    return out


def children_cpu_s() -> float:
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def load_avg() -> str:
    return "{:.2f} {:.2f} {:.2f}".format(*os.getloadavg())


@dataclass
class Flight:
    """A running emulator + companion pair (``sim``, ``comp`` processes, ``ports``)."""

    sim: subprocess.Popen[bytes]
    comp: subprocess.Popen[bytes]
    out: Path
    comp_port: int
    sim_port: int
    t_start: float


def _port_after(cmd: list[str], flag: str) -> int:
    v = cmd[cmd.index(flag) + 1]
    return int(v.rsplit(":", 1)[1]) if ":" in v else int(v)


@contextlib.contextmanager
def flight(out: Path, *, scenario: str = "paper", duration_s: float = 20.0,
           overrides: list[str] | None = None, sim_config: Path | None = None,
           config: Path = PAPER, realtime: bool = False,
           sim_args: list[str] | None = None) -> Iterator[Flight]:
    """Start the companion (waits until it listens), then the emulator. ``realtime``: the
    emulator runs on the wall clock (the flood and stall probes need wall time to pass)."""
    out.mkdir(parents=True, exist_ok=True)
    sim_cmd, comp_cmd = demo_commands(config, scenario, duration_s, out, list(overrides or []), [])
    if sim_config is not None:
        sim_cmd[sim_cmd.index("--config") + 1] = str(sim_config)
    if realtime:
        sim_cmd.remove("--lockstep")
        i = comp_cmd.index('control.time_source="autopilot"')
        comp_cmd[i] = 'control.time_source="receipt"'
        comp_cmd[comp_cmd.index("logging.block_on_backlog=true")] = "logging.block_on_backlog=false"
    sim_cmd += list(sim_args or [])
    # the probes compare log times with their own monotonic clock (flood windows, stalls)
    comp_cmd[comp_cmd.index('logging.timestamps="source"')] = 'logging.timestamps="receipt"'
    comp_port = int(comp_cmd[comp_cmd.index("--mavlink") + 1].rsplit(":", 1)[1])
    sim_port = int(sim_cmd[sim_cmd.index("--offboard-port") + 1])
    env = dict(os.environ, PYTHONUNBUFFERED="1", PYTHONPATH=str(ROOT))
    ready = out / ".companion-ready"
    ready.unlink(missing_ok=True)
    comp_log = open(out / "companion.log", "w")  # noqa: SIM115
    sim_log = open(out / "sim.log", "w")  # noqa: SIM115
    comp = subprocess.Popen(comp_cmd, stdout=comp_log, stderr=subprocess.STDOUT, env=env)
    sim: subprocess.Popen[bytes] | None = None
    try:
        t0 = time.monotonic()
        while not ready.exists():
            if comp.poll() is not None or time.monotonic() - t0 > 300.0:
                raise RuntimeError(f"companion did not start: see {out}/companion.log")
            time.sleep(0.05)
        sim = subprocess.Popen(sim_cmd, stdout=sim_log, stderr=subprocess.STDOUT, env=env)
        yield Flight(sim, comp, out, comp_port, sim_port, time.monotonic())
    finally:
        for p in (sim, comp):
            if p is not None and p.poll() is None:
                with contextlib.suppress(ProcessLookupError):
                    p.send_signal(signal.SIGCONT)
                p.terminate()
                try:
                    p.wait(timeout=20)
                except subprocess.TimeoutExpired:
                    p.kill()
                    p.wait()
        comp_log.close()
        sim_log.close()


def wait_flight(f: Flight, budget_s: float, every: Callable[[], None] | None = None,
                period_s: float = 0.5) -> tuple[int | None, int | None]:
    """Wait for the emulator to end its flight, then for the companion; return codes."""
    end = time.monotonic() + budget_s
    while time.monotonic() < end:
        if f.sim.poll() is not None:
            try:
                return f.sim.returncode, f.comp.wait(timeout=30)
            except subprocess.TimeoutExpired:
                return f.sim.returncode, None
        if f.comp.poll() is not None:
            return None, f.comp.returncode
        if every is not None:
            every()
        time.sleep(period_s)
    return f.sim.poll(), f.comp.poll()


@dataclass
class FlightFigures:
    """What a flight log says (companion side)."""

    steps: int
    sent: int
    sim_s: float
    levels: dict[str, int]
    transitions: list[tuple[float, str]]
    offboard_left: int          # active -> anything else
    offboard_active_s: float
    frames_target_lost: int
    rejected: dict[str, int]
    non_finite_commands: int
    step_t_s: list[float]

    def to_json(self) -> dict[str, Any]:
        d = asdict(self)
        d.pop("step_t_s")
        return d


def flight_figures(log: Path) -> FlightFigures:
    """Safety levels, offboard phases, visibility and rejections from a companion log."""
    import math

    levels: dict[str, int] = {}
    transitions: list[tuple[float, str]] = []
    steps = sent = lost = 0
    last_level = None
    offboard_prev = None
    left = 0
    active = 0
    t_first = t_last = None
    rejected: dict[str, int] = {}
    nonfinite = 0
    ts: list[float] = []
    with LogReader(log) as r:
        for m in r.messages(topics=["/control/step", "/mavlink/rejected",
                                    "/mavlink/out/SET_ATTITUDE_TARGET"]):
            d = m.data or {}
            if m.topic == "/mavlink/rejected":
                rejected[d["reason"]] = rejected.get(d["reason"], 0) + 1
                continue
            if m.topic.startswith("/mavlink/out"):
                f = d["fields"]
                if not all(math.isfinite(v) for v in [*f["q"], f["thrust"]]):
                    nonfinite += 1
                continue
            steps += 1
            t = float(d.get("t_s", 0.0))
            ts.append(t)
            t_first = t if t_first is None else t_first
            t_last = t
            sent += bool(d.get("sent"))
            lvl = str((d.get("safety") or {}).get("level"))
            levels[lvl] = levels.get(lvl, 0) + 1
            if lvl != last_level:
                transitions.append((t, lvl))
                last_level = lvl
            ob = d.get("offboard")
            if offboard_prev == "active" and ob != "active":
                left += 1
            active += ob == "active"
            offboard_prev = ob
            if (d.get("perception") or {}).get("status") != "ok":
                lost += 1
    sim_s = 0.0 if t_first is None or t_last is None else t_last - t_first
    return FlightFigures(steps, sent, sim_s, levels, transitions, left, active * 0.05,
                         lost, rejected, nonfinite, ts)


def write_json(path: Path, obj: Any) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(obj, indent=2, default=str))
