"""``companion log lag``: the first-order tilt lag fitted from setpoints and attitude.

The synthetic vehicles here are integrated on a 1 ms grid (exact step of the lag for a held
command), independently of the fit's event-by-event simulation; the logs are real MCAP files of
real MAVLink frames written by the companion's logger and read back by its reader.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from pymavlink.dialects.v20 import common as mavlink2

from companion.cli import main
from companion.link import Received, Sent
from companion.log.lag import LagFitError, Series, fit_lag, measure_lag, roll_pitch_from_quat
from companion.log.writer import McapLogger

H_S = 0.001  # the synthetic vehicles' integration step
NOISE_RAD = math.radians(0.1)  # measurement noise of the attitude (std)


def _commands(rng: np.random.Generator, t: np.ndarray) -> np.ndarray:
    """Roll/pitch setpoints (rad) at times ``t``: slow sines plus random steps every 0.5 s
    (a few degrees: what a controller chasing a target asks for)."""
    steps = rng.uniform(-0.06, 0.06, size=(int(t[-1] / 0.5) + 2, 2))
    k = (t / 0.5).astype(int)
    sines = np.stack([0.05 * np.sin(2 * np.pi * 0.4 * t), 0.04 * np.cos(2 * np.pi * 0.27 * t)], 1)
    return steps[k] + sines


def _fly(cmd_t: np.ndarray, cmd: np.ndarray, tau_s: float, delay_s: float, t_end: float,
         y0: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The true attitude on a 1 ms grid: each step, the command in force ``delay_s`` ago
    (held from the last setpoint), reached through the exact first-order step."""
    grid = np.arange(cmd_t[0], t_end, H_S)
    a = math.exp(-H_S / tau_s)
    y = np.empty((grid.size, 2))
    cur = np.array(y0, dtype=float)
    k = np.searchsorted(cmd_t, grid - delay_s, side="right") - 1
    for i in range(grid.size):
        y[i] = cur
        u = cmd[k[i]] if k[i] >= 0 else y0
        cur = u + (cur - u) * a
    return grid, y


def _synthetic(tau_s: float, delay_s: float, seed: int, duration_s: float = 30.0
               ) -> tuple[Series, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    cmd_t = np.arange(0.0, duration_s, 0.05) + rng.uniform(0, 0.004, int(duration_s / 0.05))
    cmd_t.sort()
    cmd = _commands(rng, cmd_t)
    grid, y = _fly(cmd_t, cmd, tau_s, delay_s, duration_s, np.zeros(2))
    # attitude sampled at ~50 Hz on the 1 ms grid, with noise
    idx = np.arange(0, grid.size, 20)
    att_t = grid[idx]
    att = y[idx] + rng.normal(0.0, NOISE_RAD, size=(idx.size, 2))
    return Series(cmd_t, cmd, att_t, att), grid, y


@pytest.mark.parametrize("tau_s", [0.08, 0.2])
def test_a_known_lag_and_delay_are_recovered(tau_s: float) -> None:
    s, _, _ = _synthetic(tau_s, 0.03, seed=int(tau_s * 1000))
    res = fit_lag([s])
    # 10 %: the two taus of this test differ by 2.5x, and the lead compensation's error grows
    # with the tau error; a fit off by one grid decade or with a wrong model fails this
    assert res.tau_s == pytest.approx(tau_s, rel=0.10)
    assert res.delay_s == pytest.approx(0.03, abs=0.01)
    assert all(t == pytest.approx(tau_s, rel=0.15) for t in res.per_axis_tau_s)
    # the residual is the measurement noise, and almost all the motion is explained
    assert res.rms_deg == pytest.approx(math.degrees(NOISE_RAD), rel=0.25)
    assert res.variance_explained > 0.95
    assert not res.warnings
    assert res.tau_range_s[0] <= res.tau_s <= res.tau_range_s[1]


def test_a_wrong_tau_fits_worse_than_the_fitted_one() -> None:
    """The squared error really is smallest at the recovered tau: the fit is not merely
    returning its start point."""
    s, _, _ = _synthetic(0.08, 0.0, seed=3)
    best = fit_lag([s], fit_delay=False)
    assert best.tau_s == pytest.approx(0.08, rel=0.10)
    # 0.05 s or 0.2 s are far outside the range whose error is near the best
    assert best.tau_range_s[1] < 0.12 and best.tau_range_s[0] > 0.05


def test_a_command_that_never_moves_is_refused() -> None:
    t = np.arange(0.0, 10.0, 0.05)
    s = Series(t, np.zeros((t.size, 2)), t + 0.01, np.zeros((t.size, 2)))
    with pytest.raises(LagFitError, match="hardly move"):
        fit_lag([s])


def test_roll_pitch_from_quaternion() -> None:
    r, p, y = 0.1, -0.2, 0.7
    cr, sr, cp, sp, cy, sy = (math.cos(r / 2), math.sin(r / 2), math.cos(p / 2),
                              math.sin(p / 2), math.cos(y / 2), math.sin(y / 2))
    q = [cr * cp * cy + sr * sp * sy, sr * cp * cy - cr * sp * sy,
         cr * sp * cy + sr * cp * sy, cr * cp * sy - sr * sp * cy]
    assert roll_pitch_from_quat(np.array([q])) == pytest.approx(np.array([[r, p]]))


# -- real MCAP logs ----------------------------------------------------------------------------


class _Buf:
    def write(self, b: bytes) -> None:
        pass


def _mav(sysid: int, compid: int) -> Any:
    return mavlink2.MAVLink(_Buf(), srcSystem=sysid, srcComponent=compid)


def _rx(mav: Any, msg: Any, t_ns: int) -> Received:
    raw = bytes(msg.pack(mav))
    back = mavlink2.MAVLink(None).decode(bytearray(raw))
    return Received(back, raw, t_ns, mav.srcSystem, mav.srcComponent, back.get_msgId(),
                    back.get_type(), back.get_seq(), False)


def _tx(mav: Any, msg: Any, t_ns: int) -> Sent:
    return Sent(msg, bytes(msg.pack(mav)), t_ns, msg.get_msgId(), msg.get_type())


def _quat(roll: float, pitch: float, yaw: float = 0.3) -> list[float]:
    cr, sr, cp, sp, cy, sy = (math.cos(roll / 2), math.sin(roll / 2), math.cos(pitch / 2),
                              math.sin(pitch / 2), math.cos(yaw / 2), math.sin(yaw / 2))
    return [cr * cp * cy + sr * sp * sy, sr * cp * cy - cr * sp * sy,
            cr * sp * cy + sr * cp * sy, cr * cp * sy - sr * sp * cy]


OFFBOARD = 6 << 16
POSCTL = 3 << 16
T_ON_S, T_OFF_S, T_END_S = 3.0, 27.0, 30.0  # OFFBOARD requested / left; log end (boot time)
BOOT_OFFSET_S = 1234.5  # companion clock - autopilot clock


def _write_flight(path: Path, tau_s: float, *, setpoints: bool = True, nan_from_s: float = 1e9,
                  gap: tuple[float, float] = (14.0, 15.0), chunk_size: int = 1 << 20,
                  quaternion: bool = False, offboard: bool = True) -> None:
    """A receipt-clock log: the autopilot (sysid 1) streams ATTITUDE at 50 Hz (received
    2-8 ms after its stamp, on a companion clock BOOT_OFFSET_S ahead) and a 1 Hz HEARTBEAT;
    the companion streams setpoints at 20 Hz from t = 0. Before T_ON_S (POSCTL) the vehicle
    holds level and ignores them; our DO_SET_MODE(OFFBOARD) is accepted at T_ON_S; at T_OFF_S
    the pilot takes over (POSCTL, no command of ours) and the vehicle levels again. No setpoint
    in ``gap`` (the vehicle holds the last one). Attitude is NaN from ``nan_from_s``;
    ``quaternion``: sent as ATTITUDE_QUATERNION instead of ATTITUDE; ``offboard`` False: our
    request is refused and every heartbeat says POSCTL (the vehicle still flies as above: only
    the log's mode records differ)."""
    rng = np.random.default_rng(7)
    ap, comp = _mav(1, 1), _mav(1, 191)
    cmd_t = np.arange(0.0, T_END_S, 0.05)
    if gap:
        cmd_t = cmd_t[(cmd_t < gap[0]) | (cmd_t >= gap[1])]
    cmd = _commands(rng, cmd_t)
    # the true vehicle: flies our setpoints only in OFFBOARD, level otherwise
    eff = np.where(((cmd_t >= T_ON_S) & (cmd_t < T_OFF_S))[:, None], cmd, 0.0)
    # a command sent before OFFBOARD and still in force when it engages is flown from then
    ev_t = np.concatenate([cmd_t, [T_ON_S, T_OFF_S]])
    ev = np.concatenate([eff, [cmd[cmd_t < T_ON_S][-1], [0.0, 0.0]]])
    order = np.argsort(ev_t, kind="stable")
    grid, y = _fly(ev_t[order], ev[order], tau_s, 0.0, T_END_S, np.zeros(2))
    off = int(BOOT_OFFSET_S * 1e9)
    items: list[tuple[str, Any]] = []
    for i in range(0, grid.size, 20):
        tb = grid[i]
        r, p = y[i] + rng.normal(0.0, NOISE_RAD, 2)
        if tb >= nan_from_s:
            r = p = float("nan")
        if quaternion:  # ATTITUDE_QUATERNION only (a stream set-up without ATTITUDE)
            msg = mavlink2.MAVLink_attitude_quaternion_message(
                round(tb * 1e3), *_quat(r, p), 0.0, 0.0, 0.0, [0.0] * 4)
        else:
            msg = mavlink2.MAVLink_attitude_message(round(tb * 1e3), r, p, 0.3, 0.0, 0.0, 0.0)
        items.append(("in", _rx(ap, msg, off + int((tb + rng.uniform(0.002, 0.008)) * 1e9))))
    for k in range(int(T_END_S)):
        mode = OFFBOARD if offboard and T_ON_S < k + 0.5 <= T_OFF_S else POSCTL
        base = 209 if mode == OFFBOARD else 217
        hb = mavlink2.MAVLink_heartbeat_message(2, 12, base, mode, 4, 3)
        items.append(("in", _rx(ap, hb, off + int((k + 0.5) * 1e9))))
    # our OFFBOARD request and its acceptance
    items.append(("out", _tx(comp, mavlink2.MAVLink_command_long_message(
        1, 1, 176, 0, 1.0, 6.0, 0.0, 0.0, 0.0, 0.0, 0.0), off + int((T_ON_S - 0.01) * 1e9))))
    items.append(("in", _rx(ap, mavlink2.MAVLink_command_ack_message(176, 0 if offboard else 4),
                            off + int(T_ON_S * 1e9))))
    if setpoints:
        for t, (r, p) in zip(cmd_t, cmd, strict=True):
            m = mavlink2.MAVLink_set_attitude_target_message(
                int(t * 1e3), 1, 1, 7, _quat(float(r), float(p)), 0.0, 0.0, 0.0, 0.5)
            items.append(("out", _tx(comp, m, off + int(t * 1e9))))
    items.sort(key=lambda it: it[1].t_rx_ns if it[0] == "in" else it[1].t_tx_ns)
    with McapLogger(path, chunk_size=chunk_size) as lg:
        for direction, item in items:
            lg.log_mavlink(direction, item)


def _cli(args: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str, str]:
    rc = main(["log", "lag", *args])
    cap = capsys.readouterr()
    return rc, cap.out, cap.err


def test_the_lag_of_a_logged_flight_from_the_cli(tmp_path: Path,
                                                 capsys: pytest.CaptureFixture[str]) -> None:
    _write_flight(tmp_path / "f.mcap", 0.15)
    rc, out, _ = _cli(["--json", "--delay", str(tmp_path / "f.mcap")], capsys)
    assert rc == 0
    res = json.loads(out)
    # receipt jitter (6 ms) is removed by placing samples at their stamps: a tau this close
    # needs the offboard gating too (the level stretches before and after fit no lag at all)
    assert res["tau_s"] == pytest.approx(0.15, rel=0.10)
    # the setpoints are logged when sent and the samples placed by the link's smallest delay
    # (2 ms): what is left is at most the 6 ms receipt jitter
    assert 0.0 <= res["delay_s"] <= 0.01
    # a tau fitted beside a delay is a diagnostic, not the lead's constant
    assert res["config_line"] is None
    # OFFBOARD from the first setpoint after the accepted request at 3 s (3.05 s: PX4 flies
    # only setpoints received in OFFBOARD) to the last OFFBOARD heartbeat at 26.5 s (the change
    # at 27 s has no request of ours: the second up to the next heartbeat is left out), less
    # the setpoint gap from max_gap_s (0.5 s) after the last setpoint before it (13.95 s) to
    # the first after it (15 s)
    assert res["offboard_s"] == pytest.approx(26.5 - 3.05 - (15.0 - 14.45), abs=0.02)
    # less the first max_delay_s (0.2 s) of each stretch, which every candidate delay needs
    assert res["samples"] == pytest.approx(50 * (22.9 - 2 * 0.2), abs=4)
    assert res["stretches"] == 2  # split at the 1 s setpoint gap
    rc, out, _ = _cli(["--json", str(tmp_path / "f.mcap")], capsys)
    alone = json.loads(out)
    # the default fits the lag alone (what the lead inverts): no delay, the same tau here
    # (the true delay is 0) and a config line for it
    assert rc == 0 and alone["delay_s"] is None
    assert alone["tau_s"] == pytest.approx(0.15, rel=0.10)
    assert alone["config_line"] == f"control.lead.attitude_lag_s = {alone['tau_s']:.3f}"
    rc, out, _ = _cli([str(tmp_path / "f.mcap")], capsys)
    assert rc == 0 and f"suggested: control.lead.attitude_lag_s = {alone['tau_s']:.3f}" in out


def test_a_log_without_setpoints_is_a_clear_error(tmp_path: Path,
                                                  capsys: pytest.CaptureFixture[str]) -> None:
    _write_flight(tmp_path / "f.mcap", 0.1, setpoints=False)
    rc, out, err = _cli([str(tmp_path / "f.mcap")], capsys)
    assert rc == 2 and out == ""
    assert "no attitude setpoints" in err and "SET_ATTITUDE_TARGET" in err


def test_non_finite_attitude_is_dropped_then_refused_when_too_little_is_left(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    _write_flight(tmp_path / "half.mcap", 0.1, nan_from_s=15.0)
    res = measure_lag(tmp_path / "half.mcap")
    assert res.dropped_nonfinite == 50 * 15
    assert res.tau_s == pytest.approx(0.1, rel=0.10)
    _write_flight(tmp_path / "nan.mcap", 0.1, nan_from_s=3.5)
    rc, _, err = _cli([str(tmp_path / "nan.mcap")], capsys)
    assert rc == 2 and "attitude samples" in err and "non-finite" in err


def test_a_truncated_log_gives_what_its_salvaged_part_holds(tmp_path: Path) -> None:
    full = tmp_path / "f.mcap"
    _write_flight(full, 0.12, chunk_size=16_000)
    whole = measure_lag(full)
    data = full.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) * 6 // 10])
    part = measure_lag(cut)
    assert 0 < part.samples < whole.samples
    assert part.tau_s == pytest.approx(0.12, rel=0.10)
    assert not whole.salvage_note and "damaged" in part.salvage_note
    cut.write_bytes(data[: len(data) // 10])  # before OFFBOARD engaged
    with pytest.raises(LagFitError, match=r"OFFBOARD.*the log is damaged"):
        measure_lag(cut)


def test_attitude_quaternion_is_used_without_attitude(tmp_path: Path) -> None:
    _write_flight(tmp_path / "q.mcap", 0.12, quaternion=True)
    res = measure_lag(tmp_path / "q.mcap")
    assert res.attitude_topic == "/mavlink/in/ATTITUDE_QUATERNION"
    assert res.tau_s == pytest.approx(0.12, rel=0.10)


def test_a_log_never_in_offboard_is_refused(tmp_path: Path,
                                            capsys: pytest.CaptureFixture[str]) -> None:
    _write_flight(tmp_path / "f.mcap", 0.1, offboard=False)
    rc, _, err = _cli([str(tmp_path / "f.mcap")], capsys)
    assert rc == 2 and "never reports OFFBOARD" in err
