"""Camera frames through shared memory, for a client on the emulator's host
(docs/reference/wire.md, "Camera frames through shared memory").

The frame server writes each frame once into a ring of slots in a memory-mapped file (under
``/dev/shm`` where there is one) and sends a client that asked for it (request ``IBVQ``) only
the segment's name once (``IBVA``) and then a 32-byte notice per frame (``IBVN``: the frame
header naming the slot) over the same TCP connection. A 1 MB frame then costs a copy into
the slot instead of a loopback write of 1 MB (and the client's read of it).

Each slot is guarded by a seqlock: its 64-bit generation is odd while the slot is written, so
a reader that sees the same even generation before and after copying the slot got one frame
whole (the slot's own header names which: a lapped slot holds a newer ``seq``). On x86-64
the stores and loads involved are not reordered (total store order), so the generation is
enough; on other CPUs the slots also carry the payload's CRC-32 (``FLAG_CRC``) for the
reader to check.
"""

from __future__ import annotations

import contextlib
import logging
import mmap
import os
import platform
import re
import struct
import tempfile
from pathlib import Path

import numpy as np
from fastcrc.crc32 import iso_hdlc as _crc32

from sim_bridge import LinkError

__all__ = [
    "ANNOUNCE",
    "FLAG_CRC",
    "NOTICE_MAGIC",
    "REQUEST",
    "REQUEST_MAGIC",
    "SEGMENT",
    "SLOT_HEADER_BYTES",
    "TRANSPORT_SHM",
    "FrameRing",
    "parse_request",
]

log = logging.getLogger(__name__)

# client -> emulator, once after connecting: magic, version 1, transport (1 shared memory)
REQUEST = struct.Struct("<4sBBH")
REQUEST_MAGIC = b"IBVQ"
TRANSPORT_SHM = 1
# emulator -> client, once before the first notice: magic, version, flags, reserved, slots,
# slot stride, the payload's offset in a slot, the segment's size, the name's length; then
# the name (UTF-8 path of the file to map)
ANNOUNCE = struct.Struct("<4sBBHIIIQI")
ANNOUNCE_MAGIC = b"IBVA"
FLAG_CRC = 1  # the slots' (and notices') crc32 is the payload's CRC-32, else 0
# emulator -> client, per frame: the 32-byte frame header with this magic, ``reserved`` =
# the slot; no payload follows (it is in the slot)
NOTICE_MAGIC = b"IBVN"
# the segment's first bytes: magic, version, reserved, slots, slot stride, payload offset
SEGMENT = struct.Struct("<4sBBHIII")
SEGMENT_MAGIC = b"IBVR"
SEGMENT_HEADER_BYTES = 4096
# a slot: u64 generation (odd while written), u64 reserved, the 32-byte frame header
# (magic IBVF), padding; the payload from SLOT_HEADER_BYTES on
SLOT_HEADER_BYTES = 64
_PAGE = 4096
_N_SLOTS = 4
_NAME = re.compile(r"^sim_bridge-frames-(\d+)-")


def parse_request(data: bytes) -> int | None:
    """The transport a client's request asks for (``TRANSPORT_SHM``), None if ``data`` is not
    a request this emulator knows."""
    if len(data) != REQUEST.size:
        return None
    magic, version, transport, _ = REQUEST.unpack(data)
    if magic != REQUEST_MAGIC or version != 1 or transport != TRANSPORT_SHM:
        return None
    return int(transport)


def _shm_dir() -> Path:
    d = Path("/dev/shm")
    return d if d.is_dir() and os.access(d, os.W_OK) else Path(tempfile.gettempdir())


def _sweep(directory: Path) -> None:
    """Remove the segments of emulators that are gone (a crash leaves its file behind: the
    name carries the writer's pid)."""
    for p in directory.glob("sim_bridge-frames-*"):
        m = _NAME.match(p.name)
        if m is None:
            continue
        try:
            os.kill(int(m[1]), 0)
        except ProcessLookupError:
            with contextlib.suppress(OSError):
                p.unlink()
                log.info("removed the stale frame segment %s", p)
        except OSError:
            pass  # alive (another user's): not ours


class FrameRing:
    """The writer's ring of ``n_slots`` frame slots of ``payload_bytes`` each in a file it
    creates (``/dev/shm/sim_bridge-frames-<pid>-<tag>``) and removes on :meth:`close`."""

    def __init__(self, payload_bytes: int, tag: str, n_slots: int = _N_SLOTS,
                 directory: Path | None = None, crc: bool | None = None) -> None:
        if payload_bytes <= 0 or n_slots < 2:
            raise LinkError("frame ring: need payload_bytes > 0 and at least 2 slots")
        self.n_slots = n_slots
        self.payload_offset = SLOT_HEADER_BYTES
        self.stride = -(-(SLOT_HEADER_BYTES + payload_bytes) // _PAGE) * _PAGE
        self.capacity = self.stride - SLOT_HEADER_BYTES
        self.size = SEGMENT_HEADER_BYTES + n_slots * self.stride
        # x86-64 keeps the seqlock's stores (and the reader's loads) in order
        self.crc = (platform.machine().lower() not in ("x86_64", "amd64")) if crc is None else crc
        directory = _shm_dir() if directory is None else directory
        _sweep(directory)
        self.path = directory / f"sim_bridge-frames-{os.getpid()}-{tag}"
        try:
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT | os.O_EXCL, 0o644)
        except OSError as e:
            raise LinkError(f"frame ring: cannot create {self.path}: {e}") from e
        try:
            # allocated now: a full /dev/shm (a container's 64 MB) is an error here, where a
            # sparse file would kill the process with SIGBUS at the first write into a hole
            if hasattr(os, "posix_fallocate"):
                os.posix_fallocate(fd, 0, self.size)
            else:  # macOS: no tmpfs under the temporary directory, an ordinary file
                os.ftruncate(fd, self.size)
            self._mm = mmap.mmap(fd, self.size)
        except OSError as e:
            with contextlib.suppress(OSError):
                self.path.unlink()
            raise LinkError(f"frame ring: cannot map {self.path}: {e}") from e
        finally:
            os.close(fd)
        self._gen = np.ndarray((n_slots,), np.uint64, self._mm, SEGMENT_HEADER_BYTES,
                               (self.stride,))
        SEGMENT.pack_into(self._mm, 0, SEGMENT_MAGIC, 1, 0, 0, n_slots, self.stride,
                          self.payload_offset)
        self._next = 0
        self.closed = False
        name = str(self.path).encode()
        self.announcement = ANNOUNCE.pack(ANNOUNCE_MAGIC, 1, FLAG_CRC if self.crc else 0, 0,
                                          n_slots, self.stride, self.payload_offset, self.size,
                                          len(name)) + name
        log.info("camera frames also through shared memory %s (%d slots)", self.path, n_slots)

    def write(self, header: struct.Struct, fields: tuple[int, int, int, int, int],
              payload: bytes | memoryview) -> bytes:
        """Put one frame's ``payload`` into the next slot; returns its notice (the frame
        header with magic IBVN, the slot as ``reserved``, the CRC-32 or 0). ``fields``:
        (encoding, seq, t_us, width, height) of the frame header."""
        if self.closed:
            raise LinkError("frame ring: closed")
        n = len(payload)
        if n > self.capacity:
            raise LinkError(f"frame ring: a {n}-byte payload does not fit a slot of "
                            f"{self.capacity}")
        enc, seq, t_us, w, h = fields
        slot = self._next
        self._next = (slot + 1) % self.n_slots
        base = SEGMENT_HEADER_BYTES + slot * self.stride
        src = np.frombuffer(payload, np.uint8)
        crc = _crc32(payload) if self.crc else 0
        self._gen[slot] += 1  # odd: being written
        np.copyto(np.frombuffer(self._mm, np.uint8, n, base + self.payload_offset), src)
        header.pack_into(self._mm, base + 16, b"IBVF", 1, enc, 0, seq, t_us, w, h, n, crc)
        self._gen[slot] += 1  # even: whole
        return header.pack(NOTICE_MAGIC, 1, enc, slot, seq, t_us, w, h, n, crc)

    def close(self) -> None:
        """Unmap and remove the file (clients that mapped it keep their mapping)."""
        if self.closed:
            return
        self.closed = True
        with contextlib.suppress(OSError):
            self.path.unlink()
        del self._gen
        with contextlib.suppress(BufferError):
            self._mm.close()
