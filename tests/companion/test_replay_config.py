"""The config a replay uses: the recorded one, with features the log predates kept off."""

from __future__ import annotations

import tomllib

from companion.config import DEFAULT_CONFIG, config_from_dict, read_document
from companion.replay import _as_flown


def _doc() -> dict:
    doc = read_document(DEFAULT_CONFIG)
    return {k: v for k, v in doc.items() if k != "sim"}


def test_a_config_recorded_before_the_estimator_replays_without_it() -> None:
    old = _doc()
    old["control"] = {k: v for k, v in old["control"].items()
                      if k not in ("estimator", "latency")}
    assert config_from_dict(old).control.estimator.enabled  # the defaults would switch it on
    cfg = config_from_dict(_as_flown(old))
    assert not cfg.control.estimator.enabled and not cfg.control.latency.enabled
    assert "estimator" not in old["control"]  # the recorded dict is not modified


def test_a_config_with_the_tables_is_replayed_as_recorded() -> None:
    new = _doc()
    assert _as_flown(new) is new
    assert config_from_dict(_as_flown(new)).control.estimator.enabled == \
        tomllib.loads(DEFAULT_CONFIG.read_text())["control"]["estimator"]["enabled"]
