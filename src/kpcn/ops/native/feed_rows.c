/* What a U-Net row stream keeps of a band of feature rows (kpcn.ops.native; kpcn.models.unet_rows.RowStream.feed):
 *
 *   guide[o, y, x]  = relu(b[o] + sum_c w[o, c] * T(x[c, y, x]))       (a 1x1 guide, full resolution)
 *   pooled[c, i, j] = T(pool2(x)[c, i, j])                             (half resolution)
 *
 * T is the input transform: the identity or sign(v) log1p(|v|) (UNetConfig.input_transform "none" / "log"),
 * log1p as kpcn_math.h computes it (within about 2 float32 steps of torch's).
 * pool2 sums as kpcn.models.layers.pool2 does: ((x[2i, 2j] + x[2i+1, 2j]) + (x[2i, 2j+1] + x[2i+1, 2j+1])) / 4.
 * Either output may be float32 or bfloat16 (rounded to nearest even, as torch rounds), at any strides (the pooled
 * features are kept channels-last). The PyTorch path makes several passes over all the channels of the band, at
 * both resolutions; here each pair of rows is read once. Pairs of rows split between `threads` OpenMP threads.
 */
#include "kpcn_math.h"

#define BLOCK 64
#define MAX_CHANNELS 64

static inline float transform(float v, int kind) {
    if (!kind) return v;
    const float a = v < 0.0f ? -v : v;
    const float l = log1p_poly(a);
    return v < 0.0f ? -l : l;
}

/* x: channel c of row y, column j at x[c * x_c + y * x_y + j] (rows, width even); gw: (g_channels, channels)
 * row-major, gb: (g_channels); guide: g[o * g_c + y * g_y + j] (g_channels 0: none); pooled: p[c * p_c + i * p_y +
 * j * p_x]. */
void feed_rows(const float *x, int64_t x_c, int64_t x_y, int channels, int rows, int width, int kind,
               const float *gw, const float *gb, int g_channels, void *guide, int64_t g_c, int64_t g_y, int guide_bf16,
               void *pooled, int64_t p_c, int64_t p_y, int64_t p_x, int pooled_bf16, int threads) {
    #pragma omp parallel for num_threads(threads) schedule(static)
    for (int i = 0; i < rows / 2; ++i) {
        float t[MAX_CHANNELS * BLOCK];
        float acc[BLOCK];
        for (int h = 0; h < 2 && g_channels; ++h) {  /* the guide of both full-resolution rows */
            const int y = 2 * i + h;
            for (int x0 = 0; x0 < width; x0 += BLOCK) {
                const int nx = width - x0 < BLOCK ? width - x0 : BLOCK;
                for (int c = 0; c < channels; ++c) {
                    const float *src = x + c * x_c + (int64_t)y * x_y + x0;
                    float *dst = t + c * BLOCK;
                    for (int j = 0; j < nx; ++j) dst[j] = transform(src[j], kind);
                }
                for (int o = 0; o < g_channels; ++o) {
                    const float *w = gw + (int64_t)o * channels;
                    for (int j = 0; j < nx; ++j) acc[j] = gb[o];
                    for (int c = 0; c < channels; ++c) {
                        const float wc = w[c];
                        const float *tc = t + c * BLOCK;
                        for (int j = 0; j < nx; ++j) acc[j] += wc * tc[j];
                    }
                    const int64_t base = o * g_c + (int64_t)y * g_y + x0;
                    if (guide_bf16) {
                        uint16_t *out = (uint16_t *)guide + base;
                        for (int j = 0; j < nx; ++j) out[j] = float_to_bf16(acc[j] > 0.0f ? acc[j] : 0.0f);
                    } else {
                        float *out = (float *)guide + base;
                        for (int j = 0; j < nx; ++j) out[j] = acc[j] > 0.0f ? acc[j] : 0.0f;
                    }
                }
            }
        }
        const int half = width / 2;
        for (int j0 = 0; j0 < half; j0 += BLOCK) {  /* the pooled row, a block of columns at a time */
            const int nj = half - j0 < BLOCK ? half - j0 : BLOCK;
            for (int c = 0; c < channels; ++c) {
                const float *r0 = x + c * x_c + (int64_t)(2 * i) * x_y + 2 * j0, *r1 = r0 + x_y;
                float *dst = t + c * BLOCK;
                for (int j = 0; j < nj; ++j) {
                    const float even = r0[2 * j] + r1[2 * j], odd = r0[2 * j + 1] + r1[2 * j + 1];
                    dst[j] = transform((even + odd) * 0.25f, kind);
                }
            }
            /* channels-last: pixel by pixel, its channels in turn (contiguous); else channel by channel */
            const int64_t base = (int64_t)i * p_y + (int64_t)j0 * p_x;
            if (p_x == 1) {
                for (int c = 0; c < channels; ++c) {
                    const float *src = t + c * BLOCK;
                    if (pooled_bf16) {
                        uint16_t *out = (uint16_t *)pooled + base + c * p_c;
                        for (int j = 0; j < nj; ++j) out[j] = float_to_bf16(src[j]);
                    } else {
                        float *out = (float *)pooled + base + c * p_c;
                        for (int j = 0; j < nj; ++j) out[j] = src[j];
                    }
                }
            } else if (pooled_bf16) {
                uint16_t *out = (uint16_t *)pooled + base;
                for (int j = 0; j < nj; ++j)
                    for (int c = 0; c < channels; ++c) out[j * p_x + c * p_c] = float_to_bf16(t[c * BLOCK + j]);
            } else {
                float *out = (float *)pooled + base;
                for (int j = 0; j < nj; ++j)
                    for (int c = 0; c < channels; ++c) out[j * p_x + c * p_c] = t[c * BLOCK + j];
            }
        }
    }
}
