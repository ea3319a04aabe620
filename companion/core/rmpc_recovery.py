"""The soft (recovery) copy's own parts: its design (:func:`recovery_design`), its velocity box
(:func:`velocity_box_return`) and its initial slacks (:func:`slack_guess`).

The soft copy is the hard problem with an L1-penalised slack on every tube, visibility and
terminal row (:mod:`companion.core.rmpc_problem`); :class:`companion.core.rmpc.Rmpc` solves it
when the hard problem fails. Split out of :mod:`companion.core.rmpc`.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from companion.core.design import design_terminal
from companion.core.params import CameraParams, RmpcParams
from companion.core.rmpc_problem import (
    Layout,
    centre,
    corner_points,
    image_point,
    tube_matrix,
    visibility_pairs,
)
from companion.core.rmpc_types import TargetMotion
from companion.core.terminal import TerminalDesign


def velocity_box_return(
    x0_abs: np.ndarray, lo: np.ndarray, hi: np.ndarray, u_max: np.ndarray, dt_s: float,
    target_drift_m_s2: float = 0.0,
) -> tuple[np.ndarray, np.ndarray]:
    """The state box of stages ``1..N`` (``lo``, ``hi``: (N, 7), absolute ``col(s, v_q)``) as
    the soft copy uses it when the measured vehicle velocity ``x0_abs[4:7]`` is already outside
    the box (a gust, the attitude lag, a late step): each velocity bound it exceeds is moved out
    to where the vehicle can be after ``n`` steps braking at ``a_ret``,
    ``bound(n) = max(bound, v0 - n dt a_ret)``, so the recovery plan returns into the box at an
    admissible rate instead of being infeasible (a fallback that ignores the target).
    ``a_ret``: ``v_q' = r + psidot_q [v_q2, -v_q1]`` (spec 4 with ``v_q = v_e + v_a``), so
    ``|r_i| = u_max_i`` against a coupling of at most ``u_max_4 |v|_inf`` brakes axis ``i`` at
    ``a_ret = u_max_i - u_max_4 |v0|_inf`` or faster (the vertical axis has no coupling), less
    ``target_drift_m_s2`` on the horizontal axes: the box is on ``v_e + v_a`` with the nominal
    ``v_a(n)`` while the planned-yaw dynamics use ``v_a`` rotated by the planned yaw
    (``stage_motion``), which moves by at most ``|v_a| (u_max_4 + |psidot_a|)`` per second. If
    ``a_ret`` is negative the bound may move further out at that rate (never infeasible by
    construction). A velocity inside the box changes nothing: the box is then exactly the hard
    problem's."""
    lo, hi = lo.copy(), hi.copy()
    v0 = np.asarray(x0_abs, dtype=float)[4:7]
    vinf = float(np.max(np.abs(v0[:2])))
    steps = np.arange(1, lo.shape[0] + 1) * dt_s
    for i, axis in enumerate(range(4, 7)):
        a_ret = u_max[i] - (u_max[3] * vinf + target_drift_m_s2 if i < 2 else 0.0)
        reach = v0[i] - np.sign(v0[i]) * steps * a_ret
        if v0[i] > hi[0, axis]:
            hi[:, axis] = np.maximum(hi[:, axis], reach)
        elif v0[i] < lo[0, axis]:
            lo[:, axis] = np.minimum(lo[:, axis], reach)
    return lo, hi


def recovery_design(rmpc: RmpcParams, camera: CameraParams,
                    terminal: TerminalDesign) -> tuple[RmpcParams, TerminalDesign]:
    """The parameters and terminal ingredients the soft copy is built from: the hard
    problem's, or its own ``rmpc.recovery_q_diag`` / ``rmpc.recovery_eps`` with P, K designed
    from them (``rmpc.terminal.method``)."""
    if rmpc.recovery_q_diag is None and rmpc.recovery_eps is None:
        return rmpc, terminal
    soft = dataclasses.replace(
        rmpc,
        q_diag=rmpc.recovery_q_diag if rmpc.recovery_q_diag is not None else rmpc.q_diag,
        eps=rmpc.recovery_eps if rmpc.recovery_eps is not None else rmpc.eps,
        recovery_q_diag=None, recovery_eps=None)
    return soft, design_terminal(soft, camera)


def hard_terminal_row(hard: RmpcParams, hard_terminal: TerminalDesign,
                      soft: RmpcParams) -> tuple[np.ndarray, float]:
    """The hard problem's terminal set as one more row of the soft copy (``rmpc.recovery_rows
    = "own+terminal"``): ``eta(N)' G eta(N) <= eps_s^2`` with ``G = P_h (eps_s / eps_h)^2``
    (``P_h`` the hard rows' matrix, :func:`tube_matrix`): ``|eta(N)|_{P_h} <= eps_h`` written
    at the soft design's terminal level, so its slack is in the units of the soft terminal
    row's and weighs like it (``rmpc.recovery_tube_penalty``).

    Why: the soft design's own rows measure the plan in their own metric, in which the hard
    problem's terminal set (the row that keeps the hard problem infeasible in an engagement
    behind a fast target) is far looser; with this row the plan also ends nearer that set, so
    the hard problem becomes feasible sooner. In the hard problem's own units (``G = P_h``,
    ``eps_h^2``) the row weighs ~7x more and the plan chases: fewer recovery steps, corners
    out after the first second (docs/reference/visibility.md, "Engagement behind a fast
    target")."""
    g = tube_matrix(hard, np.asarray(hard_terminal.p, dtype=float))
    scale = (soft.eps / hard.eps) ** 2
    return g * scale, float(soft.eps**2)


def _row_value(kind: str, eta: np.ndarray, u: np.ndarray | None, p_mat: np.ndarray,
               rmpc: RmpcParams, camera: CameraParams, d: np.ndarray | None = None,
               corner: int = -1) -> float:
    """The squared-form value of one path row (as in the NLP), evaluated with numpy
    (``eta``: the state the row's image is taken from)."""
    if kind in ("tube", "terminal_set", "goal_set"):
        return float(eta @ p_mat @ eta)
    pu, pn = corner_points(eta, rmpc)[corner] if kind == "corner" else image_point(eta)
    if kind == "terminal_visibility":
        return float(pu**2 + pn**2)
    assert u is not None
    mu, mn = centre(u, rmpc, camera, d)
    return float((pu - mu) ** 2 + (pn - mn) ** 2)



def slack_guess(lay: Layout, eta: np.ndarray, u: np.ndarray, target: TargetMotion,
                p_tube: np.ndarray, rmpc: RmpcParams, camera: CameraParams) -> np.ndarray:
    """Slacks that make the guess feasible for the soft rows (plus a small interior gap)."""
    out = np.zeros(len(lay.slack_index))
    pairs = {st: img for st, img, _ in visibility_pairs(rmpc)}
    for i, row in enumerate(lay.rows):
        u_n = u[row.stage] if row.stage < len(u) else None
        img = pairs.get(row.stage, row.stage) if row.kind in ("visibility", "corner") \
            else row.stage
        d_n = target.disturbance(row.stage) if row.stage < len(u) else None
        val = _row_value(row.kind, eta[img], u_n, p_tube, rmpc, camera, d_n, row.corner)
        if row.kind == "goal_set":  # hard_terminal_row's scale (p_tube: the hard rows')
            val *= ((rmpc.recovery_eps or rmpc.eps) / rmpc.eps) ** 2
        out[i] = max(val - row.upper, 0.0) + 1e-3
    return out
