"""The link's receive path: is a parsed frame one we accept? (hostile input, in order).

Each rejection increments ``counters[reason]``: ``bad_data`` / ``unknown_msgid`` (robust parser
pseudo-messages), ``mavlink1`` (MAVLink 2 only), ``unused`` (a message a known source may send
but we do not use, e.g. PX4's other streams: counted, not passed to ``on_reject``),
``not_whitelisted`` (any other source; see :class:`~companion.link.filters.AllowRule`),
``spoofed_source``, signing (``unsigned``, ``bad_signature``, ``old_timestamp``,
``stale_stream``), ``duplicate`` (same bytes as one of the last frames of that source), values
(``non_finite``, ``quaternion_norm``, ``speed``, ``angular_rate``). The transports add
``incomplete`` and ``parser_error`` through :meth:`ReceivePath.reject`.

Signatures are verified HERE, not by pymavlink, because pymavlink 2.4.50 stores a frame's
timestamp before checking its signature: one forged frame stamped 2^48-2 would block every
later legitimate frame of that stream. We check the signature first and only then update the
stream's timestamp (as the C library does).
"""

from __future__ import annotations

import logging
import math
from collections import Counter, OrderedDict
from collections.abc import Callable, Sequence
from typing import Any, Literal

import fastcrc
from pymavlink.dialects.v20 import common as mavlink2

from companion.link import wire
from companion.link.filters import AllowRule, ValueLimits, check_fields
from companion.link.guard import GuardParams, SourceGuard
from companion.link.messages import Received, message_fields, received
from companion.link.px4 import MAVLINK2_MAGIC
from companion.link.signing import SignatureVerifier

log = logging.getLogger(__name__)

_DEDUP_WINDOW = 64
_MIN_FRAME = wire.HEADER_LEN + wire.CRC_LEN
_SIGNED_TAIL = wire.CRC_LEN + wire.SIGNATURE_LEN
_UNKNOWN = object()
_mcrf4xx = fastcrc.crc16.mcrf4xx


def new_parser() -> Any:
    """A robust pymavlink parser (bad bytes become BAD_DATA pseudo-messages)."""
    p = mavlink2.MAVLink(None)
    p.robust_parsing = True
    return p


def reset_parser(p: Any) -> Any:
    """``p`` (from :func:`new_parser`) back to the framing state of a new one, so one parser
    serves every datagram and no datagram's leftovers reach the next (a new parser costs
    ~4 us a datagram). Only the framing state persists between frames in pymavlink 2.4:
    the buffer, its read index, the expected length and the prefix-error flag; the
    parser's own signing is unused (signatures are checked by :class:`ReceivePath`)."""
    p.buf = bytearray()
    p.buf_index = 0
    p.expected_length = mavlink2.HEADER_LEN_V1 + 2
    p.have_prefix_error = False
    return p


class ReceivePath:
    """The accept/reject decision for parsed frames (see the module docstring).

    ``enc``: the link's encoder, whose signing timestamp is kept ahead of every verified
    incoming one (MAVLink signing rule); ``counters``: the link's counters;
    ``on_reject(reason, raw, t_ns)``: at most ``guard.reject_log_per_s`` per second (a 5 s
    burst), every rejection being counted."""

    def __init__(self, rules: Sequence[AllowRule], guard: SourceGuard, params: GuardParams,
                 limits: ValueLimits, verifier: SignatureVerifier | None, enc: Any,
                 counters: Counter[str],
                 on_reject: Callable[[str, bytes, int], None] | None) -> None:
        self.rules = [(r.sysid, r.compid, r.msgids()) for r in rules]
        self.guard, self.params, self.limits = guard, params, limits
        self.verifier, self._enc, self.counters = verifier, enc, counters
        self.on_reject = on_reject
        self._reject_tokens = 5.0 * params.reject_log_per_s  # 5 s burst
        self._t_reject_ns = 0
        self._recent: dict[tuple[int, int], OrderedDict[bytes, None]] = {}
        self._allowed: dict[tuple[int, int, int], bool] = {}  # the rules' answers, memoised
        self._plans: dict[tuple[int, int, int], Any] = {}  # the fast path's (_plan)

    def reject(self, reason: str, raw: bytes, t_ns: int) -> None:
        self.counters[reason] += 1
        self.counters["rejected"] += 1
        if self.on_reject is None:
            return
        rate = self.params.reject_log_per_s
        dt = max(t_ns - self._t_reject_ns, 0) * 1e-9
        self._t_reject_ns = t_ns
        self._reject_tokens = min(5.0 * rate, self._reject_tokens + dt * rate)
        if self._reject_tokens < 1.0:
            self.counters["reject_log_suppressed"] += 1
            return
        self._reject_tokens -= 1.0
        self.on_reject(reason, raw[:512], t_ns)

    def from_known_system(self, sysid: int, compid: int) -> bool:
        """The frame names a source some rule accepts messages from (the autopilot, the AGV)."""
        return any(s == sysid and (c is None or c == compid) for s, c, _ in self.rules)

    def allowed(self, sysid: int, compid: int, msgid: int) -> bool:
        key = (sysid, compid, msgid)
        ok = self._allowed.get(key)
        if ok is None:
            ok = any(s == sysid and (c is None or c == compid) and (ids is None or msgid in ids)
                     for s, c, ids in self.rules)
            if len(self._allowed) < 65536:  # bounded: a flood of made-up ids cannot grow it
                self._allowed[key] = ok
        return ok

    def _framing(self, name: str, raw: bytes) -> str | None:
        if name == "BAD_DATA":
            return "bad_data"
        if name.startswith("UNKNOWN_"):
            return "unknown_msgid"
        if not raw or raw[0] != MAVLINK2_MAGIC:
            return "mavlink1"
        return None

    def _signed_ok(self, raw: bytes, sysid: int, compid: int, msgid: int) -> str | None:
        if self.verifier is None:
            return None
        why = self.verifier.check(raw, sysid, compid, msgid)
        if why is None:
            # keep our outgoing timestamps ahead of what we have seen (MAVLink signing rule)
            self._enc.signing.timestamp = max(
                self._enc.signing.timestamp, self.verifier.max_timestamp_10us + 1)
        return why

    def accept(self, m: Any, t_ns: int, addr: tuple[str, int] | None) -> Received | None:
        """The parsed frame ``m`` (received at ``t_ns`` from ``addr``, None on a stream) as a
        :class:`Received`, or ``None`` when it is rejected (counted, maybe reported)."""
        name = m.get_type()
        raw = bytes(m.get_msgbuf())
        why = self._framing(name, raw)
        if why is not None:
            self.reject(why, raw, t_ns)
            return None
        sysid, compid, msgid = m.get_srcSystem(), m.get_srcComponent(), m.get_msgId()
        if not self.allowed(sysid, compid, msgid):
            self._not_allowed(sysid, compid, raw, t_ns)
            return None
        signed = bool(raw[2] & mavlink2.MAVLINK_IFLAG_SIGNED)
        return self._checked(m, raw, name, sysid, compid, msgid, m.get_seq(), signed,
                             message_fields(m), t_ns, addr)

    def accept_datagram(self, data: bytes, t_ns: int,
                        addr: tuple[str, int] | None) -> Received | Literal[False] | None:
        """The fast path (:mod:`companion.link.wire`) for a datagram holding one MAVLink 2
        frame: a :class:`Received`, ``None`` when it is rejected or unused (counted), or
        ``False`` when the robust parser must read it (not one frame, an unknown msgid, a bad
        CRC, a source no rule knows: the parser's path gives the reason it always gave). A
        message nothing uses is counted from its header alone, its CRC unchecked: it is never
        decoded, delivered or acted on."""
        # the header at its offsets (wire.single_frame_header, inline: every datagram)
        n = len(data)
        if n < _MIN_FRAME or data[0] != wire.MAGIC_V2:
            return False
        flags = data[2]
        if flags & ~wire.IFLAG_SIGNED:
            return False  # an incompat flag we do not know: the parser decides
        end = wire.HEADER_LEN + data[1]
        if n != end + (_SIGNED_TAIL if flags else wire.CRC_LEN):
            return False  # not exactly one frame
        key = (data[5], data[6], data[7] | data[8] << 8 | data[9] << 16)
        s = self._plans.get(key, _UNKNOWN)
        if s is _UNKNOWN:
            s = self._plan(key)
        if s is None:
            self.counters["unused"] += 1
            return None
        if s is False or _mcrf4xx(s.crc_extra, _mcrf4xx(data[1:end], 0xFFFF)) != (
                data[end] | data[end + 1] << 8):
            return False
        payload = data[wire.HEADER_LEN:end]
        if len(payload) < s.size:  # MAVLink 2 dropped the trailing zeros: put them back
            payload += bytes(s.size - len(payload))
        t = s.unpacker.unpack(payload)
        get = s.floats
        return self._checked(wire.LazyMessage(data), data, s.name, key[0], key[1], key[2],
                             data[4], bool(flags), s.fields(t), t_ns, addr,
                             get is None or math.isfinite(sum(get(t))))

    def _plan(self, key: tuple[int, int, int]) -> Any:
        """What the fast path does with a frame of (sysid, compid, msgid), memoised: its
        :class:`wire._Spec` (decode it), None (a message of a known source nobody uses:
        counted ``unused``) or False (the robust parser reads it: a source no rule knows, a
        msgid outside the dialect)."""
        sysid, compid, msgid = key
        if not self.allowed(sysid, compid, msgid):
            plan: Any = None if self.from_known_system(sysid, compid) else False
        else:
            sp = wire.spec(msgid)
            plan = False if sp is None else sp
        if len(self._plans) < 65536:  # bounded: a flood of made-up ids cannot grow it
            self._plans[key] = plan
        return plan

    def _not_allowed(self, sysid: int, compid: int, raw: bytes, t_ns: int) -> None:
        if self.from_known_system(sysid, compid):
            # PX4's own streams we do not use (an onboard link carries dozens: HIGHRES_IMU,
            # ODOMETRY, VFR_HUD, ...): counted, never delivered, not logged as an attack
            self.counters["unused"] += 1
            return
        self.reject("not_whitelisted", raw, t_ns)

    def _checked(self, msg: Any, raw: bytes, name: str, sysid: int, compid: int, msgid: int,
                 seq: int, signed: bool, fields: dict[str, Any], t_ns: int,
                 addr: tuple[str, int] | None, all_finite: bool = False) -> Received | None:
        """The checks after decoding (source address, signature, duplicate, values), in
        order, for both paths (``all_finite``: every float is known finite)."""
        if not self.guard.frame_source_ok(sysid, compid, addr, t_ns):
            self.reject("spoofed_source", raw, t_ns)
            return None
        why = self._signed_ok(raw, sysid, compid, msgid)
        if why is not None:
            self.reject(why, raw, t_ns)
            return None
        recent = self._recent.get((sysid, compid))
        if recent is None:
            recent = self._recent[(sysid, compid)] = OrderedDict()
        if raw in recent:
            self.reject("duplicate", raw, t_ns)
            return None
        why = check_fields(name, fields, self.limits, all_finite)
        if why is not None:
            self.reject(why, raw, t_ns)
            return None
        recent[raw] = None
        if len(recent) > _DEDUP_WINDOW:
            recent.popitem(last=False)
        return received(msg, raw, t_ns, sysid, compid, msgid, name, seq,
                        self.verifier is not None and signed, fields)
