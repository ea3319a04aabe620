"""A companion-free client (plain pymavlink over UDP) flies the PX4-cascade vehicle in lockstep:
a level attitude setpoint at the vehicle's TRUE hover thrust holds the height, the same setpoint
at the configured MPC_THR_HOVER (what a client believing the parameter would send) sinks."""

from __future__ import annotations

import dataclasses
import time
from typing import Any

import pytest

from sim_bridge.config import with_link
from tests.sim.harness import MavClient, make_config, run_sim

Q_LEVEL_YAW_22_5 = [0.98078528, 0.0, 0.0, 0.19509032]  # the paper scenario's yaw


def _fly(client: MavClient, thrust: float) -> dict[int, float]:
    """Stream the setpoint, switch to OFFBOARD at 1.5 s, keep streaming to 5 s; z by time."""
    cfg = make_config(time_mode="lockstep", lockstep_timeout_s=0.02)
    veh = dataclasses.replace(cfg.sim.vehicle, attitude_model="px4", true_hover_thrust=0.6)
    cfg = with_link(
        dataclasses.replace(cfg, sim=dataclasses.replace(cfg.sim, vehicle=veh)),
        offboard_remote=f"127.0.0.1:{client.port}",
    )
    z_by_ms: dict[int, float] = {}
    switched = False
    with run_sim(cfg, duration_s=100.0) as rs:
        client.target = ("127.0.0.1", rs.ports["offboard"])
        end = time.monotonic() + 60.0
        while time.monotonic() < end:
            for m in client.recv(0.05):
                kind: Any = m.get_type()
                if kind == "LOCAL_POSITION_NED":
                    z_by_ms[m.time_boot_ms] = m.z
                if kind != "ATTITUDE_QUATERNION":
                    continue
                client.send(
                    client.mav.set_attitude_target_encode(
                        m.time_boot_ms, 1, 1, 7, Q_LEVEL_YAW_22_5, 0, 0, 0, thrust
                    )
                )
                if m.time_boot_ms >= 1500 and not switched:
                    client.command(176, 1, 6, 0)  # DO_SET_MODE OFFBOARD
                    switched = True
            if z_by_ms and max(z_by_ms) >= 5000:
                break
        mode = rs.call(lambda: rs.sim.px4.mode.label)
    assert switched and mode == "OFFBOARD"
    return z_by_ms


def _z_at(z_by_ms: dict[int, float], t_ms: int) -> float:
    return z_by_ms[min(z_by_ms, key=lambda k: abs(k - t_ms))]


@pytest.mark.slow
def test_true_hover_thrust_holds_and_the_parameter_sinks(client: MavClient) -> None:
    held = _fly(client, 0.6)
    client.drain()
    sunk = _fly(client, 0.5)
    dz_held = _z_at(held, 5000) - _z_at(held, 1500)
    dz_sunk = _z_at(sunk, 3500) - _z_at(sunk, 1500)
    print(
        f"thrust 0.6 (true hover): dz {dz_held * 100:+.1f} cm over 3.5 s; thrust 0.5 "
        f"(MPC_THR_HOVER): dz {dz_sunk * 100:+.1f} cm over 2 s"
    )
    assert abs(_z_at(held, 1500) + 3.2) < 0.05  # PX4's own hold kept the start height
    assert abs(dz_held) < 0.05
    # g (1 - 0.5 / 0.6) = 1.64 m/s^2 down: 3.27 m in 2 s without drag and motor lag
    assert 2.5 < dz_sunk < 3.27
