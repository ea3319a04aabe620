"""The recovery steps of a flight solved both ways (``rmpc.recovery_solver = "nlp" | "rti"``):
where their time goes and how far the two plans are apart.

    python bench/recovery_solver.py FLIGHT.mcap [FLIGHT.mcap ...]

Three controllers: ``nlp`` (the soft NLP), ``rti`` (the soft RTI, the soft NLP behind it) and
``rti+soft`` (the soft RTI, and ``rmpc.rti_infeasible_qp = "soft"``: a step whose hard QP is
infeasible skips the full hard NLP).

The flight's sequence of solves (its recorded ``(eta0, target)``, captured from a replay as
``bench/solver.py --log`` does) is solved again by two fresh controllers of the flight's
config, in-process (``rmpc.solve_isolation = "none"``): one per value of the key. Both see the
same measurements (open loop: the recorded ones), each its own warm start. Per recovery step
(of the "nlp" controller): the step's thread CPU time, split into the hard attempts (the
hard RTI, the hard NLP failing) and the soft solve (the soft NLP, or the soft RTI and the
soft NLP behind it when its check refused); and, on the steps both flew as recovery, the
difference of the first inputs and the plans' visibility margins (the least radius minus
distance of a corner row over the horizon, :func:`companion.core.rmpc_check.visibility_margin`,
normalised image units; negative: the plan has that corner out).
"""

from __future__ import annotations

import dataclasses
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from bench.solver_parts import capture
from companion.core.design import design_terminal
from companion.core.rmpc import Rmpc, visibility_margin


def _timed(parts: dict[str, float], label: str, fn: Callable[..., Any]) -> Callable[..., Any]:
    def wrapped(*a: Any, **k: Any) -> Any:
        c0 = time.thread_time()
        try:
            return fn(*a, **k)
        finally:
            parts[label] = parts.get(label, 0.0) + time.thread_time() - c0
    return wrapped


VARIANTS = {"nlp": {"recovery_solver": "nlp"}, "rti": {"recovery_solver": "rti"},
            "rti+soft": {"recovery_solver": "rti", "rti_infeasible_qp": "soft"}}
"""The controllers compared: ``rmpc`` keys (``rti+soft``: also ``rmpc.rti_infeasible_qp``)."""


def play(cfg: Any, calls: list[Any], keys: dict[str, str]) -> list[dict[str, Any]]:
    """Each solve of ``calls`` by a controller with the ``rmpc`` ``keys``."""
    rm = dataclasses.replace(cfg.rmpc, solve_isolation="none", **keys)
    design = design_terminal(rm, cfg.camera)
    mpc = Rmpc(rm, cfg.camera, design)
    parts: dict[str, float] = {}
    mpc._hard.solve = _timed(parts, "hard_nlp", mpc._hard.solve)  # type: ignore[method-assign]
    assert mpc._soft is not None
    mpc._soft.solve = _timed(parts, "soft_nlp", mpc._soft.solve)  # type: ignore[method-assign]
    if mpc.soft_rti is not None:
        mpc.soft_rti.step = _timed(parts, "soft_rti", mpc.soft_rti.step)  # type: ignore[method-assign]
    out = []
    for kind, arg in calls:
        if kind == "reset":
            mpc.reset()
            continue
        parts.clear()
        c0 = time.thread_time()
        r = mpc.solve(*arg)
        total = time.thread_time() - c0
        margin = float(np.min(visibility_margin(r, mpc.cfg, cfg.camera, design))) \
            if r.mode == "recovery" else np.nan
        out.append({"result": r, "total": total, **parts, "margin": margin})
    mpc.close()
    return out


def _q(a: list[float]) -> str:
    v = np.array(a) * 1e3
    return f"{np.median(v):7.2f} / {np.percentile(v, 95):7.2f}" if v.size else "   -"


def report(log: Path) -> None:
    calls, cfg, _ = capture(log)
    runs = {k: play(cfg, calls, keys) for k, keys in VARIANTS.items()}
    print(f"{log}: {sum(k == 'solve' for k, _ in calls)} solves")
    for key, steps in runs.items():
        rec = [s for s in steps if s["result"].mode == "recovery"]
        flown = [s for s in rec if "rti-soft: " in s["result"].status
                 and "; nlp: " not in s["result"].status.split("rti-soft: ")[-1]]
        hard = [s["total"] - s.get("soft_nlp", 0.0) - s.get("soft_rti", 0.0) for s in rec]
        print(f"  {key}: {len(rec)} recovery steps "
              f"({len(flown)} flew the soft RTI), "
              f"{sum(s['result'].mode == 'fallback' for s in steps)} fallbacks; "
              f"thread CPU ms median / p95: step {_q([s['total'] for s in rec])}, "
              f"hard attempts {_q(hard)}, soft NLP "
              f"{_q([s['soft_nlp'] for s in rec if 'soft_nlp' in s])}, soft RTI "
              f"{_q([s['soft_rti'] for s in rec if 'soft_rti' in s])}")
    for key in ("rti", "rti+soft"):
        _compare(key, runs["nlp"], runs[key])


def _compare(key: str, nlp: list[dict[str, Any]], other: list[dict[str, Any]]) -> None:
    both = [(a, b) for a, b in zip(nlp, other, strict=True)
            if a["result"].mode == "recovery" and b["result"].mode == "recovery"]
    if not both:
        return
    du = [float(np.max(np.abs(a["result"].u0 - b["result"].u0))) for a, b in both]
    ma, mb = np.array([a["margin"] for a, _ in both]), np.array([b["margin"] for _, b in both])
    print(f"  {key} against nlp, on the {len(both)} steps both flew as recovery: |du0| "
          f"median {np.median(du):.3f}, p95 {np.percentile(du, 95):.3f}, max {max(du):.3f}; "
          f"plan's least visibility margin (normalised image) nlp median {np.median(ma):+.4f} "
          f"min {np.min(ma):+.4f}, {key} median {np.median(mb):+.4f} min {np.min(mb):+.4f}; "
          f"{key} below nlp by > 0.01 on {int(np.sum(mb < ma - 0.01))} steps")


def main(argv: list[str] | None = None) -> int:
    for log in (argv if argv is not None else sys.argv[1:]):
        report(Path(log))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
