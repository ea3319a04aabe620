"""``python -m sim_bridge`` as a subprocess: logs its ports, exits 0 at --duration and on
SIGTERM/SIGINT."""

from __future__ import annotations

import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
FREE_PORTS = ["--bind", "127.0.0.1", "--offboard-port", "0", "--gcs-port", "0", "--agv-port",
              "0", "--frame-port", "0", "--offboard-remote", "127.0.0.1:9",
              "--gcs-remote", "127.0.0.1:9", "--truth-remote", "127.0.0.1:9"]


def _run(*args: str, timeout_s: float = 20.0) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "sim_bridge", *args], cwd=ROOT,
                          capture_output=True, text=True, timeout=timeout_s, check=False)


def test_runs_for_duration_and_logs_its_ports() -> None:
    t0 = time.monotonic()
    p = _run("--duration", "1.0", *FREE_PORTS)
    assert p.returncode == 0, p.stderr
    assert 1.0 <= time.monotonic() - t0 < 15.0
    m = re.search(r"MAVLink offboard udp 127\.0\.0\.1:(\d+) -> 127\.0\.0\.1:9, "
                  r"GCS udp 127\.0\.0\.1:(\d+)", p.stderr)
    assert m, p.stderr
    assert int(m.group(1)) > 0 and int(m.group(2)) > 0  # the real bound ports, not 0
    assert "done: t=" in p.stderr


def test_lockstep_without_client_times_out_each_step() -> None:
    p = _run("--lockstep", "--duration", "0.2", *FREE_PORTS)  # 4 steps x 0.5 s timeout
    assert p.returncode == 0, p.stderr
    assert "sim_bridge lockstep" in p.stderr
    m = re.search(r"(\d+) steps, (\d+) lockstep timeouts", p.stderr)
    assert m and m.group(1) == m.group(2) == "4", p.stderr


def test_default_ports_are_px4_sitl_ones() -> None:
    # with no port arguments: PX4 SITL's ports (14580 -> 14540, 18570 -> 14550); if another
    # program holds one, the emulator must say which and fail cleanly
    p = _run("--duration", "0.3")
    if p.returncode == 0:
        assert "offboard udp 0.0.0.0:14580 -> 127.0.0.1:14540" in p.stderr, p.stderr
        assert "GCS udp 0.0.0.0:18570 -> 127.0.0.1:14550" in p.stderr
    else:
        assert p.returncode == 2 and "cannot bind" in p.stderr, p.stderr


def test_check_config_judges_the_clock_asked_for(tmp_path: Path) -> None:
    """``--check-config --lockstep`` refuses, by name, a camera rate lockstep would ignore;
    the same file on the wall clock is fine."""
    cfg = tmp_path / "fast-camera.toml"
    cfg.write_text(f'base = "{ROOT / "config" / "paper.toml"}"\n[sim.camera]\nrate_hz = 30.0\n')
    p = _run("--config", str(cfg), "--check-config", "--lockstep")
    assert p.returncode == 2, p.stdout + p.stderr
    assert "sim.camera.rate_hz: 30 Hz has no effect in lockstep" in p.stderr
    ok = _run("--config", str(cfg), "--check-config", "--realtime")
    assert ok.returncode == 0 and "config OK" in ok.stdout, ok.stderr


def test_bad_arguments_exit_2() -> None:
    assert _run("--scenario", "no-such-scenario").returncode == 2
    assert _run("--duration", "-1", *FREE_PORTS).returncode == 2


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_exits_cleanly_on_signal(sig: signal.Signals) -> None:
    with subprocess.Popen([sys.executable, "-m", "sim_bridge", "--duration", "100",
                           *FREE_PORTS], cwd=ROOT, stderr=subprocess.PIPE, text=True,
                          env={**os.environ, "PYTHONUNBUFFERED": "1"}) as proc:
        assert proc.stderr is not None
        try:
            deadline = time.monotonic() + 15.0
            line = ""
            while "MAVLink offboard" not in line and time.monotonic() < deadline:
                line = proc.stderr.readline()
            assert "MAVLink offboard" in line
            time.sleep(0.3)
            proc.send_signal(sig)
            rc = proc.wait(10.0)
            rest = proc.stderr.read()
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
    assert rc == 0, rest
    assert "stopped by signal" in rest


def test_console_script_from_another_directory(tmp_path: Path) -> None:
    exe = shutil.which("sim-bridge")
    assert exe is not None, "the sim-bridge entry point is not installed (pip install -e .)"
    p = subprocess.run([exe, "--duration", "0.3", *FREE_PORTS], cwd=tmp_path,
                       capture_output=True, text=True, timeout=20, check=False)
    assert p.returncode == 0, p.stderr
    assert "MAVLink offboard udp 127.0.0.1:" in p.stderr
