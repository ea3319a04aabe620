/* The rectangle-topped box composited over the ground in its ROI, bit for bit as
 * sim_bridge/camera/target.py's numpy passes compute it (sim_bridge/camera/boxdraw.py builds
 * this file and checks it against those passes before use; docs/reference/emulator.md, 5.4).
 *
 * Per pixel (col, row) of the ROI, in float32 as numpy's ufuncs do (no fused multiply-add:
 * built with -ffp-contract=off): each edge line (nx, ny, c0) gives d = (nx col + ny row) + c0;
 * hmin = the minimum over the silhouette's lines, tmin = the minimum of hmin and the top's own
 * lines; h = clip(hmin, 0, 1), t = clip(tmin, 0, 1); bg = the pixel;
 * out = bg + (side - bg) h, then out = out + dtop t with a top; the pixel = (uint8)(out + 0.5).
 * The caller gives at least one silhouette line (none: its numpy passes). */
#include <stdint.h>
#include <stdlib.h>
#include <emmintrin.h>

/* m[i] = d(e, col i) for the first line (start == 0), else min(m[i], d); one row, vectorised */
static void lines_min(const float *lines, int n, const float *col, float row, int w, float *m,
                      int start)
{
    for (int k = 0; k < n; k++) {
        const float nx = lines[3 * k], ny = lines[3 * k + 1], c0 = lines[3 * k + 2];
        const float r = ny * row;
        if (k == 0 && start) {
            for (int i = 0; i < w; i++)
                m[i] = (nx * col[i] + r) + c0;
        } else {
            for (int i = 0; i < w; i++) {
                float d = (nx * col[i] + r) + c0;
                m[i] = m[i] < d ? m[i] : d;
            }
        }
    }
}

static inline float clip01(float v)
{
    float lo = v > 0.0f ? v : 0.0f;  /* np.clip: minimum(maximum(v, 0), 1) */
    return lo < 1.0f ? lo : 1.0f;
}

/* out = bg + (side - bg) clip(h) [+ dtop clip(t)], the pixel (uint8)(out + 0.5): four pixels a
 * turn with SSE2 (max/min with 0 and 1 as the scalar comparisons give them for finite values,
 * truncation), the rest one by one */
static void blend_row(uint8_t *p, const float *hm, const float *tm, int w, float side, float dtop)
{
    const __m128 z = _mm_setzero_ps(), one = _mm_set1_ps(1.0f), half = _mm_set1_ps(0.5f),
                 vs = _mm_set1_ps(side), vd = _mm_set1_ps(dtop);
    int i = 0;
    for (; i + 4 <= w; i += 4) {
        uint32_t px;
        __builtin_memcpy(&px, p + i, 4);
        __m128 bg = _mm_cvtepi32_ps(_mm_unpacklo_epi16(
            _mm_unpacklo_epi8(_mm_cvtsi32_si128((int)px), _mm_setzero_si128()),
            _mm_setzero_si128()));
        __m128 h = _mm_min_ps(_mm_max_ps(_mm_loadu_ps(hm + i), z), one);
        __m128 out = _mm_add_ps(bg, _mm_mul_ps(_mm_sub_ps(vs, bg), h));
        if (tm) {
            __m128 t = _mm_min_ps(_mm_max_ps(_mm_loadu_ps(tm + i), z), one);
            out = _mm_add_ps(out, _mm_mul_ps(vd, t));
        }
        __m128i r = _mm_cvttps_epi32(_mm_add_ps(out, half));
        r = _mm_packus_epi16(_mm_packs_epi32(r, r), r);
        px = (uint32_t)_mm_cvtsi128_si32(r);
        __builtin_memcpy(p + i, &px, 4);
    }
    for (; i < w; i++) {
        float bg = (float)p[i];
        float out = bg + (side - bg) * clip01(hm[i]);
        if (tm)
            out = out + dtop * clip01(tm[i]);
        p[i] = (uint8_t)(out + 0.5f);
    }
}

int box_rect_u8(uint8_t *img, long step, int x0, int y0, int x1, int y1, const float *hull,
                int nh, const float *top, int nt, int with_top, float side, float dtop)
{
    if (x1 <= x0 || y1 <= y0 || nh < 1 || nt < 0)
        return -1;
    const int w = x1 - x0;
    float *buf = malloc(sizeof(float) * 3 * (size_t)w);
    if (!buf)
        return -1;
    float *col = buf, *hm = buf + w, *tm = buf + 2 * w;
    for (int i = 0; i < w; i++)
        col[i] = (float)(x0 + i);
    for (int y = y0; y < y1; y++) {
        uint8_t *p = img + (long)y * step + x0;
        const float row = (float)y;
        lines_min(hull, nh, col, row, w, hm, 1);
        if (with_top) {
            for (int i = 0; i < w; i++)
                tm[i] = hm[i];
            lines_min(top, nt, col, row, w, tm, 0);
        }
        blend_row(p, hm, with_top ? tm : NULL, w, side, dtop);
    }
    free(buf);
    return 0;
}
