"""controller.kind builds each control law behind the one Controller interface."""

from __future__ import annotations

import numpy as np
import pytest

from companion.config import CONTROLLER_KINDS, load_config
from companion.control.factory import build_controller
from companion.control.seams import Controller
from companion.core.design import design_terminal
from companion.core.dynamics import euler_step
from companion.core.ibvs import IbvsPd
from companion.core.rmpc import Rmpc, RmpcParameterError, TargetMotion

ETA0 = np.array([0.0159, -0.2230, 0.6, 0.3927, -0.1307, -0.0541, 0.0])


def test_the_kinds_are_the_documented_names() -> None:
    assert CONTROLLER_KINDS == ("rmpc", "rmpc-centroid", "mpc-novis", "ibvs-pd")
    assert load_config().controller.kind == "rmpc"


@pytest.mark.parametrize("kind", CONTROLLER_KINDS)
def test_factory_builds_each_kind_and_it_solves(kind: str) -> None:
    cfg = load_config(overrides=[f'controller.kind="{kind}"'])
    design = design_terminal(cfg.rmpc, cfg.camera)
    ctrl = build_controller(cfg, design)
    assert isinstance(ctrl, Controller)
    tm = TargetMotion.constant([0.1, 0.0], [0.0, 0.0], 0.0, cfg.rmpc.horizon)
    res = ctrl.solve(ETA0, tm)
    assert res.success and np.all(np.isfinite(res.u0))
    assert np.all(np.abs(res.u0) <= np.asarray(cfg.rmpc.u_max) + 1e-9)
    if kind == "ibvs-pd":
        assert isinstance(ctrl, IbvsPd) and res.mode == "law"
        return
    assert isinstance(ctrl, Rmpc) and res.mode in ("optimal", "recovery")
    p = ctrl.cfg
    assert p.enable_visibility == (kind != "mpc-novis")
    if kind == "rmpc":
        assert p.visibility == cfg.rmpc.visibility == "corners"
    if kind == "rmpc-centroid":
        assert p.visibility == "centroid"
    assert ("visibility" in res.active_groups) == (kind != "mpc-novis")


def test_ibvs_pd_is_the_documented_law_and_decays_the_error() -> None:
    """u = k_v (lambda z* s_e - v_e) + Gamma, psidot = psidot_a + k_psi se4; on the nominal
    model from rest at a small offset the image error decays (exponential decrease)."""
    cfg = load_config(overrides=['controller.kind="ibvs-pd"'])
    ctrl = build_controller(cfg, design_terminal(cfg.rmpc, cfg.camera))
    assert isinstance(ctrl, IbvsPd)
    g = ctrl.gains
    eta = np.array([0.05, -0.03, 0.02, 0.1, 0.0, 0.0, 0.0])
    tm = TargetMotion.constant([0.0, 0.0], [0.0, 0.0], 0.0, cfg.rmpc.horizon)
    u = ctrl.solve(eta, tm).u0
    assert np.allclose(u[:3], g.kv_1_s * g.lambda_1_s * g.z_star_m * eta[:3])
    assert u[3] == pytest.approx(g.yaw_1_s * eta[3])
    e = eta.copy()
    for _ in range(400):  # 20 s
        u = ctrl.solve(e, tm).u0
        e = euler_step(e, u, np.zeros(2), np.zeros(2), 0.0, g.z_star_m, g.dt_s)
    assert np.linalg.norm(e) < 1e-3 * np.linalg.norm(eta)
    with pytest.raises(RmpcParameterError):
        ctrl.solve(np.full(7, np.nan), tm)
