"""Build the control law a config asks for (``controller.kind``), behind one interface.

Every kind is a :class:`companion.control.seams.Controller` and flies through the same
pipeline, safety ladder, emulator and report (docs/reference/visibility.md):

- ``rmpc``: the RMPC of spec 6 as configured in [rmpc] (paper.toml: every corner in view);
- ``rmpc-centroid``: the same with the paper's centroid visibility rows;
- ``mpc-novis``: the same MPC with no visibility rows (tube and terminal set kept);
- ``ibvs-pd``: classical moment-based IBVS, a PD on the same virtual-camera moments
  (:mod:`companion.core.ibvs`).
"""

from __future__ import annotations

import dataclasses
import time

from companion.config import CONTROLLER_KINDS, Config
from companion.control.seams import Controller
from companion.control.solve_guard import process_backend
from companion.core.ibvs import IbvsGains, IbvsPd
from companion.core.params import RmpcParams
from companion.core.rmpc import Rmpc
from companion.core.terminal import TerminalDesign

__all__ = ["CONTROLLER_KINDS", "build_controller", "rmpc_params_for"]


def rmpc_params_for(kind: str, rmpc: RmpcParams) -> RmpcParams:
    """The [rmpc] parameters an MPC kind flies with."""
    if kind == "rmpc-centroid":
        return dataclasses.replace(rmpc, enable_visibility=True, visibility="centroid")
    if kind == "mpc-novis":
        return dataclasses.replace(rmpc, enable_visibility=False)
    return rmpc


def build_controller(cfg: Config, terminal: TerminalDesign) -> Controller:
    """The controller of ``cfg.controller.kind`` (compiled solvers come from the cache)."""
    kind = cfg.controller.kind
    if kind == "ibvs-pd":
        c = cfg.controller
        gains = IbvsGains(c.ibvs_lambda_1_s, c.ibvs_kv_1_s, c.ibvs_yaw_gain_1_s,
                          cfg.rmpc.desired_depth_m, cfg.rmpc.u_max, cfg.rmpc.dt_s)
        return IbvsPd(gains, cfg.rmpc.horizon)
    if kind not in CONTROLLER_KINDS:  # config validation makes this unreachable
        raise ValueError(f"controller.kind: {kind!r} is not one of {CONTROLLER_KINDS}")
    params = rmpc_params_for(kind, cfg.rmpc)
    # rmpc.solve_isolation = "process": every step's NLP solves bounded in wall time in a child
    # process (companion.control.solve_guard, docs/reference/reliability.md). With
    # rmpc.solver = "rti" the real-time iteration runs in this process (a bounded QP:
    # docs/reference/solver.md) and the child solves only the steps the RTI hands to the NLP.
    backend = (process_backend(params, cfg.camera, terminal)
               if params.solve_isolation == "process" else None)
    return Rmpc(params, cfg.camera, terminal, clock=time.perf_counter, backend=backend)
