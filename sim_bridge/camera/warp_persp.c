/* cv2.warpPerspective(src, M, (w, h), flags=INTER_LINEAR | WARP_INVERSE_MAP) of a uint8,
 * one-channel image whose every sampled 2 x 2 neighbourhood lies inside the source, bit for bit
 * with OpenCV 5's float kernel as its AVX2 dispatch computes it (sim_bridge/camera/warp.py
 * builds this file, checks it against cv2.warpPerspective before use and otherwise leaves the
 * warp to OpenCV; docs/reference/emulator.md, section 5.4).
 *
 * What OpenCV computes for destination pixel (x, y), in float32 with the matrix m rounded to
 * float32 first. Per row: kx = y m1 + m2, ky = y m4 + m5, kw = y m7 + m8 (a multiply, then an
 * add). The columns its vector loop covers (16 a turn, so the largest multiple of 16):
 * X = fma(m0, x, kx) / fma(m6, x, kw), Y = fma(m3, x, ky) / (the same w); ix = floor(X),
 * a = X - ix (iy, b likewise); top = fma(a, p01 - p00, p00), bottom = fma(a, p11 - p10, p10),
 * v = fma(b, bottom - top, top); rounded to nearest (ties to even) and saturated. The last
 * columns of a row (fewer than 16) go through its scalar loop, whose expressions the compiler
 * contracted: w = fma(x, m6, y m7) + m8, X = (fma(x, m0, y m1) + m2) / w, Y likewise,
 * v0 = fma(a, p01 - p00, p00), v1 likewise, v = fma(b, v1 - v0, v0) (a pixel at a = 0.96188354,
 * b = 0.82700729 between 174, 148 / 211, 205 gives 195.49998 fused, 195.5 and so 196 unfused:
 * OpenCV gives 195; warp.py's probes hold it).
 *
 * Built with -ffp-contract=off: every fused multiply-add here is an explicit one. Returns 0;
 * -1 when a pixel samples outside [0, w - 4] x [0, h - 2] or a coordinate is not finite (the
 * caller then runs OpenCV, which handles borders); -2 without AVX2 and FMA. */
#include <stdint.h>
#include <immintrin.h>

#define AVX2 __attribute__((target("avx2,fma")))

static inline uint16_t load2(const uint8_t *p)
{
    uint16_t v;
    __builtin_memcpy(&v, p, 2);
    return v;
}

AVX2 static float fma1(float a, float b, float c)
{
    return _mm_cvtss_f32(_mm_fmadd_ss(_mm_set_ss(a), _mm_set_ss(b), _mm_set_ss(c)));
}

AVX2 static float floor1(float v)
{
    return _mm_cvtss_f32(_mm_floor_ss(_mm_setzero_ps(), _mm_set_ss(v)));
}

/* OpenCV's scalar loop for one pixel; -1 if its neighbourhood is outside the fast range */
AVX2 static int tail_pixel(const uint8_t *src, int sw, int sh, long sstep, const float *m,
                           int x, int y, uint8_t *out)
{
    float fx = (float)x, fy = (float)y;
    float w = fma1(fx, m[6], fy * m[7]) + m[8];
    float sx = (fma1(fx, m[0], fy * m[1]) + m[2]) / w;
    float sy = (fma1(fx, m[3], fy * m[4]) + m[5]) / w;
    if (!(sx >= 0.0f && sx < (float)(sw - 3) && sy >= 0.0f && sy < (float)(sh - 1)))
        return -1;
    float fix = floor1(sx), fiy = floor1(sy);
    int ix = (int)fix, iy = (int)fiy;
    float a = sx - fix, b = sy - fiy;
    const uint8_t *p = src + (long)iy * sstep + ix;
    float p00 = p[0], p01 = p[1], p10 = p[sstep], p11 = p[sstep + 1];
    float v0 = fma1(a, p01 - p00, p00);
    float v1 = fma1(a, p11 - p10, p10);
    int r = _mm_cvtss_si32(_mm_set_ss(fma1(b, v1 - v0, v0)));  /* nearest, ties to even */
    *out = (uint8_t)(r < 0 ? 0 : r > 255 ? 255 : r);
    return 0;
}

/* OpenCV's vector loop over the first n (a multiple of 8) pixels of row y */
AVX2 static int vector_row(const uint8_t *src, int sw, int sh, long sstep, const float *m,
                           int y, int n, uint8_t *out)
{
    const float fy = (float)y;
    const __m256 m0 = _mm256_set1_ps(m[0]), m3 = _mm256_set1_ps(m[3]),
                 m6 = _mm256_set1_ps(m[6]);
    const __m256 kx = _mm256_set1_ps(fy * m[1] + m[2]), ky = _mm256_set1_ps(fy * m[4] + m[5]),
                 kw = _mm256_set1_ps(fy * m[7] + m[8]);
    const __m256i xmax = _mm256_set1_epi32(sw - 4), ymax = _mm256_set1_epi32(sh - 2),
                  zero = _mm256_setzero_si256(), lo = _mm256_set1_epi32(0xff),
                  step = _mm256_set1_epi32((int)sstep);
    const __m256 eight = _mm256_set1_ps(8.0f);
    __m256 xs = _mm256_setr_ps(0, 1, 2, 3, 4, 5, 6, 7);
    __m256i bad = zero;
    for (int x = 0; x < n; x += 8) {
        __m256 w = _mm256_fmadd_ps(m6, xs, kw);
        __m256 sx = _mm256_div_ps(_mm256_fmadd_ps(m0, xs, kx), w);
        __m256 sy = _mm256_div_ps(_mm256_fmadd_ps(m3, xs, ky), w);
        xs = _mm256_add_ps(xs, eight);
        __m256 fx = _mm256_floor_ps(sx), fyv = _mm256_floor_ps(sy);
        /* not finite or beyond the int range: 0x80000000, caught as negative */
        __m256i ix = _mm256_cvtps_epi32(fx), iy = _mm256_cvtps_epi32(fyv);
        bad = _mm256_or_si256(bad, _mm256_or_si256(
            _mm256_or_si256(_mm256_cmpgt_epi32(ix, xmax), _mm256_cmpgt_epi32(iy, ymax)),
            _mm256_or_si256(_mm256_cmpgt_epi32(zero, ix), _mm256_cmpgt_epi32(zero, iy))));
        __m256 a = _mm256_sub_ps(sx, fx), b = _mm256_sub_ps(sy, fyv);
        /* a lane out of range reads pixel 0 (the call is refused at the row's end anyway) */
        __m256i addr = _mm256_andnot_si256(bad, _mm256_add_epi32(_mm256_mullo_epi32(iy, step),
                                                                  ix));
        /* the two 16-bit pairs (p00 p01, p10 p11) of each lane, inserted straight from memory */
        int32_t off[8];
        _mm256_storeu_si256((__m256i *)off, addr);
        const uint8_t *row1 = src + sstep;
        __m128i t0 = _mm_cvtsi32_si128(load2(src + off[0]));
        __m128i t1 = _mm_cvtsi32_si128(load2(row1 + off[0]));
#define INS(i) t0 = _mm_insert_epi16(t0, load2(src + off[i]), i); \
               t1 = _mm_insert_epi16(t1, load2(row1 + off[i]), i);
        INS(1) INS(2) INS(3) INS(4) INS(5) INS(6) INS(7)
#undef INS
        __m256i q = _mm256_or_si256(_mm256_cvtepu16_epi32(t0),
                                    _mm256_slli_epi32(_mm256_cvtepu16_epi32(t1), 16));
        __m256 p00 = _mm256_cvtepi32_ps(_mm256_and_si256(q, lo));
        __m256 p01 = _mm256_cvtepi32_ps(_mm256_and_si256(_mm256_srli_epi32(q, 8), lo));
        __m256 p10 = _mm256_cvtepi32_ps(_mm256_and_si256(_mm256_srli_epi32(q, 16), lo));
        __m256 p11 = _mm256_cvtepi32_ps(_mm256_srli_epi32(q, 24));
        __m256 top = _mm256_fmadd_ps(a, _mm256_sub_ps(p01, p00), p00);
        __m256 bot = _mm256_fmadd_ps(a, _mm256_sub_ps(p11, p10), p10);
        __m256i r = _mm256_cvtps_epi32(_mm256_fmadd_ps(b, _mm256_sub_ps(bot, top), top));
        __m128i r16 = _mm_packus_epi32(_mm256_castsi256_si128(r), _mm256_extracti128_si256(r, 1));
        _mm_storel_epi64((__m128i *)(out + x), _mm_packus_epi16(r16, r16));
    }
    return _mm256_testz_si256(bad, bad) ? 0 : -1;
}

int warp_persp_u8(const uint8_t *src, int sh, int sw, long sstep, uint8_t *dst, int dh, int dw,
                  long dstep, const double *dm)
{
    __builtin_cpu_init();
    if (!__builtin_cpu_supports("avx2") || !__builtin_cpu_supports("fma"))
        return -2;
    if (sw < 4 || sh < 2 || dw < 1 || dh < 1 || sstep < sw || sstep > 0x7fffffff / sh)
        return -1;
    float m[9];
    for (int i = 0; i < 9; i++)
        m[i] = (float)dm[i];
    const int nvec = dw / 16 * 16;  /* OpenCV's vector loop: 16 pixels a turn */
    for (int y = 0; y < dh; y++) {
        uint8_t *out = dst + (long)y * dstep;
        if (nvec && vector_row(src, sw, sh, sstep, m, y, nvec, out) != 0)
            return -1;
        for (int x = nvec; x < dw; x++)
            if (tail_pixel(src, sw, sh, sstep, m, x, y, out + x) != 0)
                return -1;
    }
    return 0;
}
