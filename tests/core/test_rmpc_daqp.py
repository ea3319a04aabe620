"""DAQP's C entry on kept arrays (companion/core/rmpc_daqp.py): the pinned DAQP is found, its
QPs are ``daqp.solve``'s bit for bit (the RTI's own QPs, feasible and infeasible), the RTI
flies the same commands either way, and a settings struct that differs from ``daqp.solve``'s
is caught by the start-up check."""

from __future__ import annotations

import daqp
import numpy as np
import pytest

from companion.config import load_config
from companion.core import rmpc_daqp
from companion.core.design import design_terminal
from companion.core.rmpc import Rmpc
from companion.core.rmpc_rti import QP_ITER_LIMIT
from companion.core.rmpc_scenario import closed_loop, initial_error

POSES = (((-0.2, 0.4, -3.2), np.pi / 8), ((-1.0, 0.0, -3.2), np.pi / 4))


@pytest.fixture(scope="module")
def pair():  # type: ignore[no-untyped-def]
    cfg = load_config()
    design = design_terminal(cfg.rmpc, cfg.camera)
    direct, package = (Rmpc(cfg.rmpc, cfg.camera, design) for _ in range(2))
    assert direct._rti is not None and package._rti is not None
    package._rti._direct = package._rti._cstep = None  # daqp.solve
    return direct, package


def test_the_pinned_daqp_is_used(pair) -> None:  # type: ignore[no-untyped-def]
    assert pair[0]._rti._direct is not None


def test_every_qp_is_daqp_solves_bit_for_bit(pair) -> None:  # type: ignore[no-untyped-def]
    """Each QP the RTI solves on the paper and edge loops (the edge loop's include infeasible
    ones), solved by the C entry and by daqp.solve on the same arrays: the same solution,
    exit flag and iteration count."""
    direct = pair[0]
    rti = direct._rti
    seen: list[tuple[int, int]] = []
    cstep = rti._cstep  # (the default form's QPs go through rti_qp, which calls DAQP in C)
    assert cstep is not None
    run = cstep.run

    def check() -> None:
        res = rti._direct.result
        x, _, flag, info = daqp.solve(rti._hess, rti._grad, rti._j_path, rti._up, rti._lo,
                                      rti._sense, iter_limit=QP_ITER_LIMIT)
        assert np.array_equal(rti._direct.x, np.asarray(x))
        assert (res.exitflag, res.iter) == (int(flag), int(info["iterations"]))
        seen.append((res.exitflag, res.iter))

    def both(clip: int) -> int:
        code = run(clip)
        check()
        return code

    cstep.run = both
    try:
        for pose in POSES:
            direct.reset()
            closed_loop(direct, initial_error(*pose), 60, 1e-4, 1)
        # and through DirectQp.solve (the step without the C entry's rti_qp)
        rti._cstep = None
        solve = rti._direct.solve
        rti._direct.solve = lambda: (solve(), check())[0]
        direct.reset()
        closed_loop(direct, initial_error(*POSES[1]), 60, 1e-4, 1)
    finally:
        rti._cstep = cstep
        cstep.run = run
        rti._direct.__dict__.pop("solve", None)
    flags = {flag for flag, _ in seen}
    assert {1, -1} <= flags and len(seen) > 150
    assert max(it for _, it in seen) > 1


def test_the_rti_flies_the_same_commands(pair) -> None:  # type: ignore[no-untyped-def]
    for pose in POSES:
        runs = []
        for mpc in pair:
            mpc.reset()
            loop = closed_loop(mpc, initial_error(*pose), 120, 1e-4, 2)
            runs.append((np.array([s.result.u0 for s in loop]),
                         [s.result.status for s in loop]))
        assert np.array_equal(runs[0][0], runs[1][0])
        assert runs[0][1] == runs[1][1]


def test_a_struct_unlike_daqp_solves_is_refused() -> None:
    """The start-up check compares a QP solved both ways: settings that are not
    daqp.solve's (here one active-set iteration) do not pass it."""
    found = rmpc_daqp.direct(QP_ITER_LIMIT)
    assert found is not None
    fn, settings = found
    assert rmpc_daqp._agrees(fn, settings, QP_ITER_LIMIT)
    wrong = rmpc_daqp._Settings.from_buffer_copy(settings)
    wrong.iter_limit = 1
    assert not rmpc_daqp._agrees(fn, wrong, QP_ITER_LIMIT)
