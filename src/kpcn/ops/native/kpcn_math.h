/* Vectorisable float32 functions shared by the native kernels (kpcn.ops.native): polynomials fitted for kpcn
 * (least squares on Chebyshev nodes, relative error below 1e-7), no library calls, so the compiler vectorises
 * the loops that call them. */
#ifndef KPCN_MATH_H
#define KPCN_MATH_H

#include <stdint.h>
#include <string.h>

/* 2^v, v clamped to [-126, 126]: 2^floor(v) from the exponent bits times a polynomial of the fraction. */
static inline float exp2_poly(float v) {
    v = v < -126.0f ? -126.0f : (v > 126.0f ? 126.0f : v);
    float n = __builtin_floorf(v);
    float f = v - n;  /* [0, 1) */
    float p = 0.0018762329f;
    p = p * f + 0.0089925844f;
    p = p * f + 0.0558236055f;
    p = p * f + 0.2401545346f;
    p = p * f + 0.6931529641f;
    p = p * f + 0.9999999404f;
    int32_t bits = ((int32_t)n + 127) << 23;
    float scale;
    memcpy(&scale, &bits, sizeof scale);
    return p * scale;
}

/* log1p(u) for u >= 0: u <= sqrt(2) - 1 directly, else log(m 2^e) of v = 1 + u with m in [sqrt(1/2), sqrt(2));
 * log1p(t) = t - t^2/2 + t^3 P(t) on [sqrt(1/2) - 1, sqrt(2) - 1]. */
static inline float log1p_poly(float u) {
    float v = 1.0f + u;
    uint32_t bits;
    memcpy(&bits, &v, sizeof bits);
    int e = (int)((bits >> 23) & 0xff) - 127;
    bits = (bits & 0x007fffffu) | 0x3f800000u;
    float m;
    memcpy(&m, &bits, sizeof m);
    const int big = m > 1.41421356f;
    m = big ? 0.5f * m : m;
    e += big;
    const int direct = u <= 0.41421356f;
    const float t = direct ? u : m - 1.0f;
    float p = -0.07660818845f;
    p = p * t + 0.12786330283f;
    p = p * t - 0.13161605597f;
    p = p * t + 0.14197877049f;
    p = p * t - 0.16622751951f;
    p = p * t + 0.20001412928f;
    p = p * t - 0.25000846386f;
    p = p * t + 0.33333328366f;
    const float lt = t - 0.5f * t * t + t * t * t * p;
    const float ef = direct ? 0.0f : (float)e;
    return ef * 0.693145751953125f + (ef * 1.428606765330187e-06f + lt);  /* ln 2 = hi + lo */
}

/* expm1(x): |x| < ln(sqrt 2) as x + x^2/2 + x^3 P(x) (no cancellation near 0), else 2^(x log2 e) - 1. */
static inline float expm1_poly(float x) {
    float p = 0.00019905211f;
    p = p * x + 0.00139336509f;
    p = p * x + 0.00833328813f;
    p = p * x + 0.04166647792f;
    p = p * x + 0.16666667163f;
    const float small = x + 0.5f * x * x + x * x * x * p;
    const float large = exp2_poly(x * 1.4426950408889634f) - 1.0f;
    const float a = x < 0.0f ? -x : x;
    return a < 0.34657359f ? small : large;
}

/* float32 -> bfloat16 bits, rounded to nearest even (as torch rounds; finite inputs). */
static inline uint16_t float_to_bf16(float f) {
    uint32_t b;
    memcpy(&b, &f, sizeof b);
    b += 0x7fffu + ((b >> 16) & 1u);
    return (uint16_t)(b >> 16);
}

static inline float bf16_to_float(uint16_t v) {
    uint32_t bits = (uint32_t)v << 16;
    float f;
    memcpy(&f, &bits, sizeof f);
    return f;
}

#endif
