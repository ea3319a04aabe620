"""DAQP's own C entry, ``daqp_quadprog``, called on the RTI's kept arrays (no per-call Python
wrapping): the same solver, settings and arithmetic as ``daqp.solve``, ~20-25 us less a QP.

``daqp.solve`` (the package's Cython entry) acquires six buffers, allocates the solution and
multiplier arrays, builds the problem and settings structs and a result dict on every call:
measured on 334 QPs of the paper and edge loops, 84 against 58 us warm and 122 against 98 us
with the caches evicted (load ~7). Here the structs are built once, pointing at arrays the
caller keeps and refills in place, so a QP is one foreign call. The structs are DAQP's
``DAQPProblem``, ``DAQPSettings`` and ``DAQPResult`` of the pinned version (``daqp==0.11.0``,
its ``types.h`` and ``api.h``); the settings are ``daqp.solve``'s defaults, read from its
signature, with the caller's iteration limit. :func:`direct` checks at start-up that the
installed package is that version and that a QP solved both ways gives the same solution
bit for bit, and returns None otherwise (the caller then keeps ``daqp.solve``).
"""

from __future__ import annotations

import ctypes as ct
import inspect
import logging
from importlib import metadata
from typing import Any

import daqp
import numpy as np

log = logging.getLogger(__name__)

VERSION = "0.11.0"
"""The DAQP whose structs are laid out here (pyproject.toml pins it)."""

_D, _I = ct.POINTER(ct.c_double), ct.POINTER(ct.c_int)


class _Problem(ct.Structure):
    _fields_ = [("n", ct.c_int), ("m", ct.c_int), ("ms", ct.c_int), ("H", _D), ("f", _D),
                ("A", _D), ("bupper", _D), ("blower", _D), ("sense", _I),
                ("break_points", _I), ("nh", ct.c_int), ("problem_type", ct.c_int)]


_SETTINGS = (("primal_tol", ct.c_double), ("dual_tol", ct.c_double),
             ("zero_tol", ct.c_double), ("pivot_tol", ct.c_double),
             ("progress_tol", ct.c_double), ("cycle_tol", ct.c_int), ("iter_limit", ct.c_int),
             ("fval_bound", ct.c_double), ("eps_prox", ct.c_double), ("eta_prox", ct.c_double),
             ("rho_soft", ct.c_double), ("rel_subopt", ct.c_double),
             ("abs_subopt", ct.c_double), ("sing_tol", ct.c_double),
             ("refactor_tol", ct.c_double), ("time_limit", ct.c_double),
             ("w_soft", ct.c_double), ("eq_reduction", ct.c_int), ("presolve", ct.c_int))


class _Settings(ct.Structure):
    _fields_ = list(_SETTINGS)


class _Result(ct.Structure):
    _fields_ = [("x", _D), ("lam", _D), ("fval", ct.c_double), ("soft_slack", ct.c_double),
                ("exitflag", ct.c_int), ("iter", ct.c_int), ("nodes", ct.c_int),
                ("solve_time", ct.c_double), ("setup_time", ct.c_double)]


class DirectQp:
    """One QP shape on kept arrays: ``H`` (n x n), ``f`` (n), ``A`` (rows x n, C order),
    ``up``, ``lo`` (the first ``n``: simple bounds), ``sense`` (int32); refill them in place
    and :meth:`solve`. The arrays must stay alive and in place while this object is used."""

    def __init__(self, fn: Any, settings: _Settings, h: np.ndarray, f: np.ndarray,
                 a: np.ndarray, up: np.ndarray, lo: np.ndarray, sense: np.ndarray) -> None:
        for arr, dtype in ((h, np.float64), (f, np.float64), (a, np.float64),
                           (up, np.float64), (lo, np.float64), (sense, np.int32)):
            if arr.dtype != dtype or not arr.flags.c_contiguous:
                raise ValueError("DirectQp: the arrays must be C-contiguous float64 / int32")
        n, m = f.size, up.size
        self._keep = (h, f, a, up, lo, sense)
        self.x, self._lam = np.zeros(n), np.zeros(m)
        self._problem = _Problem(n, m, m - a.shape[0], *(arr.ctypes.data_as(_D)
                                                          for arr in (h, f, a, up, lo)),
                                 sense.ctypes.data_as(_I), None, 0, 0)
        self._result = _Result(self.x.ctypes.data_as(_D), self._lam.ctypes.data_as(_D))
        self._settings = settings
        self._args = (ct.byref(self._result), ct.byref(self._problem), ct.byref(settings))
        self._fn = fn

    def pointers(self) -> tuple[int, int, int, int]:
        """The addresses of ``daqp_quadprog`` and of its result, problem and settings structs
        (the arguments of :meth:`solve`'s call, for a caller in C:
        :mod:`companion.core.rmpc_rti_cstep`)."""
        fn = ct.cast(self._fn, ct.c_void_p).value
        if fn is None:
            raise ValueError("DirectQp: daqp_quadprog has no address")
        return (fn, ct.addressof(self._result), ct.addressof(self._problem),
                ct.addressof(self._settings))

    @property
    def result(self) -> _Result:
        """DAQP's result struct (``exitflag``, ``iter``) of the last QP, whoever called DAQP
        on these structs."""
        return self._result

    def solve(self) -> tuple[np.ndarray, int, int]:
        """(solution, exit flag, iterations): ``daqp.solve``'s ``x``, ``exitflag`` and
        ``info["iterations"]``."""
        self._fn(*self._args)
        res = self._result
        return self.x.copy(), res.exitflag, res.iter  # (c_int fields: Python ints)


def direct(iter_limit: int) -> tuple[Any, _Settings] | None:
    """DAQP's ``daqp_quadprog`` and the settings ``daqp.solve(..., iter_limit=iter_limit)``
    uses, or None if the installed DAQP is not :data:`VERSION` or does not solve a test QP
    bit for bit as ``daqp.solve`` does (module docstring)."""
    try:
        if metadata.version("daqp") != VERSION:
            log.info("daqp %s is not %s: daqp.solve", metadata.version("daqp"), VERSION)
            return None
        fn = ct.CDLL(daqp.__file__).daqp_quadprog
        defaults = inspect.signature(daqp.solve).parameters
        values = [iter_limit if k == "iter_limit" else defaults[k].default for k, _ in _SETTINGS]
    except (OSError, AttributeError, KeyError, ValueError, TypeError) as exc:
        log.info("daqp's C entry not used (%s): daqp.solve", exc)
        return None
    fn.restype = None
    fn.argtypes = [ct.POINTER(_Result), ct.POINTER(_Problem), ct.POINTER(_Settings)]
    settings = _Settings(*values)
    if not _agrees(fn, settings, iter_limit):
        log.warning("daqp's C entry disagrees with daqp.solve on a test QP: daqp.solve")
        return None
    return fn, settings


def _agrees(fn: Any, settings: _Settings, iter_limit: int) -> bool:
    """A small QP with simple bounds and rows, some active, solved both ways: the same
    solution, flag and iteration count, bit for bit."""
    rng = np.random.default_rng(3)
    n, rows = 6, 4
    m = rng.normal(size=(n, n))
    h, f = m @ m.T + n * np.eye(n), rng.normal(size=n) * 10
    a = rng.normal(size=(rows, n))
    up, lo = np.full(n + rows, 0.3), np.full(n + rows, -0.2)
    sense = np.zeros(n + rows, np.int32)
    x, _, flag, info = daqp.solve(h, f, a, up, lo, sense, iter_limit=iter_limit)
    mine = DirectQp(fn, settings, h, f, a, up, lo, sense).solve()
    return (bool(np.array_equal(np.asarray(x), mine[0])) and int(flag) == mine[1]
            and int(info.get("iterations", -1)) == mine[2] and mine[2] > 1)
