"""The demo's emulator CPU a step counted like the companion's: from the companion's first
step to the exit, its start-up apart (``companion.flight.emulator_cpu_figures``), and the
``/proc`` sample it rests on (``proc_cpu_s``) against a real busy child process."""

from __future__ import annotations

import subprocess
import sys
import time

import pytest

from companion.flight import emulator_cpu_figures, proc_cpu_s


def test_start_up_is_taken_out_of_the_per_step_figure() -> None:
    f = emulator_cpu_figures(12.0, 2.0, 5000)
    assert f["emulator_cpu_ms_per_step"] == pytest.approx(2.0)
    assert f["emulator_cpu_ms_per_step_all"] == pytest.approx(2.4)
    assert f["emulator_startup_cpu_s"] == 2.0


@pytest.mark.parametrize("startup", [None, -1.0, 13.0])
def test_without_a_valid_sample_the_whole_process_counts(startup: float | None) -> None:
    f = emulator_cpu_figures(12.0, startup, 5000)
    assert f["emulator_cpu_ms_per_step"] == pytest.approx(2.4)
    assert f["emulator_startup_cpu_s"] is None


def test_nothing_measured_gives_no_figures() -> None:
    assert set(emulator_cpu_figures(None, 1.0, 5000).values()) == {None}
    assert set(emulator_cpu_figures(3.0, 1.0, 0).values()) == {None}


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="/proc is Linux's")
def test_proc_sample_follows_a_busy_child() -> None:
    child = subprocess.Popen([sys.executable, "-c", "while True: pass"])
    try:
        first = proc_cpu_s(child.pid)
        assert first is not None
        deadline = time.monotonic() + 20.0
        later = first
        while later - first < 0.2 and time.monotonic() < deadline:
            time.sleep(0.05)
            later = proc_cpu_s(child.pid) or later
        assert later - first >= 0.2  # it burns CPU, the sample sees it
    finally:
        child.kill()
        child.wait()
    assert proc_cpu_s(child.pid) is None  # reaped: gone
