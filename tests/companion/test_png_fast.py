"""The fast PNG reader gives OpenCV's pixels for the PNGs the logger writes, and declines
(None: the caller decodes with OpenCV) every other PNG and damaged files."""

from __future__ import annotations

import struct

import cv2
import numpy as np
import pytest

from companion.log import schemas as sch
from companion.log.encode import encode_image, png_bytes
from companion.log.images import image_from_raw
from companion.log.png_fast import read_png


def _cv(buf: bytes) -> np.ndarray:
    img = cv2.imdecode(np.frombuffer(buf, np.uint8), cv2.IMREAD_UNCHANGED)
    assert isinstance(img, np.ndarray)
    return img


@pytest.mark.parametrize("shape", [(419, 336), (1, 7), (7, 1), (300, 200, 3), (1, 1, 3)])
def test_the_loggers_pngs_decode_to_opencvs_pixels(shape: tuple[int, ...]) -> None:
    rng = np.random.default_rng(sum(shape))
    # smooth rows with noise: the UP filter's differences wrap below 0 and above 255
    img = (rng.integers(0, 256, shape) + np.arange(shape[0]).reshape(-1, *[1] * (len(shape) - 1))
           * 37).astype(np.uint8)
    buf = png_bytes(img)
    got = read_png(buf)
    assert got is not None and got.dtype == np.uint8 and got.flags.c_contiguous
    assert np.array_equal(got, img) and np.array_equal(got, _cv(buf))


def test_other_pngs_and_damaged_ones_are_declined() -> None:
    img = np.random.default_rng(1).integers(0, 256, (40, 30, 3)).astype(np.uint8)
    ok, other = cv2.imencode(".png", img)  # libpng's filters (PAETH...): not ours
    assert ok and read_png(other.tobytes()) is None
    ours = bytearray(png_bytes(img))
    at = ours.index(b"IDAT") + 20
    ours[at] ^= 0x10  # the chunk's CRC no longer matches
    assert read_png(bytes(ours)) is None
    assert read_png(b"\x89PNG\r\n\x1a\n" + struct.pack(">I", 13)) is None  # cut short
    assert read_png(b"not a png") is None


def test_a_logged_frame_reads_the_same_either_way() -> None:
    """image_from_raw (what replay and reports read frames with): ours the fast way, an
    OpenCV-written PNG through OpenCV, the same pixels."""
    img = np.random.default_rng(2).integers(0, 256, (50, 60)).astype(np.uint8)
    schema, raw = encode_image(img, "png", 0, "camera", 90)
    assert schema == sch.COMPRESSED_IMAGE
    got = image_from_raw(schema, sch.PROTOBUF_ENCODING, raw)
    assert got is not None and np.array_equal(got, img)
    _, other = cv2.imencode(".png", img)
    msg = sch.protobuf_class(sch.COMPRESSED_IMAGE)(frame_id="camera", format="png",
                                                   data=other.tobytes())
    got = image_from_raw(sch.COMPRESSED_IMAGE, sch.PROTOBUF_ENCODING, msg.SerializeToString())
    assert got is not None and np.array_equal(got, img)
