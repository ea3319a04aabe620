"""rotorpy's multirotor derivative (``rotorpy.vehicles.multirotor.Multirotor._s_dot_fn`` and
``compute_body_wrench``, rotorpy 3.0.0) and its ground contact (``_handle_vehicle_on_ground``)
transcribed to Python floats.

Why: rotorpy's numpy version costs ~220 us per evaluation here (small-array numpy, scipy's
``Rotation``, dict packing); RK4 at the emulator's 2.5 ms physics step evaluates it 80 times per
50 ms step, 25 ms of CPU, and a 60 s lockstep flight then ran out of ``companion demo``'s wall
budget on this loaded machine. This transcription computes the same numbers in ~20 us;
``tests/sim/test_rotorpy.py`` checks it against rotorpy's own function on random states (with
wind, aerodynamics, ground contact) to 1e-9 relative, and the integration against rotorpy's
``Multirotor.step``. It also spares the emulator rotorpy's ``multirotor`` module, which imports
``scipy.integrate`` (20 s of start-up at load 28 here, past the companion's 60 s wait for the
first camera frame in a campaign). Nothing is simplified: the same terms in the same frames
(world z up, body z up; quaternion x, y, z, w, normalised for the rotation as scipy does, not for
its derivative, as rotorpy does).

Per rotor i at ``r_i`` with speed ``w_i``, the body air velocity ``va = R^T (v - wind)`` and the
rotor's local air velocity ``l_i = va + omega x r_i``::

    T_i = k_eta w_i^2 e_z + k_h (l_ix^2 + l_iy^2) e_z        thrust + translational lift
    H_i = -w_i diag(k_d, k_d, k_z) l_i                        rotor drag + induced inflow
    D   = -|va| diag(c_Dx, c_Dy, c_Dz) va                     parasitic drag
    M   = sum r_i x (T_i + H_i) + dir_i k_m w_i^2 e_z - k_flap w_i (l_iy, -l_ix, 0)
    m v' = m g (-e_z) + R (sum (T_i + H_i) + D)  [+ the ground's normal force]
    I omega' = M - omega x I omega
    w_i' = (w_cmd_i - w_i) / tau_m
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np


class RotorpyDerivative:
    """``f(state, w_cmd)`` of rotorpy's Multirotor for one parameter set (``quad_params``)."""

    def __init__(self, quad: dict[str, Any], aero: bool, enable_ground: bool,
                 g_m_s2: float = 9.81) -> None:
        self.mass = float(quad["mass"])
        inertia = np.array([[quad["Ixx"], quad["Ixy"], quad["Ixz"]],
                            [quad["Ixy"], quad["Iyy"], quad["Iyz"]],
                            [quad["Ixz"], quad["Iyz"], quad["Izz"]]], dtype=float)
        self.inertia = tuple(tuple(float(v) for v in row) for row in inertia)
        self.inv_inertia = tuple(tuple(float(v) for v in row) for row in np.linalg.inv(inertia))
        self.rotors = tuple(tuple(float(v) for v in quad["rotor_pos"][k])
                            for k in quad["rotor_pos"])
        self.dirs = tuple(float(v) for v in quad["rotor_directions"])
        self.k_eta, self.k_m = float(quad["k_eta"]), float(quad["k_m"])
        self.k_d, self.k_z = float(quad.get("k_d", 0.0)), float(quad.get("k_z", 0.0))
        self.k_h, self.k_flap = float(quad.get("k_h", 0.0)), float(quad.get("k_flap", 0.0))
        self.c_d = (float(quad.get("c_Dx", 0.0)), float(quad.get("c_Dy", 0.0)),
                    float(quad.get("c_Dz", 0.0)))
        self.inv_tau_m = 1.0 / float(quad["tau_m"])
        self.aero, self.enable_ground, self.g = aero, enable_ground, g_m_s2
        self.ground_friction_beta = max(0.1, min(0.5, float(quad.get("ground_friction_beta",
                                                                     0.3))))

    def on_ground(self, s: Any) -> bool:
        """rotorpy's ``_on_ground``: at or below its ground plane z = 0 (1 mm)."""
        return bool(self.enable_ground and float(s[2]) <= 0.001)

    def ground_contact(self, s: np.ndarray) -> np.ndarray:
        """rotorpy's ``_handle_vehicle_on_ground`` after a step that ends on the ground: on the
        plane, no downward speed, horizontal speed x (1 - beta) (friction), no rotation, level
        with the heading kept (its ``flatten_attitude``, with scipy's rotations as rotorpy)."""
        from scipy.spatial.transform import Rotation  # the emulator imports scipy.spatial anyway

        out = s.copy()
        out[2] = 0.0
        out[5] = max(0.0, float(out[5]))
        out[3:5] *= 1.0 - self.ground_friction_beta
        out[10:13] = 0.0
        heading = Rotation.from_quat(out[6:10]).as_euler("XYZ", degrees=False)[2]
        out[6:10] = Rotation.from_euler("Z", heading, degrees=False).as_quat()
        return out

    def body_wrench(self, omega: tuple[float, float, float], speeds: Any,
                    va: tuple[float, float, float]) -> tuple[list[float], list[float]]:
        """rotorpy's ``compute_body_wrench``: force and moment in the body frame."""
        p, q, r = omega
        fx = fy = fz = mx = my = mz = 0.0
        kd, kz, kh, kf = self.k_d, self.k_z, self.k_h, self.k_flap
        for (rx, ry, rz), w, d in zip(self.rotors, speeds, self.dirs, strict=True):
            w = float(w)
            tz = self.k_eta * w * w
            hx = hy = hz = 0.0
            if self.aero:
                lx = va[0] + (q * rz - r * ry)
                ly = va[1] + (r * rx - p * rz)
                lz = va[2] + (p * ry - q * rx)
                hx, hy, hz = -w * kd * lx, -w * kd * ly, -w * kz * lz
                tz += kh * (lx * lx + ly * ly)
                mx += -kf * w * ly
                my += kf * w * lx
            gx, gy, gz = hx, hy, hz + tz
            fx, fy, fz = fx + gx, fy + gy, fz + gz
            mx += ry * gz - rz * gy
            my += rz * gx - rx * gz
            mz += rx * gy - ry * gx + d * self.k_m * w * w
        if self.aero:
            n = math.sqrt(va[0] ** 2 + va[1] ** 2 + va[2] ** 2)
            fx -= n * self.c_d[0] * va[0]
            fy -= n * self.c_d[1] * va[1]
            fz -= n * self.c_d[2] * va[2]
        return [fx, fy, fz], [mx, my, mz]

    def __call__(self, s: Any, w_cmd: Any) -> np.ndarray:
        """rotorpy's ``_s_dot_fn(t, s, cmd_rotor_speeds)`` (state layout: x, v, q xyzw, omega,
        wind, rotor speeds)."""
        _, _, x2, v0, v1, v2, q0, q1, q2, q3, p, q, r, a0, a1, a2 = (float(v) for v in s[:16])
        speeds = s[16:20]
        n = math.sqrt(q0 * q0 + q1 * q1 + q2 * q2 + q3 * q3)
        x, y, z, w = q0 / n, q1 / n, q2 / n, q3 / n
        rot = ((1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)),
               (2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)),
               (2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)))
        ax, ay, az = v0 - a0, v1 - a1, v2 - a2
        va = (rot[0][0] * ax + rot[1][0] * ay + rot[2][0] * az,
              rot[0][1] * ax + rot[1][1] * ay + rot[2][1] * az,
              rot[0][2] * ax + rot[1][2] * ay + rot[2][2] * az)
        fb, mb = self.body_wrench((p, q, r), speeds, va)
        f = [rot[i][0] * fb[0] + rot[i][1] * fb[1] + rot[i][2] * fb[2] for i in range(3)]
        weight_z = -self.mass * self.g
        if self.enable_ground and x2 <= 0.001 and weight_z + f[2] < 0:
            f[2] -= weight_z + f[2]  # the ground's normal force
        (i00, i01, i02), (i10, i11, i12), (i20, i21, i22) = self.inertia
        hx, hy, hz = i00 * p + i01 * q + i02 * r, i10 * p + i11 * q + i12 * r, \
            i20 * p + i21 * q + i22 * r
        tx = mb[0] - (q * hz - r * hy)
        ty = mb[1] - (r * hx - p * hz)
        tz = mb[2] - (p * hy - q * hx)
        j = self.inv_inertia
        out = np.empty(20)
        out[0:3] = (v0, v1, v2)
        out[3:6] = (f[0] / self.mass, f[1] / self.mass, (weight_z + f[2]) / self.mass)
        out[6:10] = (0.5 * (q3 * p - q2 * q + q1 * r), 0.5 * (q2 * p + q3 * q - q0 * r),
                     0.5 * (-q1 * p + q0 * q + q3 * r), 0.5 * (-q0 * p - q1 * q - q2 * r))
        out[10:13] = (j[0][0] * tx + j[0][1] * ty + j[0][2] * tz,
                      j[1][0] * tx + j[1][1] * ty + j[1][2] * tz,
                      j[2][0] * tx + j[2][1] * ty + j[2][2] * tz)
        out[13:16] = 0.0
        out[16:20] = [(float(c) - float(o)) * self.inv_tau_m for c, o in zip(w_cmd, speeds,
                                                                            strict=True)]
        return out
