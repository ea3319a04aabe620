"""The emulator's config loader: validated, frozen, ``base =`` deep merge, scenarios."""

from __future__ import annotations

import dataclasses
import re
from pathlib import Path

import pytest

from sim_bridge import ConfigError
from sim_bridge.config import DEFAULT_CONFIG, deep_merge, load_config, with_link, with_sim


def test_paper_config() -> None:
    c = load_config()
    assert c.scenario.name == "paper"
    assert c.scenario.uav_pose[:3] == (-0.2, 0.4, -3.2)
    assert c.sim.link.offboard_local_port == 14580 and c.sim.link.offboard_remote.endswith(
        ":14540")
    assert c.sim.vehicle.hover_thrust == 0.5 and c.sim.px4.com_of_loss_t_s == 1.0
    assert c.camera.width_px == 1000 and c.target.mavlink_sysid == 42
    assert c.ground_z_m == pytest.approx(0.3)  # AGV top at z = 0, 0.3 m high
    with pytest.raises(dataclasses.FrozenInstanceError):
        c.sim.seed = 3  # type: ignore[misc]


def test_scenario_by_name() -> None:
    assert load_config(scenario="edge").scenario.uav_pose[0] == -1.0
    with pytest.raises(ConfigError, match=r"sim\.scenarios\.nope"):
        load_config(scenario="nope")


def _variant(tmp_path: Path, body: str) -> Path:
    (tmp_path / "paper.toml").write_text(DEFAULT_CONFIG.read_text())
    p = tmp_path / "variant.toml"
    p.write_text('base = "paper.toml"\n' + body)
    return p


def test_base_deep_merge(tmp_path: Path) -> None:
    p = _variant(tmp_path, "[sim]\ntime_mode = \"lockstep\"\n[sim.vehicle]\ndrag_per_s = 0.2\n"
                 "[sim.scenarios.mine]\nuav_pose = [1.0, 2.0, -4.0, 0.0, 0.0, 0.0]\n")
    c = load_config(p, scenario="mine")
    assert c.sim.time_mode == "lockstep"
    assert c.sim.vehicle.drag_per_s == 0.2
    assert c.sim.vehicle.hover_thrust == 0.5  # kept from the base
    assert c.scenario.uav_pose == (1.0, 2.0, -4.0, 0.0, 0.0, 0.0)
    assert load_config(p, scenario="paper").scenario.uav_pose[0] == -0.2
    assert deep_merge({"a": {"b": 1, "c": 2}}, {"a": {"c": 3}}) == {"a": {"b": 1, "c": 3}}


@pytest.mark.parametrize(("body", "key"), [
    ("[sim.vehicle]\nhover_thrust = 1.5\n", "sim.vehicle.hover_thrust"),
    ("[sim.vehicle]\nmax_tilt_rad = \"a\"\n", "sim.vehicle.max_tilt_rad"),
    ("[sim.px4]\ncom_obl_rc_act = 9\n", "sim.px4.com_obl_rc_act"),
    ("[sim]\ntime_mode = \"fast\"\n", "sim.time_mode"),
    ("[sim.link]\noffboard_remote = \"nohost\"\n", "sim.link.offboard_remote"),
    ("[sim.link]\ngcs_local_port = 70000\n", "sim.link.gcs_local_port"),
    ("[sim.link]\nsysid = true\n", "sim.link.sysid"),
    ("[sim.camera]\nocclusions = [[2.0, 1.0]]\n", "sim.camera.occlusions[0]"),
    ("[sim.disturbance]\nwind_accel_ned_m_s2 = [0.0, 1.0]\n",
     "sim.disturbance.wind_accel_ned_m_s2"),
    ("[sim.vehicle]\ntypo_key = 1.0\n", "sim.vehicle"),
    ("[target]\nmavlink_sysid = 0\n", "target.mavlink_sysid"),
    ("[sim]\nphysics_dt_s = 0.1\n", "sim.physics_dt_s"),
])
def test_bad_values_name_their_key(tmp_path: Path, body: str, key: str) -> None:
    with pytest.raises(ConfigError, match=re.escape(key)):
        load_config(_variant(tmp_path, body))


def test_missing_and_looping_files(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="cannot read"):
        load_config(tmp_path / "absent.toml")
    a = tmp_path / "a.toml"
    a.write_text('base = "a.toml"\n')
    with pytest.raises(ConfigError, match="loops"):
        load_config(a)
    bad = tmp_path / "bad.toml"
    bad.write_text("[sim\n")
    with pytest.raises(ConfigError, match="not valid TOML"):
        load_config(bad)


def test_link_overrides_are_validated() -> None:
    c = with_link(load_config(), offboard_local_port=0, truth_remote="10.0.0.2:6000")
    assert c.sim.link.offboard_local_port == 0 and c.sim.link.truth_remote == "10.0.0.2:6000"
    with pytest.raises(ConfigError, match=r"sim\.link\.frame_port"):
        with_link(load_config(), frame_port=-1)
    with pytest.raises(ConfigError, match=r"sim\.link\.nope"):
        with_link(load_config(), nope=1)


def test_camera_rate_that_lockstep_would_ignore_is_refused_by_name(tmp_path: Path) -> None:
    """In lockstep the camera fires once per ``sim.step_dt_s``: a ``sim.camera.rate_hz`` that
    says otherwise would be silently ignored (a "30 Hz" flight flying at 20 Hz)."""
    p = _variant(tmp_path, "[sim]\ntime_mode = \"lockstep\"\n[sim.camera]\nrate_hz = 30.0\n")
    with pytest.raises(ConfigError, match=r"^sim\.camera\.rate_hz: 30 Hz has no effect in "
                       r"lockstep.*sim\.step_dt_s = 0\.05 s \(20 Hz\)"):
        load_config(p)
    # the same rate with the step that matches it, or on the wall clock, is what it says
    ok = _variant(tmp_path, "[sim]\ntime_mode = \"lockstep\"\nstep_dt_s = 0.0333333333333333\n"
                  "physics_dt_s = 0.0033333333333333\n[sim.camera]\nrate_hz = 30.0\n")
    assert load_config(ok).sim.camera.rate_hz == 30.0
    rt = load_config(_variant(tmp_path, "[sim.camera]\nrate_hz = 30.0\n"))
    assert rt.sim.time_mode == "realtime" and rt.sim.camera.rate_hz == 30.0
    # switching that realtime config to lockstep (``sim-bridge --lockstep``) is refused too
    with pytest.raises(ConfigError, match=r"^sim\.camera\.rate_hz: "):
        with_sim(rt, time_mode="lockstep")
    assert with_sim(load_config(), time_mode="lockstep").sim.camera.rate_hz == 20.0
