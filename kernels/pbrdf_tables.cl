/*
 * pbrdf_tables.cl -- the factors of the model that depend on few inputs, tabulated once.
 *
 * DOP = diff / (sum + fd2 * inv_K) and F00 = K sum / 2 + fd separate into
 *   Fresnel:  sum = Rs + Rp, diff = Rs - Rp       over (geometry, n, k)
 *   scale:    exp(sign * log K)                   over (geometry, sigma, ks)
 *   diffuse:  factor * fd                         over (geometry, kd, c)
 * Geometry is an explicit list of ng (theta_i, theta_r, phi) triples in degrees.  Each table is
 * written as out[ig * s_g + ip * s_p] for geometry ig and parameter pair ip = i_first * n2 + i_second;
 * global size (ng, n1 * n2).  Build options: -DPBRDF_DOUBLE, -DPBRDF_SHADOWING.
 */
#include "pbrdf.h"

#ifndef PBRDF_SHADOWING
#define PBRDF_SHADOWING PB_SHADOW_PAPER
#endif

#define PB_TABLE_ARGS                                                        \
    const int ng, const int s_g, const int s_p,                              \
    __global const real *ti, __global const real *tr, __global const real *ph, \
    __global const real *p1, __global const real *p2, const int n2

__kernel void fresnel_table(__global real *sum, __global real *diff, PB_TABLE_ARGS)
{
    const int ig = get_global_id(0), ip = get_global_id(1);
    if (ig >= ng) return;
    pb_geom g = pb_geometry(ti[ig], tr[ig], ph[ig]);
    pb_fresnel_t f = pb_fresnel(p1[ip / n2], p2[ip % n2], g.cb, g.sb);
    sum[ig * s_g + ip * s_p] = f.Rs + f.Rp;
    diff[ig * s_g + ip * s_p] = f.diff;
}

/* sign = -1 gives 1/K (for the DOP), +1 gives K (for F00). */
__kernel void scale_table(__global real *out, PB_TABLE_ARGS, const real sign)
{
    const int ig = get_global_id(0), ip = get_global_id(1);
    if (ig >= ng) return;
    pb_geom g = pb_geometry(ti[ig], tr[ig], ph[ig]);
    const real sigma = p1[ip / n2];
    const real G = pb_shadowing_factor(g, sigma, PBRDF_SHADOWING);
    out[ig * s_g + ip * s_p] = exp(sign * pb_log_specular_scale(g, sigma, p2[ip % n2], G));
}

/* factor = 2 gives fd2 (for the DOP), 1 gives fd (for F00). */
__kernel void diffuse_table(__global real *out, PB_TABLE_ARGS, const real factor)
{
    const int ig = get_global_id(0), ip = get_global_id(1);
    if (ig >= ng) return;
    pb_geom g = pb_geometry(ti[ig], tr[ig], ph[ig]);
    out[ig * s_g + ip * s_p] = factor * pb_diffuse(g, p1[ip / n2], p2[ip % n2]);
}

/* The outgoing frame's rotation (C, S) = (cos 2 psi, sin 2 psi) per geometry (pb_out_rotation2):
 * out[2 ig], out[2 ig + 1]; global size (ng). */
__kernel void frame_table(__global real *out, const int ng, __global const real *ti, __global const real *tr,
                          __global const real *ph)
{
    const int ig = get_global_id(0);
    if (ig >= ng) return;
    real S;
    const real C = pb_out_rotation2(pb_geometry(ti[ig], tr[ig], ph[ig]), ph[ig], &S);
    out[2 * ig] = C;
    out[2 * ig + 1] = S;
}

/* The terms (tn, td) of polarimetric channels (pb_channel_terms of pbrdf.h) over (channel, n, k):
 * channel ig at geometry (ti, tr, ph)[ig] with incident vectors u[4 ig ..], v[4 ig ..], output
 * component comp[ig] and kind kind[ig]; written as tn/td[ig * s_g + ip * s_p]. */
__kernel void channel_table(__global real *tn, __global real *td, PB_TABLE_ARGS, __global const real *u,
                            __global const real *v, __global const int *comp, __global const int *kind)
{
    const int ig = get_global_id(0), ip = get_global_id(1);
    if (ig >= ng) return;
    pb_geom g = pb_geometry(ti[ig], tr[ig], ph[ig]);
    pb_fresnel_t f = pb_fresnel(p1[ip / n2], p2[ip % n2], g.cb, g.sb);
    real m[16], d;
    pb_mueller_at(f, pb_frame_rotations(g, ph[ig]), (real)1, (real)0, m);
    const real uu[4] = {u[4 * ig], u[4 * ig + 1], u[4 * ig + 2], u[4 * ig + 3]};
    const real vv[4] = {v[4 * ig], v[4 * ig + 1], v[4 * ig + 2], v[4 * ig + 3]};
    const real t = pb_channel_terms(m, uu, vv, comp[ig], kind[ig], &d);
    tn[ig * s_g + ip * s_p] = t;
    td[ig * s_g + ip * s_p] = d;
}
