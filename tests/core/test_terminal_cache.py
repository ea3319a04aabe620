"""The terminal design cached beside the compiled solvers (companion/core/terminal_cache.py):
a cached design is bit-identical to a fresh one, a changed parameter designs afresh, and an
unreadable entry is designed again rather than trusted."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from companion.config import load_config
from companion.core.design import design_terminal


def _rmpc(tmp_path: Path, **changes: object):  # type: ignore[no-untyped-def]
    cfg = load_config()
    return dataclasses.replace(cfg.rmpc, cache_dir=str(tmp_path), **changes), cfg.camera


def test_cached_design_is_bit_identical(tmp_path: Path) -> None:
    rmpc, cam = _rmpc(tmp_path)
    fresh = design_terminal(rmpc, cam)
    entries = list(tmp_path.glob("terminal_*.npz"))
    assert len(entries) == 1
    cached = design_terminal(rmpc, cam)
    assert np.array_equal(cached.p, fresh.p) and np.array_equal(cached.k, fresh.k)
    assert cached.kappa == fresh.kappa and cached.gamma == fresh.gamma
    # the second call read the entry: a different stored P is what it returns
    with np.load(entries[0]) as z:
        p, k, kappa = z["p"], z["k"], z["kappa"]
    np.savez(entries[0], p=2.0 * p, k=k, kappa=kappa)
    assert np.array_equal(design_terminal(rmpc, cam).p, 2.0 * fresh.p)


def test_changed_parameter_designs_afresh(tmp_path: Path) -> None:
    rmpc, cam = _rmpc(tmp_path)
    a = design_terminal(rmpc, cam)
    q = tuple(2.0 * x for x in rmpc.q_diag)
    b = design_terminal(dataclasses.replace(rmpc, q_diag=q), cam)
    assert len(list(tmp_path.glob("terminal_*.npz"))) == 2
    assert not np.array_equal(a.p, b.p)


def test_unreadable_entry_is_designed_again(tmp_path: Path) -> None:
    rmpc, cam = _rmpc(tmp_path)
    fresh = design_terminal(rmpc, cam)
    (entry,) = tmp_path.glob("terminal_*.npz")
    entry.write_bytes(b"not an npz")
    again = design_terminal(rmpc, cam)
    assert np.array_equal(again.p, fresh.p)
