"""``companion certify``: exit statuses (0 certified, 1 paper), the JSON contract, the table,
and the feasibility report at the paper's initial error (real RMPC solves)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from companion.cli import main

ROOT = Path(__file__).resolve().parents[1]
PAPER = str(ROOT / "config" / "paper.toml")
CERTIFIED = str(ROOT / "config" / "certified.toml")
COND_KEYS = {"lhs", "rhs", "ok"}


def _json(capsys: pytest.CaptureFixture[str], argv: list[str]) -> tuple[int, dict]:
    status = main(argv)
    return status, json.loads(capsys.readouterr().out)


def _check_contract(doc: dict) -> None:
    for key in ("P", "K", "eps", "kappa", "gamma", "r_v", "L", "theorem1", "theorem2"):
        assert key in doc, key
    assert np.asarray(doc["P"]).shape == (7, 7)
    assert np.asarray(doc["K"]).shape == (4, 7)
    assert set(doc["theorem1"]) == {"cond1", "cond2", "cond3"}
    for c in doc["theorem1"].values():
        assert set(c) == COND_KEYS
        assert c["ok"] == (c["lhs"] <= c["rhs"])
    assert set(doc["theorem2"]) == COND_KEYS


def test_certified_config_exit_0_and_json(capsys: pytest.CaptureFixture[str]) -> None:
    status, doc = _json(capsys, ["certify", "--config", CERTIFIED, "--json"])
    assert status == 0
    _check_contract(doc)
    assert doc["holds"] is True
    assert doc["eps"] == pytest.approx(0.11)
    assert all(c["ok"] for c in doc["assumption2"].values())
    # the honest limit: the first problem at the paper's eta_e(0) is infeasible here
    feas = doc["feasibility"]
    assert feas["feasible"] is False
    assert feas["reach"]["se3"]["ok"] is False
    assert feas["solver_mode"] in ("recovery", "fallback")


def test_paper_config_exit_1_names_failures(capsys: pytest.CaptureFixture[str]) -> None:
    status, doc = _json(capsys, ["certify", "--json"])
    assert status == 1
    _check_contract(doc)
    assert doc["holds"] is False
    assert set(doc["failed"]) == {"kappa", "remainder", "cond3"}
    assert doc["theorem1"]["cond3"]["ok"] is False
    assert doc["theorem1"]["cond2"]["ok"] is True
    assert doc["kappa"] == 0.0
    feas = doc["feasibility"]
    assert feas["feasible"] is True and feas["solver_mode"] == "optimal"
    assert feas["eta0"] == pytest.approx([0.0159, -0.2230, 0.6, 0.3927, -0.1307, -0.0541, 0.0])


def test_table_output_and_custom_eta0(capsys: pytest.CaptureFixture[str]) -> None:
    # near the origin the first problem is feasible for the certified variant too
    status = main(["certify", "--config", CERTIFIED, "--eta0", "0.01", "-0.01", "0.05", "0.05",
                   "0", "0", "0", "--v-a", "0", "0"])
    out = capsys.readouterr().out
    assert status == 0
    assert "VERDICT: every condition holds" in out
    assert "RMPC hard problem: optimal" in out
    assert "-> feasible" in out
    for name in ("cond1", "cond2", "cond3", "theorem2", "remainder", "input4"):
        assert name in out


def test_subprocess_exit_status_paper() -> None:
    proc = subprocess.run([sys.executable, "-m", "companion", "certify", "--no-rmpc"],
                          capture_output=True, text=True, cwd=ROOT, timeout=120, check=False)
    assert proc.returncode == 1, proc.stderr
    assert "VERDICT: 3 condition(s) fail" in proc.stdout
    assert "cond3: Omega reaches |p|" in proc.stdout
