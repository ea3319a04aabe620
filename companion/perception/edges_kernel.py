"""The ``"lean2"`` edges as one compiled call (``edges_lean2_kernel.c``), bit for bit the
numbers of :func:`~companion.perception.edges_lean2.refine_quad_lean2`.

Why: a tracked frame's refinement is ~20 numpy calls on a (4, 33, 48) slab after four
``cv2.warpAffine`` and the line fits' ~30 more, each 2-6 us of numpy's per-call cost whatever
its size; the arithmetic itself is a few thousand samples. The C computes the same IEEE
operations in the same order (the source's header says how: the float32 steps in float, the
float64 ones in double, numpy's pairwise sums, the fits' moments through the BLAS function
numpy's ``@`` calls, ``cv2.warpAffine``'s float bilinear sampling as OpenCV 5 computes it).

Built once with the system's C compiler (``$CC``, else ``gcc``, else ``cc``) into the RMPC's
cache directory (``~/.cache/rmpc-ibvs``), named by the hash of the source and the flags, and
loaded with ctypes. Before it is first used, :func:`lean2_kernel` checks it on this machine:
its warp against ``cv2.warpAffine`` (random matrices, images, sizes, reads off the image) and
whole refinements against the numpy path (rendered quads, tracked and not); a passed check is
recorded beside the library, keyed by what it depends on (OpenCV's and numpy's versions, the
BLAS file, the CPU's features), so later processes skip it. Without a
compiler, without numpy's BLAS symbol, or on any difference, the numpy path is used (logged
once): the same numbers either way, only slower. ``[perception] compiled_edges = false``
keeps the numpy path.
"""

from __future__ import annotations

import ctypes as ct
import hashlib
import logging
import os
import platform
import subprocess
import threading
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt

from companion.core.ckernel import DEFAULT_CACHE_DIR, compiled_library, source_key
from companion.perception._types import FloatArray
from companion.perception.edges import EdgeFit
from companion.perception.edges_kernel_check import refine_mismatch, warp_matches
from companion.perception.edges_lean import LeanSettings
from companion.perception.edges_lean2 import _grid, refine_quad_lean2

_log = logging.getLogger(__name__)

SOURCE_PATH = Path(__file__).with_name("edges_lean2_kernel.c")
_BLOCKS = (16, 8, 32, 64, 4)  # OpenCV's vector block widths to try (AVX2, SSE/NEON, AVX-512)
_DGEMV_NAMES = ("scipy_cblas_dgemv64_", "cblas_dgemv64_", "scipy_cblas_dgemv", "cblas_dgemv")
_OUT = 36  # corners 8, line points 8, directions 8, rms 4, kept 4, blur scales 4

Refined = tuple[FloatArray, list[EdgeFit], list[float]]


@dataclass(frozen=True)
class Lean2Kernel:
    """The loaded library: its entry points, numpy's ``cblas_dgemv`` (address) and the warp's
    vector block width this machine's OpenCV uses."""

    library: Path
    refine_fn: Callable[..., int]
    warp_fn: Callable[..., int]
    dgemv: int
    block: int


class Lean2Refiner:
    """:func:`refine_quad_lean2` through the kernel (one per detector: its buffers); the
    numpy path when the kernel cannot take the call (an image not row-contiguous, a sample
    position beyond the emulated range)."""

    def __init__(self, kernel: Lean2Kernel) -> None:
        self.kernel = kernel
        # the call's fixed buffers and their addresses (a ctypes address costs ~1 us a read)
        self._out, self._scale, self._reads, self._corners = (np.zeros(_OUT), np.zeros(4),
                                                              np.zeros(4), np.zeros((4, 2)))
        self._at = [int(a.ctypes.data) for a in (self._out, self._scale, self._reads,
                                                 self._corners)]
        self._params: dict[tuple[object, ...], tuple[list[npt.NDArray[Any]], list[int]]] = {}
        self.calls = 0
        self.fallbacks = 0

    def _grid_params(self, s: LeanSettings) -> list[int]:
        """The addresses of the grid's integers, floats, priorities and work bytes."""
        key = (s.profile_half_px, s.profile_step_px, s.samples_per_edge, s.min_contrast,
               s.passes)
        p = self._params.get(key)
        if p is None:
            g = _grid(s)
            arrays: list[npt.NDArray[Any]] = [
                np.array([g.k, s.samples_per_edge, g.in_rows.start, g.in_rows.stop,
                          g.out_rows.start, g.out_rows.stop, s.passes, self.kernel.block],
                         dtype=np.int64),
                np.array([g.k0, g.step, g.k0 / g.step, s.profile_half_px, s.min_contrast,
                          float(g.in_norm)]),
                np.ascontiguousarray(g.prio.reshape(-1), dtype=np.float32),
                np.zeros(4 * g.k * s.samples_per_edge, dtype=np.uint8)]
            p = self._params[key] = (arrays, [int(a.ctypes.data) for a in arrays])
        return p[1]

    def __call__(self, gray: npt.NDArray[np.uint8], corners: FloatArray, s: LeanSettings,
                 scale: list[float] | None = None, reads: list[float] | None = None
                 ) -> Refined | None:
        self.calls += 1
        if (gray.ndim != 2 or gray.dtype != np.uint8 or gray.strides[1] != 1
                or np.shape(corners) != (4, 2)):
            self.fallbacks += 1
            return refine_quad_lean2(gray, corners, s, scale, reads)
        gi, gd, prio, work = self._grid_params(s)
        out, at_scale, at_reads, at_corners = self._at
        self._corners[...] = corners
        if scale is not None:
            self._scale[:] = scale
        if reads is not None:
            self._reads[:] = reads
        rows, cols = gray.shape
        rc = self.kernel.refine_fn(
            gray.ctypes.data, gray.strides[0], rows, cols, at_corners, gi, gd, prio,
            self.kernel.dgemv, None if scale is None else at_scale,
            None if reads is None else at_reads, work, out)
        if rc < 0:  # not emulated here: the numpy path from the start (reads untouched)
            self.fallbacks += 1
            return refine_quad_lean2(gray, corners, s, scale, reads)
        if reads is not None:
            reads[:] = self._reads.tolist()
        if rc == 1:
            return None
        return _unpack(self._out.tolist())


def _unpack(o: list[float]) -> Refined:
    """The corners, the fits (their points and directions: rows of one array, numpy's
    per-call cost) and the blur scales from the kernel's output."""
    a = np.array(o[0:24]).reshape(3, 4, 2)
    fits = [EdgeFit(a[1, i], a[2, i], o[24 + i], o[28 + i]) for i in range(4)]
    return a[0], fits, o[32:36]


Lean2Refine = Callable[[npt.NDArray[np.uint8], FloatArray, LeanSettings, "list[float] | None",
                        "list[float] | None"], "Refined | None"]


def lean2_refiner(compiled: bool = True) -> Lean2Refine:
    """:func:`refine_quad_lean2` for a detector: through the kernel when ``compiled`` and it
    loads here (a :class:`Lean2Refiner` of its own), else the numpy function itself."""
    kernel = lean2_kernel() if compiled else None
    return refine_quad_lean2 if kernel is None else Lean2Refiner(kernel)


# ---------------------------------------------------------------------------------------------
# Build, load, check

_LOADED: dict[tuple[str, str], Lean2Kernel | None] = {}
_LOCK = threading.Lock()


def lean2_kernel(cache_dir: str = DEFAULT_CACHE_DIR, source: str | None = None
                 ) -> Lean2Kernel | None:
    """The checked kernel (once per process and source), or None (the numpy path; the reason
    logged). ``source``: other C (tests: a deliberately broken kernel must fail the check)."""
    text = SOURCE_PATH.read_text() if source is None else source
    key = (str(Path(cache_dir).expanduser()), source_key(text))
    with _LOCK:
        if key not in _LOADED:
            try:
                _LOADED[key] = _load_checked(Path(key[0]), text)
            except (OSError, subprocess.SubprocessError, AttributeError) as exc:
                _log.warning("compiled edges: unavailable (%s); the numpy path", exc)
                _LOADED[key] = None
        return _LOADED[key]


def _load_checked(directory: Path, text: str) -> Lean2Kernel | None:
    found = numpy_dgemv()
    if found is None:
        _log.info("compiled edges: numpy's cblas_dgemv not found; the numpy path")
        return None
    dgemv, blas_path = found
    library = _compiled(directory, text)
    if library is None:
        return None
    lib = ct.CDLL(str(library))
    refine_fn, warp_fn = lib.lean2_refine, lib.lean2_warp
    refine_fn.restype = warp_fn.restype = ct.c_int
    vp, i64, i32 = ct.c_void_p, ct.c_int64, ct.c_int
    refine_fn.argtypes = [vp, i64, i32, i32, vp, vp, vp, vp, vp, vp, vp, vp, vp]
    warp_fn.argtypes = [vp, i64, i32, i32, vp, i32, i32, i32, vp]
    # the checks passed before on this library, OpenCV, numpy, BLAS and CPU: their result
    marker = library.with_name(f"{library.name}.{_environment_key(blas_path)}.checked")
    try:
        block = int(marker.read_text())
        if block in _BLOCKS:
            return Lean2Kernel(library, refine_fn, warp_fn, dgemv, block)
    except (OSError, ValueError):
        pass
    checked = next((b for b in _BLOCKS if warp_matches(warp_fn, b)), None)
    if checked is None:
        _log.warning("compiled edges: the warp differs from cv2.warpAffine here; the numpy path")
        return None
    kernel = Lean2Kernel(library, refine_fn, warp_fn, dgemv, checked)
    mismatch = refine_mismatch(Lean2Refiner(kernel))
    if mismatch:
        _log.warning("compiled edges: %s differs from the numpy path; the numpy path", mismatch)
        return None
    _log.debug("compiled edges: %s (warp block %d)", library, checked)
    tmp = marker.with_name(f"{marker.name}.tmp{os.getpid()}")
    try:
        tmp.write_text(f"{checked}\n")
        os.replace(tmp, marker)
    except OSError as exc:  # a read-only cache: checked again by the next process
        _log.debug("compiled edges: check not recorded: %s", exc)
    return kernel


def _environment_key(blas_path: str) -> str:
    """What the checks' result depends on besides the library: OpenCV's and numpy's
    versions, the BLAS file numpy loaded, the CPU's features (OpenCV's and the kernel's
    dispatch)."""
    h = hashlib.sha256()
    try:
        st = os.stat(blas_path)
        blas = f"{blas_path}:{st.st_size}:{st.st_mtime_ns}"
    except OSError:
        blas = blas_path
    flags = ""
    try:
        with open("/proc/cpuinfo") as info:
            flags = next((ln for ln in info if ln.startswith(("flags", "Features"))), "")
    except OSError:
        pass
    for part in (cv2.__version__, np.__version__, blas, flags, platform.machine()):
        h.update(b"\0" + part.encode())
    return h.hexdigest()[:16]


def numpy_dgemv() -> tuple[int, str] | None:
    """The address of the ``cblas_dgemv`` numpy's matmul calls (its bundled OpenBLAS, found
    among the loaded libraries) and that library's path, or None."""
    try:
        with open("/proc/self/maps") as maps:
            paths = {line.split(None, 5)[5].strip() for line in maps
                     if "blas" in line.lower() and len(line.split(None, 5)) == 6}
    except OSError:
        return None
    # the most specific name first, wherever it is: numpy's bundled OpenBLAS exports its
    # symbols prefixed (scipy_...); another library's plain cblas_dgemv (CasADi ships an
    # OpenBLAS of its own, loaded once an RMPC is built) is other code with other roundings
    libs = []
    for path in sorted(paths):
        try:
            libs.append((ct.CDLL(path), path))
        except OSError:
            continue
    for name in _DGEMV_NAMES:
        for lib, path in libs:
            fn = getattr(lib, name, None)
            if fn is not None:
                address = ct.cast(fn, ct.c_void_p).value
                if address:
                    return address, path
    return None


def _compiled(directory: Path, text: str) -> Path | None:
    """The library of ``text`` in ``directory``, compiled on a miss; None without a compiler."""
    return compiled_library(directory, text, "perception_lean2", "compiled edges")


__all__ = ["Lean2Kernel", "Lean2Refiner", "lean2_kernel", "lean2_refiner"]
