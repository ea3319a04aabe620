"""Camera sources: one async interface over the emulator's frame socket, cameras and video.

``async with open_camera(url) as cam: async for frame in cam: ...`` yields frozen
:class:`CameraFrame` values. A consumer that falls behind gets the newest frame: every source
keeps a small bounded buffer that drops the oldest frame and counts it (style habit 6).

URLs (:func:`open_camera`):

- ``tcp://127.0.0.1:5700``: the emulator's frame socket (docs/reference/wire.md),
  :class:`FrameSocketSource`: the newest frame the socket holds is taken, older ones
  skipped undecoded (``?frames=newest``, the default); ``?frames=all``: every frame in
  turn, as the lockstep emulator expects (one answer per frame it delivers).
  ``&transport=shm`` (either order): the frames through the emulator's shared memory, only
  a small notice per frame over TCP (the emulator on this host; ``transport=tcp``, the
  default, anywhere).
- ``0``, ``/dev/video0``: a local camera device, ``rtsp://...``, ``http(s)://...``, ``udp://...``:
  a live stream; a file path (or ``file://path``): a video file (read at the consumer's pace,
  nothing dropped). All through ``cv2.VideoCapture``: :class:`VideoCaptureSource`.
- ``*.mcap`` / ``mcap://``: recorded frames of a companion log (the replay source):
  :class:`McapSource`.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

from companion.camera.base import CameraError, CameraFrame, CameraSource, SourceStats
from companion.camera.capture import VideoCaptureSource
from companion.camera.recorded import McapSource
from companion.camera.socket import (
    FRAME_HEADER,
    BadRecord,
    FrameHeader,
    FrameSocketSource,
    decode_payload,
    pack_frame,
)

__all__ = [
    "FRAME_HEADER",
    "BadRecord",
    "CameraError",
    "CameraFrame",
    "CameraSource",
    "FrameHeader",
    "FrameSocketSource",
    "McapSource",
    "SourceStats",
    "VideoCaptureSource",
    "decode_payload",
    "open_camera",
    "pack_frame",
]


# ----------------------------------------------------------------------------------------------
# URL dispatch

_TCP = re.compile(r"^tcp://(?P<host>\[[^\]]+\]|[^:/?]+):(?P<port>\d+)/?(?:\?(?P<query>.*))?$")
_TCP_QUERY = {"frames": ("newest", "all"), "transport": ("tcp", "shm")}
_STREAM_SCHEMES = ("rtsp://", "rtsps://", "rtmp://", "http://", "https://", "udp://", "rtp://")


def open_camera(url: str, **kwargs: Any) -> CameraSource:
    """The source ``url`` names (see the module docstring). Nothing is opened until the
    source is entered (``async with``) or iterated; ``kwargs`` go to the source's
    constructor. Raises :class:`CameraError` for an unusable URL."""
    url = url.strip()
    if not url:
        raise CameraError("camera url: empty")
    if url.startswith("tcp://"):
        m = _TCP.match(url)
        query = _tcp_query(url, m["query"]) if m is not None else None
        if m is None or query is None:
            raise CameraError(f"camera url {url!r}: expected tcp://host:port, optionally "
                              "?frames=newest (the default) or ?frames=all, and "
                              "&transport=tcp (the default) or &transport=shm")
        kwargs.setdefault("read_ahead", query.get("frames") != "all")
        kwargs.setdefault("shared_memory", query.get("transport") == "shm")
        return FrameSocketSource(m["host"].strip("[]"), int(m["port"]), **kwargs)
    if url.startswith("mcap://") or url.endswith(".mcap"):
        return _open_mcap(url, **kwargs)
    if url.isdigit():
        return VideoCaptureSource(int(url), live=True, **kwargs)
    if url.startswith("/dev/"):
        return VideoCaptureSource(url, live=True, **kwargs)
    if url.startswith(_STREAM_SCHEMES):
        return VideoCaptureSource(url, live=True, **kwargs)
    path = url.removeprefix("file://")
    if "://" in path:
        raise CameraError(f"camera url {url!r}: unknown scheme")
    if not Path(path).expanduser().is_file():
        raise CameraError(f"camera url {url!r}: no such file")
    return VideoCaptureSource(str(Path(path).expanduser()), live=False, **kwargs)


def _tcp_query(url: str, query: str | None) -> dict[str, str] | None:
    """The frame socket URL's query as a dict (None if a key or value is unknown)."""
    out: dict[str, str] = {}
    for part in (query or "").split("&") if query else []:
        key, _, value = part.partition("=")
        if value not in _TCP_QUERY.get(key, ()) or key in out:
            return None
        out[key] = value
    return out


def _open_mcap(url: str, **kwargs: Any) -> CameraSource:
    path = url.removeprefix("mcap://")
    if not Path(path).expanduser().is_file():
        raise CameraError(f"camera url {url!r}: no such file")
    return McapSource(Path(path).expanduser(), **kwargs)


