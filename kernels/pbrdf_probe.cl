/*
 * pbrdf_probe.cl -- the device probe: is this driver able to build and run pbrdf.h?
 *
 * One work-item per point; each point is 9 consecutive inputs (theta_i, theta_r, phi in degrees,
 * n, k, sigma, ks, kd, c); out = the DOP with the paper's shadowing.  The host compares the result
 * with SPEC's check values (pbrdf_cl.engine.probe).  Build options as for every program:
 * -DPBRDF_DOUBLE for float64.
 */
#include "pbrdf.h"

__kernel void pbrdf_probe(__global real *out, __global const real *p, const int n)
{
    const int i = get_global_id(0);
    if (i >= n) return;
    __global const real *q = p + 9 * i;
    pb_geom g = pb_geometry(q[0], q[1], q[2]);
    pb_fresnel_t f = pb_fresnel(q[3], q[4], g.cb, g.sb);
    const real G = pb_shadowing_factor(g, q[5], PB_SHADOW_PAPER);
    out[i] = pb_dop(f, pb_log_specular_scale(g, q[5], q[6], G), pb_diffuse(g, q[7], q[8]));
}
