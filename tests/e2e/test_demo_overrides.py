"""``companion demo --set`` reaches every process that reads the key, or is refused.

The demo writes the merged config to ``OUT/config.toml`` and both the emulator and the
companion read it. A ``sim.*`` key changes what the emulator does (seen in its ground truth and
on the wire); a key neither program knows stops the demo with exit status 2 naming it, before
anything flies. (The shared ``target.*`` key: the ArUco flight in ``test_scenarios.py``.)
"""

from __future__ import annotations

import subprocess
import sys
import tomllib
from pathlib import Path

import numpy as np
import pytest

from companion import cli
from companion.config import DEFAULT_CONFIG
from companion.flight import run_demo
from companion.log.reader import LogReader

pytestmark = pytest.mark.slow


@pytest.mark.parametrize(("override", "named"), [
    ("sim.agv.bogus=1", "bogus"),                  # refused by the emulator
    ("sim.agv.speed_scale=-2", "sim.agv.speed_scale"),
    ("rmpc.bogus=1", "rmpc.bogus"),                # refused by the companion
    ("nosuch.key=1", "nosuch"),                    # a table neither program reads
    ("controller.kind=pid", "controller.kind"),    # a value the companion refuses
    ("controller.no_such_gain=1", "controller.no_such_gain"),
    ("sim.camera.rate_hz=30", "sim.camera.rate_hz"),  # no effect in the demo's lockstep
])
def test_an_unknown_or_bad_key_is_refused_naming_it(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], override: str, named: str,
) -> None:
    rc = cli.main(["demo", "--duration", "1", "--no-plots", "--out", str(tmp_path / "o"),
                   "--set", override])
    err = capsys.readouterr().err
    assert rc == 2
    assert named in err, err
    assert not (tmp_path / "o" / "flight.mcap").exists()  # nothing flew


def test_a_sim_key_reaches_the_emulator(tmp_path: Path) -> None:
    """``sim.agv.speed_scale=3``: the paper path at 3x, in the emulator's ground truth and in
    the FOLLOW_TARGET the companion received (paper path at 1x: v = (0.1, 0.1) m/s at t=0)."""
    rep = run_demo(DEFAULT_CONFIG, "paper", 2.0, tmp_path, ["sim.agv.speed_scale=3"], [],
                   plots=False)
    written = tomllib.loads((tmp_path / "config.toml").read_text())
    assert written["sim"]["agv"]["speed_scale"] == 3
    with LogReader(tmp_path / "flight.mcap") as r:
        truth = [m.data for m in r.messages(topics=["/truth"])]
        follow = [m.data["fields"] for m in r.messages(topics=["/mavlink/in/FOLLOW_TARGET"])]
    assert truth and follow
    v0 = np.asarray(truth[0]["agv"]["vel_ned_m_s"])
    np.testing.assert_allclose(v0[:2], [0.3, 0.3], atol=2e-3)
    np.testing.assert_allclose(follow[0]["vel"][:2], [0.3, 0.3], atol=2e-3)
    assert rep["overrides"] == ["sim.agv.speed_scale=3"]


def test_sim_bridge_check_config(tmp_path: Path) -> None:
    ok = subprocess.run([sys.executable, "-m", "sim_bridge", "--check-config", "--scenario",
                         "edge"], capture_output=True, text=True, timeout=60)
    assert ok.returncode == 0 and "config OK" in ok.stdout and "edge" in ok.stdout
    bad = tmp_path / "bad.toml"
    bad.write_text(f'base = "{DEFAULT_CONFIG}"\n[sim.vehicle]\nattitude_tau_s = -1\n')
    r = subprocess.run([sys.executable, "-m", "sim_bridge", "--check-config", "--config",
                        str(bad)], capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and "sim.vehicle.attitude_tau_s" in r.stderr
