"""The soft (recovery) copy's RTI (``rmpc.recovery_solver = "rti"``,
companion/core/rmpc_rti_soft.py) against the soft NLP: near the NLP's plan on the same
recovery step, its check refusing a violated plan, a refused step solved by the soft NLP
exactly as without the RTI, the config key and old logs."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from companion.config import ConfigError, config_from_dict, read_document
from companion.core.design import design_terminal
from companion.core.params import ParamError
from companion.core.rmpc import Rmpc
from companion.core.rmpc_rti_soft import SoftRti, build
from companion.core.rmpc_scenario import closed_loop, initial_error

EDGE_POSE = ((-1.0, 0.0, -3.2), np.pi / 4)  # the hard problem is infeasible for ~14 steps
RHO = 1e-4


@pytest.fixture(scope="module")
def cfg():  # type: ignore[no-untyped-def]
    return config_from_dict(read_document("config/paper.toml"))


@pytest.fixture(scope="module")
def design(cfg):  # type: ignore[no-untyped-def]
    return design_terminal(cfg.rmpc, cfg.camera)


def _mpc(cfg, design, recovery: str) -> Rmpc:  # type: ignore[no-untyped-def]
    return Rmpc(dataclasses.replace(cfg.rmpc, solver="rti", recovery_solver=recovery),
                cfg.camera, design)


def _soft_rti(cfg, design, layout) -> SoftRti:  # type: ignore[no-untyped-def]
    out = build(dataclasses.replace(cfg.rmpc, recovery_solver="rti"), cfg.camera, design, layout)
    assert out is not None
    return out


def _recovery_steps(mpc: Rmpc, steps: int = 12) -> list[dict]:  # type: ignore[type-arg]
    """The edge loop flown by ``mpc``; each soft NLP solve's arguments and result."""
    seen: list[dict] = []  # type: ignore[type-arg]
    soft = mpc._soft
    assert soft is not None
    solve = soft.solve

    def spy(w0, spar, lbx, ubx, backend=None):  # type: ignore[no-untyped-def]
        out = solve(w0, spar, lbx, ubx, backend)
        seen.append({"w0": w0, "spar": spar, "lbx": lbx, "ubx": ubx, "out": out})
        return out

    soft.solve = spy  # type: ignore[method-assign]
    try:
        mpc.reset()
        closed_loop(mpc, initial_error(*EDGE_POSE), steps, RHO, 1)
    finally:
        soft.solve = solve  # type: ignore[method-assign]
    return seen


def test_soft_rti_agrees_with_the_soft_nlp_on_recovery_steps(cfg, design) -> None:  # type: ignore[no-untyped-def]
    """On each recovery step of the edge loop flown by the soft NLP after the first (the
    first starts from the terminal law's rollout, not a warm start: the dispatch sends it to
    the NLP), the soft RTI from the NLP's own guess gives a plan whose first input is within
    0.05 m/s^2 (rad/s) of the NLP's (~3 % of u_max; measured 0.006-0.044) and whose soft cost
    is at most 40 % above the NLP's optimum (measured 1-40 %, +6..+25 absolute: the RTI's
    four Gauss-Newton QPs stop short of it) and never above the guess's. Tolerance: not
    rho / dt as for the hard RTI; in recovery the tube's argument does not hold anyway (the
    slacks are active), and this is the trade docs/reference/solver.md reports."""
    mpc = _mpc(cfg, design, "nlp")
    seen = _recovery_steps(mpc)
    assert len(seen) >= 8
    lay = mpc._soft.layout  # type: ignore[union-attr]
    solver = _soft_rti(cfg, design, lay)
    n_par = len(seen[0]["spar"]) - 5
    for s in seen[1:]:
        w0, spar, out = s["w0"], s["spar"], s["out"]
        assert out[0], out[1]
        e0, u_g = w0[lay.x_index[0]], w0[lay.u_index]
        lo, hi = s["lbx"][lay.x_index[1:]].ravel(), s["ubx"][lay.x_index[1:]].ravel()
        res = solver.step(e0, spar, u_g, lo, hi)
        assert res.ok, res.status
        u_nlp = out[3][lay.u_index]
        assert np.max(np.abs(res.u[0] - u_nlp[0])) <= 0.05
        assert res.cost <= 1.4 * out[4] + 1e-6
        guess = solver.evaluate(u_g.ravel(), e0, spar[:n_par], float(spar[-1]),
                                spar[n_par:n_par + 4])[2]
        assert res.cost <= guess


def test_the_check_refuses_a_violated_soft_plan(cfg, design) -> None:  # type: ignore[no-untyped-def]
    """The check (SoftRti.refusal) passes the soft NLP's plan and refuses it moved out of the
    state box, made non-finite, or costlier than a bound."""
    mpc = _mpc(cfg, design, "nlp")
    s = _recovery_steps(mpc, 4)[-1]
    lay = mpc._soft.layout  # type: ignore[union-attr]
    solver = _soft_rti(cfg, design, lay)
    spar, w = s["spar"], s["out"][3]
    n_par = len(spar) - 5
    e0, u = w[lay.x_index[0]], w[lay.u_index].ravel()
    box = (s["lbx"][lay.x_index[1:]].ravel(), s["ubx"][lay.x_index[1:]].ravel())
    eta, slack, cost = solver.evaluate(u, e0, spar[:n_par], float(spar[-1]),
                                       spar[n_par:n_par + 4])
    assert solver.refusal(eta, cost, cost, box) == ""
    assert np.max(np.abs(slack - w[lay.slack_index])) < 1e-6  # the NLP's slacks (interior)
    # every input at the box's corner: the velocities leave the state box
    bad = np.tile(np.asarray(cfg.rmpc.u_max), cfg.rmpc.horizon)
    eta_b, _, cost_b = solver.evaluate(bad, e0, spar[:n_par], 0.0, spar[n_par:n_par + 4])
    assert "state box" in solver.refusal(eta_b, cost_b, np.inf, box)
    eta_n = eta.copy()
    eta_n[3, 2] = np.nan
    assert "not finite" in solver.refusal(eta_n, cost, np.inf, box)
    assert "soft cost" in solver.refusal(eta, cost, cost - 1e-9, box)


def test_a_refused_soft_rti_step_is_the_soft_nlp_s(cfg, design) -> None:  # type: ignore[no-untyped-def]
    """With a check nothing passes (tol < 0), every soft RTI step goes to the soft NLP: the
    statuses say so, the steps are counted, and the commands are the ones flown with
    recovery_solver = "nlp" bit for bit (the soft NLP does not depend on the attempt). With
    the check as configured, the soft RTI flies recovery steps."""
    steps = 12
    ref = _mpc(cfg, design, "nlp")
    ref.reset()
    u_ref = [s.result.u0 for s in closed_loop(ref, initial_error(*EDGE_POSE), steps, RHO, 1)]
    mpc = _mpc(cfg, design, "rti")
    assert mpc.soft_rti is not None
    mpc.soft_rti.tol = -1.0
    loop = closed_loop(mpc, initial_error(*EDGE_POSE), steps, RHO, 1)
    assert np.array_equal(np.array([s.result.u0 for s in loop]), np.array(u_ref))
    refused = [s.result.status for s in loop if "rti-soft: rejected" in s.result.status]
    assert refused and all("; nlp: " in st.split("rti-soft: ")[1] for st in refused)
    assert mpc.soft_rti.rejected == len(refused) and mpc.soft_rti.accepted == 0
    mpc.soft_rti.tol = cfg.rmpc.rti_tol
    mpc.reset()
    loop = closed_loop(mpc, initial_error(*EDGE_POSE), steps, RHO, 1)
    flown = [s.result for s in loop if s.result.mode == "recovery"
             and "; nlp: " not in s.result.status.split("rti-soft: ")[-1]]
    assert flown and all("rti-soft: " in r.status for r in flown)
    u_max = np.asarray(cfg.rmpc.u_max)
    assert all(r.max_soft_violation >= 0.0 and np.all(np.abs(r.u_pred) <= u_max) for r in flown)


def test_the_config_key_round_trips_and_old_logs_read_nlp() -> None:
    """rmpc.recovery_solver: "rti" read back as given; a config without it (a log recorded
    before the key) reads "nlp", the soft NLP it flew; a bad value or rows the soft RTI
    cannot linearise are clear errors."""
    doc = read_document("config/paper.toml")
    rm = dict(doc["rmpc"])
    assert config_from_dict({**doc, "rmpc": {**rm, "recovery_solver": "rti"}}
                            ).rmpc.recovery_solver == "rti"
    rm.pop("recovery_solver", None)
    assert config_from_dict({**doc, "rmpc": rm}).rmpc.recovery_solver == "nlp"
    with pytest.raises(ConfigError, match="recovery_solver"):
        config_from_dict({**doc, "rmpc": {**rm, "recovery_solver": "qp"}})
    with pytest.raises((ConfigError, ParamError), match="recovery_rows"):
        config_from_dict({**doc, "rmpc": {**rm, "recovery_solver": "rti",
                                          "recovery_rows": "hard"}})


def test_an_infeasible_hard_qp_may_skip_the_hard_nlp(cfg, design) -> None:  # type: ignore[no-untyped-def]
    """rmpc.rti_infeasible_qp = "soft": a step whose hard QP DAQP found infeasible is not
    handed to the full hard NLP (fewer hard NLP solves, the status says so) but recovers; the
    default tries the hard NLP first, as before."""
    counts = {}
    for value in ("nlp", "soft"):
        mpc = Rmpc(dataclasses.replace(cfg.rmpc, solver="rti", recovery_solver="rti",
                                       rti_infeasible_qp=value), cfg.camera, design)
        loop = closed_loop(mpc, initial_error(*EDGE_POSE), 12, RHO, 1)
        skipped = [s.result for s in loop if "nlp: not tried (rmpc.rti_infeasible_qp = 'soft')"
                   in s.result.status]
        counts[value] = (mpc._hard.calls, len(skipped))
        if value == "soft":
            assert skipped and all(r.mode == "recovery" and "(daqp exit flag -1)" in r.status
                                   for r in skipped)
    assert counts["nlp"][1] == 0
    assert counts["soft"][0] < counts["nlp"][0]
