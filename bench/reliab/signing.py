"""Signing: MAVLink 2 signing on both ends of a lockstep flight, attacked from the side.

The emulator signs and verifies like PX4 with a provisioned key (``[sim.signing]``); the
companion with ``mavlink.signing_key_file``. With ``mavlink.allowed_sources = ["127.0.0.1"]``
the receive guard lets the attacker's frames through to the signature check, so this probe
tests signing alone. During the flight, at each end: unsigned frames claiming the other end's
identity, one frame with a forged signature stamped 2^48 - 2 (pymavlink 2.4.50 would then
refuse every later frame of that stream: docs/reference/pitfalls.md), and replays of genuine frames
read back from the companion's log. The flight must go on in OFFBOARD with the legitimate streams.
"""

from __future__ import annotations

import base64
import os
import re
import socket
import threading
import time
from pathlib import Path
from typing import Any

from pymavlink.dialects.v20 import common as mavlink2

from bench.reliab.common import (
    PAPER,
    ProbeResult,
    children_cpu_s,
    flight,
    flight_figures,
    load_avg,
    wait_flight,
)
from bench.reliab.flood import MARK_MS, attacker_frames_accepted
from companion.log.reader import LogReader

FORGED_TS = (1 << 48) - 2


def forged_frame(msg: Any, sysid: int, compid: int, ts: int = FORGED_TS) -> bytes:
    """``msg`` as a signed MAVLink 2 frame with timestamp ``ts`` and a signature made with a
    key nobody has."""
    mav = mavlink2.MAVLink(None, srcSystem=sysid, srcComponent=compid)
    mav.signing.secret_key = os.urandom(32)
    mav.signing.sign_outgoing = True
    mav.signing.link_id = 0
    mav.signing.timestamp = ts
    return bytes(msg.pack(mav))


def _raw_frames(log: Path, topic: str, n: int) -> list[bytes]:
    out: list[bytes] = []
    try:
        with LogReader(log) as r:
            for m in r.messages(topics=[topic]):
                out.append(base64.b64decode((m.data or {})["raw_b64"]))
                if len(out) >= n:
                    break
    except Exception:  # a log still being written: whatever is readable
        pass
    return out


def _counts_after(log: Path, topic: str, t_ns: int) -> int:
    with LogReader(log) as r:
        return sum(1 for _ in r.messages(topics=[topic], start_ns=t_ns))


def _sim_signing_counters(sim_log: Path) -> dict[str, int]:
    pat = re.compile(r"signing offboard: rejected (\d+) unsigned, (\d+) bad signature, "
                     r"(\d+) replayed")
    for line in sim_log.read_text().splitlines():
        m = pat.search(line)
        if m:
            return dict(zip(("unsigned", "bad_signature", "replayed"),
                            map(int, m.groups()), strict=True))
    return {}


def _attack(f: Any, out: Path, sent: dict[str, Any], n_unsigned: int, n_replay: int,
            attack_at_s: float) -> None:
    """The attacker, from the side, during the flight: unsigned frames claiming each end's
    identity, one forged signature, then genuine frames replayed from the log."""
    # during the flight: once OFFBOARD is active (both ends up and talking; a fixed wall
    # time after the start sent the emulator's share to an unbound port under load)
    while f.comp.poll() is None and f.sim.poll() is None:
        if "-> active" in (out / "companion.log").read_text():
            break
        time.sleep(0.05)
    time.sleep(attack_at_s)
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    ap = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
    comp = mavlink2.MAVLink(None, srcSystem=1, srcComponent=191)
    to_c, to_v = ("127.0.0.1", f.comp_port), ("127.0.0.1", f.sim_port)
    for i in range(n_unsigned):  # unsigned, plausible, marked
        s.sendto(bytes(ap.attitude_quaternion_encode(MARK_MS + i, 1, 0, 0, 0, 0, 0, 0)
                       .pack(ap)), to_c)
        s.sendto(bytes(comp.set_attitude_target_encode(
            0, 1, 1, 7, [1, 0, 0, 0], 0, 0, 0, 0.0).pack(comp)), to_v)
        time.sleep(0.002)
    sent["t_forge_ns"] = time.monotonic_ns()
    s.sendto(forged_frame(ap.heartbeat_encode(2, 12, 209, 3 << 16, 8, 3), 1, 1), to_c)
    s.sendto(forged_frame(comp.set_attitude_target_encode(
        0, 1, 1, 7, [1, 0, 0, 0], 0, 0, 0, 0.0), 1, 191), to_v)
    # genuine frames to replay, from the log being written (flushed about every second; under
    # load a chunk can take longer: wait until both directions have some, at most 15 s)
    rin: list[bytes] = []
    rout: list[bytes] = []
    deadline = time.monotonic() + 15.0
    while time.monotonic() < deadline and f.sim.poll() is None:
        time.sleep(1.0)
        rin = _raw_frames(f.out / "flight.mcap", "/mavlink/in/ATTITUDE_QUATERNION", n_replay)
        rout = _raw_frames(f.out / "flight.mcap", "/mavlink/out/SET_ATTITUDE_TARGET",
                           n_replay)
        if rin and rout:
            break
    for d in rin:
        s.sendto(d, to_c)
    for d in rout:
        s.sendto(d, to_v)
    sent.update(replayed_in=len(rin), replayed_out=len(rout))
    s.close()


def run_signing(out: Path, duration_s: float = 30.0, n_unsigned: int = 200,
                n_replay: int = 50, attack_at_s: float = 4.0) -> ProbeResult:
    t_w, c0 = time.monotonic(), children_cpu_s()
    out.mkdir(parents=True, exist_ok=True)
    key = os.urandom(32)
    (out / "key.hex").write_text(key.hex() + "\n")
    sim_cfg = out / "signing.toml"
    sim_cfg.write_text(f'base = "{PAPER}"\n\n[sim.signing]\nenabled = true\n'
                       f'key_hex = "{key.hex()}"\n')
    overrides = [f'mavlink.signing_key_file="{out / "key.hex"}"',
                 'mavlink.allowed_sources=["127.0.0.1"]']
    sent: dict[str, Any] = {}
    load0 = load_avg()
    with flight(out, duration_s=duration_s, overrides=overrides, sim_config=sim_cfg) as f:
        th = threading.Thread(target=_attack, args=(f, out, sent, n_unsigned, n_replay,
                                                    attack_at_s), daemon=True)
        th.start()
        sim_rc, comp_rc = wait_flight(f, 120.0 + 4.0 * duration_s)
        th.join(timeout=30)
    log = out / "flight.mcap"
    figs = flight_figures(log)
    accepted_bad, _ = attacker_frames_accepted(log)
    stats: dict[str, int] = {}
    with LogReader(log) as r:
        for m in r.messages(topics=["/mavlink/stats"]):
            stats = dict((m.data or {}).get("counters", {}))
    after = _counts_after(log, "/mavlink/in/ATTITUDE_QUATERNION", sent.get("t_forge_ns", 0))
    signed_in = 0
    with LogReader(log) as r:
        for m in r.messages(topics=["/mavlink/in/ATTITUDE_QUATERNION"]):
            signed_in += bool((m.data or {}).get("signed"))
    simc = _sim_signing_counters(out / "sim.log")
    ok = (sim_rc == 0 and comp_rc == 0 and accepted_bad == 0 and figs.offboard_left == 0
          and stats.get("unsigned", 0) >= n_unsigned and stats.get("bad_signature", 0) >= 1
          and stats.get("old_timestamp", 0) >= sent.get("replayed_in", 1) > 0
          and after > 0 and simc.get("unsigned", 0) > 0
          and simc.get("bad_signature", 0) >= 1
          and simc.get("replayed", 0) >= sent.get("replayed_out", 1) > 0)
    return ProbeResult(
        probe="signing (lockstep flight, both ends signed)",
        inputs=(f"per end: {n_unsigned} unsigned, 1 forged (ts 2^48-2), "
                f"{sent.get('replayed_in')}/{sent.get('replayed_out')} replayed (in/out)"),
        result=(f"companion rejected unsigned {stats.get('unsigned', 0)}, bad signature "
                f"{stats.get('bad_signature', 0)}, replay {stats.get('old_timestamp', 0)}; "
                f"{after} legitimate ATTITUDE_QUATERNION accepted after the forged frame; "
                f"emulator rejected {simc}; offboard left {figs.offboard_left}x; "
                f"{accepted_bad} attacker frames accepted"),
        passed=ok,
        data_lost="none beyond the attack frames (all rejected)",
        bad_commands=accepted_bad + figs.non_finite_commands,
        figures={"flight": figs.to_json(), "companion_counters": stats, "emulator": simc,
                 "signed_accepted": signed_in, "load_before": load0, "load_after": load_avg()},
        wall_s=time.monotonic() - t_w,
        cpu_s=children_cpu_s() - c0,
    )


if __name__ == "__main__":
    import json

    print(json.dumps(run_signing(Path("out/reliability/signing")).to_json(), indent=2,
                     default=str))
