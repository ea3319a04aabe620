"""The RMPC's data types: the per-step target motion, the result, the errors, the solve
backend's protocol, and the small numpy helpers every part of the solve shares (the clipped
terminal law, the absolute state box, the planned target motion).

Split out of :mod:`companion.core.rmpc` (which re-exports every public name here).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np
from numpy.typing import ArrayLike

from companion.core.dynamics import S_REF, terminal_feedforward
from companion.core.errors import CoreError
from companion.core.params import RmpcParams
from companion.core.rmpc_problem import stage_motion

# ndarray.sum() is numpy's Python wrapper around this call with axis=None (the same
# reduction, the same bits): called directly on the control step's path
_sum_all = np.add.reduce


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




_new = object.__new__


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
        # one finiteness test of everything (a sum is finite only if every term is, short of
        # an overflow near 1e308); the per-array test names the culprit when it fails
        if not math.isfinite(float(v.sum() + vd.sum() + pd.sum() + dd.sum())):
            for name, a in (("v_a_m_s", v), ("vdot_a_m_s2", vd), ("psidot_a_rad_s", pd),
                            ("disturbance_v_m_s2", dd)):
                if not np.all(np.isfinite(a)):
                    raise RmpcParameterError(f"TargetMotion.{name}: not finite ({a.tolist()})")
            raise RmpcParameterError("TargetMotion: values too large (their sum overflows)")
        object.__setattr__(self, "v_a_m_s", _ro(v))
        object.__setattr__(self, "vdot_a_m_s2", _ro(vd))
        object.__setattr__(self, "psidot_a_rad_s", _ro(pd))
        object.__setattr__(self, "disturbance_v_m_s2", _ro(dd))

    @classmethod
    def built(cls, v_a_m_s: np.ndarray, vdot_a_m_s2: np.ndarray, psidot_a_rad_s: np.ndarray,
              disturbance_v_m_s2: np.ndarray | None = None) -> TargetMotion:
        """``TargetMotion(...)`` of arrays the caller has just built for it and shares with
        nobody: float64 of the right shapes and finite (checked, else the constructor's
        error), they are taken as they are (made read-only) instead of copied (the
        prediction, every control step: four array copies fewer)."""
        n = v_a_m_s.shape[0]
        dd = np.zeros((n, 3)) if disturbance_v_m_s2 is None else disturbance_v_m_s2
        arrays = (v_a_m_s, vdot_a_m_s2, psidot_a_rad_s, dd)
        f64 = np.float64
        # (the dtypes spelt out, no generator; _sum_all is ndarray.sum's own reduction)
        if (v_a_m_s.shape != (n, 2) or vdot_a_m_s2.shape != (n, 2)
                or psidot_a_rad_s.shape != (n,) or dd.shape != (n, 3)
                or v_a_m_s.dtype != f64 or vdot_a_m_s2.dtype != f64
                or psidot_a_rad_s.dtype != f64 or dd.dtype != f64
                or not math.isfinite(float(_sum_all(v_a_m_s, None) + _sum_all(vdot_a_m_s2, None)
                                           + _sum_all(psidot_a_rad_s, None)
                                           + _sum_all(dd, None)))):
            return cls(*arrays)  # (its checks name what is wrong)
        return cls.finite(*arrays)

    @classmethod
    def finite(cls, v_a_m_s: np.ndarray, vdot_a_m_s2: np.ndarray, psidot_a_rad_s: np.ndarray,
               disturbance_v_m_s2: np.ndarray | None = None) -> TargetMotion:
        """:meth:`built` of arrays whose shapes (N, 2), (N, 2), (N,), (N, 3), float64 and
        finiteness the caller has established (the compiled prediction: its views of one
        buffer, each value tested by the kernel), without testing them again."""
        dd = (np.zeros((v_a_m_s.shape[0], 3)) if disturbance_v_m_s2 is None
              else disturbance_v_m_s2)
        for a in (v_a_m_s, vdot_a_m_s2, psidot_a_rad_s, dd):
            a.setflags(write=False)
        out = _new(cls)
        out.__dict__.update(v_a_m_s=v_a_m_s, vdot_a_m_s2=vdot_a_m_s2,
                            psidot_a_rad_s=psidot_a_rad_s, disturbance_v_m_s2=dd)
        return out

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


def planned_motion(rmpc: RmpcParams, eta: np.ndarray, u: np.ndarray, target: TargetMotion,
                   n: int, s4_ref: float) -> tuple[np.ndarray, np.ndarray, float]:
    """Stage ``n``'s target motion as the NLP uses it (:func:`stage_motion`, numpy)."""
    v_a, vdot_a, psidot_a = target.stage(n)
    va, vd, pd = stage_motion(rmpc, eta, u, v_a, vdot_a, psidot_a, s4_ref)
    return np.asarray(va, dtype=float), np.asarray(vd, dtype=float), float(pd)

