/* The rectangle detector's "lean2" sub-pixel edges (companion/perception/edges_lean2.py,
 * refine_quad_lean2) as one C call: the same numbers bit for bit as the numpy path.
 *
 * How the numbers are kept (compiled with -ffp-contract=off, no fast-math: every float and
 * double operation below is one IEEE operation, rounded as written):
 *  - the profiles' samples: cv2.warpAffine (INTER_LINEAR, WARP_INVERSE_MAP, BORDER_REPLICATE,
 *    uint8) as OpenCV 5 computes it: per destination row y the offset Mx = f(M1) f(y) + f(M2)
 *    in float (two roundings), per column x the source position sx = fma(f(M0), x, Mx) (one
 *    rounding), its floor and fraction a = sx - floor(sx) in float, the bilinear value
 *    fma(b, f1 - f0, f0) with f0 = fma(a, p01 - p00, p00), f1 = fma(a, p11 - p10, p10), and
 *    the byte by round-half-even and saturation; replicated border: each index clamped.
 *    The Python side checks this against cv2 on random matrices before using it (a
 *    mismatch: the numpy path);
 *  - numpy's float32 arithmetic in float, its float64 in double, in numpy's order: sums of
 *    float64 rows with numpy's pairwise summation (8 accumulators), the line fits' moments
 *    (`A @ ones` in numpy) through the same BLAS function numpy calls (cblas_dgemv, pointer
 *    from Python), atan2/cos/sin/sqrt from the same libm Python's math module calls.
 */
#include <math.h>
#include <stdint.h>
#include <string.h>

typedef void (*dgemv_fn)(int order, int trans, int64_t m, int64_t n, double alpha,
                         const double *a, int64_t lda, const double *x, int64_t incx,
                         double beta, double *y, int64_t incy);

enum { MAXN = 256, MAXK = 129 };

typedef struct {            /* the grid of a batch of profiles (edges_lean2._Grid2) */
    int k, n, in0, in1, out0, out1, passes, uf;
    double k0, h, k0h, half_px, min_contrast;
    float in_norm;
    const float *prio;      /* k - 1 */
    dgemv_fn dgemv;
} Grid;

typedef struct { double x0, y0, tx, ty, sp; } Frame;
typedef struct { double cu, cv, c, s, rms, kept; } Line;

typedef struct {            /* one pass's results */
    double e[4 * MAXN];
    unsigned char ok[4 * MAXN];
    double width[4];
} Pass;

/* fma in float through double: a * b is exact in double (24 + 24 bits); p + c rounded to
 * double then to float rounds twice only when the double lands on a float midpoint (its
 * low 29 mantissa bits 0x10000000): then the exact remainder (TwoSum) says which way. */
static float fma32(float a, float b, float c) {
    double p = (double)a * (double)b;
    double s = p + (double)c;
    uint64_t bits;
    memcpy(&bits, &s, sizeof bits);
    if ((bits & 0x1FFFFFFFull) == 0x10000000ull) {
        double bb = s - p;
        double err = (p - (s - bb)) + ((double)c - bb);
        if (err != 0.0) s = nextafter(s, err > 0.0 ? INFINITY : -INFINITY);
    }
    return (float)s;
}

static int ifloor(float v) {
    int i = (int)v;
    return ((float)i > v) ? i - 1 : i;
}

static int clampi(int v, int lo, int hi) { return v < lo ? lo : (v > hi ? hi : v); }

/* cv2.warpAffine of one edge's profiles into dst (k rows, n columns); -1 when a position
 * is beyond +-2^22 px (not emulated: the caller uses the numpy path). OpenCV's vector loop
 * covers the columns in blocks of `uf` (two vectors of float lanes: 16 with AVX2), the rest
 * its scalar loop: sx = fma(f(x), M0, f(y) M1) + M2 (the compiler's contraction of
 * x*M0 + y*M1 + M2), the same interpolation. The body is written once (FMA: the fused
 * multiply-add used): with the CPU's fma instruction where it has one, else fma32. */
#define WARP_BODY(FMA)                                                                     \
    float m0 = (float)m[0], m1 = (float)m[1], m2 = (float)m[2];                           \
    float m3 = (float)m[3], m4 = (float)m[4], m5 = (float)m[5];                           \
    int nv = uf > 0 ? n - n % uf : 0;                                                     \
    for (int y = 0; y < k; y++) {                                                         \
        float fy = (float)y;                                                              \
        float mx = m1 * fy, my = m4 * fy;                                                 \
        float vx = mx + m2, vy = my + m5;                                                 \
        for (int x = 0; x < n; x++) {                                                     \
            float fx = (float)x, sx, sy;                                                  \
            if (x < nv) {                                                                 \
                sx = FMA(m0, fx, vx);                                                     \
                sy = FMA(m3, fx, vy);                                                     \
            } else {                                                                      \
                sx = FMA(fx, m0, mx) + m2;                                                \
                sy = FMA(fx, m3, my) + m5;                                                \
            }                                                                             \
            if (!(fabsf(sx) < 4194304.0f && fabsf(sy) < 4194304.0f)) return -1;           \
            int ix = ifloor(sx), iy = ifloor(sy);                                         \
            float a = sx - (float)ix, b = sy - (float)iy;                                 \
            int x0 = clampi(ix, 0, cols - 1), x1 = clampi(ix + 1, 0, cols - 1);           \
            int y0 = clampi(iy, 0, rows - 1), y1 = clampi(iy + 1, 0, rows - 1);           \
            const uint8_t *r0 = img + y0 * stride, *r1 = img + y1 * stride;               \
            float p00 = r0[x0], p01 = r0[x1], p10 = r1[x0], p11 = r1[x1];                 \
            float f0 = FMA(a, p01 - p00, p00), f1 = FMA(a, p11 - p10, p10);               \
            float r = FMA(b, f1 - f0, f0);                                                \
            float q = (r + 12582912.0f) - 12582912.0f; /* round half to even, |r| < 2^22 */ \
            dst[y * n + x] = (uint8_t)(q <= 0.0f ? 0 : (q >= 255.0f ? 255 : (int)q));     \
        }                                                                                 \
    }                                                                                     \
    return 0;

static int warp_soft(const uint8_t *img, int64_t stride, int rows, int cols, const double m[6],
                     int k, int n, int uf, uint8_t *dst) {
    WARP_BODY(fma32)
}

#if defined(__x86_64__) && defined(__GNUC__)
#include <immintrin.h>

__attribute__((target("fma"))) static int warp_fma(const uint8_t *img, int64_t stride,
                                                   int rows, int cols, const double m[6],
                                                   int k, int n, int uf, uint8_t *dst) {
    WARP_BODY(__builtin_fmaf)
}

/* The same numbers eight columns at a time (AVX2 + FMA: the operations of OpenCV's own
 * vector loop, lane by lane), the columns past the last full block of 8 as warp_fma. */
__attribute__((target("avx2,fma"))) static int warp_avx2(const uint8_t *img, int64_t stride,
                                                         int rows, int cols,
                                                         const double m[6], int k, int n,
                                                         int uf, uint8_t *dst) {
    int nv = uf > 0 ? n - n % uf : 0;
    int n8 = nv - nv % 8;
    if (n8 < nv || n8 == 0) return warp_fma(img, stride, rows, cols, m, k, n, uf, dst);
    float m0 = (float)m[0], m1 = (float)m[1], m2 = (float)m[2];
    float m3 = (float)m[3], m4 = (float)m[4], m5 = (float)m[5];
    const __m256 lim = _mm256_set1_ps(4194304.0f), sign = _mm256_set1_ps(-0.0f);
    const __m256i zero = _mm256_setzero_si256(), one = _mm256_set1_epi32(1);
    const __m256i cmax = _mm256_set1_epi32(cols - 1), rmax = _mm256_set1_epi32(rows - 1);
    const __m256i bmax = _mm256_set1_epi32(255), lanes = _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7);
    int32_t i00[8], i01[8], i10[8], i11[8], q[8];
    for (int y = 0; y < k; y++) {
        float fy = (float)y;
        float mx = m1 * fy, my = m4 * fy;
        const __m256 vx = _mm256_set1_ps(mx + m2), vy = _mm256_set1_ps(my + m5);
        const __m256 vm0 = _mm256_set1_ps(m0), vm3 = _mm256_set1_ps(m3);
        for (int x = 0; x < n8; x += 8) {
            __m256 fx = _mm256_cvtepi32_ps(_mm256_add_epi32(lanes, _mm256_set1_epi32(x)));
            __m256 sx = _mm256_fmadd_ps(vm0, fx, vx), sy = _mm256_fmadd_ps(vm3, fx, vy);
            __m256 ok = _mm256_and_ps(_mm256_cmp_ps(_mm256_andnot_ps(sign, sx), lim, _CMP_LT_OQ),
                                      _mm256_cmp_ps(_mm256_andnot_ps(sign, sy), lim, _CMP_LT_OQ));
            if (_mm256_movemask_ps(ok) != 0xFF) return -1;
            __m256 flx = _mm256_floor_ps(sx), fly = _mm256_floor_ps(sy);
            __m256 a = _mm256_sub_ps(sx, flx), b = _mm256_sub_ps(sy, fly);
            __m256i ix = _mm256_cvttps_epi32(flx), iy = _mm256_cvttps_epi32(fly);
            __m256i x0 = _mm256_min_epi32(_mm256_max_epi32(ix, zero), cmax);
            __m256i x1 = _mm256_min_epi32(_mm256_max_epi32(_mm256_add_epi32(ix, one), zero), cmax);
            __m256i y0 = _mm256_min_epi32(_mm256_max_epi32(iy, zero), rmax);
            __m256i y1 = _mm256_min_epi32(_mm256_max_epi32(_mm256_add_epi32(iy, one), zero), rmax);
            _mm256_storeu_si256((__m256i *)i00, x0);
            _mm256_storeu_si256((__m256i *)i01, x1);
            _mm256_storeu_si256((__m256i *)i10, y0);
            _mm256_storeu_si256((__m256i *)i11, y1);
            float p00[8], p01[8], p10[8], p11[8];
            for (int l = 0; l < 8; l++) {
                const uint8_t *r0 = img + i10[l] * stride, *r1 = img + i11[l] * stride;
                p00[l] = r0[i00[l]];
                p01[l] = r0[i01[l]];
                p10[l] = r1[i00[l]];
                p11[l] = r1[i01[l]];
            }
            __m256 v00 = _mm256_loadu_ps(p00), v01 = _mm256_loadu_ps(p01);
            __m256 v10 = _mm256_loadu_ps(p10), v11 = _mm256_loadu_ps(p11);
            __m256 f0 = _mm256_fmadd_ps(a, _mm256_sub_ps(v01, v00), v00);
            __m256 f1 = _mm256_fmadd_ps(a, _mm256_sub_ps(v11, v10), v10);
            __m256 r = _mm256_fmadd_ps(b, _mm256_sub_ps(f1, f0), f0);
            __m256i v = _mm256_cvtps_epi32(r); /* round half to even (MXCSR's default) */
            v = _mm256_min_epi32(_mm256_max_epi32(v, zero), bmax);
            _mm256_storeu_si256((__m256i *)q, v);
            for (int l = 0; l < 8; l++) dst[y * n + x + l] = (uint8_t)q[l];
        }
    }
    /* the columns from n8 on: the scalar body (uf's tail included) */
    for (int y = 0; y < k; y++) {
        float fy = (float)y;
        float mx = m1 * fy, my = m4 * fy;
        float vx = mx + m2, vy = my + m5;
        for (int x = n8; x < n; x++) {
            float fx = (float)x, sx, sy;
            if (x < nv) {
                sx = __builtin_fmaf(m0, fx, vx);
                sy = __builtin_fmaf(m3, fx, vy);
            } else {
                sx = __builtin_fmaf(fx, m0, mx) + m2;
                sy = __builtin_fmaf(fx, m3, my) + m5;
            }
            if (!(fabsf(sx) < 4194304.0f && fabsf(sy) < 4194304.0f)) return -1;
            int ix = ifloor(sx), iy = ifloor(sy);
            float a = sx - (float)ix, b = sy - (float)iy;
            int x0 = clampi(ix, 0, cols - 1), x1 = clampi(ix + 1, 0, cols - 1);
            int y0 = clampi(iy, 0, rows - 1), y1 = clampi(iy + 1, 0, rows - 1);
            const uint8_t *r0 = img + y0 * stride, *r1 = img + y1 * stride;
            float p00 = r0[x0], p01 = r0[x1], p10 = r1[x0], p11 = r1[x1];
            float f0 = __builtin_fmaf(a, p01 - p00, p00), f1 = __builtin_fmaf(a, p11 - p10, p10);
            float r = __builtin_fmaf(b, f1 - f0, f0);
            float qq = (r + 12582912.0f) - 12582912.0f;
            dst[y * n + x] = (uint8_t)(qq <= 0.0f ? 0 : (qq >= 255.0f ? 255 : (int)qq));
        }
    }
    return 0;
}
#endif

static int warp(const uint8_t *img, int64_t stride, int rows, int cols, const double m[6],
                int k, int n, int uf, uint8_t *dst) {
#if defined(__x86_64__) && defined(__GNUC__)
    if (__builtin_cpu_supports("avx2") && __builtin_cpu_supports("fma"))
        return warp_avx2(img, stride, rows, cols, m, k, n, uf, dst);
    if (__builtin_cpu_supports("fma")) return warp_fma(img, stride, rows, cols, m, k, n, uf, dst);
#endif
    return warp_soft(img, stride, rows, cols, m, k, n, uf, dst);
}

/* numpy's pairwise sum of a float64 row (n <= 128: 8 accumulators), from 0.0 */
static double pairwise(const double *a, int n) {
    double res;
    if (n < 8) {
        res = -0.0;
        for (int i = 0; i < n; i++) res += a[i];
    } else {
        double r[8];
        int i;
        for (int j = 0; j < 8; j++) r[j] = a[j];
        for (i = 8; i < n - (n % 8); i += 8)
            for (int j = 0; j < 8; j++) r[j] += a[i + j];
        res = ((r[0] + r[1]) + (r[2] + r[3])) + ((r[4] + r[5]) + (r[6] + r[7]));
        for (; i < n; i++) res += a[i];
    }
    return 0.0 + res;
}

static void sort_d(double *v, int n) {
    for (int i = 1; i < n; i++) {
        double x = v[i];
        int j = i - 1;
        while (j >= 0 && v[j] > x) { v[j + 1] = v[j]; j--; }
        v[j + 1] = x;
    }
}

/* edges_lean2._median of the sorted first `count` entries */
static double median(const double *v, int count) {
    if (count <= 0) return 1.0;
    int h = count / 2;
    return (count % 2 == 1) ? v[h] : 0.5 * (v[h - 1] + v[h]);
}

/* edges_lean2._pass */
static int one_pass(const uint8_t *img, int64_t stride, int rows, int cols, const Grid *g,
                    const Frame *fr, const double *scale, int want_width, uint8_t *raw,
                    Pass *out) {
    int k = g->k, n = g->n;
    for (int i = 0; i < 4; i++) {
        double nx = fr[i].ty * scale[i], ny = -fr[i].tx * scale[i];
        double m[6] = {fr[i].sp * fr[i].tx, g->h * nx, fr[i].x0 + g->k0 * nx,
                       fr[i].sp * fr[i].ty, g->h * ny, fr[i].y0 + g->k0 * ny};
        if (warp(img, stride, rows, cols, m, k, n, g->uf, raw + i * k * n) != 0) return -1;
    }
    float minc = (float)g->min_contrast, k0h = (float)g->k0h;
    for (int i = 0; i < 4; i++) {
        const uint8_t *p = raw + i * k * n;
        double spacing = scale[i] * g->h;
        double wbuf[MAXN];
        int cnt = 0;
        for (int j = 0; j < n; j++) {
            float inside = 0.0f;
            for (int r = g->in0; r < g->in1; r++) inside = inside + (float)p[r * n + j];
            inside = inside * g->in_norm;
            float outside = (float)p[g->out0 * n + j];
            for (int r = g->out0 + 1; r < g->out1; r++) {
                float v = (float)p[r * n + j];
                if (v < outside) outside = v;
            }
            float level = 0.5f * (inside + outside);
            int idx = 0;
            float best = 0.0f;
            int above_prev = (float)p[j] >= level;
            for (int r = 0; r < k - 1; r++) {
                int above_next = (float)p[(r + 1) * n + j] >= level;
                float score = (above_prev > above_next) ? g->prio[r] : 0.0f;
                if (r == 0 || score > best) { best = score; idx = r; }
                above_prev = above_next;
            }
            float v0 = (float)p[idx * n + j], v1 = (float)p[(idx + 1) * n + j];
            float d = v0 - v1;
            if (!(d >= 1e-6f)) d = 1e-6f;
            float frac = (v0 - level) / d;
            float contrast = inside - outside;
            int ok = (v0 >= level) && (v1 < level) && (contrast >= minc);
            out->ok[i * n + j] = (unsigned char)ok;
            out->e[i * n + j] = ((double)idx + (double)(frac + k0h)) * spacing;
            if (want_width && ok) {
                static const int near[3] = {-2, 0, 2};
                float drop = 0.0f;
                for (int q = 0; q < 3; q++) {
                    int r = clampi(idx + near[q], 0, k - 2);
                    float dr = (float)p[r * n + j] - (float)p[(r + 1) * n + j];
                    if (q == 0 || dr > drop) drop = dr;
                }
                if (!(drop >= 1e-6f)) drop = 1e-6f;
                wbuf[cnt++] = ((double)contrast * spacing) / (double)drop;
            }
        }
        if (want_width) {
            sort_d(wbuf, cnt);
            out->width[i] = median(wbuf, cnt);
        }
    }
    return 0;
}

/* per edge the centroid and direction of the weighted (0/1) points: edges_lean._tls
 * (moments by pairwise sums) or edges_lean2._tls2 (moments by dgemv) */
static void tls(const Grid *g, const double *u, const double *v, const double *w, int gemv,
                Line *ln) {
    int n = g->n;
    double a[24 * MAXN], mom[24], ones[MAXN];
    for (int i = 0; i < 4; i++)
        for (int j = 0; j < n; j++) {
            int ij = i * n + j;
            double wu = w[ij] * u[ij], wv = w[ij] * v[ij];
            a[(0 + i) * n + j] = w[ij];
            a[(4 + i) * n + j] = wu;
            a[(8 + i) * n + j] = wv;
            a[(12 + i) * n + j] = wu * u[ij];
            a[(16 + i) * n + j] = wu * v[ij];
            a[(20 + i) * n + j] = wv * v[ij];
        }
    if (gemv) {
        for (int j = 0; j < n; j++) ones[j] = 1.0;
        g->dgemv(102, 112, n, 24, 1.0, a, n, ones, 1, 0.0, mom, 1);
    } else {
        for (int q = 0; q < 24; q++) mom[q] = pairwise(a + q * n, n);
    }
    for (int i = 0; i < 4; i++) {
        double sw = mom[i], su = mom[4 + i], sv = mom[8 + i];
        double suu = mom[12 + i], suv = mom[16 + i], svv = mom[20 + i];
        double cu = su / sw, cv = sv / sw;
        double sxx = suu - su * cu, sxy = suv - su * cv, syy = svv - sv * cv;
        double half = 0.5 * atan2(2.0 * sxy, sxx - syy);
        ln[i].cu = cu;
        ln[i].cv = cv;
        ln[i].c = cos(half);
        ln[i].s = sin(half);
        ln[i].rms = 0.0;
        ln[i].kept = 0.0;
    }
}

static void distances(const Grid *g, const double *u, const double *v, const Line *ln,
                      double *res) {
    int n = g->n;
    for (int i = 0; i < 4; i++) {
        double c0 = ln[i].c, c1 = -ln[i].s, c2 = ln[i].cu * ln[i].s - ln[i].cv * ln[i].c;
        for (int j = 0; j < n; j++) {
            double t = v[i * n + j] * c0 + u[i * n + j] * c1;
            res[i * n + j] = fabs(t + c2);
        }
    }
}

/* edges_lean._fit(final=False) / edges_lean2._fit_final; 1: an edge has too few points */
static int fit(const Grid *g, const double *u, const Pass *ps, int final, Line *ln) {
    int n = g->n, cnt[4];
    double w[4 * MAXN], res[4 * MAXN];
    double need = 0.3 * n;
    if (!(need > 4.0)) need = 4.0;
    for (int i = 0; i < 4; i++) {
        cnt[i] = 0;
        for (int j = 0; j < n; j++) {
            cnt[i] += ps->ok[i * n + j];
            w[i * n + j] = ps->ok[i * n + j] ? 1.0 : 0.0;
        }
        if ((double)cnt[i] < need) return 1;
    }
    tls(g, u, ps->e, w, final, ln);
    if (!final) return 0;
    distances(g, u, ps->e, ln, res);
    int n_keep[4], refit[4], any = 0;
    double bound[4];
    for (int i = 0; i < 4; i++) {
        double srt[MAXN];
        int c = 0;
        for (int j = 0; j < n; j++)
            if (ps->ok[i * n + j]) srt[c++] = res[i * n + j];
        sort_d(srt, c);
        double b = 3.0 * (median(srt, cnt[i]) * 1.4826 + 0.05);
        bound[i] = (0.3 > b) ? 0.3 : b;
        n_keep[i] = 0;
        for (int j = 0; j < n; j++)
            n_keep[i] += ps->ok[i * n + j] && res[i * n + j] <= bound[i];
        refit[i] = 4 <= n_keep[i] && n_keep[i] < cnt[i];
        any |= refit[i];
    }
    if (any) {
        for (int i = 0; i < 4; i++)
            if (refit[i])
                for (int j = 0; j < n; j++)
                    w[i * n + j] = (ps->ok[i * n + j] && res[i * n + j] <= bound[i]) ? 1.0 : 0.0;
        tls(g, u, ps->e, w, 1, ln);
        distances(g, u, ps->e, ln, res);
    }
    for (int i = 0; i < 4; i++) {
        double sq[MAXN];
        for (int j = 0; j < n; j++) sq[j] = w[i * n + j] * res[i * n + j] * res[i * n + j];
        double used = refit[i] ? (double)n_keep[i] : (double)cnt[i];
        ln[i].rms = sqrt(pairwise(sq, n) / used);
        ln[i].kept = (double)n_keep[i] / (double)n;
    }
    return 0;
}

/* edges_lean2._converged */
static int converged(const Line *ln, const double *u, int n, double eps) {
    for (int i = 0; i < 4; i++) {
        double end = u[i * n + n - 1];
        if (fabs(ln[i].c) < 0.5) return 0;
        double slope = ln[i].s / ln[i].c;
        if (fabs(ln[i].cv - ln[i].cu * slope) > eps
            || fabs(ln[i].cv + (end - ln[i].cu) * slope) > eps) return 0;
    }
    return 1;
}

/* edges_lean._on_line */
static Frame on_line(Frame f, Line ln) {
    double c = ln.c, s = ln.s;
    if (c < 0.0) { c = -c; s = -s; }
    double dx = c * f.tx + s * f.ty, dy = c * f.ty - s * f.tx;
    double px = f.x0 + ln.cu * f.tx + ln.cv * f.ty, py = f.y0 + ln.cu * f.ty - ln.cv * f.tx;
    double a = (f.x0 - px) * dx + (f.y0 - py) * dy;
    Frame o = {px + a * dx, py + a * dy, dx, dy, f.sp};
    return o;
}

/* edges_lean2._widen_reads */
static void widen_reads(double *reads, const Frame *fr, const double *scale, const Grid *g) {
    int last = g->n - 1;
    double half = -g->k0;
    double lx = reads[0], ly = reads[1], hx = reads[2], hy = reads[3];
    for (int i = 0; i < 4; i++) {
        double a = 0.5 * fr[i].sp * (double)last, b = half * scale[i];
        double cx = fr[i].x0 + a * fr[i].tx, cy = fr[i].y0 + a * fr[i].ty;
        double rx = fabs(a * fr[i].tx) + fabs(b * fr[i].ty);
        double ry = fabs(a * fr[i].ty) + fabs(b * fr[i].tx);
        if (cx - rx < lx) lx = cx - rx;
        if (cx + rx > hx) hx = cx + rx;
        if (cy - ry < ly) ly = cy - ry;
        if (cy + ry > hy) hy = cy + ry;
    }
    reads[0] = lx; reads[1] = ly; reads[2] = hx; reads[3] = hy;
}

/* edges_lean.edge_frames; 1: an edge too short */
static int edge_frames(const double *c, const Grid *g, Frame *fr) {
    double margin = 1.5 * g->half_px + 1.0;
    for (int i = 0; i < 4; i++) {
        double ax = c[2 * i], ay = c[2 * i + 1];
        double bx = c[2 * ((i + 1) % 4)], by = c[2 * ((i + 1) % 4) + 1];
        double dx = bx - ax, dy = by - ay;
        double length = sqrt(dx * dx + dy * dy);
        if (length < 2.0 * margin + 4.0) return 1;
        double tx = dx / length, ty = dy / length;
        Frame f = {ax + margin * tx, ay + margin * ty, tx, ty,
                   (length - 2.0 * margin) / (double)(g->n - 1)};
        fr[i] = f;
    }
    return 0;
}

/* refine_quad_lean2 from its edge frames to the lines; returns 0, 1 (None), -1 (warp) */
static int passes(const uint8_t *img, int64_t stride, int rows, int cols, const Grid *g,
                  Frame *fr, const double *scale_in, double *reads, uint8_t *raw,
                  double *u, Line *ln, double *scale) {
    static const double ones[4] = {1.0, 1.0, 1.0, 1.0};
    Pass ps;
    int n = g->n, tracked = scale_in != NULL, rc;
    const double *sc = tracked ? scale_in : ones;
    for (int i = 0; i < 4; i++)
        for (int j = 0; j < n; j++) u[i * n + j] = (double)j * fr[i].sp;
    if (reads) widen_reads(reads, fr, sc, g);
    if ((rc = one_pass(img, stride, rows, cols, g, fr, sc, 1, raw, &ps)) != 0) return rc;
    if (fit(g, u, &ps, tracked, ln)) return 1;
    for (int i = 0; i < 4; i++) {
        double w = ps.width[i];
        double m = (1.0 > w) ? 1.0 : w;
        double v = (0.5 + 0.9 * m) / 1.4;
        v = (1.0 > v) ? 1.0 : v;
        scale[i] = (3.0 < v) ? 3.0 : v;
    }
    if (tracked && converged(ln, u, n, 0.1)) return 0;
    for (int it = 1; it < g->passes; it++) {
        for (int i = 0; i < 4; i++) fr[i] = on_line(fr[i], ln[i]);
        if (reads) widen_reads(reads, fr, scale, g);
        if ((rc = one_pass(img, stride, rows, cols, g, fr, scale, 0, raw, &ps)) != 0) return rc;
        int last = it == g->passes - 1;
        if (fit(g, u, &ps, tracked || last, ln)) return 1;
        if (tracked && converged(ln, u, n, 0.02)) break;
    }
    return 0;
}

/* The whole refine_quad_lean2.
 * img: uint8 rows x cols, row stride `stride` bytes; corners: 4 x 2; grid: k, n, in0, in1,
 * out0, out1, passes, uf (the warp's vector block), then k0, h, k0 / h, profile_half_px, min_contrast, in_norm; prio: k - 1
 * floats; scale_in: 4 or NULL (not tracked); reads: 4 (widened) or NULL; work: 4 k n bytes.
 * out: corners 8, points 8, directions 8, rms 4, kept 4, scale 4.
 * Returns 0 (out written), 1 (None: an edge too short or too few profiles, or two adjacent
 * lines parallel), -1 (a sample beyond the emulated range: use the numpy path), -2 (sizes). */
int lean2_refine(const uint8_t *img, int64_t stride, int rows, int cols, const double *corners,
                 const int64_t *gi, const double *gd, const float *prio, void *dgemv,
                 const double *scale_in, double *reads, uint8_t *work, double *out) {
    Grid g = {(int)gi[0], (int)gi[1], (int)gi[2], (int)gi[3], (int)gi[4], (int)gi[5],
              (int)gi[6], (int)gi[7], gd[0], gd[1], gd[2], gd[3], gd[4], (float)gd[5], prio,
              (dgemv_fn)dgemv};
    if (g.k < 3 || g.k > MAXK || g.n < 2 || g.n > MAXN || rows < 1 || cols < 1) return -2;
    Frame fr[4];
    Line ln[4];
    double u[4 * MAXN], scale[4];
    if (edge_frames(corners, &g, fr)) return 1;
    int rc = passes(img, stride, rows, cols, &g, fr, scale_in, reads, work, u, ln, scale);
    if (rc != 0) return rc;
    double px[4], py[4], dxs[4], dys[4];
    for (int i = 0; i < 4; i++) {
        Frame f = fr[i];
        px[i] = f.x0 + ln[i].cu * f.tx + ln[i].cv * f.ty;
        py[i] = f.y0 + ln[i].cu * f.ty - ln[i].cv * f.tx;
        dxs[i] = ln[i].c * f.tx + ln[i].s * f.ty;
        dys[i] = ln[i].c * f.ty - ln[i].s * f.tx;
    }
    for (int i = 0; i < 4; i++) {
        int a = (i + 3) % 4;
        double det = dxs[i] * dys[a] - dxs[a] * dys[i];
        if (fabs(det) < 1e-6) return 1;
        double rx = px[i] - px[a], ry = py[i] - py[a];
        double t1 = (dxs[i] * ry - rx * dys[i]) / det;
        out[2 * i] = px[a] + t1 * dxs[a];
        out[2 * i + 1] = py[a] + t1 * dys[a];
    }
    for (int i = 0; i < 4; i++) {
        out[8 + 2 * i] = px[i];
        out[9 + 2 * i] = py[i];
        out[16 + 2 * i] = dxs[i];
        out[17 + 2 * i] = dys[i];
        out[24 + i] = ln[i].rms;
        out[28 + i] = ln[i].kept;
        out[32 + i] = scale[i];
    }
    return 0;
}

/* The samples of one cv2.warpAffine as emulated here (for the check against cv2). */
int lean2_warp(const uint8_t *img, int64_t stride, int rows, int cols, const double *m,
               int k, int n, int uf, uint8_t *dst) {
    return warp(img, stride, rows, cols, m, k, n, uf, dst);
}

/* The same through one of the paths a CPU may take (the tests hold each to cv2): 1 the
 * software fma (fma32), 2 the scalar loop with the fma instruction, 3 AVX2; -2: not on this
 * CPU. */
int lean2_warp_path(int path, const uint8_t *img, int64_t stride, int rows, int cols,
                    const double *m, int k, int n, int uf, uint8_t *dst) {
    if (path == 1) return warp_soft(img, stride, rows, cols, m, k, n, uf, dst);
#if defined(__x86_64__) && defined(__GNUC__)
    if (path == 2 && __builtin_cpu_supports("fma"))
        return warp_fma(img, stride, rows, cols, m, k, n, uf, dst);
    if (path == 3 && __builtin_cpu_supports("avx2") && __builtin_cpu_supports("fma"))
        return warp_avx2(img, stride, rows, cols, m, k, n, uf, dst);
#endif
    return -2;
}
