"""Schemas of every MCAP channel the companion writes.

Camera frames are Foxglove's protobuf messages (schema encoding ``protobuf``, the schema a
serialized ``FileDescriptorSet`` from ``foxglove-schemas-protobuf``): image bytes go into the
file as they are, with no base64 step, and MCAP's chunk compression does the rest. Every other
channel is JSON (schema encoding ``jsonschema``, message encoding ``json``). The JSON forms of
the two image schemas below are kept so logs written before frames moved to protobuf still read.

Foxglove's well-known schemas (``foxglove.CompressedImage``, ``foxglove.RawImage``,
``foxglove.Log``, ``foxglove.FrameTransform``, ``foxglove.PoseInFrame``) are written with their
registry names so Foxglove shows images, logs and the 3-D scene without configuration; binary
fields are base64 strings (``contentEncoding: base64``), times are ``{sec, nsec}``.
Our own schemas are named ``companion.*``; MAVLink channels get one schema per message type,
``companion.mavlink.<NAME>``, generated from pymavlink's message definitions.
"""

from __future__ import annotations

import functools
import json
from collections.abc import Mapping
from typing import Any

from companion import CompanionError

SCHEMA_ENCODING = "jsonschema"
MESSAGE_ENCODING = "json"
PROTOBUF_ENCODING = "protobuf"  # both the schema and the message encoding of protobuf channels

COMPRESSED_IMAGE = "foxglove.CompressedImage"
RAW_IMAGE = "foxglove.RawImage"
LOG = "foxglove.Log"
FRAME_TRANSFORM = "foxglove.FrameTransform"
POSE_IN_FRAME = "foxglove.PoseInFrame"
MAVLINK_PREFIX = "companion.mavlink."
PERCEPTION = "companion.Perception"
CONTROLLER_STEP = "companion.ControllerStep"
SAFETY_TRANSITION = "companion.SafetyTransition"
CONFIG = "companion.Config"
MAVLINK_REJECTED = "companion.MavlinkRejected"
JSON = "companion.Json"
MAVLINK_STATS = "companion.MavlinkStats"

#: foxglove.Log levels
LOG_LEVELS: Mapping[str, int] = {
    "UNKNOWN": 0,
    "DEBUG": 1,
    "INFO": 2,
    "WARNING": 3,
    "ERROR": 4,
    "FATAL": 5,
}


class SchemaError(CompanionError):
    """An unknown schema name."""


def _time(desc: str) -> dict[str, Any]:
    return {
        "type": "object",
        "title": "time",
        "description": desc,
        "properties": {
            "sec": {"type": "integer", "minimum": 0},
            "nsec": {"type": "integer", "minimum": 0, "maximum": 999_999_999},
        },
    }


def _vec3(title: str, desc: str) -> dict[str, Any]:
    return {
        "type": "object",
        "title": title,
        "description": desc,
        "properties": {k: {"type": "number"} for k in ("x", "y", "z")},
    }


def _quat(desc: str) -> dict[str, Any]:
    return {
        "type": "object",
        "title": "foxglove.Quaternion",
        "description": desc + " (x, y, z, w)",
        "properties": {k: {"type": "number"} for k in ("x", "y", "z", "w")},
    }


def _obj(title: str, desc: str, props: dict[str, Any], **extra: Any) -> dict[str, Any]:
    return {"title": title, "description": desc, "type": "object", "properties": props, **extra}


_STR = {"type": "string"}
_INT = {"type": "integer"}
_NUM = {"type": "number"}
_B64 = {"type": "string", "contentEncoding": "base64"}


def _arr(item: dict[str, Any], n: int | None = None) -> dict[str, Any]:
    out: dict[str, Any] = {"type": "array", "items": item}
    if n is not None:
        out["minItems"] = out["maxItems"] = n
    return out


_STATIC: dict[str, dict[str, Any]] = {
    COMPRESSED_IMAGE: _obj(
        COMPRESSED_IMAGE,
        "A compressed image",
        {
            "timestamp": _time("Timestamp of image"),
            "frame_id": _STR,
            "data": _B64,
            "format": {**_STR, "description": "Image format: jpeg or png"},
        },
    ),
    RAW_IMAGE: _obj(
        RAW_IMAGE,
        "A raw image",
        {
            "timestamp": _time("Timestamp of image"),
            "frame_id": _STR,
            "width": {"type": "integer", "minimum": 0},
            "height": {"type": "integer", "minimum": 0},
            "encoding": {**_STR, "description": "mono8, bgr8 or rgb8"},
            "step": {"type": "integer", "minimum": 0, "description": "bytes per row"},
            "data": _B64,
        },
    ),
    LOG: _obj(
        LOG,
        "A log message",
        {
            "timestamp": _time("Timestamp of log message"),
            "level": {
                "description": "Log level",
                "oneOf": [{"title": k, "const": v} for k, v in LOG_LEVELS.items()],
            },
            "message": _STR,
            "name": _STR,
            "file": _STR,
            "line": {"type": "integer", "minimum": 0},
        },
    ),
    FRAME_TRANSFORM: _obj(
        FRAME_TRANSFORM,
        "A transform between two reference frames in 3D space",
        {
            "timestamp": _time("Timestamp of transform"),
            "parent_frame_id": _STR,
            "child_frame_id": _STR,
            "translation": _vec3("foxglove.Vector3", "Translation of the child in the parent (m)"),
            "rotation": _quat("Rotation of the child frame relative to the parent"),
        },
    ),
    POSE_IN_FRAME: _obj(
        POSE_IN_FRAME,
        "A timestamped pose in a reference frame",
        {
            "timestamp": _time("Timestamp of pose"),
            "frame_id": _STR,
            "pose": _obj(
                "foxglove.Pose",
                "Pose in 3D space",
                {
                    "position": _vec3("foxglove.Vector3", "Position (m)"),
                    "orientation": _quat("Orientation"),
                },
            ),
        },
    ),
    PERCEPTION: _obj(
        PERCEPTION,
        "One camera frame's perception result (fields from companion.perception; units in names)",
        {"t_us": _INT, "frame_seq": _INT, "detected": {"type": "boolean"}},
        additionalProperties=True,
    ),
    CONTROLLER_STEP: _obj(
        CONTROLLER_STEP,
        "One control step: state, RMPC solve status, command sent (units in field names)",
        {"t_us": _INT, "success": {"type": "boolean"}, "status": _STR,
         "t_now_s": {"type": ["number", "null"],
                     "description": "when the step ran, on the frames' time base (s)"},
         "in_control": {"type": ["boolean", "null"],
                        "description": "our setpoints fly the vehicle (estimator input)"},
         "estimator": {"type": ["object", "null"], "description":
                       "offset-free estimator (docs/reference/estimator.md): hover_thrust, "
                       "d_ned_m_s2 (m/s^2, NED), hover_std, d_std_m_s2, updates, rejected, "
                       "innovation_m_s, reason",
                       "properties": {"hover_thrust": _NUM,
                                      "d_ned_m_s2": {"type": "array", "items": _NUM}}},
         "latency": {"type": ["object", "null"], "description":
                     "latency compensation: frame_age_s, horizon_s, clipped, eta_pred"}},
        additionalProperties=True,
    ),
    SAFETY_TRANSITION: _obj(
        SAFETY_TRANSITION,
        "A safety supervisor state change",
        {"t_us": _INT, "from_state": _STR, "to_state": _STR, "reason": _STR},
        additionalProperties=True,
    ),
    CONFIG: _obj(
        CONFIG,
        "The configuration this run used, written once at start",
        {"source": _STR, "toml": _STR, "config": {"type": "object"}},
    ),
    MAVLINK_REJECTED: _obj(
        MAVLINK_REJECTED,
        "A received MAVLink frame the link rejected, and why",
        {
            "reason": _STR,
            "raw_b64": {**_B64, "description": "the rejected bytes"},
            "t_rx_ns": {**_INT, "description": "link clock at receipt (ns)"},
        },
    ),
    MAVLINK_STATS: _obj(
        MAVLINK_STATS,
        "The MAVLink link's receive/send counters since it opened (cumulative), and the "
        "addresses the autopilot and the AGV are pinned to",
        {
            "counters": {"type": "object", "additionalProperties": _INT,
                         "description": "rx_datagrams, rx_accepted, rejected, one per reason "
                                        "(spoofed_source, rate_limited, bad_data, ...), tx_frames"},
            "pinned": {"type": "object", "additionalProperties": _STR,
                       "description": "sysid -> host:port"},
            "stale_dropped": {**_INT, "description": "frames/messages refused as stale"},
        },
        additionalProperties=True,
    ),
    JSON: _obj(JSON, "Free-form JSON object", {}, additionalProperties=True),
}


_MAV_TYPES: dict[str, dict[str, Any]] = {
    "float": {"type": ["number", "null"]}, "double": {"type": ["number", "null"]}, "char": _STR,
    **{t: _INT for t in ("int8_t", "uint8_t", "int16_t", "uint16_t", "int32_t", "uint32_t",
                         "int64_t", "uint64_t", "uint8_t_mavlink_version")},
}  # fmt: skip


@functools.cache
def mavlink_schema(name: str) -> dict[str, Any]:
    """Schema ``companion.mavlink.<name>``: ``fields`` typed from pymavlink's definition, plus
    the raw frame (base64), the link clock at receipt/sending and the source ids."""
    from pymavlink.dialects.v20 import common as mavlink2

    msgid = getattr(mavlink2, f"MAVLINK_MSG_ID_{name}", None)
    if msgid is None:
        raise SchemaError(f"unknown MAVLink message {name!r}")
    cls = mavlink2.mavlink_map[msgid]
    fields: dict[str, Any] = {}
    units = getattr(cls, "fieldunits_by_name", {})
    for fname, ftype, alen in zip(cls.fieldnames, cls.fieldtypes, cls.array_lengths, strict=True):
        base = _MAV_TYPES.get(ftype, {})
        prop = dict(base) if (alen == 0 or ftype == "char") else _arr(base, alen)
        if units.get(fname):
            prop["description"] = f"[{units[fname]}]"
        fields[fname] = prop
    return _obj(
        MAVLINK_PREFIX + name,
        f"MAVLink {name} (#{msgid}); NaN/inf are written as null",
        {
            "t_rx_ns": {**_INT, "description": "link clock at receipt (ns)"},
            "t_tx_ns": {**_INT, "description": "link clock at sending (ns)"},
            "sysid": _INT,
            "compid": _INT,
            "seq": _INT,
            "signed": {"type": "boolean"},
            "raw_b64": {**_B64, "description": "the whole MAVLink 2 frame as on the wire"},
            "fields": _obj(name, "decoded fields", fields),
        },
    )


def known(name: str) -> bool:
    """True when :func:`schema` can produce ``name``."""
    if name in _STATIC:
        return True
    if name.startswith(MAVLINK_PREFIX):
        try:
            mavlink_schema(name[len(MAVLINK_PREFIX) :])
        except SchemaError:
            return False
        return True
    return False


def schema(name: str) -> dict[str, Any]:
    """The JSON schema called ``name`` (a copy-safe dict; do not mutate)."""
    if name in _STATIC:
        return _STATIC[name]
    if name.startswith(MAVLINK_PREFIX):
        return mavlink_schema(name[len(MAVLINK_PREFIX) :])
    raise SchemaError(f"unknown schema {name!r}; known: {sorted(_STATIC)} and {MAVLINK_PREFIX}*")


def schema_bytes(name: str) -> bytes:
    """UTF-8 JSON text of :func:`schema` (the MCAP Schema record's data)."""
    return json.dumps(schema(name), separators=(",", ":")).encode()


#: Schemas written as protobuf (camera frames), not JSON.
PROTOBUF_SCHEMAS = frozenset({COMPRESSED_IMAGE, RAW_IMAGE})


@functools.cache
def protobuf_class(name: str) -> Any:
    """The generated protobuf message class of a :data:`PROTOBUF_SCHEMAS` name."""
    if name == COMPRESSED_IMAGE:
        from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage

        return CompressedImage
    if name == RAW_IMAGE:
        from foxglove_schemas_protobuf.RawImage_pb2 import RawImage

        return RawImage
    raise SchemaError(f"no protobuf schema {name!r}; known: {sorted(PROTOBUF_SCHEMAS)}")


@functools.cache
def protobuf_schema_bytes(name: str) -> bytes:
    """The MCAP Schema record's data for a protobuf channel: a serialized FileDescriptorSet of the
    message's .proto file and its dependencies (dependencies first), as Foxglove expects."""
    from google.protobuf.descriptor_pb2 import FileDescriptorSet

    fds = FileDescriptorSet()
    seen: set[str] = set()

    def add(fd: Any) -> None:
        for dep in fd.dependencies:
            if dep.name not in seen:
                add(dep)
        seen.add(fd.name)
        fd.CopyToProto(fds.file.add())

    add(protobuf_class(name).DESCRIPTOR.file)
    return bytes(fds.SerializeToString())


def encodings(name: str) -> tuple[str, str]:
    """(schema encoding, message encoding) the companion writes ``name`` with."""
    if name in PROTOBUF_SCHEMAS:
        return PROTOBUF_ENCODING, PROTOBUF_ENCODING
    return SCHEMA_ENCODING, MESSAGE_ENCODING


def static_names() -> tuple[str, ...]:
    return tuple(_STATIC)
