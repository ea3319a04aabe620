"""``companion replay --set`` on a log written before a key existed: the key is added when
today's config schema knows it, and a key it does not know is refused naming it (exit 2).

One short lockstep flight; its log is rewritten with a ``/config`` that lacks a key, the way a
log written before that key was added records it.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
from mcap.reader import make_reader
from mcap.writer import Writer

from companion.config import DEFAULT_CONFIG
from companion.flight import run_demo

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def older_log(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("flight")
    run_demo(DEFAULT_CONFIG, "paper", 3.0, out, [], [], plots=False)
    dst = out / "older.mcap"
    with open(out / "flight.mcap", "rb") as f, open(dst, "wb") as g:
        w = Writer(g)
        w.start()
        schemas: dict[int, int] = {}
        channels: dict[int, int] = {}
        for schema, ch, m in make_reader(f).iter_messages():
            data = m.data
            if ch.topic == "/config":  # recorded before [vehicle_limits] read_retries
                rec = json.loads(data)
                del rec["config"]["vehicle_limits"]["read_retries"]
                data = json.dumps(rec).encode()
            if ch.id not in channels:
                if schema.id not in schemas:
                    schemas[schema.id] = w.register_schema(schema.name, schema.encoding,
                                                           schema.data)
                channels[ch.id] = w.register_channel(ch.topic, ch.message_encoding,
                                                     schemas[schema.id])
            w.add_message(channels[ch.id], m.log_time, data, m.publish_time)
        w.finish()
    return dst


def _replay(log: Path, *sets: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "companion", "replay", str(log),
                           "--from-detections", "--in-process",
                           *[a for s in sets for a in ("--set", s)]],
                          capture_output=True, text=True, timeout=600.0)


def test_a_key_newer_than_the_log_is_added(older_log: Path) -> None:
    r = _replay(older_log, "vehicle_limits.read_retries=7")
    assert r.returncode == 0, r.stdout + r.stderr
    assert "--set vehicle_limits.read_retries: not in the recorded config" in r.stderr


def test_a_key_the_schema_does_not_know_is_refused_by_name(older_log: Path) -> None:
    r = _replay(older_log, "vehicle_limits.read_retrys=7")
    assert r.returncode == 2
    assert ("--set vehicle_limits.read_retrys: unknown key: vehicle_limits.read_retrys: no "
            "such key in vehicle_limits") in r.stdout + r.stderr
