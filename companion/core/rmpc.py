"""The robust MPC of spec section 6 (Yang & Li 2024, problem (2)), solved with CasADi.

Build once, then call :meth:`Rmpc.solve` every control step::

    mpc = Rmpc(cfg.rmpc, cfg.camera, design_terminal(cfg.rmpc, cfg.camera))
    res = mpc.solve(eta0, TargetMotion.constant(v_a, vdot_a, psidot_a, cfg.rmpc.horizon))
    res.u0   # (4,) [r1, r2, r3 (m/s^2, virtual frame, z down), psidot_q (rad/s)]

Each step sets the parameters, warm-starts from the previous solution shifted by one stage (the
last stage filled with the terminal law) and solves the hard problem. If that fails (infeasible
or not converged) a soft copy (L1 penalties on the tube, visibility and terminal rows) is solved
and its input is returned with ``mode='recovery'``; if that fails too, the terminal law clipped to
the input box is returned with ``mode='fallback'``. Every returned trajectory is finite and its
solver status was checked; :func:`check_solution` re-evaluates every constraint independently.

The solves run here, or on a :class:`SolveBackend` the shell provides (``rmpc.solve_isolation =
"process"``: a child process, each step's solves bounded by ``rmpc.max_solve_time_s``); a step
the backend abandons (:class:`SolveAborted`: timeout, solver restarting) is a ``'fallback'``
whose status says so (``timeout: ...``).

The problem layout is in :mod:`companion.core.rmpc_problem`, the compiled-code cache in
:mod:`companion.core.rmpc_cache`.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

import casadi as ca
import numpy as np
from numpy.typing import ArrayLike

from companion.core.design import design_terminal
from companion.core.dynamics import S_REF, euler_step, input_error, terminal_feedforward
from companion.core.errors import CoreError
from companion.core.params import CameraParams, RmpcParams
from companion.core.rmpc_cache import CompiledNlp, RmpcBuildError, compiled_nlp
from companion.core.rmpc_problem import (
    NU,
    NX,
    Layout,
    build_nlp,
    centre,
    corner_gain,
    corner_points,
    image_point,
    stage_motion,
    tube_bound,
    tube_matrix,
    visibility_pairs,
    visibility_radius,
)
from companion.core.terminal import TerminalDesign

__all__ = [
    "ConstraintViolation",
    "Rmpc",
    "RmpcBuildError",
    "RmpcError",
    "RmpcParameterError",
    "RmpcResult",
    "SolveAborted",
    "SolveBackend",
    "TargetMotion",
    "check_solution",
    "terminal_law",
]

log = logging.getLogger(__name__)

FATROP_OPTIONS: dict[str, Any] = {"print_level": 0, "mu_init": 1e-4, "tol": 1e-6}
"""mu_init 1e-4: the warm start is close to the solution, a large initial barrier undoes it."""
IPOPT_OPTIONS: dict[str, Any] = {"print_level": 0, "sb": "yes"}
RECOVERY_SOLVER = "ipopt"
"""The soft copy is solved with ipopt whatever ``rmpc.solver`` says: with active L1 penalties
the costates grow ~penalty-fold, the bilinear dynamics make fatrop's stage-wise Riccati
indefinite and fatrop crawls under heavy regularisation (measured: 'edge' start, >300
iterations, dual infeasibility stuck at ~1e-3) where ipopt converges in ~18 iterations."""
ACCEPT_TOL = 1e-6
"""Largest constraint residual (g rows and bounds, solver units) a 'success' may carry."""


class RmpcError(CoreError):
    """Root of the RMPC's errors."""


class RmpcParameterError(RmpcError, ValueError):
    """A per-step parameter (eta0, target motion) is malformed or not finite: do not command."""


class SolveAborted(RmpcError):
    """A :class:`SolveBackend` gave no result for a solve (it exceeded the step's time bound,
    or the solver process is being restarted): its message is the step's status."""


Evaluation = tuple[int, dict[str, Any], np.ndarray, float, np.ndarray]
"""One evaluation of a compiled solver: (CasADi return flag, the solve's stats entries
``success``, ``return_status``, ``unified_return_status``, ``iter_count``; x, f, g)."""


class SolveBackend(Protocol):
    """Where the NLP evaluations of :class:`Rmpc` run (``rmpc.solve_isolation``; the shell
    builds the child-process one, :mod:`companion.control.solve_guard`).

    ``start_step`` is called once per :meth:`Rmpc.solve` (the step's time bound starts);
    ``evaluate`` solves the NLP ``kind`` ('hard' or 'soft') from the given initial guess,
    parameters and variable bounds, raises :class:`SolveAborted` when it has no result in
    time, and ``RuntimeError`` when CasADi raised."""

    def start_step(self) -> None: ...

    def evaluate(self, kind: str, w0: np.ndarray, par: np.ndarray, lbx: np.ndarray,
                 ubx: np.ndarray) -> Evaluation: ...

    def close(self) -> None: ...


STATS_KEYS = ("success", "return_status", "unified_return_status", "iter_count")


def _ro(a: np.ndarray) -> np.ndarray:
    a = np.array(a, dtype=float)
    a.setflags(write=False)
    return a


@dataclass(frozen=True)
class TargetMotion:
    """Target motion over the horizon, in the virtual frame ``v`` (spec 4), one row per stage.

    ``v_a_m_s`` (N, 2): ``[v_ax, v_ay]``; ``vdot_a_m_s2`` (N, 2): their time derivatives as seen
    in the rotating frame ``v``; ``psidot_a_rad_s`` (N,): the target's yaw rate. Row ``n`` is
    used by stage ``n`` (``n = 0..N-1``); the state box at ``n = N`` uses row ``N-1``.
    Not to be confused with :class:`companion.core.state.TargetMotion` (one instant).
    """

    v_a_m_s: np.ndarray
    vdot_a_m_s2: np.ndarray
    psidot_a_rad_s: np.ndarray
    disturbance_v_m_s2: np.ndarray | None = None
    """(N, 3): the estimated disturbance acceleration in each stage's virtual frame (default
    zeros): the attitude realising ``u`` is the one of ``u - d`` (``rmpc_problem.centre``)."""

    def __post_init__(self) -> None:
        v = np.asarray(self.v_a_m_s, dtype=float)
        vd = np.asarray(self.vdot_a_m_s2, dtype=float)
        pd = np.asarray(self.psidot_a_rad_s, dtype=float)
        if v.ndim != 2 or v.shape[1] != 2 or vd.shape != v.shape or pd.shape != (v.shape[0],):
            raise RmpcParameterError(
                "TargetMotion: need v_a_m_s (N,2), vdot_a_m_s2 (N,2), psidot_a_rad_s (N,); got "
                f"{v.shape}, {vd.shape}, {pd.shape}"
            )
        dd = (np.zeros((v.shape[0], 3)) if self.disturbance_v_m_s2 is None
              else np.asarray(self.disturbance_v_m_s2, dtype=float))
        if dd.shape != (v.shape[0], 3):
            raise RmpcParameterError(f"TargetMotion.disturbance_v_m_s2: need (N,3), got {dd.shape}")
        for name, a in (("v_a_m_s", v), ("vdot_a_m_s2", vd), ("psidot_a_rad_s", pd),
                        ("disturbance_v_m_s2", dd)):
            if not np.all(np.isfinite(a)):
                raise RmpcParameterError(f"TargetMotion.{name}: not finite ({a.tolist()})")
        object.__setattr__(self, "v_a_m_s", _ro(v))
        object.__setattr__(self, "vdot_a_m_s2", _ro(vd))
        object.__setattr__(self, "psidot_a_rad_s", _ro(pd))
        object.__setattr__(self, "disturbance_v_m_s2", _ro(dd))

    @property
    def horizon(self) -> int:
        return int(self.v_a_m_s.shape[0])

    @classmethod
    def constant(
        cls, v_a_m_s: ArrayLike, vdot_a_m_s2: ArrayLike, psidot_a_rad_s: float, horizon: int
    ) -> TargetMotion:
        """The same motion at every stage."""
        return cls(
            v_a_m_s=np.tile(np.asarray(v_a_m_s, dtype=float).reshape(1, 2), (horizon, 1)),
            vdot_a_m_s2=np.tile(np.asarray(vdot_a_m_s2, dtype=float).reshape(1, 2), (horizon, 1)),
            psidot_a_rad_s=np.full(horizon, float(psidot_a_rad_s)),
        )

    def stage(self, n: int) -> tuple[np.ndarray, np.ndarray, float]:
        """``(v_a, vdot_a, psidot_a)`` of stage ``n``."""
        return self.v_a_m_s[n], self.vdot_a_m_s2[n], float(self.psidot_a_rad_s[n])

    def disturbance(self, n: int) -> np.ndarray:
        """``d`` (3,) of stage ``n`` (virtual frame, m/s^2)."""
        assert self.disturbance_v_m_s2 is not None  # set in __post_init__
        out: np.ndarray = self.disturbance_v_m_s2[n]
        return out

    def packed(self) -> np.ndarray:
        """The NLP parameter vector: per stage ``[v_ax, v_ay, vdot_ax, vdot_ay, psidot_a,
        d_x, d_y, d_z]``."""
        assert self.disturbance_v_m_s2 is not None
        return np.column_stack([self.v_a_m_s, self.vdot_a_m_s2, self.psidot_a_rad_s,
                                self.disturbance_v_m_s2]).ravel()


@dataclass(frozen=True)
class ConstraintViolation:
    """One violated constraint: what, at which stage, by how much (its natural units)."""

    constraint: str
    stage: int
    amount: float


@dataclass(frozen=True)
class RmpcResult:
    """The outcome of one RMPC step.

    ``success``: a solver converged and its trajectory passed the residual check ('optimal'
    or 'recovery'); ``mode``: 'optimal' (hard problem), 'recovery' (soft copy), 'fallback'
    (terminal law clipped to U); ``status``: the return status of the solve that produced the
    result (``hard_status``: that of the hard attempt); ``cost``: its objective;
    ``iterations`` and ``solve_time_s``: summed over the solves of this step (wall time of the
    compiled solver's evaluation on the shell's ``clock``; NaN if it raised, was abandoned
    (:class:`SolveAborted`) or without a clock); ``u0`` (4,): the input to apply;
    ``eta_pred`` (N+1, 7), ``u_pred`` (N, 4): the predicted trajectory;
    ``max_soft_violation``: largest slack of the recovery solve in the squared-row units
    (0 otherwise); ``active_groups``: constraint groups in the problem; ``target``: the motion
    the step was solved for (for :func:`check_solution`).
    """

    success: bool
    mode: str
    status: str
    hard_status: str
    cost: float
    iterations: int
    solve_time_s: float
    u0: np.ndarray
    eta_pred: np.ndarray
    u_pred: np.ndarray
    max_soft_violation: float
    active_groups: tuple[str, ...]
    target: TargetMotion


def terminal_law(
    eta: ArrayLike, v_a: ArrayLike, vdot_a: ArrayLike, psidot_a: float,
    k: np.ndarray, u_max: ArrayLike,
) -> np.ndarray:
    """``u_f = K eta + Gamma`` (spec 7) clipped to ``|u| <= u_max`` (4,).

    ``K`` maps ``eta`` to ``u_e``; ``Gamma`` is evaluated at the law's own (unclipped) yaw rate
    ``psidot_q = K_4 eta + psidot_a``, so that ``u_e = K eta`` before clipping.
    """
    e = np.asarray(eta, dtype=float)
    ke = np.asarray(k, dtype=float) @ e
    psidot_q = float(ke[3] + psidot_a)
    u = ke + terminal_feedforward(np.asarray(v_a), np.asarray(vdot_a), psidot_a, psidot_q)
    umax = np.asarray(u_max, dtype=float)
    out: np.ndarray = np.clip(u, -umax, umax)
    return out


def _state_offset(v_a: np.ndarray) -> np.ndarray:
    """``col(s, v_q) - eta_e`` = ``[s_r, v_a, 0]`` (7,)."""
    return np.array([*S_REF, v_a[0], v_a[1], 0.0])


def state_lower(rmpc: RmpcParams) -> np.ndarray:
    """Lower bound of the absolute state ``col(s, v_q)`` (7,): ``-eta_max``, and with the
    corner rows ``s3 >= min_depth_m / z*`` (the depth bound their tightening assumes)."""
    lo = -np.asarray(rmpc.eta_max, dtype=float)
    if rmpc.enable_visibility and rmpc.visibility == "corners":
        lo[2] = max(lo[2], rmpc.min_depth_m / rmpc.desired_depth_m)
    return lo


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


def planned_motion(rmpc: RmpcParams, eta: np.ndarray, u: np.ndarray, target: TargetMotion,
                   n: int, s4_ref: float) -> tuple[np.ndarray, np.ndarray, float]:
    """Stage ``n``'s target motion as the NLP uses it (:func:`stage_motion`, numpy)."""
    v_a, vdot_a, psidot_a = target.stage(n)
    va, vd, pd = stage_motion(rmpc, eta, u, v_a, vdot_a, psidot_a, s4_ref)
    return np.asarray(va, dtype=float), np.asarray(vd, dtype=float), float(pd)


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


class _Solver:
    """One compiled NLP (hard or soft) with its bounds template."""

    def __init__(
        self, rmpc: RmpcParams, camera: CameraParams, terminal: TerminalDesign, soft: bool,
        solver: str, clock: Callable[[], float] | None = None,
    ) -> None:
        self._clock = clock
        if soft:
            rmpc, terminal = recovery_design(rmpc, camera, terminal)
        nlp, layout = build_nlp(rmpc, camera, terminal, soft)
        self.layout: Layout = layout
        self.kind = "soft" if soft else "hard"
        self.solver_name = solver
        opts: dict[str, Any] = {"print_time": False, "record_time": True}
        if solver == "fatrop":
            opts |= {
                "structure_detection": "auto",
                "equality": list(layout.equality),
                "fatrop": FATROP_OPTIONS | {"max_iter": rmpc.max_iter},
            }
        else:
            opts |= {"ipopt": IPOPT_OPTIONS | {"max_iter": rmpc.max_iter}}
        name = f"rmpc_{self.kind}"
        self.compiled: CompiledNlp | None = None
        if rmpc.jit:
            # the symbolic solver is built only if the source must be generated (cache miss)
            self.compiled = compiled_nlp(lambda: ca.nlpsol(name, solver, nlp, opts),
                                         rmpc.cache_dir, f"{solver}_{self.kind}", nlp=nlp,
                                         options=repr(sorted(opts.items())))
            try:
                self.solver = ca.nlpsol(name, solver, str(self.compiled.library), opts)
            except RuntimeError as exc:
                raise RmpcBuildError(f"loading {self.compiled.library}: {exc}") from exc
        else:
            self.solver = ca.nlpsol(name, solver, nlp, opts)
        # bounds templates (the parts that never change)
        nw, ng = layout.n_w, layout.n_g
        self.lbx = np.full(nw, -np.inf)
        self.ubx = np.full(nw, np.inf)
        umax = np.asarray(rmpc.u_max, dtype=float)
        self.lbx[layout.u_index] = -umax
        self.ubx[layout.u_index] = umax
        self.lbx[layout.slack_index] = 0.0
        self.lbg = np.zeros(ng)
        self.ubg = np.zeros(ng)
        for row in layout.rows:
            self.lbg[row.g_index] = -np.inf
            self.ubg[row.g_index] = row.upper
        # Zero-copy calls (CasADi's FunctionBuffer): the solver reads its inputs from these
        # numpy arrays and writes x, f, g into the output arrays, with no DM conversion (4 DMs
        # in, 3 out: ~0.3-0.8 ms of Python-side overhead per call measured on this machine).
        # The arrays are filled in place: the buffer keeps pointers to them. The multipliers'
        # initial guesses are left unset (0, as with an empty DM). Results are bit-identical to
        # ``self.solver.call`` (tests/core/test_rmpc.py).
        buf: Any = self.solver.buffer()[0]  # (the stubs want a byte size the binding infers)
        self._buf = buf
        self._w0_in, self._p_in = np.zeros(nw), np.zeros(self.solver.nnz_in(1))
        self._lbx_in, self._ubx_in = np.zeros(nw), np.zeros(nw)
        self._x_out, self._f_out, self._g_out = np.zeros(nw), np.zeros(1), np.zeros(ng)
        for i, a in enumerate((self._w0_in, self._p_in, self._lbx_in, self._ubx_in,
                               self.lbg, self.ubg)):
            buf.set_arg(i, a.data)
        for i, a in enumerate((self._x_out, self._f_out, self._g_out)):
            buf.set_res(i, a.data)
        self.calls = 0  # evaluations of the solver (tests: nothing bad reaches it)
        self.eta_max = np.asarray(rmpc.eta_max, dtype=float)
        self.state_lo = state_lower(rmpc)
        self.u_max = np.asarray(rmpc.u_max, dtype=float)
        self.dt_s = rmpc.dt_s
        self.planned_yaw = rmpc.target_motion == "planned_yaw"
        self.eq_rows = layout.gap_index.ravel()
        self.ineq_rows = np.array([row.g_index for row in layout.rows], dtype=int)

    def bounds(self, eta0: np.ndarray, target: TargetMotion) -> tuple[np.ndarray, np.ndarray]:
        lay = self.layout
        lbx = self.lbx.copy()
        ubx = self.ubx.copy()
        big_n = lay.horizon
        v = np.vstack([target.v_a_m_s, target.v_a_m_s[-1:]])  # (N+1, 2), stage N holds N-1
        off = np.zeros((big_n + 1, NX))
        off[:, :4] = S_REF
        off[:, 4:6] = v
        lo = np.tile(self.state_lo, (big_n, 1))
        hi = np.tile(self.eta_max, (big_n, 1))
        if self.kind == "soft":
            drift = 0.0
            if self.planned_yaw:
                drift = float(np.max(np.hypot(*target.v_a_m_s.T))) * (
                    self.u_max[3] + float(np.max(np.abs(target.psidot_a_rad_s))))
            lo, hi = velocity_box_return(eta0 + off[0], lo, hi, self.u_max, self.dt_s, drift)
        lbx[lay.x_index[1:]] = lo - off[1:]
        ubx[lay.x_index[1:]] = hi - off[1:]
        lbx[lay.x_index[0]] = eta0
        ubx[lay.x_index[0]] = eta0
        return lbx, ubx

    def evaluate(self, w0: np.ndarray, par: np.ndarray, lbx: np.ndarray,
                 ubx: np.ndarray) -> Evaluation:
        """One evaluation of the compiled solver in this thread (CasADi's ``RuntimeError``
        passes through). What a solver process runs for :class:`SolveBackend`."""
        self._w0_in[:] = w0
        self._p_in[:] = par
        self._lbx_in[:] = lbx
        self._ubx_in[:] = ubx
        self._buf._eval()
        flag = int(self._buf.ret())
        # per-solve entries (success, return_status, iter_count) are set by every solve; the
        # buffer does not reset the cumulative counters and timers, which are not read here
        st = self._buf.stats() if flag == 0 else {}
        stats = {k: st[k] for k in STATS_KEYS if k in st}
        return flag, stats, self._x_out.copy(), float(self._f_out[0]), self._g_out.copy()

    def solve(
        self, w0: np.ndarray, par: np.ndarray, lbx: np.ndarray, ubx: np.ndarray,
        backend: SolveBackend | None = None,
    ) -> tuple[bool, str, dict[str, Any], np.ndarray, float, int, float]:
        """Solve (here, or on ``backend``); return (accepted, status, stats, w, cost,
        iterations, t_wall_s). :class:`SolveAborted` from the backend passes through."""
        self.calls += 1
        t0 = self._clock() if self._clock is not None else math.nan
        try:
            if backend is None:
                flag, st, w, cost, g = self.evaluate(w0, par, lbx, ubx)
            else:
                flag, st, w, cost, g = backend.evaluate(self.kind, w0, par, lbx, ubx)
        except RuntimeError as exc:  # CasADi raises on internal errors (e.g. evaluation)
            log.warning("RMPC %s solve raised: %s", self.kind, exc)
            return False, f"exception: {exc}", {}, w0, float("nan"), 0, float("nan")
        t = self._clock() - t0 if self._clock is not None else math.nan
        if flag != 0:  # what ``Function.call`` raises as "Evaluation failed"
            log.warning("RMPC %s solve: evaluation failed (flag %d)", self.kind, flag)
            return False, f"exception: evaluation failed (flag {flag})", {}, w0, float("nan"), \
                0, float("nan")
        status = _status_string(st)
        it = int(st.get("iter_count", 0))
        ok = bool(st.get("success", False))
        if ok and not (np.all(np.isfinite(w)) and np.all(np.isfinite(g)) and np.isfinite(cost)):
            ok, status = False, f"{status} (non-finite iterate)"
        if ok:
            resid = max(
                float(np.max(np.abs(g[self.eq_rows]), initial=0.0)),
                float(np.max(g[self.ineq_rows] - self.ubg[self.ineq_rows], initial=0.0)),
                float(np.max(lbx - w, initial=0.0)),
                float(np.max(w - ubx, initial=0.0)),
            )
            if resid > ACCEPT_TOL:
                ok, status = False, f"{status} (residual {resid:.3g} > {ACCEPT_TOL:g})"
        return ok, status, st, w, cost, it, t


def _status_string(st: dict[str, Any]) -> str:
    rs = st.get("return_status", "unknown")
    if isinstance(rs, str):
        return rs
    # fatrop reports an integer flag; CasADi's unified status names it
    return f"{st.get('unified_return_status', 'SOLVER_RET_UNKNOWN')} (flag {rs})"


class Rmpc:
    """The RMPC of spec 6, built (and compiled, or loaded from the cache) once.

    ``rmpc.solver`` picks fatrop or ipopt; ``rmpc.jit`` compiles the NLP functions (cached in
    ``rmpc.cache_dir``). ``solve`` is not thread-safe (it keeps the warm start). ``clock``
    (seconds, e.g. ``time.perf_counter``, given by the shell: the core reads no clock) times
    each solve for ``RmpcResult.solve_time_s``; without it that is NaN. ``backend`` (built
    from this controller once its solvers are compiled) runs the NLP evaluations elsewhere
    (:class:`SolveBackend`); :meth:`close` stops it.
    """

    def __init__(self, rmpc: RmpcParams, camera: CameraParams, terminal: TerminalDesign,
                 clock: Callable[[], float] | None = None,
                 backend: Callable[[Rmpc], SolveBackend] | None = None) -> None:
        self.cfg = rmpc
        self.camera = camera
        self.terminal = terminal
        self.horizon = rmpc.horizon
        self.u_max = np.asarray(rmpc.u_max, dtype=float)
        self.k = np.asarray(terminal.k, dtype=float)
        self.groups = tuple(
            name
            for name, on in (
                ("tube", rmpc.enable_tube),
                ("visibility", rmpc.enable_visibility),
                ("terminal", rmpc.enable_terminal),
            )
            if on
        )
        self._hard = _Solver(rmpc, camera, terminal, soft=False, solver=rmpc.solver,
                             clock=clock)
        self._soft = (
            _Solver(rmpc, camera, terminal, soft=True, solver=RECOVERY_SOLVER, clock=clock)
            if self.groups
            else None
        )
        self._prev: tuple[np.ndarray, np.ndarray] | None = None
        # sqrt((P^-1)_44): |eta|_P >= |se4| / this (see _infeasibility_certificate)
        self._se4_scale = float(np.sqrt(np.linalg.inv(np.asarray(terminal.p))[3, 3]))
        self._p_tube = tube_matrix(rmpc, np.asarray(terminal.p, dtype=float))
        self._s4_ref = 0.0  # eta0[3] of the current step (stage_motion's reference yaw)
        # where the solves run: here (None), or a backend the shell builds for this controller
        # (a child process bounded by rmpc.max_solve_time_s, companion.control.solve_guard)
        self.backend: SolveBackend | None = backend(self) if backend is not None else None

    def solver_kinds(self) -> dict[str, tuple[bool, str]]:
        """The NLPs this controller solves: kind -> (soft, solver name)."""
        out = {self._hard.kind: (False, self._hard.solver_name)}
        if self._soft is not None:
            out[self._soft.kind] = (True, self._soft.solver_name)
        return out

    def close(self) -> None:
        """Stop the solve backend (its child process), if any. Idempotent."""
        if self.backend is not None:
            self.backend.close()

    @property
    def compiled(self) -> tuple[CompiledNlp | None, CompiledNlp | None]:
        """The compiled libraries (hard, soft); ``compiled_now`` False means a cache hit."""
        return self._hard.compiled, self._soft.compiled if self._soft else None

    def reset(self) -> None:
        """Forget the warm start (e.g. after the target was lost)."""
        self._prev = None

    # ------------------------------------------------------------------------------------
    def solve(self, eta0: ArrayLike, target: TargetMotion) -> RmpcResult:
        """One RMPC step from the measured error ``eta0`` (7,) for ``target`` (N rows).

        Raises :class:`RmpcParameterError` if ``eta0`` or ``target`` is malformed or not
        finite (nothing reaches the solver). ``u0``, ``eta_pred``, ``u_pred`` and ``cost`` are
        always finite (``solve_time_s`` is NaN only if CasADi raised and gave no stats).
        """
        e0 = np.asarray(eta0, dtype=float).reshape(-1)
        if e0.shape != (NX,):
            raise RmpcParameterError(f"eta0: need 7 values, got shape {np.shape(eta0)}")
        if not np.all(np.isfinite(e0)):
            raise RmpcParameterError(f"eta0: not finite ({e0.tolist()})")
        if not isinstance(target, TargetMotion) or target.horizon != self.horizon:
            raise RmpcParameterError(f"target: need a TargetMotion with {self.horizon} rows")
        par = np.append(target.packed(), e0[3])
        self._s4_ref = float(e0[3])
        eta_g, u_g = self._guess(e0, target)
        if self.backend is not None:
            self.backend.start_step()

        lay = self._hard.layout
        certificate = self._infeasibility_certificate(e0, target)
        if certificate is None:
            lbx, ubx = self._hard.bounds(e0, target)
            w0 = self._pack(lay, eta_g, u_g)
            try:
                ok, status, _, w, cost, iters, t_wall = self._hard.solve(w0, par, lbx, ubx,
                                                                         self.backend)
            except SolveAborted as exc:
                return self._aborted(e0, target, str(exc), str(exc), 0, math.nan)
        else:  # provably infeasible: do not spend the solver's iterations on finding out
            ok, status, w, cost, iters, t_wall = False, certificate, np.zeros(0), 0.0, 0, 0.0
        hard_status = status
        if ok:
            eta_p, u_p = self._unpack(lay, w)
            self._prev = (eta_p, u_p)
            return RmpcResult(True, "optimal", status, hard_status, cost, iters, t_wall,
                              _ro(u_p[0]), _ro(eta_p), _ro(u_p), 0.0, self.groups, target)
        log.info("RMPC hard problem failed (%s): trying the soft copy", status)
        if self._soft is not None:
            slay = self._soft.layout
            slbx, subx = self._soft.bounds(e0, target)
            # the soft copy's input-rate term: against the input the previous step applied (its
            # plan's first input; a failed hard solve leaves _prev alone); off at the start and
            # after a fallback or a reset (no previous input)
            if self._prev is None:
                spar = np.concatenate([par, np.zeros(NU), [0.0]])
            else:
                spar = np.concatenate([par, self._prev[1][0],
                                       [self.cfg.recovery_input_rate_weight]])
            sw0 = self._pack(slay, eta_g, u_g)
            sw0[slay.slack_index] = self._slack_guess(slay, eta_g, u_g, target)
            try:
                sok, sstatus, _, sw, scost, sit, st_wall = self._soft.solve(
                    sw0, spar, slbx, subx, self.backend)
            except SolveAborted as exc:
                return self._aborted(e0, target, str(exc), hard_status, iters, math.nan)
            iters += sit
            t_wall += st_wall
            if sok:
                eta_p, u_p = self._unpack(slay, sw)
                self._prev = (eta_p, u_p)
                slack = float(np.max(sw[slay.slack_index], initial=0.0))
                return RmpcResult(True, "recovery", sstatus, hard_status, scost, iters, t_wall,
                                  _ro(u_p[0]), _ro(eta_p), _ro(u_p), max(slack, 0.0),
                                  self.groups, target)
            status = sstatus
            log.warning("RMPC soft copy failed too (%s): terminal-law fallback", sstatus)
        eta_f, u_f = self._rollout(e0, target)
        self._prev = None
        return RmpcResult(False, "fallback", status, hard_status,
                          self._objective(eta_f, u_f, target), iters, t_wall,
                          _ro(u_f[0]), _ro(eta_f), _ro(u_f), 0.0, self.groups, target)

    def _aborted(self, e0: np.ndarray, target: TargetMotion, status: str, hard_status: str,
                 iters: int, t_wall: float) -> RmpcResult:
        """The terminal-law fallback of a step whose solve the backend abandoned."""
        log.warning("RMPC step abandoned (%s): terminal-law fallback", status)
        eta_f, u_f = self._rollout(e0, target)
        self._prev = None
        return RmpcResult(False, "fallback", status, hard_status,
                          self._objective(eta_f, u_f, target), iters, t_wall,
                          _ro(u_f[0]), _ro(eta_f), _ro(u_f), 0.0, self.groups, target)

    def _objective(self, eta: np.ndarray, u: np.ndarray, target: TargetMotion) -> float:
        """The hard problem's cost of a trajectory (numpy)."""
        q, r = np.asarray(self.cfg.q_diag), np.asarray(self.cfg.r_diag)
        total = 0.0
        for n in range(self.horizon):
            motion = planned_motion(self.cfg, eta[n], u[n], target, n, float(eta[0][3]))
            ue = np.asarray(input_error(u[n], *motion))
            total += float(eta[n] @ (q * eta[n]) + ue @ (r * ue))
        return total + float(eta[-1] @ self.terminal.p @ eta[-1])

    def _infeasibility_certificate(self, eta0: np.ndarray, target: TargetMotion) -> str | None:
        """A proof that the hard problem is infeasible, or None (no proof: try the solver).

        Two exact arguments: (1) ``eta(0)`` is fixed, so ``|eta0|_P > X(0)`` violates the
        tube at n = 0. (2) The yaw error is decoupled and linear, ``se4(n+1) = se4(n) +
        (psidot_a(n) - psidot_q(n)) delta`` with ``|psidot_q| <= u_max[3]``, so ``se4(n)`` lies
        in a known interval; and ``min {eta' P eta : eta_4 = c} = c^2 / (P^-1)_44``, so the
        tube (n <= N-1) or terminal set (n = N) is out of reach once that interval stays
        farther than ``X(n) sqrt((P^-1)_44)`` from 0.
        """
        tube, term = "tube" in self.groups, "terminal" in self.groups
        if not (tube or term):
            return None
        if tube and float(eta0 @ self._p_tube @ eta0) > tube_bound(self.cfg, 0) ** 2:
            return "infeasible: |eta0|_P > X(0)"
        if self.cfg.heading == "cost":  # s4 is in no hard row: no yaw argument
            return None
        dt = self.cfg.dt_s
        drift = eta0[3] + np.concatenate([[0.0], np.cumsum(target.psidot_a_rad_s) * dt])
        reach = np.arange(self.horizon + 1) * dt * self.u_max[3]
        gap = np.maximum(np.abs(drift) - reach, 0.0)  # smallest |se4(n)| reachable
        for n in range(1, self.horizon + 1):
            if n < self.horizon and not tube:
                continue
            if gap[n] > tube_bound(self.cfg, n) * self._se4_scale * (1.0 + 1e-9):
                return f"infeasible: yaw error cannot reach the tube at n = {n}"
        return None

    def check(self, result: RmpcResult, tol: float = 1e-6) -> list[ConstraintViolation]:
        """:func:`check_solution` with this controller's configuration."""
        return check_solution(result, self.cfg, self.camera, self.terminal, tol=tol)

    # ------------------------------------------------------------------------------------
    def _law(self, eta: np.ndarray, target: TargetMotion, n: int) -> np.ndarray:
        # the law's own yaw rate is not known before it is computed: the nominal one
        v_a, vdot_a, psidot_a = target.stage(n)
        u_nom = np.array([0.0, 0.0, 0.0, psidot_a])
        v_a, vdot_a, psidot_a = planned_motion(self.cfg, eta, u_nom, target, n, self._s4_ref)
        return terminal_law(eta, v_a, vdot_a, psidot_a, self.k, self.u_max)

    def _step(self, eta: np.ndarray, u: np.ndarray, target: TargetMotion, n: int) -> np.ndarray:
        v_a, vdot_a, psidot_a = planned_motion(self.cfg, eta, u, target, n, self._s4_ref)
        return np.asarray(
            euler_step(eta, u, v_a, vdot_a, psidot_a, self.cfg.desired_depth_m, self.cfg.dt_s)
        )

    def _rollout(self, eta0: np.ndarray, target: TargetMotion) -> tuple[np.ndarray, np.ndarray]:
        """The clipped terminal law rolled out on the nominal model (finite by construction
        for finite inputs; clipped to the state box's scale so it can never overflow)."""
        big_n = self.horizon
        eta = np.zeros((big_n + 1, NX))
        u = np.zeros((big_n, NU))
        eta[0] = eta0
        for n in range(big_n):
            u[n] = self._law(eta[n], target, n)
            eta[n + 1] = self._step(eta[n], u[n], target, n)
        if not (np.all(np.isfinite(eta)) and np.all(np.isfinite(u))):  # pragma: no cover
            eta = np.tile(eta0, (big_n + 1, 1))
            u = np.zeros((big_n, NU))
        return eta, u

    def _guess(self, eta0: np.ndarray, target: TargetMotion) -> tuple[np.ndarray, np.ndarray]:
        """Previous solution shifted by one stage (last stage: terminal law), else a rollout."""
        if self._prev is None:
            return self._rollout(eta0, target)
        eta_p, u_p = self._prev
        big_n = self.horizon
        eta = np.empty_like(eta_p)
        u = np.empty_like(u_p)
        eta[0] = eta0
        eta[1:big_n] = eta_p[2:]
        u[: big_n - 1] = u_p[1:]
        u[big_n - 1] = self._law(eta_p[big_n], target, big_n - 1)
        eta[big_n] = self._step(eta_p[big_n], u[big_n - 1], target, big_n - 1)
        return eta, u

    @staticmethod
    def _pack(lay: Layout, eta: np.ndarray, u: np.ndarray) -> np.ndarray:
        w = np.zeros(lay.n_w)
        w[lay.x_index] = eta
        w[lay.u_index] = u
        return w

    @staticmethod
    def _unpack(lay: Layout, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return w[lay.x_index].copy(), w[lay.u_index].copy()

    def _slack_guess(self, lay: Layout, eta: np.ndarray, u: np.ndarray,
                     target: TargetMotion) -> np.ndarray:
        """Slacks that make the guess feasible for the soft rows (plus a small interior gap)."""
        out = np.zeros(len(lay.slack_index))
        pairs = {st: img for st, img, _ in visibility_pairs(self.cfg)}
        for i, row in enumerate(lay.rows):
            u_n = u[row.stage] if row.stage < len(u) else None
            img = pairs.get(row.stage, row.stage) if row.kind in ("visibility", "corner") \
                else row.stage
            d_n = target.disturbance(row.stage) if row.stage < len(u) else None
            val = _row_value(row.kind, eta[img], u_n, self._p_tube, self.cfg,
                             self.camera, d_n, row.corner)
            out[i] = max(val - row.upper, 0.0) + 1e-3
        return out


def _row_value(kind: str, eta: np.ndarray, u: np.ndarray | None, p_mat: np.ndarray,
               rmpc: RmpcParams, camera: CameraParams, d: np.ndarray | None = None,
               corner: int = -1) -> float:
    """The squared-form value of one path row (as in the NLP), evaluated with numpy
    (``eta``: the state the row's image is taken from)."""
    if kind in ("tube", "terminal_set"):
        return float(eta @ p_mat @ eta)
    pu, pn = corner_points(eta, rmpc)[corner] if kind == "corner" else image_point(eta)
    if kind == "terminal_visibility":
        return float(pu**2 + pn**2)
    assert u is not None
    mu, mn = centre(u, rmpc, camera, d)
    return float((pu - mu) ** 2 + (pn - mn) ** 2)


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
