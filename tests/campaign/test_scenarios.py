"""The scenario library: the campaign's path table against the emulator's AGV, the default
campaign's coverage (paths, 1-10x, >= 1 m/s and >= 0.5 rad/s, disturbances, slow attitude
loop) accepted by both programs' validators, and the sampled starts (seeded, inside the
documented distribution, projected independently)."""

from __future__ import annotations

import functools
import math
from pathlib import Path

import numpy as np
import pytest

from companion import ConfigError
from companion.campaign.scenarios import (
    PATHS,
    SCENARIO_NAME,
    StartDistribution,
    load_campaign,
    sample_start,
)
from companion.config import config_from_dict, read_document
from companion.config_file import merged_document
from sim_bridge.config import config_from_dict as sim_config_from_dict
from sim_bridge.physics.agv import AgvTrajectory


@functools.cache
def _peaks(trajectory: str, scale: float) -> tuple[float, float, float, float]:
    tr = AgvTrajectory(trajectory, speed_scale=scale)
    st = [tr.state(t) for t in np.arange(0.0, 260.0 / scale, 0.01 / scale)]
    v = max(float(np.hypot(*s.vel_ned_m_s[:2])) for s in st)
    w = max(abs(s.yaw_rate_rad_s) for s in st)
    a = max(float(np.hypot(*s.acc_ned_m_s2[:2])) for s in st)
    return st[0].yaw_rad, v, w, a


@pytest.mark.parametrize("path", sorted(PATHS))
def test_path_table_matches_the_emulator(path: str) -> None:
    info = PATHS[path]
    yaw0, v, w, a = _peaks(info.trajectory, 1.0)
    assert yaw0 == pytest.approx(info.yaw0_rad, abs=1e-9)
    assert v == pytest.approx(info.peak_speed_m_s, rel=1e-3, abs=1e-4)
    assert w == pytest.approx(info.peak_yaw_rate_rad_s, rel=1e-3, abs=1e-4)
    assert a == pytest.approx(info.peak_accel_m_s2, rel=1e-3, abs=1e-4)
    # speed and heading rate scale with the speed scale, acceleration with its square (the
    # ramp's is its own: sim.agv.ramp_accel_m_s2)
    _, v3, w3, a3 = _peaks(info.trajectory, 3.0)
    a3_expect = 9 * a if info.accel_scales else a
    assert (v3, w3, a3) == pytest.approx((3 * v, 3 * w, a3_expect), rel=1e-3, abs=1e-4)


def test_default_campaign_covers_the_library() -> None:
    camp = load_campaign()
    scens = camp.scenarios
    assert {s.path for s in scens} == set(PATHS) - {"ramp"}  # the ramp: campaigns/fast.toml
    scales = [s.speed_scale for s in scens]
    assert min(scales) == 1.0 and max(scales) == 10.0
    agile = [s for s in scens
             if _peaks(PATHS[s.path].trajectory, s.speed_scale)[1] >= 1.0
             and _peaks(PATHS[s.path].trajectory, s.speed_scale)[2] >= 0.5]
    assert agile, "no scenario reaches 1 m/s and 0.5 rad/s"
    sets = " ".join(x for s in scens for x in s.set)
    for key in ("gust_amplitude_m_s2", "random_bound_m_s2", "attitude_tau_s"):
        assert key in sets
    assert len(camp.controllers) * len(scens) * camp.seeds >= 200


CAMPAIGNS = Path(__file__).resolve().parents[2] / "config" / "campaigns"


@pytest.mark.parametrize("name", sorted(p.stem for p in CAMPAIGNS.glob("*.toml")))
def test_every_scenario_and_start_is_accepted_by_both_programs(name: str) -> None:
    camp = load_campaign(CAMPAIGNS / f"{name}.toml")
    base = read_document(camp.config)
    for spec in camp.runs(Path("/nonexistent"), seeds=[0, 1],
                          controllers=[camp.controllers[0].name]):
        ctrl_sets = set(camp.controllers[0].set)
        doc = merged_document(base, [o for o in spec.overrides if o not in ctrl_sets])
        config_from_dict(doc)
        emu = sim_config_from_dict(doc, scenario=SCENARIO_NAME)
        assert emu.scenario.uav_pose == pytest.approx(spec.start.uav_pose, abs=1e-6)
        assert emu.sim.agv.trajectory == PATHS[spec.path].trajectory
        assert emu.sim.agv.speed_scale == spec.speed_scale
        assert emu.sim.seed == spec.seed


def _project(pose: tuple[float, ...], yaw_a: float, length: float, width: float,
             f_px: float) -> np.ndarray:
    """The AGV top's corners (at the origin, heading yaw_a) in a level downward camera at
    ``pose``: (u forward, n right) in pixels, from the world side."""
    x, y, z, _, _, psi = pose
    c, s = math.cos(yaw_a), math.sin(yaw_a)
    corners_w = [np.array([c * a - s * b, s * a + c * b, 0.0])
                 for a, b in ((length / 2, width / 2), (length / 2, -width / 2),
                              (-length / 2, -width / 2), (-length / 2, width / 2))]
    rz = np.array([[math.cos(psi), -math.sin(psi), 0], [math.sin(psi), math.cos(psi), 0],
                   [0, 0, 1]])
    out = []
    for p in corners_w:
        pc = rz.T @ (p - np.array([x, y, z]))
        out.append([f_px * pc[0] / pc[2], f_px * pc[1] / pc[2]])
    return np.array(out)


@pytest.mark.parametrize("seed", range(12))
def test_starts_are_seeded_near_the_edge_and_project_as_drawn(seed: int) -> None:
    camp = load_campaign()
    cam = camp.camera()
    dist = camp.start
    for path in PATHS:
        st = sample_start(dist, cam, path, f"scn-{path}", seed)
        assert st == sample_start(dist, cam, path, f"scn-{path}", seed)  # seeded
        assert st != sample_start(dist, cam, path, f"scn-{path}", seed + 100)
        assert dist.height_m[0] <= st.height_m <= dist.height_m[1]
        assert st.uav_pose[2] == pytest.approx(cam.target_top_z_m - st.height_m)
        assert dist.yaw_error_rad[0] <= st.yaw_error_rad <= dist.yaw_error_rad[1]
        edge = max(abs(v) for v in st.centroid_px) / cam.visible_bound_px
        assert dist.edge_fraction[0] - 1e-9 <= edge <= dist.edge_fraction[1] + 1e-9
        px = _project(st.uav_pose, PATHS[path].yaw0_rad, cam.target_length_m,
                      cam.target_width_m, cam.focal_length_m / cam.report_pixel_size_m)
        np.testing.assert_allclose(px.mean(axis=0), st.centroid_px, atol=1e-6)
        assert float(np.max(np.abs(px))) == pytest.approx(st.max_corner_px, abs=1e-6)
        assert st.max_corner_px <= dist.max_corner_fraction * cam.visible_bound_px
        # the heading error is psi_agv - psi_uav
        assert st.yaw_error_rad == pytest.approx(PATHS[path].yaw0_rad - st.uav_pose[5])


def test_bad_start_distribution_is_refused() -> None:
    with pytest.raises(ConfigError, match=r"start\.height_m"):
        StartDistribution(height_m=(3.0, 2.0))
    with pytest.raises(ConfigError, match="edge_fraction"):
        StartDistribution(edge_fraction=(0.6, 0.99))


def test_fast_campaign_flies_1_to_3_m_s_and_up_to_1_rad_s_with_the_vehicles_limits() -> None:
    camp = load_campaign(CAMPAIGNS / "fast.toml")
    assert {c.name for c in camp.controllers} == {"rmpc", "rmpc-centroid", "mpc-novis",
                                                 "ibvs-pd"}
    peaks = [_peaks(PATHS[s.path].trajectory, s.speed_scale) for s in camp.scenarios]
    speeds = [p[1] for p in peaks]
    assert min(speeds) == pytest.approx(1.0, rel=1e-3)
    assert max(speeds) == pytest.approx(3.0, rel=1e-3)  # the ramp's cruise
    assert max(p[2] for p in peaks) == pytest.approx(1.0, rel=1e-2)  # figure eight 3x
    cfg = config_from_dict(merged_document(read_document(camp.config), camp.set))
    assert cfg.vehicle_limits.from_autopilot  # the realistic world, with the vehicle's limits
    assert "ramp" in {s.path for s in camp.scenarios}
