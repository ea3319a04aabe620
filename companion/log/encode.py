"""Encoding of log payloads: log-time stamps, JSON with non-finite values made explicit,
Foxglove images (protobuf CompressedImage / RawImage) and MAVLink message payloads."""

from __future__ import annotations

import base64
import dataclasses
import enum
import json
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

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


def encode_json(payload: Any) -> bytes:
    """Compact JSON; NaN/inf become null; numpy, bytes (base64) and dataclasses are handled."""
    try:
        text = json.dumps(payload, default=_json_default, allow_nan=False, separators=(",", ":"))
    except ValueError:  # a non-finite float somewhere
        text = json.dumps(_finite(payload), allow_nan=False, separators=(",", ":"))
    return text.encode()


def encode_image(
    image: np.ndarray, encoding: str, log_time_ns: int, frame_id: str, jpeg_quality: int
) -> tuple[str, bytes]:
    """(schema name, protobuf bytes) of a foxglove.CompressedImage (jpeg/png) or RawImage (raw).

    Costs per 1000 x 1000 mono frame on this machine: "raw" ~0.5 ms here plus the chunk
    compression (LZ4 ~2.3 ms, ~0.7 MB); "png" several ms (lossless too, ~0.3 MB); "jpeg" small
    but lossy. The live process logs crops (see companion.control.recording), far smaller."""
    import cv2

    img = np.ascontiguousarray(image)
    if img.dtype != np.uint8 or img.ndim not in (2, 3) or (img.ndim == 3 and img.shape[2] != 3):
        raise McapLogError(f"image must be uint8 HxW or HxWx3 (BGR), got {img.dtype} {img.shape}")
    ts = stamp(log_time_ns)
    if encoding in ("jpeg", "png"):
        # Lossless PNG tuned for size at little CPU: Huffman-only coding after the PAETH
        # filter. On the perception crops of a paper flight (~120 kpx, textured ground) 27.8 kB
        # and 1.6 ms CPU each, against 37.6 kB / 1.0 ms with the SUB filter and 32 kB / 35 ms
        # with zlib level 6 (the sensor noise leaves little for LZ77 to find).
        params = [cv2.IMWRITE_JPEG_QUALITY, jpeg_quality] if encoding == "jpeg" else [
            cv2.IMWRITE_PNG_COMPRESSION, 1,
            cv2.IMWRITE_PNG_STRATEGY, cv2.IMWRITE_PNG_STRATEGY_HUFFMAN_ONLY,
            cv2.IMWRITE_PNG_FILTER, cv2.IMWRITE_PNG_FILTER_PAETH,
        ]
        ok, buf = cv2.imencode(".jpg" if encoding == "jpeg" else ".png", img, params)
        if not ok:
            raise McapLogError(f"cv2 could not encode a {encoding} image")
        cmsg = sch.protobuf_class(sch.COMPRESSED_IMAGE)(
            frame_id=frame_id, format=encoding, data=buf.tobytes()
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

def xyz(v: Sequence[float]) -> dict[str, float]:
    x, y, z = (float(a) for a in v)
    return {"x": x, "y": y, "z": z}


def xyzw(q_wxyz: Sequence[float]) -> dict[str, float]:
    w, x, y, z = (float(a) for a in q_wxyz)
    return {"x": x, "y": y, "z": z, "w": w}


def mavlink_payload(direction: str, item: Any) -> dict[str, Any]:
    from companion.link import message_fields

    out: dict[str, Any] = {
        "raw_b64": base64.b64encode(item.raw).decode("ascii"),
        "fields": message_fields(item.msg),
    }
    if direction == "in":
        out.update(
            t_rx_ns=item.t_rx_ns, sysid=item.src_sysid, compid=item.src_compid, seq=item.seq,
            signed=item.signed,
        )  # fmt: skip
    else:
        out.update(t_tx_ns=item.t_tx_ns)
    return out
