"""The disturbance filter's velocity step (predict, then correct with a velocity sample) as
one CasADi function evaluated through a preallocated buffer.

The same formulas as :meth:`companion.core.disturbance.DisturbanceEstimator._predict` and
``_correct`` for ``H = [I 0]``, ``R = r I``: ``x+ = F x + g dt e_z``, ``P+ = F P F' + Q``;
``S = P[:3, :3] + r I``, ``K = P[:, :3] S^-1``, the Joseph form
``(I - K H) P (I - K H)' + r K K'``, symmetrised. Built once per state size: the numpy form
cost ~30 calls of 2-5 us each on 7 x 7 arrays every control step, this is one call. The values
agree with the numpy form to rounding (sums in another order, ``S^-1`` by its adjugate
instead of LAPACK's LU).
"""

from __future__ import annotations

import hashlib
import logging
from functools import lru_cache
from pathlib import Path
from typing import Any

import casadi as ca
import numpy as np

from companion.core.rmpc_cache import RmpcBuildError, compiled_functions

log = logging.getLogger(__name__)


class VelocityStep:
    """``step(x, p, dt, f_col, g_dt, q_diag, v, r)`` for an ``n``-state filter (n >= 7: v,
    d, theta first). ``f_col`` (3,): ``F[0:3, 6]`` (``-dt g T b``); ``q_diag`` (n,): the
    process noise's diagonal. Returns ``(x_new (n,), p_new (n, n), innov (3,), nis, det_s)``:
    the corrected state and covariance, the innovation ``v - x_pred[:3]``, its normalised
    square and ``det S`` (0: singular). Arrays returned are fresh copies.

    ``cache_dir``: compile the function to C there (the RMPC's cache, ``rmpc.cache_dir``,
    with ``rmpc.jit``): ~10x less CPU per call than CasADi's virtual machine; ``None`` (or a
    failed compilation, logged) evaluates it in the virtual machine, to the same values up to
    rounding."""

    def __init__(self, n: int, cache_dir: str | None = None) -> None:
        self.n = n
        fn = _function(n) if cache_dir is None else _compiled(n, cache_dir)
        buf: Any = fn.buffer()[0]  # this instance's own buffer (the function is shared)
        self._buf = buf
        self._arg = np.zeros(fn.nnz_in(0))
        self._res = np.zeros(fn.nnz_out(0))
        buf.set_arg(0, self._arg.data)
        buf.set_res(0, self._res.data)
        self._fn = fn
        # p goes in column-major: its slot seen as the (n, n) matrix it holds, so one
        # strided copy writes p there (p.T.reshape(-1) first copied p.T, then that)
        self._p_in = self._arg[n:n + n * n].reshape(n, n).T
        self._k0 = n + n * n

    def __call__(self, x: np.ndarray, p: np.ndarray, dt: float,
                 f_col: tuple[float, float, float], g_dt: float, q_diag: list[float],
                 v: tuple[float, float, float], r: float
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, float, float]:
        n, k0 = self.n, self._k0
        a = self._arg
        a[0:n] = x
        self._p_in[...] = p
        # the scalars and short vectors after p in one assignment: [dt, f_col, g_dt,
        # q_diag, v, r] (the same values as one slice each)
        a[k0:] = [dt, *f_col, g_dt, *q_diag, *v, r]
        self._buf._eval()
        if int(self._buf.ret()) != 0:
            raise RuntimeError(f"{self._fn.name()}: evaluation failed")
        res = self._res
        x_new = res[0:n].copy()
        p_new = res[n:n + n * n].reshape(n, n).T.copy()
        nis, det = res[k0 + 3:k0 + 5].tolist()
        return x_new, p_new, res[k0:k0 + 3].copy(), nis, det


@lru_cache(maxsize=4)
def _function(n: int) -> ca.Function:
    """The step's function for ``n`` states (built once per size and process)."""
    size = n + n * n + 1 + 3 + 1 + n + 3 + 1
    z = ca.SX.sym("z", size)
    x = z[0:n]
    p = ca.reshape(z[n:n + n * n], n, n)  # column-major: p goes in as p.T
    k0 = n + n * n
    dt, f_col, g_dt = z[k0], z[k0 + 1:k0 + 4], z[k0 + 4]
    q_diag, v, r = z[k0 + 5:k0 + 5 + n], z[k0 + 5 + n:k0 + 8 + n], z[k0 + 8 + n]
    f = ca.SX.eye(n)
    for i in range(3):
        f[i, i + 3] = dt
        f[i, 6] = f_col[i]
    x_pred = ca.mtimes(f, x)
    x_pred[2] = x_pred[2] + g_dt
    p_pred = ca.mtimes(ca.mtimes(f, p), f.T) + ca.diag(q_diag)
    s = p_pred[0:3, 0:3] + r * ca.SX.eye(3)
    det = ca.det(s)
    s_inv = _adjugate3(s) / det
    innov = v - x_pred[0:3]
    nis = ca.mtimes(ca.mtimes(innov.T, s_inv), innov)
    k = ca.mtimes(p_pred[:, 0:3], s_inv)
    x_new = x_pred + ca.mtimes(k, innov)
    i_kh = ca.SX.eye(n)
    i_kh[:, 0:3] = i_kh[:, 0:3] - k
    p_new = ca.mtimes(ca.mtimes(i_kh, p_pred), i_kh.T) + r * ca.mtimes(k, k.T)
    p_new = 0.5 * (p_new + p_new.T)
    out = ca.vertcat(x_new, ca.reshape(p_new, n * n, 1), innov, nis, det)
    return ca.Function("disturbance_velocity_step", [z], [out])


def _compiled(n: int, cache_dir: str) -> ca.Function:
    """The step's function compiled in ``cache_dir`` (found there when built before); the
    virtual machine's when compiling fails."""
    code = hashlib.sha256(Path(__file__).read_bytes()).hexdigest()
    try:
        lib = compiled_functions(lambda: [_function(n)], cache_dir, f"kf{n}",
                                 alias_key=f"{code}:{n}")
        return ca.external("disturbance_velocity_step", str(lib.library))
    except (RmpcBuildError, RuntimeError, OSError) as exc:
        log.warning("disturbance filter: not compiled (%s): CasADi's virtual machine", exc)
        return _function(n)


def _adjugate3(s: ca.SX) -> ca.SX:
    """The adjugate of a 3 x 3 matrix (``inv(s) = adj(s) / det(s)``)."""
    adj = ca.SX(3, 3)
    for i in range(3):
        for j in range(3):
            rows = [r for r in range(3) if r != j]
            cols = [c for c in range(3) if c != i]
            minor = (s[rows[0], cols[0]] * s[rows[1], cols[1]]
                     - s[rows[0], cols[1]] * s[rows[1], cols[0]])
            adj[i, j] = minor if (i + j) % 2 == 0 else -minor
    return adj


__all__ = ["VelocityStep"]
