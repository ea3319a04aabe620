"""rotorpy's Dryden wind (``rotorpy/wind/dryden_utils.py``, ``GustModelBase`` and ``DrydenWind``,
rotorpy 3.0.0, MIT, after github.com/goromal/wind-dynamics), carried as a pure function of an
explicit state so that the vehicle's ``step`` stays a pure function and the wind is seeded.

Why a port and not an import: ``rotorpy.wind.dryden_utils`` imports ``torch`` at module level
(for its batched variant) and torch is only in rotorpy's ``batched`` extra, hundreds of MB we do
not need. The filter is the same 2nd-order Tustin recursion with rotorpy's coefficients and
length scales; ``tests/sim/test_rotorpy.py`` runs rotorpy's own class (read from its installed
source) on the same noise and checks that both give the same wind to 1e-12.

Two differences from rotorpy's use, both stated in docs/reference/rotorpy.md:

* the uniform noise ``u_k`` in [-1, 1] comes from ``numpy.random.default_rng([seed, 11, k])``
  (the step index ``k``), not from numpy's global generator, so a flight is reproducible;
* rotorpy's ``sigma`` is not the wind's standard deviation: the filter is driven by unit
  uniform noise whatever the step, so the std depends on the step (sigma = 1 gives 0.073 m/s at
  0.05 s, 0.018 m/s at 2.5 ms, L = 15 m). :func:`dryden_unit_std` computes the stationary std of
  one axis for sigma = 1 exactly (the filter is linear), and :class:`DrydenParams` takes the
  std wanted, so the wind's std is what the configuration says.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

V3 = tuple[float, float, float]
# (u_km1, u_km2, y_km1, y_km2) of one axis
AxisMemory = tuple[float, float, float, float]
_NOISE_TAG = 11  # separates this stream from the other seeded streams of the emulator
_AIRSPEED_M_S = 1.0  # rotorpy's DrydenWind passes V = 1.0 m/s to every axis' gust model


@dataclass(frozen=True)
class GustCoefficients:
    """rotorpy's ``GustModelBase.__init__`` and ``run``: ``C1 y_k = C4 u_k + C5 u_km1 + C6 u_km2
    - C2 y_km1 - C3 y_km2`` for a length scale ``L`` (m), intensity ``sigma`` and step ``dt``."""

    c1: float
    c2: float
    c3: float
    c4: float
    c5: float
    c6: float

    @staticmethod
    def of(length_m: float, sigma: float, dt_s: float) -> GustCoefficients:
        v = _AIRSPEED_M_S
        b = 2 * math.sqrt(3) * length_m / v
        c = 2 * length_m / v
        alpha = sigma * math.sqrt(2 * length_m / math.pi / v)
        beta = alpha * b
        delta = 2 * c
        gamma = c * c
        return GustCoefficients(
            c1=1.0 + 2 * delta / dt_s + 4 * gamma / dt_s / dt_s,
            c2=2.0 - 8 * gamma / dt_s / dt_s,
            c3=1.0 - 2 * delta / dt_s + 4 * gamma / dt_s / dt_s,
            c4=alpha + 2 * beta / dt_s,
            c5=2 * alpha,
            c6=alpha - 2 * beta / dt_s,
        )

    def run(self, mem: AxisMemory, u_k: float) -> tuple[float, AxisMemory]:
        u1, u2, y1, y2 = mem
        y = (self.c4 * u_k + self.c5 * u1 + self.c6 * u2 - self.c2 * y1 - self.c3 * y2) / self.c1
        return y, (u_k, u1, y, y1)


def dryden_length_scales_m(altitude_m: float) -> V3:
    """rotorpy's ``DrydenWind``: MIL-F-8785C low-altitude scales, ``L_z = h``, ``L_x = L_y =
    h / (0.177 + 0.000823 h)^1.2`` (h in feet there)."""
    lz_ft = 3.281 * altitude_m
    lx_ft = lz_ft / ((0.177 + 0.000823 * lz_ft) ** 1.2)
    return lx_ft / 3.281, lx_ft / 3.281, lz_ft / 3.281


def dryden_unit_std(length_m: float, dt_s: float, n_max: int = 200_000) -> float:
    """Stationary std of rotorpy's gust filter with ``sigma = 1`` driven by uniform [-1, 1]
    noise (variance 1/3): ``sqrt(sum h_k^2 / 3)`` over its impulse response."""
    c = GustCoefficients.of(length_m, 1.0, dt_s)
    mem: AxisMemory = (0.0, 0.0, 0.0, 0.0)
    total = 0.0
    y, mem = c.run(mem, 1.0)
    total += y * y
    for _ in range(n_max):
        y, mem = c.run(mem, 0.0)
        total += y * y
        if abs(y) < 1e-12 and abs(mem[3]) < 1e-12:
            break
    return math.sqrt(total / 3.0)


@dataclass(frozen=True)
class DrydenParams:
    """Wind in the world frame the caller uses: mean (m/s) plus Dryden turbulence with the
    stationary std ``std_m_s`` per axis (0: none), updated every ``dt_s``, seeded."""

    mean_m_s: V3 = (0.0, 0.0, 0.0)
    std_m_s: V3 = (0.0, 0.0, 0.0)
    altitude_m: float = 2.0
    dt_s: float = 0.05
    seed: int = 0
    # which axis of the caller's frame is vertical (L_z applies to it)
    vertical_axis: int = 2

    def __post_init__(self) -> None:
        if not (self.altitude_m > 0 and self.dt_s > 0):
            raise ValueError("dryden: altitude_m and dt_s must be > 0")
        if any(not (math.isfinite(v) and v >= 0) for v in self.std_m_s):
            raise ValueError("dryden: std_m_s must be finite and >= 0")
        if self.vertical_axis not in (0, 1, 2):
            raise ValueError("dryden: vertical_axis must be 0, 1 or 2")


@dataclass(frozen=True)
class WindState:
    """The wind at step ``k`` (the sample held over ``[k dt, (k + 1) dt)``) and the filters'
    memory."""

    k: int
    wind_m_s: V3
    memory: tuple[AxisMemory, AxisMemory, AxisMemory]


class DrydenWind:
    """rotorpy's ``DrydenWind`` (``getWind``) on an explicit :class:`WindState`."""

    def __init__(self, params: DrydenParams) -> None:
        self.params = params
        horiz, _, vert = dryden_length_scales_m(params.altitude_m)
        lengths = [horiz, horiz, horiz]
        lengths[params.vertical_axis] = vert
        self._coef = tuple(
            GustCoefficients.of(L, std / dryden_unit_std(L, params.dt_s) if std > 0 else 0.0,
                                params.dt_s)
            for L, std in zip(lengths, params.std_m_s, strict=True)
        )

    def noise(self, k: int) -> V3:
        """``u_k`` of the three axes: uniform in [-1, 1], from the seed and ``k`` alone."""
        rng = np.random.default_rng([self.params.seed & 0xFFFFFFFF, _NOISE_TAG, k])
        u = rng.uniform(-1.0, 1.0, size=3)
        return float(u[0]), float(u[1]), float(u[2])

    def initial(self) -> WindState:
        """Step 0 from a filter at rest (rotorpy starts its filters at zero too)."""
        return self.advance_from(WindState(-1, self.params.mean_m_s, ((0.0,) * 4,) * 3), 0)

    def advance_from(self, s: WindState, k: int) -> WindState:
        """The wind at step ``k`` >= ``s.k`` (rotorpy's ``getWind(dt)`` once per step)."""
        mean = self.params.mean_m_s
        k_now, mem, wind = s.k, list(s.memory), s.wind_m_s
        while k_now < k:
            k_now += 1
            u = self.noise(k_now)
            out = [0.0, 0.0, 0.0]
            for i in range(3):
                y, mem[i] = self._coef[i].run(mem[i], u[i])
                out[i] = mean[i] + y
            wind = (out[0], out[1], out[2])
        return WindState(k_now, wind, (mem[0], mem[1], mem[2]))

    def at(self, s: WindState, t_s: float) -> WindState:
        """The state holding the wind at ``t_s`` (advanced from ``s``; restarted when ``t_s``
        lies before ``s``)."""
        k = max(0, math.floor(t_s / self.params.dt_s + 1e-9))
        if k < s.k:
            s = self.initial()
        return self.advance_from(s, k) if k > s.k else s
