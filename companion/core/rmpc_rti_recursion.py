"""``rti_lin`` with H and g by a backward recursion (``rmpc.rti_linearisation = "recursion"``).

The same stage functions as the C loops (:mod:`companion.core.rmpc_rti_loops`, whose library
layout, sizes, helpers and API this reuses), but the condensed Gauss-Newton Hessian
``H = 2 J_r' J_r`` and gradient ``g = 2 J_r' r`` are not formed from the condensed residual
Jacobian ``J_r``: with the stage terms ``Q_n = R_x' R_x``, ``S_n = R_u' R_x``,
``R_n = R_u' R_u``, ``q_n = R_x' r``, ``s_n = R_u' r`` (stage ``n``'s residual ``r`` and its
Jacobians ``R_x``, ``R_u``) and the terminal ``W_N = R_N' R_N``, ``w_N = R_N' r_N``, the
backward recursion

    W_n = Q_n + A_n' W_{n+1} A_n,          w_n = q_n + A_n' w_{n+1},
    H[n][n] = R_n + B_n' W_{n+1} B_n,      g[n] = s_n + B_n' w_{n+1},
    H[n][k] = (S_n + B_n' W_{n+1} A_n) dx_n/du_k   (k < n)

gives the same matrix (the sum over the later stages' residuals of ``dx_m/du_n' R_x' R_x
dx_m/du_k`` collected into ``W_{n+1}``), with ~1/4 of the multiplications: per stage a few
7 x 7 products and one 4 x 7 times ``dx_n/dU`` (the state rows the loops already form for the
path rows and the state box), instead of ``J_r``'s rows times themselves. The sums run in
another order, so the numbers differ from the graph form's in the last bits (~1e-15
relative; tests/core/test_rmpc_rti_recursion.py bounds them at 1e-12 relative to H's, g's
largest entry): a log flown with "graph" or "loops" replays on its own recorded form.
"""

from __future__ import annotations

from companion.core import rmpc_rti_loops

_ENTRY_MARK = "CASADI_SYMBOL_EXPORT int rti_lin("
_API_MARK = "CASADI_SYMBOL_EXPORT casadi_int rti_lin_n_in"

ENTRY = r"""
/* out (m x k, column-major) = X' Y, X (rows x m) and Y (rows x k) column-major */
static void rti_tdot(const casadi_real* X, const casadi_real* Y, int rows, int m, int k,
                     casadi_real* out) {
  int a, b, i;
  for (b = 0; b < k; ++b)
    for (a = 0; a < m; ++a) {
      casadi_real s = 0.;
      for (i = 0; i < rows; ++i) s += X[rows * a + i] * Y[rows * b + i];
      out[a + m * b] = s;
    }
}

/* out (NX x k, column-major) = W (NX x NX) Y (NX x k), column-major */
static void rti_wmul(const casadi_real* W, const casadi_real* Y, int k, casadi_real* out) {
  int i, j, b;
  for (b = 0; b < k; ++b) {
    for (i = 0; i < NX; ++i) out[i + NX * b] = 0.;
    for (j = 0; j < NX; ++j) {
      casadi_real y = Y[j + NX * b];
      for (i = 0; i < NX; ++i) out[i + NX * b] += W[i + NX * j] * y;
    }
  }
}

/* one stage's terms of the recursion, kept from the forward pass for the backward one */
typedef struct {
  casadi_real A[NX * NX], B[NX * NU], Q[NX * NX], S[NU * NX], R[NU * NU], q[NX], s[NU];
} rti_terms_t;

/* stage n backwards: its H rows (lower part) and g entries from W, w (W_{n+1}, w_{n+1}),
   then W, w become W_n, w_n; Sx: dx_n/dU (NX rows, row stride NUA; none at n = 0) */
static void rti_back(const rti_terms_t* t, int n, const casadi_real* Sx, casadi_real* W,
                     casadi_real* w, casadi_real* H, casadi_real* g) {
  casadi_real WA[NX * NX], WB[NX * NU], M[NU * NX], D[NU * NU], v[NX];
  int a, b, i;
  rti_wmul(W, t->A, NX, WA);
  rti_wmul(W, t->B, NU, WB);
  rti_tdot(t->B, WB, NX, NU, NU, D);
  rti_tdot(t->B, WA, NX, NU, NX, M);
  for (i = 0; i < NU * NX; ++i) M[i] += t->S[i];
  if (n > 0) rti_mul(M, NU, Sx, NU * n, H + NU * n * NUA);
  for (a = 0; a < NU; ++a)
    for (b = 0; b <= a; ++b) H[(NU * n + a) * NUA + NU * n + b] = t->R[a + NU * b] + D[a + NU * b];
  rti_tdot(t->B, w, NX, NU, 1, v);
  for (a = 0; a < NU; ++a) g[NU * n + a] = t->s[a] + v[a];
  rti_tdot(t->A, w, NX, NX, 1, v);
  for (i = 0; i < NX; ++i) w[i] = t->q[i] + v[i];
  rti_tdot(t->A, WA, NX, NX, NX, W);
  for (i = 0; i < NX * NX; ++i) W[i] += t->Q[i];
}

CASADI_SYMBOL_EXPORT int rti_lin(const casadi_real** arg, casadi_real** res, casadi_int* iw,
                                 casadi_real* w, int mem) {
  const casadi_real *U = arg[0], *p = arg[2];
  casadi_real *H = res[0], *g = res[1], *cv = res[2], *Jc = res[3];
  casadi_real x[NX], r[NRMAX], gv[NGMAX], Rx[NRMAX * NX], Ru[NRMAX * NU], Gx[NGMAX * NX],
      Gu[NGMAX * NU], W[NX * NX], wv[NX];
  rti_terms_t terms[NH];
  const casadi_real* S = Jc; /* dx(n)/dU: the state rows of stage n (none at n = 0) */
  casadi_real sw[SZ_W];
  casadi_int siw[SZ_IW + 1];
  const casadi_real* sarg[SZ_ARG];
  casadi_real* sres[SZ_RES];
  int n, i, c, ncol, rowg = NS;
  (void)iw; (void)w; (void)mem;
  for (i = 0; i < NX; ++i) x[i] = arg[1][i];
  for (n = 0; n < NH; ++n) {
    rti_terms_t* t = terms + n;
    ncol = NU * n;
    sarg[0] = x; sarg[1] = U + NU * n; sarg[2] = p + NPS * n; sarg[3] = p + NPS * NH;
    sres[0] = cv + NX * n; sres[1] = r; sres[2] = gv; sres[3] = t->A; sres[4] = t->B;
    sres[5] = Rx; sres[6] = Ru; sres[7] = Gx; sres[8] = Gu;
    if (rti_stage_fn[n](sarg, sres, siw, sw, 0)) return 1;
    rti_tdot(Rx, Rx, NR, NX, NX, t->Q);
    rti_tdot(Ru, Rx, NR, NU, NX, t->S);
    rti_tdot(Ru, Ru, NR, NU, NU, t->R);
    rti_tdot(Rx, r, NR, NX, 1, t->q);
    rti_tdot(Ru, r, NR, NU, 1, t->s);
    if (rti_ng[n]) {
      rti_rows(Gx, Gu, rti_ng[n], S, ncol, Jc + rowg * NUA);
      for (i = 0; i < rti_ng[n]; ++i) cv[rowg + i] = gv[i];
      rowg += rti_ng[n];
    }
    /* dx(n+1)/du(k) = A dx(n)/du(k), k < n; B at k = n: the state rows of stage n+1 */
    rti_rows(t->A, t->B, NX, S, ncol, Jc + NX * n * NUA);
    S = Jc + NX * n * NUA;
    for (i = 0; i < NX; ++i) x[i] = cv[NX * n + i];
  }
  sarg[0] = x;
  sres[0] = r; sres[1] = gv; sres[2] = Rx; sres[3] = Gx;
  if (rti_terminal_fn(sarg, sres, siw, sw, 0)) return 1;
  rti_rows(Gx, 0, NGT, S, NUA, Jc + rowg * NUA);
  for (i = 0; i < NGT; ++i) cv[rowg + i] = gv[i];
  rti_tdot(Rx, Rx, NRT, NX, NX, W);
  rti_tdot(Rx, r, NRT, NX, 1, wv);
  for (n = NH - 1; n >= 0; --n)
    rti_back(terms + n, n, n > 0 ? Jc + NX * (n - 1) * NUA : 0, W, wv, H, g);
  /* H's lower triangle doubled, mirrored onto the upper one */
  for (i = 0; i < NUA; ++i) {
    g[i] *= 2.;
    for (c = 0; c <= i; ++c) { H[i * NUA + c] *= 2.; H[c * NUA + i] = H[i * NUA + c]; }
  }
  return 0;
}

"""
"""``rti_lin`` by the recursion (module docstring), between the loops' helpers and API."""


def _driver() -> str:
    head, found, rest = rmpc_rti_loops.DRIVER.partition(_ENTRY_MARK)
    _, api_found, api = rest.partition(_API_MARK)
    if not found or not api_found:
        raise RuntimeError("rmpc_rti_loops.DRIVER: its rti_lin entry or API not found")
    return f"{head}{ENTRY.strip()}\n\n{_API_MARK}{api}"


DRIVER = _driver()
"""The loops' typedef and helpers, :data:`ENTRY`, the loops' API functions."""
