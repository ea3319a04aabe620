"""``companion log export --tlog``: a real MCAP log of real MAVLink frames, exported, then read
back by pymavlink's own tlog reader and by its ``mavlogdump.py`` tool."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
from pymavlink import mavutil
from pymavlink.dialects.v20 import common as mavlink2

from companion.cli import main
from companion.link import Received, Sent
from companion.log.tlog import TlogExportError, export_tlog
from companion.log.writer import McapLogger

UNIX_T0_US = 1_763_900_000_000_000  # SYSTEM_TIME's Unix time at log time T_SYS_NS
T_SYS_NS = 2_000_000_000


class _Buf:
    def write(self, b: bytes) -> None:
        pass


def _mav(sysid: int, compid: int) -> Any:
    m = mavlink2.MAVLink(_Buf(), srcSystem=sysid, srcComponent=compid)
    return m


def _rx(mav: Any, msg: Any, t_ns: int) -> Received:
    raw = bytes(msg.pack(mav))
    back = mavlink2.MAVLink(None).decode(bytearray(raw))
    return Received(
        back,
        raw,
        t_ns,
        mav.srcSystem,
        mav.srcComponent,
        back.get_msgId(),
        back.get_type(),
        back.get_seq(),
        False,
    )


def _tx(mav: Any, msg: Any, t_ns: int) -> Sent:
    raw = bytes(msg.pack(mav))
    return Sent(msg, raw, t_ns, msg.get_msgId(), msg.get_type())


def _write_log(path: Path, *, with_system_time: bool = True, corrupt: bool = True) -> list[Any]:
    """A log with ~2 s of autopilot traffic in, setpoints out; returns what it holds as
    (log time ns, type) in order."""
    ap, comp = _mav(1, 1), _mav(1, 191)
    expected: list[Any] = []
    with McapLogger(path) as lg:
        for i in range(40):
            t = 1_000_000_000 + i * 50_000_000  # 20 Hz from t = 1 s
            items: list[tuple[str, Any]] = [
                (
                    "in",
                    _rx(
                        ap,
                        mavlink2.MAVLink_attitude_quaternion_message(
                            i * 50, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, [0.0] * 4
                        ),
                        t,
                    ),
                ),
                (
                    "out",
                    _tx(
                        comp,
                        mavlink2.MAVLink_set_attitude_target_message(
                            i * 50, 1, 1, 7, [1.0, 0.0, 0.0, 0.0], 0.0, 0.0, 0.0, 0.5
                        ),
                        t + 1000,
                    ),
                ),
            ]
            if i % 20 == 0:
                items.append(
                    (
                        "in",
                        _rx(
                            ap,
                            mavlink2.MAVLink_heartbeat_message(2, 12, 209, 6 << 16, 4, 3),
                            t + 2000,
                        ),
                    )
                )
            if with_system_time and t == T_SYS_NS:
                items.append(
                    (
                        "in",
                        _rx(ap, mavlink2.MAVLink_system_time_message(UNIX_T0_US, i * 50), t + 3000),
                    )
                )
            for direction, item in items:
                lg.log_mavlink(direction, item)
                expected.append(((item.t_rx_ns if direction == "in" else item.t_tx_ns), item.name))
        if corrupt:  # a frame whose bytes do not decode as its topic says: skipped, counted
            bad = _rx(ap, mavlink2.MAVLink_heartbeat_message(2, 12, 209, 0, 4, 3), 4_000_000_000)
            lg.log_mavlink(
                "in",
                Received(
                    bad.msg,
                    bad.raw[:-3] + b"\x00\x00\x00",
                    bad.t_rx_ns,
                    1,
                    1,
                    0,
                    "HEARTBEAT",
                    0,
                    False,
                ),
            )
    return sorted(expected, key=lambda e: e[0])


def _read_tlog(path: Path) -> list[tuple[float, str, Any]]:
    conn = mavutil.mavlink_connection(str(path))
    out = []
    while (m := conn.recv_match()) is not None:
        if m.get_type() != "BAD_DATA":
            out.append((m._timestamp, m.get_type(), m))
    conn.close()
    return out


def test_round_trip_through_pymavlink_anchored_on_system_time(tmp_path: Path) -> None:
    expected = _write_log(tmp_path / "f.mcap")
    res = export_tlog(tmp_path / "f.mcap", tmp_path / "f.tlog")
    assert res.time_base == "SYSTEM_TIME" and res.skipped == 1
    assert res.frames == len(expected)
    got = _read_tlog(tmp_path / "f.tlog")
    assert [name for _, name, _ in got] == [name for _, name in expected]
    offset_s = UNIX_T0_US * 1e-6 - (T_SYS_NS + 3000) * 1e-9
    for (ts, _, _), (t_ns, _) in zip(got, expected, strict=True):
        assert ts == pytest.approx(t_ns * 1e-9 + offset_s, abs=2e-6)  # us resolution
    assert got[0][0] == pytest.approx(UNIX_T0_US * 1e-6 - 1.0, abs=1e-3)  # a 2025 date
    # fields survive: the setpoints' thrust and the autopilot's mode
    sat = [m for _, n, m in got if n == "SET_ATTITUDE_TARGET"]
    assert len(sat) == 40 and all(m.thrust == pytest.approx(0.5) for m in sat)
    hb = [m for _, n, m in got if n == "HEARTBEAT"]
    assert [m.custom_mode for m in hb] == [6 << 16, 6 << 16]
    assert {m.get_srcSystem() for _, _, m in got} == {1}
    assert {m.get_srcComponent() for _, n, m in got if n == "SET_ATTITUDE_TARGET"} == {191}


def test_log_time_base_and_the_cli(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    expected = _write_log(tmp_path / "f.mcap", with_system_time=False, corrupt=False)
    out = tmp_path / "f.tlog"
    assert main(["log", "export", "--tlog", str(out), str(tmp_path / "f.mcap")]) == 0
    text = capsys.readouterr().out
    assert f"wrote {len(expected)} MAVLink frames" in text and "time base: log" in text
    got = _read_tlog(out)
    assert [t for t, _, _ in got] == pytest.approx([t * 1e-9 for t, _ in expected], abs=2e-6)


def test_mavlogdump_reads_it(tmp_path: Path) -> None:
    tool = shutil.which("mavlogdump.py")
    if tool is None:
        pytest.skip("pymavlink's mavlogdump.py is not on PATH")
    expected = _write_log(tmp_path / "f.mcap")
    export_tlog(tmp_path / "f.mcap", tmp_path / "f.tlog")
    p = subprocess.run(
        [
            sys.executable,
            tool,
            "--types",
            "SET_ATTITUDE_TARGET,HEARTBEAT",
            str(tmp_path / "f.tlog"),
        ],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert p.returncode == 0, p.stderr
    lines = [ln for ln in p.stdout.splitlines() if ln.strip()]
    assert len(lines) == sum(1 for _, n in expected if n in ("SET_ATTITUDE_TARGET", "HEARTBEAT"))
    assert lines[0].startswith("2025-") and "SET_ATTITUDE_TARGET" in lines[0]


def test_bad_inputs_fail_clearly_and_write_nothing(tmp_path: Path) -> None:
    with McapLogger(tmp_path / "empty.mcap") as lg:
        lg.log_text("/control/safety", 1, "nominal")
    out = tmp_path / "x.tlog"
    with pytest.raises(TlogExportError, match="no MAVLink messages"):
        export_tlog(tmp_path / "empty.mcap", out)
    with pytest.raises(TlogExportError, match="time base"):
        export_tlog(tmp_path / "empty.mcap", out, time_base="gps")
    (tmp_path / "junk.mcap").write_bytes(b"not an mcap file at all")
    assert main(["log", "export", "--tlog", str(out), str(tmp_path / "junk.mcap")]) == 2
    assert not out.exists() and not (tmp_path / "x.tlog.part").exists()
