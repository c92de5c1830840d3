/*
 * pb_math.h -- elementary functions of pbrdf.h: pb_sqrt, pb_exp, pb_log, pb_erfc, pb_hypot and
 * pb_sincos_pi4 (sin and cos for |y| <= pi/4, after pb_sincosd's exact degree
 * reduction).
 *
 * Included by pbrdf.h after it has defined real (scalar, or a vector with -DPB_VECTOR_REAL=N).
 *
 * Both precisions use the branch-free versions below by default (PB_FAST_MATH): pure arithmetic,
 * bit operations and ?: selects, so that they inline and vectorise (PoCL 3.0 calls its builtins
 * out of line, spilling every vector register, and evaluates erfc with scalar code: float64
 * evaluation ran at half the speed it does with these).  -DPB_BUILTIN_MATH selects the OpenCL
 * builtins instead.  Max relative errors against float64 (float32 versions, at the same float32
 * arguments) or against numpy/scipy (float64 versions), measured by tests/test_fastmath.py, which
 * asserts the bounds in brackets:
 *   pb_exp         f32 8.2e-8 [1.2e-7]  x in [-104, 89]; 0 below, +inf above; denormal results
 *                                       within one denormal step
 *                  f64 2.2e-16 [3e-16]  x in [-746, 710], likewise
 *   pb_log         f32 8.2e-8 [1.0e-7]  every x > 0, denormals included; log(0) = -inf, NaN below 0
 *                  f64 2.2e-16 [3e-16]  likewise
 *   pb_erfc        f32 3.5e-7 [4.0e-7]  x in [0, 10.5] where erfc(x) >= FLT_MIN; 0 beyond 10.5;
 *                                       x >= 0 only
 *                  f64 1.1e-15 [1.5e-15] x in [0, 26] (against 40-digit values: 4.4e-16); 0 beyond 27
 *   pb_sincos_pi4  f32 1.0e-7 [1.2e-7]  |y| <= pi/4 (pb_sincosd: 1.4e-7 [2e-7] for any degrees)
 *                  f64 2.2e-16 [3e-16]  (pb_sincosd: [4e-16])
 *   pb_hypot       f32 1.1e-7 [1.2e-7]  |x|, |y| in [1e-18, 1e18] (sqrt(x^2 + y^2): no rescaling)
 *                  f64 2.2e-16 [3e-16]  |x|, |y| in [1e-150, 1e150]
 *   pb_sqrt: correctly rounded, both precisions
 *   pb_exp_normal, pb_log_normal: pb_exp and pb_log bit for bit where their results are normal
 *                  (exp: x in [-87, 88] in float32, [-708, 709] in float64; log: normal x > 0),
 *                  without the clamps and special cases (tests/test_fastmath.py checks the bits)
 * The float32 polynomial coefficients are weighted minimax fits (Lawson) in float64, rounded to
 * float32; float64 uses Taylor series (exp, sincos), FDLIBM's log polynomial and a Chebyshev
 * series for erfc.
 * These rely on IEEE arithmetic as written: do not build with -cl-fast-relaxed-math or
 * -cl-unsafe-math-optimizations ((x + 2^23) - 2^23 is not x).
 */
#ifndef PB_MATH_H
#define PB_MATH_H

#if !defined(PB_BUILTIN_MATH)
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

#if defined(PB_FAST_MATH) && defined(PBRDF_DOUBLE)

/* float64: exp(x): x = n ln2 + r, |r| <= ln2/2 (Cody-Waite: ln2_hi has 21 trailing zero bits, so
 * n ln2_hi is exact), exp(r) = 1 + r + r^2 P(r) with P the Taylor series to r^11 (truncation
 * below 1e-17 relative), times 2^n in two factors (normal for every n in range). */
inline real pb_exp_reduced(real x, pb_bits *pn)
{
    const real t = x * 1.4426950408889634 + PB_ROUND_MAGIC;  /* n = rint(x / ln2) in t's low bits */
    const real nf = t - PB_ROUND_MAGIC;
    const pb_bits n = PB_AS_BITS(t) - PB_AS_BITS(PB_ROUND_MAGIC);
    *pn = n;
    const real r = (x - nf * 6.93147180369123816490e-01) - nf * 1.90821492927058770002e-10;
    const real P = 0.5 + r * (1.6666666666666666e-01 + r * (4.1666666666666664e-02 + r * (8.3333333333333332e-03
                   + r * (1.3888888888888889e-03 + r * (1.9841269841269841e-04 + r * (2.4801587301587302e-05
                   + r * (2.7557319223985893e-06 + r * (2.7557319223985888e-07 + r * (2.5052108385441720e-08
                   + r * (2.0876756987868100e-09 + r * 1.6059043836821613e-10))))))))));
    return (real)1 + (r + r * r * P);
}

inline real pb_exp(real x)
{
    x = x < -746.0 ? (real)-746.0 : x;  /* exp(-746) < 2^-1075: rounds to 0 */
    x = x > 710.0 ? (real)710.0 : x;    /* exp(710) > DBL_MAX: +inf */
    pb_bits n;
    const real p = pb_exp_reduced(x, &n);
    const pb_bits n1 = n >> 1;  /* n in [-1077, 1025]: both halves give normal powers of 2 */
    return p * PB_AS_REAL((n1 + 1023) << 52) * PB_AS_REAL((n - n1 + 1023) << 52);
}

/* pb_exp(x) for x in [-708, 709] (normal results: 2^n is one normal power of 2), bit for bit,
 * without the clamps and the second factor. */
inline real pb_exp_normal(real x)
{
    pb_bits n;
    const real p = pb_exp_reduced(x, &n);
    return p * PB_AS_REAL((n + 1023) << 52);
}

/* float64: log(x): x = 2^e m with m in [sqrt(1/2), sqrt(2)), f = m - 1, s = f / (2 + f),
 * log(1 + f) = f - f^2/2 + s (f^2/2 + R(s^2)) with R the minimax polynomial of FDLIBM's e_log.c
 * (error below 1 ulp), plus e ln2 (Cody-Waite split).  Denormals are scaled by 2^54 first;
 * log(0) = -inf, log(x < 0) = NaN, log(+inf) = +inf, NaN stays NaN. */
inline real pb_log_scaled(real xs, pb_bits e_sub)  /* log(xs 2^-e_sub), xs normal, > 0, finite */
{
    const pb_bits ix = PB_AS_BITS(xs) - (pb_bits)0x3fe6a09e667f3bcdL;  /* bits of sqrt(1/2) */
    const pb_bits e = (ix >> 52) - e_sub;
    const real f = PB_AS_REAL((ix & (pb_bits)0x000fffffffffffffL) + (pb_bits)0x3fe6a09e667f3bcdL) - (real)1;
    const real ef = PB_AS_REAL(e + PB_AS_BITS(PB_ROUND_MAGIC)) - PB_ROUND_MAGIC;  /* (real)e */
    const real s = f / ((real)2 + f);
    const real z = s * s, w = z * z;
    const real R = z * (6.666666666666735130e-01 + w * (2.857142874366239149e-01 + w * (1.818357216161805012e-01
                   + w * 1.479819860511658591e-01)))
                   + w * (3.999999999940941908e-01 + w * (2.222219843214978396e-01 + w * 1.531383769920937332e-01));
    const real hfsq = (real)0.5 * f * f;
    return ef * 6.93147180369123816490e-01 - ((hfsq - (s * (hfsq + R) + ef * 1.90821492927058770002e-10)) - f);
}

inline real pb_log(real x)
{
    const pb_bits sub = x < 0x1p-1022;
    const real xs = sub ? x * (real)0x1p54 : x;
    real r = pb_log_scaled(xs, sub ? (pb_bits)54 : (pb_bits)0);
    r = x < (real)INFINITY ? r : x;
    return x > (real)0 ? r : x == (real)0 ? (real)-INFINITY : (real)NAN;
}

/* float64: P(q) of pb_erfc, a Chebyshev series of degree 26 in q mapped from [-1, 25/29] (x in
 * [0, 27]) onto [-1, 1], evaluated by Clenshaw's recurrence (coefficients from 40-digit erfc
 * values at 2000 Chebyshev nodes; truncation 1e-16).  x is split into 26-bit halves; erfc is 0
 * beyond x = 27 (erfc(27) < 1e-318). */
#define PB_ERFC_SPLIT ((pb_bits)0xfffffffff8000000L)
#define PB_ERFC_ZERO ((real)27)
#define PB_CLENSHAW(c) { const real b0 = u2 * b1 - b2 + (real)(c); b2 = b1; b1 = b0; }
inline real pb_erfc_series(real q)
{
    const real u = q * 1.0740740740740742 + 0.07407407407407411;
    const real u2 = (real)2 * u;
    real b2 = (real)0, b1 = (real)-1.015271658266677e-18;
    PB_CLENSHAW(-6.256175477884e-17);
    PB_CLENSHAW(-2.3391884723788363e-16);
    PB_CLENSHAW(2.5158594605268048e-20);
    PB_CLENSHAW(3.670374942366494e-15);
    PB_CLENSHAW(1.4538457400804143e-14);
    PB_CLENSHAW(-3.249984758271317e-15);
    PB_CLENSHAW(-2.5583434136028265e-13);
    PB_CLENSHAW(-9.093478766010714e-13);
    PB_CLENSHAW(1.1500490764983634e-12);
    PB_CLENSHAW(2.062635527456776e-11);
    PB_CLENSHAW(5.062186591581214e-11);
    PB_CLENSHAW(-2.2760610317834061e-10);
    PB_CLENSHAW(-1.7489408085673871e-09);
    PB_CLENSHAW(-6.173785623864705e-10);
    PB_CLENSHAW(3.6241640662636236e-08);
    PB_CLENSHAW(1.0872974541345352e-07);
    PB_CLENSHAW(-6.205050348889623e-07);
    PB_CLENSHAW(-3.9651852960545826e-06);
    PB_CLENSHAW(1.1385394763548858e-05);
    PB_CLENSHAW(0.00012585620959943607);
    PB_CLENSHAW(-0.00040284209186637544);
    PB_CLENSHAW(-0.003935557574655554);
    PB_CLENSHAW(0.03383415117427362);
    PB_CLENSHAW(-0.10426944550821916);
    PB_CLENSHAW(0.040802111220209554);
    return u * b1 - b2 + (real)0.18232722389066927;
}
#undef PB_CLENSHAW

/* float64: sin(y), and cos(y) in *c, for |y| <= pi/4: the Taylor series to y^15 and y^16
 * (truncation below 5e-17 relative). */
inline real pb_sincos_pi4(real y, real *c)
{
    const real z = y * y;
    *c = (real)1 - (real)0.5 * z + z * z * (4.1666666666666664e-02 + z * (-1.3888888888888889e-03
         + z * (2.4801587301587302e-05 + z * (-2.7557319223985888e-07 + z * (2.0876756987868100e-09
         + z * (-1.1470745597729725e-11 + z * 4.7794773323873853e-14))))));
    return y + y * z * (-1.6666666666666666e-01 + z * (8.3333333333333332e-03 + z * (-1.9841269841269841e-04
           + z * (2.7557319223985893e-06 + z * (-2.5052108385441720e-08 + z * (1.6059043836821613e-10
           + z * -7.6471637318198164e-13))))));
}

#elif defined(PB_FAST_MATH)

/* exp(x): x = n ln2 + r, |r| <= ln2/2 (Cody-Waite, ln2 = 0.693359375 - 2.12194440e-4 with n ln2_hi
 * exact), exp(r) = 1 + r + r^2 P(r), times 2^n in two factors (normal for every n in range, so
 * denormal results round once; the clamps make exp(-inf) = 0 and exp(+inf) = +inf). */
inline real pb_exp_reduced(real x, pb_bits *pn)
{
    const real t = x * 1.44269504f + PB_ROUND_MAGIC;  /* n = rint(x / ln2) in t's low bits */
    const real nf = t - PB_ROUND_MAGIC;
    const pb_bits n = PB_AS_BITS(t) - PB_AS_BITS(PB_ROUND_MAGIC);
    *pn = n;
    const real r = (x - nf * 0.693359375f) - nf * -2.12194440e-4f;
    return (real)1 + (r + r * r * (0.49999994f + r * (0.16666521f + r * (0.04166839f
           + r * (0.00836871f + r * 0.0013814613f)))));
}

inline real pb_exp(real x)
{
    x = x < -104.0f ? (real)-104.0f : x;  /* exp(-104) < 2^-150: rounds to 0 */
    x = x > 89.0f ? (real)89.0f : x;      /* exp(89) > FLT_MAX: +inf */
    pb_bits n;
    const real p = pb_exp_reduced(x, &n);
    const pb_bits n1 = n >> 1;  /* n in [-150, 128]: both halves give normal powers of 2 */
    return p * PB_AS_REAL((n1 + 127) << 23) * PB_AS_REAL((n - n1 + 127) << 23);
}

/* pb_exp(x) for x in [-87, 88] (normal results: 2^n is one normal power of 2), bit for bit,
 * without the clamps and the second factor. */
inline real pb_exp_normal(real x)
{
    pb_bits n;
    const real p = pb_exp_reduced(x, &n);
    return p * PB_AS_REAL((n + 127) << 23);
}

/* log(x): x = 2^e m with m in [sqrt(1/2), sqrt(2)), f = m - 1, log(1 + f) = f - f^2/2 + f^3 P(f),
 * plus e ln2 (Cody-Waite split).  Denormals are scaled by 2^23 first; log(0) = -inf,
 * log(x < 0) = NaN, log(+inf) = +inf, NaN stays NaN. */
inline real pb_log_scaled(real xs, pb_bits e_sub)  /* log(xs 2^-e_sub), xs normal, > 0, finite */
{
    const pb_bits ix = PB_AS_BITS(xs) - 0x3f3504f3;      /* bits of sqrt(1/2) */
    const pb_bits e = (ix >> 23) - e_sub;
    const real f = PB_AS_REAL((ix & 0x007fffff) + 0x3f3504f3) - (real)1;
    const real ef = PB_AS_REAL(e + PB_AS_BITS(PB_ROUND_MAGIC)) - PB_ROUND_MAGIC;  /* (real)e */
    const real z = f * f;
    const real y = f * z * (0.3333333f + f * (-0.2500082f + f * (0.20001227f + f * (-0.16623357f
                   + f * (0.14201757f + f * (-0.13160183f + f * (0.12761576f + f * -0.07634497f)))))));
    return ((y + ef * -2.12194440e-4f) - (real)0.5f * z + f) + ef * 0.693359375f;
}

inline real pb_log(real x)
{
    const pb_bits sub = x < 0x1p-126f;
    const real xs = sub ? x * (real)0x1p23f : x;
    real r = pb_log_scaled(xs, sub ? (pb_bits)23 : (pb_bits)0);
    r = x < (real)INFINITY ? r : x;
    return x > (real)0 ? r : x == (real)0 ? (real)-INFINITY : (real)NAN;
}

/* float32: P(q) of pb_erfc (the form of N. Juffa's erfcf, coefficients refitted).  x is split
 * into 12-bit halves; erfc is 0 beyond x = 10.5 (erfc(10.5) < 1e-49; also no inf - inf, no
 * inf / inf). */
#define PB_ERFC_SPLIT ((pb_bits)0xfffff000)
#define PB_ERFC_ZERO 10.5f
inline real pb_erfc_series(real q)
{
    return 0.2769784f + q * (-0.092764f + q * (-0.16603157f + q * (0.16405566f
           + q * (-0.05420262f + q * (-0.008060887f + q * (0.008625355f + q * (0.0013125681f
           + q * (-0.0012223385f + q * -0.0003961044f))))))));
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
inline real pb_erfc_e(real x, real e) { return erfc(x); }
inline real pb_exp_normal(real x) { return exp(x); }
inline real pb_log_normal(real x) { return log(x); }
inline real pb_hypot(real x, real y) { return hypot(x, y); }
inline real pb_sincos_pi4(real y, real *c) { return sincos(y, c); }

#endif  /* PB_FAST_MATH */

#ifdef PB_FAST_MATH
/* pb_log(x) for normal finite x > 0, bit for bit, without the scaling of denormals and the special
 * cases. */
inline real pb_log_normal(real x)
{
    return pb_log_scaled(x, (pb_bits)0);
}

/* erfc(x) for x >= 0 (the shadowing function's argument) = exp(-x^2) erfcx(x), with
 * (1 + 2x) erfcx(x) = 1 + P(q), q = (x - 2) / (x + 2) (pb_erfc_series of each precision), and the
 * rounding error t of x^2 corrected: exp(-x^2) = exp(-fl(x^2)) (1 - t).  pb_erfc_e takes
 * e = exp(-fl(x^2)) from its caller (pb_shadow_S, which needs it too), pb_erfc computes it. */
inline real pb_erfc_e(real x, real e_x2)
{
    const real d = (real)1 + (real)2 * x;
    const real rcp = (real)1 / ((x + (real)2) * d);
    const real q = (x - (real)2) * d * rcp;
    const real ex = ((real)1 + pb_erfc_series(q)) * ((x + (real)2) * rcp);  /* erfcx(x) */
    /* t = x^2 - fl(x^2), exactly, by splitting x into halves (Dekker) */
    const real s = x * x;
    const real xh = PB_AS_REAL(PB_AS_BITS(x) & PB_ERFC_SPLIT);
    const real xl = x - xh;
    const real t = ((xh * xh - s) + (real)2 * xh * xl) + xl * xl;
    const real e = e_x2 * ex;
    const real r = e - e * t;
    return x > PB_ERFC_ZERO ? (real)0 : r;
}

inline real pb_erfc(real x)
{
    return pb_erfc_e(x, pb_exp(-x * x));
}

/* sqrt(x^2 + y^2), no rescaling: |x|, |y| must stay within about 1e-19 .. 1e19 in float32,
 * 1e-150 .. 1e150 in float64. */
inline real pb_hypot(real x, real y)
{
    return pb_sqrt(x * x + y * y);
}
#endif  /* PB_FAST_MATH */

#endif  /* PB_MATH_H */
