"""Parameter types of the pure core: the camera, the RMPC and its terminal design, the
thrust mapping. Frozen and validated on construction (:class:`ParamError` names the config
key); the shell's config loader (``companion.config``) builds them from the TOML file, and each
field's ``check`` metadata is the per-value rule it applies first.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from companion.core.disturbance import EstimatorParams
from companion.core.errors import ParamError
from companion.core.latency import LatencyParams
from companion.core.lead import LeadParams


def positive(x: float) -> str | None:
    return None if x > 0 else "must be > 0"


def nonneg(x: float) -> str | None:
    return None if x >= 0 else "must be >= 0"


def unit(x: float) -> str | None:
    return None if 0 < x <= 1 else "must be in (0, 1]"


def checked(fn: Callable[[Any], str | None]) -> dict[str, Any]:
    return {"check": fn}


@dataclass(frozen=True)
class CameraParams:
    """Pinhole camera and its mount (spec section 1)."""

    focal_length_m: float = field(metadata=checked(positive))
    pixel_size_m: float = field(metadata=checked(positive))
    width_px: int = field(metadata=checked(positive))
    height_px: int = field(metadata=checked(positive))
    visible_fraction: float = field(metadata=checked(unit))
    report_pixel_size_m: float = field(metadata=checked(positive))
    mount_offset_m: tuple[float, float, float]
    mount_rpy_rad: tuple[float, float, float]
    calibration_file: str = ""

    def __post_init__(self) -> None:
        # The companion flies a camera whose optical axis is the body's z axis at the body
        # origin (the paper's mount), turned by any angle about that axis (mount yaw: a camera
        # fitted with its image "up" to the side or backwards). The detected points are then
        # re-projected into body axes (core.state.virtual_image_points); the visibility rows
        # are circles about the optical axis, so they hold unchanged. A tilted or offset camera
        # would be flown with the wrong geometry: refused here instead of failing in the air
        # (docs/reference/limits.md).
        for name in ("mount_offset_m", "mount_rpy_rad"):
            value = getattr(self, name)
            if len(value) != 3 or not all(math.isfinite(float(v)) for v in value):
                raise ParamError(f"camera.{name}: need 3 finite numbers, got {list(value)}")
        if any(float(v) != 0.0 for v in self.mount_offset_m):
            raise ParamError(
                f"camera.mount_offset_m: {list(self.mount_offset_m)} is not supported by the "
                "companion yet (the camera's optical centre must be at the body origin)")
        if any(float(v) != 0.0 for v in self.mount_rpy_rad[:2]):
            raise ParamError(
                f"camera.mount_rpy_rad: {list(self.mount_rpy_rad)}: a tilted camera (roll or "
                "pitch) is not supported by the companion yet; only a turn about the optical "
                "axis (the third value, yaw) is")

    @property
    def mount_yaw_rad(self) -> float:
        """The camera's turn about the body z axis (its optical axis) (rad)."""
        return float(self.mount_rpy_rad[2])

    @property
    def visible_half_m(self) -> float:
        """Half side of the visible area on the image plane (metres): ``u~_b = n~_b``."""
        return 0.5 * self.visible_fraction * min(self.width_px, self.height_px) * self.pixel_size_m

    @property
    def r_v(self) -> float:
        """Radius of the inscribed circle of the visible area, normalised (spec 6)."""
        return self.visible_half_m / self.focal_length_m

    @property
    def visible_bound_report_px(self) -> float:
        """Half side of the visible area in report pixels (the paper's 500 px)."""
        return self.visible_half_m / self.report_pixel_size_m


@dataclass(frozen=True)
class TerminalParams:
    method: str
    p_scale: float = field(default=1.0, metadata=checked(positive))
    # Optional explicit terminal matrices (from an offline LMI design); empty = compute.
    p_matrix: tuple[tuple[float, ...], ...] = ()
    k_matrix: tuple[tuple[float, ...], ...] = ()
    kappa: float = 0.0

    def __post_init__(self) -> None:
        if self.method not in ("dare", "lmi", "given"):
            raise ParamError(
                f"rmpc.terminal.method: {self.method!r} is not 'dare', 'lmi' or 'given'"
            )
        if self.method == "given" and (len(self.p_matrix) != 7 or len(self.k_matrix) != 4):
            raise ParamError("rmpc.terminal: method 'given' needs p_matrix (7x7), k_matrix (4x7)")


@dataclass(frozen=True)
class RmpcParams:
    """The RMPC of spec section 6 with the paper's numbers as defaults (spec section 8)."""

    dt_s: float = field(metadata=checked(positive))
    horizon: int = field(metadata=checked(positive))
    tube_h: float = field(metadata=checked(positive))
    eps: float = field(metadata=checked(positive))
    rho: float = field(metadata=checked(nonneg))
    desired_depth_m: float = field(metadata=checked(positive))
    q_diag: tuple[float, float, float, float, float, float, float]
    r_diag: tuple[float, float, float, float]
    eta_max: tuple[float, float, float, float, float, float, float]
    u_max: tuple[float, float, float, float]
    g_m_s2: float = field(metadata=checked(positive))
    enable_visibility: bool
    enable_tube: bool
    enable_terminal: bool
    recovery_penalty: float = field(metadata=checked(positive))
    # How each step's hard problem is solved (docs/reference/solver.md): "nlp" (the full NLP by
    # nlp_solver, in the solver child process with rmpc.solve_isolation = "process") or "rti"
    # (real-time iteration: one QP from the NLP linearised at the shifted previous solution,
    # solved in-process; a solution the nonlinear check rejects is solved as "nlp").
    # A config written before this key existed says "fatrop"/"ipopt" here: companion.config
    # reads that as solver = "nlp" with that nlp_solver (how such a log replays as flown).
    solver: str
    jit: bool
    cache_dir: str
    max_iter: int = field(metadata=checked(positive))
    terminal: TerminalParams
    # Which image the visibility circle about M(u(n)) constrains: "spec" = p(n) (spec 6 and
    # the paper's (2d); the applied input u(0) is in no row), "causal" = p(n+1), the image
    # taken with the attitude u(n) produces (u(0) checked against the next image).
    visibility_pairing: str = "spec"
    # What the visibility rows keep inside the visible area (docs/reference/visibility.md):
    # "centroid" (the paper's rows: the image of the target's centre) or "corners" (every target
    # corner,
    # its image predicted from s_e, s3 and s4 and the target's known shape).
    visibility: str = "centroid"
    # Depth bound for the corner rows' tightening: the predicted depth never goes below it
    # (imposed as a state bound s3 >= min_depth_m / z* with "corners"), metres.
    min_depth_m: float = field(default=1.0, metadata=checked(positive))
    # Where the yaw error s4 enters the hard rows: "tube" (the paper: in the tube and the
    # terminal set, so a yaw error the yaw-rate bound cannot remove in time makes the problem
    # infeasible) or "cost" (s4 minimised out of those rows: heading only in the cost).
    heading: str = "tube"
    # Target motion over the horizon: "nominal" (the vehicle assumed to turn with the target,
    # v_a and vdot_a fixed parameters) or "planned_yaw" (v_a and vdot_a rotated by the planned
    # yaw, vdot_a with the planned yaw rate: exact for the constant-turn target model).
    target_motion: str = "nominal"
    # L1 weight of the tube and terminal rows' slacks in the soft (recovery) copy; the
    # visibility rows keep recovery_penalty (equal by default; config/paper.toml puts the
    # tube 10x above visibility: docs/records/2026-11-visibility.md section 5).
    recovery_tube_penalty: float = field(default=1.0e3, metadata=checked(positive))
    # Input-rate weight of the soft (recovery) copy only: ``w sum_i ((u_i(n+1) - u_i(n)) /
    # u_max_i)^2`` over the horizon plus the same for u(0) against the input the previous
    # step applied. The soft copy's cost is dominated by the L1 slacks, which leave its input
    # nearly free (it flipped r3 between -1.5 and +1.5 m/s^2 on consecutive steps). A runtime
    # parameter of the compiled soft NLP (no recompilation per value); 0 = off.
    recovery_input_rate_weight: float = field(default=0.0, metadata=checked(nonneg))
    # The soft (recovery) copy's own stage weights and terminal level (None: the hard
    # problem's q_diag and eps). Its terminal ingredients (P, K) are then designed from them
    # (rmpc.terminal.method), so its tube, terminal and visibility rows are those of that
    # design. A stiff q_diag shrinks the terminal set and stretches P's metric, and the soft
    # copy, whose slacks are measured in it, then chases harder from a start it cannot hold;
    # softer weights here keep the engagement as gentle as theirs (config/realistic.toml,
    # docs/records/2026-11-offset-free.md section 4).
    recovery_q_diag: tuple[float, float, float, float, float, float, float] | None = None
    recovery_eps: float | None = None
    # Which tube, visibility and terminal rows the soft copy's slacks relax when it has its
    # own design (recovery_q_diag / recovery_eps): "own" (that design's P, eps and gamma) or
    # "hard" (the hard problem's: the slacks then measure how far the plan is from the hard
    # problem's feasible set, whose reach ends recovery; the soft design keeps the cost) or
    # "own+terminal" (its own rows plus the hard problem's terminal set, scaled to its own
    # terminal level: rmpc_recovery.hard_terminal_row). An old config reads "own", as it flew.
    recovery_rows: str = "own"
    # A second, loaded solver process on stand-by (solve_isolation = "process"): a timeout or
    # a lost solver process promotes it, so the next step solves instead of flying the
    # terminal law while a fresh process loads (~0.6-1 s). ~60 MB and ~0.7 s of CPU once.
    solver_spare: bool = False
    # How far the target's along-track acceleration is extrapolated over the horizon:
    # "linear" (held for the whole horizon) or "box" (held until the predicted speed reaches
    # the vehicle's velocity bound eta_max[4], or the current speed if that is higher; then
    # constant speed). docs/records/2026-11-visibility.md section 5.
    target_speed_extrapolation: str = "linear"
    # The target's corners (N, 2) in its own frame (x forward, y right), metres. Not a config
    # key: companion.config fills it from [target] (used by visibility = "corners").
    target_corners_m: tuple[tuple[float, float], ...] = ()
    # Where the NLP solves run (docs/reference/reliability.md): "process" (a child process the shell
    # kills and replaces when a solve is stuck, i.e. runs past max_solve_time_s on the CPU: a
    # solver that never returns cannot freeze the control loop) or "none" (in the calling thread,
    # unbounded: tests, offline tools). The core itself only runs "none"; the shell builds it.
    solve_isolation: str = "none"
    # Wall-time bound of one RMPC step's solves (hard problem plus soft copy), seconds. A step
    # that exceeds it is abandoned and flies the terminal law ('fallback', status 'timeout'); a
    # solve that waited for the CPU keeps its solver process ('starved'), a stuck one does not.
    max_solve_time_s: float = field(default=0.25, metadata=checked(positive))
    # What max_solve_time_s counts: "wall" (real time: on a vehicle a late command is a missed
    # deadline) or "cpu" (the solver process's own CPU time, per solve: a lockstep simulation
    # waits for every command, so only a solver that never returns must be cut, and a busy
    # machine's descheduling must not cut a finite solve; the wall wait is then only a backstop,
    # max(10 s, 20 x max_solve_time_s)).
    solve_time_clock: str = "wall"
    # The NLP solver of the hard problem ("fatrop", structure-exploiting, or "ipopt"); the
    # soft copy is always solved with ipopt (companion.core.rmpc_nlp.RECOVERY_SOLVER).
    nlp_solver: str = "fatrop"
    # solver = "rti": QPs per step at most (the second and later re-linearised at the previous
    # QP's solution; a third or later only while the plan's excess keeps shrinking) before a
    # plan still violating the nonlinear hard rows by more than rti_tol goes to the full NLP.
    rti_max_qp: int = field(default=2, metadata=checked(positive))
    # solver = "rti": how far a hard row of the nonlinear problem (tube, visibility, terminal:
    # natural units, not squared; state box: state units) may be exceeded by the RTI plan
    # rolled out through the nonlinear model. docs/reference/solver.md says why this value.
    rti_tol: float = field(default=1.0e-6, metadata=checked(positive))
    # solver = "rti": the linearisation's compiled form: "recursion" (the C loops below with
    # H and g by a backward recursion over the stages: ~1/4 of the multiplications; the
    # graph's numbers to ~1e-15), "loops" (C loops over CasADi's stage
    # Jacobians, ~40 KB of code), "graph" (CasADi's matrix operations, ~0.3 MB of code; the
    # same numbers as "loops" bit for bit) or "scalar" (the same numbers to ~1e-15 as ~66 k
    # scalar operations, ~73 s of CPU to compile). A log recorded before this key replays
    # with "graph", the form it flew.
    rti_linearisation: str = "graph"
    # How the soft (recovery) copy is solved when the hard problem fails: "nlp" (ipopt, the
    # full soft NLP) or "rti" (one QP linearised at the shifted previous plan, by the hard
    # RTI's functions compiled for the soft design; a plan its check rejects is solved as
    # "nlp"; needs recovery_rows = "own"). docs/reference/solver.md, "The soft copy's RTI".
    # A log recorded before this key replays with "nlp", as flown.
    recovery_solver: str = "nlp"
    # solver = "rti": a step whose hard QP DAQP finds infeasible (the hard problem linearised at
    # the guess has no solution) goes to "nlp" (the full hard NLP, then the soft copy if that
    # fails: as before) or "soft" (the soft copy directly, the full hard NLP not tried: a
    # linearisation's infeasibility is no proof, measured: the full NLP failed on every such
    # step of the fast circle; docs/reference/solver.md, "The soft copy's RTI").
    rti_infeasible_qp: str = "nlp"
    # The hard NLP's iteration limit (None: max_iter, which then bounds the soft copy's ipopt
    # alone). A hard NLP that converges does so in few iterations (warm-started: median 11,
    # p99 25, 4 of 1554 above 30), one that fails runs ~45 (up to 101) at ~0.6 ms of CPU each
    # before the soft copy solves: docs/reference/solver.md, "The hard NLP's iteration limit".
    hard_max_iter: int | None = None

    def __post_init__(self) -> None:
        if self.visibility_pairing not in ("spec", "causal"):
            raise ParamError(
                f"rmpc.visibility_pairing: {self.visibility_pairing!r} is not 'spec' or 'causal'"
            )
        for key, value, allowed in (
            ("visibility", self.visibility, ("centroid", "corners")),
            ("heading", self.heading, ("tube", "cost")),
            ("target_motion", self.target_motion, ("nominal", "planned_yaw")),
            ("target_speed_extrapolation", self.target_speed_extrapolation,
             ("linear", "box")),
            ("solve_isolation", self.solve_isolation, ("process", "none")),
            ("solve_time_clock", self.solve_time_clock, ("wall", "cpu")),
            ("rti_linearisation", self.rti_linearisation,
             ("recursion", "loops", "graph", "scalar")),
            ("recovery_rows", self.recovery_rows, ("own", "hard", "own+terminal")),
            ("recovery_solver", self.recovery_solver, ("nlp", "rti")),
            ("rti_infeasible_qp", self.rti_infeasible_qp, ("nlp", "soft")),
        ):
            if value not in allowed:
                raise ParamError(
                    f"rmpc.{key}: {value!r} is not one of {', '.join(map(repr, allowed))}"
                )
        if self.visibility == "corners" and len(self.target_corners_m) < 3:
            raise ParamError(
                "rmpc.visibility: 'corners' needs the target's corners (from [target])"
            )
        for name in ("q_diag", "r_diag", "eta_max", "u_max", "recovery_q_diag"):
            for i, v in enumerate(getattr(self, name) or ()):
                if not v > 0:
                    raise ParamError(f"rmpc.{name}[{i}]: must be > 0 (got {v})")
        if not (math.isfinite(self.max_solve_time_s) and self.max_solve_time_s > 0):
            raise ParamError(
                f"rmpc.max_solve_time_s: must be a finite time > 0 s (got {self.max_solve_time_s})"
            )
        if self.recovery_eps is not None and not (
                math.isfinite(self.recovery_eps) and self.recovery_eps > 0):
            raise ParamError(f"rmpc.recovery_eps: must be > 0 (got {self.recovery_eps})")
        if self.solver not in ("nlp", "rti"):
            raise ParamError(f"rmpc.solver: {self.solver!r} is not 'nlp' or 'rti'")
        if self.recovery_solver == "rti" and self.recovery_rows != "own":
            raise ParamError("rmpc.recovery_solver = 'rti' needs rmpc.recovery_rows = 'own' "
                             f"(got {self.recovery_rows!r})")
        if self.nlp_solver not in ("fatrop", "ipopt"):
            raise ParamError(f"rmpc.nlp_solver: {self.nlp_solver!r} is not 'fatrop' or 'ipopt'")
        if self.hard_max_iter is not None and not self.hard_max_iter > 0:
            raise ParamError(f"rmpc.hard_max_iter: must be > 0 (got {self.hard_max_iter})")
        if self.tube_h < 1:
            raise ParamError("rmpc.tube_h: must be >= 1 (X(n) must not shrink below eps)")
        if self.u_max[2] >= self.g_m_s2:
            raise ParamError("rmpc.u_max[2]: must be < g (the thrust must stay positive)")

    @property
    def psidot_max(self) -> float:
        return self.u_max[3]

    @property
    def lipschitz_l(self) -> float:
        """Remark 1: ``L = psidot_max + 1/z*``."""
        return self.psidot_max + 1.0 / self.desired_depth_m


@dataclass(frozen=True)
class ControlParams:
    rate_hz: float = field(metadata=checked(positive))
    hover_thrust: float = field(metadata=checked(unit))
    thrust_min: float = field(metadata=checked(nonneg))
    thrust_max: float = field(metadata=checked(unit))
    # Whose clock stamps frames and telemetry: "receipt" (local monotonic clock on arrival:
    # a real vehicle) or "autopilot" (source stamps: frames and telemetry share the
    # autopilot's boot clock, as the emulator's do; needed in lockstep) or "timesync" (source
    # stamps as "autopilot", and "now" on the autopilot's clock from MAVLink TIMESYNC: what the
    # latency compensation measures the frame's age with; docs/reference/estimator.md).
    time_source: str = "receipt"
    # Offset-free estimator (hover thrust, disturbance) and latency compensation
    # (companion/core/disturbance.py, latency.py; docs/reference/estimator.md).
    estimator: EstimatorParams = field(default_factory=EstimatorParams)
    latency: LatencyParams = field(default_factory=LatencyParams)
    # Tilt-lag lead compensation of the commands (companion/core/lead.py).
    lead: LeadParams = field(default_factory=LeadParams)

    def __post_init__(self) -> None:
        if not self.thrust_min < self.hover_thrust < self.thrust_max:
            raise ParamError("control: need thrust_min < hover_thrust < thrust_max")
        if self.time_source not in ("receipt", "autopilot", "timesync"):
            raise ParamError(f"control.time_source: {self.time_source!r} is not 'receipt', "
                             "'autopilot' or 'timesync'")
        est = self.estimator
        if est.enabled and not est.hover_min <= self.hover_thrust <= est.hover_max:
            raise ParamError(
                f"control.hover_thrust: {self.hover_thrust} is outside control.estimator's "
                f"[hover_min, hover_max] = [{est.hover_min}, {est.hover_max}]")
        if est.hover_max >= self.thrust_max or est.hover_min <= self.thrust_min:
            raise ParamError("control.estimator: need thrust_min < hover_min and "
                             "hover_max < thrust_max")
