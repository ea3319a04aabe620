/* cv2.resize(src, (2w, 2h), interpolation=INTER_LINEAR) of a uint8, one-channel image, bit for
 * bit (sim_bridge/camera/upsample.py builds it and checks it against OpenCV before use; SSE2,
 * x86-64's baseline: OpenCV's own kernels for this call are its SSE2 baseline ones too, and
 * assemble the horizontal pass's pixel pairs with scalar shifts).
 *
 * OpenCV's fixed-point path for an exact 2x: the horizontal sum h in quarters (output column
 * 2k from source columns k-1, k with weights 1, 3; 2k+1 from k, k+1 with 3, 1; the first and
 * last output columns 4 times their edge pixel); the rows take the same taps with the edge's
 * index clamped and the weights kept; out = (floor(h0 b0 / 4) + floor(h1 b1 / 4) + 2) >> 2
 * with b the row weights (its vertical pass: pmulhw of h << 5 by b << 9). With a = floor(h / 4)
 * and c = floor(3 h / 4) per source row: output row 2j is (a[j-1] + c[j] + 2) >> 2, row 2j+1
 * is (c[j] + a[j+1] + 2) >> 2 (indices clamped). Every value fits 16 bits (3 h <= 3060). */
#include <stdint.h>
#include <immintrin.h>

#define AVX2 __attribute__((target("avx2")))

/* a = floor(h/4), c = floor(3h/4) of the horizontal sums of one source row (2w values) */
/* the even and odd columns of source columns k .. k+15 (k >= 1, k + 16 < w), 32 values each */
AVX2 static int row_ac_avx2(const uint8_t *s, int w, uint16_t *a, uint16_t *c)
{
    int k = 1;
    for (; k + 16 < w; k += 16) {
        __m256i p = _mm256_cvtepu8_epi16(_mm_loadu_si128((const __m128i *)(s + k - 1)));
        __m256i q = _mm256_cvtepu8_epi16(_mm_loadu_si128((const __m128i *)(s + k)));
        __m256i r = _mm256_cvtepu8_epi16(_mm_loadu_si128((const __m128i *)(s + k + 1)));
        __m256i q3 = _mm256_add_epi16(q, _mm256_add_epi16(q, q));
        __m256i e = _mm256_add_epi16(p, q3), o = _mm256_add_epi16(q3, r);
        __m256i e3 = _mm256_add_epi16(e, _mm256_add_epi16(e, e));
        __m256i o3 = _mm256_add_epi16(o, _mm256_add_epi16(o, o));
        __m256i ea = _mm256_srli_epi16(e, 2), oa = _mm256_srli_epi16(o, 2);
        __m256i ec = _mm256_srli_epi16(e3, 2), oc = _mm256_srli_epi16(o3, 2);
        /* the unpacks interleave within each 128-bit half: put the halves back in order */
        __m256i al = _mm256_unpacklo_epi16(ea, oa), ah = _mm256_unpackhi_epi16(ea, oa);
        __m256i cl = _mm256_unpacklo_epi16(ec, oc), ch = _mm256_unpackhi_epi16(ec, oc);
        _mm256_storeu_si256((__m256i *)(a + 2 * k), _mm256_permute2x128_si256(al, ah, 0x20));
        _mm256_storeu_si256((__m256i *)(a + 2 * k + 16), _mm256_permute2x128_si256(al, ah, 0x31));
        _mm256_storeu_si256((__m256i *)(c + 2 * k), _mm256_permute2x128_si256(cl, ch, 0x20));
        _mm256_storeu_si256((__m256i *)(c + 2 * k + 16), _mm256_permute2x128_si256(cl, ch, 0x31));
    }
    return k;
}

static int use_avx2;

static void row_ac(const uint8_t *s, int w, uint16_t *a, uint16_t *c)
{
    const __m128i z = _mm_setzero_si128();
    int h0 = 4 * s[0];
    a[0] = (uint16_t)(h0 >> 2);
    c[0] = (uint16_t)((3 * h0) >> 2);
    /* k from 1: even column 2k = s[k-1] + 3 s[k], odd column 2k+1 = 3 s[k] + s[k+1]; the
     * vector loop takes k = 1 .. while k + 8 < w (needs s[k+8] for the odd of k+7) */
    int k = use_avx2 ? row_ac_avx2(s, w, a, c) : 1;
    for (; k + 8 < w; k += 8) {
        __m128i p = _mm_unpacklo_epi8(_mm_loadl_epi64((const __m128i *)(s + k - 1)), z);
        __m128i q = _mm_unpacklo_epi8(_mm_loadl_epi64((const __m128i *)(s + k)), z);
        __m128i r = _mm_unpacklo_epi8(_mm_loadl_epi64((const __m128i *)(s + k + 1)), z);
        __m128i q3 = _mm_add_epi16(q, _mm_add_epi16(q, q));
        __m128i e = _mm_add_epi16(p, q3);               /* columns 2k, 2k+2, ... */
        __m128i o = _mm_add_epi16(q3, r);               /* columns 2k+1, ... */
        __m128i e3 = _mm_add_epi16(e, _mm_add_epi16(e, e));
        __m128i o3 = _mm_add_epi16(o, _mm_add_epi16(o, o));
        __m128i ea = _mm_srli_epi16(e, 2), oa = _mm_srli_epi16(o, 2);
        __m128i ec = _mm_srli_epi16(e3, 2), oc = _mm_srli_epi16(o3, 2);
        _mm_storeu_si128((__m128i *)(a + 2 * k), _mm_unpacklo_epi16(ea, oa));
        _mm_storeu_si128((__m128i *)(a + 2 * k + 8), _mm_unpackhi_epi16(ea, oa));
        _mm_storeu_si128((__m128i *)(c + 2 * k), _mm_unpacklo_epi16(ec, oc));
        _mm_storeu_si128((__m128i *)(c + 2 * k + 8), _mm_unpackhi_epi16(ec, oc));
    }
    for (; k < w; k++) {
        int e = s[k - 1] + 3 * s[k];
        a[2 * k] = (uint16_t)(e >> 2);
        c[2 * k] = (uint16_t)((3 * e) >> 2);
        if (k < w - 1) {
            int o = 3 * s[k] + s[k + 1];
            a[2 * k + 1] = (uint16_t)(o >> 2);
            c[2 * k + 1] = (uint16_t)((3 * o) >> 2);
        }
    }
    /* column 1 (k = 0's odd) and the last column */
    int o0 = 3 * s[0] + (w > 1 ? s[1] : s[0]);
    a[1] = (uint16_t)(o0 >> 2);
    c[1] = (uint16_t)((3 * o0) >> 2);
    int hl = 4 * s[w - 1];
    a[2 * w - 1] = (uint16_t)(hl >> 2);
    c[2 * w - 1] = (uint16_t)((3 * hl) >> 2);
}

/* (x + y + 2) >> 2 of the first multiple of 32 values */
AVX2 static int mix_avx2(const uint16_t *x, const uint16_t *y, int n, uint8_t *out)
{
    const __m256i two = _mm256_set1_epi16(2);
    int i = 0;
    for (; i + 32 <= n; i += 32) {
        __m256i lo = _mm256_srli_epi16(_mm256_add_epi16(_mm256_add_epi16(
            _mm256_loadu_si256((const __m256i *)(x + i)),
            _mm256_loadu_si256((const __m256i *)(y + i))), two), 2);
        __m256i hi = _mm256_srli_epi16(_mm256_add_epi16(_mm256_add_epi16(
            _mm256_loadu_si256((const __m256i *)(x + i + 16)),
            _mm256_loadu_si256((const __m256i *)(y + i + 16))), two), 2);
        /* the pack works per 128-bit half: quarters 0, 2, 1, 3 are the output's order */
        _mm256_storeu_si256((__m256i *)(out + i),
                            _mm256_permute4x64_epi64(_mm256_packus_epi16(lo, hi), 0xD8));
    }
    return i;
}

static void mix(const uint16_t *x, const uint16_t *y, int n, uint8_t *out)
{
    const __m128i two = _mm_set1_epi16(2);
    int i = use_avx2 ? mix_avx2(x, y, n, out) : 0;
    for (; i + 16 <= n; i += 16) {
        __m128i lo = _mm_srli_epi16(_mm_add_epi16(_mm_add_epi16(
            _mm_loadu_si128((const __m128i *)(x + i)), _mm_loadu_si128((const __m128i *)(y + i))), two), 2);
        __m128i hi = _mm_srli_epi16(_mm_add_epi16(_mm_add_epi16(
            _mm_loadu_si128((const __m128i *)(x + i + 8)), _mm_loadu_si128((const __m128i *)(y + i + 8))), two), 2);
        _mm_storeu_si128((__m128i *)(out + i), _mm_packus_epi16(lo, hi));
    }
    for (; i < n; i++)
        out[i] = (uint8_t)((x[i] + y[i] + 2) >> 2);
}

int upsample2x_u8(const uint8_t *src, int h, int w, long sstep, uint8_t *dst, long dstep,
                  uint16_t *scratch)
{
    if (h < 1 || w < 2)
        return -1;
    __builtin_cpu_init();
    use_avx2 = __builtin_cpu_supports("avx2");
    int n = 2 * w;
    uint16_t *pa = scratch, *pc = scratch + n, *a = scratch + 2 * n, *c = scratch + 3 * n;
    row_ac(src, w, pa, pc);
    mix(pa, pc, n, dst);
    for (int j = 1; j < h; j++) {
        row_ac(src + j * sstep, w, a, c);
        mix(pc, a, n, dst + (2 * j - 1) * dstep);
        mix(pa, c, n, dst + (2 * j) * dstep);
        uint16_t *t = pa; pa = a; a = t;
        t = pc; pc = c; c = t;
    }
    mix(pc, pa, n, dst + (2 * h - 1) * dstep);
    return 0;
}
