"""The terminal ingredients for a parameter set: DARE, a given (P, K) or the LMI design.

Yang & Li 2024, Section IV (terminal set Omega, law K, kappa) and Remark 2.
"""

from __future__ import annotations

import numpy as np

from companion.core.params import CameraParams, RmpcParams
from companion.core.terminal import (
    TerminalDesign,
    dare_terminal,
    decay_margin,
    linearised_model,
    terminal_visibility_radius,
    tilt_limits,
)
from companion.core.terminal_cache import cached_design


def design_terminal(rmpc: RmpcParams, camera: CameraParams) -> TerminalDesign:
    """The terminal ingredients for a config (``rmpc.terminal.method``); a DARE or LMI design
    is cached in ``rmpc.cache_dir`` (:mod:`companion.core.terminal_cache`)."""
    phi_max, theta_max = tilt_limits(rmpc.u_max, rmpc.g_m_s2)
    gamma = terminal_visibility_radius(
        phi_max, theta_max, camera.visible_half_m, camera.focal_length_m
    )
    tc = rmpc.terminal

    def design() -> tuple[np.ndarray, np.ndarray, float]:
        return _matrices(rmpc, gamma)

    if tc.method == "given":
        p, k, kappa = design()
    else:
        inputs = (tc, rmpc.dt_s, rmpc.desired_depth_m, rmpc.q_diag, rmpc.r_diag, rmpc.u_max,
                  rmpc.g_m_s2, rmpc.eps, gamma)
        p, k, kappa = cached_design(rmpc.cache_dir, inputs, design)
    return TerminalDesign(
        p=p,
        k=k,
        kappa=kappa,
        eps=rmpc.eps,
        gamma=gamma,
        r_v=camera.r_v,
        lipschitz_l=rmpc.lipschitz_l,
        method=tc.method,
    )


def _matrices(rmpc: RmpcParams, gamma: float) -> tuple[np.ndarray, np.ndarray, float]:
    """``(P, K, kappa)`` of the configured method (reads only what the cache key names)."""
    a, b = linearised_model(rmpc.dt_s, rmpc.desired_depth_m)
    q = np.diag(rmpc.q_diag)
    r = np.diag(rmpc.r_diag)
    tc = rmpc.terminal
    kappa: float | None = None  # None: the largest the decay inequality allows
    if tc.method == "given":
        k = np.array(tc.k_matrix, dtype=float)
        p = np.array(tc.p_matrix, dtype=float)
        kappa = tc.kappa if tc.kappa > 0 else None
    elif tc.method == "dare":
        lqr = dare_terminal(a, b, q, r)
        k, p = lqr.k, lqr.p
    else:
        # Remark 2: LMI design aimed at the certificate (imported here: cvxpy is slow to load).
        from companion.core.certificate import paper_path_feedforward_bound
        from companion.core.lmi import lmi_certified_design

        lmi = lmi_certified_design(
            a, b, q, r, eps=rmpc.eps, u_max=rmpc.u_max,
            gamma_ff_bound=paper_path_feedforward_bound(), gamma=gamma,
            kappa=tc.kappa if tc.kappa > 0 else 4e-4,
        )
        k, p, kappa = lmi.k, lmi.p, lmi.kappa
    if tc.p_scale != 1.0:
        p = tc.p_scale * p
        kappa = None  # a scaled P has its own margin
    if kappa is None:
        kappa = max(0.0, decay_margin(a, b, k, p, q, r))
    return p, k, kappa
