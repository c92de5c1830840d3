/*
 * pbrdf_points.cl -- element-wise evaluation of the pBRDF model over arrays.
 *
 * Build options: -DPBRDF_DOUBLE (float64, else float32), -DPBRDF_SHADOWING=<0 none|1 paper|2 smith>,
 * -I <this folder>; -DPB_VECTOR_REAL=N builds the *_vec kernels instead, which evaluate N
 * consecutive points per work-item with the same device functions on vector types.
 * Each of the nine inputs is a buffer with a stride: 1 for a full array of length n, 0 for one
 * value broadcast to every point.  Angles are in degrees.  quantity_points evaluates any quantity
 * of the registry (-DPB_QUANTITY); dop_points_vec and brdf_points_vec are the vector kernels of
 * the two quantities the registry marks ``vector``.
 *
 * Broadcast inputs (issue #12): the *_bcast_* twins (quantity_bcast_points, dop_bcast_points_vec,
 * brdf_bcast_points_vec) read each input through an index rule instead of a stride, from a table
 * `rules` of PB_RULE_LEN uints per input (pbrdf_cl.engine.input_plan and engine.rule_table write
 * it): kind 0, one value; kind 1, one value per point of the launch (as stride 1); kind 2, the
 * launch's point l (global flat index t = start + l) reads x[(t / div) % mod] of the compact
 * array x (a short axis, or a run of axes, sent once).  The host turns start into the 32-bit
 * offsets r0 = start % div and q0 = (start / div) % mod, so that the kernels need only 32-bit
 * arithmetic: the index is (q0 + (r0 + l) / div) % mod, both divisions by a multiplier and a
 * shift computed on the host (PB_UDIV).  The model's code is the same macro body for both.
 */
#include "pbrdf.h"

#ifndef PBRDF_SHADOWING
#define PBRDF_SHADOWING PB_SHADOW_PAPER
#endif

/* The nine inputs, each a buffer of element type T and a stride. */
#define PB_INPUT_ARGS(T)                                                     \
    __global const T *ti, const int s_ti, __global const T *tr, const int s_tr, \
    __global const T *ph, const int s_ph, __global const T *nn, const int s_n,  \
    __global const T *kk, const int s_k, __global const T *sg, const int s_sg,  \
    __global const T *ks, const int s_ks, __global const T *kd, const int s_kd, \
    __global const T *cc, const int s_c

/* The nine inputs of the broadcast twins, each a buffer of element type T, and their rules. */
#define PB_BCAST_ARGS(T)                                                              \
    __global const T *ti, __global const T *tr, __global const T *ph, __global const T *nn, \
    __global const T *kk, __global const T *sg, __global const T *ks, __global const T *kd, \
    __global const T *cc, __constant const uint *rules

/* The fields of one input's rule in `rules` (pbrdf_cl.engine.RULE_FIELDS names them in order).
 * Bounds the host keeps (engine.RULE_MAX, engine.RULE_LAUNCH_MAX): div, mod <= 2^30 and launches of
 * at most 2^22 points, so every numerator below is < 2^31. */
#define PB_RULE_LEN 9
#define PB_R_KIND 0
#define PB_R_DIV 1
#define PB_R_DIV_M 2
#define PB_R_DIV_S 3
#define PB_R_MOD 4
#define PB_R_MOD_M 5
#define PB_R_MOD_S 6
#define PB_R_R0 7
#define PB_R_Q0 8

/* n / d for 0 <= n < 2^31 by d's multiplier m = ceil(2^(31+s) / d) < 2^32, s = ceil(log2 d)
 * (Granlund and Montgomery 1994, with 31-bit numerators: exact for every n < 2^31, d <= 2^31);
 * for scalars and for uint vectors alike. */
#define PB_UDIV(n, m, s) (mul_hi((n) << 1, (m)) >> (s))

/* The compact index of the point at launch offset l under rule r (kind 2). */
inline uint pb_rule_index(__constant const uint *r, const uint l)
{
    const uint u = r[PB_R_R0] + l;
    const uint q = r[PB_R_Q0] + PB_UDIV(u, r[PB_R_DIV_M], r[PB_R_DIV_S]);
    return q - PB_UDIV(q, r[PB_R_MOD_M], r[PB_R_MOD_S]) * r[PB_R_MOD];
}

#ifndef PB_VECTOR_REAL

#define PB_POINT_ARGS const int n, PB_INPUT_ARGS(real)

/* input x (stride s, or rule j of `rules`) at point i of the launch */
#define PB_IN1_STRIDED(x, s, j) x[i * s]
inline real pb_in1_rule(__global const real *x, __constant const uint *r, const int i)
{
    if (r[PB_R_KIND] == 1)
        return x[i];
    if (r[PB_R_KIND] == 0)
        return x[0];
    return x[pb_rule_index(r, (uint)i)];
}
#define PB_IN1_RULE(x, s, j) pb_in1_rule(x, rules + (j) * PB_RULE_LEN, i)

/* Everything a point needs: geometry, Fresnel, log K and the diffuse term, its inputs read by
 * IN(buffer, stride, rule number). */
#define PB_POINT_BODY_OF(IN)                                                 \
    const int i = get_global_id(0);                                          \
    if (i >= n) return;                                                      \
    const real v_ph = IN(ph, s_ph, 2);                                       \
    pb_geom g = pb_geometry(IN(ti, s_ti, 0), IN(tr, s_tr, 1), v_ph);         \
    pb_fresnel_t f = pb_fresnel(IN(nn, s_n, 3), IN(kk, s_k, 4), g.cb, g.sb); \
    const real sigma = IN(sg, s_sg, 5);                                      \
    const real G = pb_shadowing_factor(g, sigma, PBRDF_SHADOWING);           \
    const real logK = pb_log_specular_scale(g, sigma, IN(ks, s_ks, 6), G);   \
    const real fd = pb_diffuse(g, IN(kd, s_kd, 7), IN(cc, s_c, 8));
#define PB_POINT_BODY PB_POINT_BODY_OF(PB_IN1_STRIDED)

/* Any quantity of the registry (pbrdf_cl/quantities.py), built with -DPB_QUANTITY=<name> and
 * -DPB_WIDTH=<values per point>: pbrdf.h's pb_point_<name> for each point. */
#ifdef PB_QUANTITY
#define PB_QUANTITY_STORE                                                    \
    real v[PB_WIDTH];                                                        \
    PB_CAT(pb_point_, PB_QUANTITY)(g, f, v_ph, logK, fd, v);                 \
    for (int j = 0; j < PB_WIDTH; j++)                                       \
        out[(size_t)PB_WIDTH * i + j] = v[j];

__kernel void quantity_points(__global real *out, PB_POINT_ARGS)
{
    PB_POINT_BODY
    PB_QUANTITY_STORE
}

/* quantity_points with its inputs read through their rules (broadcast inputs sent once). */
__kernel void quantity_bcast_points(__global real *out, const int n, PB_BCAST_ARGS(real))
{
    PB_POINT_BODY_OF(PB_IN1_RULE)
    PB_QUANTITY_STORE
}

/* quantity at every (geometry, parameter set) pair: a 2-D range of S parameter sets (dimension 0:
 * the six arrays nn..cc of length S) times G geometries (dimension 1: geometries g0 .. g0 + G - 1 of
 * the lists ti, tr, ph), out laid out geometry by geometry, out[((g - g0) * S + s) * PB_WIDTH + j].  The sample sets of a global
 * sensitivity analysis and the finite-difference steps of a Jacobian share every geometry, so
 * this is one dense evaluation; the host checks the domain of both lists beforehand. */
__kernel void quantity_outer(__global real *out, const int S, const int G, const int g0,
                             __global const real *ti, __global const real *tr, __global const real *ph,
                             __global const real *nn, __global const real *kk, __global const real *sg,
                             __global const real *ks, __global const real *kd, __global const real *cc)
{
    const int s = get_global_id(0), j = get_global_id(1), gi = g0 + j;
    if (s >= S || j >= G) return;
    pb_geom g = pb_geometry(ti[gi], tr[gi], ph[gi]);
    pb_fresnel_t f = pb_fresnel(nn[s], kk[s], g.cb, g.sb);
    const real G_ = pb_shadowing_factor(g, sg[s], PBRDF_SHADOWING);
    const real logK = pb_log_specular_scale(g, sg[s], ks[s], G_);
    real v[PB_WIDTH];
    PB_CAT(pb_point_, PB_QUANTITY)(g, f, ph[gi], logK, pb_diffuse(g, kd[s], cc[s]), v);
    const size_t at = ((size_t)j * S + s) * PB_WIDTH;
    for (int w = 0; w < PB_WIDTH; w++)
        out[at + w] = v[w];
}
#endif  /* PB_QUANTITY */

/* Weighted sum of squared DOP residuals for an explicit list of P parameter vectors (one
 * work-item each) over M measurements (theta_i, theta_r, phi in degrees, observed DOP, weight). */
__kernel void objective_points(__global real *sse, const int P,
                               __global const real *nn, __global const real *kk, __global const real *sg,
                               __global const real *ks, __global const real *kd, __global const real *cc,
                               __global const real *ti, __global const real *tr, __global const real *ph,
                               __global const real *obs, __global const real *w, const int M)
{
    const int p = get_global_id(0);
    if (p >= P) return;
    real acc = (real)0;
    for (int m = 0; m < M; m++) {
        pb_geom g = pb_geometry(ti[m], tr[m], ph[m]);
        pb_fresnel_t f = pb_fresnel(nn[p], kk[p], g.cb, g.sb);
        const real G = pb_shadowing_factor(g, sg[p], PBRDF_SHADOWING);
        const real logK = pb_log_specular_scale(g, sg[p], ks[p], G);
        const real r = pb_dop(f, logK, pb_diffuse(g, kd[p], cc[p])) - obs[m];
        acc += w[m] * r * r;
    }
    sse[p] = acc;
}

#else  /* PB_VECTOR_REAL */

/* N points are read and written as one vector at any element-aligned address (pbrdf.h's pb_vl, pb_vs) */
/* input x of stride s (0 or 1) for the N points of work-item i (an if: PoCL 3.0's compiler
 * crashes on a ?: between a vload and a broadcast) */
inline real pb_in(__global const PB_SCALAR *x, const int s, const int i)
{
    if (s)
        return pb_vl(i, x);
    return (real)x[0];
}
#define PB_IN(x, s) pb_in(x, s, i)
#define PB_IN_STRIDED(x, s, j) PB_IN(x, s)

/* the lane numbers 0 .. N-1 as reals */
#if PB_VECTOR_REAL == 4
#define PB_LANES ((real)(0, 1, 2, 3))
#elif PB_VECTOR_REAL == 8
#define PB_LANES ((real)(0, 1, 2, 3, 4, 5, 6, 7))
#elif PB_VECTOR_REAL == 16
#define PB_LANES ((real)(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15))
#else
#error "the broadcast kernels need PB_VECTOR_REAL 4, 8 or 16"
#endif

/* input x under rule r for the N points of work-item i: kinds 1 and 0 as pb_in.  Kind 2 takes two
 * forms (the host lays the compact values out for them, engine.broadcast_table): div = 1, N
 * consecutive values from index q, one vector load (the table repeats its first N - 1 values at
 * its end, so no load wraps); div >= N, at most two values, x[q] on the lanes before the next
 * block starts and x[q + 1] after it (the table repeats its first value at its end).
 * Measured on PoCL 3.0 and 3.1, float32: an element-by-element gather of N indices here made the
 * kernel 20-30% slower than dop_points_vec even where it never ran; with these two forms the
 * twin costs ~5-14% more than dop_points_vec (the per-input dispatch on the kind), which is why
 * calls without a broadcast input keep the plain kernels. */
inline real pb_in_rule(__global const PB_SCALAR *x, __constant const uint *r, const int i)
{
    const uint kind = r[PB_R_KIND];
    if (kind == 1)
        return pb_vl(i, x);
    if (kind == 0)
        return (real)x[0];
    const uint div = r[PB_R_DIV], mod = r[PB_R_MOD];
    const uint u = r[PB_R_R0] + (uint)i * PB_VECTOR_REAL;
    if (div == 1) {
        uint q = r[PB_R_Q0] + u;
        q -= PB_UDIV(q, r[PB_R_MOD_M], r[PB_R_MOD_S]) * mod;
        return pb_vl(0, x + q);
    }
    const uint qd = PB_UDIV(u, r[PB_R_DIV_M], r[PB_R_DIV_S]);
    uint q = r[PB_R_Q0] + qd;
    q -= PB_UDIV(q, r[PB_R_MOD_M], r[PB_R_MOD_S]) * mod;
    /* u - qd div: the lanes left in block q */
    return PB_LANES < (real)(div - (u - qd * div)) ? (real)x[q] : (real)x[q + 1];
}
#define PB_IN_RULE(x, s, j) pb_in_rule(x, rules + (j) * PB_RULE_LEN, i)

#define PB_VEC_ARGS const int nvec, PB_INPUT_ARGS(PB_SCALAR)

/* The domain of the inputs, as pbrdf_cl.model.inputs.RULES states it: theta_i, theta_r in [0, 90); n,
 * sigma, ks > 0; k, kd >= 0; c in [-1, 0]; everything finite (NaN fails every comparison).  A point outside it gets NaN,
 * which the host's check of the result finds; only then does it look for (and name) the offender,
 * so it reads no input before the launch. */
#define PB_INF ((real)INFINITY)
#define PB_FINITE(x) (((x) > -PB_INF) & ((x) < PB_INF))
#define PB_IN_DOMAIN                                                                              \
    ((v_ti >= (real)0) & (v_ti < (real)90) & (v_tr >= (real)0) & (v_tr < (real)90) & PB_FINITE(v_ph) & \
     (v_n > (real)0) & (v_n < PB_INF) & (v_k >= (real)0) & (v_k < PB_INF) & (sigma > (real)0) &     \
     (sigma < PB_INF) & (v_ks > (real)0) & (v_ks < PB_INF) & (v_kd >= (real)0) & (v_kd < PB_INF) &   \
     (v_c >= (real)-1) & (v_c <= (real)0))

/* The N points of work-item i, their inputs read by IN(buffer, stride, rule number). */
#define PB_VEC_INPUTS_OF(IN)                                                 \
    const int i = get_global_id(0);                                          \
    if (i >= nvec) return;                                                   \
    const real v_ti = IN(ti, s_ti, 0), v_tr = IN(tr, s_tr, 1), v_ph = IN(ph, s_ph, 2); \
    const real v_n = IN(nn, s_n, 3), v_k = IN(kk, s_k, 4), sigma = IN(sg, s_sg, 5);   \
    const real v_ks = IN(ks, s_ks, 6), v_kd = IN(kd, s_kd, 7), v_c = IN(cc, s_c, 8);
#define PB_VEC_BODY_OF(IN)                                                   \
    PB_VEC_INPUTS_OF(IN)                                                     \
    pb_geom g = pb_geometry(v_ti, v_tr, v_ph);                               \
    pb_fresnel_t f = pb_fresnel(v_n, v_k, g.cb, g.sb);                       \
    const real G = pb_shadowing_factor(g, sigma, PBRDF_SHADOWING);           \
    const real logK = pb_log_specular_scale(g, sigma, v_ks, G);              \
    const real fd = pb_diffuse(g, v_kd, v_c);
#define PB_VEC_BODY PB_VEC_BODY_OF(PB_IN_STRIDED)

/* nvec work-items of N points each: the arrays hold nvec * N points (the host pads). */
__kernel void dop_points_vec(__global PB_SCALAR *out, PB_VEC_ARGS)
{
    PB_VEC_BODY
    pb_vs(PB_IN_DOMAIN ? pb_dop_of(f, pb_diffuse2_over_K(g, sigma, v_ks, G, v_kd, v_c)) : (real)NAN, i, out);
}

/* The DOP of a conductor (kd = 0 at every point: the host picks it where kd is one value, 0): then
 * 2 fd / K is 0 (pb_diffuse2_over_K) and the DOP is (Rs - Rp) / (Rs + Rp), whatever sigma, ks and
 * the shadowing, which are not computed; the same values as dop_points_vec's bit for bit (a kernel
 * of its own: a branch on kd inside dop_points_vec slowed the whole kernel by 5-11%). */
#define PB_CONDUCTOR_BODY_OF(IN)                                             \
    PB_VEC_INPUTS_OF(IN)                                                     \
    const pb_geom g = pb_geometry(v_ti, v_tr, v_ph);                         \
    pb_vs(PB_IN_DOMAIN ? pb_dop_of(pb_fresnel(v_n, v_k, g.cb, g.sb), (real)0) : (real)NAN, i, out);

__kernel void dop_conductor_points_vec(__global PB_SCALAR *out, PB_VEC_ARGS)
{
    PB_CONDUCTOR_BODY_OF(PB_IN_STRIDED)
}

__kernel void brdf_points_vec(__global PB_SCALAR *out, PB_VEC_ARGS)
{
    PB_VEC_BODY
    pb_vs(PB_IN_DOMAIN ? pb_brdf(f, logK, fd) : (real)NAN, i, out);
}

/* The twins with inputs read through their rules (broadcast inputs sent once; kind 1 inputs
 * hold nvec * N points, padded by the host; kind 2 indices stay below mod for padding too). */
__kernel void dop_bcast_points_vec(__global PB_SCALAR *out, const int nvec, PB_BCAST_ARGS(PB_SCALAR))
{
    PB_VEC_BODY_OF(PB_IN_RULE)
    pb_vs(PB_IN_DOMAIN ? pb_dop_of(f, pb_diffuse2_over_K(g, sigma, v_ks, G, v_kd, v_c)) : (real)NAN, i, out);
}

__kernel void dop_conductor_bcast_points_vec(__global PB_SCALAR *out, const int nvec, PB_BCAST_ARGS(PB_SCALAR))
{
    PB_CONDUCTOR_BODY_OF(PB_IN_RULE)
}

__kernel void brdf_bcast_points_vec(__global PB_SCALAR *out, const int nvec, PB_BCAST_ARGS(PB_SCALAR))
{
    PB_VEC_BODY_OF(PB_IN_RULE)
    pb_vs(PB_IN_DOMAIN ? pb_brdf(f, logK, fd) : (real)NAN, i, out);
}

/* quantity_outer's vector form for the vector quantities: N consecutive parameter sets (dimension 0,
 * S = nvec * N of them: the host pads) at one geometry (dimension 1, geometries g0 ..). */
#define PB_OUTER_VEC_ARGS                                                                     \
    const int nvec, const int G, const int g0, __global const PB_SCALAR *ti,                  \
    __global const PB_SCALAR *tr, __global const PB_SCALAR *ph, __global const PB_SCALAR *nn, \
    __global const PB_SCALAR *kk, __global const PB_SCALAR *sg, __global const PB_SCALAR *ks, \
    __global const PB_SCALAR *kd, __global const PB_SCALAR *cc
#define PB_OUTER_VEC_BODY                                                                     \
    const int i = get_global_id(0), j = get_global_id(1), gi = g0 + j;                       \
    if (i >= nvec || j >= G) return;                                                          \
    pb_geom g = pb_geometry((real)ti[gi], (real)tr[gi], (real)ph[gi]);                        \
    pb_fresnel_t f = pb_fresnel(pb_in(nn, 1, i), pb_in(kk, 1, i), g.cb, g.sb);                \
    const real sigma = pb_in(sg, 1, i);                                                       \
    const real logK = pb_log_specular_scale(g, sigma, pb_in(ks, 1, i),                        \
                                            pb_shadowing_factor(g, sigma, PBRDF_SHADOWING));  \
    const real fd = pb_diffuse(g, pb_in(kd, 1, i), pb_in(cc, 1, i));                          \
    const int at = j * nvec + i;

__kernel void dop_outer_vec(__global PB_SCALAR *out, PB_OUTER_VEC_ARGS)
{
    PB_OUTER_VEC_BODY
    pb_vs(pb_dop(f, logK, fd), at, out);
}

__kernel void brdf_outer_vec(__global PB_SCALAR *out, PB_OUTER_VEC_ARGS)
{
    PB_OUTER_VEC_BODY
    pb_vs(pb_brdf(f, logK, fd), at, out);
}

#endif  /* PB_VECTOR_REAL */
