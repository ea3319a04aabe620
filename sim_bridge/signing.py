"""MAVLink 2 message signing as PX4 does it with a provisioned key: the pure core (hashlib and
struct only; no sockets, clocks or pymavlink).

Verification follows the MAVLink C library's ``mavlink_signature_check`` that PX4 runs
(``mavlink_helpers.h``) and PX4's ``MavlinkSignControl::accept_unsigned``
(``src/modules/mavlink/mavlink_sign_control.cpp``):

* A signed frame is checked FIRST against its signature: ``SHA-256(key || frame without the
  last 6 bytes)[:6]`` must equal those 6 bytes. A frame that fails this changes no state.
  (pymavlink 2.4.50's ``check_signature`` stores the timestamp before this check, so one
  forged frame stamped 2^48 - 2 locks the real sender out; we do not.)
* Then the timestamp (10 us units since 2015-01-01 00:00 UTC, 48 bits), per stream
  ``(link_id, sysid, compid)``: a known stream must strictly increase (else: replay); a new
  stream is accepted only if its timestamp is at most 60 s older than ours, and at most
  :data:`MAX_STREAMS` streams are tracked. Only then is the stream's timestamp stored and our
  own raised to it (our next outgoing timestamp is at least that).
* Unsigned frames are rejected, except the ids PX4 always accepts unsigned
  (:data:`UNSIGNED_ALLOWED_MSGIDS`: RADIO_STATUS, ADSB_VEHICLE, COLLISION).

As in PX4, one table of streams is shared by all the vehicle's links.
"""

from __future__ import annotations

import enum
import hashlib
import hmac
from dataclasses import dataclass, field

MAVLINK2_MAGIC = 0xFD
IFLAG_SIGNED = 0x01
HEADER_LEN = 10            # magic .. msgid (MAVLink 2)
SIGNATURE_LEN = 13         # link_id (1), timestamp (6), signature (6)
EPOCH_2015_UNIX_S = 1_420_070_400
TIMESTAMP_UNITS_PER_S = 100_000   # 10 us
NEW_STREAM_WINDOW = 6_000_000     # 60 s in 10 us units (the C library's 6000*1000)
MAX_STREAMS = 16                  # MAVLINK_MAX_SIGNING_STREAMS
TIMESTAMP_MAX = (1 << 48) - 1

RADIO_STATUS = 109
ADSB_VEHICLE = 246
COLLISION = 247
UNSIGNED_ALLOWED_MSGIDS = frozenset({RADIO_STATUS, ADSB_VEHICLE, COLLISION})


class Verdict(enum.Enum):
    """Outcome of :meth:`SigningState.verify` for one frame."""

    SIGNED = "signed"                        # accepted: good signature, fresh timestamp
    UNSIGNED_ALLOWED = "unsigned_allowed"    # accepted: an id PX4 takes unsigned
    UNSIGNED = "unsigned"                    # rejected
    BAD_SIGNATURE = "bad_signature"          # rejected (wrong key, forged, corrupted)
    REPLAY = "replay"                        # rejected: timestamp not above the stream's last
    OLD_STREAM = "old_stream"                # rejected: new stream more than 60 s behind us
    TOO_MANY_STREAMS = "too_many_streams"    # rejected
    MALFORMED = "malformed"                  # rejected: not a MAVLink 2 frame

    @property
    def accepted(self) -> bool:
        return self in (Verdict.SIGNED, Verdict.UNSIGNED_ALLOWED)


def timestamp_from_unix(unix_s: float) -> int:
    """Signing timestamp (10 us since 2015-01-01 UTC) of a Unix time in seconds."""
    return max(0, int((unix_s - EPOCH_2015_UNIX_S) * TIMESTAMP_UNITS_PER_S))


def signature(key: bytes, frame_without_sig: bytes) -> bytes:
    """The 6 signature bytes of a frame: ``frame_without_sig`` is the whole frame up to and
    including the link id and the 6 timestamp bytes."""
    return hashlib.sha256(key + frame_without_sig).digest()[:6]


def sign_frame(key: bytes, unsigned_frame: bytes, link_id: int, timestamp: int) -> bytes:
    """Sign a MAVLink 2 frame that already has the SIGNED incompat flag set in its header and
    its CRC computed over that header (what a signing encoder packs before the signature)."""
    body = unsigned_frame + bytes([link_id]) + timestamp.to_bytes(6, "little")
    return body + signature(key, body)


@dataclass
class SigningState:
    """Key, our timestamp and the per-stream timestamps of one vehicle."""

    key: bytes
    timestamp: int = 0
    streams: dict[tuple[int, int, int], int] = field(default_factory=dict)
    counts: dict[Verdict, int] = field(default_factory=lambda: dict.fromkeys(Verdict, 0))

    def __post_init__(self) -> None:
        if len(self.key) != 32:
            raise ValueError(f"key: must be 32 bytes, got {len(self.key)}")

    def verify(self, frame: bytes) -> Verdict:
        """Check one received frame (the raw bytes, signature block included) and update the
        stream state only if it is accepted."""
        v = self._verify(frame)
        self.counts[v] += 1
        return v

    def _verify(self, frame: bytes) -> Verdict:
        if len(frame) < HEADER_LEN + 2 or frame[0] != MAVLINK2_MAGIC:
            return Verdict.MALFORMED
        msgid = frame[7] | (frame[8] << 8) | (frame[9] << 16)
        if not frame[2] & IFLAG_SIGNED:
            return Verdict.UNSIGNED_ALLOWED if msgid in UNSIGNED_ALLOWED_MSGIDS \
                else Verdict.UNSIGNED
        if len(frame) < HEADER_LEN + 2 + SIGNATURE_LEN:
            return Verdict.MALFORMED
        if not hmac.compare_digest(signature(self.key, frame[:-6]), frame[-6:]):
            return Verdict.BAD_SIGNATURE  # before any state is touched
        link_id = frame[-SIGNATURE_LEN]
        ts = int.from_bytes(frame[-12:-6], "little")
        stream = (link_id, frame[5], frame[6])
        last = self.streams.get(stream)
        if last is None:
            if len(self.streams) >= MAX_STREAMS:
                return Verdict.TOO_MANY_STREAMS
            if ts + NEW_STREAM_WINDOW < self.timestamp:
                return Verdict.OLD_STREAM
        elif ts <= last:
            return Verdict.REPLAY
        self.streams[stream] = ts
        self.timestamp = max(self.timestamp, ts)
        return Verdict.SIGNED

    def next_timestamp(self, unix_s: float) -> int:
        """The timestamp for our next outgoing frame: wall time, but always above every
        timestamp we sent or accepted."""
        self.timestamp = min(TIMESTAMP_MAX, max(self.timestamp + 1, timestamp_from_unix(unix_s)))
        return self.timestamp
