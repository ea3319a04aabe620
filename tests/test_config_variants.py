"""Every shipped config loads; the variants say what their headers claim."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from companion import ConfigError
from companion.config import Config, load_config

CONFIG_DIR = Path(__file__).resolve().parent.parent / "config"


@pytest.mark.parametrize("path", sorted(CONFIG_DIR.glob("*.toml")), ids=lambda p: p.name)
def test_every_shipped_config_loads(path: Path) -> None:
    cfg = load_config(path)
    assert cfg.rmpc.horizon == 16 and cfg.camera.r_v == pytest.approx(0.45)


@pytest.mark.parametrize(
    ("override", "key"),
    [("rmpc.horizon=0", "rmpc.horizon"), ("camera.visible_fraction=1.5", "camera.visible_fraction"),
     ("rmpc.solver=\"qpoases\"", "rmpc.solver"), ("control.time_source=\"gps\"", "time_source"),
     ("rmpc.u_max=[1,1,1]", "rmpc.u_max"), ("safety.nope=1", "safety.nope"),
     ("logging.compression=\"gzip\"", "logging.compression"),
     ("rmpc.visibility=\"edges\"", "rmpc.visibility"), ("rmpc.heading=\"soft\"", "rmpc.heading"),
     ("rmpc.target_motion=\"exact\"", "rmpc.target_motion"),
     ("rmpc.min_depth_m=0", "rmpc.min_depth_m"),
     ("rmpc.recovery_q_diag=[1,1,1,1,1,1,0]", "rmpc.recovery_q_diag"),
     ("rmpc.recovery_q_diag=[1,1,1]", "rmpc.recovery_q_diag"),
     ("rmpc.recovery_eps=0", "rmpc.recovery_eps"),
     ("rmpc.target_corners_m=[[1,1]]", "rmpc.target_corners_m"),
     ("controller.kind=\"pid\"", "controller.kind"),
     ("controller.ibvs_kv_1_s=-1", "controller.ibvs_kv_1_s"),
     # the companion flies only the paper's mount: a tilted or offset camera is refused, not ignored
     ("camera.mount_rpy_rad=[0.0,0.2,0.0]", "camera.mount_rpy_rad"),
     ("camera.mount_offset_m=[0.1,0.0,0.0]", "camera.mount_offset_m")],
)
def test_a_bad_value_names_its_key(override: str, key: str) -> None:
    with pytest.raises(ConfigError, match=key.replace(".", r"\.")):
        load_config(None, [override])


def test_broken_toml_is_a_clear_error(tmp_path: Path) -> None:
    bad = tmp_path / "bad.toml"
    bad.write_text('base = "%s"\n[rmpc\neps = 1\n' % (CONFIG_DIR / "paper.toml"))
    with pytest.raises(ConfigError, match="not valid TOML"):
        load_config(bad)


def test_lmi_feasible_variant_fails_only_theorem1_cond2_and_is_feasible_at_paper_start() -> None:
    p = subprocess.run(
        [sys.executable, "-m", "companion", "certify", "--config",
         str(CONFIG_DIR / "lmi-feasible.toml"), "--json"],
        capture_output=True, text=True, timeout=300,
    )
    assert p.returncode == 1, p.stderr
    d = json.loads(p.stdout)
    assert list(d["failed"]) == ["cond2"]
    assert d["feasibility"]["feasible"] is True
    assert d["theorem1"]["cond3"]["ok"] and d["theorem2"]["ok"]


def test_realistic_weights_are_stiffer_and_keep_the_acceleration_bounds_on_omega() -> None:
    """config/realistic.toml's RMPC tuning says: a horizontal stiffness like PX4's position loop
    (1.71 m/s^2 per m) where the paper's is ~0.34, eps as large as K's acceleration bounds on
    Omega allow, and the paper start still feasible."""
    from companion.core.design import design_terminal

    paper, real = load_config(CONFIG_DIR / "paper.toml"), load_config(CONFIG_DIR / "realistic.toml")
    z = real.rmpc.desired_depth_m

    def stiffness(cfg: Config) -> float:  # m/s^2 of r1 per m of horizontal error (s1 = x / z*)
        return float(design_terminal(cfg.rmpc, cfg.camera).k[0, 0]) / z

    k_paper, k_real = stiffness(paper), stiffness(real)
    assert k_paper < 0.4 and 1.5 < k_real < 2.2, (k_paper, k_real)
    p = subprocess.run(
        [sys.executable, "-m", "companion", "certify", "--config",
         str(CONFIG_DIR / "realistic.toml"), "--json"],
        capture_output=True, text=True, timeout=300,
    )
    d = json.loads(p.stdout)
    a2 = d["assumption2"]
    assert all(a2[f"input{i}"]["ok"] for i in (1, 2, 3)), a2
    assert a2["input1"]["lhs"] > 0.9 * a2["input1"]["rhs"]  # eps about as large as they allow
    assert d["feasibility"]["feasible"] is True
