"""The companion's progress file (``--progress-file``, a demo's progress bar): rewritten at most
once every ``PROGRESS_INTERVAL_S`` of wall time, whatever the step rate, and always at the end
with the CPU per step."""

from __future__ import annotations

from pathlib import Path

from companion.control.runtime import CompanionApp


def _app(path: Path) -> CompanionApp:
    app = CompanionApp.__new__(CompanionApp)  # the progress needs only these
    app.progress_file = path
    app._next_progress_s = 0.0
    app._elapsed_s = 0.0
    app.steps = 0
    app.cpu_ms_per_step = None
    return app


def test_progress_is_rewritten_at_most_once_an_interval(tmp_path: Path) -> None:
    path = tmp_path / "progress"
    app = _app(path)
    app.steps, app._elapsed_s = 20, 1.0
    app._progress_due()
    assert path.read_text() == "1.000 20\n"
    app.steps, app._elapsed_s = 40, 2.0
    app._progress_due()  # within the interval: not rewritten
    assert path.read_text() == "1.000 20\n"
    app._next_progress_s = 0.0  # the interval is over
    app._progress_due()
    assert path.read_text() == "2.000 40\n"


def test_the_final_progress_is_written_whatever_the_interval(tmp_path: Path) -> None:
    path = tmp_path / "progress"
    app = _app(path)
    app.steps, app._elapsed_s = 20, 1.0
    app._progress_due()
    app.steps, app._elapsed_s, app.cpu_ms_per_step = 30, 1.5, 3.25
    app._write_progress(final=True)
    assert path.read_text() == "1.500 30 3.2500\n"
