"""The RMPC optimisation problem of spec section 6 as a CasADi NLP in OCP (fatrop) order.

Decision vector, stage by stage (fatrop's structure detection needs this order)::

    w = [x_0, u_0, (sl_0), x_1, u_1, (sl_1), ..., x_N, (sl_N)]

``x_n = eta(n)`` (7), ``u_n = (r1, r2, r3, psidot_q)`` (4, the ABSOLUTE input), ``sl_n`` the
slacks of the soft (recovery) copy only. Constraint rows, stage by stage::

    g = [gap_0, path_0, gap_1, path_1, ..., gap_{N-1}, path_{N-1}, path_N]

with the gap rows written ``x_{n+1} - F(x_n, u_n)`` (explicit Euler) and the path rows of stage
``n`` depending on ``x_n, u_n, sl_n`` only. ``eta(0)`` is fixed by equal bounds on ``x_0``;
input and state boxes are bounds on ``w``. Parameters ``p`` (8 N + 1): per stage
``[v_ax, v_ay, vdot_ax, vdot_ay, psidot_a, d_x, d_y, d_z]`` (m/s, m/s^2, rad/s, m/s^2; virtual
frame), then ``s4_ref`` (rad, the measured ``s4 = eta0[3]``: the yaw the nominal motion was
predicted for, used by ``target_motion = "planned_yaw"``, :func:`stage_motion`). ``d`` is the
estimated disturbance acceleration (``companion.core.disturbance``): the input ``u`` is the
vehicle's acceleration, so the attitude that realises it, and with it the visible area's
centre ``M``, is the one of the specific force ``u - d``.
The soft copy has :data:`NP_SOFT_EXTRA` more parameters after ``s4_ref``: ``u_prev`` (4, the
input the previous step applied) and ``w_du`` (the input-rate weight,
``rmpc.recovery_input_rate_weight``; 0 when there is no previous input): its cost adds
``w_du sum_i ((u_i(0) - u_prev_i)^2 + sum_n (u_i(n+1) - u_i(n))^2) / u_max_i^2``.

Groups (RmpcParams switches):

- ``tube``: ``eta(n)' P eta(n) <= X(n)^2``, ``X(n) = ((N-n) H + n)/N eps`` for n = 0..N
  (the row at n = N, ``X(N) = eps``, is the terminal set and is shared with ``terminal``);
- ``visibility``: ``|p(n) - M(u(n))|^2 <= (r_v - n rho e^{L (n-1) delta})^2`` for n = 1..N-1,
  ``p(n) = [se1, se2]/s3``, ``s3 = se3 + 1``, ``M`` the mapped visible-area centre; with
  ``rmpc.visibility = "corners"`` one row per target corner ``p_i`` (:func:`corner_points`),
  tightened by ``k_c`` times the paper's margin (:func:`visibility_radius`,
  docs/reference/visibility.md);
- ``terminal``: ``eta(N)' P eta(N) <= eps^2`` (Omega) and ``|p(N)|^2 <= gamma^2``.

With ``rmpc.heading = "cost"`` the tube and terminal-set rows use ``P`` with ``s4`` minimised
out (:func:`tube_matrix`): the yaw error is then only in the cost.

The soft copy subtracts a slack ``>= 0`` from each of these rows and adds
``recovery_penalty * slack`` (visibility rows) or ``recovery_tube_penalty * slack`` (tube and
terminal rows) to the cost (an exact L1 penalty); dynamics, input bounds and the state box stay
hard, except that a velocity bound the measured state already exceeds is moved out to where
braking at an admissible rate can bring it (``rmpc.velocity_box_return``; otherwise the soft
copy would be infeasible at stage 1). A soft copy with its own weights
(``rmpc.recovery_q_diag``, :func:`companion.core.rmpc_recovery.recovery_design`) relaxes its
own design's rows, or with ``rmpc.recovery_rows = "hard"`` the hard problem's (``build_nlp``'s
``row_design``: the cost stays the soft design's); ``"own+terminal"`` adds to its own rows the
hard problem's terminal set at its own terminal level (``build_nlp``'s ``goal``, a row of kind
``"goal_set"`` at stage N: :func:`companion.core.rmpc_recovery.hard_terminal_row`).
"""

from __future__ import annotations

from typing import Any

import casadi as ca
import numpy as np

from companion.core._backend import is_symbolic, xp
from companion.core.dynamics import S_REF, euler_step, input_error
from companion.core.geometry import attitude_from_accel, visible_area_centre
from companion.core.params import CameraParams, RmpcParams
from companion.core.rmpc_layout import Layout as Layout  # (re-exported: its users import it here)
from companion.core.rmpc_layout import Row as Row
from companion.core.rmpc_memo import Nlp, memoized_nlp
from companion.core.terminal import TerminalDesign, tilt_limits

NX = 7
NU = 4
NP_STAGE = 8
GROUPS = ("tube", "visibility", "terminal")
NP_SOFT_EXTRA = NU + 1  # soft copy only: u_prev (4), w_du


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


def visibility_radius(rmpc: RmpcParams, terminal: TerminalDesign, n: int,
                      gain: float = 1.0) -> float:
    """``r_v - gain n rho e^{L (n-1) delta}`` (spec 6), the tightened radius at stage ``n``.

    ``gain`` 1 is the paper's centroid row; the corner rows use :func:`corner_gain`."""
    margin = n * rmpc.rho * float(np.exp(terminal.lipschitz_l * (n - 1) * rmpc.dt_s))
    return terminal.r_v - gain * margin


def corners_m(rmpc: RmpcParams) -> np.ndarray:
    """The target's corners (K, 2) in its own frame (m, x forward, y right)."""
    return np.asarray(rmpc.target_corners_m, dtype=float).reshape(-1, 2)


def corner_gain(rmpc: RmpcParams, camera: CameraParams) -> float:
    """``k_c``: how much a state disturbance of Euclidean size 1 in ``(se1, se2, se3, s4)``
    can move a corner's normalised image point (docs/reference/visibility.md):

        k_c = sqrt(1 + (c_max / z*)^2 + p_max^2) / s3_min

    ``c_max`` the largest corner distance from the target's centre, ``s3_min = min_depth/z*``
    (a state bound with the corner rows), ``p_max = r_v + |M|_max`` the farthest a corner
    satisfying its row can be from the image centre (``|M|`` at the tilt limits)."""
    c_max = float(np.max(np.hypot(*corners_m(rmpc).T)))
    phi_max, theta_max = tilt_limits(rmpc.u_max, rmpc.g_m_s2)
    half = camera.visible_half_m
    mu, mn = visible_area_centre(phi_max, theta_max, half, half, camera.focal_length_m)
    p_max = camera.r_v + float(np.hypot(mu, mn))
    s3_min = rmpc.min_depth_m / rmpc.desired_depth_m
    return float(np.sqrt(1.0 + (c_max / rmpc.desired_depth_m) ** 2 + p_max**2) / s3_min)


def corner_points(eta: Any, rmpc: RmpcParams) -> list[tuple[Any, Any]]:
    """Normalised virtual-image points ``p_i`` of the target's corners predicted from ``eta``.

    A corner ``c_i`` (target frame) sits at ``Rz(psi_a) c_i`` from the target's centre; in the
    virtual frame (yaw ``psi_q``) that is ``Rz(s4) c_i`` with ``s4 = psi_a - psi_q`` (spec 3),
    at the depth ``z = s3 z*``. So ``p_i = ([se1, se2] + Rz(s4) c_i / z*) / s3``: exact for a
    horizontal planar target (no approximation beyond the error state itself)."""
    m = xp(eta)
    s3 = eta[2] + S_REF[2]
    c4, s4 = m.cos(eta[3]), m.sin(eta[3])
    z = rmpc.desired_depth_m
    out = []
    for cx, cy in corners_m(rmpc):
        du = (c4 * cx - s4 * cy) / z
        dn = (s4 * cx + c4 * cy) / z
        out.append(((eta[0] + du) / s3, (eta[1] + dn) / s3))
    return out


def tube_matrix(rmpc: RmpcParams, p_mat: np.ndarray) -> np.ndarray:
    """The matrix of the tube and terminal-set rows: ``P`` (``heading = "tube"``), or ``P``
    with ``s4`` minimised out (``"cost"``): ``min_{s4} eta' P eta = eta' P_r eta``,
    ``P_r = P - P[:, 3] P[3, :] / P[3, 3]`` (the Schur complement; row/column 3 are zero)."""
    p = np.asarray(p_mat, dtype=float)
    if rmpc.heading == "tube":
        return p
    out: np.ndarray = p - np.outer(p[:, 3], p[3, :]) / p[3, 3]
    out[3, :] = 0.0
    out[:, 3] = 0.0
    return out


def stage_motion(rmpc: RmpcParams, x: Any, u: Any, v_a: Any, vdot_a: Any, psidot_a: Any,
                 s4_ref: Any) -> tuple[Any, Any, Any]:
    """The target motion ``(v_a, vdot_a, psidot_a)`` stage ``n`` uses (spec 4).

    ``"nominal"``: the parameters as given (predicted for a vehicle yaw that turns with the
    target, :mod:`companion.core.prediction`). ``"planned_yaw"``: the vehicle's planned yaw
    differs from that nominal yaw by ``theta = s4_ref - s4(n)`` (``s4 = psi_a - psi_q`` and the
    nominal keeps ``s4 = s4_ref``), so the target's velocity in the virtual frame is the nominal
    one rotated by ``-theta``, and ``vdot_a = Rz(-theta) a_nom + psidot_q(n) [v_ay, -v_ax]``
    with the planned yaw rate ``psidot_q(n) = u[3]``, where ``a_nom = vdot_nom - psidot_a
    [v_y, -v_x]_nom`` is the target's acceleration in the nominal frame."""
    if rmpc.target_motion == "nominal":
        return v_a, vdot_a, psidot_a
    m = xp(x, u, v_a, vdot_a, s4_ref)
    th = s4_ref - x[3]
    c, s = m.cos(th), m.sin(th)
    va0 = c * v_a[0] + s * v_a[1]
    va1 = -s * v_a[0] + c * v_a[1]
    an0 = vdot_a[0] - psidot_a * v_a[1]
    an1 = vdot_a[1] + psidot_a * v_a[0]
    vd0 = c * an0 + s * an1 + u[3] * va1
    vd1 = -s * an0 + c * an1 - u[3] * va0
    if is_symbolic(x, u, v_a, vdot_a, s4_ref):
        return ca.vertcat(va0, va1), ca.vertcat(vd0, vd1), psidot_a
    return np.array([float(va0), float(va1)]), np.array([float(vd0), float(vd1)]), psidot_a


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
    rmpc: RmpcParams, camera: CameraParams, terminal: TerminalDesign, soft: bool,
    row_design: tuple[RmpcParams, TerminalDesign] | None = None,
    goal: tuple[np.ndarray, float] | None = None,
) -> tuple[Nlp, Layout]:
    """The NLP ``{x, p, f, g}`` (SX) and its layout; ``row_design``, ``goal``: module doc.
    The expressions are built when first read: a problem built before (the same arguments,
    the same code) gets its layout and graph digest from ``rmpc.cache_dir``
    (:mod:`companion.core.rmpc_memo`)."""
    def build() -> tuple[dict[str, ca.SX], Layout]:
        return _expressions(rmpc, camera, terminal, soft, row_design, goal)

    return memoized_nlp(build, rmpc.cache_dir, (rmpc, camera, terminal, soft, row_design, goal))


def _expressions(
    rmpc: RmpcParams, camera: CameraParams, terminal: TerminalDesign, soft: bool,
    row_design: tuple[RmpcParams, TerminalDesign] | None,
    goal: tuple[np.ndarray, float] | None,
) -> tuple[dict[str, ca.SX], Layout]:
    """:func:`build_nlp`'s expressions, derived now."""
    row_rmpc, row_terminal = row_design or (rmpc, terminal)
    big_n = rmpc.horizon
    q, r = np.diag(rmpc.q_diag), np.diag(rmpc.r_diag)
    p_mat = np.asarray(terminal.p, dtype=float)
    xs = [ca.SX.sym(f"x{n}", NX) for n in range(big_n + 1)]
    us = [ca.SX.sym(f"u{n}", NU) for n in range(big_n)]
    par = ca.SX.sym("p", NP_STAGE * big_n + 1 + (NP_SOFT_EXTRA if soft else 0))
    s4_ref = par[NP_STAGE * big_n]
    w: list[ca.SX] = []
    g: list[ca.SX] = []
    equality: list[bool] = []  # per g row: an equality (dynamics gap) or not
    rows: list[Row] = []  # the path rows (the soft-able ones: tube, visibility, terminal)
    x_index, u_index = np.zeros((big_n + 1, NX), dtype=int), np.zeros((big_n, NU), dtype=int)
    gap_index = np.zeros((big_n, NX), dtype=int)
    slack_index: list[int] = []
    n_w, n_g = 0, 0
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
        for group, kind, val, upper, corner in _path_items(row_rmpc, camera, row_terminal, n,
                                                           x, u, x_next, d, vis_stage, goal):
            s_idx: int | None = None
            if soft:
                s = ca.SX.sym(f"sl_{kind}_{n}")
                s_idx = int(add_w(s)[0])
                slack_index.append(s_idx)
                weight = (rmpc.recovery_penalty if group == "visibility"
                          else rmpc.recovery_tube_penalty)
                cost = cost + weight * s
                val = val - s
            g.append(val)
            equality.append(False)
            rows.append(Row(group, kind, n, n_g, upper, s_idx, corner))
            n_g += 1

    for n in range(big_n):
        x, u = xs[n], us[n]
        pn_ = par[NP_STAGE * n : NP_STAGE * (n + 1)]
        v_a, vdot_a, psidot_a = stage_motion(rmpc, x, u, pn_[0:2], pn_[2:4], pn_[4], s4_ref)
        x_index[n], u_index[n] = add_w(x), add_w(u)  # in this order: w is x_n, u_n, ...
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
        path_rows(n, x, u, x_next, pn_[5:8])  # d: the estimated disturbance
    if soft:
        cost = cost + _input_rate(rmpc, us, par)
    x_index[big_n] = add_w(xs[big_n])
    cost = cost + ca.bilin(p_mat, xs[big_n], xs[big_n])
    path_rows(big_n, xs[big_n], None)

    nlp = {"x": ca.vertcat(*w), "p": par, "f": cost, "g": ca.vertcat(*g)}
    layout = Layout(horizon=big_n, soft=soft, n_w=n_w, n_g=n_g, x_index=x_index,
                    u_index=u_index, gap_index=gap_index, rows=tuple(rows),
                    equality=tuple(equality), slack_index=np.array(slack_index, dtype=int))
    return nlp, layout


def _input_rate(rmpc: RmpcParams, us: list[ca.SX], par: ca.SX) -> ca.SX:
    """The soft copy's input-rate term (module docstring): ``w_du`` times u(0) against
    ``u_prev``, then stage to stage, each normalised by ``u_max``."""
    big_n = rmpc.horizon
    u_prev = par[NP_STAGE * big_n + 1 : NP_STAGE * big_n + 1 + NU]
    w_du = par[NP_STAGE * big_n + 1 + NU]
    inv_u2 = np.diag(1.0 / np.asarray(rmpc.u_max, dtype=float) ** 2)
    rate = ca.bilin(inv_u2, us[0] - u_prev, us[0] - u_prev)
    for n in range(big_n - 1):
        rate = rate + ca.bilin(inv_u2, us[n + 1] - us[n], us[n + 1] - us[n])
    return w_du * rate


def _path_items(rmpc: RmpcParams, camera: CameraParams, terminal: TerminalDesign, n: int,
                x: ca.SX, u: ca.SX | None, x_next: ca.SX | None, d: ca.SX | None,
                vis_stage: dict[int, int], goal: tuple[np.ndarray, float] | None = None,
                ) -> list[tuple[str, str, ca.SX, float, int]]:
    """Stage ``n``'s path rows before any slack: (group, kind, value, bound on the value,
    corner) in the order :func:`build_nlp` lays them out (tube, visibility; at n = N the
    terminal set, terminal visibility and ``goal``'s row ``eta' G eta <= b``, if any)."""
    big_n = rmpc.horizon
    p_tube = tube_matrix(rmpc, np.asarray(terminal.p, dtype=float))
    items: list[tuple[str, str, ca.SX, float, int]] = []
    if n < big_n:
        if rmpc.enable_tube:
            items.append(("tube", "tube", ca.bilin(p_tube, x, x), tube_bound(rmpc, n) ** 2, -1))
        if rmpc.enable_visibility and n in vis_stage:
            assert u is not None and x_next is not None
            img = vis_stage[n]
            x_img = x if img == n else x_next
            mu, mn = centre(u, rmpc, camera, d)
            if rmpc.visibility == "corners":
                rad2 = visibility_radius(rmpc, terminal, img, corner_gain(rmpc, camera)) ** 2
                for i, (pu, pn) in enumerate(corner_points(x_img, rmpc)):
                    val = (pu - mu) ** 2 + (pn - mn) ** 2
                    items.append(("visibility", "corner", val, rad2, i))
            else:
                pu, pn = image_point(x_img)
                val = (pu - mu) ** 2 + (pn - mn) ** 2
                items.append(("visibility", "visibility", val,
                              visibility_radius(rmpc, terminal, img) ** 2, -1))
        return items
    if rmpc.enable_tube or rmpc.enable_terminal:  # X(N) = eps: the tube ends in Omega
        group = "terminal" if rmpc.enable_terminal else "tube"
        items.append((group, "terminal_set", ca.bilin(p_tube, x, x), rmpc.eps**2, -1))
    if rmpc.enable_terminal:
        pu, pn = image_point(x)
        items.append(("terminal", "terminal_visibility", pu**2 + pn**2, terminal.gamma**2, -1))
    if goal is not None:
        items.append(("terminal", "goal_set", ca.bilin(goal[0], x, x), goal[1], -1))
    return items
