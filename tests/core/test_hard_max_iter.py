"""``rmpc.hard_max_iter`` bounds the hard NLP's iterations, and only the hard NLP's.

A hard NLP that fails (the soft copy then solves) ran ~45 fatrop iterations before giving up;
the limit ends it sooner (docs/reference/solver.md, "The hard NLP's iteration limit"). The soft
copy's ipopt keeps ``rmpc.max_iter``: it needs up to ~37 iterations where the hard NLP
converges in ~11.
"""

from __future__ import annotations

import dataclasses
import time

import pytest

from companion.config import Config, load_config
from companion.core.design import design_terminal
from companion.core.errors import ParamError
from companion.core.rmpc import Rmpc
from companion.core.rmpc_scenario import horizon_motion, initial_error

PAPER_POSE = ((-0.2, 0.4, -3.2), 0.39269908169872414)  # (spec 8: yaw pi/8)


@pytest.fixture(scope="module")
def cfg() -> Config:
    return load_config(overrides=['rmpc.solver="nlp"'])


def _solve(cfg: Config, hard_max_iter: int | None) -> tuple[Rmpc, object]:
    params = dataclasses.replace(cfg.rmpc, hard_max_iter=hard_max_iter)
    mpc = Rmpc(params, cfg.camera, design_terminal(params, cfg.camera), clock=time.perf_counter)
    tm = horizon_motion(0.0, PAPER_POSE[1], params.horizon, params.dt_s)
    return mpc, mpc.solve(initial_error(*PAPER_POSE), tm)


def test_the_limit_reaches_the_hard_nlp_and_leaves_the_soft_copy(cfg: Config) -> None:
    unbounded, res = _solve(cfg, None)
    assert res.mode == "optimal", res.status
    needed = res.iterations
    assert needed > 3  # (from the terminal law's rollout: a cold start)
    bounded, capped = _solve(cfg, 2)
    # two iterations do not reach the optimum: the hard NLP stops at its limit, and the soft
    # copy, still bounded by max_iter (100), solves the step
    assert capped.mode == "recovery", capped.status
    assert capped.hard_status != res.hard_status
    assert bounded.solver_kinds()["soft"] == unbounded.solver_kinds()["soft"]
    hard, soft = bounded.nlps()[:2]
    assert hard.options["fatrop"]["max_iter"] == 2
    assert soft.options["ipopt"]["max_iter"] == cfg.rmpc.max_iter
    # a limit above what the solve needs changes nothing
    _, same = _solve(cfg, needed + 1)
    assert same.mode == "optimal" and same.iterations == needed
    assert (same.u0 == res.u0).all()


def test_the_shipped_configs_limit_and_its_check(cfg: Config) -> None:
    assert load_config().rmpc.hard_max_iter == 30
    with pytest.raises(ParamError, match="hard_max_iter"):
        dataclasses.replace(cfg.rmpc, hard_max_iter=0)
