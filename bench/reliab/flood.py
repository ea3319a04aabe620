"""Flood: hostile datagrams at the companion's MAVLink port during a realtime flight.

The mix (seeded): random bytes; NaN / huge telemetry claiming the autopilot's sysid/compid
(valid CRC); MAVLink 1 frames; truncated frames; and PLAUSIBLE frames with the autopilot's
identity (a tilted attitude, a displaced position, a HEARTBEAT in another mode): a spoofed
source. All come from another address than the emulator's. Every attacker frame carries a mark
(``time_boot_ms >= MARK_MS``, or HEARTBEAT ``system_status = 8``) so the log shows whether any
was ever accepted: a command sent after an accepted attacker frame counts as built from bad data.
"""

from __future__ import annotations

import itertools
import math
import random
import socket
import threading
import time
from pathlib import Path
from typing import Any

from pymavlink.dialects.v20 import common as mavlink2

from bench.reliab.common import (
    ProbeResult,
    children_cpu_s,
    flight,
    flight_figures,
    load_avg,
    udp_socket_drops,
    wait_flight,
)
from companion.log.reader import LogReader

MARK_MS = 3_000_000_000
MARK_STATUS = 8  # MAV_STATE_FLIGHT_TERMINATION: the emulator never reports it
KINDS = ("random", "nan_huge", "mavlink1", "truncated", "spoof_plausible")


class _Enc:
    def __init__(self, sysid: int, compid: int) -> None:
        self.mav = mavlink2.MAVLink(None, srcSystem=sysid, srcComponent=compid)

    def pack(self, msg: Any, v1: bool = False) -> bytes:
        if v1:
            m1 = mavlink2.MAVLink(None, srcSystem=self.mav.srcSystem,
                                  srcComponent=self.mav.srcComponent)
            m1.WIRE_PROTOCOL_VERSION = "1.0"
            return bytes(msg.pack(m1, force_mavlink1=True))
        return bytes(msg.pack(self.mav))


def hostile_datagrams(n: int, seed: int = 13, sysid: int = 1,
                      compid: int = 1) -> tuple[list[bytes], dict[str, int]]:
    """``n`` hostile datagrams and how many of each kind."""
    rng = random.Random(seed)
    e = _Enc(sysid, compid)
    out: list[bytes] = []
    counts = dict.fromkeys(KINDS, 0)
    bad_vals = (math.nan, math.inf, -math.inf, 1e30, -1e30)
    for i in range(n):
        kind = KINDS[i % len(KINDS)]
        counts[kind] += 1
        t = MARK_MS + i
        if kind == "random":
            d = rng.randbytes(rng.randint(1, 300))
        elif kind == "nan_huge":
            v = bad_vals[rng.randrange(len(bad_vals))]
            if rng.random() < 0.5:
                m = e.mav.attitude_quaternion_encode(t, v, 0.0, 0.0, 1.0, v, v, v)
            else:
                m = e.mav.local_position_ned_encode(t, v, v, v, v, v, v)
            d = e.pack(m)
        elif kind == "mavlink1":
            d = e.pack(e.mav.attitude_encode(t, 0.5, 0.5, 0.0, 0.0, 0.0, 0.0), v1=True)
        elif kind == "truncated":
            full = e.pack(e.mav.attitude_quaternion_encode(t, 0.9, 0.3, 0.2, 0.1, 0, 0, 0))
            d = full[: rng.randint(1, len(full) - 1)]
        else:
            r = rng.random()
            if r < 0.4:  # a 40 deg roll, normalised: passes every value check
                c, s_ = math.cos(0.35), math.sin(0.35)
                m = e.mav.attitude_quaternion_encode(t, c, s_, 0.0, 0.0, 0.0, 0.0, 0.0)
            elif r < 0.8:
                m = e.mav.local_position_ned_encode(t, 5.0, -5.0, -1.0, 1.0, 0.0, 0.0)
            else:  # HEARTBEAT in POSCTL, armed
                m = e.mav.heartbeat_encode(2, 12, 209, 3 << 16, MARK_STATUS, 3)
            d = e.pack(m)
        out.append(d)
    return out, counts


def send_flood(port: int, datagrams: list[bytes], rate_per_s: float,
               sock: socket.socket | None = None) -> tuple[float, float, int]:
    """Send at ``rate_per_s`` (bursts of 500); returns (t_start, t_end) monotonic s and the
    number of send errors (a full socket buffer)."""
    s = sock or socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    errors = 0
    t0 = time.monotonic()
    burst = 500
    for k in range(0, len(datagrams), burst):
        for d in datagrams[k:k + burst]:
            try:
                s.sendto(d, ("127.0.0.1", port))
            except OSError:
                errors += 1
        due = t0 + (k + burst) / rate_per_s
        delay = due - time.monotonic()
        if delay > 0:
            time.sleep(delay)
    t1 = time.monotonic()
    if sock is None:
        s.close()
    return t0, t1, errors


def attacker_frames_accepted(log: Path) -> tuple[int, int | None]:
    """Attacker-marked frames in /mavlink/in (accepted), and the log time of the first."""
    n, first = 0, None
    with LogReader(log) as r:
        for m in r.messages(topics=["/mavlink/in/ATTITUDE_QUATERNION",
                                    "/mavlink/in/LOCAL_POSITION_NED", "/mavlink/in/HEARTBEAT",
                                    "/mavlink/in/ATTITUDE"]):
            f = (m.data or {}).get("fields", {})
            if int(f.get("time_boot_ms", 0)) >= MARK_MS or (
                    m.topic.endswith("HEARTBEAT") and f.get("system_status") == MARK_STATUS):
                n += 1
                first = m.log_time_ns if first is None else first
    return n, first


def run_flood(out: Path, n: int = 100_000, rate_per_s: float = 21_700.0,
              duration_s: float = 30.0, flood_at_s: float = 12.0, seed: int = 13,
              scenario: str = "paper", realtime: bool = False) -> ProbeResult:
    """A flight (lockstep by default: the flood competes with the real telemetry for the
    socket and the CPU, and a lost real datagram shows up as stale telemetry in simulated time
    whatever the machine's load; ``realtime``: on the wall clock, where the load of the machine
    matters too); ``n`` hostile datagrams from ``flood_at_s`` of wall time after the companion
    reports OFFBOARD active. The flood must end before the flight does (``flood_inside``):
    once the vehicle is gone for ``mavlink.repin_after_s`` an unsigned spoofer may take the
    pin, which is not what this probe measures."""
    t_w, c0 = time.monotonic(), children_cpu_s()
    datagrams, kinds = hostile_datagrams(n, seed)
    load0 = load_avg()
    window: dict[str, Any] = {}
    drops = {"bound": 0, "connected": 0}
    with flight(out, scenario=scenario, duration_s=duration_s, realtime=realtime) as f:
        def sample_drops() -> None:
            for k, v in udp_socket_drops(f.comp_port).items():
                drops[k] = max(drops[k], v)

        def attack() -> None:
            # during the flight: once OFFBOARD is active (the vehicle is pinned by then)
            while f.comp.poll() is None and f.sim.poll() is None:
                if "-> active" in (out / "companion.log").read_text():
                    break
                time.sleep(0.05)
            time.sleep(flood_at_s)
            if f.comp.poll() is None and f.sim.poll() is None:
                window["t0"], window["t1"], window["errors"] = send_flood(
                    f.comp_port, datagrams, rate_per_s)
        th = threading.Thread(target=attack, daemon=True)
        th.start()
        sim_rc, comp_rc = wait_flight(f, 120.0 + 3.0 * duration_s, every=sample_drops,
                                      period_s=0.2)
        th.join(timeout=60)
    log = out / "flight.mcap"
    figs = flight_figures(log)
    accepted, first_bad_ns = attacker_frames_accepted(log)
    t0 = window.get("t0", math.nan)
    t1 = window.get("t1", math.nan)
    in_win = [(t, lvl) for t, lvl in _step_levels(log) if t0 <= t <= t1 + 1.0]
    not_tracking = sum(1 for _, lvl in in_win if lvl != "tracking")
    changes = sum(1 for a, b in itertools.pairwise(in_win) if a[1] != b[1])
    bad_cmds = _commands_after(log, first_bad_ns) if first_bad_ns is not None else 0
    stats = _last_stats(log)
    ended = f.sim.returncode is not None
    flood_inside = "t1" in window and _last_step_ns(log) * 1e-9 >= t1 + 1.0
    ok = (sim_rc == 0 and comp_rc == 0 and accepted == 0 and flood_inside and bad_cmds == 0
          and figs.non_finite_commands == 0 and not_tracking == 0 and figs.offboard_left == 0
          and bool(in_win) and drops["connected"] == 0)
    rate = n / (t1 - t0) if t1 > t0 else math.nan
    res = ProbeResult(
        probe=f"flood ({'realtime' if realtime else 'lockstep'} flight)",
        inputs=f"{n} datagrams in {t1 - t0:.2f} s ({rate:.0f}/s): " + ", ".join(
            f"{v} {k}" for k, v in kinds.items()),
        result=(f"{accepted} attacker frames accepted; steps in the flood window "
                f"{len(in_win)}, not tracking {not_tracking}, level changes {changes}; "
                f"offboard left {figs.offboard_left}x; companion rc {comp_rc}"),
        passed=ok,
        data_lost=(f"kernel drops: vehicle/AGV sockets {drops['connected']}, unknown-sender "
                   f"socket {drops['bound']}; "
                   f"dropped unparsed: spoofed_source {stats.get('spoofed_source', 0)}, "
                   f"rate_limited {stats.get('rate_limited', 0)}"),
        bad_commands=bad_cmds + figs.non_finite_commands,
        figures={"flight": figs.to_json(), "link_counters": stats, "send_errors":
                 window.get("errors"), "kernel_drops": drops, "load_before": load0,
                 "load_after": load_avg(), "flood_inside_flight": flood_inside,
                 "sim_ended": ended,
                 "flood_window_s": [t0 - f.t_start, t1 - f.t_start] if "t0" in window else None},
        wall_s=time.monotonic() - t_w,
        cpu_s=children_cpu_s() - c0,
    )
    return res


def _step_levels(log: Path) -> list[tuple[float, str]]:
    """(monotonic receipt time s of the frame, safety level) of every control step."""
    out = []
    with LogReader(log) as r:
        for m in r.messages(topics=["/control/step"]):
            d = m.data or {}
            out.append((m.log_time_ns * 1e-9, str((d.get("safety") or {}).get("level"))))
    return out


def _last_step_ns(log: Path) -> int:
    last = 0
    with LogReader(log) as r:
        for m in r.messages(topics=["/control/step"], decode=False):
            last = m.log_time_ns
    return last


def _commands_after(log: Path, t_ns: int) -> int:
    with LogReader(log) as r:
        return sum(1 for _ in r.messages(topics=["/mavlink/out/SET_ATTITUDE_TARGET"],
                                         start_ns=t_ns))


def _last_stats(log: Path) -> dict[str, int]:
    last: dict[str, int] = {}
    with LogReader(log) as r:
        for m in r.messages(topics=["/mavlink/stats"]):
            last = dict((m.data or {}).get("counters", {}))
    return last


if __name__ == "__main__":
    import argparse
    import json

    ap = argparse.ArgumentParser()
    ap.add_argument("--n", type=int, default=100_000)
    ap.add_argument("--out", type=Path, default=Path("out/reliability/flood"))
    ap.add_argument("--realtime", action="store_true")
    a = ap.parse_args()
    print(json.dumps(run_flood(a.out, a.n, realtime=a.realtime).to_json(), indent=2,
                     default=str))
