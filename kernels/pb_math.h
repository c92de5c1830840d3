/*
 * pb_math.h -- elementary functions of pbrdf.h: pb_sqrt, pb_exp, pb_log, pb_erfc, pb_hypot and
 * pb_sincos_pi4 (sin and cos for |y| <= pi/4, after pb_sincosd's exact degree
 * reduction).
 *
 * Included by pbrdf.h after it has defined real (scalar, or a vector with -DPB_VECTOR_REAL=N).
 *
 * float32 builds use the branch-free versions below by default (PB_FAST_MATH): pure arithmetic,
 * bit operations and ?: selects, so that they inline and vectorise (PoCL 3.0 calls its builtins
 * out of line, and evaluates erfc with scalar code).  -DPB_BUILTIN_MATH selects the OpenCL
 * builtins instead; float64 builds always use the builtins (float64 results must stay within
 * 1e-12 of the reference).  Max relative errors of the float32 versions against float64 at the
 * same float32 arguments (measured by tests/test_fastmath.py, which asserts the bounds in brackets):
 *   pb_exp         8.2e-8 [1.2e-7]  x in [-104, 89]; 0 below, +inf above; denormal results
 *                                   within one denormal step
 *   pb_log         8.2e-8 [1.0e-7]  every x > 0, denormals included; log(0) = -inf, NaN below 0
 *   pb_erfc        3.5e-7 [4.0e-7]  x in [0, 10.5] where erfc(x) >= FLT_MIN; 0 beyond 10.5;
 *                                   x >= 0 only
 *   pb_sincos_pi4  1.0e-7 [1.2e-7]  |y| <= pi/4 (pb_sincosd: 1.4e-7 [2e-7] for any degrees)
 *   pb_hypot       1.1e-7 [1.2e-7]  |x|, |y| in [1e-18, 1e18] (sqrt(x^2 + y^2): no rescaling)
 *   pb_sqrt: correctly rounded, both precisions
 * The polynomial coefficients are weighted minimax fits (Lawson) in float64, rounded to float32.
 * These rely on IEEE arithmetic as written: do not build with -cl-fast-relaxed-math or
 * -cl-unsafe-math-optimizations ((x + 2^23) - 2^23 is not x).
 */
#ifndef PB_MATH_H
#define PB_MATH_H

#if !defined(PBRDF_DOUBLE) && !defined(PB_BUILTIN_MATH)
#define PB_FAST_MATH 1
#endif

/* Integers of the width of real, for bit manipulation: int/long, or their vectors. */
#ifdef PB_VECTOR_REAL
typedef PB_CAT(PB_ISCALAR, PB_VECTOR_REAL) pb_bits;
#define PB_AS_BITS(x) PB_CAT(as_, PB_CAT(PB_ISCALAR, PB_VECTOR_REAL))(x)
#define PB_AS_REAL(x) PB_CAT(as_, PB_CAT(PB_SCALAR, PB_VECTOR_REAL))(x)
#else
typedef PB_ISCALAR pb_bits;
#define PB_AS_BITS(x) PB_CAT(as_, PB_ISCALAR)(x)
#define PB_AS_REAL(x) PB_CAT(as_, PB_SCALAR)(x)
#endif

#ifdef PBRDF_DOUBLE
#define PB_ROUND_MAGIC ((real)0x1.8p52)    /* (x + 1.5 2^52) - 1.5 2^52 = rint(x) for |x| < 2^51 */
#else
#define PB_ROUND_MAGIC ((real)0x1.8p23f)   /* (x + 1.5 2^23) - 1.5 2^23 = rint(x) for |x| < 2^22 */
#endif

/* sqrt, correctly rounded (as the builtin), inline: PoCL 3.0 calls its builtins out of line, and
 * such a call spills every live vector register; clang's __builtin_sqrt element by element
 * becomes one vector square-root instruction on x86-64 (not on SPIR: Oclgrind lacks llvm.sqrt). */
#if defined(__clang__) && defined(__x86_64__)
#ifdef PBRDF_DOUBLE
#define PB_SQRT1 __builtin_sqrt
#else
#define PB_SQRT1 __builtin_sqrtf
#endif
/* flat up to 8 elements: LLVM 14's SLP vectoriser turns nested pairs into 128-bit pieces */
#define PB_SQRT2(x) (PB_CAT(PB_SCALAR, 2))(PB_SQRT1((x).s0), PB_SQRT1((x).s1))
#define PB_SQRT4(x) (PB_CAT(PB_SCALAR, 4))(PB_SQRT1((x).s0), PB_SQRT1((x).s1), PB_SQRT1((x).s2), \
                                           PB_SQRT1((x).s3))
#define PB_SQRT8(x) (PB_CAT(PB_SCALAR, 8))(PB_SQRT1((x).s0), PB_SQRT1((x).s1), PB_SQRT1((x).s2), \
                                           PB_SQRT1((x).s3), PB_SQRT1((x).s4), PB_SQRT1((x).s5), \
                                           PB_SQRT1((x).s6), PB_SQRT1((x).s7))
#define PB_SQRT16(x) (PB_CAT(PB_SCALAR, 16))(PB_SQRT8((x).lo), PB_SQRT8((x).hi))
#ifdef PB_VECTOR_REAL
inline real pb_sqrt(real x) { return PB_CAT(PB_SQRT, PB_VECTOR_REAL)(x); }
#else
inline real pb_sqrt(real x) { return PB_SQRT1(x); }
#endif
#else
inline real pb_sqrt(real x) { return sqrt(x); }
#endif

#ifdef PB_FAST_MATH

/* exp(x): x = n ln2 + r, |r| <= ln2/2 (Cody-Waite, ln2 = 0.693359375 - 2.12194440e-4 with n ln2_hi
 * exact), exp(r) = 1 + r + r^2 P(r), times 2^n in two factors (normal for every n in range, so
 * denormal results round once; the clamps make exp(-inf) = 0 and exp(+inf) = +inf). */
inline real pb_exp(real x)
{
    x = x < -104.0f ? (real)-104.0f : x;  /* exp(-104) < 2^-150: rounds to 0 */
    x = x > 89.0f ? (real)89.0f : x;      /* exp(89) > FLT_MAX: +inf */
    const real t = x * 1.44269504f + PB_ROUND_MAGIC;  /* n = rint(x / ln2) in t's low bits */
    const real nf = t - PB_ROUND_MAGIC;
    const pb_bits n = PB_AS_BITS(t) - PB_AS_BITS(PB_ROUND_MAGIC);
    const real r = (x - nf * 0.693359375f) - nf * -2.12194440e-4f;
    const real p = (real)1 + (r + r * r * (0.49999994f + r * (0.16666521f + r * (0.04166839f
                   + r * (0.00836871f + r * 0.0013814613f)))));
    const pb_bits n1 = n >> 1;  /* n in [-150, 128]: both halves give normal powers of 2 */
    return p * PB_AS_REAL((n1 + 127) << 23) * PB_AS_REAL((n - n1 + 127) << 23);
}

/* log(x): x = 2^e m with m in [sqrt(1/2), sqrt(2)), f = m - 1, log(1 + f) = f - f^2/2 + f^3 P(f),
 * plus e ln2 (Cody-Waite split).  Denormals are scaled by 2^23 first; log(0) = -inf,
 * log(x < 0) = NaN, log(+inf) = +inf, NaN stays NaN. */
inline real pb_log(real x)
{
    const pb_bits sub = x < 0x1p-126f;
    const real xs = sub ? x * (real)0x1p23f : x;
    const pb_bits ix = PB_AS_BITS(xs) - 0x3f3504f3;      /* bits of sqrt(1/2) */
    const pb_bits e = (ix >> 23) - (sub ? (pb_bits)23 : (pb_bits)0);
    const real f = PB_AS_REAL((ix & 0x007fffff) + 0x3f3504f3) - (real)1;
    const real ef = PB_AS_REAL(e + PB_AS_BITS(PB_ROUND_MAGIC)) - PB_ROUND_MAGIC;  /* (real)e */
    const real z = f * f;
    const real y = f * z * (0.3333333f + f * (-0.2500082f + f * (0.20001227f + f * (-0.16623357f
                   + f * (0.14201757f + f * (-0.13160183f + f * (0.12761576f + f * -0.07634497f)))))));
    real r = ((y + ef * -2.12194440e-4f) - (real)0.5f * z + f) + ef * 0.693359375f;
    r = x < (real)INFINITY ? r : x;
    return x > (real)0 ? r : x == (real)0 ? (real)-INFINITY : (real)NAN;
}

/* erfc(x) for x >= 0 (the shadowing function's argument) = exp(-x^2) erfcx(x), with
 * (1 + 2x) erfcx(x) = 1 + P(q), q = (x - 2) / (x + 2) (the form of N. Juffa's erfcf, coefficients
 * refitted), and the rounding error t of x^2 corrected: exp(-x^2) = exp(-fl(x^2)) (1 - t).
 * exp(-x * x) is written as the callers write it, so that the compiler shares it with them. */
inline real pb_erfc(real x)
{
    const real d = (real)1 + (real)2 * x;
    const real rcp = (real)1 / ((x + (real)2) * d);
    const real q = (x - (real)2) * d * rcp;
    const real p = 0.2769784f + q * (-0.092764f + q * (-0.16603157f + q * (0.16405566f
                   + q * (-0.05420262f + q * (-0.008060887f + q * (0.008625355f + q * (0.0013125681f
                   + q * (-0.0012223385f + q * -0.0003961044f))))))));
    const real ex = ((real)1 + p) * ((x + (real)2) * rcp);  /* erfcx(x) */
    /* t = x^2 - fl(x^2), exactly, by splitting x into 12-bit halves (Dekker) */
    const real s = x * x;
    const real xh = PB_AS_REAL(PB_AS_BITS(x) & (pb_bits)0xfffff000);
    const real xl = x - xh;
    const real t = ((xh * xh - s) + (real)2 * xh * xl) + xl * xl;
    const real e = pb_exp(-x * x) * ex;
    const real r = e - e * t;
    return x > 10.5f ? (real)0 : r;  /* erfc(10.5) < 1e-49; also no inf - inf, no inf / inf */
}

/* sqrt(x^2 + y^2) (no rescaling: |x|, |y| must stay within about 1e-19 .. 1e19). */
inline real pb_hypot(real x, real y)
{
    return pb_sqrt(x * x + y * y);
}

/* sin(y), and cos(y) in *c, for |y| <= pi/4: y + y^3 S(y^2) and 1 - y^2/2 + y^4 C(y^2). */
inline real pb_sincos_pi4(real y, real *c)
{
    const real z = y * y;
    *c = (real)1 - (real)0.5f * z + z * z * (0.041666646f + z * (-0.0013887316f + z * 2.4433157e-05f));
    return y + y * z * (-0.16666655f + z * (0.00833216f + z * -0.00019515284f));
}

#else  /* the OpenCL builtins */

inline real pb_exp(real x) { return exp(x); }
inline real pb_log(real x) { return log(x); }
inline real pb_erfc(real x) { return erfc(x); }
inline real pb_hypot(real x, real y) { return hypot(x, y); }
inline real pb_sincos_pi4(real y, real *c) { return sincos(y, c); }

#endif  /* PB_FAST_MATH */

#endif  /* PB_MATH_H */
