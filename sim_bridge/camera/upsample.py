"""The ground's 2x upsampling (``cv2.resize(..., INTER_LINEAR)`` of the half-resolution warp)
through a small compiled kernel (``upsample2x.c``, SSE2) that gives OpenCV's pixels at about a
third of its CPU: OpenCV runs its baseline SSE2 kernels for this call, the horizontal pass
assembling pixel pairs with scalar shifts (docs/reference/emulator.md, section 5.3).

Built once with the system's C compiler (``$CC``, else ``gcc``, else ``cc``) into the
emulator's cache directory (``scene.cache_dir()``), named by the hash of the source, the flags
and the machine, and loaded with ctypes. Before its first use in a process it is checked
against ``cv2.resize`` on random images (the frame's size and small odd ones): any difference,
no compiler, a failed build or a machine other than x86-64 leaves ``cv2.resize`` in charge
(logged once). The same pixels either way, only the cost differs.
"""

from __future__ import annotations

import ctypes as ct
import functools
import hashlib
import logging
import os
import platform
import shutil
import subprocess
import tempfile
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np

log = logging.getLogger(__name__)

SOURCE_PATH = Path(__file__).with_name("upsample2x.c")
FLAGS = ("-O2", "-fPIC", "-shared")
_Kernel = Callable[..., int]


def _compiler() -> str | None:
    for name in (os.environ.get("CC"), "gcc", "cc"):
        if name and shutil.which(name):
            return name
    return None


def build_library(source_path: Path, flags: tuple[str, ...], directory: Path) -> Path | None:
    """The shared library of the C file ``source_path`` built with ``flags`` in ``directory``
    (built now if missing: named by the hash of the source, the flags and the machine), or
    None without a compiler, off x86-64 or when the build fails."""
    cc = _compiler()
    if cc is None or platform.machine().lower() not in ("x86_64", "amd64"):
        return None
    source = source_path.read_bytes()
    key = hashlib.sha256(source + " ".join(flags).encode() + platform.platform().encode())
    lib = directory / f"{source_path.stem}-{key.hexdigest()[:24]}.so"
    if lib.exists():
        return lib
    try:
        directory.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryDirectory(dir=directory) as tmp:
            out = Path(tmp) / lib.name
            subprocess.run([cc, *flags, "-o", str(out), str(source_path)], check=True,
                           capture_output=True, timeout=60)
            os.replace(out, lib)  # atomic: a concurrent start loads all or nothing
    except (OSError, subprocess.SubprocessError) as e:
        log.info("%s not built (%s): OpenCV instead", source_path.name, e)
        return None
    return lib


def _build(directory: Path) -> Path | None:
    """The kernel's shared library in ``directory`` (built now if missing), or None."""
    return build_library(SOURCE_PATH, FLAGS, directory)


def _load(lib: Path) -> _Kernel:
    fn = ct.CDLL(str(lib)).upsample2x_u8
    fn.argtypes = [ct.c_void_p, ct.c_int, ct.c_int, ct.c_long, ct.c_void_p, ct.c_long,
                   ct.c_void_p]
    fn.restype = ct.c_int
    return fn


def _run(fn: _Kernel, src: np.ndarray) -> np.ndarray:
    h, w = src.shape
    out = np.empty((2 * h, 2 * w), np.uint8)
    scratch = np.empty(8 * w, np.uint16)  # four rows of 2w values
    if fn(src.ctypes.data, h, w, src.strides[0], out.ctypes.data, out.strides[0],
          scratch.ctypes.data) != 0:
        raise ValueError("upsample2x: bad shape")
    return out


def _matches(fn: _Kernel) -> bool:
    """The kernel's output equals ``cv2.resize``'s on random images of the ground's size and
    of small odd sizes (every code path: the vector loop, its tail, the edges)."""
    rng = np.random.default_rng(2024)
    sizes = [(500, 500), (500, 500), (37, 61), (1, 2), (2, 3), (9, 17), (16, 9), (33, 8)]
    for h, w in sizes:
        src = rng.integers(0, 256, (h, w), dtype=np.uint8)
        ref = cv2.resize(src, (2 * w, 2 * h), interpolation=cv2.INTER_LINEAR)
        if not np.array_equal(_run(fn, src), ref):
            return False
    return True


def load_checked(what: str, build: Callable[[Path], Path | None],
                 load: Callable[[Path], _Kernel], matches: Callable[[_Kernel], bool],
                 fallback: str, directory: Path | None) -> _Kernel | None:
    """A compiled kernel built (``build``) into ``directory`` (default: the emulator's cache),
    loaded and held to what it replaces (``matches``) before first use; None (``fallback``
    runs then) without a compiler, a loadable library or an exact match. The one loader of
    the camera's kernels (upsampling, warp, box)."""
    from sim_bridge.camera.scene import cache_dir

    lib = build(cache_dir() if directory is None else directory)
    if lib is None:
        return None
    try:
        fn = load(lib)
    except (OSError, AttributeError) as e:  # not a library, or not this one
        log.info("%s kernel not loaded (%s): %s", what, e, fallback)
        return None
    if not matches(fn):
        log.warning("%s kernel differs from %s on this machine: %s", what, fallback, fallback)
        return None
    return fn


@functools.lru_cache(maxsize=1)
def kernel(directory: Path | None = None) -> _Kernel | None:
    """The checked kernel of this process, or None (``cv2.resize`` then)."""
    return load_checked("upsample", _build, _load, _matches, "cv2.resize", directory)


def upsample2x(src: np.ndarray) -> np.ndarray:
    """``cv2.resize(src, (2 w, 2 h), interpolation=cv2.INTER_LINEAR)`` of a uint8 (h, w) image,
    through the kernel when it is available (the same pixels)."""
    fn = kernel()
    h, w = src.shape[:2]
    if (fn is None or src.dtype != np.uint8 or src.ndim != 2 or w < 2 or h < 1
            or src.strides[1] != 1):
        return cv2.resize(src, (2 * w, 2 * h), interpolation=cv2.INTER_LINEAR)
    return _run(fn, src)
