"""``rmpc.rti_linearisation = "loops"`` (companion/core/rmpc_rti_loops.py): the C condensing
gives the graph form's outputs bit for bit (H, g, the rows, their Jacobian), on real plans and
on random inputs, so a flight's commands do not depend on the form; and the cache compiles
appended C with a library's own flags (the flags name the library)."""

from __future__ import annotations

from pathlib import Path

import casadi as ca
import numpy as np
import pytest

from companion.core.rmpc import Rmpc
from companion.core.rmpc_cache import compiled_functions
from companion.core.rmpc_scenario import closed_loop, initial_error
from tests.core.rti_forms import PAPER_POSE, form_pair, linearisation_points


@pytest.fixture(scope="module")
def pair():  # type: ignore[no-untyped-def]
    return form_pair("loops", "graph")


def _outputs(mpc: Rmpc, u: np.ndarray, eta0: np.ndarray, par: np.ndarray) -> list[np.ndarray]:
    assert mpc._rti is not None
    return [a.copy() for a in mpc._rti._lin(u, eta0, par)]


def test_the_loops_are_the_graph_bit_for_bit(pair) -> None:  # type: ignore[no-untyped-def]
    """Every output of the compiled C loops equals the compiled graph's exactly, at the
    linearisation points of real closed loops (paper and edge, each step's guess) and at
    random points (large inputs, states far from the tube: any sign, no special zeros)."""
    loops, graph = pair
    assert loops.cfg.rti_linearisation == "loops" and graph.cfg.rti_linearisation == "graph"
    assert loops._rti.compiled[0].library != graph._rti.compiled[0].library
    points = linearisation_points(loops)
    for u, eta0, par in points:
        for a, b in zip(_outputs(loops, u, eta0, par), _outputs(graph, u, eta0, par),
                        strict=True):
            assert a.shape == b.shape
            assert np.array_equal(a, b), np.max(np.abs(a - b))


def test_the_two_forms_fly_the_same_commands(pair) -> None:  # type: ignore[no-untyped-def]
    """The same closed loop with either form: the same commands, bit for bit, and the same
    steps handed to the full NLP."""
    runs = []
    for mpc in pair:
        mpc.reset()
        loop = closed_loop(mpc, initial_error(*PAPER_POSE), 60, 1e-4, 3)
        runs.append((np.array([s.result.u0 for s in loop]),
                     [s.result.status for s in loop]))
    assert np.array_equal(runs[0][0], runs[1][0])
    assert runs[0][1] == runs[1][1]


def test_appended_c_is_compiled_with_its_own_flags(tmp_path: Path) -> None:
    """compiled_functions compiles C appended after the generated functions (calling them by
    name), with the flags given; other flags are another library (the key hashes them)."""
    x = ca.SX.sym("x")
    twice = ca.Function("twice", [x], [2 * x])
    appended = """
CASADI_SYMBOL_EXPORT int plus_one(const casadi_real** arg, casadi_real** res, casadi_int* iw,
                                  casadi_real* w, int mem) {
  if (twice(arg, res, iw, w, mem)) return 1;
  res[0][0] += 1.;
  return 0;
}
CASADI_SYMBOL_EXPORT casadi_int plus_one_n_in(void) { return 1; }
CASADI_SYMBOL_EXPORT casadi_int plus_one_n_out(void) { return 1; }
"""
    built = []
    for flags in (("-O3",), ("-O1",)):
        lib = compiled_functions(lambda: ([twice], appended), str(tmp_path), "t",
                                 alias_key="k", flags=flags)
        assert lib.compiled_now
        fn = ca.external("plus_one", str(lib.library))
        assert float(fn(3.0)) == 7.0
        built.append(lib.library)
    assert built[0] != built[1]
    again = compiled_functions(lambda: ([twice], appended), str(tmp_path), "t",
                               alias_key="k", flags=("-O3",))
    assert again.library == built[0] and not again.compiled_now
