"""The index bookkeeping of one RMPC NLP (:func:`companion.core.rmpc_problem.build_nlp`):
its own module so that the NLP memo (:mod:`companion.core.rmpc_memo`) reads and writes it
without importing the builder."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True)
class Row:
    """One soft-able path-constraint row: group, stage, g index, bound on g, slack index."""

    group: str
    kind: str  # "tube", "visibility", "corner", "terminal_set", "terminal_visibility"
    stage: int
    g_index: int
    upper: float
    slack_index: int | None
    corner: int = -1  # which target corner a "corner" row keeps in view


@dataclass(frozen=True)
class Layout:
    """Index bookkeeping of one NLP (hard or soft)."""

    horizon: int
    soft: bool
    n_w: int
    n_g: int
    x_index: np.ndarray  # (N+1, 7) indices into w
    u_index: np.ndarray  # (N, 4)
    gap_index: np.ndarray  # (N, 7) indices into g
    rows: tuple[Row, ...]
    equality: tuple[bool, ...]
    slack_index: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=int))
