"""The NLP built once per problem (companion/core/rmpc_memo.py): a problem built before gives
the same layout and graph digest without deriving its expressions, reads of the expressions
still get the real graph, a changed parameter builds afresh and an unreadable entry is built
again rather than trusted."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import casadi as ca
import numpy as np

from companion.config import load_config
from companion.core.design import design_terminal
from companion.core.params import CameraParams, RmpcParams
from companion.core.rmpc_cache import problem_key
from companion.core.rmpc_memo import Nlp, graph_digest
from companion.core.rmpc_problem import build_nlp
from companion.core.terminal import TerminalDesign


def _problem(tmp_path: Path, **changes: object) -> tuple[RmpcParams, CameraParams,
                                                         TerminalDesign]:
    cfg = load_config()
    rmpc = dataclasses.replace(cfg.rmpc, cache_dir=str(tmp_path), **changes)
    return rmpc, cfg.camera, design_terminal(rmpc, cfg.camera)


def _plain(nlp: Nlp) -> dict[str, ca.SX]:
    return {k: nlp[k] for k in ("x", "p", "f", "g")}


def test_a_problem_built_before_is_not_derived_again(tmp_path: Path) -> None:
    rmpc, cam, term = _problem(tmp_path)
    for soft in (False, True):
        fresh, lay = build_nlp(rmpc, cam, term, soft)
        assert fresh.built  # a miss builds (and writes the memo)
        again, lay2 = build_nlp(rmpc, cam, term, soft)
        assert not again.built
        # the same layout, entry by entry
        assert lay2.rows == lay.rows and lay2.equality == lay.equality
        assert (lay2.horizon, lay2.soft, lay2.n_w, lay2.n_g) == (lay.horizon, lay.soft,
                                                                 lay.n_w, lay.n_g)
        for name in ("x_index", "u_index", "gap_index", "slack_index"):
            assert np.array_equal(getattr(lay2, name), getattr(lay, name))
        # the same key for the compiled libraries, without the graph
        assert problem_key(again, "t", "o") == problem_key(fresh, "t", "o")
        assert not again.built
        # and the graph when something reads it: the same graph
        assert graph_digest(_plain(again)) == fresh.digest
        assert again.built
    assert len(list(tmp_path.glob("rmpc_problem_*.json"))) == 2


def test_a_changed_parameter_builds_afresh(tmp_path: Path) -> None:
    rmpc, cam, term = _problem(tmp_path)
    a, lay = build_nlp(rmpc, cam, term, False)
    # the last bits count: eps is in the rows' bounds (the layout), q in the graph
    eps = dataclasses.replace(rmpc, eps=rmpc.eps * (1.0 + 2.0**-40))
    b, lay_b = build_nlp(eps, cam, term, False)
    assert b.built and b.digest == a.digest
    assert [r.upper for r in lay_b.rows] != [r.upper for r in lay.rows]
    q = dataclasses.replace(rmpc, q_diag=(rmpc.q_diag[0] * (1.0 + 2.0**-40), *rmpc.q_diag[1:]))
    b, _ = build_nlp(q, cam, term, False)
    assert b.built and b.digest != a.digest
    p2 = dataclasses.replace(term, p=np.asarray(term.p) * (1.0 + 2.0**-40))
    c, _ = build_nlp(rmpc, cam, p2, False)
    assert c.built and c.digest != a.digest


def test_an_unreadable_entry_is_built_again(tmp_path: Path) -> None:
    rmpc, cam, term = _problem(tmp_path)
    fresh, _ = build_nlp(rmpc, cam, term, False)
    (entry,) = tmp_path.glob("rmpc_problem_*.json")
    for bad in ("not json", '{"digest": "x"}', '{"layout": {}}'):
        entry.write_text(bad)
        nlp, _ = build_nlp(rmpc, cam, term, False)
        assert nlp.built and nlp.digest == fresh.digest
    # a recorded digest is what a hit returns (the memo is read, not recomputed)
    text = entry.read_text()
    entry.write_text(text.replace(fresh.digest, "0" * 64))
    assert build_nlp(rmpc, cam, term, False)[0].digest == "0" * 64
