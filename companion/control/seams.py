"""The typed seams of the control loop: what a pipeline takes, as ``Protocol``s.

A frame's path, read top to bottom (and followed by mypy)::

    FrameSource  --CameraFrame-->  Perceiver  --PerceptionResult-->  (core: moments, error
    state)  --eta_e, TargetMotion-->  Controller  --RmpcResult (u0)-->  setpoint -> MAVLink

- :class:`FrameSource`: :class:`companion.camera.CameraSource` and every camera source
  (``async with source: async for frame in source``).
- :class:`Perceiver`: :class:`companion.perception.Perception` (pixels -> target corners).
- :class:`Controller`: :class:`companion.core.rmpc.Rmpc` and any other control law flown
  through the same pipeline; it maps the error state and the predicted target motion to an
  input ``u0 = (ax, ay, az, yaw_rate)`` (virtual frame, m/s^2 and rad/s) with its status.
"""

from __future__ import annotations

from collections.abc import AsyncIterator
from types import TracebackType
from typing import TYPE_CHECKING, Protocol, Self, runtime_checkable

import numpy as np
from numpy.typing import ArrayLike

from companion.core.rmpc import RmpcResult, TargetMotion
from companion.perception import PerceptionResult

if TYPE_CHECKING:  # (the camera package loads asyncio and the capture back-ends: a replay
    # needs neither)
    from companion.camera import CameraFrame


@runtime_checkable
class FrameSource(Protocol):
    """An async source of camera frames (newest first when the consumer falls behind)."""

    async def __aenter__(self) -> Self: ...

    async def __aexit__(self, exc_type: type[BaseException] | None,
                        exc: BaseException | None, tb: TracebackType | None) -> None: ...

    def __aiter__(self) -> AsyncIterator[CameraFrame]: ...


@runtime_checkable
class Perceiver(Protocol):
    """Pixels -> the target's corners (raw pixels and metric image coordinates)."""

    def process(self, image: np.ndarray) -> PerceptionResult: ...


@runtime_checkable
class Controller(Protocol):
    """Error state ``eta_e`` (7,) and the target's predicted motion -> the input to apply.

    ``solve`` never raises on a failed solve: the result's ``mode`` says what happened
    (``"optimal"``, ``"recovery"``, ``"fallback"``...) and ``u0`` is always finite.
    ``reset`` forgets warm starts (a new engagement)."""

    def solve(self, eta0: ArrayLike, target: TargetMotion) -> RmpcResult: ...

    def reset(self) -> None: ...
