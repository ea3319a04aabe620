"""The paper's stability and feasibility certificate (Assumption 2, Theorems 1 and 2).

Yang & Li 2024, Assumption 2, Remark 2, Theorems 1 and 2; docs/reference/math.md, section 7.
Everything here is pure math (numpy, scipy, cvxpy): the certificate *evaluates* each condition
as ``lhs <= rhs`` with the numbers it used, it never decides a verdict any other way.

Notation (shapes): ``P`` (7, 7) terminal matrix, ``K`` (4, 7) terminal gain (``u_e = K eta``),
``Omega = {eta : eta' P eta <= eps^2}``, ``Q* = Q + K' R K``,
``Lambda(n) = lambda_max(sqrt(P)) rho e^{L n delta}``, ``X(n) = ((N - n) H + n)/N eps``,
``p = [se1/s3, se2/s3]`` with ``s3 = 1 + se3`` (Remark 3).

The terminal feed-forward ``Gamma`` (spec 7) is bounded component-wise by ``gamma_ff_bound``:
with ``vdot_a`` the derivative of the target velocity components *as seen in the rotating frame
v* (spec 4), ``Gamma[0:2] = Rz(psi)^T a_target_world`` exactly (the ``psidot_q v_a`` terms
cancel), so ``|Gamma_1|, |Gamma_2| <= |a_target|``, ``Gamma_3 = 0``, ``|Gamma_4| <=
|psidot_a|``. :func:`paper_path_feedforward_bound` evaluates these on the paper's AGV path.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import scipy.linalg
import scipy.optimize

from companion.core.errors import CoreError
from companion.core.params import RmpcParams
from companion.core.terminal import TerminalDesign, linearised_model


class CertificateError(CoreError):
    """The terminal design cannot be computed (infeasible LMI, solver failure, bad input)."""


# ----------------------------------------------------------------------------------------------
# Small linear-algebra helpers


def _sym(m: np.ndarray) -> np.ndarray:
    return np.asarray(0.5 * (m + m.T), dtype=float)


def _lmax(m: np.ndarray) -> float:
    return float(np.max(np.linalg.eigvalsh(_sym(m))))


def _lmin(m: np.ndarray) -> float:
    return float(np.min(np.linalg.eigvalsh(_sym(m))))


def paper_path_feedforward_bound(
    period_s: float = 2.0 * math.pi / 0.025, samples: int = 20001
) -> tuple[float, float, float, float]:
    """Component bound of ``Gamma`` on the paper's AGV path (spec 8), dense in one period.

    ``x_a = 0.1 t``, ``y_a = 4 sin(0.025 t)``: ``|a| = 0.0025 |sin(0.025 t)|`` m/s^2 and
    ``psidot_a = (xd ydd - yd xdd)/(xd^2 + yd^2)`` rad/s. Returns
    ``(a_max, a_max, 0, psidot_a_max)`` = ``(0.0025, 0.0025, 0, 0.025)``.
    """
    t = np.linspace(0.0, period_s, samples)
    xd = np.full_like(t, 0.1)
    yd = 0.1 * np.cos(0.025 * t)
    xdd = np.zeros_like(t)
    ydd = -0.0025 * np.sin(0.025 * t)
    a_max = float(np.max(np.hypot(xdd, ydd)))
    psidot = (xd * ydd - yd * xdd) / (xd**2 + yd**2)
    return a_max, a_max, 0.0, float(np.max(np.abs(psidot)))


# ----------------------------------------------------------------------------------------------
# Theorem 1 (3): the largest image offset |p| on Omega


@dataclass(frozen=True)
class VisibilityMax:
    """``max_{eta in Omega} |p|`` and where it is attained.

    ``value``: the maximum (dimensionless, normalised image units; ``inf`` when ``s3`` can reach
    0 on Omega); ``eta``: a maximiser (7,) on the boundary of Omega; ``se12_max``: the paper's
    literal ``max |(se1, se2)|`` on Omega (no division by ``s3``), for reference.
    """

    value: float
    eta: np.ndarray
    se12_max: float


def _max_unit_quadratic(a2: np.ndarray, b2: np.ndarray, c0: float) -> tuple[float, np.ndarray]:
    """``max_{|w| = 1} w' a2 w + 2 b2' w + c0`` over the unit circle (grid + local refine)."""
    th = np.linspace(0.0, 2.0 * math.pi, 1441)[:-1]
    w = np.stack([np.cos(th), np.sin(th)])
    vals = np.einsum("in,ij,jn->n", w, a2, w) + 2.0 * (b2 @ w) + c0
    i = int(np.argmax(vals))

    def neg(t: float) -> float:
        ww = np.array([math.cos(t), math.sin(t)])
        return -float(ww @ a2 @ ww + 2.0 * b2 @ ww + c0)

    step = th[1] - th[0]
    res = scipy.optimize.minimize_scalar(
        neg, bounds=(th[i] - step, th[i] + step), method="bounded", options={"xatol": 1e-13}
    )
    t_best = float(res.x) if -res.fun >= vals[i] else float(th[i])
    return max(-float(res.fun), float(vals[i])), np.array([math.cos(t_best), math.sin(t_best)])


def max_visibility_on_omega(p: np.ndarray, eps: float) -> VisibilityMax:
    """``max |p|``, ``p = [se1, se2]/(1 + se3)``, over ``Omega = {eta' P eta <= eps^2}``.

    Only ``z = (se1, se2, se3)`` matters; the projection of Omega onto it is the ellipsoid
    ``z' W3^-1 z <= eps^2`` with ``W3 = (P^-1)[:3, :3]``. ``|p| <= g`` on it iff, for every unit
    ``w`` (2,), ``max_z (w' z12 - g z3) = eps |W3^1/2 (w, -g)| <= g``, i.e. the ellipsoid lies
    in the cone ``|z12| <= g (1 + z3)``. The left side is convex in ``g``; the smallest ``g``
    satisfying it is found by bisection, the maximisation over ``w`` exactly on the unit
    circle (dense grid + refinement). Infinite when ``eps sqrt(W3[2,2]) >= 1`` (s3 reaches 0).
    """
    w_full = np.linalg.inv(_sym(np.asarray(p, dtype=float)))
    w3 = _sym(w_full[:3, :3])
    se12_max = eps * math.sqrt(_lmax(w3[:2, :2]))
    ext3 = eps * math.sqrt(w3[2, 2])
    if ext3 >= 1.0:
        return VisibilityMax(math.inf, np.full(7, np.nan), se12_max)

    def phi(g: float) -> tuple[float, np.ndarray]:
        f, w = _max_unit_quadratic(w3[:2, :2], -g * w3[:2, 2], g * g * w3[2, 2])
        return eps * math.sqrt(max(f, 0.0)) - g, w

    lo, hi = 0.0, max(se12_max, 1e-12)
    while phi(hi)[0] > 0.0:
        lo, hi = hi, 2.0 * hi
        if hi > 1e9:  # pragma: no cover - excluded by ext3 < 1
            return VisibilityMax(math.inf, np.full(7, np.nan), se12_max)
    for _ in range(100):
        mid = 0.5 * (lo + hi)
        if phi(mid)[0] > 0.0:
            lo = mid
        else:
            hi = mid
        if hi - lo <= 1e-13 * max(1.0, hi):
            break
    g = hi
    _, wdir = phi(g)
    # Maximiser of c'eta on Omega for c = (w, -g, 0...): eta = eps W c / sqrt(c' W c).
    c = np.zeros(7)
    c[:2] = wdir
    c[2] = -g
    eta = eps * (w_full @ c) / math.sqrt(float(c @ w_full @ c))
    return VisibilityMax(g, eta, se12_max)


def visibility_of(eta: np.ndarray) -> np.ndarray:
    """``|p|`` of states ``eta`` (..., 7): ``|(se1, se2)| / (1 + se3)``."""
    e = np.asarray(eta, dtype=float)
    return np.asarray(np.hypot(e[..., 0], e[..., 1]) / (1.0 + e[..., 2]), dtype=float)


# ----------------------------------------------------------------------------------------------
# Assumption 2 (3): the nonlinear remainder (sampled check)


def remainder_ratio_max(
    a: np.ndarray,
    b: np.ndarray,
    k: np.ndarray,
    p: np.ndarray,
    eps: float,
    dt: float,
    psidot_a_max: float,
    samples: int = 20000,
    seed: int = 0,
) -> tuple[float, np.ndarray]:
    """Sampled ``max (r'Pr + 2 eta'A_K'P r) / (eta'P eta)`` over Omega (Assumption 2 (3)).

    With the terminal law ``u = K eta + Gamma`` the input error is ``u_e = K eta`` and the Euler
    step of spec 4 is ``eta+ = A_K eta + r`` with ``r = dt psidot_q J eta``,
    ``J eta = [se2, -se1, 0, 0, ve2, -ve1, 0]`` and ``psidot_q = K_4 eta + psidot_a`` (the
    target's ``v_a``, ``vdot_a`` cancel). On the ray ``eta = s d`` (``d'Pd = 1``, ``0 < s <=
    eps``) the ratio is ``dt^2 psi^2 d'J'PJd + 2 dt psi d'A_K'PJd``, convex in ``psi``; ``psi``
    lies in ``+-(eps |K_4 d| + psidot_a_max)``, so each ray's maximum is bounded in closed form
    (exact when the interval's end is attained). The rays are sampled (uniform on the
    P-sphere) and the best one is refined locally: a sampled, not a proven, bound.
    Returns ``(ratio, eta_worst)``.
    """
    ak = a + b @ k
    jm = np.zeros((7, 7))
    jm[0, 1], jm[1, 0], jm[4, 5], jm[5, 4] = 1.0, -1.0, 1.0, -1.0
    ps = _sym(p)
    lchol = np.linalg.cholesky(ps)  # P = L L'
    m_alpha = _sym(jm.T @ ps @ jm)
    m_beta = _sym(ak.T @ ps @ jm)
    k4 = k[3]

    def ratio_of(d: np.ndarray) -> np.ndarray:
        # d: (n, 7) with d'Pd = 1
        alpha = np.einsum("ni,ij,nj->n", d, m_alpha, d)
        beta = np.einsum("ni,ij,nj->n", d, m_beta, d)
        psi = eps * np.abs(d @ k4) + psidot_a_max
        return np.asarray(dt * dt * psi * psi * alpha + 2.0 * dt * psi * np.abs(beta))

    rng = np.random.default_rng(seed)
    x = rng.standard_normal((samples, 7))
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    d = scipy.linalg.solve_triangular(lchol.T, x.T, lower=False).T  # d = L'^-1 x: d'Pd = 1
    vals = ratio_of(d)
    i = int(np.argmax(vals))

    def neg(xv: np.ndarray) -> float:
        xn = xv / np.linalg.norm(xv)
        dd = scipy.linalg.solve_triangular(lchol.T, xn, lower=False)
        return -float(ratio_of(dd[None, :])[0])

    res = scipy.optimize.minimize(neg, x[i], method="Nelder-Mead",
                                  options={"xatol": 1e-10, "fatol": 1e-14, "maxiter": 4000})
    best = max(float(vals[i]), -float(res.fun))
    xb = res.x / np.linalg.norm(res.x) if -res.fun >= vals[i] else x[i]
    db = scipy.linalg.solve_triangular(lchol.T, xb, lower=False)
    return best, eps * db


# ----------------------------------------------------------------------------------------------
# The certificate


@dataclass(frozen=True)
class Condition:
    """One inequality ``lhs <= rhs`` as evaluated; ``ok`` is exactly ``lhs <= rhs``."""

    name: str
    lhs: float
    rhs: float
    ok: bool
    note: str = ""

    def as_dict(self) -> dict[str, float | bool | str]:
        return {"lhs": self.lhs, "rhs": self.rhs, "ok": self.ok, "note": self.note}


def _cond(name: str, lhs: float, rhs: float, note: str = "") -> Condition:
    return Condition(name, float(lhs), float(rhs), bool(lhs <= rhs), note)


@dataclass(frozen=True)
class CertificateInputs:
    """Everything the certificate depends on (units: ``dt_s`` s, ``lipschitz_l`` 1/s)."""

    p: np.ndarray  # (7, 7)
    k: np.ndarray  # (4, 7)
    kappa: float
    eps: float
    q: np.ndarray  # (7, 7)
    r: np.ndarray  # (4, 4)
    a: np.ndarray  # (7, 7) linearised model (Euler, dt_s)
    b: np.ndarray  # (7, 4)
    horizon: int  # N
    tube_h: float  # H
    rho: float
    lipschitz_l: float
    dt_s: float
    gamma: float  # terminal visibility radius
    u_max: tuple[float, float, float, float]
    gamma_ff_bound: tuple[float, float, float, float]  # |Gamma_i| bound (see module doc)


@dataclass(frozen=True)
class Certificate:
    """The evaluated conditions. ``holds``: all of them hold.

    ``assumption2``: ``kappa`` (0 < kappa < 1), ``decay`` (the matrix inequality with this
    kappa: ``lhs`` = its largest eigenvalue, ``rhs`` = 0), ``input_i`` (u_f in U on Omega) and
    ``remainder`` (sampled). ``theorem1``: ``cond1..3``; ``theorem2``: one condition.
    """

    assumption2: tuple[Condition, ...]
    theorem1: tuple[Condition, Condition, Condition]
    theorem2: Condition
    visibility: VisibilityMax
    lambdas: tuple[float, ...]  # Lambda(0..N)
    cond2_sharp: Condition
    """Not part of the verdict: Theorem 1 (2) with the contraction the proof actually uses.

    The proof bounds ``|A_K eta + r|_P^2 <= eta'(A_K'PA_K + kappa P) eta`` (Assumption 2 (3))
    and then, by (2), by ``(1 - lmin(Q*)/lmax(P)) |eta|_P^2``. Stopping at the first step gives
    ``c = sqrt(lambda_max(P^-1/2 A_K'PA_K P^-1/2) + kappa) <= sqrt(1 - lmin(Q*)/lmax(P))`` and
    the condition ``Lambda(N) <= (1 - c) eps``: the same proof, never more demanding."""

    @property
    def conditions(self) -> tuple[Condition, ...]:
        return (*self.assumption2, *self.theorem1, self.theorem2)

    @property
    def holds(self) -> bool:
        return all(c.ok for c in self.conditions)

    @property
    def failed(self) -> tuple[Condition, ...]:
        return tuple(c for c in self.conditions if not c.ok)


DECAY_ROUNDOFF = 1e-12
"""Allowance on the decay margin: the DARE P meets the inequality with equality, which the
eigenvalue computation returns as ~ +-1e-15."""


def tube_lambda(p: np.ndarray, rho: float, lipschitz_l: float, dt_s: float, n: int) -> float:
    """``Lambda(n) = lambda_max(sqrt(P)) rho e^{L n delta}`` (Theorem 1)."""
    return math.sqrt(_lmax(p)) * rho * math.exp(lipschitz_l * n * dt_s)


def decay_margin_of(ci: CertificateInputs) -> float:
    """Largest ``kappa`` with ``A_K' P A_K - (1 - kappa) P <= -(Q + K' R K)``.

    ``1 - lambda_max(P^-1/2 (A_K'PA_K + Q*) P^-1/2)``; <= 0 means no kappa in (0, 1) works.
    """
    ak = ci.a + ci.b @ ci.k
    p = _sym(ci.p)
    wv, v = np.linalg.eigh(p)
    p_inv_half = v @ np.diag(wv**-0.5) @ v.T
    m = p_inv_half @ (ak.T @ p @ ak + ci.q + ci.k.T @ ci.r @ ci.k) @ p_inv_half
    return 1.0 - _lmax(m)


def certify(ci: CertificateInputs, remainder_samples: int = 20000) -> Certificate:
    """Evaluate Assumption 2 and Theorems 1, 2 of the paper for these ingredients."""
    p = _sym(np.asarray(ci.p, dtype=float))
    k = np.asarray(ci.k, dtype=float)
    n_h, eps = ci.horizon, ci.eps
    if _lmin(p) <= 0.0:
        raise CertificateError("P is not positive definite")
    w = np.linalg.inv(p)
    qs = ci.q + k.T @ ci.r @ k
    lam_p_max, lam_p_min = _lmax(p), _lmin(p)
    x_ratio = _lmin(qs) / lam_p_max
    contraction = math.sqrt(max(0.0, 1.0 - x_ratio))
    lam = tuple(tube_lambda(p, ci.rho, ci.lipschitz_l, ci.dt_s, n) for n in range(n_h + 1))

    a2: list[Condition] = [
        Condition("kappa", ci.kappa, 1.0, bool(0.0 < ci.kappa < 1.0), "need 0 < kappa < 1"),
        _cond("decay", ci.kappa, decay_margin_of(ci) + DECAY_ROUNDOFF,
              "kappa <= largest kappa with A_K'PA_K - (1-kappa)P <= -Q* (+1e-12 round-off)"),
    ]
    for i in range(4):
        reach = eps * math.sqrt(max(0.0, float(k[i] @ w @ k[i])))
        a2.append(_cond(f"input{i + 1}", reach + ci.gamma_ff_bound[i], ci.u_max[i],
                        "eps sqrt(K_i P^-1 K_i') + |Gamma_i|max <= u_max_i"))
    ratio, _ = remainder_ratio_max(ci.a, ci.b, k, p, eps, ci.dt_s, ci.gamma_ff_bound[3],
                                   samples=remainder_samples)
    a2.append(_cond("remainder", ratio, ci.kappa,
                    "sampled max over Omega of (r'Pr + 2 eta'A_K'Pr)/(eta'P eta) <= kappa"))

    vis = max_visibility_on_omega(p, eps)
    t1 = (
        _cond("cond1", lam[n_h - 1], (ci.tube_h - 1.0) / n_h * eps, "Lambda(N-1) <= (H-1)/N eps"),
        _cond("cond2", lam[n_h], (1.0 - contraction) * eps,
              "Lambda(N) <= (1 - sqrt(1 - lmin(Q*)/lmax(P))) eps"),
        _cond("cond3", vis.value, ci.gamma, "max over Omega of |p| <= gamma"),
    )
    lam_qp = _lmax(ci.q) / lam_p_min
    tube = [((n_h - n) * ci.tube_h + n) / n_h * eps for n in range(n_h + 1)]
    s = sum(lam[n - 1] ** 2 + 2.0 * lam[n - 1] * tube[n] for n in range(1, n_h + 1))
    lhs2 = lam_qp * s + lam[n_h] ** 2 + 2.0 * contraction * lam[n_h] * eps
    t2 = _cond("theorem2", lhs2, lam_qp * eps * eps,
               "lambda(Q,P) sum(Lambda(n-1)^2 + 2 Lambda(n-1) X(n)) + Lambda(N)^2 + "
               "2 sqrt(1 - lmin(Q*)/lmax(P)) Lambda(N) eps <= lambda(Q,P) eps^2")
    ak = ci.a + ci.b @ k
    wv, vv = np.linalg.eigh(p)
    ph = vv @ np.diag(wv**-0.5) @ vv.T
    c_sharp = math.sqrt(max(0.0, _lmax(ph @ ak.T @ p @ ak @ ph) + ci.kappa))
    sharp = _cond("cond2_sharp", lam[n_h], (1.0 - c_sharp) * eps,
                  "Lambda(N) <= (1 - sqrt(lmax(P^-1/2 A_K'PA_K P^-1/2) + kappa)) eps "
                  "(not the paper's; same proof, needs Assumption 2)")
    return Certificate(tuple(a2), t1, t2, vis, lam, sharp)



def inputs_from_design(
    rmpc: RmpcParams, design: TerminalDesign,
    gamma_ff_bound: tuple[float, float, float, float] | None = None,
) -> CertificateInputs:
    """:class:`CertificateInputs` for a config and its terminal design (spec 7).

    ``gamma_ff_bound`` defaults to :func:`paper_path_feedforward_bound` (the paper's AGV path).
    """
    a, b = linearised_model(rmpc.dt_s, rmpc.desired_depth_m)
    return CertificateInputs(
        p=np.asarray(design.p, dtype=float),
        k=np.asarray(design.k, dtype=float),
        kappa=float(design.kappa),
        eps=float(design.eps),
        q=np.diag(rmpc.q_diag),
        r=np.diag(rmpc.r_diag),
        a=a,
        b=b,
        horizon=rmpc.horizon,
        tube_h=rmpc.tube_h,
        rho=rmpc.rho,
        lipschitz_l=design.lipschitz_l,
        dt_s=rmpc.dt_s,
        gamma=float(design.gamma),
        u_max=rmpc.u_max,
        gamma_ff_bound=gamma_ff_bound or paper_path_feedforward_bound(),
    )


# ----------------------------------------------------------------------------------------------
# Where the guarantee applies: feasibility of the first RMPC problem

PAPER_ETA0 = (0.0159, -0.2230, 0.6, 0.3927, -0.1307, -0.0541, 0.0)
"""The paper's initial error ``eta_e(0)`` (spec 8)."""
PAPER_V_A = (0.1307, 0.0541)
"""The AGV's velocity in the virtual frame at t = 0 (m/s), ``= -v_e(0)`` of the hovering UAV."""


@dataclass(frozen=True)
class ChannelReach:
    """A decoupled channel of the nominal model from ``eta0``: the interval ``[lo, hi]`` its
    state reaches at ``n = N`` under ``|u| <= u_max`` and the extent ``+-omega`` of Omega in it.
    ``ok``: the intervals meet (necessary for the terminal constraint ``|eta(N)|_P <= eps``)."""

    name: str
    lo: float
    hi: float
    omega: float
    ok: bool


def terminal_reach(
    eta0: Sequence[float] | np.ndarray, p: np.ndarray, eps: float, dt_s: float, z_star_m: float,
    horizon: int, u_max: Sequence[float], psidot_a_max: float,
) -> tuple[ChannelReach, ChannelReach]:
    """Necessary condition for the first RMPC problem: can ``se3`` and ``se4`` reach Omega?

    The depth and yaw channels of spec 4 are exactly linear and decoupled:
    ``se3(N) = se3(0) - dt/z* (N ve3(0) + dt sum_{j<N-1} (N-1-j) r3(j))`` and
    ``se4(N) = se4(0) - dt sum_n (psidot_q(n) - psidot_a(n))``. Omega's extent in coordinate
    ``i`` is ``eps sqrt((P^-1)_ii)``. If a channel's reachable interval misses it, no input
    sequence meets the terminal constraint: the problem is infeasible, whatever the solver says.
    """
    e = np.asarray(eta0, dtype=float)
    w = np.linalg.inv(_sym(np.asarray(p, dtype=float)))
    n = horizon
    ramp = dt_s * u_max[2] * n * (n - 1) / 2.0
    c3 = e[2] - dt_s / z_star_m * n * e[6]
    lo3, hi3 = c3 - dt_s / z_star_m * ramp, c3 + dt_s / z_star_m * ramp
    yaw = n * dt_s * (u_max[3] + psidot_a_max)
    lo4, hi4 = e[3] - yaw, e[3] + yaw
    out = []
    for name, lo, hi, idx in (("se3", lo3, hi3, 2), ("se4", lo4, hi4, 3)):
        om = eps * math.sqrt(w[idx, idx])
        out.append(ChannelReach(name, float(lo), float(hi), om, bool(lo <= om and hi >= -om)))
    return out[0], out[1]


@dataclass(frozen=True)
class FeasibilityReport:
    """Is the first RMPC problem (hard constraints) feasible from ``eta0``?

    ``reach``: the exact necessary check of :func:`terminal_reach`; ``solver_mode``: what the
    RMPC returned ('optimal' = the hard problem was solved; 'recovery'/'fallback' = it was not),
    ``solver_status``: its status of the hard attempt ('' when no solver was run);
    ``feasible``: the hard problem was solved (False also when the reach check already fails).
    """

    eta0: tuple[float, ...]
    v_a_m_s: tuple[float, float]
    reach: tuple[ChannelReach, ChannelReach]
    solver_mode: str
    solver_status: str
    feasible: bool | None


def feasibility_report(
    eta0: Sequence[float], v_a_m_s: Sequence[float], ci: CertificateInputs, z_star_m: float,
    solve: Callable[[np.ndarray], tuple[str, str]] | None,
) -> FeasibilityReport:
    """Feasibility of the first RMPC problem from ``eta0`` (target velocity ``v_a_m_s``).

    ``solve(eta0) -> (mode, hard_status)`` runs the RMPC's hard problem (mode 'optimal' when it
    was solved); ``None`` runs only the necessary reach check (``feasible`` is then ``None``
    unless that check already proves infeasibility).
    """
    e = np.asarray(eta0, dtype=float).reshape(7)
    reach = terminal_reach(e, ci.p, ci.eps, ci.dt_s, z_star_m, ci.horizon, ci.u_max,
                           ci.gamma_ff_bound[3])
    mode, status = ("", "") if solve is None else solve(e)
    feasible: bool | None
    if not all(c.ok for c in reach):
        feasible = False
    elif solve is None:
        feasible = None
    else:
        feasible = mode == "optimal"
    return FeasibilityReport(tuple(float(x) for x in e),
                             (float(v_a_m_s[0]), float(v_a_m_s[1])), reach, mode, status,
                             feasible)


