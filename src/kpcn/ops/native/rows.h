/* Row functions shared between the native kernels' sources (kpcn.ops.native): each makes one output row. */
#ifndef KPCN_ROWS_H
#define KPCN_ROWS_H

#include <stdint.h>

/* upsample_guide.c: row r of bilinear_up2(low) + W_g guide for `channels` channels (see upsample_guide_rows). */
void kpcn_upsample_guide_row(const float *low, int64_t l_c, int64_t l_y, int low_w,
                             const void *guide, int64_t g_c, int64_t g_y, int g_channels, int guide_bf16,
                             const float *wg, int channels, float *out, int64_t o_c, int64_t o_y, int r,
                             float *gbuf, float *vbuf);

/* softmax_apply.c: row y of the bounded-softmax kernels z applied to the padded img (see softmax_apply_rows). */
void kpcn_softmax_apply_row(const float *z, int64_t z_c, int64_t z_y, int k, float s,
                            const float *img, int64_t i_c, int64_t i_y, int channels,
                            float *out, int64_t o_c, int64_t o_y, int y, int width);

#endif
