"""The merged config file every process of a flight reads (``companion/config_file.py``):
TOML written back reads the same, overrides create keys and tables, paths survive the move."""

from __future__ import annotations

import tomllib
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from companion import ConfigError
from companion.config import DEFAULT_CONFIG, config_from_dict, read_document
from companion.config_file import absolutize_paths, apply_override, dump_toml, merged_document

_keys = st.text(st.characters(codec="utf-8", exclude_categories=("Cs",)), min_size=1,
                max_size=8)
_scalars = (st.booleans() | st.integers(-(2**63), 2**63 - 1)
            | st.floats(allow_nan=False) | st.text(max_size=12))
_values = st.recursive(_scalars, lambda inner: st.lists(inner, max_size=4), max_leaves=8)
_docs = st.recursive(st.dictionaries(_keys, _values, max_size=4),
                     lambda inner: st.dictionaries(_keys, inner | _values, max_size=4),
                     max_leaves=12)


@settings(max_examples=200, deadline=None)
@given(doc=_docs)
def test_dump_toml_round_trips(doc: dict) -> None:
    assert tomllib.loads(dump_toml(doc)) == doc


def test_the_paper_config_round_trips_and_validates() -> None:
    doc = read_document(DEFAULT_CONFIG)
    again = tomllib.loads(dump_toml(doc))
    assert again == doc
    assert config_from_dict(again) == config_from_dict(doc)


def test_overrides_set_existing_keys_and_create_missing_tables() -> None:
    doc = read_document(DEFAULT_CONFIG)
    out = merged_document(doc, ["sim.agv.speed_scale=3", 'target.pattern="aruco"',
                                "sim.scenarios.s1.uav_pose=[0.5, 0, -3, 0, 0, 1]",
                                "sim.camera_model.latency_ms=30", "newtable.kind=rmpc"])
    assert out["sim"]["agv"]["speed_scale"] == 3
    assert out["target"]["pattern"] == "aruco"
    assert out["sim"]["scenarios"]["s1"]["uav_pose"] == [0.5, 0, -3, 0, 0, 1]
    assert out["sim"]["camera_model"] == {"level": "ideal", "latency_ms": 30}
    assert out["newtable"] == {"kind": "rmpc"}  # a new table; a bare word is a string
    assert doc["sim"]["agv"]["speed_scale"] == 1.0  # the input is not touched


@pytest.mark.parametrize("bad", ["novalue", "=3", "sim..agv=1", "sim.agv.speed_scale.x=1",
                                 "sim.agv=3"])
def test_malformed_overrides_are_refused(bad: str) -> None:
    with pytest.raises(ConfigError, match="override"):
        apply_override(read_document(DEFAULT_CONFIG), bad)


def test_relative_paths_become_absolute(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(tmp_path)
    doc = read_document(Path(__file__).parents[2] / "config" / "realistic-sensors.toml")
    absolutize_paths(doc, DEFAULT_CONFIG)
    p = Path(doc["camera"]["calibration_file"])
    assert p.is_absolute() and p.is_file()
