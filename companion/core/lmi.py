"""Terminal ingredients by LMI design (Remark 2 of Yang & Li 2024), aimed at the certificate of
:mod:`companion.core.certificate`. Pure math (numpy, cvxpy)."""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import cvxpy as cp
import numpy as np
import scipy.linalg
import scipy.optimize

from companion.core.certificate import CertificateError, _lmax, _sym

_bmat: Callable[..., Any] = cp.bmat  # type: ignore[attr-defined]
_reshape: Callable[..., Any] = cp.reshape  # type: ignore[attr-defined]


# ----------------------------------------------------------------------------------------------
# LMI design (Remark 2)


@dataclass(frozen=True)
class LmiDesign:
    """Result of :func:`lmi_terminal`: ``P = W^-1``, ``K = Y W^-1``, the ``kappa`` used."""

    p: np.ndarray
    k: np.ndarray
    kappa: float
    status: str
    objective: float


def lmi_terminal(
    a: np.ndarray,
    b: np.ndarray,
    q: np.ndarray,
    r: np.ndarray,
    *,
    eps: float,
    kappa: float,
    u_max: Sequence[float],
    gamma_ff_bound: Sequence[float],
    p_max: float | None = None,
    vis_gamma: float | None = None,
    vis_dirs: int = 96,
    w33_min: float | None = None,
    contain: Sequence[tuple[np.ndarray, float]] = (),
    objective_state: np.ndarray | None = None,
    solver: str = "CLARABEL",
) -> LmiDesign:
    """Find ``K``, ``P > 0`` with ``A_K' P A_K - (1 - kappa) P <= -(Q + K' R K)`` (Remark 2).

    Variables ``W = P^-1``, ``Y = K W``; the decay inequality is, by a Schur complement,
    ``[[(1-k)W, (AW+BY)', W Q^1/2, Y' R^1/2], [AW+BY, W, 0, 0], [Q^1/2 W, 0, I, 0],
    [R^1/2 Y, 0, 0, I]] >= 0``. Further (all convex in ``W, Y``):

    - inputs on Omega: ``eps^2 K_i W K_i' <= (u_max_i - |Gamma_i|max)^2`` as
      ``[[(u_max_i - G_i)^2/eps^2, Y_i], [Y_i', W]] >= 0``;
    - ``p_max``: ``lambda_max(P) <= p_max`` as ``W >= I/p_max`` (Theorem 1 (2));
    - ``vis_gamma = g``: Theorem 1 (3) itself, ``max_Omega |p| <= g``: for every unit ``w``,
      ``eps^2 (w, -g)' W[:3,:3] (w, -g) <= g^2`` (see :func:`max_visibility_on_omega`), linear
      in ``W``; imposed on ``vis_dirs`` directions ``w`` (the exact check follows the design);
    - ``w33_min``: ``(P^-1)[2,2] >= w33_min``, i.e. Omega reaches ``|se3| = eps sqrt(w33_min)``;
    - ``contain``: states ``x`` with levels ``l``: ``x' P x <= l^2``;
    - objective: minimise ``x' P x`` for ``objective_state`` (a state the terminal set should
      contain with margin) or, without it, maximise ``t`` with ``W >= t I``
      (smallest ``lambda_max(P)``).
    """
    n, m = b.shape
    qh = scipy.linalg.sqrtm(q).real
    rh = scipy.linalg.sqrtm(r).real
    wv = cp.Variable((n, n), symmetric=True)
    yv = cp.Variable((m, n))
    t = cp.Variable()
    awby = a @ wv + b @ yv
    zn = np.zeros((n, n))
    lmi = _bmat([
        [(1.0 - kappa) * wv, awby.T, wv @ qh, yv.T @ rh],
        [awby, wv, zn, np.zeros((n, m))],
        [qh @ wv, zn, np.eye(n), np.zeros((n, m))],
        [rh @ yv, np.zeros((m, n)), np.zeros((m, n)), np.eye(m)],
    ])
    cons = [0.5 * (lmi + lmi.T) >> 0, wv >> 1e-6 * np.eye(n)]
    for i in range(m):
        room = float(u_max[i]) - float(gamma_ff_bound[i])
        if room <= 0:
            raise CertificateError(f"input {i + 1}: |Gamma| bound leaves no room in u_max")
        blk = _bmat([[np.array([[room**2 / eps**2]]), yv[i:i + 1, :]], [yv[i:i + 1, :].T, wv]])
        cons.append(0.5 * (blk + blk.T) >> 0)
    if p_max is not None:
        cons.append(wv >> np.eye(n) / p_max)
    if vis_gamma is not None:
        for th in np.linspace(0.0, 2.0 * math.pi, vis_dirs, endpoint=False):
            c = np.array([math.cos(th), math.sin(th), -vis_gamma])
            cons.append(c @ wv[:3, :3] @ c <= vis_gamma**2 / eps**2)
    if w33_min is not None:
        cons.append(wv[2, 2] >= w33_min)
    for x, level in contain:
        xc = np.asarray(x, dtype=float).reshape(n, 1)
        blk = _bmat([[np.array([[level**2]]), xc.T], [xc, wv]])
        cons.append(0.5 * (blk + blk.T) >> 0)
    prob = _problem(cons, wv, t, objective_state)
    _solve(prob, wv, solver)
    w = _sym(np.asarray(wv.value))
    p = _sym(np.linalg.inv(w))
    k = np.asarray(yv.value) @ np.linalg.inv(w)
    return LmiDesign(p=p, k=k, kappa=kappa, status=str(prob.status), objective=float(prob.value))


def _problem(cons: list[Any], wv: Any, t: Any, objective_state: np.ndarray | None) -> Any:
    """The design's objective: the smallest ``x' P x`` for ``objective_state`` (a state the
    terminal set should contain with margin), else the largest ``t`` with ``W >= t I``."""
    n = wv.shape[0]
    if objective_state is not None:
        xo = np.asarray(objective_state, dtype=float).reshape(n, 1)
        blk = _bmat([[_reshape(t, (1, 1), order="C"), xo.T], [xo, wv]])
        cons.append(0.5 * (blk + blk.T) >> 0)
        return cp.Problem(cp.Minimize(t), cons)
    cons.append(wv >> t * np.eye(n))
    return cp.Problem(cp.Maximize(t), cons)


def _solve(prob: Any, wv: Any, solver: str) -> None:
    """Solve ``prob``; :class:`CertificateError` when the solver fails or it is infeasible."""
    try:
        with warnings.catch_warnings():
            # "Solution may be inaccurate": the result is verified exactly afterwards
            warnings.simplefilter("ignore", UserWarning)
            prob.solve(solver=solver)
    except cp.error.SolverError as exc:
        raise CertificateError(f"LMI solver {solver} failed: {exc}") from None
    if prob.status not in ("optimal", "optimal_inaccurate") or wv.value is None:
        raise CertificateError(f"LMI design infeasible (status {prob.status})")


def _final_kappa(a: np.ndarray, b: np.ndarray, k: np.ndarray, p: np.ndarray, q: np.ndarray,
                 r: np.ndarray, kappa: float) -> float:
    """The design's kappa, never above what (P, K) actually allow (solver tolerance)."""
    ak = a + b @ k
    wv, v = np.linalg.eigh(_sym(p))
    ph = v @ np.diag(wv**-0.5) @ v.T
    margin = 1.0 - _lmax(ph @ (ak.T @ p @ ak + q + k.T @ r @ k) @ ph)
    return max(0.0, min(kappa, margin * (1.0 - 1e-9)))


def lmi_certified_design(
    a: np.ndarray,
    b: np.ndarray,
    q: np.ndarray,
    r: np.ndarray,
    *,
    eps: float,
    u_max: Sequence[float],
    gamma_ff_bound: Sequence[float],
    gamma: float,
    kappa: float = 4e-4,
    vis_margins: Sequence[float] = (0.97, 0.985, 1.0),
) -> LmiDesign:
    """The LMI design aimed at the certificate for this ``eps`` (deterministic, ~0.3 s).

    :func:`lmi_terminal` with Theorem 1 (3) imposed as ``max_Omega |p| <= m gamma`` for the
    first ``m`` in ``vis_margins`` that is feasible, maximising ``t`` with ``W >= t I`` (the
    smallest ``lambda_max(P)``, which is what Theorem 1 (1), (2) and Theorem 2 need). Without a
    feasible ``m``, the plain design (decay + inputs only). ``kappa``: the decay margin
    demanded; it must exceed the nonlinear remainder ratio of Assumption 2 (3) (~1.6e-4 for
    the paper's numbers). The returned ``kappa`` never exceeds what ``(P, K)`` allow.
    """
    des: LmiDesign | None = None
    for m in vis_margins:
        try:
            des = lmi_terminal(a, b, q, r, eps=eps, kappa=kappa, u_max=u_max,
                               gamma_ff_bound=gamma_ff_bound, vis_gamma=m * gamma)
            break
        except CertificateError:
            continue
    if des is None:
        des = lmi_terminal(a, b, q, r, eps=eps, kappa=kappa, u_max=u_max,
                           gamma_ff_bound=gamma_ff_bound)
    kap = _final_kappa(a, b, des.k, des.p, q, r, kappa)
    return LmiDesign(p=des.p, k=des.k, kappa=kap, status=des.status, objective=des.objective)

PAPER_TERMINAL_STATE = (-0.006, -0.076, 0.44, 0.153, -0.005, -0.062, 0.24)
"""Where the first RMPC problem from :data:`PAPER_ETA0` can end (``eta(N)``, measured): the
depth error cannot drop below 0.375 in 16 steps, the yaw error below 0.133."""


def lmi_fit_design(
    a: np.ndarray,
    b: np.ndarray,
    q: np.ndarray,
    r: np.ndarray,
    *,
    eps: float,
    fit_state: Sequence[float],
    fit_level: float,
    u_max: Sequence[float],
    gamma_ff_bound: Sequence[float],
    gamma: float,
    kappa: float = 4e-4,
    vis_margin: float = 0.99,
    p_max_hi: float = 5.0,
) -> LmiDesign:
    """The LMI design with the smallest ``lambda_max(P)`` whose Omega contains ``fit_state``
    at level ``fit_level eps`` (``|x|_P <= fit_level eps``) and meets Theorem 1 (3) with
    ``vis_margin gamma`` (bisection on ``p_max`` of :func:`lmi_terminal`, ~2 s).

    This shapes Omega for a known start (e.g. :data:`PAPER_TERMINAL_STATE`); with the paper's
    numbers at eps = 0.13 it makes the first problem at the paper's eta_e(0) feasible with
    every condition but Theorem 1 (2) holding (``cond2_sharp`` holds).
    """
    x = np.asarray(fit_state, dtype=float)

    def fits(pm: float) -> LmiDesign | None:
        try:
            d = lmi_terminal(a, b, q, r, eps=eps, kappa=kappa, u_max=u_max,
                             gamma_ff_bound=gamma_ff_bound, vis_gamma=vis_margin * gamma,
                             objective_state=x, p_max=pm)
        except CertificateError:
            return None
        return d if math.sqrt(max(d.objective, 0.0)) <= fit_level * eps else None

    best = fits(p_max_hi)
    if best is None:
        raise CertificateError(f"no design fits the state at level {fit_level} eps")
    lo, hi = _lmax(q), p_max_hi
    for _ in range(24):
        mid = math.sqrt(lo * hi)
        d = fits(mid)
        if d is None:
            lo = mid
        else:
            hi, best = mid, d
        if hi / lo < 1.002:
            break
    kap = _final_kappa(a, b, best.k, best.p, q, r, kappa)
    return LmiDesign(p=best.p, k=best.k, kappa=kap, status=best.status, objective=best.objective)
