"""The terminal design's matrices cached beside the compiled solvers (``rmpc.cache_dir``).

Every flight and every replay designs the same terminal ingredients from the same parameters;
the DARE alone costs ~1.6 s of start-up, most of it importing ``scipy.linalg``. The design's
``P``, ``K`` and ``kappa`` are stored once as ``terminal_<key>.npz``, ``key`` hashing every
input that determines them (the parameters the design reads, the sources of the design
modules, the numpy / scipy / cvxpy versions), so a changed parameter, a changed design or
another library finds no entry and designs afresh. The stored arrays are the computed float64
values themselves: a cached design is bit-identical to a fresh one.

A cache that cannot be read or written is never an error: the design is computed.
"""

from __future__ import annotations

import hashlib
import logging
import os
import tempfile
from collections.abc import Callable
from functools import cache
from importlib import metadata
from pathlib import Path

import numpy as np

log = logging.getLogger(__name__)

#: the modules whose code determines P, K and kappa (their source goes into the key)
_DESIGN_MODULES = ("design.py", "terminal.py", "lmi.py", "certificate.py")
_LIBRARIES = ("numpy", "scipy", "cvxpy")

Matrices = tuple[np.ndarray, np.ndarray, float]


@cache
def _version(name: str) -> str:
    """The installed version of ``name``: the ``Version:`` header of its metadata, read as
    text (``metadata.version`` parses the whole file as e-mail headers: scipy's holds its
    licences, ~10-40 ms of every start-up for the three libraries); once per process."""
    try:
        text = metadata.distribution(name).read_text("METADATA") or ""
    except metadata.PackageNotFoundError:
        return "-"
    for line in text.splitlines():
        if line.startswith("Version:"):
            return line[len("Version:"):].strip()
        if not line:  # the end of the headers
            break
    return metadata.version(name)


def design_key(inputs: tuple[object, ...]) -> str:
    """The cache key of a design: ``inputs`` (the parameters it reads, as exact reprs), the
    design modules' sources and the libraries' versions."""
    h = hashlib.sha256(repr(inputs).encode())
    here = Path(__file__).resolve().parent
    for name in _DESIGN_MODULES:
        h.update(name.encode())
        h.update((here / name).read_bytes())
    for lib in _LIBRARIES:
        h.update(f"{lib}={_version(lib)}".encode())
    return h.hexdigest()[:24]


def _load(path: Path) -> Matrices | None:
    try:
        with np.load(path, allow_pickle=False) as z:
            p, k, kappa = z["p"], z["k"], z["kappa"]
    except (OSError, ValueError, KeyError) as exc:
        log.warning("terminal design cache %s unreadable (%s): designing afresh", path, exc)
        return None
    if p.shape != (7, 7) or k.shape != (4, 7) or kappa.shape != ():
        log.warning("terminal design cache %s has wrong shapes: designing afresh", path)
        return None
    return p.astype(float), k.astype(float), float(kappa)


def _store(path: Path, m: Matrices) -> None:
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=path.stem, suffix=".tmp.npz")
        with os.fdopen(fd, "wb") as f:
            np.savez(f, p=m[0], k=m[1], kappa=np.float64(m[2]))
        os.replace(tmp, path)  # atomic: a concurrent reader sees the whole file or none
    except OSError as exc:
        log.warning("terminal design cache %s not written (%s)", path, exc)


def cached_design(cache_dir: str, inputs: tuple[object, ...],
                  design: Callable[[], Matrices]) -> Matrices:
    """``design()``'s ``(P, K, kappa)``, from ``cache_dir`` when a design with the same key
    was stored there, else computed and stored."""
    if not cache_dir:
        return design()
    path = Path(cache_dir).expanduser() / f"terminal_{design_key(inputs)}.npz"
    if path.exists():
        hit = _load(path)
        if hit is not None:
            return hit
    m = design()
    _store(path, m)
    return m
