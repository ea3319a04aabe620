"""``[perception]``: the companion's detector tuning (the emulator ignores it); a module of
its own so that :mod:`companion.config` stays a small room (the names are re-exported there)."""

from __future__ import annotations

from dataclasses import dataclass

from companion import ConfigError

__all__ = ["RECTANGLE_EDGES", "PerceptionConfig"]


@dataclass(frozen=True)
class PerceptionConfig:
    """Optional table ``[perception]``: the companion's detector tuning (the emulator ignores
    it). ``rectangle_threshold``: 0 = the rectangle detector's grey threshold is chosen per
    frame between the ground's median and the brightest region's level (follows exposure and
    light changes); 1..254 = that fixed grey level. ``rectangle_level_fraction``: where the
    per-frame threshold sits between the ground's median (0) and the top's level (1).
    ``rectangle_edges``: how the rectangle's sub-pixel edges are measured: "lean2" (the
    default since 2026-11-28: "lean"'s measure with fewer numpy calls and about one pass a
    tracked frame), "lean" (tracking from the previous corners, three passes) or "profiles"
    (the detector before both; a log recorded without this key replays with it, see
    ``companion.replay``; a log records the method it flew). ``compiled_edges``: "lean2"'s
    refinement as one compiled C call (built once with the system's C compiler, cached with
    the RMPC's libraries; the same numbers bit for bit, checked against the numpy path when a
    process loads it); false, or no compiler: the numpy path."""

    rectangle_threshold: int = 0
    rectangle_level_fraction: float = 0.7
    rectangle_edges: str = "lean2"
    compiled_edges: bool = True

    def __post_init__(self) -> None:
        if not 0 <= self.rectangle_threshold <= 254:
            raise ConfigError(
                f"perception.rectangle_threshold: {self.rectangle_threshold} is not 0 (adaptive)"
                " or a grey level in 1..254")
        if not 0.3 <= self.rectangle_level_fraction <= 0.9:
            raise ConfigError(
                f"perception.rectangle_level_fraction: {self.rectangle_level_fraction} is not in"
                " [0.3, 0.9]")
        if self.rectangle_edges not in RECTANGLE_EDGES:
            raise ConfigError(
                f"perception.rectangle_edges: {self.rectangle_edges!r} is not one of"
                f" {', '.join(map(repr, RECTANGLE_EDGES))}")


RECTANGLE_EDGES = ("lean2", "lean", "profiles")
"""The rectangle detector's edge methods (``companion.perception.rectangle.EDGE_METHODS``)."""
