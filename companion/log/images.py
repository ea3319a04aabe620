"""Pictures of logged image messages: foxglove.CompressedImage / RawImage, as protobuf (the
writer's encoding) or JSON with base64 data (older logs). A message that does not decode gives
``None`` and a warning, never an exception (the reader salvages what it can).
"""

from __future__ import annotations

import base64
import logging
from typing import Any

import numpy as np

from companion.log import schemas as sch
from companion.log.encode import decode_json
from companion.log.png_fast import read_png

log = logging.getLogger(__name__)

def image_from_raw(schema_name: str, message_encoding: str, raw: bytes) -> np.ndarray | None:
    """The picture of a stored image message (protobuf, or JSON from older logs), or None."""
    if message_encoding == sch.PROTOBUF_ENCODING:
        return decode_protobuf_image(schema_name, raw)[1]
    try:
        msg = decode_json(raw)
    except ValueError:
        return None
    return decode_image(schema_name, msg) if isinstance(msg, dict) else None


def decode_protobuf_image(
    schema_name: str, raw: bytes
) -> tuple[dict[str, Any] | None, np.ndarray | None]:
    """(fields without ``data``, picture) of a protobuf foxglove.CompressedImage / RawImage;
    (None, None) when the bytes do not parse."""
    from google.protobuf.message import DecodeError

    try:
        msg = sch.protobuf_class(schema_name).FromString(raw)
    except DecodeError as e:
        log.warning("undecodable %s: %s", schema_name, e)
        return None, None
    fields: dict[str, Any] = {
        "timestamp": {"sec": msg.timestamp.seconds, "nsec": msg.timestamp.nanos},
        "frame_id": msg.frame_id,
    }
    if schema_name == sch.COMPRESSED_IMAGE:
        fields["format"] = msg.format
    else:
        fields.update(width=msg.width, height=msg.height, encoding=msg.encoding, step=msg.step)
    return fields, _image_from_bytes(schema_name, fields, msg.data)


def decode_image(schema_name: str, msg: dict[str, Any]) -> np.ndarray | None:
    """The picture of a decoded foxglove.CompressedImage / RawImage JSON message, or None."""
    try:
        buf = base64.b64decode(msg.get("data", ""), validate=True)
    except (ValueError, TypeError) as e:
        log.warning("undecodable image: %s", e)
        return None
    return _image_from_bytes(schema_name, msg, buf)


def _image_from_bytes(schema_name: str, msg: dict[str, Any], buf: bytes) -> np.ndarray | None:
    import cv2

    try:
        if schema_name == sch.COMPRESSED_IMAGE:
            img = read_png(buf) if buf[:4] == b"\x89PNG" else None  # ours: the fast way
            if img is not None:
                return img
            img = cv2.imdecode(np.frombuffer(buf, np.uint8), cv2.IMREAD_UNCHANGED)
            return img if isinstance(img, np.ndarray) else None
        h, w, step = int(msg["height"]), int(msg["width"]), int(msg["step"])
        ch = {"mono8": 1, "bgr8": 3, "rgb8": 3}[msg["encoding"]]
        rows = np.frombuffer(buf, np.uint8)[: h * step].reshape(h, step)[:, : w * ch]
        if ch == 1:
            return rows.reshape(h, w)
        img = rows.reshape(h, w, ch)
        return img if msg["encoding"] == "bgr8" else np.ascontiguousarray(img[:, :, ::-1])
    except (ValueError, KeyError, TypeError) as e:
        log.warning("undecodable image: %s", e)
        return None
