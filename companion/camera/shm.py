"""Camera frames through shared memory, the client's side (docs/reference/wire.md, "Camera
frames through shared memory"): the request a client sends, the segment's announcement and
:class:`SharedFrames`, which maps the emulator's ring of frame slots and copies a frame out
of its slot only when the slot's seqlock shows it whole and the slot still holds the frame
its notice names (a torn or lapped slot gives None: never a frame of mixed contents)."""

from __future__ import annotations

import contextlib
import mmap
import os
import struct
from dataclasses import dataclass

import numpy as np
from fastcrc.crc32 import iso_hdlc as _crc32

from companion.camera.base import CameraError

# docs/reference/wire.md, camera frames through shared memory
REQUEST = struct.Struct("<4sBBH")
REQUEST_SHM = REQUEST.pack(b"IBVQ", 1, 1, 0)
ANNOUNCE = struct.Struct("<4sBBHIIIQI")
ANNOUNCE_MAGIC = b"IBVA"
NOTICE_MAGIC = b"IBVN"
FLAG_CRC = 1
SEGMENT = struct.Struct("<4sBBHIII")
SEGMENT_MAGIC = b"IBVR"
SEGMENT_HEADER_BYTES = 4096
SLOT_HEADER_BYTES = 64
MAX_NAME_BYTES = 4096
_SLOT_FRAME_HEADER = struct.Struct("<4sBBHIQHHII")  # the frame header in a slot (magic IBVF)


@dataclass(frozen=True)
class Announcement:
    """The segment a frame server writes its frames into (record ``IBVA``)."""

    flags: int
    n_slots: int
    stride_bytes: int
    payload_offset: int
    size_bytes: int
    name_len: int

    @classmethod
    def unpack(cls, data: bytes) -> Announcement:
        magic, version, flags, _res, n, stride, off, size, name_len = ANNOUNCE.unpack(data)
        if magic != ANNOUNCE_MAGIC or version != 1:
            raise CameraError(f"bad shared-memory announcement {magic!r} v{version}")
        if not (0 < n <= 1024 and SLOT_HEADER_BYTES <= off < stride
                and size == SEGMENT_HEADER_BYTES + n * stride and 0 < name_len <= MAX_NAME_BYTES):
            raise CameraError(f"inconsistent shared-memory announcement: {n} slots of {stride} "
                              f"bytes (payload at {off}) in {size}, name of {name_len} bytes")
        return cls(flags, n, stride, off, size, name_len)


class SharedFrames:
    """A read-only map of the ring ``path`` that ``ann`` describes. Raises
    :class:`CameraError` with the path when it cannot be opened or is not that ring."""

    def __init__(self, path: str, ann: Announcement) -> None:
        self.path = path
        self.ann = ann
        hint = ("; shared memory needs the emulator on this host (drop ?transport=shm to read "
                "the frames over TCP)")
        try:
            fd = os.open(path, os.O_RDONLY)
        except OSError as e:
            raise CameraError(f"shared-memory frames: cannot open {path}: {e}{hint}") from e
        try:
            size = os.fstat(fd).st_size
            if size < ann.size_bytes:
                raise CameraError(f"shared-memory frames: {path} has {size} bytes, the "
                                  f"announcement {ann.size_bytes}{hint}")
            self._mm = mmap.mmap(fd, ann.size_bytes, prot=mmap.PROT_READ)
        except OSError as e:
            raise CameraError(f"shared-memory frames: cannot map {path}: {e}{hint}") from e
        finally:
            os.close(fd)
        seg = SEGMENT.unpack_from(self._mm, 0)
        if seg != (SEGMENT_MAGIC, 1, 0, 0, ann.n_slots, ann.stride_bytes, ann.payload_offset):
            self._mm.close()
            raise CameraError(f"shared-memory frames: {path} is not the announced ring "
                              f"(its header {seg!r}){hint}")
        # the slots' generations, each one aligned 8-byte load (the seqlock)
        self._gens = [np.frombuffer(self._mm, np.uint64, 1, self._base(i))
                      for i in range(ann.n_slots)]

    def _base(self, slot: int) -> int:
        return SEGMENT_HEADER_BYTES + slot * self.ann.stride_bytes

    def read(self, slot: int, seq: int, t_us: int, payload_len: int,
             crc32: int) -> memoryview | None:
        """A copy of the payload in ``slot`` if the slot holds frame ``seq`` whole, else None
        (being written, or already overwritten by a newer frame). Raises :class:`CameraError`
        for a notice that does not fit the ring."""
        ann = self.ann
        if slot >= ann.n_slots or payload_len > ann.stride_bytes - ann.payload_offset:
            raise CameraError(f"shared-memory notice for slot {slot}, {payload_len} bytes: "
                              f"outside the ring ({ann.n_slots} slots)")
        gen = self._gens[slot]
        g1 = int(gen[0])
        if g1 & 1:
            return None
        base = self._base(slot)
        head = _SLOT_FRAME_HEADER.unpack_from(self._mm, base + 16)
        if head[4] != seq or head[5] != t_us or head[8] != payload_len:
            return None  # a newer frame (or none yet) in the slot
        out = np.empty(payload_len, np.uint8)
        out[:] = np.frombuffer(self._mm, np.uint8, payload_len, base + ann.payload_offset)
        if int(gen[0]) != g1:
            return None  # written while we copied
        if ann.flags & FLAG_CRC and _crc32(out.data) != crc32:
            return None
        out.setflags(write=False)
        return out.data

    def close(self) -> None:
        self._gens = []
        with contextlib.suppress(BufferError, ValueError):
            self._mm.close()
