/*
 * pbrdf_grid.cl -- dense grids, on-device reductions and the least-squares objective, all
 * combining the tables of pbrdf_tables.cl (no transcendental function per grid point).
 *
 * The full grid's flat index is ((g * PB_NNK + nk) * PB_NM + s) * PB_NI + j with
 *   g  = (i_theta_i * N_theta_r + i_theta_r) * N_phi + i_phi     geometry
 *   nk = i_n * N_k + i_k,  s = i_sigma * N_ks + i_ks,  j = i_kd * N_c + i_c.
 * Build options: -DPBRDF_DOUBLE, -DPB_NNK, -DPB_NM, -DPB_NI (compile-time sizes let the index
 * arithmetic vectorise), -DPB_INDEX=uint|ulong, the quantity's defines from its registry record
 * (pbrdf_cl/quantities.py: -DPB_QUANTITY=<name> combines with pbrdf.h's pb_grid_<name>, -DPB_WIDTH
 * values per grid point, -DPB_FRAME when it needs the frame table, -DPB_GRID_VECTOR for the DOP's
 * vector row body), -DPB_ROW_LEVEL and -DPB_ROW_LEN for the row kernels, -DPB_OBJECTIVE for
 * objective_rows.  A grid point's PB_WIDTH values are consecutive in the output.
 * Tables for geometry rows g0 ..: sum/diff[(g - g0) * PB_NNK + nk], scale[(g - g0) * PB_NM + s],
 * diffuse[(g - g0) * PB_NI + j], frame[2 (g - g0)] = (C, S) (a 1-value dummy without PB_FRAME).
 */
#include "pbrdf.h"

#ifndef PB_INDEX
#define PB_INDEX uint
#endif
typedef PB_INDEX pbidx;

#ifndef PB_QUANTITY
#define PB_QUANTITY dop
#endif
#ifndef PB_WIDTH
#define PB_WIDTH 1
#endif
#ifdef PB_FRAME
#define PB_FRAME_C(g) frame[2 * (g)]
#define PB_FRAME_S(g) frame[2 * (g) + 1]
#else
#define PB_FRAME_C(g) ((real)1)
#define PB_FRAME_S(g) ((real)0)
#endif
/* component q of the quantity at geometry row g from the table values */
#define PB_COMBINE(sum, diff, dif, scl, g, q) \
    PB_CAT(pb_grid_, PB_QUANTITY)(sum, diff, dif, scl, PB_FRAME_C(g), PB_FRAME_S(g), q)

#define PB_TABLES                                                            \
    __global const real *sum, __global const real *diff,                     \
    __global const real *scale, __global const real *dif, __global const real *frame

__kernel void grid_values(__global real *out, const pbidx start, const pbidx count, const pbidx g0,
                          PB_TABLES)
{
    const pbidx gid = get_global_id(0);
    if (gid >= count) return;
    pbidx i = start + gid;
    const pbidx j = i % PB_NI; i /= PB_NI;
    const pbidx s = i % PB_NM; i /= PB_NM;
    const pbidx nk = i % PB_NNK;
    const pbidx g = i / PB_NNK - g0;
    for (int q = 0; q < PB_WIDTH; q++)
        out[gid * PB_WIDTH + q] = PB_COMBINE(sum[g * PB_NNK + nk], diff[g * PB_NNK + nk], dif[g * PB_NI + j],
                                             scale[g * PB_NM + s], g, q);
}

#ifdef PB_REDUCE
/* Reductions over a set of axes without materialising the grid.  Generated definitions:
 * PB_NKEPT, PB_KEPT_SIZE[], PB_KEPT_FAM[], PB_KEPT_COEF[] (kept axes, outermost first) and
 * PB_NRED, PB_RED_SIZE[], PB_RED_FAM[], PB_RED_COEF[] (reduced axes), PB_RED_TOTAL; family
 * 0..3 = g, nk, s, j; coef = the axis' stride inside its family.  Work-item (o, part) reduces
 * the reduced indices r = part, part + n_part, ... of kept output o: min, argmin (r) and sum. */
__kernel void grid_reduce(__global real *vmin, __global pbidx *vargmin, __global real *vsum,
                          const pbidx o_start, const pbidx o_count, const pbidx n_part, PB_TABLES)
{
    const pbidx o_local = get_global_id(0), part = get_global_id(1);
    if (o_local >= o_count || part >= n_part) return;
    pbidx base[4] = {0, 0, 0, 0};
    pbidx o = o_start + o_local;
    for (int a = PB_NKEPT - 1; a >= 0; a--) {
        base[PB_KEPT_FAM[a]] += (o % PB_KEPT_SIZE[a]) * PB_KEPT_COEF[a];
        o /= PB_KEPT_SIZE[a];
    }
    real best = INFINITY, acc = (real)0, comp = (real)0;
    pbidx best_r = 0;
    for (pbidx r = part; r < PB_RED_TOTAL; r += n_part) {
        pbidx idx[4] = {base[0], base[1], base[2], base[3]};
        pbidx q = r;
        for (int a = PB_NRED - 1; a >= 0; a--) {
            idx[PB_RED_FAM[a]] += (q % PB_RED_SIZE[a]) * PB_RED_COEF[a];
            q /= PB_RED_SIZE[a];
        }
        const real v = PB_COMBINE(sum[idx[0] * PB_NNK + idx[1]], diff[idx[0] * PB_NNK + idx[1]],
                                  dif[idx[0] * PB_NI + idx[3]], scale[idx[0] * PB_NM + idx[2]], idx[0], 0);
        if (v < best) { best = v; best_r = r; }
        const real y = v - comp;  /* Kahan summation */
        const real t = acc + y;
        comp = (t - acc) - y;
        acc = t;
    }
    const pbidx out = o_local * n_part + part;
    vmin[out] = best;
    vargmin[out] = best_r;
    vsum[out] = acc;
}
#endif

/* Weighted sum of squared DOP residuals for a grid of parameter vectors
 * p = (nk * PB_NM + s) * PB_NI + j over M measurements, one work-item per vector (used when the
 * rows of objective_rows would be too long).  Tables as for objective_rows.  The objective kernels
 * add to what sse holds where more is not 0 (the next block of measurements, in the same order
 * and the same precision as one launch over all of them: the same sums, bit for bit).
 * PB_SETS data sets of the same measurements (default 1): obs and w hold set t's value of
 * measurement m at [m * PB_SETS + t], and set t's sums follow set t - 1's, count values apart
 * (each DOP combined once, its residual taken against every set's: each set's sums are those of
 * a launch for it alone, bit for bit).  The loops over the sets are unrolled (PB_UNROLL): PoCL 3.0
 * (LLVM 14, the PyPI wheel) kept their sums in memory otherwise, and three sets took twice as long. */
#ifndef PB_SETS
#define PB_SETS 1
#endif
#define PB_UNROLL _Pragma("unroll")
__kernel void objective_grid(__global real *sse, const pbidx start, const pbidx count,
                             PB_TABLES, __global const real *obs, __global const real *w, const int M,
                             const int more)
{
    const pbidx gid = get_global_id(0);
    if (gid >= count) return;
    pbidx p = start + gid;
    const pbidx j = p % PB_NI; p /= PB_NI;
    const pbidx s = p % PB_NM;
    const pbidx nk = p / PB_NM;
    real acc[PB_SETS];
    PB_UNROLL for (int t = 0; t < PB_SETS; t++)
        acc[t] = more ? sse[t * count + gid] : (real)0;
    for (int m = 0; m < M; m++) {
        const real v = pb_dop_combine(sum[m * PB_NNK + nk], diff[m * PB_NNK + nk], dif[m * PB_NI + j],
                                      scale[m * PB_NM + s]);
        PB_UNROLL for (int t = 0; t < PB_SETS; t++) {
            const real r = v - obs[m * PB_SETS + t];
            acc[t] += w[m * PB_SETS + t] * r * r;
        }
    }
    PB_UNROLL for (int t = 0; t < PB_SETS; t++)
        sse[t * count + gid] = acc[t];
}

/* One work-item per row of PB_ROW_LEN contiguous values sharing their outer indices, so the
 * inner loops vectorise.  PB_ROW_LEVEL 1: rows (g, nk, s), loop j; 2: rows (g, nk), loop s, j;
 * 3: rows g, loop nk, s, j. */
__kernel void grid_rows(__global real *out, const pbidx row_start, const pbidx rows, const pbidx g0,
                        PB_TABLES)
{
    const pbidx gid = get_global_id(0);
    if (gid >= rows) return;
    pbidx i = row_start + gid;
#if PB_ROW_LEVEL == 1
    const pbidx s = i % PB_NM; i /= PB_NM;
    const pbidx nk = i % PB_NNK;
    const pbidx g = i / PB_NNK - g0;
    const real su = sum[g * PB_NNK + nk], di = diff[g * PB_NNK + nk], sc = scale[g * PB_NM + s];
    __global const real *fd = dif + g * PB_NI;
    __global real *o = out + gid * (PB_NI * PB_WIDTH);
    int j = 0;
#ifdef PB_GRID_VECTOR
    for (; j + PB_VW <= PB_NI; j += PB_VW)
        pb_vstore(pb_dop_combine_v((realv)su, (realv)di, pb_vload(0, fd + j), (realv)sc), 0, o + j);
#endif
    for (; j < PB_NI; j++)
        for (int q = 0; q < PB_WIDTH; q++)
            o[j * PB_WIDTH + q] = PB_COMBINE(su, di, fd[j], sc, g, q);
#elif PB_ROW_LEVEL == 2
    const pbidx nk = i % PB_NNK;
    const pbidx g = i / PB_NNK - g0;
    const real su = sum[g * PB_NNK + nk], di = diff[g * PB_NNK + nk];
    __global const real *fd = dif + g * PB_NI, *sc = scale + g * PB_NM;
    __global real *o = out + gid * (PB_NM * PB_NI * PB_WIDTH);
    for (int s = 0; s < PB_NM; s++)
        for (int j = 0; j < PB_NI; j++)
            for (int q = 0; q < PB_WIDTH; q++)
                o[(s * PB_NI + j) * PB_WIDTH + q] = PB_COMBINE(su, di, fd[j], sc[s], g, q);
#else
    const pbidx g = i - g0;
    __global const real *fd = dif + g * PB_NI, *sc = scale + g * PB_NM;
    __global const real *su = sum + g * PB_NNK, *di = diff + g * PB_NNK;
    __global real *o = out + gid * (PB_NNK * PB_NM * PB_NI * PB_WIDTH);
    for (int nk = 0; nk < PB_NNK; nk++)
        for (int s = 0; s < PB_NM; s++)
            for (int j = 0; j < PB_NI; j++)
                for (int q = 0; q < PB_WIDTH; q++)
                    o[((nk * PB_NM + s) * PB_NI + j) * PB_WIDTH + q] = PB_COMBINE(su[nk], di[nk], fd[j], sc[s], g, q);
#endif
}

/* The objective by rows: work-item (nk, s) [PB_ROW_LEVEL 1] or nk [level 2] accumulates the
 * PB_ROW_LEN parameter vectors of its row over the M measurements, PB_QB at a time; tables are
 * laid out measurement by measurement: sum/diff[m * PB_NNK + nk], scale[m * PB_NM + s],
 * dif[m * PB_NI + j].  PB_SETS data sets as objective_grid's: set t's sums rows * PB_ROW_LEN
 * values after set t - 1's. */
#ifdef PB_OBJECTIVE
#define PB_QB 16
__kernel void objective_rows(__global real *sse, const pbidx row_start, const pbidx rows, PB_TABLES,
                             __global const real *obs, __global const real *w, const int M, const int more)
{
    const pbidx gid = get_global_id(0);
    if (gid >= rows) return;
    const pbidx i = row_start + gid;
#if PB_ROW_LEVEL == 1
    const pbidx s = i % PB_NM;
    const pbidx nk = i / PB_NM;
#else
    const pbidx nk = i;
#endif
    __global real *o = sse + gid * PB_ROW_LEN;
    const pbidx set_stride = rows * PB_ROW_LEN;
#if PB_ROW_LEVEL == 1
    /* whole vectors first, the tail below */
    for (int q0 = 0; q0 + PB_VW <= PB_ROW_LEN; q0 += PB_VW) {
        realv acc[PB_SETS];
        PB_UNROLL for (int t = 0; t < PB_SETS; t++)
            acc[t] = more ? pb_vload(0, o + t * set_stride + q0) : (realv)0;
        for (int m = 0; m < M; m++) {
            const realv v = pb_dop_combine_v((realv)sum[m * PB_NNK + nk], (realv)diff[m * PB_NNK + nk],
                                             pb_vload(0, dif + m * PB_NI + q0), (realv)scale[m * PB_NM + s]);
            PB_UNROLL for (int t = 0; t < PB_SETS; t++) {
                const realv r = v - (realv)obs[m * PB_SETS + t];
                acc[t] += (realv)w[m * PB_SETS + t] * r * r;
            }
        }
        PB_UNROLL for (int t = 0; t < PB_SETS; t++)
            pb_vstore(acc[t], 0, o + t * set_stride + q0);
    }
    for (int q0 = PB_ROW_LEN / PB_VW * PB_VW; q0 < PB_ROW_LEN; q0 += PB_QB) {
#else
    for (int q0 = 0; q0 < PB_ROW_LEN; q0 += PB_QB) {
#endif
        real acc[PB_SETS][PB_QB];
        PB_UNROLL for (int t = 0; t < PB_SETS; t++)
            for (int q = 0; q < PB_QB; q++)
                acc[t][q] = more ? o[t * set_stride + min(q0 + q, PB_ROW_LEN - 1)] : (real)0;
        for (int m = 0; m < M; m++) {
            const real su = sum[m * PB_NNK + nk], di = diff[m * PB_NNK + nk];
            __global const real *fd = dif + m * PB_NI, *sc = scale + m * PB_NM;
            for (int q = 0; q < PB_QB; q++) {
                const int qq = min(q0 + q, PB_ROW_LEN - 1);  /* clamped: the tail block re-reads */
#if PB_ROW_LEVEL == 1
                const real v = pb_dop_combine(su, di, fd[qq], sc[s]);
#else
                const real v = pb_dop_combine(su, di, fd[qq % PB_NI], sc[qq / PB_NI]);
#endif
                PB_UNROLL for (int t = 0; t < PB_SETS; t++) {
                    const real r = v - obs[m * PB_SETS + t];
                    acc[t][q] += w[m * PB_SETS + t] * r * r;
                }
            }
        }
        PB_UNROLL for (int t = 0; t < PB_SETS; t++)
            for (int q = 0; q < PB_QB && q0 + q < PB_ROW_LEN; q++)
                o[t * set_stride + q0 + q] = acc[t][q];
    }
}
#endif

#ifdef PB_CHANNELS
/* The objective of polarimetric channels (pbrdf.h's pb_channel_combine and pb_channel_residual):
 * sum_m w_m r_m^2 over M channels for parameter vectors p = (nk * PB_NM + s) * PB_NI + j, from the
 * channel tables tn/td[m * PB_NNK + nk] (pbrdf_tables.cl's channel_table), 1/K as scale[m * PB_NM + s]
 * and the diffuse term fd[m * PB_NI + j], with each channel's coefficients abc[3 m ..] = (a, b, c)
 * and whether it is an AoP (aop[m]: its residual wrapped modulo 180 degrees).  objective_channels:
 * one work-item per vector; objective_channel_rows: as objective_rows (PB_ROW_LEVEL 1 or 2). */
#define PB_CHANNEL_TABLES                                                    \
    __global const real *tn, __global const real *td, __global const real *scale, __global const real *dif, \
    __global const real *obs, __global const real *w, __global const real *abc, __global const int *aop, const int M

__kernel void objective_channels(__global real *sse, const pbidx start, const pbidx count, PB_CHANNEL_TABLES,
                                 const int more)
{
    const pbidx gid = get_global_id(0);
    if (gid >= count) return;
    pbidx p = start + gid;
    const pbidx j = p % PB_NI; p /= PB_NI;
    const pbidx s = p % PB_NM;
    const pbidx nk = p / PB_NM;
    real acc = more ? sse[gid] : (real)0;
    for (int m = 0; m < M; m++) {
        const real v = pb_channel_combine(tn[m * PB_NNK + nk], td[m * PB_NNK + nk], scale[m * PB_NM + s],
                                          dif[m * PB_NI + j], abc[3 * m], abc[3 * m + 1], abc[3 * m + 2], aop[m]);
        const real r = pb_channel_residual(v, obs[m], aop[m]);
        acc += w[m] * r * r;
    }
    sse[gid] = acc;
}

#ifdef PB_OBJECTIVE
__kernel void objective_channel_rows(__global real *sse, const pbidx row_start, const pbidx rows, PB_CHANNEL_TABLES,
                                     const int more)
{
    const pbidx gid = get_global_id(0);
    if (gid >= rows) return;
    const pbidx i = row_start + gid;
#if PB_ROW_LEVEL == 1
    const pbidx s = i % PB_NM;
    const pbidx nk = i / PB_NM;
#else
    const pbidx nk = i;
#endif
    __global real *o = sse + gid * PB_ROW_LEN;
#if PB_ROW_LEVEL == 1
    for (int q0 = 0; q0 + PB_VW <= PB_ROW_LEN; q0 += PB_VW) {
        realv acc = more ? pb_vload(0, o + q0) : (realv)0;
        for (int m = 0; m < M; m++) {
            const realv v = pb_channel_combine_v((realv)tn[m * PB_NNK + nk], (realv)td[m * PB_NNK + nk],
                                                 (realv)scale[m * PB_NM + s], pb_vload(0, dif + m * PB_NI + q0),
                                                 abc[3 * m], abc[3 * m + 1], abc[3 * m + 2], aop[m]);
            const realv r = pb_channel_residual_v(v, (realv)obs[m], aop[m]);
            acc += (realv)w[m] * r * r;
        }
        pb_vstore(acc, 0, o + q0);
    }
    for (int q0 = PB_ROW_LEN / PB_VW * PB_VW; q0 < PB_ROW_LEN; q0 += PB_QB) {
#else
    for (int q0 = 0; q0 < PB_ROW_LEN; q0 += PB_QB) {
#endif
        real acc[PB_QB];
        for (int q = 0; q < PB_QB; q++)
            acc[q] = more ? o[min(q0 + q, PB_ROW_LEN - 1)] : (real)0;
        for (int m = 0; m < M; m++) {
            const real n_ = tn[m * PB_NNK + nk], d_ = td[m * PB_NNK + nk];
            const real a = abc[3 * m], b = abc[3 * m + 1], c = abc[3 * m + 2], ob = obs[m], wm = w[m];
            const int is_aop = aop[m];
            __global const real *fd = dif + m * PB_NI, *sc = scale + m * PB_NM;
            for (int q = 0; q < PB_QB; q++) {
                const int qq = min(q0 + q, PB_ROW_LEN - 1);  /* clamped: the tail block re-reads */
#if PB_ROW_LEVEL == 1
                const real v = pb_channel_combine(n_, d_, sc[s], fd[qq], a, b, c, is_aop);
#else
                const real v = pb_channel_combine(n_, d_, sc[qq / PB_NI], fd[qq % PB_NI], a, b, c, is_aop);
#endif
                const real r = pb_channel_residual(v, ob, is_aop);
                acc[q] += wm * r * r;
            }
        }
        for (int q = 0; q < PB_QB && q0 + q < PB_ROW_LEN; q++)
            o[q0 + q] = acc[q];
    }
}
#endif
#endif
