/*
 * pbrdf.h -- device functions of the six-parameter pBRDF model (Zhu et al. 2020).
 *
 * The physics lives here and in pbrdf_cl/reference.py, which mirrors this file
 * function by function (same names without the "pb_" prefix, same steps in the
 * same order).  Change one, change the other.  See shared/SPEC.md for the
 * equations; the forms used here are algebraically equal but avoid cancellation:
 *
 *   cos^2 b = cos^2((ti+tr)/2) + sin ti sin tr cos^2(phi/2)      (all terms >= 0)
 *   sin^2 b = sin^2((ti-tr)/2) + sin ti sin tr sin^2(phi/2)
 *   tan^2 a = ((sin ti - sin tr)^2 + 4 sin ti sin tr cos^2(phi/2)) / (cos ti + cos tr)^2
 *   Fresnel D = ((n-k)(n+k) - 1) + cos^2 b, A, B from the non-cancelling root and A*B = n*k,
 *   A - cos b = (E + B^2)/(A + cos b) with E = D - cos^2 b when E >= 0 (near-index-matched media);
 *   Rs - Rp = 4 A t Rs / ((A + t)^2 + B^2), t = sin b tan b (>= 0: no cancellation);
 *   the specular scale K is carried as log K so that no 0*inf or inf/inf can occur.
 *
 * Precision: compile with -DPBRDF_DOUBLE for float64, without it for float32.
 * Angles are in degrees; trigonometry reduces them exactly before converting to radians.
 */
#ifndef PBRDF_H
#define PBRDF_H

#define PB_CAT_(a, b) a##b
#define PB_CAT(a, b) PB_CAT_(a, b)

/* Inline every function of this file and pb_math.h: PoCL 3.0 otherwise leaves some out of line,
 * and a call spills every live vector register. */
#ifdef __clang__
#pragma clang attribute push (__attribute__((always_inline)), apply_to = function)
#endif

#ifdef PBRDF_DOUBLE
#pragma OPENCL EXTENSION cl_khr_fp64 : enable
#define PB_SCALAR double
#define PB_ISCALAR long
#else
#define PB_SCALAR float
#define PB_ISCALAR int
#endif

/* Every function below is branch-free in its real arguments (?: selects), so with
 * -DPB_VECTOR_REAL=N the same source computes N points at once: real is then floatN/doubleN
 * (and pb_bits, of pb_math.h, the integer vector of the same element width). */
#ifdef PB_VECTOR_REAL
typedef PB_CAT(PB_SCALAR, PB_VECTOR_REAL) real;
/* the N lanes of real at any element-aligned global address (as vloadN / vstoreN: PoCL 3.0 calls
 * those builtins out of line), for the per-point and LM kernels */
typedef real __attribute__((aligned(sizeof(PB_SCALAR)))) pb_real_unaligned;
#define pb_vl(i, p) (((const __global pb_real_unaligned *)(p))[i])
#define pb_vs(v, i, p) (((__global pb_real_unaligned *)(p))[i] = (v))
#else
typedef PB_SCALAR real;
#endif

/* exp, log, erfc, hypot, sincos: float32 builds use branch-free inline versions (see there) */
#include "pb_math.h"

#define PB_SHADOW_NONE 0
#define PB_SHADOW_PAPER 1
#define PB_SHADOW_SMITH 2

/* Beyond this argument the shadowing function S is below 1e-36 and is taken as 0. */
#define PB_SHADOW_ARG_MAX ((real)9)
#define PB_PI ((real)3.14159265358979323846)
#define PB_1_PI ((real)0.318309886183790671538)
#define PB_SQRT_PI ((real)1.77245385090551602730)
#define PB_SQRT2 ((real)1.41421356237309504880)

typedef struct {
    real cti, sti, ctr, str;   /* cos/sin of the zenith angles */
    real cb, sb;               /* cos/sin of the facet incidence angle b (eq. 2) */
    real tan2a;                /* tan^2 of the facet tilt a (eq. 3) */
} pb_geom;

#define PB_DEG ((real)0.0174532925199432957692)

/* sin and cos of x degrees with exact argument reduction to [-45, 45]: relative accuracy
 * near multiples of 90 degrees (cos 89.9 in float32 would otherwise lose four digits).
 * q = rint(x / 90) by the round-to-integer constant, q mod 4 in its low bits; x - 90 q is exact
 * (a tie either way reduces exactly) for |x| < 2^25 degrees in float32, 2^52 in float64. */
inline real pb_sincosd(real x, real *c)
{
    const real t = x * (real)(1.0 / 90) + PB_ROUND_MAGIC;
    real q = t - PB_ROUND_MAGIC;
    real cy;
    real sy = pb_sincos_pi4((x - (real)90 * q) * PB_DEG, &cy);
    /* quadrant q mod 4 from bit tests (Oclgrind misevaluates the chain iq == 0 ? : iq == 1 ? ...
     * on (bits & 3) for q >= 4): odd swaps sin and cos, bit 1 of q (of q + 1) is the sign of
     * sin (of cos), moved to the sign bit */
    const pb_bits iq = PB_AS_BITS(t);
    const pb_bits odd = (iq & 1) != 0;
    const pb_bits top = 8 * sizeof(PB_SCALAR) - 2;
    *c = PB_AS_REAL(PB_AS_BITS(odd ? sy : cy) ^ (((iq + 1) & 2) << top));
    return PB_AS_REAL(PB_AS_BITS(odd ? cy : sy) ^ ((iq & 2) << top));
}

/* Eq. 2-3 in stable form; angles in degrees. */
inline pb_geom pb_geometry(real ti, real tr, real phi)
{
    pb_geom g;
    real c;
    g.sti = pb_sincosd(ti, &c); g.cti = c;
    g.str = pb_sincosd(tr, &c); g.ctr = c;
    real sh = pb_sincosd((real)0.5 * phi, &c);
    real ch = c;
    real cp = pb_sincosd((real)0.5 * (((real)90 - ti) + ((real)90 - tr)), &c);  /* cos((ti+tr)/2) */
    /* sin((ti - tr)/2): |(ti - tr)/2| < 45 on the domain, where pb_sincosd's reduction is the
     * identity (q = 0): its polynomial alone, the same value bit for bit, one cosine fewer */
    real sm = pb_sincos_pi4((real)0.5 * (ti - tr) * PB_DEG, &c);
    real q = g.sti * g.str;
    g.cb = pb_sqrt(cp * cp + q * ch * ch);
    g.sb = pb_sqrt(sm * sm + q * sh * sh);
    real ds = g.sti - g.str;
    real cs = g.cti + g.ctr;
    g.tan2a = (ds * ds + (real)4 * q * ch * ch) / (cs * cs);
    return g;
}

typedef struct {
    real Rs, Rp;     /* |rs|^2, |rp|^2 (eq. 11-13) */
    real diff;       /* Rs - Rp, >= 0 */
    real re_x, im_x; /* x = rs rp* (eq. 10) */
} pb_fresnel_t;

/* Eq. 11-13 on the facet, angle b, complex index n + ik. */
inline pb_fresnel_t pb_fresnel(real n, real k, real cb, real sb)
{
    pb_fresnel_t f;
    real nk = n * k;
    real E = (n - k) * (n + k) - (real)1;   /* D - cos^2 b: exact for n = 1, k = 0 */
    real D = E + cb * cb;
    real sC = pb_hypot((real)2 * nk, D);
    /* the root that does not cancel, sqrt((sC + |D|)/2): A for D >= 0, B for D < 0; the other
     * from A B = n k */
    real root = pb_sqrt((real)0.5 * (sC + (D >= (real)0 ? D : -D)));
    real other = root > (real)0 ? nk / root : (real)0;
    real A = D >= (real)0 ? root : other;
    real B = D >= (real)0 ? other : root;
    real B2 = B * B;
    real ap = A + cb;
    real am = E >= (real)0 ? (E + B2) / ap : A - cb;  /* A - cb = (A^2 - cb^2)/(A + cb) */
    f.Rs = (am * am + B2) / (ap * ap + B2);
    real t = sb * sb / cb;
    real tm = A - t, tp = A + t;
    real Rs_den = f.Rs / (tp * tp + B2);
    f.Rp = Rs_den * (tm * tm + B2);
    f.diff = Rs_den * (real)4 * A * t;
    f.re_x = -Rs_den * ((A - t) * (A + t) + B2);
    f.im_x = Rs_den * (real)2 * B * t;
    return f;
}

/* Eq. 7-9: the shadowing function S(theta) of one beam, for the three variants. */
inline real pb_shadow_S(real ct, real st, real sigma, int variant)
{
    if (variant == PB_SHADOW_NONE)
        return (real)0;
    /* ifs rather than ?: on the (scalar) variant: Oclgrind miscomputes such selects on vectors */
    real w = sigma;
    if (variant == PB_SHADOW_SMITH)
        w = PB_SQRT2 * sigma;
    real a = ct / (w * st);
    a = a < PB_SHADOW_ARG_MAX ? a : PB_SHADOW_ARG_MAX;
    real den = a * a;
    if (variant == PB_SHADOW_SMITH)
        den = a;
    real e = pb_exp_normal(-a * a);  /* a <= 9: exp(-81) is normal in float32 */
    real S = e / ((real)2 * PB_SQRT_PI * den) - (real)0.5 * pb_erfc_e(a, e);
    return a < PB_SHADOW_ARG_MAX ? S : (real)0;
}

/* G = 1 / (1 + S(ti) + S(tr)). */
inline real pb_shadowing_of(real s_i, real s_r)
{
    return (real)1 / ((real)1 + s_i + s_r);
}

inline real pb_shadowing_factor(pb_geom g, real sigma, int variant)
{
    return pb_shadowing_of(pb_shadow_S(g.cti, g.sti, sigma, variant), pb_shadow_S(g.ctr, g.str, sigma, variant));
}

/* log of the scalar factor K of the specular term (eq. 6):
 * K = ks exp(-tan^2 a / (2 sigma^2)) G / (8 pi sigma^2 cos^4 a cos ti cos tr). */
inline real pb_log_specular_scale(pb_geom g, real sigma, real ks, real G)
{
    real inv_s = (real)1 / sigma;
    real u2 = g.tan2a > (real)0 ? g.tan2a * inv_s * inv_s : (real)0;  /* tan^2 a / sigma^2 */
    real inv_cos2a = (real)1 + g.tan2a;
    return pb_log(ks * G * inv_cos2a * inv_cos2a / ((real)8 * PB_PI * g.cti * g.ctr))
           - (real)2 * pb_log(sigma) - (real)0.5 * u2;
}

/* 2 fd / K (eq. 6 and 15) in one exponential, = 2 pb_diffuse(g, kd, c) exp(-pb_log_specular_scale(g,
 * sigma, ks, G)): 16 kd sigma^2 cos ti cos tr / (ks G (1 + tan^2 a)^2) exp(c log(cos ti cos tr)
 * + tan^2 a / (2 sigma^2)) (the Minnaert factor's exponential and 1/K's in one), 0 where kd = 0,
 * +inf where the exponential overflows (K underflows: the DOP is then diff / (sum + inf), as from
 * log K).  The per-point DOP kernels take it (pb_dop_of): two logarithms and two exponentials fewer
 * than exp(-log K) and the Minnaert factor apart, and no rounding of a large log K in between. */
inline real pb_diffuse2_over_K(pb_geom g, real sigma, real ks, real G, real kd, real c)
{
    real inv_s = (real)1 / sigma;
    real u2 = g.tan2a > (real)0 ? g.tan2a * inv_s * inv_s : (real)0;  /* tan^2 a / sigma^2 */
    real inv_cos2a = (real)1 + g.tan2a;
    real p = g.cti * g.ctr;
    real e = pb_exp(c * pb_log_normal(p) + (real)0.5 * u2);  /* p >= cos^2(90 - 1 ulp): normal */
    real r = (real)16 * kd * p * sigma * sigma / (ks * G * inv_cos2a * inv_cos2a);
    return kd == (real)0 ? (real)0 : (e < (real)INFINITY ? r * e : e);
}

/* Eq. 15's Minnaert factor (cos ti cos tr)^c. */
inline real pb_minnaert(pb_geom g, real c)
{
    return pb_exp(c * pb_log(g.cti * g.ctr));
}

/* Eq. 15: Minnaert diffuse term kd/pi (cos ti cos tr)^c, from its factor pb_minnaert(g, c). */
inline real pb_diffuse_of(real kd, real minnaert)
{
    return kd == (real)0 ? (real)0 : kd * PB_1_PI * minnaert;
}

/* Eq. 15: Minnaert diffuse term kd/pi (cos ti cos tr)^c. */
inline real pb_diffuse(pb_geom g, real kd, real c)
{
    return pb_diffuse_of(kd, pb_minnaert(g, c));
}

/* Eq. 17-18 from precomputed factors: DOP = (Rs - Rp) / (Rs + Rp + fd2 / K), where
 * fd2 = 2 fd and inv_K = 1/K (an infinite inv_K with fd2 = 0 means no diffuse term).
 * Written once as a body for any real type T (scalar or vector: ?: selects per element). */
#define PB_DOP_COMBINE_BODY(T)                                               \
    {                                                                        \
        const T r = fd2 > (T)0 ? fd2 * inv_K : (T)0;                         \
        const T den = sum + r;                                               \
        return den > (T)0 ? diff / den : (T)0;                               \
    }
inline real pb_dop_combine(real sum, real diff, real fd2, real inv_K) PB_DOP_COMBINE_BODY(real)

/* Vector width PB_VW of the row kernels (build option; default 8). */
#ifndef PB_VW
#define PB_VW 8
#endif
#if !defined(PB_VECTOR_REAL) && !defined(PB_HOST_C)  /* PB_HOST_C: compiled as C (the bench's C loop) */
typedef PB_CAT(PB_SCALAR, PB_VW) realv;
/* vloadN / vstoreN of PB_VW values at any element-aligned global address, as a vector access
 * through an under-aligned type (pbrdf_points.cl's pb_vstoren): PoCL 3.0 (LLVM 14, the PyPI
 * wheel) calls the builtins out of line, each call spilling the live vector registers of the loops
 * that read the pixels' data per measurement.  The same values bit for bit. */
typedef realv __attribute__((aligned(sizeof(PB_SCALAR)))) pb_realv_unaligned;
#define pb_vload(i, p) (((const __global pb_realv_unaligned *)(p))[i])
#define pb_vstore(v, i, p) (((__global pb_realv_unaligned *)(p))[i] = (v))
/* pb_dop_combine on PB_VW values at once (the same body). */
inline realv pb_dop_combine_v(realv sum, realv diff, realv fd2, realv inv_K) PB_DOP_COMBINE_BODY(realv)
#endif

/* F00 = K (Rs + Rp) / 2 + fd from precomputed factors. */
inline real pb_brdf_combine(real sum, real K, real fd)
{
    return (real)0.5 * K * sum + fd;
}

/* Eq. 17-18 at inv_K = 1/K: K (Rs - Rp) / (K (Rs + Rp) + 2 fd). */
inline real pb_dop_at(pb_fresnel_t f, real inv_K, real fd)
{
    return pb_dop_combine(f.Rs + f.Rp, f.diff, (real)2 * fd, inv_K);
}

/* Eq. 17-18 from fd2_K = 2 fd / K (pb_diffuse2_over_K): (Rs - Rp) / (Rs + Rp + 2 fd / K). */
inline real pb_dop_of(pb_fresnel_t f, real fd2_K)
{
    return pb_dop_combine(f.Rs + f.Rp, f.diff, fd2_K, (real)1);
}

/* Eq. 17-18: DOP for unpolarized incidence, = K (Rs - Rp) / (K (Rs + Rp) + 2 fd). */
inline real pb_dop(pb_fresnel_t f, real logK, real fd)
{
    return pb_dop_at(f, pb_exp(-logK), fd);
}

/* F00 = K (Rs + Rp) / 2 + fd. */
inline real pb_brdf(pb_fresnel_t f, real logK, real fd)
{
    return pb_brdf_combine(f.Rs + f.Rp, pb_exp(logK), fd);
}

typedef struct {
    real ci, si;  /* cos/sin of the rotation from the incident beam's macro frame to the facet frame */
    real co, so;  /* cos/sin of the rotation from the facet frame to the reflected beam's macro frame */
} pb_frames;

/* Frame rotations of the out-of-plane Mueller matrix (SPEC, psps convention); phi in degrees.
 * w_i = (sti cph, sti sph, cti) towards the source, w_r = (str, 0, ctr) towards the viewer;
 * macro bases s = unit(k x z), p = k x s; facet s_f = unit(k_in x h) = unit(w_r x w_i). */
inline pb_frames pb_frame_rotations(pb_geom g, real phi)
{
    pb_frames fr;
    real cph;
    real sph = pb_sincosd(phi, &cph);
    real vx = -g.ctr * g.sti * sph;
    real vy = g.ctr * g.sti * cph - g.str * g.cti;
    real vz = g.str * g.sti * sph;
    real nv = pb_sqrt(vx * vx + vy * vy + vz * vz);
    /* retro-reflection (nv = 0): any facet frame gives the same matrix; take s_in */
    vx = nv > (real)0 ? vx / nv : -sph;
    vy = nv > (real)0 ? vy / nv : cph;
    vz = nv > (real)0 ? vz / nv : (real)0;
    /* s_in = (-sph, cph, 0), p_in = (cti cph, cti sph, -sti) */
    fr.ci = -vx * sph + vy * cph;
    fr.si = vx * g.cti * cph + vy * g.cti * sph - vz * g.sti;
    /* s_out = (0, -1, 0), p_out = (ctr, 0, -str); so = s_out . (k_out x s_f) = -s_f . p_out */
    fr.co = -vy;
    fr.so = -(vx * g.ctr - vz * g.str);
    return fr;
}

/* (c^2 - s^2, 2 c s): cos and sin of twice the rotation angle whose cos, sin are c, s; returns the
 * first, the second in *s2. */
inline real pb_rotation2(real c, real s, real *s2)
{
    *s2 = (real)2 * c * s;
    return c * c - s * s;
}

/* The 4x4 Mueller matrix F = K R_out M^s R_in + fd e00 (eq. 10, 15, 16) at the scale K itself,
 * row-major into m[16].  R(c, s) = [[1,0,0,0],[0,c2,s2,0],[0,-s2,c2,0],[0,0,0,1]], c2 = c^2 - s^2,
 * s2 = 2 c s.  With K = 1 and fd = 0 it is P = R_out M^s R_in, the specular part per unit K. */
inline void pb_mueller_at(pb_fresnel_t f, pb_frames fr, real K, real fd, real *m)
{
    real m00 = (real)0.5 * K * (f.Rs + f.Rp);
    real m01 = (real)0.5 * K * f.diff;
    real rx = K * f.re_x, ix = K * f.im_x;
    real s, S;
    real c = pb_rotation2(fr.ci, fr.si, &s), C = pb_rotation2(fr.co, fr.so, &S);
    /* A = M^s R_in */
    real a1[4] = {m01, m00 * c, m00 * s, (real)0};
    real a2[4] = {(real)0, -rx * s, rx * c, ix};
    m[0] = m00 + fd; m[1] = m01 * c; m[2] = m01 * s; m[3] = (real)0;
    for (int j = 0; j < 4; j++) {
        m[4 + j] = C * a1[j] + S * a2[j];
        m[8 + j] = -S * a1[j] + C * a2[j];
    }
    m[12] = (real)0; m[13] = ix * s; m[14] = -ix * c; m[15] = rx;
}

/* F = K R_out M^s R_in + fd e00 from log K (pb_mueller_at). */
inline void pb_mueller(pb_fresnel_t f, pb_frames fr, real logK, real fd, real *m)
{
    pb_mueller_at(f, fr, pb_exp(logK), fd, m);
}

/* The first column of F (pb_mueller): the Stokes vector (S0, S1, S2, S3) reflected for unpolarised
 * incidence of unit radiance, from the factors of the grid tables: sum = Rs + Rp, diff = Rs - Rp,
 * K, fd and the outgoing frame's rotation (C, S) = (cos 2 psi, sin 2 psi) of pb_rotation2.
 * Component comp (0..3); S3 = 0: the model's first column has no circular part. */
inline real pb_stokes_combine(real sum, real diff, real K, real fd, real C, real S, int comp)
{
    const real m01 = (real)0.5 * K * diff;
    const real v = comp == 0 ? (real)0.5 * K * sum + fd : (comp == 1 ? C * m01 : -S * m01);
    return comp < 3 ? v : (real)0;
}

/* Angle of linear polarisation, degrees in (-90, 90], of the Stokes vector's S1 = L1, S2 = L2:
 * AoP = atan2(L2, L1) / 2 in the psps frame of the outgoing beam; NaN where L1 = L2 = 0 (DOP = 0,
 * AoP undefined). */
inline real pb_aop_of(real L1, real L2)
{
    const real a = (real)0.5 * atan2(L2, L1) / PB_DEG;
    const real b = a <= (real)-90 ? a + (real)180 : a + (real)0;  /* -90 is +90; -0 is 0 */
    return ((L1 != (real)0) | (L2 != (real)0)) ? b : (real)NAN;
}

/* AoP from the grid tables' factors (see pb_stokes_combine).  L = (S1, S2) = m01 (C, -S) with
 * m01 = K diff / 2, so where the light is polarised (diff > 0, and K > 0 unless there is no diffuse
 * term: where pb_dop_combine is > 0) L points along (C, -S): taken as that, so that an underflow
 * of K diff cannot make it undefined. */
inline real pb_aop_combine(real diff, real K, real fd, real C, real S)
{
    const real on = ((diff > (real)0) & ((K > (real)0) | (fd == (real)0))) ? (real)1 : (real)0;
    return pb_aop_of(on * C, -on * S);
}

/* ---- Polarimetric channels (SPEC, "Polarized incidence and polarimetric measurements"): one
 * number a polarimeter measures at one geometry, for an incident Stokes vector u (1, s1, s2, s3;
 * a basis vector e_j for a Mueller element).  F = K P + fd e00 with P = R_out M^s R_in per unit K
 * (pb_mueller_at with K = 1, fd = 0), so every channel comes from two terms of P and the scale:
 *   PB_CHANNEL_RATIO  (F u)_comp / (F v)_0, or (F u)_comp itself: tn = (P u)_comp, td = (P v)_0;
 *   PB_CHANNEL_DOP    |(F u)_123| / (F u)_0:  tn = |(P u)_123|, td = (P u)_0;
 *   PB_CHANNEL_AOP    AoP of F u (degrees):   tn = the AoP of P u (the diffuse term adds to S0 only).
 * and pb_channel_combine's (K tn + a fd) / (K td + b fd) for a normalised channel or K tn + a fd for
 * an absolute one, with the channel's coefficients (a = u0 for S0 or M00, else 0; b = v0 and c = 0
 * for a normalised channel, b = 0 and c = 1 for an absolute one).  u and v are the channel's own (scalars, the same for every lane of a vector real). */
#define PB_CHANNEL_RATIO 0
#define PB_CHANNEL_DOP 1
#define PB_CHANNEL_AOP 2

/* The terms (tn, *td) of a channel of kind `kind`, output component `comp`, from P (m[16]). */
inline real pb_channel_terms(const real *m, const real *u, const real *v, int comp, int kind, real *td)
{
    real t[4];
    for (int i = 0; i < 4; i++)
        t[i] = m[4 * i] * u[0] + m[4 * i + 1] * u[1] + m[4 * i + 2] * u[2] + m[4 * i + 3] * u[3];
    real tn = t[comp];
    *td = m[0] * v[0] + m[1] * v[1] + m[2] * v[2] + m[3] * v[3];
    if (kind == PB_CHANNEL_DOP) {
        tn = pb_sqrt(t[1] * t[1] + t[2] * t[2] + t[3] * t[3]);
        *td = t[0];
    }
    if (kind == PB_CHANNEL_AOP) {
        tn = pb_aop_of(t[1], t[2]);
        *td = (real)1;
    }
    return tn;
}

/* A channel's value from its terms, inv_K = 1/K, the diffuse term fd and its coefficients (scalars,
 * the same for every lane: the branches below are uniform): an AoP is tn; an absolute channel
 * (c != 0) is K tn + a fd; a normalised one (tn + a q) / (td + b q), q = fd / K (0 where there is no
 * diffuse term, whatever K), 0 where that denominator is 0 (no light).  The scale enters as 1/K, as
 * in the DOP (pb_dop_combine), so that a K that underflows (a sharp lobe seen off specular) leaves
 * the ratio exact; a zero coefficient adds nothing (no 0 * inf). */
#define PB_CHANNEL_COMBINE_BODY(T)                                           \
    {                                                                        \
        if (aop)                                                             \
            return tn;                                                       \
        if (c != 0)                                                          \
            return tn / inv_K + a * fd;                                      \
        const T q = fd > (T)0 ? fd * inv_K : (T)0;                           \
        T num = tn, den = td;                                                \
        if (a != 0)                                                          \
            num += a * q;                                                    \
        if (b != 0)                                                          \
            den += b * q;                                                    \
        return den > (T)0 ? num / den : (T)0;                                \
    }
inline real pb_channel_combine(real tn, real td, real inv_K, real fd, PB_SCALAR a, PB_SCALAR b, PB_SCALAR c,
                               int aop)
    PB_CHANNEL_COMBINE_BODY(real)
#if !defined(PB_VECTOR_REAL) && !defined(PB_HOST_C)
inline realv pb_channel_combine_v(realv tn, realv td, realv inv_K, realv fd, PB_SCALAR a, PB_SCALAR b, PB_SCALAR c,
                                  int aop)
    PB_CHANNEL_COMBINE_BODY(realv)
#endif

/* One channel at one point of the model: P from the Fresnel factors and frames, then its terms and
 * value (pb_channel_terms, pb_channel_combine). */
inline real pb_channel(pb_fresnel_t f, pb_frames fr, real logK, real fd, const real *u, const real *v, int comp,
                       int kind, PB_SCALAR a, PB_SCALAR b, PB_SCALAR c)
{
    real m[16], td;
    pb_mueller_at(f, fr, (real)1, (real)0, m);
    const real tn = pb_channel_terms(m, u, v, comp, kind, &td);
    return pb_channel_combine(tn, td, pb_exp(-logK), fd, a, b, c, kind == PB_CHANNEL_AOP);
}

/* The residual of a channel's value against its measurement, wrapped into (-90, 90] for an AoP
 * (angles modulo 180 degrees); an undefined AoP (NaN) is 90 degrees off.  Written once as a body for
 * any real type T (pb_channel_residual_v: PB_VW values at once, one measurement). */
#define PB_CHANNEL_RESIDUAL_BODY(T)                                          \
    {                                                                        \
        const T r = value - obs;                                             \
        if (!aop)                                                            \
            return r;                                                        \
        const T w = r - (T)180 * rint(r / (T)180);                           \
        return isnan(w) ? (T)90 : w;                                         \
    }
inline real pb_channel_residual(real value, real obs, int aop) PB_CHANNEL_RESIDUAL_BODY(real)
#if !defined(PB_VECTOR_REAL) && !defined(PB_HOST_C)
inline realv pb_channel_residual_v(realv value, realv obs, int aop) PB_CHANNEL_RESIDUAL_BODY(realv)
#endif

/* ---- The output quantities.  Each has two entry points of fixed signature, named after its
 * registry name (pbrdf_cl/quantities.py: the kernels are built with -DPB_QUANTITY=<name>):
 *   void pb_point_<name>(pb_geom g, pb_fresnel_t f, real phi, real logK, real fd, real *out)
 *     writes the quantity's width values of one point (pbrdf_points.cl's quantity_points);
 *   real pb_grid_<name>(real sum, real diff, real fdx, real scale, real C, real S, int comp)
 *     component comp from the tables (pbrdf_grid.cl): scale = K or 1/K and fdx = fd or 2 fd as the
 *     registry's table factors say; (C, S) the outgoing frame rotation where the registry asks
 *     for the frame table, else (1, 0). */
inline void pb_point_dop(pb_geom g, pb_fresnel_t f, real phi, real logK, real fd, real *out)
{
    out[0] = pb_dop(f, logK, fd);
}
inline real pb_grid_dop(real sum, real diff, real fd2, real inv_K, real C, real S, int comp)
{
    return pb_dop_combine(sum, diff, fd2, inv_K);
}

inline void pb_point_brdf(pb_geom g, pb_fresnel_t f, real phi, real logK, real fd, real *out)
{
    out[0] = pb_brdf(f, logK, fd);
}
inline real pb_grid_brdf(real sum, real diff, real fd, real K, real C, real S, int comp)
{
    return pb_brdf_combine(sum, K, fd);
}

inline void pb_point_mueller(pb_geom g, pb_fresnel_t f, real phi, real logK, real fd, real *out)
{
    pb_mueller(f, pb_frame_rotations(g, phi), logK, fd, out);
}

/* (cos 2 psi, sin 2 psi) of the outgoing frame rotation: the frame table of the grid path */
inline real pb_out_rotation2(pb_geom g, real phi, real *S)
{
    const pb_frames fr = pb_frame_rotations(g, phi);
    return pb_rotation2(fr.co, fr.so, S);
}

inline void pb_point_stokes(pb_geom g, pb_fresnel_t f, real phi, real logK, real fd, real *out)
{
    real S;
    const real C = pb_out_rotation2(g, phi, &S);
    const real K = pb_exp(logK);
    for (int comp = 0; comp < 4; comp++)
        out[comp] = pb_stokes_combine(f.Rs + f.Rp, f.diff, K, fd, C, S, comp);
}
inline real pb_grid_stokes(real sum, real diff, real fd, real K, real C, real S, int comp)
{
    return pb_stokes_combine(sum, diff, K, fd, C, S, comp);
}

inline void pb_point_aop(pb_geom g, pb_fresnel_t f, real phi, real logK, real fd, real *out)
{
    real S;
    const real C = pb_out_rotation2(g, phi, &S);
    out[0] = pb_aop_combine(f.diff, pb_exp(logK), fd, C, S);
}
inline real pb_grid_aop(real sum, real diff, real fd, real K, real C, real S, int comp)
{
    return pb_aop_combine(diff, K, fd, C, S);
}

#ifdef __clang__
#pragma clang attribute pop
#endif

#endif /* PBRDF_H */
