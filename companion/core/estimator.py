"""Target velocity from the image when the target's own state (FOLLOW_TARGET) is stale.

Spec 4 inverted: ``s1' = -(v_qx - v_ax)/z* + s2 psidot_q`` gives
``v_ax = v_qx + z* (s1' - s2 psidot_q)``, likewise ``v_ay = v_qy + z* (s2' + s1 psidot_q)``,
with ``s'`` by finite differences between frames, low-pass filtered. Pure numpy.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np


@dataclass
class ImageVelocityEstimator:
    """Target velocity from the image when FOLLOW_TARGET is stale (spec 4 inverted):
    ``v_ax = v_qx + z* (s1' - s2 psidot_q)``, ``v_ay = v_qy + z* (s2' + s1 psidot_q)``, with
    ``s'`` by finite differences, low-pass filtered. Output in NED."""

    z_star: float
    alpha: float = 0.2
    prev: tuple[float, list[float]] | None = None
    v_ned: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def update(self, t_s: float, s: np.ndarray, v_q_v: np.ndarray, yaw: float,
               yaw_rate: float) -> np.ndarray:
        # plain floats (numpy's element-wise formulas, the same values)
        sl = np.asarray(s, dtype=float).tolist()
        if self.prev is not None and t_s > self.prev[0]:
            dt = t_s - self.prev[0]
            sp = self.prev[1]
            sd0, sd1 = (sl[0] - sp[0]) / dt, (sl[1] - sp[1]) / dt
            vq0, vq1 = float(v_q_v[0]), float(v_q_v[1])
            vx = vq0 + self.z_star * (sd0 - sl[1] * yaw_rate)
            vy = vq1 + self.z_star * (sd1 + sl[0] * yaw_rate)
            c, sn = math.cos(yaw), math.sin(yaw)
            v_a_ned = (c * vx - sn * vy, sn * vx + c * vy, 0.0)
            if all(map(math.isfinite, v_a_ned)):
                a = self.alpha
                self.v_ned = np.array([(1 - a) * o + a * n
                                       for o, n in zip(self.v_ned.tolist(), v_a_ned,
                                                       strict=True)])
        self.prev = (t_s, sl)
        return self.v_ned.copy()
