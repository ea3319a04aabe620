"""An independent client flies the emulator: MAVSDK 4.x (C++ core) over UDP on 127.0.0.1."""

from __future__ import annotations

import asyncio
import dataclasses
import math
import socket
import time
from collections.abc import Awaitable, Callable
from typing import Any

import pytest
from mavsdk.asyncio import ComponentType, Configuration, Mavsdk
from mavsdk.asyncio.plugins.action import ActionAsync
from mavsdk.asyncio.plugins.offboard import Attitude, OffboardAsync
from mavsdk.asyncio.plugins.telemetry import TelemetryAsync
from mavsdk.plugins.telemetry import FlightMode

from sim_bridge.config import with_link
from tests.sim.harness import make_config, run_sim


def _free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


async def _until(get: Callable[[], Awaitable[Any]], ok: Callable[[Any], bool],
                 timeout_s: float, what: str) -> Any:
    end = time.monotonic() + timeout_s
    last = None
    while time.monotonic() < end:
        last = await get()
        if ok(last):
            return last
        await asyncio.sleep(0.05)
    raise AssertionError(f"timed out waiting for {what}; last value {last!r}")


def _mode(v: Any) -> str:
    return FlightMode(int(v)).name


async def _fly(port: int) -> dict[str, Any]:
    seen: dict[str, Any] = {}
    config = Configuration.create_with_component_type(ComponentType.GROUND_STATION)
    async with Mavsdk(config) as mavsdk:
        await mavsdk.add_any_connection(f"udpin://127.0.0.1:{port}")
        system = await mavsdk.first_autopilot(10.0)
        assert system is not None, "MAVSDK found no autopilot"
        tel, action, offboard = TelemetryAsync(system), ActionAsync(system), OffboardAsync(system)

        # telemetry: attitude, position/velocity, armed, flight mode
        att = await _until(tel.attitude_euler, lambda a: math.isfinite(a.roll_deg), 5, "attitude")
        assert abs(att.roll_deg) < 0.1 and abs(att.pitch_deg) < 0.1
        assert math.isclose(att.yaw_deg, 22.5, abs_tol=0.1)  # the paper scenario's yaw
        pv = await _until(tel.position_velocity_ned, lambda p: math.isfinite(p.position.down_m),
                          5, "position")
        assert math.isclose(pv.position.down_m, 0.3, abs_tol=1e-3)  # on the ground
        assert math.isclose(pv.position.north_m, -0.2, abs_tol=1e-3)
        assert await tel.armed() is False
        await _until(tel.flight_mode, lambda m: _mode(m) == "POSCTL", 3, "POSCTL")
        await _until(tel.in_air, lambda v: v is False, 3, "on ground")

        await action.arm()
        await _until(tel.armed, lambda v: v is True, 3, "armed")

        # attitude setpoint, offboard start: the heartbeat must report OFFBOARD
        await offboard.set_attitude(Attitude(8.0, 0.0, 30.0, 0.56))
        await offboard.start()
        await _until(tel.flight_mode, lambda m: _mode(m) == "OFFBOARD", 3, "OFFBOARD")
        a = await _until(tel.attitude_euler,
                         lambda a: abs(a.roll_deg - 8.0) < 0.3 and abs(a.yaw_deg - 30.0) < 0.3,
                         3, "attitude to follow the setpoint")
        seen["attitude"] = a
        pv = await _until(tel.position_velocity_ned, lambda p: p.position.down_m < -0.5, 5,
                          "climb")
        assert pv.velocity.east_m_s > 0.1  # rolled right: drifts east
        await _until(tel.in_air, lambda v: v is True, 3, "in air")
        await offboard.set_attitude(Attitude(-4.0, 0.0, 30.0, 0.5))
        await _until(tel.attitude_euler, lambda a: abs(a.roll_deg + 4.0) < 0.3, 3, "new roll")

        # stop offboard -> Hold; land; disarmed once on the ground
        await offboard.stop()
        await _until(tel.flight_mode, lambda m: _mode(m) == "HOLD", 3, "HOLD")
        await action.land()
        await _until(tel.flight_mode, lambda m: _mode(m) == "LAND", 3, "LAND")
        await _until(tel.in_air, lambda v: v is False, 15, "touch-down")
        try:
            await action.disarm()
        except Exception as e:  # auto-disarm (COM_DISARM_LAND) may have come first
            seen["disarm_error"] = repr(e)
        await _until(tel.armed, lambda v: v is False, 4, "disarmed")
        seen["final_mode"] = _mode(await tel.flight_mode())
    return seen


@pytest.mark.slow
@pytest.mark.parametrize("attitude_model", ["first-order", "px4"])
def test_mavsdk_flies_the_emulator(attitude_model: str) -> None:
    port = _free_udp_port()
    cfg = make_config(start="ground")
    veh = dataclasses.replace(cfg.sim.vehicle, attitude_model=attitude_model)
    cfg = dataclasses.replace(cfg, sim=dataclasses.replace(cfg.sim, vehicle=veh))
    cfg = with_link(cfg, offboard_remote=f"127.0.0.1:{port}")
    with run_sim(cfg) as rs:
        seen = asyncio.run(_fly(port))
        stats = rs.call(rs.sim.stats)
    assert seen["final_mode"] == "LAND"
    assert stats.setpoints_received > 20  # MAVSDK's 20 Hz stream
    assert stats.acks_sent == stats.commands
    assert stats.offboard.rx_bad == 0 and stats.offboard.rx_foreign == 0
