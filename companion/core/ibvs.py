"""Classical moment-based IBVS: a PD on the virtual-camera moments (a baseline for the RMPC).

The law of the IBVS literature the paper builds on (Chaumette & Hutchinson's exponential
decrease of the feature error, with image moments in a virtual camera so that the
translational features decouple: Tahri & Chaumette 2005; Jabbari et al. 2013). With the
paper's features (spec 3-4) the interaction is ``s_e[i]' = -v_e[i] / z*`` (i = 1..3, plus the
yaw-rotation terms) and ``se4' = psidot_a - psidot_q``. The classical kinematic law asks for
``v_e = lambda z* s_e[0:3]`` (so that ``s_e' = -lambda s_e``) and ``psidot_q = psidot_a +
k_psi se4``; a velocity loop of gain ``k_v`` turns the velocity demand into the acceleration
this vehicle is commanded with::

    r[0:3]   = k_v (lambda z* s_e[0:3] - v_e) + Gamma[0:3]
    psidot_q = psidot_a + k_psi se4

i.e. a PD on the moments (``v_e = -z* s_e'``: ``Kp = k_v lambda z*``, ``Kd = k_v z*``),
``Gamma`` the target's feed-forward of spec 7 (its acceleration seen in the rotating frame).
Clipped to the same input box as the RMPC. There is no visibility constraint: the image error
decays exponentially, which keeps a target in view only if it started well inside.

Pure math (numpy). :class:`IbvsPd` has the :class:`companion.control.seams.Controller` shape:
``solve(eta0, target) -> RmpcResult`` with ``mode = "law"`` and the law rolled out over the
horizon on the nominal model (for the log and plots).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from companion.core.dynamics import euler_step, terminal_feedforward
from companion.core.rmpc import RmpcParameterError, RmpcResult, TargetMotion

__all__ = ["IbvsGains", "IbvsPd", "ibvs_input"]


@dataclass(frozen=True)
class IbvsGains:
    """``lambda_1_s`` image-error decay rate, ``kv_1_s`` velocity-loop gain, ``yaw_1_s`` yaw
    gain (all 1/s); ``z_star_m`` desired depth; ``u_max`` (4,) the input box; ``dt_s`` the
    control interval (for the rollout)."""

    lambda_1_s: float
    kv_1_s: float
    yaw_1_s: float
    z_star_m: float
    u_max: tuple[float, float, float, float]
    dt_s: float

    def __post_init__(self) -> None:
        for name in ("lambda_1_s", "kv_1_s", "yaw_1_s", "z_star_m", "dt_s"):
            if not getattr(self, name) > 0:
                raise RmpcParameterError(f"IbvsGains.{name}: must be > 0")


def ibvs_input(eta: ArrayLike, v_a: ArrayLike, vdot_a: ArrayLike, psidot_a: float,
               gains: IbvsGains) -> np.ndarray:
    """The IBVS PD input ``u = (r1, r2, r3, psidot_q)`` (m/s^2, rad/s, virtual frame), clipped."""
    e = np.asarray(eta, dtype=float)
    psidot_q = float(psidot_a + gains.yaw_1_s * e[3])
    acc = gains.kv_1_s * (gains.lambda_1_s * gains.z_star_m * e[0:3] - e[4:7])
    ff = np.asarray(terminal_feedforward(np.asarray(v_a), np.asarray(vdot_a), psidot_a,
                                         psidot_q))
    u = np.array([*(acc + ff[0:3]), psidot_q])
    umax = np.asarray(gains.u_max, dtype=float)
    out: np.ndarray = np.clip(u, -umax, umax)
    return out


class IbvsPd:
    """The IBVS PD behind the controller interface (no state: ``reset`` does nothing)."""

    def __init__(self, gains: IbvsGains, horizon: int) -> None:
        self.gains = gains
        self.horizon = int(horizon)

    def reset(self) -> None:
        """Nothing to forget."""

    def solve(self, eta0: ArrayLike, target: TargetMotion) -> RmpcResult:
        """The law at ``eta0`` (``mode = "law"``), rolled out over the horizon on the nominal
        error dynamics. Raises :class:`RmpcParameterError` on malformed or non-finite input."""
        e0 = np.asarray(eta0, dtype=float).reshape(-1)
        if e0.shape != (7,) or not np.all(np.isfinite(e0)):
            raise RmpcParameterError(f"eta0: need 7 finite values, got {np.shape(eta0)}")
        if not isinstance(target, TargetMotion) or target.horizon != self.horizon:
            raise RmpcParameterError(f"target: need a TargetMotion with {self.horizon} rows")
        g = self.gains
        eta = np.zeros((self.horizon + 1, 7))
        u = np.zeros((self.horizon, 4))
        eta[0] = e0
        for n in range(self.horizon):
            v_a, vdot_a, psidot_a = target.stage(n)
            u[n] = ibvs_input(eta[n], v_a, vdot_a, psidot_a, g)
            eta[n + 1] = euler_step(eta[n], u[n], v_a, vdot_a, psidot_a, g.z_star_m, g.dt_s)
        if not (np.all(np.isfinite(eta)) and np.all(np.isfinite(u))):  # pragma: no cover
            eta = np.tile(e0, (self.horizon + 1, 1))
            u = np.tile(u[0], (self.horizon, 1))
        return RmpcResult(True, "law", "ibvs-pd", "ibvs-pd", 0.0, 0, 0.0, u[0].copy(), eta, u,
                          0.0, (), target)
