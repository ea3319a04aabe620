"""Ground truth on the wire (docs/reference/wire.md, "Ground truth"): one UTF-8 JSON object per UDP
datagram, for loggers and scoring only (the companion's control path never reads it).

:func:`truth_record` builds the record from the emulator's state; :class:`TruthPublisher`
sends it without ever blocking or raising on the network (failures are counted).
"""

from __future__ import annotations

import logging
import math
import socket
from collections.abc import Sequence
from types import TracebackType
from typing import Any

import numpy as np
import orjson

from sim_bridge import LinkError
from sim_bridge.camera.camera import RenderedFrame
from sim_bridge.physics.agv import AgvState

__all__ = ["TruthPublisher", "truth_record"]

log = logging.getLogger(__name__)

_MAX_DATAGRAM = 65507


def _num(x: float) -> float | None:
    """A JSON-safe float: non-finite values become null."""
    v = float(x)
    return v if math.isfinite(v) else None


def _vec(x: Sequence[float] | np.ndarray) -> list[float | None]:
    # tolist(): the same Python floats as float() of each element, without a numpy scalar each;
    # one sum finds a vector of finite numbers (all of them, nearly always) at once
    v: list[float] = np.asarray(x, dtype=float).reshape(-1).tolist()
    if math.isfinite(sum(v)):  # inf/nan in v make the sum inf/nan (so may an overflow: fine)
        return v  # type: ignore[return-value]
    return [e if math.isfinite(e) else None for e in v]


def _rows(x: np.ndarray) -> list[list[float | None]]:
    """An (n, k) array as n lists (``[_vec(r) for r in x]``), in one ``tolist`` when finite."""
    rows: list[list[float]] = np.asarray(x, dtype=float).reshape(len(x), -1).tolist()
    if math.isfinite(sum(map(sum, rows))):  # as in _vec: one sum finds them all finite
        return rows  # type: ignore[return-value]
    return [_vec(r) for r in rows]


def _dumps(record: dict[str, Any]) -> bytes:
    """``record`` as compact JSON. orjson (~10x json's speed, ~0.1 ms a step less): the same
    values in the shortest round-trip form as json writes them, but exponents unpadded
    (``1e-5`` where json wrote ``1e-05``); both parse to the same floats, and the companion
    logs the bytes once orjson parses them. A non-finite float becomes null, as
    :func:`truth_record` writes it anyway (json refused one: none ever reached it)."""
    return orjson.dumps(record)


def truth_record(
    t_us: int,
    frame_seq: int | None,
    uav_pos_ned_m: Sequence[float] | np.ndarray,
    uav_vel_ned_m_s: Sequence[float] | np.ndarray,
    uav_q_wxyz: Sequence[float] | np.ndarray,
    uav_rates_frd_rad_s: Sequence[float] | np.ndarray,
    agv: AgvState,
    frame: RenderedFrame | None,
    disturbance_accel_ned_m_s2: Sequence[float] | np.ndarray = (0.0, 0.0, 0.0),
    mode: str = "",
    armed: bool = False,
    setpoint_age_s: float | None = None,
) -> dict[str, Any]:
    """The ground-truth record of one step (docs/reference/wire.md), JSON-ready (plain
    floats/lists).

    ``frame`` is the frame rendered at this step (``None``: no frame this step; then
    ``corners_px`` is null and ``target_in_image`` false). ``setpoint_age_s``: seconds since the
    last setpoint (``None`` = none yet -> null). Non-finite numbers become null.
    """
    rec: dict[str, Any] = {
        "t_us": int(t_us),
        "frame_seq": None if frame_seq is None else int(frame_seq),
        "uav": {
            "pos_ned_m": _vec(uav_pos_ned_m),
            "vel_ned_m_s": _vec(uav_vel_ned_m_s),
            "q_wxyz": _vec(uav_q_wxyz),
            "rates_frd_rad_s": _vec(uav_rates_frd_rad_s),
        },
        "agv": {
            "pos_ned_m": _vec(agv.pos_ned_m),
            "vel_ned_m_s": _vec(agv.vel_ned_m_s),
            "acc_ned_m_s2": _vec(agv.acc_ned_m_s2),
            "yaw_rad": _num(agv.yaw_rad),
            "yaw_rate_rad_s": _num(agv.yaw_rate_rad_s),
        },
        "corners_px": None,
        "top_corners_px": None,
        "target_in_image": False,
        "disturbance_accel_ned_m_s2": _vec(disturbance_accel_ned_m_s2),
        "mode": str(mode),
        "armed": bool(armed),
        "setpoint_age_s": None if setpoint_age_s is None else _num(setpoint_age_s),
    }
    if frame is not None:
        rec["corners_px"] = _rows(frame.corners_px)
        rec["top_corners_px"] = _rows(frame.top_corners_px)
        rec["target_in_image"] = bool(frame.target_in_image)
    return rec


class TruthPublisher:
    """Sends ground-truth records as UDP JSON datagrams to ``host:port``.

    Non-blocking: :meth:`publish` never raises on a network error (no listener, full buffer),
    it counts it in :attr:`errors` and returns ``False``. Use as a (sync) context manager or
    call :meth:`close`.
    """

    def __init__(self, host: str, port: int) -> None:
        self.address = (host, port)
        self.sent = 0
        self.errors = 0
        try:
            self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            self._sock.setblocking(False)
        except OSError as e:
            raise LinkError(f"ground truth: cannot open a UDP socket: {e}") from e

    def publish(self, record: dict[str, Any]) -> bool:
        """Send one record; ``True`` if the datagram left, ``False`` (counted) otherwise."""
        try:
            data = _dumps(record)
            if len(data) > _MAX_DATAGRAM:
                raise ValueError(f"record of {len(data)} bytes exceeds one datagram")
            self._sock.sendto(data, self.address)
        except (OSError, ValueError, TypeError) as e:
            self.errors += 1
            if self.errors in (1, 10, 100) or self.errors % 1000 == 0:
                log.warning(
                    "ground truth to %s:%d failed (%d so far): %s", *self.address, self.errors, e
                )
            return False
        self.sent += 1
        return True

    def close(self) -> None:
        self._sock.close()

    def __enter__(self) -> TruthPublisher:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()
