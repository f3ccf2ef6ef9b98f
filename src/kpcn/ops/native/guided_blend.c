/* The coarse-to-fine blend of a row band's full-resolution kernel level, with the normal-guided upsampling and the
 * high-band gain (kpcn.models.unet_rows.RowStream.rows; UNetConfig.edge_upsample and band_gain):
 *
 *   out = lerp(U(D f), f, beta) + alpha * U(coarse - D f)
 *
 * f: the level's filtered colour over the band's rows; D: the 2x2 average; coarse: the coarser levels' combined
 * result at half resolution; U: kpcn.models.guided's joint bilateral 2x upsampling, the four bilinear taps (9, 3, 3,
 * 1 sixteenths) each also weighted by exp(-|n_p - n_q|^2 / (2 sigma^2)) relative to the nearest tap and renormalised,
 * n_p the fine guide (the frame's normal) at the output pixel, n_q the half-resolution guide at the tap, the band's
 * half-resolution rows and columns repeated at its edges as the PyTorch path pads them. The PyTorch path makes the
 * four tap weights as full-resolution maps and a dozen passes over them; here each output pixel is made at once.
 * Rows split between `threads` OpenMP threads.
 */
#include "kpcn_math.h"
#ifdef _OPENMP
#include <omp.h>
#endif

static inline int clampi(int v, int hi) { return v < 0 ? 0 : (v > hi ? hi : v); }

/* f: channel c of band row y at f[c * f_c + y * f_y + x], rows x width (both even); coarse: (channels, rows / 2,
 * width / 2) at coarse[c * c_c + i * c_y + j]; nf: the fine guide (g_channels, rows, width); nc: the half-resolution
 * guide (g_channels, rows / 2, width / 2); alpha, beta: (rows, width) at [y * a_y + x]; out: (channels, n, width),
 * band rows r0 .. r0 + n. scratch: 2 * channels * (rows / 2) * (width / 2) floats (D f and coarse - D f). */
void guided_blend_rows(const float *f, int64_t f_c, int64_t f_y, int rows, int width, int channels,
                       const float *coarse, int64_t c_c, int64_t c_y,
                       const float *nf, int64_t nf_c, int64_t nf_y, const float *nc, int64_t nc_c, int64_t nc_y,
                       int g_channels, float sigma, const float *alpha, int64_t a_y, const float *beta, int64_t b_y,
                       int r0, int n, float *out, int64_t o_c, int64_t o_y, float *scratch, int threads) {
    const int hc = rows / 2, wc = width / 2;
    const int64_t plane = (int64_t)hc * wc;
    float *df = scratch, *corr = scratch + (int64_t)channels * plane;
    /* log2(e) / (2 sigma^2): the weights as powers of two (exp2_poly) */
    const float scale = -1.4426950408889634f * 0.5f / (sigma * sigma);
    const float bw[4] = {9.0f / 16.0f, 3.0f / 16.0f, 3.0f / 16.0f, 1.0f / 16.0f};
    #pragma omp parallel num_threads(threads)
    {
        #pragma omp for schedule(static)
        for (int i = 0; i < hc; ++i)
            for (int c = 0; c < channels; ++c) {
                const float *a = f + c * f_c + (int64_t)(2 * i) * f_y, *b = a + f_y;
                const float *q = coarse + c * c_c + (int64_t)i * c_y;
                float *d = df + c * plane + (int64_t)i * wc, *e = corr + c * plane + (int64_t)i * wc;
                for (int j = 0; j < wc; ++j) {
                    const float m = 0.25f * ((a[2 * j] + a[2 * j + 1]) + (b[2 * j] + b[2 * j + 1]));
                    d[j] = m;
                    e[j] = q[j] - m;
                }
            }
        #pragma omp for schedule(static)
        for (int k = 0; k < n; ++k) {
            const int y = r0 + k, i = y / 2, ir = clampi(i + 2 * (y % 2) - 1, hc - 1);
            const float *ar = alpha + (int64_t)y * a_y, *br = beta + (int64_t)y * b_y;
            for (int x = 0; x < width; ++x) {
                const int j = x / 2, jf = clampi(j + 2 * (x % 2) - 1, wc - 1);
                const int64_t tap[4] = {(int64_t)i * wc + j, (int64_t)i * wc + jf, (int64_t)ir * wc + j,
                                        (int64_t)ir * wc + jf};
                const int64_t ctap[4] = {(int64_t)i * nc_y + j, (int64_t)i * nc_y + jf, (int64_t)ir * nc_y + j,
                                         (int64_t)ir * nc_y + jf};
                float dist[4] = {0.0f, 0.0f, 0.0f, 0.0f};
                for (int g = 0; g < g_channels; ++g) {
                    const float p = nf[g * nf_c + (int64_t)y * nf_y + x];
                    const float *gq = nc + g * nc_c;
                    for (int t = 0; t < 4; ++t) {
                        const float dd = p - gq[ctap[t]];
                        dist[t] += dd * dd;
                    }
                }
                float near = dist[0];
                for (int t = 1; t < 4; ++t) near = dist[t] < near ? dist[t] : near;
                float w[4], total = 0.0f;
                for (int t = 0; t < 4; ++t) {
                    w[t] = exp2_poly((dist[t] - near) * scale) * bw[t];
                    total += w[t];
                }
                for (int t = 0; t < 4; ++t) w[t] /= total;
                const float al = ar[x], be = br[x];
                for (int c = 0; c < channels; ++c) {
                    const float *d = df + c * plane, *e = corr + c * plane;
                    const float ud = w[0] * d[tap[0]] + w[1] * d[tap[1]] + w[2] * d[tap[2]] + w[3] * d[tap[3]];
                    const float uc = w[0] * e[tap[0]] + w[1] * e[tap[1]] + w[2] * e[tap[2]] + w[3] * e[tap[3]];
                    const float fv = f[c * f_c + (int64_t)y * f_y + x];
                    out[c * o_c + (int64_t)k * o_y + x] = (ud + be * (fv - ud)) + al * uc;
                }
            }
        }
    }
}
