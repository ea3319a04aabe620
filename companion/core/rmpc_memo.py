"""The RMPC's NLP built once per problem, not once per start-up.

Deriving an NLP's expression graph (:func:`companion.core.rmpc_problem.build_nlp`) costs
~0.2 s of CPU, and a controller needs three (the hard problem for its solver and for the
RTI, and the soft copy), while a start-up with the compiled libraries in the cache reads only
two things from them: the problem's layout (indices and row bounds) and the digest of its
expression graph (the libraries' alias files are named by it, :mod:`companion.core.rmpc_cache`).
So :func:`memoized_nlp` keeps those two in ``rmpc.cache_dir`` as
``rmpc_problem_<key>.json`` and hands back an :class:`Nlp` whose expressions are built only
if something reads them (a cache miss of a library, ``rmpc.jit = false``, a test).

``key`` hashes everything the graph is a function of: the builder's arguments (every field of
the parameter sets, every entry of the terminal matrices, exactly), the source of every module
of ``companion/core`` (the builder and all it calls live there: any edit there builds again
once), and the CasADi and numpy versions. A missing or unreadable file builds and writes it.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import os
from collections.abc import Callable, Iterator, Mapping
from functools import cache
from pathlib import Path
from typing import Any

import casadi as ca
import numpy as np

from companion.core.rmpc_layout import Layout, Row

log = logging.getLogger(__name__)

_KEYS = ("x", "p", "f", "g")
Built = tuple[dict[str, ca.SX], Layout]


class Nlp(Mapping[str, Any]):
    """``{x, p, f, g}`` of one NLP (SX), built on first read; :attr:`digest` (of its graph)
    without building when the memo knew it."""

    def __init__(self, build: Callable[[], Built], digest: str | None = None,
                 expressions: dict[str, ca.SX] | None = None) -> None:
        self._build = build
        self._digest = digest
        self._expressions = expressions

    def expressions(self) -> dict[str, ca.SX]:
        """The expressions as a plain dict (what ``ca.nlpsol`` takes); built if need be."""
        if self._expressions is None:
            self._expressions = self._build()[0]
        return self._expressions

    @property
    def built(self) -> bool:
        """Whether the expressions exist in this process (tests: a memo hit builds nothing)."""
        return self._expressions is not None

    @property
    def digest(self) -> str:
        if self._digest is None:
            self._digest = graph_digest(self.expressions())
        return self._digest

    def __getitem__(self, key: str) -> Any:
        return self.expressions()[key]

    def __iter__(self) -> Iterator[str]:
        return iter(_KEYS)

    def __len__(self) -> int:
        return len(_KEYS)


def graph_digest(nlp: Mapping[str, Any]) -> str:
    """SHA-256 of the serialized ``(x, p) -> (f, g)`` graph (what the generated code is of)."""
    if isinstance(nlp, Nlp):
        return nlp.digest
    oracle = ca.Function("nlp", [nlp["x"], nlp["p"]], [nlp["f"], nlp["g"]])
    return hashlib.sha256(oracle.serialize().encode()).hexdigest()


def memoized_nlp(build: Callable[[], Built], cache_dir: str, args: tuple[Any, ...]
                 ) -> tuple[Nlp, Layout]:
    """``build()``'s NLP (lazy) and layout, from ``cache_dir``'s memo when ``args`` (the
    builder's arguments) and the core code were seen before (module docstring)."""
    path = Path(cache_dir).expanduser() / f"rmpc_problem_{_input_key(args)}.json"
    try:
        data = json.loads(path.read_text())
        return Nlp(build, str(data["digest"])), _layout(data["layout"])
    except (OSError, ValueError, KeyError, TypeError):
        pass
    expressions, layout = build()
    nlp = Nlp(build, None, expressions)
    _write(path, {"digest": nlp.digest, "layout": _plain(layout)})
    return nlp, layout


def _write(path: Path, data: dict[str, Any]) -> None:
    """Atomically; a read-only or missing cache only loses the shortcut."""
    tmp = path.with_name(f"{path.name}.tmp{os.getpid()}")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp.write_text(json.dumps(data))
        os.replace(tmp, path)
    except OSError as exc:
        log.debug("NLP memo not written: %s", exc)


@cache
def _code_digest() -> str:
    """The source of every module under companion/core, and the versions the graph's numbers
    could depend on."""
    h = hashlib.sha256()
    root = Path(__file__).resolve().parent
    for f in sorted(root.rglob("*.py")):
        h.update(str(f.relative_to(root)).encode() + b"\0" + f.read_bytes() + b"\0")
    for v in (getattr(ca, "__version__", "?"), np.__version__):
        h.update(str(v).encode() + b"\0")
    return h.hexdigest()


def _input_key(args: tuple[Any, ...]) -> str:
    h = hashlib.sha256(_code_digest().encode())
    h.update(repr(_canonical(args)).encode())
    return h.hexdigest()[:24]


def _canonical(v: Any) -> Any:
    """``v`` as nested tuples of exact text: floats by ``float.hex``, arrays by their bytes,
    dataclasses by type and every field."""
    if dataclasses.is_dataclass(v) and not isinstance(v, type):
        return (type(v).__qualname__, tuple((f.name, _canonical(getattr(v, f.name)))
                                            for f in dataclasses.fields(v)))
    if isinstance(v, np.ndarray):
        return ("ndarray", v.dtype.str, v.shape, np.ascontiguousarray(v).tobytes().hex())
    if isinstance(v, np.generic):
        return _canonical(v.item())
    if isinstance(v, bool | int | str | None):
        return (type(v).__name__, v)
    if isinstance(v, float):
        return ("float", v.hex())
    if isinstance(v, list | tuple):
        return (type(v).__name__, tuple(_canonical(x) for x in v))
    if isinstance(v, Mapping):
        return ("map", tuple(sorted((str(k), _canonical(x)) for k, x in v.items())))
    raise TypeError(f"NLP memo: cannot key a {type(v).__name__}")


def _plain(lay: Layout) -> dict[str, Any]:
    return {"horizon": lay.horizon, "soft": lay.soft, "n_w": lay.n_w, "n_g": lay.n_g,
            "x_index": lay.x_index.tolist(), "u_index": lay.u_index.tolist(),
            "gap_index": lay.gap_index.tolist(),
            "rows": [[r.group, r.kind, r.stage, r.g_index, r.upper.hex(), r.slack_index,
                      r.corner] for r in lay.rows],
            "equality": list(lay.equality), "slack_index": lay.slack_index.tolist()}


def _layout(d: dict[str, Any]) -> Layout:
    def idx(v: Any) -> np.ndarray:
        return np.array(v, dtype=int)

    rows = tuple(Row(str(g), str(k), int(st), int(gi), float.fromhex(up),
                     None if si is None else int(si), int(c))
                 for g, k, st, gi, up, si, c in d["rows"])
    return Layout(horizon=int(d["horizon"]), soft=bool(d["soft"]), n_w=int(d["n_w"]),
                  n_g=int(d["n_g"]), x_index=idx(d["x_index"]).reshape(-1, 7),
                  u_index=idx(d["u_index"]).reshape(-1, 4),
                  gap_index=idx(d["gap_index"]).reshape(-1, 7), rows=rows,
                  equality=tuple(bool(e) for e in d["equality"]),
                  slack_index=idx(d["slack_index"]))
