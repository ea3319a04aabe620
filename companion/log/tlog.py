"""Export the MAVLink traffic of an MCAP flight log as a telemetry log (``.tlog``).

A tlog is what MAVProxy and QGroundControl write: for every MAVLink frame, an 8-byte
big-endian timestamp (microseconds since the Unix epoch) followed by the frame's bytes as they
were on the wire. pymavlink (``mavutil.mavlink_connection("x.tlog")``, ``mavlogdump.py``),
MAVExplorer and QGroundControl's log replay read it.

The frames are the raw bytes the companion logged on ``/mavlink/in/<NAME>`` (received from the
autopilot and the target) and ``/mavlink/out/<NAME>`` (sent), in log-time order; each frame is
parsed again before it is written, and a frame that does not decode as the message its topic
names is skipped and counted, never written.

Time: the MCAP log time is a monotonic clock (or simulated time). With ``time_base="auto"``
the first SYSTEM_TIME from the autopilot with a non-zero ``time_unix_usec`` anchors it to
Unix time (the autopilot's clock, as a GCS would show it); without one, or with
``time_base="log"``, the log times are written as they are (tools then show dates near 1970).
"""

from __future__ import annotations

import base64
import binascii
import os
import struct
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

from companion import CompanionError
from companion.log.reader import LogReader

MAVLINK_TOPICS = ("/mavlink/in/", "/mavlink/out/")
TIME_BASES = ("auto", "log")
_STAMP = struct.Struct(">Q")


class TlogExportError(CompanionError):
    """The log cannot be exported (no MAVLink traffic, unwritable output, bad option)."""


@dataclass(frozen=True)
class TlogExport:
    """What :func:`export_tlog` wrote: ``frames`` and their ``types`` (name -> count),
    ``skipped`` frames that did not decode, the timestamps of the first and last frame (us),
    and ``time_base``: ``"SYSTEM_TIME"`` (anchored to the autopilot's Unix time) or ``"log"``."""

    path: Path
    frames: int
    skipped: int
    first_us: int
    last_us: int
    time_base: str
    offset_ns: int
    types: dict[str, int] = field(default_factory=dict)


def _parser() -> object:
    from pymavlink.dialects.v20 import common as mavlink2

    mav = mavlink2.MAVLink(None)
    mav.robust_parsing = True
    return mav


def _decode(raw: bytes, name: str) -> bool:
    """True when ``raw`` is exactly one MAVLink frame of message ``name``."""
    mav = _parser()
    try:
        msgs = mav.parse_buffer(raw) or []  # type: ignore[attr-defined]
    except Exception:  # pymavlink raises its own and struct errors on garbage
        return False
    return len(msgs) == 1 and msgs[0].get_type() == name


def _anchor_ns(reader: LogReader) -> int | None:
    """Unix time minus log time (ns), from the first SYSTEM_TIME with a Unix time."""
    for m in reader.messages(["/mavlink/in/SYSTEM_TIME"]):
        fields = (m.data or {}).get("fields") or {}
        unix_us = fields.get("time_unix_usec")
        if isinstance(unix_us, int) and unix_us > 0:
            return unix_us * 1000 - m.log_time_ns
    return None


def export_tlog(log_path: str | Path, out_path: str | Path, time_base: str = "auto") -> TlogExport:
    """Write the MAVLink frames of ``log_path`` (an MCAP flight log) to ``out_path`` as a tlog.
    The file appears only when complete (written next to it, then renamed)."""
    if time_base not in TIME_BASES:
        raise TlogExportError(f"time base {time_base!r} not in {TIME_BASES}")
    out = Path(out_path)
    tmp = out.with_name(out.name + ".part")
    types: Counter[str] = Counter()
    skipped = 0
    first_us = last_us = -1
    with LogReader(log_path) as reader:
        topics = [c.topic for c in reader.channels if c.topic.startswith(MAVLINK_TOPICS)]
        if not topics:
            raise TlogExportError(f"{log_path}: no MAVLink messages (/mavlink/in|out/*) to export")
        offset = _anchor_ns(reader) if time_base == "auto" else None
        used = "SYSTEM_TIME" if offset is not None else "log"
        offset = offset or 0
        try:
            with open(tmp, "wb") as f:
                for m in reader.messages(topics):
                    name = m.topic.rsplit("/", 1)[-1]
                    try:
                        raw = base64.b64decode((m.data or {}).get("raw_b64") or "", validate=True)
                    except (binascii.Error, ValueError, TypeError):
                        raw = b""
                    t_us = (m.log_time_ns + offset) // 1000
                    if not raw or t_us < 0 or not _decode(raw, name):
                        skipped += 1
                        continue
                    f.write(_STAMP.pack(t_us))
                    f.write(raw)
                    types[name] += 1
                    if first_us < 0:
                        first_us = t_us
                    last_us = t_us
                f.flush()
                os.fsync(f.fileno())
            if not types:
                tmp.unlink(missing_ok=True)
                raise TlogExportError(f"{log_path}: none of {skipped} MAVLink frames decoded")
            os.replace(tmp, out)
        except OSError as e:
            tmp.unlink(missing_ok=True)
            raise TlogExportError(f"cannot write {out}: {e.strerror or e}") from e
    return TlogExport(
        out,
        sum(types.values()),
        skipped,
        first_us,
        last_us,
        used,
        offset,
        dict(sorted(types.items())),
    )
