"""MAVLink 2 signing: key files, the signing clock and an incoming-signature verifier that
checks the signature before it updates a stream's timestamp (docs/reference/pitfalls.md)."""

from __future__ import annotations

import hashlib
import logging
import time
from collections.abc import Iterable
from pathlib import Path

from pymavlink.dialects.v20 import common as mavlink2

from companion.link.errors import LinkError

log = logging.getLogger(__name__)


_SIGNING_EPOCH_UNIX_S = 1420070400  # 2015-01-01T00:00:00Z, MAVLink signing time origin
_NEW_STREAM_MAX_AGE_10US = 6_000_000  # 60 s, as pymavlink and the C library

# ----------------------------------------------------------------------------------------------
# Signing


def load_signing_key(path: str | Path) -> bytes:
    """Read a 32-byte MAVLink 2 signing key: a file of exactly 32 raw bytes, or 64 hex
    characters (whitespace around them ignored)."""
    p = Path(path)
    try:
        data = p.read_bytes()
    except OSError as e:
        raise LinkError(f"signing key file {str(p)!r}: {e.strerror}") from e
    if len(data) == 32:
        return data
    try:
        text = data.decode("ascii").strip()
        if len(text) == 64:
            return bytes.fromhex(text)
    except (UnicodeDecodeError, ValueError):
        pass
    raise LinkError(
        f"signing key file {str(p)!r}: expected 32 raw bytes or 64 hex characters, "
        f"got {len(data)} bytes"
    )


def signing_timestamp_now() -> int:
    """MAVLink signing time: units of 10 us since 2015-01-01 (wall clock, as the protocol says)."""
    return int((max(time.time(), _SIGNING_EPOCH_UNIX_S) - _SIGNING_EPOCH_UNIX_S) * 100_000)


class SignatureVerifier:
    """Verify incoming MAVLink 2 signatures: signature FIRST, then the per-stream timestamp.

    Streams are keyed by (link_id, sysid, compid); a frame must be newer than the last accepted
    one of its stream; a new stream must not be older than 60 s.
    """

    def __init__(self, key: bytes, allow_unsigned_msgids: Iterable[int] = ()) -> None:
        if len(key) != 32:
            raise LinkError("signing key must be 32 bytes")
        self._key = key
        self._allow_unsigned = frozenset(allow_unsigned_msgids)
        self._streams: dict[tuple[int, int, int], int] = {}
        self.max_timestamp_10us = signing_timestamp_now()

    def check(self, raw: bytes, sysid: int, compid: int, msgid: int) -> str | None:
        """Reason to reject ``raw`` (a whole MAVLink 2 frame), or None to accept it."""
        if not raw[2] & mavlink2.MAVLINK_IFLAG_SIGNED:
            return None if msgid in self._allow_unsigned else "unsigned"
        if len(raw) < 10 + 2 + 13:
            return "bad_signature"
        digest = hashlib.sha256(self._key + raw[:-6]).digest()[:6]
        if digest != raw[-6:]:
            return "bad_signature"
        link_id = raw[-13]
        ts = int.from_bytes(raw[-12:-6], "little")
        key = (link_id, sysid, compid)
        last = self._streams.get(key)
        if last is not None:
            if ts <= last:
                return "old_timestamp"
        elif ts + _NEW_STREAM_MAX_AGE_10US < max(self.max_timestamp_10us, signing_timestamp_now()):
            return "stale_stream"
        self._streams[key] = ts
        self.max_timestamp_10us = max(self.max_timestamp_10us, ts)
        return None

