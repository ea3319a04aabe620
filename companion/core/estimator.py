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
    prev: tuple[float, np.ndarray] | None = None
    v_ned: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def update(self, t_s: float, s: np.ndarray, v_q_v: np.ndarray, yaw: float,
               yaw_rate: float) -> np.ndarray:
        if self.prev is not None and t_s > self.prev[0]:
            dt = t_s - self.prev[0]
            sd = (s - self.prev[1]) / dt
            v_a_v = np.array([
                v_q_v[0] + self.z_star * (sd[0] - s[1] * yaw_rate),
                v_q_v[1] + self.z_star * (sd[1] + s[0] * yaw_rate),
                0.0,
            ])
            c, sn = math.cos(yaw), math.sin(yaw)
            v_a_ned = np.array([c * v_a_v[0] - sn * v_a_v[1], sn * v_a_v[0] + c * v_a_v[1], 0.0])
            if np.all(np.isfinite(v_a_ned)):
                self.v_ned = (1 - self.alpha) * self.v_ned + self.alpha * v_a_ned
        self.prev = (t_s, np.array(s, dtype=float))
        return self.v_ned.copy()
