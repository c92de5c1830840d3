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

#ifndef PB_VECTOR_REAL

#define PB_POINT_ARGS const int n, PB_INPUT_ARGS(real)

/* Everything a point needs: geometry, Fresnel, log K and the diffuse term. */
#define PB_POINT_BODY                                                        \
    const int i = get_global_id(0);                                          \
    if (i >= n) return;                                                      \
    pb_geom g = pb_geometry(ti[i * s_ti], tr[i * s_tr], ph[i * s_ph]); \
    pb_fresnel_t f = pb_fresnel(nn[i * s_n], kk[i * s_k], g.cb, g.sb);       \
    const real sigma = sg[i * s_sg];                                         \
    const real G = pb_shadowing_factor(g, sigma, PBRDF_SHADOWING);                  \
    const real logK = pb_log_specular_scale(g, sigma, ks[i * s_ks], G);      \
    const real fd = pb_diffuse(g, kd[i * s_kd], cc[i * s_c]);

/* Any quantity of the registry (pbrdf_cl/quantities.py), built with -DPB_QUANTITY=<name> and
 * -DPB_WIDTH=<values per point>: pbrdf.h's pb_point_<name> for each point. */
#ifdef PB_QUANTITY
__kernel void quantity_points(__global real *out, PB_POINT_ARGS)
{
    PB_POINT_BODY
    real v[PB_WIDTH];
    PB_CAT(pb_point_, PB_QUANTITY)(g, f, ph[i * s_ph], logK, fd, v);
    for (int j = 0; j < PB_WIDTH; j++)
        out[(size_t)PB_WIDTH * i + j] = v[j];
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

/* N points as one vector at any element-aligned address (vloadN/vstoreN: PoCL 3.0 calls these
 * out of line) */
typedef real __attribute__((aligned(sizeof(PB_SCALAR)))) pb_real_unaligned;
#define pb_vstoren(v, i, p) (((__global pb_real_unaligned *)(p))[i] = (v))
/* input x of stride s (0 or 1) for the N points of work-item i (an if: PoCL 3.0's compiler
 * crashes on a ?: between a vload and a broadcast) */
inline real pb_in(__global const PB_SCALAR *x, const int s, const int i)
{
    if (s)
        return ((__global const pb_real_unaligned *)x)[i];
    return (real)x[0];
}
#define PB_IN(x, s) pb_in(x, s, i)

#define PB_VEC_ARGS const int nvec, PB_INPUT_ARGS(PB_SCALAR)

/* The domain of the inputs, as pbrdf_cl.api.RULES states it: theta_i, theta_r in [0, 90); n, sigma,
 * ks > 0; k, kd >= 0; everything finite (NaN fails every comparison).  A point outside it gets NaN,
 * which the host's check of the result finds; only then does it look for (and name) the offender,
 * so it reads no input before the launch. */
#define PB_INF ((real)INFINITY)
#define PB_FINITE(x) (((x) > -PB_INF) & ((x) < PB_INF))
#define PB_IN_DOMAIN                                                                              \
    ((v_ti >= (real)0) & (v_ti < (real)90) & (v_tr >= (real)0) & (v_tr < (real)90) & PB_FINITE(v_ph) & \
     (v_n > (real)0) & (v_n < PB_INF) & (v_k >= (real)0) & (v_k < PB_INF) & (sigma > (real)0) &     \
     (sigma < PB_INF) & (v_ks > (real)0) & (v_ks < PB_INF) & (v_kd >= (real)0) & (v_kd < PB_INF) &   \
     PB_FINITE(v_c))

#define PB_VEC_BODY                                                          \
    const int i = get_global_id(0);                                          \
    if (i >= nvec) return;                                                   \
    const real v_ti = PB_IN(ti, s_ti), v_tr = PB_IN(tr, s_tr), v_ph = PB_IN(ph, s_ph); \
    const real v_n = PB_IN(nn, s_n), v_k = PB_IN(kk, s_k), sigma = PB_IN(sg, s_sg);   \
    const real v_ks = PB_IN(ks, s_ks), v_kd = PB_IN(kd, s_kd), v_c = PB_IN(cc, s_c);  \
    pb_geom g = pb_geometry(v_ti, v_tr, v_ph);                               \
    pb_fresnel_t f = pb_fresnel(v_n, v_k, g.cb, g.sb);                       \
    const real G = pb_shadowing_factor(g, sigma, PBRDF_SHADOWING);           \
    const real logK = pb_log_specular_scale(g, sigma, v_ks, G);              \
    const real fd = pb_diffuse(g, v_kd, v_c);

/* nvec work-items of N points each: the arrays hold nvec * N points (the host pads). */
__kernel void dop_points_vec(__global PB_SCALAR *out, PB_VEC_ARGS)
{
    PB_VEC_BODY
    pb_vstoren(PB_IN_DOMAIN ? pb_dop(f, logK, fd) : (real)NAN, i, out);
}

__kernel void brdf_points_vec(__global PB_SCALAR *out, PB_VEC_ARGS)
{
    PB_VEC_BODY
    pb_vstoren(PB_IN_DOMAIN ? pb_brdf(f, logK, fd) : (real)NAN, i, out);
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
    pb_vstoren(pb_dop(f, logK, fd), at, out);
}

__kernel void brdf_outer_vec(__global PB_SCALAR *out, PB_OUTER_VEC_ARGS)
{
    PB_OUTER_VEC_BODY
    pb_vstoren(pb_brdf(f, logK, fd), at, out);
}

#endif  /* PB_VECTOR_REAL */
