"""The config a replay uses: the recorded one, with features the log predates kept off."""

from __future__ import annotations

import re
import tomllib
from pathlib import Path

import pytest

from companion import ConfigError
from companion.config import DEFAULT_CONFIG, Config, config_from_dict, read_document
from companion.log.reader import LogReader
from companion.log.writer import McapLogger
from companion.replay import _as_flown, replay_config, schema_refuses


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


# --- `companion replay --set` on a log older than a key --------------------------------------

def _log_with_config(path: Path, doc: dict) -> Path:
    with McapLogger(path) as lg:
        lg.log_config(1_000, "# recorded\n", doc, "paper.toml")
    return path


def _replay_cfg(path: Path, overrides: list[str]) -> Config:
    with LogReader(path) as reader:
        return replay_config(reader, None, overrides)


def test_replay_set_adds_a_key_the_recorded_config_lacks(tmp_path: Path) -> None:
    old = _doc()
    old["vehicle_limits"] = {k: v for k, v in old["vehicle_limits"].items()
                             if k != "read_retries"}
    del old["live"]  # a whole (optional) table the log predates
    log_path = _log_with_config(tmp_path / "old.mcap", old)
    cfg = _replay_cfg(log_path, ["vehicle_limits.read_retries=7", "live.port=9000",
                                 "rmpc.eps=0.2"])
    assert cfg.vehicle_limits.read_retries == 7
    assert cfg.live.port == 9000
    assert cfg.rmpc.eps == 0.2  # a recorded key: replaced as before
    # the rest as recorded / as the schema's defaults
    assert cfg.vehicle_limits.margin == old["vehicle_limits"]["margin"]
    assert "read_retries" not in old["vehicle_limits"]  # the recorded dict is not modified


@pytest.mark.parametrize(("override", "named"), [
    ("rmpc.no_such_gain=1", "rmpc.no_such_gain: no such key in rmpc"),
    ("nosuch.key=1", "nosuch: no such key in the config"),
    ("rmpc.eps.deeper=1", "rmpc.eps: a value, not a table"),
    ("vehicle_limits.read_retries", "expected KEY=VALUE"),
])
def test_replay_set_refuses_a_key_the_schema_does_not_know(tmp_path: Path, override: str,
                                                          named: str) -> None:
    old = _doc()
    del old["vehicle_limits"]["read_retries"]
    log_path = _log_with_config(tmp_path / "old.mcap", old)
    with pytest.raises(ConfigError, match=re.escape(named)):
        _replay_cfg(log_path, [override])


def test_a_known_key_is_found_and_an_unknown_one_named() -> None:
    assert schema_refuses("control.estimator.enabled") is None
    assert schema_refuses("vehicle_limits") is None
    assert "no such key in control.estimator" in str(schema_refuses("control.estimator.bogus"))
