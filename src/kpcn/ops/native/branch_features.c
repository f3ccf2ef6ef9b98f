/* The diffuse/specular features of a band (kpcn.features.branch_features with variances, 27 channels a branch) in
 * two passes over its pixels instead of some sixty tensor ops:
 *
 *   1. per pixel: every layer made finite (NaN, +-Inf -> 0); each variance made >= 0 and clamped to the largest a
 *      pixel mean can have (its layer's mean squared, 1 for normals, times 1.01 plus 1e-6, at most 1e30; a
 *      one-channel variance against the brightest channel's bound), the clamped values counted; the albedo and
 *      depth clamped at 0, the depth divided by the frame's depth scale; the diffuse colour max(d, 0) / (a + EPS)
 *      and its variance mean_c(v_c / (a_c + EPS)^2); the specular log1p(max(s, 0)) and mean_c(v_c / (1 + s_c)^2);
 *      the normal, albedo and depth variances' channel means (the depth's over the scale squared);
 *   2. forward differences in x and y (0 on the band's last column and row) of each branch's colour and of the
 *      normal, albedo and depth, into channels 4-13 and 14-23.
 *
 * Layers are read at any strides (views of a frame's (H, W, C) arrays); a layer of one channel stands for three.
 * Outputs: the branches' features (27, h, w) and the albedo (3, h, w), contiguous; tmp: 4 planes of h x w floats;
 * rows: threads x 31 rows of width floats. Rows split between `threads` OpenMP threads (torch's pool).
 */
#include "kpcn_math.h"
#ifdef _OPENMP
#include <omp.h>
#endif

#define N_LAYERS 10
#define EPS_ALBEDO 0.00316f
#define VARIANCE_MAX 1e30f

/* layer order in `layers` */
enum { DIFFUSE, SPECULAR, ALBEDO, NORMAL, DEPTH, DIFFUSE_VAR, SPECULAR_VAR, ALBEDO_VAR, NORMAL_VAR, DEPTH_VAR };

typedef struct {
    const float *p;
    int64_t c, y, x;
    int channels;
} layer_t;

static inline float finite(float v) {
    uint32_t b;
    memcpy(&b, &v, sizeof b);
    return (b & 0x7f800000u) == 0x7f800000u ? 0.0f : v;  /* NaN and +-Inf -> 0 */
}

/* Channel c of row y of a layer (channel 0 of a one-channel layer), finite, into dst (strides 1 and 3 vectorised). */
static void read_row(const layer_t *l, int c, int y, int n, float *restrict dst) {
    const float *restrict src = l->p + (c < l->channels ? c : 0) * l->c + (int64_t)y * l->y;
    if (l->x == 1) {
        for (int x = 0; x < n; ++x) dst[x] = finite(src[x]);
    } else if (l->x == 3) {
        for (int x = 0; x < n; ++x) dst[x] = finite(src[3 * x]);
    } else {
        for (int x = 0; x < n; ++x) dst[x] = finite(src[(int64_t)x * l->x]);
    }
}

static inline float bound_of(float m, int unit) {
    float m2 = m * m;
    if (unit && m2 < 1.0f) m2 = 1.0f;
    const float b = m2 * 1.01f + 1e-6f;
    return b < VARIANCE_MAX ? b : VARIANCE_MAX;
}

/* A variance row (channels of `var`, 1 or 3) made >= 0 and clamped to its mean's bound (mean: `mean_channels`
 * rows; a one-channel variance against the brightest channel's bound), in place; returns the values clamped. */
static int64_t bound_rows(float *const var[3], int var_channels, float *const mean[3], int mean_channels,
                          int unit, int n, float *restrict bound) {
    for (int x = 0; x < n; ++x) bound[x] = 0.0f;
    int64_t clamped = 0;
    for (int c = 0; c < var_channels; ++c) {
        const float *restrict m = mean[var_channels == 1 ? 0 : c];
        if (var_channels == 1 && mean_channels > 1) {
            for (int x = 0; x < n; ++x) {
                float b = bound_of(mean[0][x], unit);
                for (int k = 1; k < mean_channels; ++k) {
                    const float bk = bound_of(mean[k][x], unit);
                    b = bk > b ? bk : b;
                }
                bound[x] = b;
            }
        } else {
            for (int x = 0; x < n; ++x) bound[x] = bound_of(m[x], unit);
        }
        float *restrict v = var[c];
        for (int x = 0; x < n; ++x) {
            float s = v[x] > 0.0f ? v[x] : 0.0f;
            clamped += s > bound[x];
            v[x] = s < bound[x] ? s : bound[x];
        }
    }
    return clamped;
}

void branch_features_rows(const float *const ptrs[N_LAYERS], const int64_t strides[N_LAYERS][3],
                          const int channels[N_LAYERS], int height, int width, float depth_scale, int want_diffuse,
                          int want_specular, float *diffuse_out, float *specular_out, float *albedo_out, float *tmp,
                          float *rows, int64_t clamped[5], int threads) {
    layer_t l[N_LAYERS];
    for (int i = 0; i < N_LAYERS; ++i)
        l[i] = (layer_t){ptrs[i], strides[i][0], strides[i][1], strides[i][2], channels[i]};
    const int64_t plane = (int64_t)height * width;
    float *normal = tmp, *depth = tmp + 3 * plane;  /* the normal and depth as planes, for their differences */
    float *outs[2] = {want_diffuse ? diffuse_out : NULL, want_specular ? specular_out : NULL};
    const float scale2 = depth_scale * depth_scale;
    int64_t c_dv = 0, c_sv = 0, c_av = 0, c_nv = 0, c_zv = 0;
    #pragma omp parallel num_threads(threads)
    {
        int t = 0;
#ifdef _OPENMP
        t = omp_get_thread_num();
#endif
        /* this thread's rows: 3 channels of each layer, and one for the bounds */
        float *buf = rows + (int64_t)t * (3 * N_LAYERS + 1) * width;
        float *r[N_LAYERS][3];
        for (int i = 0; i < N_LAYERS; ++i)
            for (int c = 0; c < 3; ++c) r[i][c] = buf + (int64_t)(3 * i + c) * width;
        float *bound = buf + (int64_t)3 * N_LAYERS * width;
        #pragma omp for schedule(static) reduction(+ : c_dv, c_sv, c_av, c_nv, c_zv)
        for (int y = 0; y < height; ++y) {  /* 1. per pixel */
            const int64_t row = (int64_t)y * width;
            for (int i = 0; i < N_LAYERS; ++i) {
                if ((i == DIFFUSE || i == DIFFUSE_VAR) && !outs[0]) continue;
                if ((i == SPECULAR || i == SPECULAR_VAR) && !outs[1]) continue;
                const int nc = i == DEPTH || i == DEPTH_VAR ? 1 : (i >= DIFFUSE_VAR ? l[i].channels : 3);
                for (int c = 0; c < nc; ++c) read_row(&l[i], c, y, width, r[i][c]);
            }
            /* the variances bounded by their layers' means, before the layers are clamped */
            c_nv += bound_rows(r[NORMAL_VAR], l[NORMAL_VAR].channels, r[NORMAL], 3, 1, width, bound);
            c_av += bound_rows(r[ALBEDO_VAR], l[ALBEDO_VAR].channels, r[ALBEDO], 3, 0, width, bound);
            c_zv += bound_rows(r[DEPTH_VAR], 1, r[DEPTH], 1, 0, width, bound);
            if (outs[0]) c_dv += bound_rows(r[DIFFUSE_VAR], l[DIFFUSE_VAR].channels, r[DIFFUSE], 3, 0, width, bound);
            if (outs[1]) c_sv += bound_rows(r[SPECULAR_VAR], l[SPECULAR_VAR].channels, r[SPECULAR], 3, 0, width, bound);
            const int nv_c = l[NORMAL_VAR].channels, av_c = l[ALBEDO_VAR].channels;
            for (int c = 0; c < 3; ++c) {
                const float *restrict a = r[ALBEDO][c], *restrict nr = r[NORMAL][c];
                float *restrict ao = albedo_out + c * plane + row, *restrict no = normal + c * plane + row;
                for (int x = 0; x < width; ++x) {
                    ao[x] = a[x] > 0.0f ? a[x] : 0.0f;
                    no[x] = nr[x];
                }
            }
            {
                const float *restrict z = r[DEPTH][0];
                float *restrict zo = depth + row;
                for (int x = 0; x < width; ++x) zo[x] = (z[x] > 0.0f ? z[x] : 0.0f) / depth_scale;
            }
            for (int b = 0; b < 2; ++b) {
                float *o = outs[b];
                if (!o) continue;
                const int layer = b ? SPECULAR : DIFFUSE, var = b ? SPECULAR_VAR : DIFFUSE_VAR;
                const int vc = l[var].channels;
                float *restrict cv = o + 3 * plane + row;
                for (int x = 0; x < width; ++x) cv[x] = 0.0f;
                for (int c = 0; c < 3; ++c) {
                    const float *restrict s = r[layer][c], *restrict v = r[var][vc == 1 ? 0 : c];
                    const float *restrict a = albedo_out + c * plane + row;
                    float *restrict co = o + c * plane + row;
                    if (b) {
                        for (int x = 0; x < width; ++x) {
                            const float raw = s[x] > 0.0f ? s[x] : 0.0f;
                            co[x] = log1p_poly(raw);
                            cv[x] += v[x] / ((1.0f + raw) * (1.0f + raw));
                        }
                    } else {
                        for (int x = 0; x < width; ++x) {
                            const float raw = s[x] > 0.0f ? s[x] : 0.0f, ae = a[x] + EPS_ALBEDO;
                            co[x] = raw / ae;
                            cv[x] += v[x] / (ae * ae);
                        }
                    }
                }
                float *restrict nvo = o + 24 * plane + row, *restrict avo = o + 25 * plane + row;
                float *restrict zvo = o + 26 * plane + row;
                for (int x = 0; x < width; ++x) {
                    cv[x] /= 3.0f;
                    nvo[x] = (r[NORMAL_VAR][0][x] + r[NORMAL_VAR][nv_c == 1 ? 0 : 1][x]
                              + r[NORMAL_VAR][nv_c == 1 ? 0 : 2][x]) / 3.0f;
                    avo[x] = (r[ALBEDO_VAR][0][x] + r[ALBEDO_VAR][av_c == 1 ? 0 : 1][x]
                              + r[ALBEDO_VAR][av_c == 1 ? 0 : 2][x]) / 3.0f;
                    const float zv = r[DEPTH_VAR][0][x];
                    zvo[x] = ((zv + zv) + zv) / 3.0f / scale2;  /* the mean of the three channels it stands for */
                }
            }
        }
        #pragma omp for schedule(static)
        for (int y = 0; y < height; ++y) {  /* 2. forward differences: colour, normal, albedo, depth */
            for (int b = 0; b < 2; ++b) {
                float *o = outs[b];
                if (!o) continue;
                const float *src[10] = {o, o + plane, o + 2 * plane, normal, normal + plane, normal + 2 * plane,
                                        albedo_out, albedo_out + plane, albedo_out + 2 * plane, depth};
                for (int k = 0; k < 10; ++k) {
                    const float *restrict s = src[k] + (int64_t)y * width;
                    float *restrict gx = o + (4 + k) * plane + (int64_t)y * width;
                    float *restrict gy = o + (14 + k) * plane + (int64_t)y * width;
                    for (int x = 0; x < width - 1; ++x) gx[x] = s[x + 1] - s[x];
                    gx[width - 1] = 0.0f;
                    if (y + 1 < height) {
                        const float *restrict below = s + width;
                        for (int x = 0; x < width; ++x) gy[x] = below[x] - s[x];
                    } else {
                        for (int x = 0; x < width; ++x) gy[x] = 0.0f;
                    }
                }
            }
        }
    }
    clamped[0] = c_dv, clamped[1] = c_sv, clamped[2] = c_av, clamped[3] = c_nv, clamped[4] = c_zv;
}
