/* The guided head's full-resolution channels for a band of rows (kpcn.ops.native; the U-Net's GuidedHead):
 *
 *   out[o, r, x] = bilinear_up2(low)[o, r + 2, x] + sum_g wg[o, g] * guide[g, r, x]
 *
 * low: the head's half-resolution product (bias added) over a band of half-resolution rows whose first and last
 * rows are only read, as context (kpcn.models.layers.upsample2 with context_rows): 2 * low_rows - 4 output rows.
 * Bilinear 2x upsampling as align_corners=False does it: output row 2i is 3/4 low[i] + 1/4 low[i - 1], row 2i + 1
 * is 3/4 low[i] + 1/4 low[i + 1], the same for columns, the edge columns repeated. guide: float32 or bfloat16
 * (guide_bf16), read as float32. The PyTorch path makes four interpolation passes over every channel, then a
 * matrix product; here each output row is made in the cache. Rows split between `threads` OpenMP threads.
 */
#include "kpcn_math.h"
#include "rows.h"
#ifdef _OPENMP
#include <omp.h>
#endif

void kpcn_upsample_guide_row(const float *low, int64_t l_c, int64_t l_y, int low_w,
                             const void *guide, int64_t g_c, int64_t g_y, int g_channels, int guide_bf16,
                             const float *wg, int channels, float *out, int64_t o_c, int64_t o_y, int r,
                             float *gbuf, float *vbuf) {
    const int width = 2 * low_w;
    const int u = r + 2;                      /* the row of the whole upsampled band */
    const int i = u / 2, n = (u % 2) ? i + 1 : i - 1;
    for (int g = 0; g < g_channels; ++g) {    /* the guide's row, as float32 */
        float *dst = gbuf + (int64_t)g * width;
        if (guide_bf16) {
            const uint16_t *src = (const uint16_t *)guide + g * g_c + (int64_t)r * g_y;
            for (int x = 0; x < width; ++x) dst[x] = bf16_to_float(src[x]);
        } else {
            const float *src = (const float *)guide + g * g_c + (int64_t)r * g_y;
            for (int x = 0; x < width; ++x) dst[x] = src[x];
        }
    }
    for (int o = 0; o < channels; ++o) {
        const float *a = low + o * l_c + (int64_t)i * l_y, *b = low + o * l_c + (int64_t)n * l_y;
        for (int j = 0; j < low_w; ++j) vbuf[j] = 0.75f * a[j] + 0.25f * b[j];
        float *dst = out + o * o_c + (int64_t)r * o_y;
        dst[0] = vbuf[0];
        for (int j = 0; j < low_w - 1; ++j) {  /* the columns between j and j + 1, as one interleaved store */
            dst[2 * j + 1] = 0.75f * vbuf[j] + 0.25f * vbuf[j + 1];
            dst[2 * j + 2] = 0.75f * vbuf[j + 1] + 0.25f * vbuf[j];
        }
        dst[width - 1] = vbuf[low_w - 1];
        for (int g = 0; g < g_channels; ++g) {
            const float wgt = wg[o * g_channels + g];
            const float *gr = gbuf + (int64_t)g * width;
            for (int x = 0; x < width; ++x) dst[x] += wgt * gr[x];
        }
    }
}

/* low: channel o of half-resolution row i at low[o * l_c + i * l_y + j], low_rows x low_w; guide: channel g of
 * output row r at guide[g * g_c + r * g_y + x]; wg: (channels, g_channels) row-major; out: (channels,
 * 2 low_rows - 4, 2 low_w). scratch: at least threads * (g_channels + 1) * 2 low_w floats. */
void upsample_guide_rows(const float *low, int64_t l_c, int64_t l_y, int low_rows, int low_w,
                         const void *guide, int64_t g_c, int64_t g_y, int g_channels, int guide_bf16,
                         const float *wg, int channels, float *out, int64_t o_c, int64_t o_y,
                         float *scratch, int threads) {
    const int rows = 2 * low_rows - 4;
    const int64_t per = (int64_t)(g_channels + 1) * 2 * low_w;
    #pragma omp parallel num_threads(threads)
    {
        int t = 0;
#ifdef _OPENMP
        t = omp_get_thread_num();
#endif
        float *gbuf = scratch + t * per, *vbuf = gbuf + (int64_t)g_channels * 2 * low_w;
        #pragma omp for schedule(static)
        for (int r = 0; r < rows; ++r)
            kpcn_upsample_guide_row(low, l_c, l_y, low_w, guide, g_c, g_y, g_channels, guide_bf16, wg, channels,
                                    out, o_c, o_y, r, gbuf, vbuf);
    }
}
