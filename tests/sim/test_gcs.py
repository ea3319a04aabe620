"""The ground-station link (docs/reference/wire.md): parameters, missions and the position messages
a
GCS shows, first with a pymavlink client on the emulator's GCS port, then with MAVProxy, a
real ground station, run headless against the ``sim-bridge`` command."""

from __future__ import annotations

import contextlib
import math
import os
import queue
import re
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from sim_bridge.config import with_link
from sim_bridge.follow_target import latlon_from_ned
from sim_bridge.gcs import (
    PARAM_TYPE_INT32,
    PARAM_TYPE_REAL32,
    ParamSpec,
    ParamStore,
    from_wire,
    to_wire,
)
from sim_bridge.px4.streams import CAPABILITIES
from sim_bridge.px4_params import px4_param_specs
from tests.sim.harness import MavClient, RunningSim, make_config, run_sim

ROOT = Path(__file__).resolve().parents[2]
REQUEST_AUTOPILOT_CAPABILITIES = 520
N_PARAMS = len(px4_param_specs(make_config()))  # sim_bridge/px4_params.py


# ------------------------------------------------------------------------ the pure store
def test_int_params_travel_bytewise_and_floats_as_is() -> None:
    for v in (0, 1, 7, 4001, -1, 2**31 - 1, -(2**31)):
        w = to_wire(PARAM_TYPE_INT32, v)
        assert from_wire(PARAM_TYPE_INT32, w) == v
    assert to_wire(PARAM_TYPE_INT32, 1) != 1.0  # a denormal: the bytes, not the number
    assert to_wire(PARAM_TYPE_REAL32, 0.5) == 0.5


def test_store_ranges_and_change_callback() -> None:
    seen: list[tuple[str, float]] = []
    st = ParamStore((ParamSpec("A", PARAM_TYPE_REAL32, 1.0, 0.0, 2.0),
                     ParamSpec("B", PARAM_TYPE_INT32, 3, 0, 7)),
                    on_change=lambda n, v: seen.append((n, v)))
    assert st.set("A", 1.5) == (0, True) and st.value("A") == 1.5
    assert st.set("A", 1.5) == (0, True)  # unchanged: no callback
    assert st.set("A", 2.5) == (0, False) and st.value("A") == 1.5
    assert st.set("A", math.nan) == (0, False)
    assert st.set("B", 5.4) == (1, True) and st.value("B") == 5.0
    assert st.set("C", 1.0) is None
    assert seen == [("A", 1.5), ("B", 5.0)]
    with pytest.raises(ValueError, match="unique"):
        ParamStore((ParamSpec("A", PARAM_TYPE_REAL32, 0.0),) * 2)
    with pytest.raises(ValueError, match="16 characters"):
        ParamSpec("A_VERY_LONG_PARAM_NAME", PARAM_TYPE_REAL32, 0.0)


# ------------------------------------------------------------------------ pymavlink GCS
@contextlib.contextmanager
def _gcs_sim(c: MavClient, **sim_changes: Any) -> Iterator[RunningSim]:
    cfg = with_link(make_config(**sim_changes), gcs_remote=f"127.0.0.1:{c.port}")
    with run_sim(cfg) as rs:
        c.target = ("127.0.0.1", rs.ports["gcs"])
        yield rs


def _gcs_client() -> MavClient:
    return MavClient(sysid=255, compid=190)  # a ground station's ids


def _params(msgs: list[Any]) -> dict[str, Any]:
    return {m.param_id: m for m in msgs if m.get_type() == "PARAM_VALUE"}


def test_gcs_port_streams_what_a_ground_station_shows() -> None:
    c = _gcs_client()
    try:
        with _gcs_sim(c) as rs:
            msgs = c.collect(1.2)
            origin = rs.sim.cfg.target
    finally:
        c.close()
    kinds = {m.get_type() for m in msgs}
    assert {"HEARTBEAT", "SYS_STATUS", "GLOBAL_POSITION_INT", "LOCAL_POSITION_NED"} <= kinds
    hb = next(m for m in msgs if m.get_type() == "HEARTBEAT")
    assert (hb.type, hb.autopilot, hb.base_mode & 128) == (2, 12, 128)
    lp = next(m for m in msgs if m.get_type() == "LOCAL_POSITION_NED")
    gp = next(m for m in msgs if m.get_type() == "GLOBAL_POSITION_INT")
    lat, lon, alt = latlon_from_ned([lp.x, lp.y, lp.z], origin.origin_lat_deg,
                                    origin.origin_lon_deg, origin.origin_alt_m)
    assert abs(gp.lat - lat * 1e7) <= 2 and abs(gp.lon - lon * 1e7) <= 2
    assert abs(gp.alt - alt * 1000) <= 5 and abs(gp.alt - (origin.origin_alt_m + 3.2) * 1000) < 5
    assert abs(gp.relative_alt) <= 5  # at home: airborne start, home = start pose


def test_parameter_protocol() -> None:
    c = _gcs_client()
    try:
        with _gcs_sim(c) as rs:
            c.send(c.mav.param_request_list_encode(1, 1))
            got = c.collect(0.5)
            plist = [m for m in got if m.get_type() == "PARAM_VALUE"]
            c.send(c.mav.param_request_read_encode(1, 1, b"MPC_THR_HOVER", -1))
            by_name = c.wait_for(lambda m: m.get_type() == "PARAM_VALUE", 1.0)
            c.send(c.mav.param_request_read_encode(1, 1, b"", 10))
            by_index = c.wait_for(lambda m: m.get_type() == "PARAM_VALUE", 1.0)
            c.send(c.mav.param_request_read_encode(1, 1, b"NO_SUCH_PARAM", -1))
            unknown = c.wait_for(lambda m: m.get_type() == "PARAM_VALUE", 0.3)
            # PARAM_SET: float, then an int32 sent byte-wise; both echoed and in force
            c.send(c.mav.param_set_encode(1, 1, b"COM_OF_LOSS_T", 2.5, PARAM_TYPE_REAL32))
            echo_f = c.wait_for(lambda m: m.get_type() == "PARAM_VALUE", 1.0)
            c.send(c.mav.param_set_encode(1, 1, b"COM_OBL_RC_ACT",
                                          to_wire(PARAM_TYPE_INT32, 4), PARAM_TYPE_INT32))
            echo_i = c.wait_for(lambda m: m.get_type() == "PARAM_VALUE", 1.0)
            c.send(c.mav.param_set_encode(1, 1, b"COM_OBL_RC_ACT",
                                          to_wire(PARAM_TYPE_INT32, 9), PARAM_TYPE_INT32))
            refused = c.wait_for(lambda m: m.get_type() == "PARAM_VALUE", 1.0)
            p = rs.call(lambda: rs.sim.px4.p)
    finally:
        c.close()
    assert len(plist) == N_PARAMS
    assert sorted(m.param_index for m in plist) == list(range(N_PARAMS))
    assert {m.param_count for m in plist} == {N_PARAMS}
    ps = _params(plist)
    assert {"MPC_THR_HOVER", "COM_OF_LOSS_T", "COM_OBL_RC_ACT", "MAV_SYS_ID"} <= set(ps)
    assert ps["MPC_THR_HOVER"].param_value == 0.5 and ps["MPC_THR_HOVER"].param_type == 9
    assert from_wire(6, ps["MAV_SYS_ID"].param_value) == 1 and ps["MAV_SYS_ID"].param_type == 6
    assert by_name is not None and by_name.param_id == "MPC_THR_HOVER"
    assert by_index is not None and by_index.param_index == 10
    assert unknown is None
    assert echo_f is not None and (echo_f.param_id, echo_f.param_value) == ("COM_OF_LOSS_T", 2.5)
    assert echo_i is not None and from_wire(6, echo_i.param_value) == 4
    assert refused is not None and from_wire(6, refused.param_value) == 4  # 9 is out of range
    assert (p.com_of_loss_t_s, p.com_obl_rc_act) == (2.5, 4)  # the commander uses them


def test_mission_protocol_and_autopilot_version() -> None:
    c = _gcs_client()
    try:
        with _gcs_sim(c):
            c.send(c.mav.mission_request_list_encode(1, 1, 0))
            count = c.wait_for(lambda m: m.get_type() == "MISSION_COUNT", 1.0)
            c.send(c.mav.mission_request_list_encode(1, 1, 1))  # geofence
            fence = c.wait_for(lambda m: m.get_type() == "MISSION_COUNT", 1.0)
            c.send(c.mav.mission_clear_all_encode(1, 1, 0))
            ack = c.wait_for(lambda m: m.get_type() == "MISSION_ACK", 1.0)
            c.send(c.mav.mission_count_encode(1, 1, 3, 0))
            upload = c.wait_for(lambda m: m.get_type() == "MISSION_ACK", 1.0)
            c.command(REQUEST_AUTOPILOT_CAPABILITIES, 1)
            av = c.wait_for(lambda m: m.get_type() == "AUTOPILOT_VERSION", 1.0)
            c.command(512, 242)  # REQUEST_MESSAGE HOME_POSITION
            home = c.wait_for(lambda m: m.get_type() == "HOME_POSITION", 1.0)
    finally:
        c.close()
    assert count is not None and (count.count, count.mission_type) == (0, 0)
    assert (count.target_system, count.target_component) == (255, 190)
    assert fence is not None and (fence.count, fence.mission_type) == (0, 1)
    assert ack is not None and ack.type == 0
    assert upload is not None and upload.type == 3  # MAV_MISSION_UNSUPPORTED
    assert av is not None and av.capabilities == CAPABILITIES
    assert av.capabilities & 16 and av.capabilities & 8192  # PARAM_ENCODE_BYTEWISE, MAVLINK2
    assert home is not None and math.isclose(home.z, -3.2, abs_tol=1e-6)


# ------------------------------------------------------------------------ MAVProxy
class _Proc:
    """A process whose stdout lines are collected by a thread, with expect()."""

    def __init__(self, args: list[str], cwd: Path, stdin: bool = False) -> None:
        env = dict(os.environ, PYTHONPATH=str(ROOT), PYTHONUNBUFFERED="1")
        self.p = subprocess.Popen(args, cwd=cwd, env=env, text=True,
                                  stdin=subprocess.PIPE if stdin else subprocess.DEVNULL,
                                  stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
        self.lines: queue.Queue[str] = queue.Queue()
        self.seen: list[str] = []
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        assert self.p.stdout is not None
        for line in self.p.stdout:
            self.lines.put(line.rstrip("\n"))

    def expect(self, pattern: str, timeout_s: float) -> re.Match[str]:
        rx = re.compile(pattern)
        for line in self.seen:
            if m := rx.search(line):
                self.seen.remove(line)
                return m
        end = time.monotonic() + timeout_s
        while (left := end - time.monotonic()) > 0:
            try:
                line = self.lines.get(timeout=left)
            except queue.Empty:
                break
            if m := rx.search(line):
                return m
            self.seen.append(line)
        raise AssertionError(f"no line matching {pattern!r} in {timeout_s} s; got:\n"
                             + "\n".join(self.seen[-40:]))

    def send(self, line: str) -> None:
        assert self.p.stdin is not None
        self.p.stdin.write(line + "\n")
        self.p.stdin.flush()

    def stop(self) -> None:
        if self.p.poll() is None:
            self.p.terminate()
            try:
                self.p.wait(5.0)
            except subprocess.TimeoutExpired:
                self.p.kill()
                self.p.wait(5.0)
        self._reader.join(5.0)  # EOF once the process is gone
        for f in (self.p.stdin, self.p.stdout):
            if f is not None:
                with contextlib.suppress(OSError):
                    f.close()


def _free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        port: int = s.getsockname()[1]
        return port


@pytest.mark.slow
@pytest.mark.timeout(60)
def test_mavproxy_sees_mode_arming_position_params_and_missions(tmp_path: Path) -> None:
    """MAVProxy (headless, commands on stdin) on the port the emulator's GCS link sends to:
    it detects the vehicle, reports ARMED and POSCTL, downloads the parameters, shows the
    position, sets a parameter, lists an empty mission and switches the mode to Hold."""
    pytest.importorskip("MAVProxy")
    gcs_port = _free_udp_port()
    sim = _Proc([sys.executable, "-m", "sim_bridge", "--duration", "40", "--bind", "127.0.0.1",
                 "--offboard-port", "0", "--agv-port", "0", "--frame-port", "0",
                 "--gcs-port", "0", "--gcs-remote", f"127.0.0.1:{gcs_port}",
                 "--offboard-remote", f"127.0.0.1:{_free_udp_port()}",
                 "--truth-remote", f"127.0.0.1:{_free_udp_port()}"], tmp_path)
    mp: _Proc | None = None
    try:
        sim.expect(r"GCS udp", 10.0)
        mp = _Proc([sys.executable, "-m", "MAVProxy.mavproxy",
                    f"--master=udpin:127.0.0.1:{gcs_port}", f"--state-basedir={tmp_path}",
                    "--default-modules=link,param,wp,mode,cmdlong,arm,misc"],
                   tmp_path, stdin=True)
        mp.expect(r"Detected vehicle 1:1", 15.0)
        mp.expect(r"^ARMED|ARMED$", 5.0)
        mp.expect(r"Mode POSCTL", 5.0)
        mp.expect(rf"Received {N_PARAMS} parameters", 15.0)
        mp.send("status GLOBAL_POSITION_INT")
        g = mp.expect(r"GLOBAL_POSITION_INT \{.*lat : (-?\d+), lon : (-?\d+), alt : (-?\d+)",
                      5.0)
        lat, lon, alt = latlon_from_ned([-0.2, 0.4, -3.2], 47.397742, 8.545594, 488.0)
        assert abs(int(g[1]) - lat * 1e7) < 20 and abs(int(g[2]) - lon * 1e7) < 20
        assert abs(int(g[3]) - alt * 1000) < 50
        mp.send("status HEARTBEAT")
        h = mp.expect(r"HEARTBEAT \{.*base_mode : (\d+), custom_mode : (\d+)", 5.0)
        assert int(h[1]) & 128 and int(h[2]) == 3 << 16  # armed, POSCTL
        mp.send("param show COM_OBL_RC_ACT")
        mp.expect(r"COM_OBL_RC_ACT\s+0\b", 5.0)
        mp.send("param set COM_OBL_RC_ACT 5")  # MAVProxy queues the set: read back until seen
        for _ in range(10):
            mp.send("param fetch COM_OBL_RC_ACT")
            if mp.expect(r"COM_OBL_RC_ACT = (\d+)", 5.0)[1] == "5":
                break
            time.sleep(0.3)
        else:
            raise AssertionError("COM_OBL_RC_ACT never read back as 5")
        mp.send("wp list")
        mp.expect(r"(?i)requesting 0 waypoints|no waypoints|0 waypoints", 5.0)
        # MAVProxy 1.8.74's "mode LOITER" hands pymavlink 2.4.50 a tuple for a PX4 vehicle and
        # fails ("required argument is not a float"): send the DO_SET_MODE it would have sent
        mp.send("long DO_SET_MODE 1 4 3")  # custom mode, AUTO, LOITER (Hold)
        mp.expect(r"DO_SET_MODE.*ACCEPTED", 5.0)
        mp.expect(r"Mode AUTO_LOITER|Mode LOITER", 5.0)
    finally:
        if mp is not None:
            mp.stop()
        sim.stop()
