"""One QP of the RTI step as one foreign call (``rti_qp``, C in the linearisation's library).

:meth:`companion.core.rmpc_rti.RtiSolver.step` spends ~30 us of Python a QP between its
compiled parts (the linearisation, the QP's bounds, DAQP, the state box's test, the update
and clipping of the inputs, the nonlinear check), and in flight, where a step starts with
cold caches, each crossing costs more. ``rti_qp`` (the C after the API of
:data:`companion.core.rmpc_rti_loops.DRIVER`, so in the ``"loops"`` and ``"recursion"``
libraries) runs them in a row on the arrays the step keeps, reading every pointer from one
table built here once:

0. on the step's first QP, the guess clipped to the input box (as 5.);
1. ``rti_lin`` on its argument and output arrays (the same call ``ca.external`` makes);
2. the QP's bounds ``u_max - U``, ``u_min - U``, ``path_upper - c_p`` (the Python step's
   subtractions, element by element: the same IEEE numbers);
3. DAQP's ``daqp_quadprog`` on :class:`companion.core.rmpc_daqp.DirectQp`'s structs (the same
   call as :meth:`~companion.core.rmpc_daqp.DirectQp.solve`);
4. the state box, linearised, ``lo <= J_x du + c_x <= hi``: the Python step decides it on
   numpy's product (BLAS: its summation order is the library's). Here a row passes only if
   it holds with a margin of ``1e-12 (sum |J_x du| + |c_x|) + 1e-300``, ~70 times any
   summation order's rounding (``2 gamma_64 sum |J_x du|`` plus the addition's; the
   absolute term: products below the normal range, which round absolutely), so that numpy's
   number passes too; a failed QP, or any row not clearly inside, returns to Python, which
   decides exactly as before (the whole QP with the state box's rows, or its failure);
5. ``U += du`` clipped to the input box (``np.maximum`` then ``np.minimum``: a NaN stays);
6. ``rti_val``, the nonlinear check, on its arrays (the state box written there by the step).

So a step that goes through it computes the same numbers bit for bit as one that does not
(tests/core/test_rmpc_rti_cstep.py: every step record of the paper and edge loops). Its
return: 0 (the QP solved, the inputs updated, the check evaluated: read ``rti_val``'s
outputs), 1 (step 3 or 4 returned: DAQP's result is in its struct, the inputs not updated),
-1 / -2 (``rti_lin`` / ``rti_val`` failed).
"""

from __future__ import annotations

import ctypes as ct
import functools
from collections.abc import Callable
from pathlib import Path

import casadi as ca
import numpy as np

from companion.core.rmpc_daqp import DirectQp

SLOTS = 24
"""Entries of the pointer table (its layout: :class:`CStep`'s ``__init__``)."""


def _address(a: np.ndarray) -> int:
    return int(a.ctypes.data)


class CStep:
    """``rti_qp`` of the library at ``lin_library`` bound to the step's arrays (module
    docstring). ``lin_args`` (U, eta0, p), ``lin_res`` (H, g, c, J_c'): ``rti_lin``'s
    arrays; ``val``: ``rti_val``'s CasADi function (its work sizes) and ``val_args``,
    ``val_res`` its arrays; the arrays must stay in place while this object is used."""

    def __init__(self, lin_library: Path, val_library: Path, qp: DirectQp,
                 lin_args: list[np.ndarray], lin_res: list[np.ndarray], val: ca.Function,
                 val_args: list[np.ndarray], val_res: list[np.ndarray],
                 bounds: tuple[np.ndarray, ...]) -> None:
        lib, val_lib = ct.CDLL(str(lin_library)), ct.CDLL(str(val_library))
        fn = lib.rti_qp
        fn.restype = ct.c_int
        fn.argtypes = [ct.c_void_p, ct.c_int]
        u_max, u_min, path_upper, up, lo = bounds
        for a in (*lin_args, *lin_res, *val_args, *val_res, *bounds):
            if a.dtype != np.float64 or not a.flags.c_contiguous:
                raise ValueError("CStep: the arrays must be C-contiguous float64")
        n_u, n_p = lin_args[0].size, lin_res[2].size - val_args[3].size  # (C: NUA, NC - NS)
        if {u_max.size, u_min.size} != {n_u} or path_upper.size != n_p \
                or {up.size, lo.size} != {n_u + n_p}:
            raise ValueError("CStep: the bounds' sizes are not the library's")
        # rti_val's work arrays (CasADi's generated code uses arg/res beyond n_in/n_out)
        self._val_arg = (ct.c_void_p * max(int(val.sz_arg()), len(val_args)))(
            *(_address(a) for a in val_args))
        self._val_res = (ct.c_void_p * max(int(val.sz_res()), len(val_res)))(
            *(_address(a) for a in val_res))
        self._val_iw = np.zeros(max(int(val.sz_iw()), 1), dtype=np.int64)
        self._val_w = np.zeros(max(int(val.sz_w()), 1))
        # the table rti_qp reads: 0-2 rti_lin's arguments (U, eta0, p), 3-6 its outputs
        # (H, g, c, J_c'), 7 unused, 8-11 daqp_quadprog and its result, problem and
        # settings, 12-16 u_max, u_min, path_upper, the QP's upper and lower bounds, 17-18
        # the state box (rti_val's arguments 3, 4), 19-23 rti_val, its arg and res tables,
        # its iw and w
        slots: list[int | None] = [
            *(_address(a) for a in lin_args), *(_address(a) for a in lin_res), None,
            *qp.pointers(),
            *(_address(a) for a in (u_max, u_min, path_upper, up, lo)),
            _address(val_args[3]), _address(val_args[4]),
            ct.cast(val_lib.rti_val, ct.c_void_p).value,
            ct.addressof(self._val_arg), ct.addressof(self._val_res),
            _address(self._val_iw), _address(self._val_w)]
        if len(slots) != SLOTS:
            raise ValueError(f"CStep: {len(slots)} table entries, not {SLOTS}")
        self._table = (ct.c_void_p * SLOTS)(*slots)
        self._keep = (lib, val_lib, qp, lin_args, lin_res, val_args, val_res, bounds)
        self.result = qp.result
        """DAQP's result struct of the last QP (``exitflag``, ``iter``)."""
        self.run: Callable[[int], int] = functools.partial(fn, ct.addressof(self._table))
        """``run(clip)``: one QP (``clip``: first clip the inputs to the box, the step's
        first QP); the return code of the module docstring."""
