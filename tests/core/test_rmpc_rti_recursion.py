"""``rmpc.rti_linearisation = "recursion"`` (companion/core/rmpc_rti_recursion.py): H and g by
the backward recursion equal the graph form's to round-off (bounded below), the rows and their
Jacobian bit for bit, on real plans and random inputs; a closed loop flies the same commands
within 1e-9 and hands the same steps to the full NLP."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from companion.config import load_config
from companion.core.params import ParamError
from companion.core.rmpc_scenario import closed_loop, initial_error
from tests.core.rti_forms import PAPER_POSE, form_pair, linearisation_points

REL_TOL = 1e-12
"""H's entries within REL_TOL of H's largest; g's within REL_TOL of the Cauchy-Schwarz bound
of each entry's terms, |g_i| = 2 |J_i' r| <= 2 sqrt(H_ii / 2) |r| (g vanishes near a
solution, so its own size is no scale: measured ~1e-15 of H's and ~1e-17 absolute)."""


@pytest.fixture(scope="module")
def pair():  # type: ignore[no-untyped-def]
    return form_pair("recursion", "graph")


def test_the_recursion_is_the_graph_to_round_off(pair) -> None:  # type: ignore[no-untyped-def]
    """H within REL_TOL of H's largest entry, g within REL_TOL of its terms' bound (the
    residual's norm from the NLP's cost, f = |r|^2), the rows and their Jacobian exactly,
    at real closed loops' linearisation points and at random points."""
    rec, graph = pair
    assert rec._rti.compiled[0].library != graph._rti.compiled[0].library
    for u, eta0, par in linearisation_points(rec):
        a = [x.copy() for x in rec._rti._lin(u, eta0, par)]
        b = [x.copy() for x in graph._rti._lin(u, eta0, par)]
        hess = b[0].reshape(a[0].size // b[1].size, -1)
        assert np.max(np.abs(a[0] - b[0])) <= REL_TOL * np.max(np.abs(b[0]))
        _, _, cost = graph._rti.rows(u, eta0, par)
        bound = 2.0 * np.sqrt(np.diag(hess) / 2.0) * np.sqrt(cost)
        assert (np.abs(a[1] - b[1]) <= REL_TOL * bound + 1e-300).all()
        assert np.array_equal(a[2], b[2]) and np.array_equal(a[3], b[3])
        assert np.array_equal(a[0], a[0].T)  # (mirrored)


def test_the_recursion_flies_the_same_commands(pair) -> None:  # type: ignore[no-untyped-def]
    """The same closed loop with either form: commands within 1e-9, the same statuses."""
    runs = []
    for mpc in pair:
        mpc.reset()
        loop = closed_loop(mpc, initial_error(*PAPER_POSE), 60, 1e-4, 3)
        runs.append((np.array([s.result.u0 for s in loop]),
                     [s.result.status.split(" (")[0] for s in loop]))
    assert np.max(np.abs(runs[0][0] - runs[1][0])) <= 1e-9
    assert runs[0][1] == runs[1][1]


def test_an_unknown_form_is_refused() -> None:
    cfg = load_config()
    with pytest.raises(ParamError, match="rti_linearisation"):
        dataclasses.replace(cfg.rmpc, rti_linearisation="recurse")


def test_each_step_keeps_its_own_plan(pair) -> None:  # type: ignore[no-untyped-def]
    """The step works in the compiled functions' argument arrays; the plans it hands out are
    copies: a later step (another guess) does not change an earlier one's, and the same
    inputs give the same plan."""
    rec = pair[0]
    rec.reset()
    res = [s.result for s in closed_loop(rec, initial_error(*PAPER_POSE), 5, 1e-4, 1)]
    eta0 = res[-1].eta_pred[0]
    par = np.append(res[-1].target.packed(), eta0[3])
    lo, hi = rec._state_box(res[-1].target)
    first = rec._rti.step(eta0, par, res[-1].u_pred, lo, hi)
    kept = first.u.copy()
    second = rec._rti.step(eta0, par, 0.5 * res[-1].u_pred, lo, hi)
    assert not np.array_equal(second.u, kept)
    assert np.array_equal(first.u, kept)
    assert np.array_equal(rec._rti.step(eta0, par, res[-1].u_pred, lo, hi).u, kept)
