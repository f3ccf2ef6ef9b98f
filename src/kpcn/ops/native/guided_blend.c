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
 * four tap weights as full-resolution maps and a dozen passes over them; here a row's weights are made in a buffer
 * of four rows that stays in the cache, then every channel's row from them.
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
 * band rows r0 .. r0 + n. scratch: 2 * channels * (rows / 2) * (width / 2) floats (D f and coarse - D f), then
 * 4 * width floats for each thread (a row's tap weights). */
void guided_blend_rows(const float *f, int64_t f_c, int64_t f_y, int rows, int width, int channels,
                       const float *coarse, int64_t c_c, int64_t c_y,
                       const float *nf, int64_t nf_c, int64_t nf_y, const float *nc, int64_t nc_c, int64_t nc_y,
                       int g_channels, float sigma, const float *alpha, int64_t a_y, const float *beta, int64_t b_y,
                       int r0, int n, float *out, int64_t o_c, int64_t o_y, float *scratch, int threads) {
    const int hc = rows / 2, wc = width / 2;
    const int64_t plane = (int64_t)hc * wc;
    float *df = scratch, *corr = scratch + (int64_t)channels * plane, *wbuf = corr + (int64_t)channels * plane;
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
        int t = 0;
#ifdef _OPENMP
        t = omp_get_thread_num();
#endif
        float *wrow = wbuf + (int64_t)t * 4 * width;
        #pragma omp for schedule(static)
        for (int k = 0; k < n; ++k) {
            const int y = r0 + k, i = y / 2, ir = clampi(i + 2 * (y % 2) - 1, hc - 1);
            /* the row's four tap weights, output columns 2j (far column j - 1) and 2j + 1 (far column j + 1) */
            float *w0 = wrow, *w1 = wrow + width, *w2 = wrow + 2 * width, *w3 = wrow + 3 * width;
            for (int x = 0; x < width; ++x) {
                w0[x] = 0.0f; w1[x] = 0.0f; w2[x] = 0.0f; w3[x] = 0.0f;
            }
            for (int g = 0; g < g_channels; ++g) {
                const float *p = nf + g * nf_c + (int64_t)y * nf_y;
                const float *qi = nc + g * nc_c + (int64_t)i * nc_y, *qr = nc + g * nc_c + (int64_t)ir * nc_y;
                for (int x = 0; x < width; ++x) {
                    const int j = x >> 1, jf = clampi(j + 2 * (x & 1) - 1, wc - 1);
                    const float a = p[x] - qi[j], b = p[x] - qi[jf], c = p[x] - qr[j], d = p[x] - qr[jf];
                    w0[x] += a * a; w1[x] += b * b; w2[x] += c * c; w3[x] += d * d;
                }
            }
            for (int x = 0; x < width; ++x) {
                const float m01 = w0[x] < w1[x] ? w0[x] : w1[x], m23 = w2[x] < w3[x] ? w2[x] : w3[x];
                const float near = m01 < m23 ? m01 : m23;
                const float e0 = exp2_poly((w0[x] - near) * scale) * bw[0];
                const float e1 = exp2_poly((w1[x] - near) * scale) * bw[1];
                const float e2 = exp2_poly((w2[x] - near) * scale) * bw[2];
                const float e3 = exp2_poly((w3[x] - near) * scale) * bw[3];
                const float inv = 1.0f / (e0 + e1 + e2 + e3);
                w0[x] = e0 * inv; w1[x] = e1 * inv; w2[x] = e2 * inv; w3[x] = e3 * inv;
            }
            const float *ar = alpha + (int64_t)y * a_y, *br = beta + (int64_t)y * b_y;
            for (int c = 0; c < channels; ++c) {
                const float *di = df + c * plane + (int64_t)i * wc, *dr = df + c * plane + (int64_t)ir * wc;
                const float *ei = corr + c * plane + (int64_t)i * wc, *er = corr + c * plane + (int64_t)ir * wc;
                const float *fr = f + c * f_c + (int64_t)y * f_y;
                float *o = out + c * o_c + (int64_t)k * o_y;
                for (int x = 0; x < width; ++x) {
                    const int j = x >> 1, jf = clampi(j + 2 * (x & 1) - 1, wc - 1);
                    const float ud = w0[x] * di[j] + w1[x] * di[jf] + w2[x] * dr[j] + w3[x] * dr[jf];
                    const float uc = w0[x] * ei[j] + w1[x] * ei[jf] + w2[x] * er[j] + w3[x] * er[jf];
                    o[x] = (ud + br[x] * (fr[x] - ud)) + ar[x] * uc;
                }
            }
        }
    }
}
