"""A config knob that has no effect in the chosen mode is named in a warning (issue 25)."""

from __future__ import annotations

import logging
from pathlib import Path

import pytest

from companion.config import load_config
from companion.control.knobs import ineffective_knobs, warn_ineffective_knobs

ROOT = Path(__file__).resolve().parents[2]


def test_the_shipped_configs_set_no_inert_knob() -> None:
    for f in sorted((ROOT / "config").glob("*.toml")):
        assert ineffective_knobs(load_config(f)) == [], f.name


@pytest.mark.parametrize(("overrides", "named"), [
    (["control.lead.enabled=false", "control.lead.attitude_lag_s=0.2"],
     "control.lead.attitude_lag_s = 0.2 has no effect: control.lead.enabled = false"),
    (["control.estimator.enabled=false", "control.estimator.velocity_noise_m_s=0.05"],
     "control.estimator.velocity_noise_m_s = 0.05 has no effect"),
    (["control.latency.auto_delay=false", "control.latency.auto_delay_window=31"],
     "control.latency.auto_delay_window = 31 has no effect"),
    (["control.latency.enabled=false", "control.latency.max_prediction_s=0.2"],
     "control.latency.max_prediction_s = 0.2 has no effect"),
    (["logging.preview_rate_hz=0", "logging.preview_jpeg_quality=90"],
     "logging.preview_jpeg_quality = 90 has no effect"),
    (['logging.perception_input="none"', 'logging.image_encoding="raw"'],
     "logging.image_encoding = 'raw' has no effect"),
    (["live.enabled=false", "live.port=9000"], "live.port = 9000 has no effect"),
])
def test_an_inert_knob_is_named(overrides: list[str], named: str) -> None:
    found = ineffective_knobs(load_config(None, overrides))
    assert any(f.startswith(named) for f in found), found
    # the same knob in effect (its switch on): no word
    switch = overrides[0].split("=")[0]
    on = {"logging.preview_rate_hz": "5", "logging.perception_input": '"crop"'}.get(
        switch, "true")
    assert ineffective_knobs(load_config(None, [*overrides[1:], f"{switch}={on}"])) == []


def test_the_warning_is_logged(caplog: pytest.LogCaptureFixture) -> None:
    with caplog.at_level(logging.WARNING):
        warn_ineffective_knobs(load_config(None, ["control.lead.enabled=false",
                                                  "control.lead.max_m_s2=0.5"]))
    assert "control.lead.max_m_s2 = 0.5 has no effect" in caplog.text
