"""The CPU-budget bench, short form (``python bench/cpu_budget.py`` flies the 60 s sweep): a
realtime paper flight with the companion and its children under a cgroup CPU quota of 0.8 of
a core. Real processes, real sockets, a real quota. No timed assertions: what must hold is that
the companion flies and answers, that it never crashes or commands from bad data, and that the
quota really confined it. Skipped, with the reason, where no cgroup CPU quota can be set."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from pathlib import Path

import pytest
from mcap.reader import make_reader

from bench.cgroup_quota import CgroupUnavailable, create_quota
from bench.cpu_budget import (
    EXIT_BAD_INPUT,
    EXIT_NO_CGROUP,
    PAPER,
    ROOT,
    BenchError,
    fly_budget,
    variant_settings,
    write_variant,
)

FRACTION = 0.8


def _quota_or_skip(tag: str) -> None:
    try:
        create_quota(FRACTION, f"rmpc-budget-test-{os.getpid()}-{tag}").remove()
    except CgroupUnavailable as e:
        pytest.skip(f"no cgroup CPU quota on this machine: {e}")


@pytest.mark.slow
def test_a_flight_under_a_quota_answers_and_is_confined(tmp_path: Path) -> None:
    _quota_or_skip("flight")
    variant = tmp_path / "config.toml"
    write_variant(PAPER, variant_settings(None, []), variant)
    row = fly_budget(FRACTION, variant, "paper", 10.0, tmp_path / "f")
    # no crash: both programs ended by themselves or on SIGTERM, cleanly
    assert row["rc"] == {"emulator": 0, "companion": 0}, row["rc"]
    # the companion flew: frames reached it, it stepped on them and sent commands
    assert row["frames_offered"] > 0 and row["steps"] > 0
    assert 0 < row["commands_sent"] <= row["frames_offered"]
    # every command on the wire is finite (the log, read with the mcap reader)
    n = 0
    with open(tmp_path / "f" / "flight.mcap", "rb") as fh:
        for _, _, m in make_reader(fh).iter_messages(
                topics=["/mavlink/out/SET_ATTITUDE_TARGET"]):
            f = json.loads(m.data)["fields"]
            assert all(math.isfinite(v) for v in [*f["q"], f["thrust"]])
            n += 1
    assert n == row["commands_sent"]
    # the quota was the one asked for, and it held the companion: its processes ran in the
    # group (the group's CPU accounts for what getrusage says the companion and its reaped
    # children used), and the group was throttled or stayed within quota x wall time
    assert row["quota"]["quota_us"] == round(FRACTION * row["quota"]["period_us"])
    assert row["cpu_startup_s"] is not None and row["cpu_flight_s"] is not None
    used_s = row["cpu_startup_s"] + row["cpu_flight_s"]
    assert row["cpu_rusage_s"] is not None
    assert used_s >= 0.9 * row["cpu_rusage_s"] and row["cpu_rusage_s"] > 0.5
    assert (row["throttled_periods"] or 0) > 0 or (
        row["cpu_flight_s"] <= FRACTION * row["wall_s"] + 0.05)
    # the report's figures made it into the row (what the sweep prints)
    for key in ("latency_median_ms", "latency_p95_ms", "fallbacks", "corner_max_px"):
        assert key in row
    assert row["verdict"]["target"].startswith("full")


def test_bad_overrides_are_refused_before_anything_flies() -> None:
    for bad in ("logging.preview_rate_hz", "=3", "a..b=1"):
        with pytest.raises(BenchError) as e:
            variant_settings(None, [bad])
        assert e.value.status == EXIT_BAD_INPUT
    with pytest.raises(BenchError):
        variant_settings(0.0, [])
    keys = variant_settings(10.0, ['controller.kind=ibvs-pd', "logging.preview_rate_hz=0"])
    assert keys["rmpc.dt_s"] == repr(0.1) and keys["sim.camera.rate_hz"] == "10.0"
    assert keys["controller.kind"] == '"ibvs-pd"'  # a bare word is a string, as with --set


def test_the_variant_file_is_read_by_the_emulator(tmp_path: Path) -> None:
    variant = tmp_path / "config.toml"
    write_variant(PAPER, variant_settings(None, ["sim.agv.speed_scale=2.5"]), variant)
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    r = subprocess.run([sys.executable, "-m", "sim_bridge", "--check-config", "--config",
                        str(variant), "--scenario", "paper"], capture_output=True, text=True,
                       env=env, timeout=120)
    assert r.returncode == 0, r.stderr
    assert "x2.5" in r.stdout  # the override reached the emulator through the base chain


def test_where_no_quota_can_be_set_the_bench_says_why_and_exits_3(tmp_path: Path) -> None:
    """A directory that is no cgroup with the cpu controller (what a machine without one, or a
    user without a delegated subtree, amounts to): refused before anything starts."""
    plain = tmp_path / "not-a-cgroup"
    plain.mkdir()
    out = tmp_path / "out"
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    r = subprocess.run([sys.executable, str(ROOT / "bench" / "cpu_budget.py"), "--duration", "5",
                        "--fraction", "0.5", "--out", str(out), "--cgroup-dir", str(plain)],
                       capture_output=True, text=True, env=env, timeout=120)
    assert r.returncode == EXIT_NO_CGROUP, (r.returncode, r.stderr)
    assert "no CPU quota can be set" in r.stderr and "cpu controller" in r.stderr
    assert not out.exists() and not any(plain.iterdir())  # nothing written, nothing started
