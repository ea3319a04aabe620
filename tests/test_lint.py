"""The tree stays ruff-clean and strict-mypy-clean (pyproject.toml holds both settings)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent


@pytest.mark.parametrize(
    "cmd",
    [[sys.executable, "-m", "ruff", "check", "."],
     [sys.executable, "-m", "mypy", "companion", "sim_bridge"]],
    ids=["ruff", "mypy-strict"],
)
def test_static_checks(cmd: list[str]) -> None:
    p = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert p.returncode == 0, p.stdout[-4000:] + p.stderr[-2000:]
