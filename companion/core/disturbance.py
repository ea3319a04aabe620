"""Offset-free tracking: a Kalman filter for the hover thrust and a slowly varying disturbance.

The vehicle's translational model (NED, z down), as PX4 maps normalised thrust ``T`` to
specific force with its hover thrust ``h`` (``T = h`` gives 1 g)::

    v' = g e_z - g T theta R(q) e_z + d,        theta = 1 / h

``R(q) e_z`` is the body z axis (FRD) in NED, ``d`` (3, m/s^2, NED) is everything else that
moves the vehicle slowly: drag, wind, a mass or thrust-curve error seen as a force. The model is
linear in the state ``x = [v (3, m/s), d (3, m/s^2), theta (1/thrust)]`` for known ``T`` and
attitude, so a linear Kalman filter with a time-varying transition estimates it from the
velocity telemetry alone::

    x+ = F x + [g e_z dt, 0, 0],   F = [[I, dt I, -dt g T b], [0, I, 0], [0, 0, 1]],  b = R(q) e_z
    z  = v + noise

``d`` and ``theta`` follow random walks. Near hover ``T b`` barely changes, so ``d_z`` and
``theta`` are nearly collinear: the filter gives ``d_z`` a much smaller random walk, so that a
steady vertical offset is read as a hover-thrust error (what it almost always is) and ``d_z``
stays a slow residual.

How the estimate is used (docs/reference/estimator.md): the controller's input ``u = [r, psidot]``
stays the vehicle's *acceleration* in the virtual frame (spec 4); the setpoint mapping (spec 5)
asks for the specific force ``r - d_v - g e_z`` (``d_v`` = ``d`` in the virtual frame) with the
estimated hover thrust, so the vehicle achieves ``r`` and the model holds.

With an accelerometer (``accelerometer = true``, PX4's HIGHRES_IMU, docs/reference/estimator.md
section 1b) the filter gains two states, the accelerometer's bias ``b`` in body x and y (a slow
random walk), and a second measurement: in body axes the thrust has no x/y component, so the
horizontal specific force measured is ``(R' d)_xy + b + noise`` whatever the thrust model. The
velocity still pins the steady ``d`` (and so ``b``): a biased accelerometer leaves the steady
estimate where the velocity puts it, while the fast part of ``d`` is read directly.

Safety: every input is checked (non-finite or implausible data is rejected and counted, the
estimate is kept); the estimate is clipped to configured bounds after each update; the
covariance is kept symmetric and bounded; a non-finite result resets the filter. numpy, and the
velocity step compiled (:mod:`companion.core.disturbance_step`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from companion.core.disturbance_step import VelocityStep
from companion.core.errors import ParamError
from companion.core.frozen import make

_NX = 7  # v (3), d (3), theta
_NB = 2  # with the accelerometer: its bias in body x, y (states 7, 8)
_EYE3 = np.eye(3)
_ORTHO_TOL = 1e-3 + 1e-5 * _EYE3  # np.allclose's atol + rtol |b| against the identity


@dataclass(frozen=True)
class EstimatorParams:
    """``[control.estimator]``: the offset-free estimator (units in the names).

    ``velocity_noise_m_s``: std of a velocity measurement. ``disturbance_noise_m_s2_sqrt_s``:
    random walk of the horizontal disturbance (std growth per sqrt(s));
    ``vertical_disturbance_noise_m_s2_sqrt_s`` the same for ``d_z`` (small: see the module).
    ``hover_noise_per_sqrt_s``: random walk of the hover thrust (normalised thrust per
    sqrt(s)); ``hover_initial_std``: prior std of the configured hover thrust.
    ``hover_min``/``hover_max``: bounds on the estimate; ``disturbance_max_m_s2``: bound on
    each component of ``d``. ``max_dt_s``: a longer gap between velocity samples restarts the
    prediction from the measurement (the estimate is kept). ``innovation_gate``: a velocity
    whose normalised innovation squared exceeds it is rejected as an outlier.
    ``autopilot_thrust``: before our setpoints fly the vehicle (PX4's own modes, e.g. the
    pre-flight stream before OFFBOARD), estimate from the autopilot's own thrust setpoint
    (ATTITUDE_TARGET) while it reports the vehicle in the air, so the hover thrust is known
    before the first command of ours is flown; a setpoint older than
    ``autopilot_thrust_max_age_s`` is not used.

    ``accelerometer``: also fuse HIGHRES_IMU's horizontal specific force (body x/y) as a
    measurement of ``d`` (docs/reference/estimator.md, section 1b); ``accel_noise_m_s2``: std of one
    sample per axis; ``accel_disturbance_noise_m_s2_sqrt_s``: the random walk of ``d_x``,
    ``d_y`` while accelerometer samples arrive (at most ``accel_max_age_s`` old);
    ``accel_bias_noise_m_s2_sqrt_s``/``accel_bias_initial_std_m_s2``: random walk and prior
    std of the accelerometer's bias state (body x, y), bounded by ``accel_bias_max_m_s2``; the
    larger the random walk, the more of the accelerometer's slow content the bias takes and
    the higher the frequency from which the accelerometer, not the velocity, sets ``d``
    (complementary filtering). A sample beyond ``accel_max_m_s2`` on either axis is refused.
    """

    enabled: bool = True
    velocity_noise_m_s: float = 0.02
    disturbance_noise_m_s2_sqrt_s: float = 0.3
    vertical_disturbance_noise_m_s2_sqrt_s: float = 0.01
    hover_noise_per_sqrt_s: float = 0.02
    hover_initial_std: float = 0.15
    hover_min: float = 0.2
    hover_max: float = 0.8
    disturbance_max_m_s2: float = 3.0
    max_dt_s: float = 0.5
    innovation_gate: float = 400.0
    autopilot_thrust: bool = True
    autopilot_thrust_max_age_s: float = 0.25
    accelerometer: bool = False
    accel_noise_m_s2: float = 1.0
    accel_disturbance_noise_m_s2_sqrt_s: float = 0.3
    accel_bias_noise_m_s2_sqrt_s: float = 0.3
    accel_bias_initial_std_m_s2: float = 0.2
    accel_bias_max_m_s2: float = 1.0
    accel_max_m_s2: float = 30.0
    accel_max_age_s: float = 0.5

    def __post_init__(self) -> None:
        pos = ("velocity_noise_m_s", "hover_initial_std", "max_dt_s", "innovation_gate",
               "disturbance_max_m_s2", "autopilot_thrust_max_age_s", "accel_noise_m_s2",
               "accel_bias_initial_std_m_s2", "accel_bias_max_m_s2", "accel_max_m_s2",
               "accel_max_age_s")
        for name in pos:
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ParamError(f"control.estimator.{name}: must be > 0 (got {v!r})")
        for name in ("disturbance_noise_m_s2_sqrt_s", "vertical_disturbance_noise_m_s2_sqrt_s",
                     "hover_noise_per_sqrt_s", "accel_disturbance_noise_m_s2_sqrt_s",
                     "accel_bias_noise_m_s2_sqrt_s"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise ParamError(f"control.estimator.{name}: must be >= 0 (got {v!r})")
        if not (0.0 < self.hover_min < self.hover_max < 1.0):
            raise ParamError("control.estimator: need 0 < hover_min < hover_max < 1 "
                             f"(got {self.hover_min}, {self.hover_max})")


@dataclass(frozen=True)
class DisturbanceEstimate:
    """What the controller uses: ``hover_thrust`` (normalised, within the bounds),
    ``d_ned_m_s2`` (3,), their stds, and bookkeeping (``updates``, ``rejected``, last
    ``innovation_m_s`` (3,), ``reason`` of the last rejection or ``""``). With the
    accelerometer: its estimated bias (body x, y) and the number of its samples used."""

    hover_thrust: float
    d_ned_m_s2: tuple[float, float, float]
    hover_std: float
    d_std_m_s2: tuple[float, float, float]
    updates: int
    rejected: int
    innovation_m_s: tuple[float, float, float]
    reason: str = ""
    accel_bias_m_s2: tuple[float, float] | None = None
    accel_updates: int = 0

    def to_record(self) -> dict[str, object]:
        rec: dict[str, object] = {
            "hover_thrust": self.hover_thrust, "d_ned_m_s2": list(self.d_ned_m_s2),
            "hover_std": self.hover_std, "d_std_m_s2": list(self.d_std_m_s2),
            "updates": self.updates, "rejected": self.rejected,
            "innovation_m_s": list(self.innovation_m_s), "reason": self.reason,
        }
        if self.accel_bias_m_s2 is not None:
            rec["accel_bias_m_s2"] = list(self.accel_bias_m_s2)
            rec["accel_updates"] = self.accel_updates
        return rec


@dataclass
class DisturbanceEstimator:
    """The filter. ``update(t_s, v_ned, thrust, body_z_ned)`` once per new velocity sample:
    ``thrust`` and ``body_z_ned`` are the normalised thrust commanded and the body z axis in NED
    (``R(q) e_z``, measured attitude) over the interval since the previous sample.
    ``update_accel(...)`` once per accelerometer sample (``params.accelerometer``), in time
    order with the velocity samples."""

    params: EstimatorParams
    hover_thrust0: float
    g_m_s2: float = 9.81
    #: compile the velocity step there (:class:`companion.core.disturbance_step.VelocityStep`)
    cache_dir: str | None = None
    x: np.ndarray = field(init=False)
    p: np.ndarray = field(init=False)
    t_s: float | None = field(init=False, default=None)
    updates: int = field(init=False, default=0)
    rejected: int = field(init=False, default=0)
    accel_updates: int = field(init=False, default=0)
    innovation: np.ndarray = field(init=False)
    reason: str = field(init=False, default="")
    _t_vel: float | None = field(init=False, default=None)  # the last velocity sample's time
    _t_acc: float | None = field(init=False, default=None)  # the last accelerometer update's
    _step: VelocityStep = field(init=False, repr=False)
    _est_cache: tuple[Any, ...] | None = field(init=False, default=None, repr=False)

    def __post_init__(self) -> None:
        h0 = float(self.hover_thrust0)
        if not (self.params.hover_min <= h0 <= self.params.hover_max):
            raise ParamError(
                f"control.hover_thrust {h0} is outside control.estimator.hover_min..hover_max")
        self._step = VelocityStep(self.n, self.cache_dir)
        self.reset()

    @property
    def n(self) -> int:
        """Number of states: 7, or 9 with the accelerometer's bias."""
        return _NX + (_NB if self.params.accelerometer else 0)

    def reset(self) -> None:
        """Back to the prior: ``d = 0``, hover thrust as configured, velocity unknown,
        accelerometer bias 0."""
        pr = self.params
        h0 = float(self.hover_thrust0)
        self.x = np.zeros(self.n)
        self.x[6] = 1.0 / h0
        theta_std = pr.hover_initial_std / (h0 * h0)  # d(1/h) = dh / h^2
        diag = [1.0, 1.0, 1.0, 0.05**2, 0.05**2, 0.01**2, theta_std**2]
        if pr.accelerometer:
            diag += [pr.accel_bias_initial_std_m_s2**2] * _NB
        self.p = np.diag(diag)
        self.t_s = None
        self._t_vel = None
        self._t_acc = None
        self.innovation = np.zeros(3)

    # ------------------------------------------------------------------------------------------

    @property
    def hover_thrust(self) -> float:
        return 1.0 / float(self.x[6])

    def estimate(self) -> DisturbanceEstimate:
        # the same estimate as the last call while nothing it reads changed (every change
        # replaces x, p or innovation, or counts; _anchor's in-place writes touch only the
        # velocity, which it does not read): the step asks twice (frozen: shared)
        c = self._est_cache
        key = (self.updates, self.rejected, self.accel_updates, self.reason)
        if (c is not None and c[0] is self.x and c[1] is self.p and c[2] is self.innovation
                and c[3] == key):
            cached: DisturbanceEstimate = c[4]
            return cached
        est = self._estimate()
        self._est_cache = (self.x, self.p, self.innovation, key, est)
        return est

    def _estimate(self) -> DisturbanceEstimate:
        # plain floats: numpy's per-call overhead on 3-vectors cost more than the arithmetic
        x = self.x.tolist()
        p_diag = self.p.diagonal().tolist()
        theta = x[6]
        theta_std = math.sqrt(max(p_diag[6], 0.0))
        dx, dy, dz = (math.sqrt(max(v, 0.0)) for v in p_diag[3:6])
        bias = (x[7], x[8]) if self.params.accelerometer else None
        ix, iy, iz = self.innovation.tolist()
        return make(
            DisturbanceEstimate, hover_thrust=1.0 / theta,
            d_ned_m_s2=(x[3], x[4], x[5]),
            hover_std=theta_std / (theta * theta),
            d_std_m_s2=(dx, dy, dz),
            updates=self.updates, rejected=self.rejected,
            innovation_m_s=(ix, iy, iz),
            reason=self.reason, accel_bias_m_s2=bias, accel_updates=self.accel_updates,
        )

    def update(self, t_s: float, v_ned_m_s: ArrayLike, thrust_norm: float | None,
               body_z_ned: ArrayLike | None) -> bool:
        """Predict to ``t_s`` with the command held since the last sample, then correct with
        the measured velocity. Returns False (estimate unchanged, reason set) for bad data.

        ``thrust_norm is None`` (nothing was commanded: not flying under our control) only
        re-anchors the velocity; the estimate is not touched.
        """
        v = _three(v_ned_m_s)
        if v is None or not _all_finite(v) or not math.isfinite(float(t_s)):
            return self._reject("non-finite velocity or time")
        if self.t_s is not None and t_s <= self.t_s:
            return self._reject("velocity sample not newer than the last one")
        if thrust_norm is None or body_z_ned is None:
            self._anchor(t_s, v)
            return True
        b = _checked_inputs(thrust_norm, body_z_ned)
        if b is None:
            return self._reject(f"non-finite or implausible thrust {thrust_norm!r} or body z "
                                f"{np.asarray(body_z_ned).tolist()}")
        if self.t_s is None or self._t_vel is None or t_s - self._t_vel > self.params.max_dt_s:
            self._anchor(t_s, v)
            return True
        res, innov = self._velocity_step(t_s, t_s - self.t_s, float(thrust_norm), b, v)
        if isinstance(res, str):
            if res.startswith("outlier"):
                # an outlier: keep the estimate, re-anchor the velocity so one glitch is not
                # followed by a string of rejections
                self._anchor(t_s, v)
                return self._reject(f"velocity {res}")
            return self._reject(res)
        self.t_s = t_s
        self._t_vel = t_s
        self.innovation = innov
        self.updates += 1
        self.reason = ""
        return True

    def update_accel(self, t_s: float, f_body_xy_m_s2: ArrayLike, thrust_norm: float | None,
                     body_z_ned: ArrayLike | None, r_body_to_ned: ArrayLike) -> bool:
        """One accelerometer sample at ``t_s``: the specific force measured in body x and y
        (bias-corrected by the autopilot, our bias state takes the rest) with the attitude
        ``r_body_to_ned`` at ``t_s``; ``thrust_norm``/``body_z_ned`` as in :meth:`update` for
        the interval since the filter's last sample. Predicts to ``t_s`` and corrects with
        ``f_xy = (R' d)_xy + b``. Returns False and leaves the estimate alone when it is not
        used: accelerometer off, no recent velocity (the filter is not running), a sample not
        newer than the filter, no known thrust (counted as neither), or bad data (rejected,
        counted, reason set)."""
        if not self.params.accelerometer:
            return False
        if self.t_s is None or self._t_vel is None:
            return False
        f = np.asarray(f_body_xy_m_s2, dtype=float).reshape(-1)
        rot = np.asarray(r_body_to_ned, dtype=float)
        fl = f.tolist()
        if (f.shape != (2,) or not _all_finite(fl) or not math.isfinite(float(t_s))
                or max(abs(fl[0]), abs(fl[1])) > self.params.accel_max_m_s2):
            return self._reject(f"non-finite or implausible accelerometer sample {fl}")
        # np.allclose(R'R, I, atol=1e-3) (rtol 1e-5), without its wrapper's cost
        if (rot.shape != (3, 3) or not np.isfinite(rot).all()
                or not (np.abs(rot.T @ rot - _EYE3) <= _ORTHO_TOL).all()):
            return self._reject("accelerometer attitude is not a rotation")
        if t_s < self.t_s:
            return False  # older than what the filter holds: no update
        if t_s - self._t_vel > self.params.max_dt_s:
            return False  # the velocity is stale: the next velocity sample restarts the filter
        if t_s == self.t_s:  # the instant of the filter's last sample: nothing to predict
            x_pred, p_pred = self.x, self.p
        else:
            if thrust_norm is None or body_z_ned is None:
                return False  # the thrust that flew is unknown: no prediction, no update
            b = _checked_inputs(thrust_norm, body_z_ned)
            if b is None:
                return self._reject(f"non-finite or implausible thrust {thrust_norm!r} or "
                                    f"body z {np.asarray(body_z_ned).tolist()}")
            x_pred, p_pred = self._predict(t_s, t_s - self.t_s, float(thrust_norm),
                                           np.array(b))
        h = np.zeros((2, self.n))
        h[:, 3:6] = rot[:, 0:2].T  # (R' d)_xy
        h[:, 7:9] = np.eye(2)
        innov = f - h @ x_pred
        r = np.eye(2) * self.params.accel_noise_m_s2**2
        res = self._correct(x_pred, p_pred, h, innov, r)
        if isinstance(res, str):
            if res.startswith("outlier"):
                # keep the prediction (the velocity still holds the filter)
                self.x, self.p, self.t_s = self._clip(x_pred), p_pred, t_s
            return self._reject(f"accelerometer {res}")
        self.t_s = t_s
        self._t_acc = t_s
        self.accel_updates += 1
        return True

    # ------------------------------------------------------------------------------------------

    def _velocity_step(self, t_s: float, dt: float, thrust: float,
                       b: tuple[float, float, float], v: tuple[float, float, float]
                       ) -> tuple[str | None, np.ndarray]:
        """:meth:`_predict` to ``t_s``, then :meth:`_correct` with ``v`` (``H = [I 0]``,
        ``R = r I``, without the products by H), in one call of
        :mod:`companion.core.disturbance_step`; returns the verdict and the innovation."""
        g = self.g_m_s2
        c = -dt * g * thrust
        bx, by, bz = b
        r = self.params.velocity_noise_m_s**2
        x_new, p_new, innov, nis, det = self._step(
            self.x, self.p, dt, (c * bx, c * by, c * bz), g * dt, self._q_diag(t_s, dt),
            v, r)
        if det == 0.0:
            self.reset()
            return "singular innovation covariance: filter reset", innov
        if not math.isfinite(nis) or nis > self.params.innovation_gate:
            return f"outlier (normalised innovation {nis:.3g})", innov
        if not math.isfinite(float(x_new.sum() + p_new.sum())):  # finite iff every entry is
            self.reset()
            return "non-finite estimate: filter reset", innov
        self.x = self._clip(x_new)
        self.p = p_new
        return None, innov

    def _correct(self, x_pred: np.ndarray, p_pred: np.ndarray, h: np.ndarray,
                 innov: np.ndarray, r: np.ndarray) -> str | None:
        """Kalman correction (Joseph form) into ``self.x``/``self.p``; a reason string (and
        nothing changed) for an outlier, a singular innovation covariance or a non-finite
        result (the last two reset the filter)."""
        s = h @ p_pred @ h.T + r
        try:
            s_inv = np.linalg.inv(s)
        except np.linalg.LinAlgError:
            self.reset()
            return "singular innovation covariance: filter reset"
        nis = float(innov @ s_inv @ innov)
        if not math.isfinite(nis) or nis > self.params.innovation_gate:
            return f"outlier (normalised innovation {nis:.3g})"
        k = p_pred @ h.T @ s_inv
        x_new = x_pred + k @ innov
        i_kh = np.eye(self.n) - k @ h
        p_new = i_kh @ p_pred @ i_kh.T + k @ r @ k.T  # Joseph form: stays PSD
        p_new = 0.5 * (p_new + p_new.T)
        if not (np.all(np.isfinite(x_new)) and np.all(np.isfinite(p_new))):
            self.reset()
            return "non-finite estimate: filter reset"
        self.x = self._clip(x_new)
        self.p = p_new
        return None

    def _predict(self, t_s: float, dt: float, thrust: float,
                 b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        g = self.g_m_s2
        n = self.n
        f = np.eye(n)
        f[0, 3] = f[1, 4] = f[2, 5] = dt
        f[0:3, 6] = -dt * g * thrust * b
        x = f @ self.x
        x[2] += g * dt
        # the velocity also integrates the disturbance's random walk over the interval
        p = f @ self.p @ f.T + np.diag(self._q_diag(t_s, dt))
        return x, p

    def _q_diag(self, t_s: float, dt: float) -> list[float]:
        """The process noise's diagonal over ``dt`` up to ``t_s``."""
        pr = self.params
        h = self.hover_thrust
        # with a recent accelerometer sample the horizontal disturbance may move faster: it is
        # measured directly, not only through the velocity's derivative
        q_d = pr.disturbance_noise_m_s2_sqrt_s
        if (pr.accelerometer and self._t_acc is not None
                and t_s - self._t_acc <= pr.accel_max_age_s):
            q_d = pr.accel_disturbance_noise_m_s2_sqrt_s
        q = [0.0, 0.0, 0.0, q_d**2 * dt, q_d**2 * dt,
             pr.vertical_disturbance_noise_m_s2_sqrt_s**2 * dt,
             (pr.hover_noise_per_sqrt_s / (h * h)) ** 2 * dt]
        if pr.accelerometer:
            q += [pr.accel_bias_noise_m_s2_sqrt_s**2 * dt] * _NB
        return q

    def _anchor(self, t_s: float, v: ArrayLike) -> None:
        self.x[:3] = v
        self.p[:3, :] = 0.0
        self.p[:, :3] = 0.0
        self.p[:3, :3] = np.eye(3) * self.params.velocity_noise_m_s**2
        self.t_s = t_s
        self._t_vel = t_s

    def _clip(self, x: np.ndarray) -> np.ndarray:
        """``x`` with d, theta (and the bias) clipped to their bounds (``np.clip``'s values,
        element by element in plain floats: cheaper on so few)."""
        pr = self.params
        v = x.tolist()
        d_max = pr.disturbance_max_m_s2
        for i in (3, 4, 5):
            v[i] = min(max(v[i], -d_max), d_max)
        v[6] = min(max(v[6], 1.0 / pr.hover_max), 1.0 / pr.hover_min)
        if pr.accelerometer:
            b_max = pr.accel_bias_max_m_s2
            v[7] = min(max(v[7], -b_max), b_max)
            v[8] = min(max(v[8], -b_max), b_max)
        return np.array(v)

    def _reject(self, why: str) -> bool:
        self.rejected += 1
        self.reason = why
        return False


def _all_finite(values: Sequence[float]) -> bool:
    return all(map(math.isfinite, values))  # (a builtin over the values: no generator)


def _three(x: ArrayLike) -> tuple[float, float, float] | None:
    """Three floats (a telemetry 3-tuple without an array); ``None`` for another shape."""
    a = x if isinstance(x, tuple) else np.asarray(x, dtype=float).reshape(-1).tolist()
    return (float(a[0]), float(a[1]), float(a[2])) if len(a) == 3 else None


def _checked_inputs(thrust_norm: float,
                    body_z_ned: ArrayLike) -> tuple[float, float, float] | None:
    """The body z axis as floats, or None when it or the thrust is non-finite/implausible."""
    b = _three(body_z_ned)
    if b is None:
        return None
    bx, by, bz = b
    if (not _all_finite(b) or not math.isfinite(thrust_norm)
            or not 0.0 <= thrust_norm <= 1.0
            or abs(math.sqrt(bx * bx + by * by + bz * bz) - 1.0) > 1e-3):
        return None
    return b


def compensated_input(u: ArrayLike, d_ned_m_s2: ArrayLike, yaw_rad: float) -> np.ndarray:
    """The input the setpoint mapping (spec 5) must realise so that the vehicle's acceleration
    is ``u[0:3]`` despite the disturbance: ``u - [Rz(yaw)' d, 0]`` (4,), virtual frame."""
    uu = np.array(u, dtype=float).reshape(4)
    d = np.asarray(d_ned_m_s2, dtype=float).reshape(3)
    c, s = math.cos(yaw_rad), math.sin(yaw_rad)
    d_v = np.array([c * d[0] + s * d[1], -s * d[0] + c * d[1], d[2]])
    uu[:3] -= d_v
    return uu


__all__ = ["DisturbanceEstimate", "DisturbanceEstimator", "EstimatorParams", "compensated_input"]
