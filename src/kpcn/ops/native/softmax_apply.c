/* Per-pixel softmax kernels applied in one pass (kpcn.ops.native).
 *
 * For every output pixel (y, x) of rows [y0, y1):
 *
 *   w_t   = exp(s tanh(z_t / s))                       t = 0 .. k*k - 1   (bounded logits, UNetConfig.logit_scale)
 *   out_c = sum_t w_t * img_c[y + i_t, x + j_t] / sum_t w_t              c = 0 .. channels - 1
 *
 * with img already padded by k // 2 on every side ("valid" application). The PyTorch path does the same in
 * about 2 k*k + 3 channels passes over memory (kpcn.models.kernel_heads._softmax_weights, then
 * kpcn.ops.kernel_apply_padded); here each pixel's weights live in a small block that stays in the L1 cache.
 * tanh is computed as 2 sigmoid(2u) - 1, exp as exp2, both with a polynomial 2^x (relative error < 1e-7)
 * that the compiler vectorises. The rows are split between `threads` OpenMP threads: built with -fopenmp, the
 * library links libgomp.so.1 by its soname, which in a process that has imported torch is torch's own runtime
 * (one thread pool: no second set of threads spinning beside torch's).
 */
#include "kpcn_math.h"
#include "rows.h"

#define BLOCK 64

/* One row y of the output (see softmax_apply_rows); z_y may be 0 (one row of logits for every y). */
void kpcn_softmax_apply_row(const float *z, int64_t z_c, int64_t z_y, int k, float s,
                            const float *img, int64_t i_c, int64_t i_y, int channels,
                            float *out, int64_t o_c, int64_t o_y, int y, int width) {
    const int taps = k * k;
    const float log2e = 1.4426950408889634f;
    const float in_scale = -2.0f * log2e / s;  /* sigmoid(2z/s) = 1 / (1 + 2^(in_scale z)) */
    const float a = 2.0f * s * log2e;          /* s tanh(z/s) log2(e) = a sigmoid(2z/s) - a/2 */
    const float half_a = 0.5f * a;
    float w[taps * BLOCK];
    float sum[BLOCK], inv[BLOCK], acc[BLOCK];
    for (int x0 = 0; x0 < width; x0 += BLOCK) {
        const int nx = width - x0 < BLOCK ? width - x0 : BLOCK;
        for (int x = 0; x < nx; ++x) sum[x] = 0.0f;
        for (int t = 0; t < taps; ++t) {
            const float *zt = z + t * z_c + (int64_t)y * z_y + x0;
            float *wt = w + t * BLOCK;
            for (int x = 0; x < nx; ++x) {
                float sig = 1.0f / (1.0f + exp2_poly(in_scale * zt[x]));
                float e = exp2_poly(a * sig - half_a);
                wt[x] = e;
                sum[x] += e;
            }
        }
        for (int x = 0; x < nx; ++x) inv[x] = 1.0f / sum[x];
        for (int c = 0; c < channels; ++c) {
            for (int x = 0; x < nx; ++x) acc[x] = 0.0f;
            for (int i = 0; i < k; ++i) {
                const float *row = img + c * i_c + (int64_t)(y + i) * i_y + x0;
                for (int j = 0; j < k; ++j) {
                    const float *wt = w + (i * k + j) * BLOCK;
                    const float *src = row + j;
                    for (int x = 0; x < nx; ++x) acc[x] += wt[x] * src[x];
                }
            }
            float *dst = out + c * o_c + (int64_t)y * o_y + x0;
            for (int x = 0; x < nx; ++x) dst[x] = acc[x] * inv[x];
        }
    }
}

/* z: logits, tap t of pixel (y, x) at z[t * z_c + y * z_y + x]; img: channel c of padded pixel (y, x) at
 * img[c * i_c + y * i_y + x]; out: out[c * o_c + y * o_y + x]; rows [0, height), `threads` threads.
 * s: the logits' bound (0 < s <= 80: 2^(s log2 e) stays finite). */
void softmax_apply_rows(const float *z, int64_t z_c, int64_t z_y, int k, float s,
                        const float *img, int64_t i_c, int64_t i_y, int channels,
                        float *out, int64_t o_c, int64_t o_y, int height, int width, int threads) {
    #pragma omp parallel for num_threads(threads) schedule(static)
    for (int y = 0; y < height; ++y)
        kpcn_softmax_apply_row(z, z_c, z_y, k, s, img, i_c, i_y, channels, out, o_c, o_y, y, width);
}
