"""The companion's "no camera frame" stop in a lockstep flight outlasts the emulator's own
lockstep timeout (else a setpoint lost under load ends the flight instead of timing out)."""

from __future__ import annotations

import argparse
from pathlib import Path

import pytest

from companion.flight import (
    CAMERA_TIMEOUT_MARGIN_S,
    camera_timeout_s,
    demo_commands,
    positive_seconds,
)

CONFIG = Path(__file__).resolve().parents[2] / "config"


def _merged(tmp_path: Path, lockstep_s: float | None) -> Path:
    path = tmp_path / "merged.toml"
    base = (CONFIG / "paper.toml").as_posix()
    text = f'base = "{base}"\n'
    if lockstep_s is not None:
        text += f"[sim]\nlockstep_timeout_s = {lockstep_s}\n"
    path.write_text(text)
    return path


@pytest.mark.parametrize("lockstep_s", [10.0, 30.0])
def test_camera_timeout_outlasts_the_lockstep_timeout(tmp_path: Path, lockstep_s: float) -> None:
    assert camera_timeout_s(_merged(tmp_path, lockstep_s)) == lockstep_s + CAMERA_TIMEOUT_MARGIN_S


def test_camera_timeout_never_below_the_default(tmp_path: Path) -> None:
    # paper.toml's 0.5 s lockstep timeout: 5.5 s; never shorter than `companion run`'s 5 s
    assert camera_timeout_s(_merged(tmp_path, None)) == pytest.approx(5.5)
    assert camera_timeout_s(_merged(tmp_path, 0.01)) == pytest.approx(5.01)


def test_demo_passes_the_camera_timeout(tmp_path: Path) -> None:
    _, comp = demo_commands(_merged(tmp_path, 10.0), "paper", 5.0, tmp_path, [], [])
    assert comp[comp.index("--camera-timeout") + 1] == "15.0"


@pytest.mark.parametrize("text", ["0", "-1", "nan", "inf", "soon"])
def test_run_refuses_a_bad_camera_timeout(text: str) -> None:
    with pytest.raises(argparse.ArgumentTypeError, match="seconds"):
        positive_seconds(text)
    assert positive_seconds("12.5") == 12.5
