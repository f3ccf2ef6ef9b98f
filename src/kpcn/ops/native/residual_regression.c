/* The detail stage's regression with one fit per 2x2 block (kpcn.ops.regression.residual_regression, stride 2,
 * a 3-channel guide, 3 colour channels), in six passes instead of some forty tensor passes:
 *
 *   0. per pixel: the guide g, base = log1p(denoised), r = log1p(noisy) - base, as planes (input rows read at
 *      any stride: the detail stage passes pixel-major views of numpy arrays);
 *   1. per 2x2 block: the means over its four pixels (an odd frame's last row and column repeated, as the
 *      replicate padding does) of g, r', g_i g_j (i <= j) and g_i r' (21 planes), r' = r clipped to
 *      [-clip, clip] (clip <= 0: not clipped);
 *   2. those means over a (2 rb + 1)^2 window of blocks (of the window's blocks inside the frame), then each
 *      block's ridge fit A = (cov(g, g) + eps I)^-1 cov(g, r') by cofactors and its offset -A . mean(g) (12 planes);
 *   3. A and the offset averaged over the same window; per pixel detail = off + A . g, with `bound` clipped to
 *      [-min(|r|, clip), min(|r|, clip)], and out = max(expm1(base + detail), 0), planar (3, height, width).
 *
 * scratch: 9 planes of height x width and 66 of ((height + 1) / 2) x ((width + 1) / 2) floats. Rows split between
 * `threads` OpenMP threads (torch's pool).
 */
#include "kpcn_math.h"

#define STATS 21
#define FIT 12

static inline float clamp_abs(float v, float c) { return v < -c ? -c : (v > c ? c : v); }

/* n values of a row read at a stride into dst (strides 1 and 3, a planar or a pixel-major RGB row, vectorised). */
static void gather_row(const float *restrict src, int64_t stride, int n, float *restrict dst) {
    if (stride == 1) {
        memcpy(dst, src, (size_t)n * sizeof *dst);
    } else if (stride == 3) {
        for (int x = 0; x < n; ++x) dst[x] = src[3 * x];
    } else {
        for (int x = 0; x < n; ++x) dst[x] = src[(int64_t)x * stride];
    }
}

/* The 2x2 block means of the products a * clip(b) of two planes, each given as its two rows of the block row
 * (b clipped to [-c, c]; a = NULL: b's own block means); an odd width's last block repeats its column. */
static void block_means(const float *const a[2], const float *const b[2], float c, float *restrict out, int width) {
    const float *restrict b0 = b[0], *restrict b1 = b[1];
    const int pairs = width / 2;
    if (a) {
        const float *restrict a0 = a[0], *restrict a1 = a[1];
        for (int j = 0; j < pairs; ++j)
            out[j] = ((a0[2 * j] * clamp_abs(b0[2 * j], c) + a0[2 * j + 1] * clamp_abs(b0[2 * j + 1], c))
                      + (a1[2 * j] * clamp_abs(b1[2 * j], c) + a1[2 * j + 1] * clamp_abs(b1[2 * j + 1], c))) * 0.25f;
    } else {
        for (int j = 0; j < pairs; ++j)
            out[j] = ((clamp_abs(b0[2 * j], c) + clamp_abs(b0[2 * j + 1], c))
                      + (clamp_abs(b1[2 * j], c) + clamp_abs(b1[2 * j + 1], c))) * 0.25f;
    }
    if (width % 2) {
        const int x = width - 1;
        const float p0 = (a ? a[0][x] : 1.0f) * clamp_abs(b0[x], c), p1 = (a ? a[1][x] : 1.0f) * clamp_abs(b1[x], c);
        out[pairs] = ((p0 + p0) + (p1 + p1)) * 0.25f;
    }
}

/* The horizontal window mean of `planes` planes of block row bi: src -> dst (planes of hb x wb). */
static void box_row_x(const float *restrict src, float *restrict dst, int planes, int64_t plane, int bi, int wb,
                      int rb) {
    for (int q = 0; q < planes; ++q) {
        const float *restrict s = src + q * plane + (int64_t)bi * wb;
        float *restrict o = dst + q * plane + (int64_t)bi * wb;
        for (int j = 0; j < wb; ++j) {
            const int lo = j - rb < 0 ? 0 : j - rb, hi = j + rb > wb - 1 ? wb - 1 : j + rb;
            float acc = 0.0f;
            for (int k = lo; k <= hi; ++k) acc += s[k];
            o[j] = acc / (float)(hi - lo + 1);
        }
    }
}

/* The vertical window mean at block row bi of `planes` planes of src into row (planes x wb). */
static void box_row_y(const float *restrict src, float *restrict row, int planes, int64_t plane, int bi, int hb,
                      int wb, int rb) {
    const int lo = bi - rb < 0 ? 0 : bi - rb, hi = bi + rb > hb - 1 ? hb - 1 : bi + rb;
    const float inv = 1.0f / (float)(hi - lo + 1);
    for (int q = 0; q < planes; ++q) {
        float *restrict o = row + (int64_t)q * wb;
        for (int j = 0; j < wb; ++j) o[j] = 0.0f;
        for (int k = lo; k <= hi; ++k) {
            const float *restrict s = src + q * plane + (int64_t)k * wb;
            for (int j = 0; j < wb; ++j) o[j] += s[j];
        }
        for (int j = 0; j < wb; ++j) o[j] *= inv;
    }
}

/* Each block's fit of block row m (STATS x wb window means) into its FIT planes at fo. */
static void fit_row(const float *restrict m, float *restrict fo, int64_t plane, int wb, float eps) {
    for (int bj = 0; bj < wb; ++bj) {
        const float mg0 = m[0 * wb + bj], mg1 = m[1 * wb + bj], mg2 = m[2 * wb + bj];
        const float a = m[6 * wb + bj] - mg0 * mg0 + eps, b = m[7 * wb + bj] - mg0 * mg1;
        const float cc = m[8 * wb + bj] - mg0 * mg2, d = m[9 * wb + bj] - mg1 * mg1 + eps;
        const float e = m[10 * wb + bj] - mg1 * mg2, f = m[11 * wb + bj] - mg2 * mg2 + eps;
        const float a00 = d * f - e * e, a01 = cc * e - b * f, a02 = b * e - cc * d;
        const float a11 = a * f - cc * cc, a12 = b * cc - a * e, a22 = a * d - b * b;
        const float inv = 1.0f / (a * a00 + b * a01 + cc * a02);
        for (int c = 0; c < 3; ++c) {
            const float mr = m[(3 + c) * wb + bj];
            const float c0 = m[(12 + c) * wb + bj] - mg0 * mr, c1 = m[(15 + c) * wb + bj] - mg1 * mr;
            const float c2 = m[(18 + c) * wb + bj] - mg2 * mr;
            const float k0 = (a00 * c0 + a01 * c1 + a02 * c2) * inv;
            const float k1 = (a01 * c0 + a11 * c1 + a12 * c2) * inv;
            const float k2 = (a02 * c0 + a12 * c1 + a22 * c2) * inv;
            fo[c * plane + bj] = k0;
            fo[(3 + c) * plane + bj] = k1;
            fo[(6 + c) * plane + bj] = k2;
            fo[(9 + c) * plane + bj] = -(k0 * mg0 + k1 * mg1 + k2 * mg2);
        }
    }
}

/* One output row: detail from the block row's averaged fits m (FIT x wb), bounded, added in log1p space. */
static void output_row(const float *restrict m, const float *const g[3], const float *const base[3],
                       const float *const res[3], float *const out[3], int wb, int width, float clip, int bound) {
    for (int c = 0; c < 3; ++c) {
        const float *restrict k0 = m + c * wb, *restrict k1 = m + (3 + c) * wb;
        const float *restrict k2 = m + (6 + c) * wb, *restrict off = m + (9 + c) * wb;
        const float *restrict g0 = g[0], *restrict g1 = g[1], *restrict g2 = g[2];
        const float *restrict bs = base[c], *restrict rs = res[c];
        float *restrict o = out[c];
        for (int x = 0; x < width; ++x) {
            const int bj = x >> 1;
            float detail = off[bj] + g0[x] * k0[bj] + g1[x] * k1[bj] + g2[x] * k2[bj];
            if (bound) {
                const float r = rs[x];
                float reach = r < 0.0f ? -r : r;
                reach = reach < clip ? reach : clip;
                detail = clamp_abs(detail, reach);
            }
            const float v = expm1_poly(bs[x] + detail);
            o[x] = v > 0.0f ? v : 0.0f;
        }
    }
}

void residual_regression_s2(const float *dp, int64_t d_c, int64_t d_y, int64_t d_x,
                            const float *np_, int64_t n_c, int64_t n_y, int64_t n_x,
                            const float *gp, int64_t g_c, int64_t g_y, int64_t g_x,
                            float *out, int height, int width, int rb, float eps, float clip, int bound,
                            float *scratch, int threads) {
    const int hb = (height + 1) / 2, wb = (width + 1) / 2;
    const int64_t full = (int64_t)height * width, plane = (int64_t)hb * wb;
    float *G = scratch, *B = G + 3 * full, *R = B + 3 * full;
    float *stats = R + 3 * full, *tmp = stats + STATS * plane, *fit = tmp + STATS * plane, *fit_x = fit + FIT * plane;
    const float fclip = clip > 0.0f ? clip : 3.0e38f;
    #pragma omp parallel num_threads(threads)
    {
        #pragma omp for schedule(static)
        for (int y = 0; y < height; ++y) {  /* 0. planes of g, log1p(denoised) and r */
            for (int c = 0; c < 3; ++c) {
                float *restrict bo = B + c * full + (int64_t)y * width;
                float *restrict ro = R + c * full + (int64_t)y * width;
                gather_row(gp + c * g_c + (int64_t)y * g_y, g_x, width, G + c * full + (int64_t)y * width);
                gather_row(dp + c * d_c + (int64_t)y * d_y, d_x, width, bo);
                gather_row(np_ + c * n_c + (int64_t)y * n_y, n_x, width, ro);
                for (int x = 0; x < width; ++x) {
                    const float dv = bo[x], nv = ro[x];
                    const float base = log1p_poly(dv > 0.0f ? dv : 0.0f);
                    bo[x] = base;
                    ro[x] = log1p_poly(nv > 0.0f ? nv : 0.0f) - base;
                }
            }
        }
        #pragma omp for schedule(static)
        for (int bi = 0; bi < hb; ++bi) {  /* 1. the blocks' means of the per-pixel terms, plane by plane */
            const int64_t y0 = (int64_t)(2 * bi) * width;
            const int64_t y1 = (int64_t)(2 * bi + 1 < height ? 2 * bi + 1 : height - 1) * width;
            float *o = stats + (int64_t)bi * wb;
            const float *gr[3][2], *rr[3][2];
            for (int c = 0; c < 3; ++c) {
                gr[c][0] = G + c * full + y0;
                gr[c][1] = G + c * full + y1;
                rr[c][0] = R + c * full + y0;
                rr[c][1] = R + c * full + y1;
            }
            const float none = 3.0e38f;  /* the guide is not clipped */
            int q = 0;
            for (int c = 0; c < 3; ++c, ++q) block_means(NULL, gr[c], none, o + q * plane, width);
            for (int c = 0; c < 3; ++c, ++q) block_means(NULL, rr[c], fclip, o + q * plane, width);
            for (int i = 0; i < 3; ++i)
                for (int j = i; j < 3; ++j, ++q) block_means(gr[i], gr[j], none, o + q * plane, width);
            for (int i = 0; i < 3; ++i)
                for (int c = 0; c < 3; ++c, ++q) block_means(gr[i], rr[c], fclip, o + q * plane, width);
        }
        #pragma omp for schedule(static)
        for (int bi = 0; bi < hb; ++bi) box_row_x(stats, tmp, STATS, plane, bi, wb, rb);
        #pragma omp for schedule(static)
        for (int bi = 0; bi < hb; ++bi) {  /* 2. the window means, and each block's fit */
            float *m = stats + (int64_t)bi * STATS * wb;  /* stats' values are in tmp now: its room is free */
            box_row_y(tmp, m, STATS, plane, bi, hb, wb, rb);
            fit_row(m, fit + (int64_t)bi * wb, plane, wb, eps);
        }
        #pragma omp for schedule(static)
        for (int bi = 0; bi < hb; ++bi) box_row_x(fit, fit_x, FIT, plane, bi, wb, rb);
        #pragma omp for schedule(static)
        for (int bi = 0; bi < hb; ++bi) {  /* 3. the fits' window means applied to the block's pixels */
            float *m = stats + (int64_t)bi * FIT * wb;  /* free again: the fits are in fit_x */
            box_row_y(fit_x, m, FIT, plane, bi, hb, wb, rb);
            for (int h = 0; h < 2 && 2 * bi + h < height; ++h) {
                const int64_t row = (int64_t)(2 * bi + h) * width;
                const float *g[3] = {G + row, G + full + row, G + 2 * full + row};
                const float *base[3] = {B + row, B + full + row, B + 2 * full + row};
                const float *res[3] = {R + row, R + full + row, R + 2 * full + row};
                float *o[3] = {out + row, out + full + row, out + 2 * full + row};
                output_row(m, g, base, res, o, wb, width, fclip, bound);
            }
        }
    }
}
