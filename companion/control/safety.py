"""Safety supervisor: which kind of command the control loop may send now.

Pure logic with explicit time. Fallback order (issue: the companion process, Safety):

1. ``TRACKING``   every input healthy: the RMPC's input (its ``recovery`` mode is normal
                  operation, not a failure).
2. ``REACQUIRE``  the target is out of sight but FOLLOW_TARGET is fresh: follow its predicted
                  position and climb within limits to widen the view.
3. ``TERMINAL``   something is unhealthy (solver failure, target lost with no FOLLOW_TARGET)
                  but the error state is still valid: the terminal law ``K eta + Gamma``.
4. ``HOVER``      after ``hover_fallback_s`` of trouble, or at once when the state itself is
                  invalid (stale telemetry, non-finite values): a hover setpoint at the last
                  valid yaw, built from no current measurement: zero acceleration through the
                  offset-free estimate as it stood (bounded, from data that passed its checks:
                  the estimated hover thrust, tilted against the estimated disturbance), or
                  level at the configured hover thrust with the estimator off.
5. ``SILENT``     after ``silence_after_s``: stop streaming, so PX4's own offboard-loss
                  failsafe (COM_OBL_RC_ACT) takes over.

The loop returns to ``TRACKING`` as soon as the inputs are healthy again.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass

from companion.config import SafetyConfig


class SafetyLevel(enum.Enum):
    TRACKING = "tracking"
    REACQUIRE = "reacquire"
    TERMINAL = "terminal"
    HOVER = "hover"
    SILENT = "silent"


@dataclass(frozen=True)
class Health:
    """One control tick's view of its inputs (ages in seconds, ``inf`` if never seen)."""

    t_s: float
    telemetry_age_s: float
    target_age_s: float
    follow_target_age_s: float
    inputs_finite: bool
    solver_ok: bool


@dataclass(frozen=True)
class SafetyDecision:
    level: SafetyLevel
    reason: str
    changed: bool


class SafetySupervisor:
    def __init__(self, cfg: SafetyConfig) -> None:
        self._cfg = cfg
        self.level = SafetyLevel.TRACKING
        self.reason = "start"
        self._trouble_since: float | None = None
        self._last: SafetyDecision | None = None  # the last unchanged decision (reused)

    def state_valid(self, h: Health) -> bool:
        """The measured error state can be trusted (fresh, finite telemetry and target)."""
        return (
            h.inputs_finite
            and h.telemetry_age_s <= self._cfg.telemetry_timeout_s
            and h.target_age_s <= self._cfg.target_lost_timeout_s
        )

    def update(self, h: Health) -> SafetyDecision:
        cfg = self._cfg
        telemetry_ok = h.inputs_finite and h.telemetry_age_s <= cfg.telemetry_timeout_s
        target_ok = h.target_age_s <= cfg.target_lost_timeout_s
        follow_ok = h.follow_target_age_s <= cfg.follow_target_timeout_s
        if telemetry_ok and target_ok and h.solver_ok:
            self._trouble_since = None
            return self._set(SafetyLevel.TRACKING, "inputs healthy")
        if telemetry_ok and not target_ok and follow_ok:
            self._trouble_since = None
            return self._set(
                SafetyLevel.REACQUIRE,
                f"target not seen for {h.target_age_s:.2f} s; following FOLLOW_TARGET",
            )
        if self._trouble_since is None:
            self._trouble_since = h.t_s
        elapsed = h.t_s - self._trouble_since
        why = _describe(h, cfg, telemetry_ok, target_ok, follow_ok)
        if elapsed >= cfg.silence_after_s:
            return self._set(SafetyLevel.SILENT, f"{why} for {elapsed:.2f} s: stop streaming")
        if elapsed >= cfg.hover_fallback_s or not telemetry_ok:
            return self._set(SafetyLevel.HOVER, f"{why}: level hover")
        if not target_ok:
            # Target lost and no FOLLOW_TARGET: the error state is a guess, not a measurement.
            return self._set(SafetyLevel.HOVER, f"{why}: level hover")
        return self._set(SafetyLevel.TERMINAL, f"{why}: terminal law")

    def _set(self, level: SafetyLevel, reason: str) -> SafetyDecision:
        last = self._last
        if (last is not None and level is last.level is self.level and reason == last.reason
                and reason == self.reason):
            return last  # the same decision as the step before (frozen: shared, not rebuilt)
        changed = level is not self.level
        self.level = level
        self.reason = reason
        decision = SafetyDecision(level, reason, changed)
        self._last = None if changed else decision
        return decision


def _describe(
    h: Health, cfg: SafetyConfig, telemetry_ok: bool, target_ok: bool, follow_ok: bool
) -> str:
    parts = []
    if not h.inputs_finite:
        parts.append("non-finite input")
    if h.telemetry_age_s > cfg.telemetry_timeout_s:
        parts.append(f"telemetry stale ({h.telemetry_age_s:.2f} s)")
    if not target_ok:
        parts.append(f"target lost ({h.target_age_s:.2f} s)")
        if not follow_ok:
            parts.append("FOLLOW_TARGET stale")
    if not h.solver_ok:
        parts.append("solver failed")
    del telemetry_ok
    return ", ".join(parts) or "unhealthy"
