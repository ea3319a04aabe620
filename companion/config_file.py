"""One merged config file for every process of a flight.

``companion demo`` (and every campaign run) reads the config file with its ``base`` chain,
applies the ``--set KEY=VALUE`` overrides to the whole document (the emulator's ``[sim]`` table
included) and writes the result to ``OUT/config.toml``, which both the emulator and the
companion then read. An override therefore reaches every process that reads its key, and a key
that neither program knows is refused by their validators before anything flies.

Unlike :func:`companion.config.load_config`, an override here may add a key or a table the file
does not spell out (``sim.camera_model.latency_ms``, ``sim.scenarios.NAME.uav_pose``): each
program's validator then accepts it (a key with a default) or refuses it naming the key.
"""

from __future__ import annotations

import copy
import json
import math
import tomllib
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from companion import ConfigError

__all__ = ["absolutize_paths", "apply_override", "dump_toml", "merged_document"]

_REPO_ROOT = Path(__file__).resolve().parent.parent

#: Keys holding a file path, relative to the working directory, the config file or the
#: repository (the emulator's lookup order): made absolute so a copy of the document written
#: elsewhere still finds them.
PATH_KEYS = ("camera.calibration_file", "mavlink.signing_key_file", "sim.signing.key_file")


def parse_value(text: str) -> Any:
    """A TOML value (``3``, ``"aruco"``, ``[1, 2]``, ``true``); a bare word is a string."""
    try:
        return tomllib.loads(f"v = {text.strip()}")["v"]
    except tomllib.TOMLDecodeError:
        return text.strip()


def apply_override(doc: dict[str, Any], text: str) -> None:
    """Apply ``KEY=VALUE`` (dotted key, TOML value) to ``doc`` in place, creating missing
    tables. Raises :class:`ConfigError` if the text is not ``key=value`` or a path component
    is a value rather than a table."""
    key, sep, value = text.partition("=")
    key = key.strip()
    parts = key.split(".")
    if not sep or not key or any(not p.strip() for p in parts):
        raise ConfigError(f"override {text!r}: expected key=value, e.g. sim.agv.speed_scale=3")
    node = doc
    for i, part in enumerate(parts[:-1]):
        nxt = node.setdefault(part, {})
        if not isinstance(nxt, dict):
            raise ConfigError(f"override {key}: {'.'.join(parts[: i + 1])} is a value, "
                              "not a table")
        node = nxt
    if isinstance(node.get(parts[-1]), dict):
        raise ConfigError(f"override {key}: is a table; set one of its keys")
    node[parts[-1]] = parse_value(value)


def merged_document(doc: Mapping[str, Any], overrides: Sequence[str]) -> dict[str, Any]:
    """A deep copy of a parsed (base-merged) config document with ``overrides`` applied."""
    out = copy.deepcopy(dict(doc))
    for ov in overrides:
        apply_override(out, ov)
    return out


def absolutize_paths(doc: dict[str, Any], source: Path) -> None:
    """Make the :data:`PATH_KEYS` that name an existing file absolute (in place): looked up in
    the working directory, next to ``source`` (the config file), then in the repository."""
    for key in PATH_KEYS:
        *tables, name = key.split(".")
        node: Any = doc
        for t in tables:
            node = node.get(t) if isinstance(node, dict) else None
        if not isinstance(node, dict) or not isinstance(node.get(name), str) or not node[name]:
            continue
        p = Path(node[name]).expanduser()
        if p.is_absolute():
            continue
        for base in (Path.cwd(), source.resolve().parent, _REPO_ROOT):
            if (base / p).is_file():
                node[name] = str((base / p).resolve())
                break


def _scalar(v: Any, where: str) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if math.isnan(v):
            return "nan"
        if math.isinf(v):
            return "inf" if v > 0 else "-inf"
        return repr(v)
    if isinstance(v, str):
        return _string(v)
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_scalar(x, where) for x in v) + "]"
    if isinstance(v, Mapping):
        return "{" + ", ".join(f"{_key(k)} = {_scalar(x, where)}" for k, x in v.items()) + "}"
    raise ConfigError(f"{where}: cannot write {type(v).__name__} {v!r} as TOML")


def _key(k: str) -> str:
    bare = k and all(c.isalnum() or c in "-_" for c in k) and k.isascii()
    return k if bare else _string(k)


def _string(s: str) -> str:
    # JSON's escapes are TOML's; TOML also forbids a raw DEL
    return json.dumps(s, ensure_ascii=False).replace("\x7f", "\\u007f")


def dump_toml(doc: Mapping[str, Any]) -> str:
    """``doc`` as TOML text (``tomllib.loads(dump_toml(d)) == d`` for TOML-representable
    documents: tables, strings, numbers, booleans, lists)."""
    lines: list[str] = []

    def table(node: Mapping[str, Any], path: list[str]) -> None:
        values = [(k, v) for k, v in node.items() if not isinstance(v, Mapping)]
        subs = [(k, v) for k, v in node.items() if isinstance(v, Mapping)]
        if path and (values or not subs):
            lines.append("")
            lines.append("[" + ".".join(_key(p) for p in path) + "]")
        for k, v in values:
            lines.append(f"{_key(k)} = {_scalar(v, '.'.join([*path, k]))}")
        for k, v in subs:
            table(v, [*path, k])

    table(doc, [])
    return "\n".join(lines).lstrip("\n") + "\n"
