/* The guided head's kernel logits made and applied in one pass over a band of rows (kpcn.ops.native):
 *
 *   z_t[r, x] = bilinear_up2(low)[t, r + 2, x] + sum_g wg[t, g] * guide[g, r, x]       t = 0 .. k*k - 1
 *   out_c[r, x] = sum_t w_t img_c[r + i_t, x + j_t] / sum_t w_t,   w_t = exp(s tanh(z_t / s))
 *
 * what upsample_guide_rows followed by softmax_apply_rows over the k*k tap channels compute, to the last bit, without
 * the band's logits going to memory: each thread makes one row of them in its own buffer (k*k rows of the frame's
 * width: ~190 kB at 1920 columns, within the L2 cache) and applies it at once. The head's other channels (the
 * blend's weights, the albedo's logits) stay upsample_guide_rows' (kpcn.models.unet_rows).
 */
#include "rows.h"
#ifdef _OPENMP
#include <omp.h>
#endif

/* low, guide, wg: as upsample_guide_rows (low's channels and wg's rows: the k*k taps first); img: channel c of padded
 * row y at img[c * i_c + y * i_y + x], 2 low_rows - 4 + k - 1 rows of 2 low_w + k - 1 columns; out: (channels,
 * 2 low_rows - 4, 2 low_w). scratch: at least threads * (k*k + g_channels + 1) * 2 low_w floats. */
void guided_softmax_rows(const float *low, int64_t l_c, int64_t l_y, int low_rows, int low_w,
                         const void *guide, int64_t g_c, int64_t g_y, int g_channels, int guide_bf16,
                         const float *wg, int k, float s, const float *img, int64_t i_c, int64_t i_y, int channels,
                         float *out, int64_t o_c, int64_t o_y, float *scratch, int threads) {
    const int rows = 2 * low_rows - 4, width = 2 * low_w, taps = k * k;
    const int64_t per = (int64_t)(taps + g_channels + 1) * width;
    #pragma omp parallel num_threads(threads)
    {
        int t = 0;
#ifdef _OPENMP
        t = omp_get_thread_num();
#endif
        float *zbuf = scratch + t * per, *gbuf = zbuf + (int64_t)taps * width;
        float *vbuf = gbuf + (int64_t)g_channels * width;
        #pragma omp for schedule(static)
        for (int r = 0; r < rows; ++r) {
            /* the row's logits: tap t at zbuf[t * width + x] (o_y 0: every row writes the same buffer) */
            kpcn_upsample_guide_row(low, l_c, l_y, low_w, guide, g_c, g_y, g_channels, guide_bf16, wg, taps,
                                    zbuf, width, 0, r, gbuf, vbuf);
            kpcn_softmax_apply_row(zbuf, width, 0, k, s, img, i_c, i_y, channels, out, o_c, o_y, r, width);
        }
    }
}
