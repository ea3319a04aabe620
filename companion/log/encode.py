"""Encoding of log payloads: log-time stamps, JSON with non-finite values made explicit,
Foxglove images (protobuf CompressedImage / RawImage) and MAVLink message payloads."""

from __future__ import annotations

import base64
import binascii
import dataclasses
import enum
import json
import math
import struct
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import orjson
from isal import isal_zlib

from companion.log import McapLogError
from companion.log import schemas as sch


def stamp(t_ns: int) -> dict[str, int]:
    """Foxglove ``time`` ({sec, nsec}) of a non-negative time in ns."""
    t = max(int(t_ns), 0)
    return {"sec": t // 1_000_000_000, "nsec": t % 1_000_000_000}


def _json_default(o: Any) -> Any:
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, bytes | bytearray | memoryview):
        return base64.b64encode(bytes(o)).decode("ascii")
    if dataclasses.is_dataclass(o) and not isinstance(o, type):
        return {f.name: getattr(o, f.name) for f in dataclasses.fields(o)}
    if isinstance(o, enum.Enum):
        return o.value if isinstance(o.value, int | float | str) else o.name
    if isinstance(o, set | frozenset | tuple):
        return list(o)
    if isinstance(o, Path):
        return str(o)
    if isinstance(o, Mapping):
        return dict(o)
    raise TypeError(f"cannot log a {type(o).__name__} as JSON")


def _finite(o: Any) -> Any:
    """Replace NaN/inf by None (JSON has no NaN), converting what _json_default knows."""
    if isinstance(o, float):
        return o if math.isfinite(o) else None
    if isinstance(o, dict):
        return {k: _finite(v) for k, v in o.items()}
    if isinstance(o, list | tuple):
        return [_finite(v) for v in o]
    if isinstance(o, str | int | bool) or o is None:
        return o
    return _finite(_json_default(o))


def _orjson_default(o: Any) -> Any:
    # numpy arrays as Python lists (float64 values, as the json path writes them; orjson's own
    # numpy option would write float32 arrays at float32 precision)
    if isinstance(o, np.ndarray):
        return o.tolist()
    return _json_default(o)


_ORJSON_OPTIONS = orjson.OPT_NON_STR_KEYS


def encode_json(payload: Any) -> bytes:
    """Compact JSON; NaN/inf become null; numpy, bytes (base64) and dataclasses are handled.

    orjson (a pinned dependency): a flight's step record costs ~25 us instead
    of ~400 us with the json module (which must walk it again to null its NaNs). The text may
    differ from the json module's in float spelling (``1e-05`` vs ``1e-5``), never in value."""
    try:
        return orjson.dumps(payload, default=_orjson_default, option=_ORJSON_OPTIONS)
    except TypeError:  # orjson.JSONEncodeError: an int beyond 64 bits, an unknown type, ...
        pass  # the json module encodes what it can and says what it cannot
    try:
        text = json.dumps(payload, default=_json_default, allow_nan=False, separators=(",", ":"))
    except ValueError:  # a non-finite float somewhere
        text = json.dumps(_finite(payload), allow_nan=False, separators=(",", ":"))
    return text.encode()


def decode_json(raw: bytes | str) -> Any:
    """The value of a JSON text (orjson; the json module for what orjson refuses but it reads:
    the NaN/Infinity literals or integers beyond 64 bits some writers produce). Raises
    ``ValueError`` (incl. ``UnicodeDecodeError``) when neither reads it."""
    try:
        return orjson.loads(raw)
    except orjson.JSONDecodeError:
        return json.loads(raw)


def decode_json_object(raw: bytes | str) -> dict[str, Any] | None:
    """The JSON object in ``raw``; None when it is not JSON or not an object (a damaged or
    foreign record: the caller skips it)."""
    try:
        out = decode_json(raw)
    except ValueError:
        return None
    return out if isinstance(out, dict) else None


def encode_image(
    image: np.ndarray, encoding: str, log_time_ns: int, frame_id: str, jpeg_quality: int
) -> tuple[str, bytes]:
    """(schema name, protobuf bytes) of a foxglove.CompressedImage (jpeg/png) or RawImage (raw).

    Costs per 1000 x 1000 mono frame on this machine: "raw" ~0.5 ms here plus the chunk
    compression (LZ4 ~2.3 ms, ~0.7 MB); "png" (lossless, :func:`png_bytes`) ~4 ms, ~0.3 MB;
    "jpeg" small but lossy. The live process logs crops (see companion.control.recording), far
    smaller."""
    import cv2

    img = np.ascontiguousarray(image)
    if img.dtype != np.uint8 or img.ndim not in (2, 3) or (img.ndim == 3 and img.shape[2] != 3):
        raise McapLogError(f"image must be uint8 HxW or HxWx3 (BGR), got {img.dtype} {img.shape}")
    ts = stamp(log_time_ns)
    if encoding in ("jpeg", "png"):
        if encoding == "png":
            data = png_bytes(img)
        else:
            ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, jpeg_quality])
            if not ok:
                raise McapLogError("cv2 could not encode a jpeg image")
            data = buf.tobytes()
        cmsg = sch.protobuf_class(sch.COMPRESSED_IMAGE)(
            frame_id=frame_id, format=encoding, data=data
        )
        cmsg.timestamp.seconds, cmsg.timestamp.nanos = ts["sec"], ts["nsec"]
        return sch.COMPRESSED_IMAGE, cmsg.SerializeToString()
    h, w = img.shape[:2]
    rmsg = sch.protobuf_class(sch.RAW_IMAGE)(
        frame_id=frame_id, width=w, height=h, encoding="mono8" if img.ndim == 2 else "bgr8",
        step=w * (1 if img.ndim == 2 else 3), data=img.tobytes(),
    )  # fmt: skip
    rmsg.timestamp.seconds, rmsg.timestamp.nanos = ts["sec"], ts["nsec"]
    return sch.RAW_IMAGE, rmsg.SerializeToString()


IMAGE_ENCODINGS = ("jpeg", "png", "raw")


def _png_chunk(kind: bytes, data: bytes) -> bytes:
    # ISA-L's CRC-32 (the same CRC as zlib's, several times faster on a crop's ~30 kB IDAT)
    crc = isal_zlib.crc32(data, isal_zlib.crc32(kind))
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", crc)


def png_bytes(image: np.ndarray) -> bytes:
    """A standard 8-bit PNG (greyscale, or RGB from a BGR image) of ``image``, lossless: every
    row with PNG's UP filter (the difference to the row above, one numpy subtraction), deflated
    by ISA-L (``isal``) at level 1. Any PNG decoder reads it (Foxglove, OpenCV, the reader).

    Why not ``cv2.imencode``: libpng's zlib deflates at ~70 MB/s even Huffman-only; ISA-L at
    several hundred. On the crops of a paper flight (~110 kpx, textured ground with sensor
    noise) 0.48 ms and 30.5 kB a crop, against 2.1 ms and 27.2 kB for OpenCV's PAETH +
    Huffman-only (UP filter with zlib instead: 1.6 ms, 35.8 kB)."""
    img = np.ascontiguousarray(image)
    h, w = img.shape[:2]
    if h == 0 or w == 0:
        raise McapLogError(f"cannot encode an empty image ({w} x {h}) as PNG")
    if img.ndim == 3:
        img = img[:, :, ::-1].reshape(h, w * 3)  # BGR -> RGB, one row of bytes per image row
    rows = np.empty((h, img.shape[1] + 1), dtype=np.uint8)
    rows[0, 0] = 0  # no filter on the first row
    rows[0, 1:] = img[0]
    rows[1:, 0] = 2  # UP: the byte minus the byte above, modulo 256
    np.subtract(img[1:], img[:-1], out=rows[1:, 1:])
    header = struct.pack(">IIBBBBB", w, h, 8, 0 if image.ndim == 2 else 2, 0, 0, 0)
    return b"".join((
        b"\x89PNG\r\n\x1a\n", _png_chunk(b"IHDR", header),
        _png_chunk(b"IDAT", isal_zlib.compress(rows.data, 1)), _png_chunk(b"IEND", b""),
    ))

def xyz(v: Sequence[float]) -> dict[str, float]:
    x, y, z = (float(a) for a in v)
    return {"x": x, "y": y, "z": z}


def xyzw(q_wxyz: Sequence[float]) -> dict[str, float]:
    w, x, y, z = (float(a) for a in q_wxyz)
    return {"x": x, "y": y, "z": z, "w": w}


def _fields(item: Any) -> dict[str, Any]:
    """The message's fields: decoded once by the link on receipt (``Received.fields``)."""
    fields = getattr(item, "fields", None)
    if fields is not None:
        return fields  # type: ignore[no-any-return]
    from companion.link import message_fields

    return message_fields(item.msg)


def mavlink_payload(direction: str, item: Any) -> dict[str, Any]:
    raw_b64 = binascii.b2a_base64(item.raw, newline=False).decode("ascii")
    if direction == "in":
        return {
            "raw_b64": raw_b64, "fields": _fields(item), "t_rx_ns": item.t_rx_ns,
            "sysid": item.src_sysid, "compid": item.src_compid, "seq": item.seq,
            "signed": item.signed,
        }  # fmt: skip
    return {"raw_b64": raw_b64, "fields": _fields(item), "t_tx_ns": item.t_tx_ns}
