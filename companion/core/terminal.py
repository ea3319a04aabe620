"""Terminal ingredients of spec section 7: linearisation, K and P.

Linearisation of the error dynamics at the origin with ``psidot = 0``:
``se_i' = -ve_i/z*`` (i = 1..3), ``se4' = -u_e4``, ``ve' = u_e[0:3]``, discretised with explicit
Euler at ``dt``: ``eta(k+1) = A eta(k) + B u_e(k)``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg


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
    p = scipy.linalg.solve_discrete_are(a, b, q, r)
    p = 0.5 * (p + p.T)
    k = -np.linalg.solve(r + b.T @ p @ b, b.T @ p @ a)
    return LqrTerminal(k=k, p=p)
