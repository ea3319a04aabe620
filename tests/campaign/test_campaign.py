"""A small campaign end to end through the Dask engine (a local cluster of 2 worker processes):
three short lockstep flights, one of them with a key no program knows (an error row, not the
campaign's end); the table, summary and plots hold the runs; a second invocation skips them."""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest

from companion import cli
from companion.campaign.summary import read_table
from companion.config import DEFAULT_CONFIG

pytestmark = pytest.mark.slow

CAMPAIGN = f"""
config = "{DEFAULT_CONFIG}"
duration_s = 3.0
seeds = 1
set = ['logging.image_encoding="jpeg"', "sim.lockstep_timeout_s=1.0"]

[start]
height_m = [2.8, 3.2]
edge_fraction = [0.3, 0.5]

[[controllers]]
name = "rmpc"
set = []

[[controllers]]
name = "unknown-key"
set = ["rmpc.no_such_key=1"]

[[scenarios]]
name = "circle-3x"
path = "circle"
speed_scale = 3.0

[[scenarios]]
name = "paper-1x"
path = "paper"
speed_scale = 1.0
"""


def test_small_campaign_end_to_end_and_resume(tmp_path: Path,
                                               capsys: pytest.CaptureFixture[str]) -> None:
    camp = tmp_path / "small.toml"
    camp.write_text(CAMPAIGN)
    out = tmp_path / "out"
    args = ["campaign", "--campaign", str(camp), "--out", str(out), "--workers", "2",
            "--no-progress", "--scenarios", "circle-3x,paper-1x"]
    # 2 scenarios x 2 controllers: the unknown key fails fast, so 2 real flights
    assert cli.main(args) == 0
    rows = {r["run_id"]: r for r in read_table(out / "results.csv")}
    assert set(rows) == {f"{s}__{c}__s0" for s in ("circle-3x", "paper-1x")
                         for c in ("rmpc", "unknown-key")}
    for s in ("circle-3x", "paper-1x"):
        ok, bad = rows[f"{s}__rmpc__s0"], rows[f"{s}__unknown-key__s0"]
        assert ok["status"] == "ok", ok
        assert ok["frames"] >= 55 and ok["solves"] > 0
        assert ok["corner_max_px"] > 0 and ok["agv_max_speed_m_s"] > 0
        assert bad["status"] == "error" and "rmpc.no_such_key" in bad["error"]
        assert not (out / "runs" / f"{s}__rmpc__s0" / "flight.mcap").exists()  # not kept
    # the AGV's speed in the table is the emulator's: the circle at 3x is 0.9 m/s
    assert rows["circle-3x__rmpc__s0"]["agv_max_speed_m_s"] == pytest.approx(0.9, abs=1e-3)
    # two worker processes flew them (each run records its worker's pid)
    pids = {r["worker_pid"] for r in rows.values() if r["status"] == "ok"}
    assert os.getpid() not in pids
    summary = (out / "summary.md").read_text()
    for rid in ("circle-3x", "paper-1x", "rmpc", "unknown-key", "rmpc.no_such_key"):
        assert rid in summary
    for name in ("in_view_vs_speed", "corner_max", "recovery_fraction", "rms_errors",
                 "solve_times"):
        p = out / "plots" / f"{name}.png"
        assert p.stat().st_size > 1000 and p.read_bytes()[:4] == b"\x89PNG"
    engine = json.loads((out / "engine.json").read_text())
    assert engine["flown"] == 4 and engine["workers"] == 2
    capsys.readouterr()

    # resume: every run is finished, nothing flies, the table is the same
    before = {p: p.stat().st_mtime_ns for p in out.glob("runs/*/result.json")}
    assert cli.main(args) == 0
    assert "flights/min" not in capsys.readouterr().out  # nothing flown
    assert {p: p.stat().st_mtime_ns for p in out.glob("runs/*/result.json")} == before
    assert {r["run_id"]: r for r in read_table(out / "results.csv")} == rows
    assert json.loads((out / "engine.json").read_text()) == engine  # not rewritten

    # the summary alone, metrics recomputed from each run's report.json: the same rows
    (out / "results.csv").unlink()
    assert cli.main([*args, "--summary-only"]) == 0
    assert {r["run_id"]: r for r in read_table(out / "results.csv")} == rows
