"""One QP of the RTI step as one foreign call (companion/core/rmpc_rti_cstep.py, ``rti_qp``):
the same step records bit for bit as the step with Python between the compiled parts, on
closed loops and on the paths that go back to Python (a state box the QP's step leaves, a
row on its bound, a QP that fails)."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import numpy as np
import pytest

from companion.config import load_config
from companion.core.design import design_terminal
from companion.core.rmpc import Rmpc, RmpcResult
from companion.core.rmpc_rti import RtiOutcome, RtiSolver
from companion.core.rmpc_scenario import closed_loop, initial_error
from tests.core.rti_forms import halfway_state_bounds

PAPER_POSE = ((-0.2, 0.4, -3.2), np.pi / 8)
EDGE_POSE = ((-1.0, 0.0, -3.2), np.pi / 4)


@pytest.fixture(scope="module")
def mpc() -> Rmpc:
    cfg = load_config()
    return Rmpc(dataclasses.replace(cfg.rmpc, solver="rti"), cfg.camera,
                design_terminal(cfg.rmpc, cfg.camera))


def _solver(mpc: Rmpc) -> RtiSolver:
    assert mpc._rti is not None
    return mpc._rti


class _Codes:
    """Records ``rti_qp``'s return codes (the C step's run wrapped)."""

    def __init__(self, solver: RtiSolver) -> None:
        assert solver._cstep is not None, "the default form has the C step"
        self.codes: list[int] = []
        self._run = run = solver._cstep.run

        def recorded(clip: int) -> int:
            code = run(clip)
            self.codes.append(code)
            return code
        self._solver = solver
        solver._cstep.run = recorded

    def close(self) -> None:
        assert self._solver._cstep is not None
        self._solver._cstep.run = self._run


def _python(solver: RtiSolver, fn: Callable[[], object]) -> object:
    """``fn()`` with the step's Python between the compiled parts (no C step)."""
    kept, solver._cstep = solver._cstep, None
    try:
        return fn()
    finally:
        solver._cstep = kept


def _loop(mpc: Rmpc, pose: tuple, steps: int) -> list[RmpcResult]:
    mpc.reset()
    return [s.result for s in closed_loop(mpc, initial_error(*pose), steps, 1e-4, 1)]


def _same_result(a: RmpcResult, b: RmpcResult) -> bool:
    return (a.status == b.status and a.mode == b.mode and a.cost == b.cost
            and a.iterations == b.iterations and np.array_equal(a.u0, b.u0)
            and np.array_equal(a.eta_pred, b.eta_pred) and np.array_equal(a.u_pred, b.u_pred))


def _same_outcome(a: RtiOutcome, b: RtiOutcome) -> bool:
    return (a.ok == b.ok and a.status == b.status and a.qps == b.qps
            and a.qp_iterations == b.qp_iterations and np.array_equal(a.eta, b.eta)
            and np.array_equal(a.u, b.u) and np.array_equal([a.cost, a.violation],
                                                            [b.cost, b.violation],
                                                            equal_nan=True))


def test_the_c_step_flies_the_python_steps_records(mpc: Rmpc) -> None:
    """Paper and edge loops (engagement, rejected steps, the full NLP behind them,
    tracking): every step record the same bit for bit with and without the C step, and the
    C step did the QPs (most of them through to the check, code 0; the others: QPs
    that DAQP found infeasible on the edge loop's engagement)."""
    solver = _solver(mpc)
    for pose in (PAPER_POSE, EDGE_POSE):
        rec = _Codes(solver)
        try:
            with_c = _loop(mpc, pose, 120)
        finally:
            rec.close()
        without = _python(solver, lambda pose=pose: _loop(mpc, pose, 120))
        assert isinstance(without, list)
        assert all(_same_result(a, b) for a, b in zip(with_c, without, strict=True))
        assert set(rec.codes) <= {0, 1} and rec.codes.count(0) >= 100
        assert any("nlp: " in r.status for r in with_c)  # (a rejected step was in it)


def _paper_point(mpc: Rmpc) -> tuple[np.ndarray, ...]:
    """A paper step's inputs (eta0, par, guess, lo, hi), the guess half-way between hover
    and the flown plan (a QP with a real step)."""
    good = _loop(mpc, PAPER_POSE, 40)[-1]
    eta0 = good.eta_pred[0]
    par = np.append(good.target.packed(), eta0[3])
    lo, hi = mpc._state_box(good.target)
    return eta0, par, 0.5 * good.u_pred, lo, hi


def _both(solver: RtiSolver, args: tuple[np.ndarray, ...]) -> tuple[RtiOutcome, RtiOutcome,
                                                                     list[int], int]:
    """The step on ``args`` with the C step (its codes, the whole QPs solved) and without."""
    rec = _Codes(solver)
    full0 = solver.full_qps
    try:
        with_c = solver.step(*args)
    finally:
        rec.close()
    full = solver.full_qps - full0
    without = _python(solver, lambda: solver.step(*args))
    assert isinstance(without, RtiOutcome)
    return with_c, without, rec.codes, full


def test_a_state_box_the_step_leaves_is_decided_in_python(mpc: Rmpc) -> None:
    """The first QP's step leaves a state row (its box moved half-way in): rti_qp returns
    to Python, which solves the whole QP; the same outcome as without the C step."""
    solver = _solver(mpc)
    eta0, par, guess, lo, hi = _paper_point(mpc)
    with_c, without, codes, full = _both(solver, (eta0, par, guess, lo, hi))
    assert codes[0] == 0 and full == 0 and _same_outcome(with_c, without)
    # the state row the QP moves most (linearised), its bound moved half-way in
    u = np.clip(guess.ravel(), -solver.u_max, solver.u_max)
    du = solver._qp(u, eta0, par, lo, hi)[0]
    lo2, hi2 = halfway_state_bounds(solver, du, lo, hi)
    with_c, without, codes, full = _both(solver, (eta0, par, guess, lo2, hi2))
    assert codes[0] == 1 and full >= 1
    assert _same_outcome(with_c, without)


def test_a_row_on_its_bound_is_decided_in_python(mpc: Rmpc) -> None:
    """A state row whose linearised value is exactly its bound (numpy's number: inside) is
    not decided in C, where the product may round otherwise: rti_qp returns to Python,
    which keeps the QP's step; the same outcome as without the C step."""
    solver = _solver(mpc)
    eta0, par, guess, lo, hi = _paper_point(mpc)
    u = np.clip(guess.ravel(), -solver.u_max, solver.u_max)
    plain = _python(solver, lambda: solver.step(eta0, par, guess, lo, hi))
    assert isinstance(plain, RtiOutcome) and plain.qps == 1
    solver._lin(u, eta0, par)
    du = solver._qp(u, eta0, par, lo, hi)[0]
    x_lin = solver._j_state.dot(du) + solver._c_x
    hi2 = hi.copy()
    hi2[20] = x_lin[20]
    with_c, without, codes, full = _both(solver, (eta0, par, guess, lo, hi2))
    assert codes[0] == 1 and full == 0
    assert _same_outcome(with_c, without)


def test_a_failed_qp_is_the_python_steps(mpc: Rmpc) -> None:
    """An empty state box (lower bound above the upper one on a row): the whole QP is
    infeasible; the step fails the same way with and without the C step."""
    solver = _solver(mpc)
    eta0, par, guess, lo, hi = _paper_point(mpc)
    lo2, hi2 = lo.copy(), hi.copy()
    lo2[3], hi2[3] = 1.0, -1.0
    with_c, without, codes, _ = _both(solver, (eta0, par, guess, lo2, hi2))
    assert codes == [1] and not with_c.ok and "failed (daqp exit flag" in with_c.status
    assert _same_outcome(with_c, without)


def test_a_guess_outside_the_input_box_is_clipped_alike(mpc: Rmpc) -> None:
    """A guess with inputs beyond the box (either side): rti_qp clips it before the first
    linearisation as the Python step does; the same outcome."""
    solver = _solver(mpc)
    eta0, par, guess, lo, hi = _paper_point(mpc)
    wild = guess.copy()
    wild[::2] = 3.0 * solver.u_max.reshape(wild.shape)[::2]
    wild[1::2] = -3.0 * solver.u_max.reshape(wild.shape)[1::2]
    with_c, without, codes, _ = _both(solver, (eta0, par, wild, lo, hi))
    assert codes and codes[0] in (0, 1)
    assert _same_outcome(with_c, without)
