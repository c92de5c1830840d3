"""Several sets' DOP residuals in one call of the reference model (:class:`SetStack`).

At a few dozen measurements per set the reference model's cost is mostly per call (two dozen
numpy operations of a few microseconds each), not per point: :func:`pbrdf_cl.fit_joint`, which
evaluated each set in turn, paid it once per set at every step of its local stages.  The stack
lays the sets' geometries side by side, padded to the longest set (a set's padding repeats its
last point, and its residuals there are zero), and evaluates:

- the joint rows (:meth:`SetStack.joint_rows`): every set at each joint parameter vector, the
  parameters broadcast per set ((B, S, 1) against the (S, M) geometry);
- the own rows (:meth:`SetStack.own_rows`): each row one set's parameter vector (the sets' own
  fits, batched into one descent), the geometry of each row's set gathered per row.

Each residual is computed by the same operations on the same numbers as a set's
:class:`~pbrdf_cl.fitting.sample.stages.Residuals` (elementwise, whatever the layout): the
results are those of the sets evaluated one by one, bit for bit.
"""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from ...model import reference
from ...model.inputs import MEMBERS
from ..sample.stages import (
    DISTINCT_VALUES,
    FACTORS,
    RUN_ROWS,
    Residuals,
    finite_rows,
    in_row_blocks,
    same_runs,
)


class SetStack:
    """The DOP residuals of ``parts`` (one :class:`~pbrdf_cl.fitting.sample.stages.Residuals` per
    set, DOP only, the same free parameters and the same held ones, at any values) in one model
    call.  Build it with :meth:`of`, which says None where the sets cannot be stacked."""

    def __init__(self, parts):
        sizes = np.array([p.dop.size for p in parts])
        width = int(sizes.max())
        self.free = parts[0].free
        self.sizes, self.width = sizes, width

        def padded(values):
            out = np.empty((len(parts), width))
            for i, (v, m) in enumerate(zip(values, sizes)):
                out[i, :m] = v
                out[i, m:] = v[-1] if m else 0.0
            return out
        fields = vars(parts[0].model.g)
        self.model = parts[0].model.with_geometry(SimpleNamespace(**{
            k: padded([np.broadcast_to(vars(p.model.g)[k], (m,)) for p, m in zip(parts, sizes)]) for k in fields}))
        self.dop = padded([p.dop for p in parts])
        self.std = padded([p.dop_std for p in parts])
        self.mask = np.arange(width)[None, :] < sizes[:, None]
        self.ragged = bool((sizes < width).any())
        self.cells = np.flatnonzero(self.mask.reshape(-1))  # the joint rows' columns, set by set
        names = sorted(set().union(*(p.base for p in parts)))
        # held parameters: one value per set, (S,) for the own rows, and (1, S, 1) for the joint rows
        self.held = {n: np.array([float(p.base[n]) for p in parts]) for n in names}
        self.held_rows = {n: v[None, :, None] for n, v in self.held.items()}

    @classmethod
    def of(cls, parts):
        """A stack of ``parts`` where every part is a DOP-only
        :class:`~pbrdf_cl.fitting.sample.stages.Residuals` with the same free and held parameters,
        else None (polarimetric sets, intensities, a parameter held in some sets only)."""
        if len(parts) < 2 or any(type(p) is not Residuals or p.f00 is not None for p in parts):
            return None
        if len({p.free for p in parts}) > 1 or len({tuple(sorted(p.base)) for p in parts}) > 1:
            return None
        if len({p.model.variant for p in parts}) > 1:
            return None
        return cls(parts)

    def fits(self, rows):
        """Whether ``rows`` rows of every set are few enough for one call (below
        :data:`~pbrdf_cl.fitting.sample.stages.DISTINCT_VALUES` values, where the model computes
        each factor directly: a set evaluated alone does the same)."""
        return rows * self.width * len(self.sizes) < DISTINCT_VALUES

    def joint_rows(self, X, columns):
        """The stacked residuals of the joint vectors ``X`` (B, d): set i's free parameters are
        ``X[:, columns[:, i]]`` (``columns``: (free, sets), each set's joint columns, as
        ``np.stack(index, axis=1)`` of the sets' column indices); (B, total measurements), set by set."""
        p = dict(self.held_rows)
        values = X[:, columns]  # (B, free, sets): one gather, each parameter a view of it
        for j, n in enumerate(self.free):
            p[n] = values[:, j, :, None]
        r = (self.model.dop_rows(p) - self.dop) / self.std
        return finite_rows(r.reshape(len(X), -1)[:, self.cells] if self.ragged else r.reshape(len(X), -1))

    def own_rows(self, X, which):
        """The residuals of the parameter vectors ``X`` (B, free), row b one of set ``which[b]``:
        (B, longest set), zero beyond its set's measurements; of big sets a few rows at a time
        (:func:`~pbrdf_cl.fitting.sample.stages.in_row_blocks`, as a set alone)."""
        which = np.asarray(which, dtype=np.intp)
        return in_row_blocks(lambda a, b: self._own_rows_of(X[a:b], which[a:b]), len(X), self.width)

    def tagged_rows(self, Y):
        """:meth:`own_rows` of rows whose last column is their set (an ``extra`` column of
        :func:`~pbrdf_cl.fitting.common.lm_batch`, or a lockstep's rows)."""
        return self.own_rows(Y[:, :-1], Y[:, -1].astype(np.intp))

    def _own_rows_of(self, X, which):
        p = {n: v[which][:, None] for n, v in self.held.items()}
        p.update((n, X[:, j:j + 1]) for j, n in enumerate(self.free))
        if len(X) >= RUN_ROWS:
            # each factor once per run of consecutive rows of one set with the same values of its
            # parameters (stages.same_runs, the set a parameter too: a finite-difference Jacobian's
            # rows hold most of them), at the geometry of the run's set: the same numbers, bit for bit
            p[SET] = which[:, None]
            dop = reference.dop(*(same_runs(lambda q, part=part: getattr(self._at(q[SET][:, 0]), part)(q), p,
                                            MEMBERS[family] + (SET,)) for part, family in FACTORS))
        else:
            dop = self._at(which).dop_rows(p)
        r = finite_rows((dop - self.dop[which]) / self.std[which])
        return np.where(self.mask[which], r, 0.0) if self.ragged else r

    def _at(self, which):
        """The model at the geometry of the sets ``which``, one row each."""
        return self.model.with_geometry(SimpleNamespace(**{k: v[which] for k, v in vars(self.model.g).items()}))


#: The own rows' set, as a parameter of :func:`~pbrdf_cl.fitting.sample.stages.same_runs`' rows.
SET = "set"
