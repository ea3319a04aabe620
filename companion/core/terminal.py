"""Terminal ingredients of spec section 7: linearisation, K and P.

Linearisation of the error dynamics at the origin with ``psidot = 0``:
``se_i' = -ve_i/z*`` (i = 1..3), ``se4' = -u_e4``, ``ve' = u_e[0:3]``, discretised with explicit
Euler at ``dt``: ``eta(k+1) = A eta(k) + B u_e(k)``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


def linearised_model(dt: float, z_star: float) -> tuple[np.ndarray, np.ndarray]:
    """Discrete ``(A, B)`` (7x7, 7x4) of the error dynamics at the origin (Euler, step ``dt``)."""
    ac = np.zeros((7, 7))
    bc = np.zeros((7, 4))
    for i in range(3):
        ac[i, 4 + i] = -1.0 / z_star
        bc[4 + i, i] = 1.0
    bc[3, 3] = -1.0
    return np.eye(7) + dt * ac, dt * bc


@dataclass(frozen=True)
class LqrTerminal:
    """``u_e = K eta`` and the cost-to-go ``eta' P eta`` of the DARE (unconstrained LQR)."""

    k: np.ndarray  # (4, 7)
    p: np.ndarray  # (7, 7), symmetric positive definite


def dare_terminal(a: np.ndarray, b: np.ndarray, q: np.ndarray, r: np.ndarray) -> LqrTerminal:
    """Solve the discrete algebraic Riccati equation; ``K = -(R + B'PB)^-1 B'PA``."""
    import scipy.linalg  # here: the solver's child process loads this module, never solves it

    p = scipy.linalg.solve_discrete_are(a, b, q, r)
    p = 0.5 * (p + p.T)
    k = -np.linalg.solve(r + b.T @ p @ b, b.T @ p @ a)
    return LqrTerminal(k=k, p=p)


@dataclass(frozen=True)
class TerminalDesign:
    """Everything the RMPC and the certificate need from the offline design (spec 6, 7).

    ``p`` (7x7) and ``k`` (4x7): terminal cost/set matrix and terminal gain (``u_e = K eta``);
    ``kappa``: decay margin with ``A_K' P A_K - (1 - kappa) P <= -(Q + K' R K)``: the largest
    such value (0 if none) for 'dare' or a scaled P, the design's for 'lmi', the configured one
    for 'given' (if > 0; the certificate checks it);
    ``eps``: terminal level (``Omega = {|eta|_P <= eps}``); ``gamma``: terminal visibility radius;
    ``r_v``: visibility circle radius; ``lipschitz_l``: L of Remark 1 (1/s).
    """

    p: np.ndarray
    k: np.ndarray
    kappa: float
    eps: float
    gamma: float
    r_v: float
    lipschitz_l: float
    method: str


def decay_margin(a: np.ndarray, b: np.ndarray, k: np.ndarray, p: np.ndarray,
                 q: np.ndarray, r: np.ndarray) -> float:
    """Largest ``kappa`` with ``A_K' P A_K - (1 - kappa) P <= -(Q + K' R K)`` (Assumption 2).

    The inequality is ``A_K'PA_K + Q* <= (1 - kappa) P``, i.e. ``1 - kappa >= lambda_max(
    P^-1/2 (A_K'PA_K + Q*) P^-1/2)``. A result <= 0 means no kappa in (0, 1) exists for this P.
    """
    ak = a + b @ k
    qs = q + k.T @ r @ k
    w, v = np.linalg.eigh(p)
    p_inv_half = v @ np.diag(w**-0.5) @ v.T
    m = p_inv_half @ (ak.T @ p @ ak + qs) @ p_inv_half
    return float(1.0 - np.max(np.linalg.eigvalsh(0.5 * (m + m.T))))


def tilt_limits(u_max: tuple[float, ...], g: float) -> tuple[float, float]:
    """Largest |roll| and |pitch| (rad) that inputs within ``u_max`` can command (spec 5)."""
    from companion.core.geometry import attitude_from_accel

    worst_phi = 0.0
    worst_theta = 0.0
    for r1 in (-u_max[0], u_max[0]):
        for r2 in (-u_max[1], u_max[1]):
            for r3 in (-u_max[2], 0.0, u_max[2]):
                phi, theta, _ = attitude_from_accel(
                    np.float64(r1), np.float64(r2), np.float64(r3), g
                )
                worst_phi = max(worst_phi, abs(float(phi)))
                worst_theta = max(worst_theta, abs(float(theta)))
    return worst_phi, worst_theta


def terminal_visibility_radius(
    phi_max: float, theta_max: float, half_m: float, lam: float
) -> float:
    """``gamma``: radius about the origin of the circle inscribed in the intersection of the
    visible area mapped to the virtual image at the extreme attitudes ``(+-phi_max,
    +-theta_max)`` (normalised units).

    The origin lies inside every mapped quadrangle, so the distance from it to the boundary
    of their intersection is the smallest distance to any quadrangle's edges.
    """
    from companion.core.geometry import real_to_virtual

    corners = np.array([[1, 1], [1, -1], [-1, -1], [-1, 1]], dtype=float) * half_m
    best = np.inf
    for phi in (-phi_max, phi_max):
        for theta in (-theta_max, theta_max):
            uv, nv = real_to_virtual(corners[:, 0], corners[:, 1], phi, theta, lam)
            poly = np.column_stack([uv, nv]) / lam
            for i in range(4):
                p0, p1 = poly[i], poly[(i + 1) % 4]
                d = p1 - p0
                t = np.clip(-(p0 @ d) / (d @ d), 0.0, 1.0)
                best = min(best, float(np.linalg.norm(p0 + t * d)))
    return best
