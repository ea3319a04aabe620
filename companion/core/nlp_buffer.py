"""Zero-copy evaluation of a compiled CasADi NLP solver, shared by the controller's own solver
(:class:`companion.core.rmpc_nlp.NlpSolver`) and the solver process's loaded copy
(:class:`companion.control.solver_child.LoadedNlp`), so that the two evaluate the same library
the same way (bit-identical results). Imports only CasADi and numpy: a solver process loads it
without the rest of the controller.

CasADi's FunctionBuffer reads the solver's inputs from numpy arrays and writes x, f, g into
output arrays, with no DM conversion (4 DMs in, 3 out: ~0.3-0.8 ms of Python-side overhead per
call measured on this machine). The arrays are filled in place: the buffer keeps pointers to
them. The multipliers' initial guesses are left unset (0, as with an empty DM).
"""

from __future__ import annotations

from typing import Any

import casadi as ca
import numpy as np

#: the solver statistics a result carries
STATS_KEYS = ("success", "return_status", "unified_return_status", "iter_count")


class NlpBuffer:
    """``solver``'s zero-copy buffer over arrays of its own; ``lbg``/``ubg`` are used in place
    (the buffer keeps pointers to them: do not rebind them, fill them)."""

    def __init__(self, solver: ca.Function, lbg: np.ndarray, ubg: np.ndarray) -> None:
        nw, ng = int(solver.nnz_in(0)), len(lbg)
        buf: Any = solver.buffer()[0]  # (the stubs want a byte size the binding infers)
        self._buf = buf
        self._w0_in, self._p_in = np.zeros(nw), np.zeros(int(solver.nnz_in(1)))
        self._lbx_in, self._ubx_in = np.zeros(nw), np.zeros(nw)
        self._x_out, self._f_out, self._g_out = np.zeros(nw), np.zeros(1), np.zeros(ng)
        for i, a in enumerate((self._w0_in, self._p_in, self._lbx_in, self._ubx_in, lbg, ubg)):
            buf.set_arg(i, a.data)
        for i, a in enumerate((self._x_out, self._f_out, self._g_out)):
            buf.set_res(i, a.data)

    def evaluate(self, w0: np.ndarray, par: np.ndarray, lbx: np.ndarray,
                 ubx: np.ndarray) -> tuple[int, dict[str, Any], np.ndarray, float, np.ndarray]:
        """One evaluation in this thread: (return flag, :data:`STATS_KEYS` statistics, x, f,
        g). CasADi's ``RuntimeError`` passes through."""
        self._w0_in[:] = w0
        self._p_in[:] = par
        self._lbx_in[:] = lbx
        self._ubx_in[:] = ubx
        self._buf._eval()
        flag = int(self._buf.ret())
        # per-solve entries (success, return_status, iter_count) are set by every solve; the
        # buffer does not reset the cumulative counters and timers, which are not read here
        st = self._buf.stats() if flag == 0 else {}
        stats = {k: st[k] for k in STATS_KEYS if k in st}
        return flag, stats, self._x_out.copy(), float(self._f_out[0]), self._g_out.copy()
