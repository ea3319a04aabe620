"""What a ground station needs from the vehicle beyond telemetry and commands: the parameter
protocol and an (empty) mission store, answered on every link as PX4 does.

* Parameters (https://mavlink.io/en/services/parameter.html, PX4 ``mavlink_parameters.cpp``):
  PARAM_REQUEST_LIST -> one PARAM_VALUE per parameter (index, count); PARAM_REQUEST_READ by
  name, or by index when ``param_index >= 0``; PARAM_SET -> the parameter's PARAM_VALUE
  echoed back with the value now in force. Like PX4, integer parameters travel
  byte-wise: the int32's four bytes reinterpreted as the float32 ``param_value``
  (MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE). Unknown names and indices get no answer
  (PX4 sends none either). A set outside a parameter's range is refused: the echo carries the
  unchanged value.
* Missions (https://mavlink.io/en/services/mission.html): no mission is stored.
  MISSION_REQUEST_LIST -> MISSION_COUNT 0 (of the requested mission type); MISSION_CLEAR_ALL
  -> MISSION_ACK accepted; an upload (MISSION_COUNT) of 0 items -> accepted, of more ->
  MAV_MISSION_UNSUPPORTED.

:class:`ParamStore` is pure (no sockets); :class:`GcsServices` is the thin part that reads
the messages and answers on the link they came from.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

PARAM_TYPE_INT32 = 6   # MAV_PARAM_TYPE_INT32
PARAM_TYPE_REAL32 = 9  # MAV_PARAM_TYPE_REAL32
MISSION_ACCEPTED = 0
MISSION_UNSUPPORTED = 3


@dataclass(frozen=True)
class ParamSpec:
    """One parameter: PX4's name (at most 16 characters), type and allowed range."""

    name: str
    type_id: int
    default: float
    min_value: float = -math.inf
    max_value: float = math.inf

    def __post_init__(self) -> None:
        if not 0 < len(self.name) <= 16:
            raise ValueError(f"param {self.name!r}: name must be 1..16 characters")
        if self.type_id not in (PARAM_TYPE_INT32, PARAM_TYPE_REAL32):
            raise ValueError(f"param {self.name}: type must be INT32 or REAL32")


def to_wire(type_id: int, value: float) -> float:
    """The float32 ``param_value`` carrying ``value`` (byte-wise for INT32)."""
    if type_id == PARAM_TYPE_INT32:
        f: float = struct.unpack("<f", struct.pack("<i", int(value)))[0]
        return f
    return float(value)


def from_wire(type_id: int, wire: float) -> float:
    """Inverse of :func:`to_wire`."""
    if type_id == PARAM_TYPE_INT32:
        i: int = struct.unpack("<i", struct.pack("<f", wire))[0]
        return float(i)
    return float(wire)


class ParamStore:
    """The vehicle's parameters, in a fixed order (the index of the protocol)."""

    def __init__(self, specs: tuple[ParamSpec, ...],
                 on_change: Callable[[str, float], None] | None = None) -> None:
        names = [s.name for s in specs]
        if len(set(names)) != len(names):
            raise ValueError("param names must be unique")
        self.specs = specs
        self._index = {s.name: i for i, s in enumerate(specs)}
        self.values = [float(s.default) for s in specs]
        self._on_change = on_change

    def __len__(self) -> int:
        return len(self.specs)

    def index_of(self, name: str) -> int | None:
        return self._index.get(name)

    def value(self, name: str) -> float:
        return self.values[self._index[name]]

    def set(self, name: str, value: float) -> tuple[int, bool] | None:
        """Set ``name`` (a decoded value); returns (index, whether it was accepted), or None
        for an unknown name."""
        i = self._index.get(name)
        if i is None:
            return None
        spec = self.specs[i]
        if spec.type_id == PARAM_TYPE_INT32:
            value = float(round(value)) if math.isfinite(value) else value
        if not (math.isfinite(value) and spec.min_value <= value <= spec.max_value):
            return i, False
        changed = value != self.values[i]
        self.values[i] = value
        if changed and self._on_change is not None:
            self._on_change(name, value)
        return i, True


def _param_id(raw: Any) -> str:
    if isinstance(raw, bytes):
        raw = raw.decode("ascii", "replace")
    return str(raw).split("\x00", 1)[0]


class GcsServices:
    """Answers the parameter and mission protocols for the link a request came from.
    ``handle`` returns whether it took the message."""

    def __init__(self, params: ParamStore) -> None:
        self.params = params
        self.param_values_sent = 0
        self.param_sets = 0

    def handle(self, link: Any, msg: Any, addr: tuple[str, int]) -> bool:
        mtype = msg.get_type()
        if mtype == "PARAM_REQUEST_LIST":
            for i in range(len(self.params)):
                self._send_param(link, i, None)  # to every peer, as PX4 broadcasts them
            return True
        if mtype == "PARAM_REQUEST_READ":
            i = int(msg.param_index)
            if i < 0:
                found = self.params.index_of(_param_id(msg.param_id))
                i = -1 if found is None else found
            if 0 <= i < len(self.params):
                self._send_param(link, i, addr)
            return True
        if mtype == "PARAM_SET":
            name = _param_id(msg.param_id)
            j = self.params.index_of(name)
            if j is None:
                return True
            spec = self.params.specs[j]
            res = self.params.set(name, from_wire(spec.type_id, float(msg.param_value)))
            self.param_sets += 1
            if res is not None:
                self._send_param(link, res[0], None)  # PX4 announces changes to all
            return True
        src = (msg.get_srcSystem(), msg.get_srcComponent())
        if mtype == "MISSION_REQUEST_LIST":
            link.send(link.mav.mission_count_encode(*src, 0, int(msg.mission_type)), addr)
            return True
        if mtype == "MISSION_CLEAR_ALL":
            link.send(link.mav.mission_ack_encode(*src, MISSION_ACCEPTED,
                                                  int(msg.mission_type)), addr)
            return True
        if mtype == "MISSION_COUNT":
            result = MISSION_ACCEPTED if int(msg.count) == 0 else MISSION_UNSUPPORTED
            link.send(link.mav.mission_ack_encode(*src, result, int(msg.mission_type)), addr)
            return True
        return False

    def _send_param(self, link: Any, i: int, addr: tuple[str, int] | None) -> None:
        spec = self.params.specs[i]
        link.send(link.mav.param_value_encode(
            spec.name.encode("ascii"), to_wire(spec.type_id, self.params.values[i]),
            spec.type_id, len(self.params), i), addr)
        self.param_values_sent += 1
