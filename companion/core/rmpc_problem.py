"""The RMPC optimisation problem of spec section 6 as a CasADi NLP in OCP (fatrop) order.

Decision vector, stage by stage (fatrop's structure detection needs this order)::

    w = [x_0, u_0, (sl_0), x_1, u_1, (sl_1), ..., x_N, (sl_N)]

``x_n = eta(n)`` (7), ``u_n = (r1, r2, r3, psidot_q)`` (4, the ABSOLUTE input), ``sl_n`` the
slacks of the soft (recovery) copy only. Constraint rows, stage by stage::

    g = [gap_0, path_0, gap_1, path_1, ..., gap_{N-1}, path_{N-1}, path_N]

with the gap rows written ``x_{n+1} - F(x_n, u_n)`` (explicit Euler) and the path rows of stage
``n`` depending on ``x_n, u_n, sl_n`` only. ``eta(0)`` is fixed by equal bounds on ``x_0``;
input and state boxes are bounds on ``w``. Parameters ``p`` (8 N): per stage
``[v_ax, v_ay, vdot_ax, vdot_ay, psidot_a, d_x, d_y, d_z]`` (m/s, m/s^2, rad/s, m/s^2; virtual
frame). ``d`` is the estimated disturbance acceleration (``companion.core.disturbance``): the
input ``u`` is the vehicle's acceleration, so the attitude that realises it, and with it the
visible area's centre ``M``, is the one of the specific force ``u - d``.

Groups (RmpcParams switches):

- ``tube``: ``eta(n)' P eta(n) <= X(n)^2``, ``X(n) = ((N-n) H + n)/N eps`` for n = 0..N
  (the row at n = N, ``X(N) = eps``, is the terminal set and is shared with ``terminal``);
- ``visibility``: ``|p(n) - M(u(n))|^2 <= (r_v - n rho e^{L (n-1) delta})^2`` for n = 1..N-1,
  ``p(n) = [se1, se2]/s3``, ``s3 = se3 + 1``, ``M`` the mapped visible-area centre;
- ``terminal``: ``eta(N)' P eta(N) <= eps^2`` (Omega) and ``|p(N)|^2 <= gamma^2``.

The soft copy subtracts a slack ``>= 0`` from each of these rows and adds
``recovery_penalty * slack`` to the cost (an exact L1 penalty); dynamics, input bounds and the
state box stay hard.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import casadi as ca
import numpy as np

from companion.core.dynamics import S_REF, euler_step, input_error
from companion.core.geometry import attitude_from_accel, visible_area_centre
from companion.core.params import CameraParams, RmpcParams
from companion.core.terminal import TerminalDesign

NX = 7
NU = 4
NP_STAGE = 8
GROUPS = ("tube", "visibility", "terminal")


@dataclass(frozen=True)
class Row:
    """One soft-able path-constraint row: group, stage, g index, bound on g, slack index."""

    group: str
    kind: str  # "tube", "visibility", "terminal_set", "terminal_visibility"
    stage: int
    g_index: int
    upper: float
    slack_index: int | None


@dataclass(frozen=True)
class Layout:
    """Index bookkeeping of one NLP (hard or soft)."""

    horizon: int
    soft: bool
    n_w: int
    n_g: int
    x_index: np.ndarray  # (N+1, 7) indices into w
    u_index: np.ndarray  # (N, 4)
    gap_index: np.ndarray  # (N, 7) indices into g
    rows: tuple[Row, ...]
    equality: tuple[bool, ...]
    slack_index: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=int))


def tube_bound(rmpc: RmpcParams, n: int) -> float:
    """``X(n) = ((N - n) H + n)/N eps`` (spec 6)."""
    big_n = rmpc.horizon
    return ((big_n - n) * rmpc.tube_h + n) / big_n * rmpc.eps


def visibility_pairs(rmpc: RmpcParams) -> list[tuple[int, int, int]]:
    """``(stage, image index, input index)`` of every visibility row.

    ``spec`` (spec 6, the paper's (2d)): ``|p(n) - M(u(n))|`` for n = 1..N-1: the image at
    stage n against the attitude that input n asks for. The applied input u(0) is in no row.
    ``causal``: ``|p(n+1) - M(u(n))|`` for n = 0..N-2: the image at n+1 is taken with the
    attitude u(n) produced during the step (the paper's ``phi_d(k+1)`` from ``r(k)``), so the
    applied input u(0) is checked against the next image. Written in stage n as
    ``p(F(x_n, u_n))`` to keep the stage structure; tightened with the radius of stage n+1.
    """
    big_n = rmpc.horizon
    if rmpc.visibility_pairing == "causal":
        return [(n, n + 1, n) for n in range(big_n - 1)]
    return [(n, n, n) for n in range(1, big_n)]


def visibility_radius(rmpc: RmpcParams, terminal: TerminalDesign, n: int) -> float:
    """``r_v - n rho e^{L (n-1) delta}`` (spec 6), the tightened radius at stage ``n``."""
    return terminal.r_v - n * rmpc.rho * float(np.exp(terminal.lipschitz_l * (n - 1) * rmpc.dt_s))


def image_point(eta: Any) -> tuple[Any, Any]:
    """``p = [se1/s3, se2/s3]`` with ``s3 = se3 + 1`` (spec 6, Remark 3)."""
    s3 = eta[2] + S_REF[2]
    return eta[0] / s3, eta[1] / s3


def centre(u: Any, rmpc: RmpcParams, camera: CameraParams, d: Any = None) -> tuple[Any, Any]:
    """``M(u)``: centre of the visible area in the virtual image at the attitude ``u`` asks
    (with a disturbance ``d`` (3, virtual frame): the attitude of ``u - d``)."""
    if d is None:
        phi, theta, _ = attitude_from_accel(u[0], u[1], u[2], rmpc.g_m_s2)
    else:
        phi, theta, _ = attitude_from_accel(u[0] - d[0], u[1] - d[1], u[2] - d[2],
                                            rmpc.g_m_s2)
    half = camera.visible_half_m
    return visible_area_centre(phi, theta, half, half, camera.focal_length_m)


def build_nlp(
    rmpc: RmpcParams, camera: CameraParams, terminal: TerminalDesign, soft: bool
) -> tuple[dict[str, ca.SX], Layout]:
    """The NLP ``{x, p, f, g}`` (SX) and its layout. See the module docstring."""
    big_n = rmpc.horizon
    q = np.diag(rmpc.q_diag)
    r = np.diag(rmpc.r_diag)
    p_mat = np.asarray(terminal.p, dtype=float)
    xs = [ca.SX.sym(f"x{n}", NX) for n in range(big_n + 1)]
    us = [ca.SX.sym(f"u{n}", NU) for n in range(big_n)]
    par = ca.SX.sym("p", NP_STAGE * big_n)

    w: list[ca.SX] = []
    g: list[ca.SX] = []
    equality: list[bool] = []
    rows: list[Row] = []
    x_index = np.zeros((big_n + 1, NX), dtype=int)
    u_index = np.zeros((big_n, NU), dtype=int)
    gap_index = np.zeros((big_n, NX), dtype=int)
    slack_index: list[int] = []
    n_w = 0
    n_g = 0
    cost: ca.SX = ca.SX(0.0)

    def add_w(v: ca.SX) -> np.ndarray:
        nonlocal n_w
        w.append(v)
        idx = np.arange(n_w, n_w + v.shape[0])
        n_w += v.shape[0]
        return idx

    vis_stage = {st: img for st, img, _ in visibility_pairs(rmpc)}

    def path_rows(n: int, x: ca.SX, u: ca.SX | None, x_next: ca.SX | None = None,
                  d: ca.SX | None = None) -> None:
        """Add stage ``n``'s path rows (and slacks, appended to w right after x_n/u_n)."""
        nonlocal n_g, cost
        items: list[tuple[str, str, ca.SX, float]] = []
        if n < big_n:
            if rmpc.enable_tube:
                items.append(("tube", "tube", ca.bilin(p_mat, x, x), tube_bound(rmpc, n) ** 2))
            if rmpc.enable_visibility and n in vis_stage:
                assert u is not None and x_next is not None
                img = vis_stage[n]
                pu, pn = image_point(x if img == n else x_next)
                mu, mn = centre(u, rmpc, camera, d)
                val = (pu - mu) ** 2 + (pn - mn) ** 2
                items.append(
                    ("visibility", "visibility", val, visibility_radius(rmpc, terminal, img) ** 2)
                )
        else:
            if rmpc.enable_tube or rmpc.enable_terminal:  # X(N) = eps: the tube ends in Omega
                group = "terminal" if rmpc.enable_terminal else "tube"
                items.append((group, "terminal_set", ca.bilin(p_mat, x, x), rmpc.eps**2))
            if rmpc.enable_terminal:
                pu, pn = image_point(x)
                items.append(
                    ("terminal", "terminal_visibility", pu**2 + pn**2, terminal.gamma**2)
                )
        for group, kind, val, upper in items:
            s_idx: int | None = None
            if soft:
                s = ca.SX.sym(f"sl_{kind}_{n}")
                s_idx = int(add_w(s)[0])
                slack_index.append(s_idx)
                cost = cost + rmpc.recovery_penalty * s
                val = val - s
            g.append(val)
            equality.append(False)
            rows.append(Row(group, kind, n, n_g, upper, s_idx))
            n_g += 1

    for n in range(big_n):
        x, u = xs[n], us[n]
        pn_ = par[NP_STAGE * n : NP_STAGE * (n + 1)]
        v_a, vdot_a, psidot_a, d_n = pn_[0:2], pn_[2:4], pn_[4], pn_[5:8]
        x_index[n] = add_w(x)
        u_index[n] = add_w(u)
        ue = input_error(u, v_a, vdot_a, psidot_a)
        cost = cost + ca.bilin(q, x, x) + ca.bilin(r, ue, ue)
        x_next = euler_step(x, u, v_a, vdot_a, psidot_a, rmpc.desired_depth_m, rmpc.dt_s)
        gap = xs[n + 1] - x_next
        # g: the gap rows of stage n come before its path rows (fatrop's structure detection);
        # w: the path rows' slacks are appended right after u_n, i.e. before x_{n+1}.
        gap_index[n] = np.arange(n_g, n_g + NX)
        g.append(gap)
        equality.extend([True] * NX)
        n_g += NX
        path_rows(n, x, u, x_next, d_n)
    x_index[big_n] = add_w(xs[big_n])
    cost = cost + ca.bilin(p_mat, xs[big_n], xs[big_n])
    path_rows(big_n, xs[big_n], None)

    nlp = {"x": ca.vertcat(*w), "p": par, "f": cost, "g": ca.vertcat(*g)}
    layout = Layout(
        horizon=big_n,
        soft=soft,
        n_w=n_w,
        n_g=n_g,
        x_index=x_index,
        u_index=u_index,
        gap_index=gap_index,
        rows=tuple(rows),
        equality=tuple(equality),
        slack_index=np.array(slack_index, dtype=int),
    )
    return nlp, layout
