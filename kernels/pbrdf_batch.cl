/*
 * pbrdf_batch.cl -- per-pixel inversion of image stacks (pbrdf_cl/batch.py): the coarse grid
 * stage and the bounded Levenberg-Marquardt stage, for many pixels at once.
 *
 * Pixels are the fastest index of every per-pixel array, padded to a multiple of the vector
 * width: x[m * P + p] for measurement m of pixel p (P the padded count).  Padding pixels have
 * weight 0.  No physics here: everything model-related calls kernels/pbrdf.h.
 *
 * Grid stage (built without PB_VECTOR_REAL; PB_VW pixels per work-item as realv lanes): the
 * weighted SSE of every pixel at every grid point, reduced on the device to the minimum (and
 * its grid point) of each region of the grid; a region is a contiguous range [rstart[r],
 * rstart[r+1]) of the region-ordered grid points.
 *   batch_grid_table   shared geometry: the DOP table T[q * M + m] of grid point q at
 *                      measurement m, computed once; SSE = c + sum_m (b_m T - 2 a_m) T with
 *                      a = w dop, b = w, c = sum w dop^2 per pixel (a product of the table with
 *                      the pixels' data: no model evaluation per pixel).
 *   batch_grid_factors per-pixel geometry: the factor tables of pbrdf_tables.cl for the geometry
 *                      list m * P + p, laid out table[param * (M P) + m * P + p], combined per
 *                      pixel and grid point (pb_dop_combine); grid point q is order[q], decoded
 *                      as (nk * PB_NM + s) * PB_NI + j.
 * Polarimetric channels (pbrdf_cl.model.measurables: s1, s2, s3, Mueller elements, DOP, AoP under
 * any incident state; one channel = one number measured at one measurement index, C per pixel):
 *   batch_channel_values  shared geometry and incident states: the value table T[q * C + c] of
 *                      every grid point q (region order) and channel c, from compute.channels' tables
 *                      (pb_channel_combine), computed once;
 *   batch_grid_channels   each pixel's sum_c w_c r_c^2 over T, r = pb_channel_residual (an AoP's
 *                      wrapped modulo 180 degrees, so not the product form of batch_grid_table);
 *   batch_grid_channel_factors  per-pixel geometry or incident states: channel_table, scale_table
 *                      (1/K) and diffuse_table (fd) of pbrdf_tables.cl for the list c * P + p, laid
 *                      out as batch_grid_factors' tables, combined per pixel and grid point.
 *
 * LM stage (built with -DPB_VECTOR_REAL=N: N problems per work-item as the lanes of real):
 *   batch_lm           from a start per problem (problem = start slot * P + pixel), a bounded
 *                      Levenberg-Marquardt descent mirroring pbrdf_cl.inversion._lm_batch: damping
 *                      in coordinates scaled to the bounds, coordinates on a bound whose descent
 *                      points outwards held, steps projected onto the bounds, forward-difference
 *                      Jacobians (each column recomputes only the factor its parameter enters).
 *   Build options: PB_D free parameters; PB_X_N, PB_X_K, PB_X_SIGMA, PB_X_KD, PB_X_C, PB_X_KS the
 *   slot of each parameter in x (-1: fixed at base[]; PB_BASE_ROWS: at base[i * P + pixel], each
 *   pixel's own fixed values); PB_INTENSITY adds the F00 residuals
 *   (then kd in x is kd/ks and ks enters x as log ks); PB_PIXEL_GEOMETRY reads the geometry table
 *   per pixel instead of shared (pb_geom_at); PB_GEODESIC the geodesic acceleration; PB_LOG_N, PB_LOG_K,
 *   PB_LOG_KD: x holds log(n - 1), log k, log kd instead of n, k, kd (a corner's coordinates:
 *   pbrdf_cl.batch.CORNERS); PBRDF_SHADOWING.  PB_CHANNELS: the residuals are M polarimetric channels
 *   instead of M DOP values (pb_channel_terms, pb_channel_combine, pb_channel_residual: an AoP's
 *   residuals and differences wrapped): the geometry table then also holds each channel's frame
 *   rotations and its incident and normalising vectors u, v (rows 7..18, see pb_chan_at), and
 *   chan[5 m ..] its component, kind and coefficients a, b, c (the same for every pixel).
 */
#include "pbrdf.h"

#ifndef PBRDF_SHADOWING
#define PBRDF_SHADOWING PB_SHADOW_PAPER
#endif

#ifndef PB_VECTOR_REAL

/* The grid kernels' sums are written a * b + c, which the compiler contracts into one fused
 * multiply-add (the pragma; OpenCL C's default too), bit for bit fma(a, b, c): PoCL 3.0 (LLVM 14,
 * the PyPI wheel) calls the fma() builtin on float8 out of its library, 4-5 times slower than the
 * contracted instruction (scripts/bench_batch.py --only profile), where PoCL 3.1 inlines both. */
#pragma OPENCL FP_CONTRACT ON

/* Grid points per tile of batch_grid_table: each measurement's data are loaded once per tile. */
#define PB_TILE 4

__kernel void batch_grid_table(__global real *best, __global real *arg, const int P, const int M,
                               __global const real *T, __global const int *rstart, const int R,
                               __global const real *a2, __global const real *b, __global const real *c)
{
    const int p0 = get_global_id(0) * PB_VW;
    if (p0 >= P) return;
    const realv cc = pb_vload(0, c + p0);
    for (int r = 0; r < R; r++) {
        realv bs = (realv)INFINITY, bq = (realv)0;
        const int q1 = rstart[r + 1];
        for (int q0 = rstart[r]; q0 < q1; q0 += PB_TILE) {
            realv acc[PB_TILE];
            __global const real *t[PB_TILE];
            for (int u = 0; u < PB_TILE; u++) {
                acc[u] = cc;
                t[u] = T + (size_t)min(q0 + u, q1 - 1) * M;  /* clamped: the last tile re-reads */
            }
            for (int m = 0; m < M; m++) {
                const realv bm = pb_vload(0, b + m * P + p0), am = pb_vload(0, a2 + m * P + p0);
                /* a2 = -2 w dop: acc += (w T - 2 w dop) T */
                for (int u = 0; u < PB_TILE; u++) {
                    const realv tm = (realv)t[u][m];
                    acc[u] = (bm * tm + am) * tm + acc[u];  /* two FMAs (FP_CONTRACT, above) */
                }
            }
            for (int u = 0; u < PB_TILE && q0 + u < q1; u++) {
                const realv q_ = (realv)(real)(q0 + u);
                bq = acc[u] < bs ? q_ : bq;
                bs = acc[u] < bs ? acc[u] : bs;
            }
        }
        pb_vstore(bs, 0, best + r * P + p0);
        pb_vstore(bq, 0, arg + r * P + p0);
    }
}

__kernel void batch_grid_channels(__global real *best, __global real *arg, const int P, const int C,
                                  __global const real *T, __global const int *rstart, const int R,
                                  __global const real *obs, __global const real *w, __global const int *aop)
{
    const int p0 = get_global_id(0) * PB_VW;
    if (p0 >= P) return;
    for (int r = 0; r < R; r++) {
        realv bs = (realv)INFINITY, bq = (realv)0;
        const int q1 = rstart[r + 1];
        for (int q0 = rstart[r]; q0 < q1; q0 += PB_TILE) {
            realv acc[PB_TILE];
            __global const real *t[PB_TILE];
            for (int u = 0; u < PB_TILE; u++) {
                acc[u] = (realv)0;
                t[u] = T + (size_t)min(q0 + u, q1 - 1) * C;  /* clamped: the last tile re-reads */
            }
            for (int c = 0; c < C; c++) {
                const realv wc = pb_vload(0, w + c * P + p0), oc = pb_vload(0, obs + c * P + p0);
                const int is_aop = aop[c];
                for (int u = 0; u < PB_TILE; u++) {
                    const realv res = pb_channel_residual_v((realv)t[u][c], oc, is_aop);
                    acc[u] = wc * res * res + acc[u];
                }
            }
            for (int u = 0; u < PB_TILE && q0 + u < q1; u++) {
                const realv q_ = (realv)(real)(q0 + u);
                bq = acc[u] < bs ? q_ : bq;
                bs = acc[u] < bs ? acc[u] : bs;
            }
        }
        pb_vstore(bs, 0, best + r * P + p0);
        pb_vstore(bq, 0, arg + r * P + p0);
    }
}

/* Global size (G, C): T[q * C + c] of grid point q (region order: order[q], decoded as in
 * batch_grid_factors over nm (sigma, ks) pairs and ni (kd, c) pairs, given at run time: one program
 * for every grid) and channel c, from the tables tn/td[c * nnk + nk], 1/K as scale[c * nm + s], fd as
 * dif[c * ni + j]. */
__kernel void batch_channel_values(__global real *T, const int G, const int C, __global const int *order,
                                   const int nnk, const int nm, const int ni,
                                   __global const real *tn, __global const real *td, __global const real *scale,
                                   __global const real *dif, __global const real *abc, __global const int *aop)
{
    const int q = get_global_id(0), c = get_global_id(1);
    if (q >= G || c >= C) return;
    const int gp = order[q];
    const int j = gp % ni, s = (gp / ni) % nm, nk = gp / (ni * nm);
    T[(size_t)q * C + c] = pb_channel_combine(tn[c * nnk + nk], td[c * nnk + nk], scale[c * nm + s],
                                              dif[c * ni + j], abc[3 * c], abc[3 * c + 1], abc[3 * c + 2], aop[c]);
}

#ifdef PB_NI
__kernel void batch_grid_factors(__global real *best, __global real *arg, const int P, const int M,
                                 __global const real *sum, __global const real *diff,
                                 __global const real *scale, __global const real *dif,
                                 __global const int *order, __global const int *rstart, const int R,
                                 __global const real *obs, __global const real *w)
{
    const int p0 = get_global_id(0) * PB_VW;
    if (p0 >= P) return;
    const int ng = M * P;
    for (int r = 0; r < R; r++) {
        realv bs = (realv)INFINITY, bq = (realv)0;
        for (int q = rstart[r]; q < rstart[r + 1]; q++) {
            const int gp = order[q];
            const int j = gp % PB_NI, s = (gp / PB_NI) % PB_NM, nk = gp / (PB_NI * PB_NM);
            __global const real *su = sum + (size_t)nk * ng + p0, *di = diff + (size_t)nk * ng + p0;
            __global const real *sc = scale + (size_t)s * ng + p0, *fd = dif + (size_t)j * ng + p0;
            realv acc = (realv)0;
            for (int m = 0; m < M; m++) {
                const int o = m * P;
                const realv res = pb_dop_combine_v(pb_vload(0, su + o), pb_vload(0, di + o), pb_vload(0, fd + o),
                                                   pb_vload(0, sc + o)) - pb_vload(0, obs + o + p0);
                acc = pb_vload(0, w + o + p0) * res * res + acc;
            }
            const realv q_ = (realv)(real)q;
            /* a NaN sum never wins: acc < bs is false */
            bq = acc < bs ? q_ : bq;
            bs = acc < bs ? acc : bs;
        }
        pb_vstore(bs, 0, best + r * P + p0);
        pb_vstore(bq, 0, arg + r * P + p0);
    }
}

__kernel void batch_grid_channel_factors(__global real *best, __global real *arg, const int P, const int C,
                                         __global const real *tn, __global const real *td,
                                         __global const real *scale, __global const real *dif,
                                         __global const int *order, __global const int *rstart, const int R,
                                         __global const real *obs, __global const real *w,
                                         __global const real *abc, __global const int *aop)
{
    const int p0 = get_global_id(0) * PB_VW;
    if (p0 >= P) return;
    const int ng = C * P;
    for (int r = 0; r < R; r++) {
        realv bs = (realv)INFINITY, bq = (realv)0;
        for (int q = rstart[r]; q < rstart[r + 1]; q++) {
            const int gp = order[q];
            const int j = gp % PB_NI, s = (gp / PB_NI) % PB_NM, nk = gp / (PB_NI * PB_NM);
            __global const real *n_ = tn + (size_t)nk * ng + p0, *d_ = td + (size_t)nk * ng + p0;
            __global const real *sc = scale + (size_t)s * ng + p0, *fd = dif + (size_t)j * ng + p0;
            realv acc = (realv)0;
            for (int c = 0; c < C; c++) {
                const int o = c * P;
                const int is_aop = aop[c];
                const realv v = pb_channel_combine_v(pb_vload(0, n_ + o), pb_vload(0, d_ + o), pb_vload(0, sc + o),
                                                     pb_vload(0, fd + o), abc[3 * c], abc[3 * c + 1], abc[3 * c + 2],
                                                     is_aop);
                const realv res = pb_channel_residual_v(v, pb_vload(0, obs + o + p0), is_aop);
                acc = pb_vload(0, w + o + p0) * res * res + acc;
            }
            const realv q_ = (realv)(real)q;
            bq = acc < bs ? q_ : bq;
            bs = acc < bs ? acc : bs;
        }
        pb_vstore(bs, 0, best + r * P + p0);
        pb_vstore(bq, 0, arg + r * P + p0);
    }
}
#endif

#else /* PB_VECTOR_REAL: the LM stage */

#define PB_N PB_VECTOR_REAL
/* the N lanes read and written with pbrdf.h's pb_vl / pb_vs */
typedef PB_SCALAR scalar;

#ifdef PBRDF_DOUBLE
#define PB_EPS_SQRT ((real)1.4901161193847656e-08)
#define PB_HUGE ((real)1e300)
#define PB_TINY ((real)1e-300)
#else
#define PB_EPS_SQRT ((real)3.4526698e-04f)
#define PB_HUGE ((real)1e30f)
#define PB_TINY ((real)1e-30f)
#endif

#ifndef PB_X_KS
#define PB_X_KS -1
#endif
/* parameter value: x[slot] when free, else the base value */
#define PB_SLOT(s) ((s) >= 0 ? (s) : 0)
#define PB_PAR(s, fixed) ((s) >= 0 ? x[PB_SLOT(s)] : (real)(fixed))
/* the fixed parameters' values: base[i] (i = n, k, sigma, ks, kd, c), the same for every problem, or
 * with PB_BASE_ROWS base[i * P + p] per pixel (the lanes' pixels p0 ..; the problems of several
 * held values in one launch: the label stage's candidates) */
#ifdef PB_BASE_ROWS
#define PB_BASE(i) pb_vl(0, base + (size_t)(i) * P + p0)
#else
#define PB_BASE(i) ((real)base[i])
#endif

typedef struct {
    real n, k, sigma, ks, kd, c;  /* kd absolute (kd/ks times ks with intensities) */
} pb_par;

inline pb_par pb_params(const real *x, __global const scalar *base, const int P, const int p0)
{
    pb_par p;
    p.n = PB_PAR(PB_X_N, PB_BASE(0));
    p.k = PB_PAR(PB_X_K, PB_BASE(1));
    p.sigma = PB_PAR(PB_X_SIGMA, PB_BASE(2));
    p.ks = PB_X_KS >= 0 ? exp(x[PB_SLOT(PB_X_KS)]) : PB_BASE(3);
    p.kd = PB_PAR(PB_X_KD, PB_BASE(4));
    p.c = PB_PAR(PB_X_C, PB_BASE(5));
/* a corner's coordinates (the descent along its valley): log(n - 1), log k, log kd/ks */
#ifdef PB_LOG_N
    p.n = (real)1 + exp(p.n);
#endif
#ifdef PB_LOG_K
    p.k = exp(p.k);
#endif
#ifdef PB_LOG_KD
    p.kd = exp(p.kd);
#endif
#ifdef PB_INTENSITY
    p.kd = p.kd * p.ks;
#endif
    return p;
}

/* The geometry (pb_geometry's values) of measurement m, from a table computed once (the host's
 * reference.geometry, which mirrors it): geo[c * M + m] for shared geometry, geo[(c * M + m) * P
 * + p] per pixel (PB_PIXEL_GEOMETRY: the lanes' pixels p0 ..), c = cti, sti, ctr, str, cb, sb,
 * tan2a.  A descent evaluates every measurement's model dozens of times; its geometry never changes. */
inline pb_geom pb_geom_at(__global const scalar *geo, const int m, const int p0, const int M, const int P)
{
#ifdef PB_PIXEL_GEOMETRY
#define PB_G(c) pb_vl(0, geo + ((size_t)(c) * M + m) * P + p0)
#else
#define PB_G(c) ((real)geo[(c) * M + m])
#endif
    pb_geom g;
    g.cti = PB_G(0); g.sti = PB_G(1); g.ctr = PB_G(2); g.str = PB_G(3);
    g.cb = PB_G(4); g.sb = PB_G(5); g.tan2a = PB_G(6);
#undef PB_G
    return g;
}

#ifdef PB_CHANNELS
/* A polarimetric channel of the descent: its incident and normalising vectors (per pixel where the
 * geometry is), component, kind (uniform: the same for every lane) and coefficients. */
typedef struct {
    real u[4], v[4];
    int comp, kind, aop;
    scalar a, b, c;  /* pb_channel_combine's coefficients: uniform */
} pb_chan;

/* Channel m's outgoing and incoming frame rotations (rows 7..10 of the geometry table: ci, si, co,
 * so of pb_frame_rotations, from the host's reference.frame_rotations), its vectors u and v (rows
 * 11..14, 15..18) and chan[5 m ..] = comp, kind, a, b, c. */
#ifdef PB_PIXEL_GEOMETRY
#define PB_G(c) pb_vl(0, geo + ((size_t)(c) * M + m) * P + p0)
#else
#define PB_G(c) ((real)geo[(c) * M + m])
#endif
inline pb_frames pb_frames_at(__global const scalar *geo, const int m, const int p0, const int M, const int P)
{
    pb_frames fr;
    fr.ci = PB_G(7); fr.si = PB_G(8); fr.co = PB_G(9); fr.so = PB_G(10);
    return fr;
}

inline pb_chan pb_chan_at(__global const scalar *geo, __global const scalar *chan, const int m, const int p0,
                          const int M, const int P)
{
    pb_chan ch;
    for (int j = 0; j < 4; j++) {
        ch.u[j] = PB_G(11 + j);
        ch.v[j] = PB_G(15 + j);
    }
    ch.comp = (int)chan[5 * m];
    ch.kind = (int)chan[5 * m + 1];
    ch.aop = ch.kind == PB_CHANNEL_AOP;
    ch.a = (scalar)chan[5 * m + 2];
    ch.b = (scalar)chan[5 * m + 3];
    ch.c = (scalar)chan[5 * m + 4];
    return ch;
}
#undef PB_G

/* The channel's terms (tn, *td) of P = R_out M^s R_in per unit K (pb_mueller_at, pb_channel_terms). */
inline real pb_chan_terms(pb_fresnel_t f, pb_frames fr, const pb_chan *ch, real *td)
{
    real m[16];
    pb_mueller_at(f, fr, (real)1, (real)0, m);
    return pb_channel_terms(m, ch->u, ch->v, ch->comp, ch->kind, td);
}

/* The channel's value from its terms, 1/K and fd (pb_channel_combine). */
inline real pb_chan_value(const pb_chan *ch, real tn, real td, real inv_K, real fd)
{
    return pb_channel_combine(tn, td, inv_K, fd, ch->a, ch->b, ch->c, ch->aop);
}
#endif

/* Residuals (DOP, and F00 with intensities) of one measurement and their forward differences
 * along each free parameter, accumulated into sse, A = J^T J (row-major PB_D x PB_D), gr = J^T r. */
inline void pb_accumulate(real res, const real *col, real *sse, real *A, real *gr)
{
    *sse += res * res;
    for (int i = 0; i < PB_D; i++) {
        gr[i] += col[i] * res;
        for (int j = 0; j <= i; j++)
            A[i * PB_D + j] += col[i] * col[j];
    }
}

#ifndef PB_NQ
#define PB_NQ 1
#endif

/* Evaluate the weighted residuals at x (and the Jacobian's normal equations) for the lanes'
 * problems; h: the forward steps in x (internal coordinates). */
inline void pb_evaluate(const real *x, const real *h, __global const scalar *base,
                        __global const scalar *geo,
                        __global const scalar *obs, __global const scalar *w,
                        __global const scalar *fobs, __global const scalar *fw,
                        const int P, const int M, const int p0, real *sse, real *A, real *gr,
                        __global scalar *rows, const int Q, const int q0, __global const scalar *chan)
{
    *sse = (real)0;
    for (int i = 0; i < PB_D; i++) {
        gr[i] = (real)0;
        for (int j = 0; j < PB_D; j++)
            A[i * PB_D + j] = (real)0;
    }
    const pb_par p = pb_params(x, base, P, p0);
    /* the parameters one step along each free coordinate */
    real xs[PB_D];
    pb_par ps[PB_D];
    for (int i = 0; i < PB_D; i++) {
        for (int j = 0; j < PB_D; j++)
            xs[j] = x[j] + (i == j ? h[j] : (real)0);
        ps[i] = pb_params(xs, base, P, p0);
    }
#ifdef PB_CHANNELS
    /* M polarimetric channels in groups of PB_NQ consecutive channels at one geometry (the quantities
     * measured at one measurement): per group the geometry's factors and P = R_out M^s R_in once (and
     * once per column that moves n or k), per channel its terms and value, the forward differences
     * of its wrapped residual (an AoP's) along each free parameter.  (Written here, not as a function
     * of ps: Oclgrind cannot create the kernel with one.) */
    for (int m0 = 0; m0 < M; m0 += PB_NQ) {
        const pb_geom g = pb_geom_at(geo, m0, p0, M, P);
        const pb_frames fr = pb_frames_at(geo, m0, p0, M, P);
        const pb_fresnel_t f = pb_fresnel(p.n, p.k, g.cb, g.sb);
        const real logK = pb_log_specular_scale(g, p.sigma, p.ks, pb_shadowing_factor(g, p.sigma, PBRDF_SHADOWING));
        const real inv_K = pb_exp(-logK), mn = pb_minnaert(g, p.c);
        const real fd = pb_diffuse_of(p.kd, mn);
        real P0[16];
        pb_mueller_at(f, fr, (real)1, (real)0, P0);
        /* per channel of the group (its pb_chan read again where it is needed) */
        real sw[PB_NQ], tn0[PB_NQ], td0[PB_NQ], v0[PB_NQ], col[PB_NQ * PB_D];
        for (int j = 0; j < PB_NQ; j++) {
            const pb_chan ch = pb_chan_at(geo, chan, m0 + j, p0, M, P);
            sw[j] = pb_sqrt(pb_vl(0, w + (m0 + j) * P + p0));
            tn0[j] = pb_channel_terms(P0, ch.u, ch.v, ch.comp, ch.kind, &td0[j]);
            v0[j] = pb_chan_value(&ch, tn0[j], td0[j], inv_K, fd);
        }
        for (int i = 0; i < PB_D; i++) {
            const pb_par q = ps[i];
            /* only the factors the moved parameter enters are recomputed */
            const int moves_f = i == PB_X_N || i == PB_X_K;
            const int moves_s = i == PB_X_SIGMA || i == PB_X_KS;
            const real inv_Ki = moves_s ? pb_exp(-pb_log_specular_scale(g, q.sigma, q.ks,
                                                                          pb_shadowing_factor(g, q.sigma,
                                                                                              PBRDF_SHADOWING)))
                                        : inv_K;
            const real fdi = i == PB_X_C ? pb_diffuse(g, q.kd, q.c)
                                         : ((i == PB_X_KD || i == PB_X_KS) ? pb_diffuse_of(q.kd, mn) : fd);
            real Pi[16];
            if (moves_f)
                pb_mueller_at(pb_fresnel(q.n, q.k, g.cb, g.sb), fr, (real)1, (real)0, Pi);
            for (int j = 0; j < PB_NQ; j++) {
                const pb_chan ch = pb_chan_at(geo, chan, m0 + j, p0, M, P);
                real tni = tn0[j], tdi = td0[j];
                if (moves_f)
                    tni = pb_channel_terms(Pi, ch.u, ch.v, ch.comp, ch.kind, &tdi);
                col[j * PB_D + i] = sw[j] * pb_channel_residual(pb_chan_value(&ch, tni, tdi, inv_Ki, fdi), v0[j],
                                                                ch.aop) / h[i];
            }
        }
        for (int j = 0; j < PB_NQ; j++) {
            const int m = m0 + j;
            const int aop = (int)chan[5 * m + 1] == PB_CHANNEL_AOP;
            const real res0 = sw[j] * pb_channel_residual(v0[j], pb_vl(0, obs + m * P + p0), aop);
            pb_accumulate(res0, col + j * PB_D, sse, A, gr);
#ifdef PB_GEODESIC
            /* this channel's Jacobian row and residual, for the geodesic acceleration */
            for (int i = 0; i < PB_D; i++)
                pb_vs(col[j * PB_D + i], 0, rows + (size_t)(m * (PB_D + 1) + i) * PB_N);
            pb_vs(res0, 0, rows + (size_t)(m * (PB_D + 1) + PB_D) * PB_N);
#endif
        }
    }
#else
    for (int m = 0; m < M; m++) {
        const int o = m * P + p0;
        const pb_geom g = pb_geom_at(geo, m, p0, M, P);
        const real sw = pb_sqrt(pb_vl(0, w + o));
        const pb_fresnel_t f = pb_fresnel(p.n, p.k, g.cb, g.sb);
        const real logK = pb_log_specular_scale(g, p.sigma, p.ks, pb_shadowing_factor(g, p.sigma, PBRDF_SHADOWING));
        /* 1/K and the Minnaert factor, shared by the columns that do not move them */
        const real inv_K = pb_exp(-logK), mn = pb_minnaert(g, p.c);
        const real fd = pb_diffuse_of(p.kd, mn);
        const real dop0 = pb_dop_at(f, inv_K, fd);
        real col[PB_D];
#ifdef PB_INTENSITY
        const real swf = pb_sqrt(pb_vl(0, fw + o));
        const real f000 = pb_brdf(f, logK, fd);
        real fcol[PB_D];
#endif
        for (int i = 0; i < PB_D; i++) {
            const pb_par q = ps[i];
            /* only the factors the moved parameter enters are recomputed */
            const int moves_f = i == PB_X_N || i == PB_X_K;
            const int moves_s = i == PB_X_SIGMA || i == PB_X_KS;
            const pb_fresnel_t fi = moves_f ? pb_fresnel(q.n, q.k, g.cb, g.sb) : f;
            const real logKi = moves_s ? pb_log_specular_scale(g, q.sigma, q.ks,
                                                                pb_shadowing_factor(g, q.sigma, PBRDF_SHADOWING))
                                       : logK;
            const real inv_Ki = moves_s ? pb_exp(-logKi) : inv_K;
            const real fdi = i == PB_X_C ? pb_diffuse(g, q.kd, q.c)
                                         : ((i == PB_X_KD || i == PB_X_KS) ? pb_diffuse_of(q.kd, mn) : fd);
            col[i] = sw * (pb_dop_at(fi, inv_Ki, fdi) - dop0) / h[i];
#ifdef PB_INTENSITY
            fcol[i] = swf * (pb_brdf(fi, logKi, fdi) - f000) / h[i];
#endif
        }
        pb_accumulate(sw * (dop0 - pb_vl(0, obs + o)), col, sse, A, gr);
#ifdef PB_GEODESIC
        /* this point's Jacobian row and residual, for the geodesic acceleration */
        for (int i = 0; i < PB_D; i++)
            pb_vs(col[i], 0, rows + (size_t)(m * (PB_D + 1) + i) * PB_N);
        pb_vs(sw * (dop0 - pb_vl(0, obs + o)), 0, rows + (size_t)(m * (PB_D + 1) + PB_D) * PB_N);
#endif
#ifdef PB_INTENSITY
        pb_accumulate(swf * (f000 - pb_vl(0, fobs + o)), fcol, sse, A, gr);
#endif
    }
#endif
    for (int i = 0; i < PB_D; i++)
        for (int j = i + 1; j < PB_D; j++)
            A[i * PB_D + j] = A[j * PB_D + i];
    /* non-finite residuals lose against any finite point (as _finite does for the host stages) */
    *sse = isfinite(*sse) ? *sse : PB_HUGE;
}

#ifdef PB_GEODESIC
/* Geodesic acceleration (Transtrum and Sethna 2012): b = J_s^T r_vv at x, the residuals' second
 * directional derivative along the step du (coordinates scaled to the bounds) from a finite
 * difference at x + hv du: r_vv = 2 (r(x + hv du) - r - hv J_s du) / hv^2, with the Jacobian rows
 * and residuals of x that pb_evaluate stored in rows. */
inline void pb_accel_rhs(const real *x, const real *du, const real *span, const real hv,
                         __global const scalar *lo, __global const scalar *hi, __global const scalar *base,
                         __global const scalar *geo,
                         __global const scalar *obs, __global const scalar *w,
                         const int P, const int M, const int p0, __global const scalar *rows, const int Q,
                         const int q0, real *b, __global const scalar *chan)
{
    real xv[PB_D];
    for (int i = 0; i < PB_D; i++) {
        xv[i] = clamp(x[i] + hv * du[i] * span[i], (real)lo[i], (real)hi[i]);
        b[i] = (real)0;
    }
    const pb_par p = pb_params(xv, base, P, p0);
    for (int m = 0; m < M; m++) {
        const int o = m * P + p0;
        const pb_geom g = pb_geom_at(geo, m, p0, M, P);
        const pb_fresnel_t f = pb_fresnel(p.n, p.k, g.cb, g.sb);
        const real logK = pb_log_specular_scale(g, p.sigma, p.ks, pb_shadowing_factor(g, p.sigma, PBRDF_SHADOWING));
#ifdef PB_CHANNELS
        const pb_chan ch = pb_chan_at(geo, chan, m, p0, M, P);
        real td;
        const real tn = pb_chan_terms(f, pb_frames_at(geo, m, p0, M, P), &ch, &td);
        const real rv = pb_sqrt(pb_vl(0, w + o)) * pb_channel_residual(
            pb_chan_value(&ch, tn, td, pb_exp(-logK), pb_diffuse(g, p.kd, p.c)), pb_vl(0, obs + o), ch.aop);
#else
        const real rv = pb_sqrt(pb_vl(0, w + o)) * (pb_dop(f, logK, pb_diffuse(g, p.kd, p.c)) - pb_vl(0, obs + o));
#endif
        real jrow[PB_D], jdu = (real)0;
        for (int i = 0; i < PB_D; i++) {
            jrow[i] = pb_vl(0, rows + (size_t)(m * (PB_D + 1) + i) * PB_N) * span[i];
            jdu += jrow[i] * du[i];
        }
        const real r0 = pb_vl(0, rows + (size_t)(m * (PB_D + 1) + PB_D) * PB_N);
        const real rvv = (real)2 * (rv - r0 - hv * jdu) / (hv * hv);
        for (int i = 0; i < PB_D; i++)
            b[i] += jrow[i] * rvv;
    }
}
#endif

/* scipy's '2-point' steps: sqrt(eps) max(1, |x|), inwards at an upper bound, as taken */
inline void pb_steps(const real *x, __global const scalar *hi, real *h)
{
    for (int i = 0; i < PB_D; i++) {
        const real s = PB_EPS_SQRT * fmax((real)1, fabs(x[i]));
        const real t = x[i] + s > (real)hi[i] ? -s : s;
        h[i] = (x[i] + t) - x[i];
    }
}

/* Solve (M) u = -g for the symmetric positive definite M (PB_D x PB_D, destroyed) by Cholesky;
 * ok = 0 in lanes where a pivot is not positive and finite. */
inline void pb_solve(real *Mx, const real *g, real *u, real *ok)
{
    for (int j = 0; j < PB_D; j++) {
        real d = Mx[j * PB_D + j];
        for (int k = 0; k < j; k++)
            d -= Mx[j * PB_D + k] * Mx[j * PB_D + k];
        const real good = (d > (real)0 && isfinite(d)) ? (real)1 : (real)0;
        *ok = fmin(*ok, good);
        const real l = pb_sqrt(d > (real)0 ? d : (real)1);
        Mx[j * PB_D + j] = l;
        for (int i = j + 1; i < PB_D; i++) {
            real s = Mx[i * PB_D + j];
            for (int k = 0; k < j; k++)
                s -= Mx[i * PB_D + k] * Mx[j * PB_D + k];
            Mx[i * PB_D + j] = s / l;
        }
    }
    real y[PB_D];
    for (int i = 0; i < PB_D; i++) {
        real s = -g[i];
        for (int k = 0; k < i; k++)
            s -= Mx[i * PB_D + k] * y[k];
        y[i] = s / Mx[i * PB_D + i];
    }
    for (int i = PB_D - 1; i >= 0; i--) {
        real s = y[i];
        for (int k = i + 1; k < PB_D; k++)
            s -= Mx[k * PB_D + i] * u[k];
        u[i] = s / Mx[i * PB_D + i];
    }
    for (int i = 0; i < PB_D; i++)
        u[i] = (*ok > (real)0 && isfinite(u[i])) ? u[i] : (real)0;
}

/* The descent's coordinates held on a bound (1 where x is on a bound and the gradient points
 * out of it), and the gradient g in coordinates scaled to the bounds with those held left out. */
inline void pb_held(const real *x, const real *gr, const real *span, const real *tol,
                    __global const scalar *lo, __global const scalar *hi, real *held, real *g)
{
    for (int i = 0; i < PB_D; i++) {
        const real gi = gr[i] * span[i];
        held[i] = (((x[i] <= (real)lo[i] + tol[i]) && (gi > (real)0)) ||
                   ((x[i] >= (real)hi[i] - tol[i]) && (gi < (real)0))) ? (real)1 : (real)0;
        g[i] = held[i] > (real)0 ? (real)0 : gi;
    }
}

/* The damped normal matrix in coordinates scaled to the bounds: J^T J with the held coordinates'
 * rows and columns zeroed, plus lam + held on the diagonal. */
inline void pb_damped(const real *A, const real *span, const real *held, const real lam, real *Mx)
{
    for (int i = 0; i < PB_D; i++)
        for (int j = 0; j < PB_D; j++)
            Mx[i * PB_D + j] = ((held[i] > (real)0 || held[j] > (real)0) ? (real)0 : A[i * PB_D + j] * span[i] * span[j])
                               + (i == j ? lam + held[i] : (real)0);
}

/* Mx: As with the rows and columns of the coordinates ``fixed`` (1) replaced by the identity. */
inline void pb_pinned(const real *As, const real *fixed, real *Mx)
{
    for (int i = 0; i < PB_D; i++)
        for (int j = 0; j < PB_D; j++)
            Mx[i * PB_D + j] = (fixed[i] > (real)0 || fixed[j] > (real)0) ? (i == j ? (real)1 : (real)0)
                                                                       : As[i * PB_D + j];
}

/* The trace of J^T J in coordinates scaled to the bounds. */
inline real pb_scaled_trace(const real *A, const real *span)
{
    real t = (real)0;
    for (int i = 0; i < PB_D; i++)
        t += A[i * PB_D + i] * span[i] * span[i];
    return t;
}

/* Settled: the Gauss-Newton step from x (the coordinates held on a bound left out, a ridge of
 * 1e-8 of the mean curvature) would lower the objective by at most 1e-9 of itself (plus 1e-14):
 * the descent is at a minimum, not crawling along a valley.  1 or 0 per lane. */
inline real pb_settled(const real *x, const real *A, const real *gr, const real sse, const real *span,
                       const real *tol, __global const scalar *lo, __global const scalar *hi)
{
    real g[PB_D], Mx[PB_D * PB_D], u[PB_D], held[PB_D];
    const real ridge = (real)1e-8 * pb_scaled_trace(A, span) / (real)PB_D + PB_TINY;
    pb_held(x, gr, span, tol, lo, hi, held, g);
    pb_damped(A, span, held, ridge, Mx);
    real okd = (real)1, dec = (real)0;
    pb_solve(Mx, g, u, &okd);
    for (int i = 0; i < PB_D; i++)
        dec -= g[i] * u[i];
    return (okd > (real)0 && dec <= (real)1e-9 * sse + (real)1e-14) ? (real)1 : (real)0;
}

/* X[i * Q + q]: in the start, out the end (internal coordinates); sse_out[q], jtj_out[(i * PB_D
 * + j) * Q + q] (J^T J at the end, unscaled), settled[q] (1 where a Gauss-Newton step would
 * gain almost nothing: see the end).
 * Problem q belongs to pixel q % P. */
__kernel void batch_lm(__global scalar *X, __global scalar *sse_out, __global scalar *jtj_out,
                       __global scalar *settled, const int Q, const int P, const int M, const int iterations,
                       __global const scalar *base, __global const scalar *lo, __global const scalar *hi,
                       __global const scalar *geo,
                       __global const scalar *obs, __global const scalar *w,
                       __global const scalar *fobs, __global const scalar *fw, __global scalar *rows,
                       __global const scalar *chan)
{
    const int q0 = get_global_id(0) * PB_N;
    /* rows: two slots of M x (PB_D + 1) lane vectors per work-item, contiguous (the current
     * point's Jacobian rows and residuals, the trial's), for the geodesic acceleration */
    __global scalar *cur = rows + (size_t)(q0 / PB_N) * 2 * M * (PB_D + 1) * PB_N;
    __global scalar *trial = cur + (size_t)M * (PB_D + 1) * PB_N;
    if (q0 >= Q) return;
    const int p0 = q0 % P;
    real x[PB_D], h[PB_D], A[PB_D * PB_D], gr[PB_D], sse;
    real span[PB_D], tol[PB_D];
    for (int i = 0; i < PB_D; i++) {
        span[i] = (real)(hi[i] - lo[i]);
        tol[i] = (real)1e-12 * span[i];
        x[i] = clamp(pb_vl(0, X + i * Q + q0), (real)lo[i], (real)hi[i]);
    }
    pb_steps(x, hi, h);
    pb_evaluate(x, h, base, geo, obs, w, fobs, fw, P, M, p0, &sse, A, gr, cur, Q, q0, chan);
    real lam = (real)1e-3 * pb_scaled_trace(A, span) / (real)PB_D;
    lam = isfinite(lam) && lam > (real)0 ? lam : (real)1e-3;
    /* 1 while this lane descends, 0 once it has settled or its damping saturated: a lane stops
     * on its own account, whatever the work-item's other lanes do, so that a problem's result
     * does not depend on which problems share its vector (fit_batch's blocks, _polish's
     * compaction) */
    real active = (real)1;
    for (int it = 0; it < iterations; it++) {
        if (it > 0)
            active *= (real)1 - pb_settled(x, A, gr, sse, span, tol, lo, hi);
        /* every lane stopped: nothing left to gain */
        if (all(active == (real)0))
            break;
        real g[PB_D], Mx[PB_D * PB_D], du[PB_D], held[PB_D];
        pb_held(x, gr, span, tol, lo, hi, held, g);
        pb_damped(A, span, held, lam, Mx);
        real ok = (real)1, As[PB_D * PB_D];
        for (int i = 0; i < PB_D * PB_D; i++)
            As[i] = Mx[i];
        pb_solve(Mx, g, du, &ok);
        /* the coordinates this step would take out of the bounds go onto them, and the others are
         * solved again with those fixed there (an active-set guess: clipping the step instead
         * spoils it, and a descent into a bound crawls) */
        real hit[PB_D], delta[PB_D];
        int any_hit = 0;
        for (int i = 0; i < PB_D; i++) {
            const real xn = x[i] + du[i] * span[i];
            hit[i] = (held[i] == (real)0 && (xn < (real)lo[i] || xn > (real)hi[i])) ? (real)1 : (real)0;
            delta[i] = hit[i] > (real)0 ? (clamp(xn, (real)lo[i], (real)hi[i]) - x[i]) / span[i] : (real)0;
            any_hit |= any(hit[i] > (real)0);
        }
        if (any_hit) {
            real g2[PB_D], du2[PB_D], ok2 = (real)1;
            for (int i = 0; i < PB_D; i++) {
                real s = g[i];
                for (int j = 0; j < PB_D; j++)
                    s += (i == j ? (real)0 : As[i * PB_D + j]) * delta[j];
                g2[i] = hit[i] > (real)0 ? (real)0 : s;
            }
            pb_pinned(As, hit, Mx);
            pb_solve(Mx, g2, du2, &ok2);
            for (int i = 0; i < PB_D; i++)
                du[i] = hit[i] > (real)0 ? delta[i] : (ok2 > (real)0 ? du2[i] : du[i]);
        }
#ifdef PB_GEODESIC
        /* the acceleration a along the coordinates that move freely, kept where 2 |a| <= 0.75 |du|
         * (else the plain step): the step is du + a / 2, which follows a curved valley */
        {
            real b[PB_D], a[PB_D], fixed[PB_D], ok3 = (real)1;
            pb_accel_rhs(x, du, span, (real)0.1, lo, hi, base, geo, obs, w, P, M, p0, cur, Q, q0, b, chan);
            for (int i = 0; i < PB_D; i++) {
                fixed[i] = (held[i] > (real)0 || hit[i] > (real)0) ? (real)1 : (real)0;
                b[i] = fixed[i] > (real)0 ? (real)0 : b[i];
            }
            pb_pinned(As, fixed, Mx);
            pb_solve(Mx, b, a, &ok3);
            real na = (real)0, nv = (real)0;
            for (int i = 0; i < PB_D; i++) {
                na += a[i] * a[i];
                nv += du[i] * du[i];
            }
            const real use = (ok3 > (real)0 && (real)4 * na <= (real)0.5625 * nv && isfinite(na)) ? (real)1 : (real)0;
            for (int i = 0; i < PB_D; i++)
                du[i] = use > (real)0 ? du[i] + (real)0.5 * a[i] : du[i];
        }
#endif
        real xt[PB_D], ht[PB_D], At[PB_D * PB_D], grt[PB_D], sset;
        for (int i = 0; i < PB_D; i++)
            xt[i] = clamp(x[i] + du[i] * span[i], (real)lo[i], (real)hi[i]);
        pb_steps(xt, hi, ht);
        pb_evaluate(xt, ht, base, geo, obs, w, fobs, fw, P, M, p0, &sset, At, grt, trial, Q, q0, chan);
        const real better = (sset < sse ? (real)1 : (real)0) * active;
        const int any_better = any(better > (real)0);
        if (any_better) {
            for (int i = 0; i < PB_D; i++) {
                x[i] = better > (real)0 ? xt[i] : x[i];
                h[i] = better > (real)0 ? ht[i] : h[i];
                gr[i] = better > (real)0 ? grt[i] : gr[i];
                for (int j = 0; j < PB_D; j++)
                    A[i * PB_D + j] = better > (real)0 ? At[i * PB_D + j] : A[i * PB_D + j];
            }
            sse = better > (real)0 ? sset : sse;
#ifdef PB_GEODESIC
            for (size_t k = 0; k < (size_t)M * (PB_D + 1); k++) {
                __global scalar *c = cur + k * PB_N;
                pb_vs(better > (real)0 ? pb_vl(0, trial + k * PB_N) : pb_vl(0, c), 0, c);
            }
#endif
        }
        lam = active > (real)0 ? clamp(better > (real)0 ? lam * (real)0.3 : lam * (real)6, PB_TINY, PB_HUGE) : lam;
        /* a lane whose damping saturated: no step can improve it */
        active *= lam < PB_HUGE ? (real)1 : (real)0;
    }
    const real done = pb_settled(x, A, gr, sse, span, tol, lo, hi);
    for (int i = 0; i < PB_D; i++) {
        pb_vs(x[i], 0, X + i * Q + q0);
        for (int j = 0; j < PB_D; j++)
            pb_vs(A[i * PB_D + j], 0, jtj_out + (i * PB_D + j) * Q + q0);
    }
    pb_vs(sse, 0, sse_out + q0);
    pb_vs(done, 0, settled + q0);
}

#endif
