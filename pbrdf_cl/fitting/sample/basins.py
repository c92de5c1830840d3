"""The grid stage's objective read for seeds: its local minima (:func:`grid_basins`), the valleys
of its profiles (:func:`grid_profiles`, :func:`profile_seeds`) and its bound slices
(:func:`bound_seeds`), for the local stages of :func:`pbrdf_cl.fit`."""
import numpy as np


def grid_point(axes, free, idx):
    return np.array([axes[n][i] for n, i in zip(free, idx)])


def local_spacing(values, i):
    """The larger of the two grid steps around index i."""
    left = values[i] - values[i - 1] if i > 0 else 0.0
    right = values[i + 1] - values[i] if i + 1 < values.size else 0.0
    return max(left, right)


def grid_basins(sse, n_basins, pool=4096):
    """Grid indices of the best ``n_basins`` local minima, at least 3 cells apart in some axis.

    Only the ``pool`` lowest cells are examined first (a partition, not a sort, of the grid);
    the greedy choice depends only on lower minima, so when the pool yields ``n_basins`` the
    answer is the same as from the whole grid, which is searched otherwise."""
    flat = sse.ravel()
    if flat.size > 4 * pool:
        cells = lowest_cells(sse, pool)
    else:
        cells = np.arange(flat.size)
    chosen = _grid_minima(sse, cells, n_basins)
    if len(chosen) < n_basins and cells.size < flat.size:
        chosen = _grid_minima(sse, np.arange(flat.size), n_basins)
    return [tuple(int(v) for v in c) for c in chosen]


def lowest_cells(sse, pool):
    """The flat indices of the cells at or below the ``pool``-th lowest value of ``sse`` (as
    ``flatnonzero(flat <= partition(flat, pool)[pool])``, the same cells).  The minima along the
    first axis give a threshold that at least ``pool + 1`` cells reach, so the partition runs
    on those cells only, not on the whole grid."""
    flat = sse.ravel()
    rows = sse.reshape(sse.shape[0], -1).min(axis=0)
    top = np.partition(rows, pool)[pool] if sse.ndim > 1 and rows.size > pool else np.nan
    if np.isnan(top):  # too few columns, or NaN among their minima (a NaN column's minimum is NaN)
        return np.flatnonzero(flat <= np.partition(flat, pool)[pool])
    cells = np.flatnonzero(flat <= top)
    values = flat[cells]
    return cells[values <= np.partition(values, pool)[pool]]


def profile_seeds(sse, profiles, free, basins, count, rise):
    """Grid indices of up to ``count`` more seeds: for each parameter, the valleys of its grid
    profile that none of ``basins`` lies in (separated from them by a ridge at least ``rise``
    higher than the valley floor), each seeded at the best grid point of its slice; the best
    valleys first."""
    if count <= 0:
        return []
    found = []
    for j, n in enumerate(free):
        prof = profiles[n]
        taken = sorted({b[j] for b in basins})
        for i in range(prof.size):
            if not ((i == 0 or prof[i] <= prof[i - 1]) and (i == prof.size - 1 or prof[i] < prof[i + 1])):
                continue
            # the lowest ridge between this valley floor and any basin's slice
            ridge = min(prof[min(i, t):max(i, t) + 1].max() for t in taken)
            if ridge - prof[i] >= rise:
                found.append((prof[i], j, i))
    found.sort()
    out = []
    for _, j, i in found:
        idx = _slice_argmin(sse, j, i)
        if _apart(idx, list(basins) + out):
            out.append(idx)
        if len(out) == count:
            break
    return out


def bound_seeds(sse, basins):
    """Grid indices of the best point of each parameter's two bound slices (the optimum of
    this model often sits on a bound: k = 0, n = 1, sigma = 1, kd = 0), where no basin is
    within 3 cells."""
    out = []
    for j in range(sse.ndim):
        for i in (0, sse.shape[j] - 1):
            idx = _slice_argmin(sse, j, i)
            if _apart(idx, list(basins) + out):
                out.append(idx)
    return out


def _slice_argmin(sse, j, i):
    """Grid index of the best point of the slice ``sse[..., i, ...]`` (index i along axis j)."""
    sl = np.take(sse, i, axis=j)
    rest = [int(v) for v in np.unravel_index(int(np.argmin(sl)), sl.shape)]
    return tuple(rest[:j] + [int(i)] + rest[j:])


def _apart(idx, others, cells=3):
    """True when grid index ``idx`` is at least ``cells`` cells from each of ``others`` in some axis."""
    return all(max(abs(int(a) - int(b)) for a, b in zip(idx, o)) >= cells for o in others)


def _grid_minima(sse, cells, n_basins):
    idx = np.array(np.unravel_index(cells, sse.shape)).T
    vals = sse.ravel()[cells]
    is_min = np.ones(cells.size, bool)
    for ax in range(sse.ndim):
        for shift in (-1, 1):
            nb = idx.copy()
            nb[:, ax] += shift
            inside = (nb[:, ax] >= 0) & (nb[:, ax] < sse.shape[ax])
            nbv = np.full(cells.size, np.inf)
            nbv[inside] = sse[tuple(nb[inside].T)]
            is_min &= vals <= nbv
    cand = idx[is_min]
    order = np.argsort(vals[is_min], kind="stable")
    chosen = []
    for c in cand[order]:
        if _apart(c, chosen):
            chosen.append(c)
        if len(chosen) == n_basins:
            break
    return chosen


def grid_profiles(sse, free):
    """Profile of the grid objective along each free parameter: the minimum over the others
    (float64, one value per grid node).  Two passes over the grid: the minimum over the
    trailing axes gives the leading axes' profiles and vice versa."""
    k = (sse.ndim + 1) // 2
    lead = sse.reshape(int(np.prod(sse.shape[:k])), -1)
    head = lead.min(axis=1).reshape(sse.shape[:k])  # over the trailing axes
    tail = lead.min(axis=0).reshape(sse.shape[k:])  # over the leading axes
    out = {}
    for i, n in enumerate(free):
        part, j = (head, i) if i < k else (tail, i - k)
        others = tuple(a for a in range(part.ndim) if a != j)
        out[n] = (part.min(axis=others) if others else part).astype(np.float64)
    return out
