"""The horizon's target motion as one compiled call (``prediction_kernel.c``), bit for bit
the numbers of :func:`companion.core.prediction.predict_target_motion`'s stage loop.

Why: that loop is ~16 Python iterations of a dozen float operations each, ~50 us a control
step, where the arithmetic takes well under a microsecond. The C computes the same IEEE
double operations in the same order, calling the C library's ``cos``, ``sin`` and ``atan2``
(the functions Python's ``math`` calls), built by :mod:`companion.core.ckernel`.

Before first use in a process, :func:`motion_kernel` checks it against the Python loop on
fixed pseudo-random cases (moving, stopped, capped, turning, with and without a disturbance;
~30 ms of CPU): any bit of difference, no compiler, or a failed build, and the Python loop is used
(logged once): the same numbers either way, only slower.
"""

from __future__ import annotations

import ctypes as ct
import logging
import math
import subprocess
from collections.abc import Callable
from pathlib import Path

import numpy as np

from companion.core.ckernel import DEFAULT_CACHE_DIR, compiled_library, source_key

_log = logging.getLogger(__name__)

SOURCE_PATH = Path(__file__).with_name("prediction_kernel.c")
N_IN = 14
"""The kernel's inputs: [v0x, v0y, a0x, a0y, speed, w, yaw_q, dt, has_cap, cap, has_d, d0,
d1, d2]."""

Values = tuple[float, float, float, float, float, float, float, float, float | None]
"""(v0x, v0y, a0x, a0y, speed, psidot, yaw_q, dt, the speed cap or None)."""
Arrays = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]
"""(v_v (N, 2), vdot (N, 2), psidot (N,), d (N, 3) or None): one call's fresh arrays."""
PythonLoop = Callable[[Values, int, list[float] | None], Arrays]


class MotionKernel:
    """The loaded ``predict_motion`` (one per process; each call builds its own arguments)."""

    def __init__(self, fn: Callable[..., int]) -> None:
        self._fn = fn
        self._args = ct.c_double * N_IN

    def __call__(self, values: Values, horizon: int,
                 d: list[float] | None) -> tuple[Arrays, bool]:
        """``values``: (v0x, v0y, a0x, a0y, speed, w, yaw_q, dt, cap or None); ``d``: the
        disturbance (3,) or None. Fresh arrays (views of one new buffer) and whether every
        value is finite (the kernel's own test)."""
        buf = np.empty(8 * horizon)
        cap = values[8]
        d0, d1, d2 = (0.0, 0.0, 0.0) if d is None else d
        args = self._args(*values[:8], 0.0 if cap is None else 1.0,
                          0.0 if cap is None else cap, 0.0 if d is None else 1.0, d0, d1, d2)
        finite = self._fn(args, horizon, buf.__array_interface__["data"][0]) == 0
        n2 = 2 * horizon
        return (buf[:n2].reshape(horizon, 2), buf[n2:2 * n2].reshape(horizon, 2),
                buf[2 * n2:5 * horizon], None if d is None else buf[5 * horizon:].reshape(
                    horizon, 3)), finite


_LOADED: dict[tuple[str, str], MotionKernel | None] = {}


def motion_kernel(python_loop: PythonLoop, cache_dir: str = DEFAULT_CACHE_DIR,
                  source: str | None = None) -> MotionKernel | None:
    """The checked kernel (once per process and source), or None (the Python loop; the
    reason logged). ``python_loop``: the reference it is checked against; ``source``: other
    C (tests: a deliberately wrong kernel must fail the check)."""
    text = SOURCE_PATH.read_text() if source is None else source
    key = (str(Path(cache_dir).expanduser()), source_key(text))
    # (no lock: the core stays free of threading; two threads loading at once would both
    # build and check the same library, each renaming its own file into place)
    if key not in _LOADED:
        try:
            _LOADED[key] = _load_checked(Path(key[0]), text, python_loop)
        except (OSError, subprocess.SubprocessError, AttributeError) as exc:
            _log.warning("compiled prediction: unavailable (%s); the Python loop", exc)
            _LOADED[key] = None
    return _LOADED[key]


def _load_checked(directory: Path, text: str, python_loop: PythonLoop) -> MotionKernel | None:
    library = compiled_library(directory, text, "prediction", "compiled prediction")
    if library is None:
        return None
    fn = ct.CDLL(str(library)).predict_motion
    fn.restype = ct.c_int
    fn.argtypes = [ct.POINTER(ct.c_double), ct.c_int, ct.c_void_p]
    kernel = MotionKernel(fn)
    mismatch = first_mismatch(kernel, python_loop)
    if mismatch:
        _log.warning("compiled prediction: %s differs from the Python loop; the Python loop",
                     mismatch)
        return None
    _log.debug("compiled prediction: %s", library)
    return kernel


def check_cases(count: int = 200, seed: int = 20261128
                ) -> list[tuple[Values, int, list[float] | None]]:
    """The check's inputs: pseudo-random motions (fixed seed), each with and without a
    disturbance and a speed cap, and the edge cases (stopped, crawling below the 1e-6 m/s
    threshold, decelerating through zero, a cap below and above the speed, no turn)."""
    rng = np.random.default_rng(seed)
    cases: list[tuple[Values, int, list[float] | None]] = []
    for i in range(count):
        v = rng.normal(0.0, 1.0, 2) * (0.0 if i % 17 == 0 else 1e-7 if i % 19 == 0 else 1.0)
        a = rng.normal(0.0, 0.5, 2)
        speed = float(np.hypot(v[0], v[1]))
        w = float(rng.normal(0.0, 0.4)) if i % 5 else 0.0
        cap = (None, 0.3, 1.0, 2.5, math.nan)[(i // 2) % 5]
        d = None if i % 3 == 0 else [float(x) for x in rng.normal(0.0, 0.3, 3)]
        values = (float(v[0]), float(v[1]), float(a[0]), float(a[1]), speed, w,
                  float(rng.uniform(-math.pi, math.pi)), (0.05, 0.1, 0.0333)[i % 3], cap)
        cases.append((values, (16, 1, 40)[i % 3], d))
    return cases


def first_mismatch(kernel: MotionKernel, python_loop: PythonLoop) -> str:
    """The first case (:func:`check_cases`) whose arrays differ in any bit, or ""."""
    for values, horizon, d in check_cases():
        (got, finite), want = kernel(values, horizon, d), python_loop(values, horizon, d)
        if not finite:
            return f"non-finite flag on finite values ({values}, N {horizon})"
        for name, g, w in zip(("v_a", "vdot_a", "psidot_a", "disturbance"), got, want,
                              strict=True):
            if (g is None) != (w is None):
                return f"{name} present in one only ({values}, N {horizon})"
            if g is not None and w is not None and not (
                    g.shape == w.shape and np.array_equal(g.view(np.uint64),
                                                          np.ascontiguousarray(w).view(np.uint64))):
                return f"{name} ({values}, N {horizon}, d {d})"
    return ""
