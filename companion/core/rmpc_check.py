"""The independent check of an RMPC solution: every constraint of spec 6 re-evaluated with
numpy on the returned trajectory (:func:`check_solution`), and the visibility rows' margins.

Split out of :mod:`companion.core.rmpc`.
"""

from __future__ import annotations

import numpy as np

from companion.core.dynamics import euler_step
from companion.core.params import CameraParams, RmpcParams
from companion.core.rmpc_problem import (
    NU,
    NX,
    centre,
    corner_gain,
    corner_points,
    image_point,
    tube_bound,
    tube_matrix,
    visibility_pairs,
    visibility_radius,
)
from companion.core.rmpc_types import (
    ConstraintViolation,
    RmpcResult,
    _state_offset,
    planned_motion,
    state_lower,
)
from companion.core.terminal import TerminalDesign


def check_solution(
    result: RmpcResult,
    rmpc: RmpcParams,
    camera: CameraParams,
    terminal: TerminalDesign,
    tol: float = 1e-6,
    groups: tuple[str, ...] | None = None,
) -> list[ConstraintViolation]:
    """Every constraint of spec 6 evaluated on ``result``'s trajectory with numpy.

    Independent of the solver: dynamics (max |gap| per stage), input box, absolute state box
    (n = 1..N; ``eta(0)`` is the measurement), and the groups in ``groups`` (default: the
    result's active groups): tube ``|eta(n)|_P <= X(n)`` (n = 0..N, X(N) = eps), visibility
    ``|p(n) - M(u(n))| <= r_v - n rho e^{L(n-1) delta}`` (n = 1..N-1), terminal
    ``|eta(N)|_P <= eps`` and ``|p(N)| <= gamma``. Amounts are in natural units (not squared);
    a constraint counts as violated when it exceeds its bound by more than ``tol``.
    """
    groups = result.active_groups if groups is None else groups
    eta, u, tgt = result.eta_pred, result.u_pred, result.target
    big_n = rmpc.horizon
    p_mat = np.asarray(terminal.p, dtype=float)
    eta_max = np.asarray(rmpc.eta_max, dtype=float)
    state_lo = state_lower(rmpc)
    u_max = np.asarray(rmpc.u_max, dtype=float)
    out: list[ConstraintViolation] = []

    def add(name: str, n: int, amount: float) -> None:
        if not amount <= tol:  # also catches NaN
            out.append(ConstraintViolation(name, n, float(amount)))

    if eta.shape != (big_n + 1, NX) or u.shape != (big_n, NU):
        return [ConstraintViolation("shape", -1, float("inf"))]
    s4_ref = float(eta[0][3])
    for n in range(big_n):
        v_a, vdot_a, psidot_a = planned_motion(rmpc, eta[n], u[n], tgt, n, s4_ref)
        nxt = euler_step(eta[n], u[n], v_a, vdot_a, psidot_a, rmpc.desired_depth_m, rmpc.dt_s)
        add("dynamics", n, float(np.max(np.abs(eta[n + 1] - nxt))))
        add("input", n, float(np.max(np.abs(u[n]) - u_max)))
    for n in range(1, big_n + 1):
        absolute = eta[n] + _state_offset(tgt.v_a_m_s[min(n, big_n - 1)])
        add("state", n, float(max(np.max(absolute - eta_max), np.max(state_lo - absolute))))
    p_tube = tube_matrix(rmpc, p_mat)
    norm_p = np.sqrt(np.maximum(np.einsum("ni,ij,nj->n", eta, p_tube, eta), 0.0))
    if "tube" in groups:
        for n in range(big_n):
            add("tube", n, float(norm_p[n] - tube_bound(rmpc, n)))
    if "visibility" in groups:
        for n, img, inp in visibility_pairs(rmpc):
            mu, mn = centre(u[inp], rmpc, camera, tgt.disturbance(inp))
            for pu, pn, radius in _visibility_points(eta[img], rmpc, camera, terminal, img):
                add("visibility", n, float(np.hypot(pu - mu, pn - mn)) - radius)
    if "terminal" in groups or "tube" in groups:  # X(N) = eps
        add("terminal_set", big_n, float(norm_p[big_n] - rmpc.eps))
    if "terminal" in groups:
        pu, pn = image_point(eta[big_n])
        add("terminal_visibility", big_n, float(np.hypot(pu, pn) - terminal.gamma))
    if not (np.all(np.isfinite(result.u0)) and np.allclose(result.u0, u[0])):
        out.append(ConstraintViolation("u0", 0, float("inf")))
    return out


def visibility_margin(
    result: RmpcResult, rmpc: RmpcParams, camera: CameraParams, terminal: TerminalDesign
) -> np.ndarray:
    """Radius minus distance of every visibility row (:func:`visibility_pairs` order, N-1
    values): 0 means binding."""
    pairs = visibility_pairs(rmpc)
    out = np.zeros(len(pairs))
    for i, (_, img, inp) in enumerate(pairs):
        mu, mn = centre(result.u_pred[inp], rmpc, camera, result.target.disturbance(inp))
        out[i] = min(radius - float(np.hypot(pu - mu, pn - mn)) for pu, pn, radius
                     in _visibility_points(result.eta_pred[img], rmpc, camera, terminal, img))
    return out


def _visibility_points(eta: np.ndarray, rmpc: RmpcParams, camera: CameraParams,
                       terminal: TerminalDesign, img: int) -> list[tuple[float, float, float]]:
    """``(p_u, p_n, tightened radius)`` of each point a visibility row keeps in view: the
    centroid (``rmpc.visibility = "centroid"``) or every corner (``"corners"``)."""
    if rmpc.visibility == "corners":
        radius = visibility_radius(rmpc, terminal, img, corner_gain(rmpc, camera))
        return [(float(pu), float(pn), radius) for pu, pn in corner_points(eta, rmpc)]
    pu, pn = image_point(eta)
    return [(float(pu), float(pn), visibility_radius(rmpc, terminal, img))]
