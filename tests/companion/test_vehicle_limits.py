"""The vehicle's limits from the autopilot (docs/guides/vehicle-limits.md): the companion's
parameter read over real UDP against the emulator (by name, an INT32 decoded byte-wise, a
missing parameter, an autopilot that does not answer), the bounds built from the values, and
the configured bounds the autopilot would refuse."""

from __future__ import annotations

import asyncio
import math
import socket
import struct
import time

import pytest
from pymavlink.dialects.v20 import common as mavlink2

from companion.config import load_config
from companion.control.vehicle_limits import (
    PARAM_NAMES,
    apply_limits,
    autopilot_bounds,
    refused_bounds,
)
from companion.link import MavlinkLink, default_allow_rules
from companion.link.params import ParamReader, decode_param_value
from sim_bridge.config import with_link
from sim_bridge.config.links import ImpairmentConfig
from sim_bridge.impairment import ImpairmentParams
from sim_bridge.px4_params import px4_param_specs
from tests.sim.harness import make_config, run_sim

PX4_DEFAULTS = {"MPC_XY_VEL_MAX": 12.0, "MPC_Z_VEL_MAX_UP": 3.0, "MPC_Z_VEL_MAX_DN": 1.5,
                "MPC_ACC_HOR": 3.0, "MPC_ACC_HOR_MAX": 5.0, "MPC_ACC_UP_MAX": 4.0,
                "MPC_ACC_DOWN_MAX": 3.0, "MPC_TILTMAX_AIR": 45.0, "MC_YAWRATE_MAX": 200.0,
                "MPC_YAWRAUTO_MAX": 60.0, "MPC_THR_HOVER": 0.5}


def _link(port: int = 0) -> MavlinkLink:
    return MavlinkLink(f"udpin:127.0.0.1:{port}", source_system=1, source_component=191,
                       target_system=1, target_component=1,
                       allow=default_allow_rules(1, 1, 42, 1))


async def _read_from_emulator(names: tuple[str, ...], timeout_s: float = 0.3, retries: int = 3,
                              **sim_changes: object) -> tuple[
        dict[str, float], tuple[str, ...], int, dict[str, int]]:
    async with _link() as link:
        port = link.local_address[1]  # type: ignore[index]
        cfg = with_link(make_config(**sim_changes), offboard_remote=f"127.0.0.1:{port}")
        reader = ParamReader(link, 1, 1)

        async def feed() -> None:
            async for rx in link:
                if rx.name == "PARAM_VALUE":
                    reader.on_param_value(rx.msg.to_dict(), rx.src_sysid, rx.src_compid)

        with run_sim(cfg):
            task = asyncio.create_task(feed())
            res = await reader.read(names, timeout_s=timeout_s, retries=retries)
            task.cancel()
        types = {n: p.param_type for n, p in res.values.items()}
        return {n: p.value for n, p in res.values.items()}, res.missing, res.requests_sent, types


def test_the_companion_reads_the_emulators_limits_over_udp() -> None:
    names = (*PARAM_NAMES, "SYS_AUTOSTART", "NO_SUCH_PARAM")
    t0 = time.monotonic()
    values, missing, sent, types = asyncio.run(_read_from_emulator(names))
    elapsed = time.monotonic() - t0
    expect = {s.name: float(s.default) for s in px4_param_specs(make_config())}
    for n in PARAM_NAMES:
        assert values[n] == pytest.approx(expect[n], rel=1e-6), n
    assert values["MPC_XY_VEL_MAX"] == 12.0 and values["MPC_THR_HOVER"] == 0.5
    # an INT32 travels byte-wise and is decoded as such (4001, not the denormal 5.6e-42)
    assert types["SYS_AUTOSTART"] == 6 and values["SYS_AUTOSTART"] == 4001.0
    # a name the autopilot does not know: no answer (as PX4), asked 3 times, reported missing
    assert missing == ("NO_SUCH_PARAM",)
    # every name once, the missing one twice more (a late answer on a loaded machine: again)
    assert len(names) + 2 <= sent <= 3 * len(names)
    assert elapsed < 30.0  # it ends (3 rounds of 0.3 s plus the emulator's start)


def test_sim_params_override_what_the_emulator_serves() -> None:
    values, missing, _, _ = asyncio.run(_read_from_emulator(
        ("MPC_XY_VEL_MAX", "MPC_YAWRAUTO_MAX"),
        params=(("MPC_XY_VEL_MAX", 5.0), ("MPC_YAWRAUTO_MAX", 30.0))))
    assert values == {"MPC_XY_VEL_MAX": 5.0, "MPC_YAWRAUTO_MAX": 30.0} and missing == ()


def _impaired(to_companion: ImpairmentParams, to_vehicle: ImpairmentParams,
              seed: int) -> ImpairmentConfig:
    return ImpairmentConfig(links=("offboard",), seed=seed, vehicle_to_companion=to_companion,
                            companion_to_vehicle=to_vehicle)


def test_a_slow_autopilot_is_waited_for() -> None:
    """Every answer arrives 1 s after its request (a loaded autopilot or link): 3 tries of a
    fixed 0.3 s would give up after 0.9 s with everything missing; the tries back off
    (0.3, 0.6, 1.2 s) and the answers to the first requests are taken when they come."""
    slow = _impaired(ImpairmentParams(delay_s=1.0), ImpairmentParams(), seed=3)
    values, missing, sent, _ = asyncio.run(_read_from_emulator(
        PARAM_NAMES, timeout_s=0.3, retries=3, impairment=slow))
    assert missing == ()
    assert values["MPC_XY_VEL_MAX"] == 12.0 and values["MPC_THR_HOVER"] == 0.5
    assert sent <= 3 * len(PARAM_NAMES)


def test_a_lossy_link_loses_no_parameter() -> None:
    """A quarter of the datagrams lost each way, with delay, jitter, reordering, duplicates:
    each lost request or answer costs one more request of that name alone."""
    lossy = _impaired(
        ImpairmentParams(drop_p=0.25, delay_s=0.05, jitter_s=0.05, reorder_p=0.1,
                         duplicate_p=0.05),
        ImpairmentParams(drop_p=0.25, delay_s=0.02, jitter_s=0.02), seed=11)
    values, missing, sent, _ = asyncio.run(_read_from_emulator(
        PARAM_NAMES, timeout_s=0.2, retries=12, impairment=lossy))
    assert missing == ()
    expect = {s.name: float(s.default) for s in px4_param_specs(make_config())}
    assert values == pytest.approx({n: expect[n] for n in PARAM_NAMES}, rel=1e-6)
    # some were asked again (P(no loss on 11 round trips) = 0.56^11 ~ 0.2 %), never a round
    assert len(PARAM_NAMES) < sent


def test_an_autopilot_that_does_not_answer_times_out_with_every_name_missing() -> None:
    """A peer that sends HEARTBEATs (so the link knows where to send) and never answers."""

    async def main() -> tuple[tuple[str, ...], int, float, int]:
        async with _link() as link:
            port = link.local_address[1]  # type: ignore[index]
            sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            sock.bind(("127.0.0.1", 0))
            mav = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
            hb = mav.heartbeat_encode(2, 12, 0, 0, 3).pack(mav)
            reader = ParamReader(link, 1, 1)

            async def beat() -> None:
                while True:
                    sock.sendto(hb, ("127.0.0.1", port))
                    await asyncio.sleep(0.05)

            task = asyncio.create_task(beat())
            t0 = time.monotonic()
            res = await reader.read(("MPC_XY_VEL_MAX", "MPC_ACC_HOR"), timeout_s=0.2, retries=2)
            dt = time.monotonic() - t0
            task.cancel()
            received = 0
            sock.setblocking(False)
            while True:
                try:
                    data = sock.recv(4096)
                except BlockingIOError:
                    break
                received += data.count(b"\xfd")  # MAVLink 2 frames the peer got
            sock.close()
            return res.missing, res.requests_sent, dt, received

    missing, sent, dt, received = asyncio.run(main())
    assert missing == ("MPC_XY_VEL_MAX", "MPC_ACC_HOR")
    assert sent == 4 and received >= 4  # 2 names x 2 tries, on the wire
    assert dt >= 0.6  # it waited both tries (0.2 s, then twice that) before giving up


def test_no_autopilot_heard_means_nothing_sent_and_everything_missing() -> None:
    async def main() -> tuple[tuple[str, ...], int]:
        async with _link() as link:
            res = await ParamReader(link, 1, 1).read(("MPC_ACC_HOR",), timeout_s=0.1,
                                                     peer_timeout_s=0.2)
            return res.missing, res.requests_sent

    assert asyncio.run(main()) == (("MPC_ACC_HOR",), 0)


def test_bytewise_decoding_of_integer_types() -> None:
    as_float = struct.unpack("<f", struct.pack("<i", -7))[0]
    assert math.isnan(as_float) and decode_param_value(6, as_float) == -7.0
    assert decode_param_value(6, struct.unpack("<f", struct.pack("<i", 4001))[0]) == 4001.0
    assert decode_param_value(1, struct.unpack("<f", bytes([1, 0, 0, 0]))[0]) == 1.0
    assert decode_param_value(9, 0.25) == 0.25
    with pytest.raises(ValueError, match="param_type 8"):
        decode_param_value(8, 0.0)


def test_bounds_from_px4_defaults_with_the_margin() -> None:
    cfg = load_config("config/realistic.toml")
    assert cfg.vehicle_limits.from_autopilot and cfg.vehicle_limits.margin == 0.2
    out, overrides = apply_limits(cfg, PX4_DEFAULTS)
    g = cfg.rmpc.g_m_s2
    assert out.rmpc.eta_max[4:] == (9.6, 9.6, 1.2)          # 0.8 x 12, 0.8 x min(3, 1.5)
    assert out.rmpc.eta_max[:4] == cfg.rmpc.eta_max[:4]     # the image bounds untouched
    assert out.rmpc.u_max == (2.4, 2.4, 2.4, round(0.8 * math.radians(60.0), 3))
    assert out.control.hover_thrust == 0.5
    assert overrides[1] == f"rmpc.u_max={list(out.rmpc.u_max)!r}"
    # a tilt limit below what MPC_ACC_HOR asks binds instead: g tan(15 deg) = 2.63 < 3
    low = apply_limits(cfg, {**PX4_DEFAULTS, "MPC_TILTMAX_AIR": 15.0})[0]
    assert low.rmpc.u_max[0] == round(0.8 * g * math.tan(math.radians(15.0)), 3)
    # a missing parameter keeps the configured bound
    part = apply_limits(cfg, {"MPC_ACC_HOR": 3.0})[0]
    assert part.rmpc.eta_max == cfg.rmpc.eta_max and part.rmpc.u_max[2:] == cfg.rmpc.u_max[2:]
    assert autopilot_bounds({}, g)["v_xy_m_s"] is None


def test_configured_bounds_beyond_the_autopilots_are_reported_with_their_key() -> None:
    paper = load_config("config/paper.toml")
    assert not paper.vehicle_limits.from_autopilot
    assert refused_bounds(paper, PX4_DEFAULTS) == []  # the paper's numbers are inside PX4's
    tight = {**PX4_DEFAULTS, "MPC_XY_VEL_MAX": 0.8, "MPC_YAWRAUTO_MAX": 10.0,
             "MPC_TILTMAX_AIR": 20.0, "MPC_ACC_HOR": 2.0}
    lines = refused_bounds(load_config("config/paper.toml", ["rmpc.u_max=[3.0, 3.0, 3.0, 0.3]"]),
                           tight)
    text = "\n".join(lines)
    assert "rmpc.eta_max[4] = 2 m/s is beyond the autopilot's MPC_XY_VEL_MAX" not in text
    assert "rmpc.eta_max[4] = 1 m/s is beyond the autopilot's MPC_XY_VEL_MAX (0.8 m/s)" in text
    assert "rmpc.u_max[3] = 0.3 rad/s is beyond" in text  # 10 deg/s = 0.17 rad/s
    assert "rmpc.u_max[0] = 3 m/s^2" in text
    assert "MPC_TILTMAX_AIR (20.0 deg)" in text
