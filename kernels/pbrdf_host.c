/*
 * pbrdf_host.c -- pbrdf.h compiled as C on the host, for the benchmark's limits (scripts/bench.py):
 * the same DOP as the per-point kernels, in an OpenMP loop the C compiler vectorises, and a stream
 * loop that moves the same bytes without computing (the memory roofline).  Not part of the
 * library's computation.  Build (pbrdf_cl.bench does it on the fly):
 *   cc -O3 -march=native -ffast-math -fno-associative-math -fno-finite-math-only -fopenmp -shared -fPIC
 *      [-DPBRDF_DOUBLE] -I <kernels> pbrdf_host.c
 * (-fno-associative-math keeps pb_math.h's (x + 2^23) - 2^23 rounding; -fno-finite-math-only its
 * infinities.)
 */
#include <math.h>
#include <string.h>

#define __global
#define __constant const
#define __kernel
#define PB_HOST_C 1

static inline int pb_c_as_int(float x) { int i; memcpy(&i, &x, sizeof i); return i; }
static inline float pb_c_as_float(int i) { float x; memcpy(&x, &i, sizeof x); return x; }
static inline long pb_c_as_long(double x) { long i; memcpy(&i, &x, sizeof i); return i; }
static inline double pb_c_as_double(long i) { double x; memcpy(&x, &i, sizeof x); return x; }
#define as_int pb_c_as_int
#define as_float pb_c_as_float
#define as_long pb_c_as_long
#define as_double pb_c_as_double
#ifdef PBRDF_DOUBLE
static inline double pb_c_sincos(double x, double *c) { *c = cos(x); return sin(x); }
#else
static inline float pb_c_sincos(float x, float *c) { *c = cosf(x); return sinf(x); }
#endif
#define sincos pb_c_sincos  /* OpenCL's sincos returns the sine */
#define inline static inline
#include "pbrdf.h"
#undef inline

/* DOP of n points (paper shadowing), as dop_points computes it. */
void pb_host_dop(long n, const real *ti, const real *tr, const real *ph, const real *nn, const real *kk,
                 const real *sg, const real *ks, const real *kd, const real *cc, real *out)
{
    #pragma omp parallel for simd schedule(static)
    for (long i = 0; i < n; i++) {
        pb_geom g = pb_geometry(ti[i], tr[i], ph[i]);
        pb_fresnel_t f = pb_fresnel(nn[i], kk[i], g.cb, g.sb);
        const real G = pb_shadowing_factor(g, sg[i], PB_SHADOW_PAPER);
        out[i] = pb_dop(f, pb_log_specular_scale(g, sg[i], ks[i], G), pb_diffuse(g, kd[i], cc[i]));
    }
}

/* The memory traffic of a path without its arithmetic: read nin arrays of n values, write one. */
void pb_host_stream(long n, int nin, const real *const *in, real *out)
{
    #pragma omp parallel for simd schedule(static)
    for (long i = 0; i < n; i++) {
        real s = (real)0;
        for (int k = 0; k < nin; k++)
            s += in[k][i];
        out[i] = s;
    }
}
