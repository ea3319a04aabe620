"""What the RTI linearisation forms' tests share: two controllers differing only in
``rmpc.rti_linearisation``, the closed loops' starting poses, and the points to compare the
forms at (real closed loops' linearisation points, random points, zero)."""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from companion.config import load_config
from companion.core.design import design_terminal
from companion.core.rmpc import Rmpc
from companion.core.rmpc_scenario import closed_loop, initial_error

PAPER_POSE = ((-0.2, 0.4, -3.2), np.pi / 8)
EDGE_POSE = ((-1.0, 0.0, -3.2), np.pi / 4)

Point = tuple[np.ndarray, np.ndarray, np.ndarray]


def form_pair(first: str, second: str) -> tuple[Rmpc, Rmpc]:
    """The default config's RTI controller with each of two linearisation forms."""
    cfg = load_config()
    design = design_terminal(cfg.rmpc, cfg.camera)
    a, b = (Rmpc(dataclasses.replace(cfg.rmpc, solver="rti", rti_linearisation=form),
                 cfg.camera, design) for form in (first, second))
    return a, b


def linearisation_points(mpc: Rmpc) -> list[Point]:
    """``(U, eta0, p)`` at each step of 30-step closed loops from the paper and edge poses
    (each step's guess), at random points (large inputs, states far from the tube: any sign,
    no special zeros) and at zero."""
    points = []
    for pose in (PAPER_POSE, EDGE_POSE):
        mpc.reset()
        for s in closed_loop(mpc, initial_error(*pose), 30, 1e-4, 1):
            r = s.result
            points.append((r.u_pred.ravel(), r.eta_pred[0],
                           np.append(r.target.packed(), r.eta_pred[0][3])))
    rng = np.random.default_rng(7)
    assert mpc._rti is not None
    n_u, n_p = mpc._rti.n_u, points[0][2].size
    for scale in (1e-3, 0.1, 1.0, 3.0):
        points.append((rng.normal(size=n_u) * scale, rng.normal(size=7) * scale,
                       rng.normal(size=n_p) * scale))
    points.append((np.zeros(n_u), np.zeros(7), np.zeros(n_p)))
    return points


def halfway_state_bounds(solver: Any, du: np.ndarray, lo: np.ndarray,
                         hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(lo, hi)`` with the bound of the state row that the linearised step ``du`` moves most
    (from the solver's last linearisation) moved half-way towards it: a box the step leaves."""
    c_x = solver._c_x.copy()
    x_lin = c_x + solver._j_state @ du
    i = int(np.argmax(np.abs(x_lin - c_x)))
    lo2, hi2 = lo.copy(), hi.copy()
    if x_lin[i] > c_x[i]:
        hi2[i] = 0.5 * (x_lin[i] + c_x[i])
    else:
        lo2[i] = 0.5 * (x_lin[i] + c_x[i])
    return lo2, hi2
