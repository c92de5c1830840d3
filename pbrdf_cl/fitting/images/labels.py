"""Image fits with shared material parameters: :class:`LabelJob`, the job of ``pbrdf_cl.fit_batch(stack,
labels=L, shared=("n", "k"))``.

An integer label image ``L`` over the stack's pixels says which pixels are of one material (0: not
fitted).  The pixels of a label share the ``shared`` parameters (the complex index n, k by
default: one value, standard error and interval per label), the other parameters stay per pixel.
DOP alone barely determines n and k at one pixel; the pixels of a material together do.

The job runs in two steps: the label stage (:func:`pbrdf_cl.fitting.images.label_stage.run_label_stage`,
:meth:`LabelJob.prepare`: passes over the whole stack that find each label's shared values), then
the usual per-pixel pass, block by block (:meth:`LabelJob.fit_rows`: each pixel fitted with its
label's values held), in memory, into a store or on ``dask.distributed`` workers as any
:class:`~pbrdf_cl.fitting.images.job.BatchJob`; on workers the label stage's passes over the blocks
run there too (:mod:`pbrdf_cl.fitting.images.label_workers`).
"""
from __future__ import annotations

import hashlib

import numpy as np

from ...io.source import open_stack
from ..common import GOODNESS_P, LABEL_MISTAKE_CAUSES, OUTSIDE_FOOTNOTE, outside_interval
from ..setup import check_shared
from . import label_adjust, label_search
from .dataset import empty_outputs, make_dataset
from .job import BLOCK_BUDGET, N_STARTS, BatchJob
from .label_stage import LABEL_STATUS, held_setup, run_label_stage
from .label_workers import WorkerBlocks
from .pixel_fit import fit_block
from .pixels import grid_values, regions, take

#: The parameters the pixels of a label share by default: the complex index.
DEFAULT_SHARED = ("n", "k")
#: A label needs at least this many pixels (a label of one pixel is a per-pixel fit).
MIN_LABEL_PIXELS = 2


def read_labels(data, labels):
    """(data, labels): ``labels`` as given (an array or DataArray), or the variable of that name in
    the stack ``data`` (a Dataset, a dict of arrays or a path), then left out of the data."""
    if not isinstance(labels, str):
        if labels is None:
            raise ValueError("labels: give an integer label image over the pixels (0: not fitted)")
        return data, labels
    if isinstance(data, dict):
        if labels not in data:
            raise ValueError(f"labels={labels!r}: no such variable in the data ({', '.join(map(str, data))})")
        data = dict(data)
        return data, data.pop(labels)
    if isinstance(data, str) or hasattr(data, "__fspath__"):
        data = open_stack(data)
    if not hasattr(data, "data_vars") or labels not in data:
        have = ", ".join(map(str, getattr(data, "data_vars", ())))
        raise ValueError(f"labels={labels!r}: no such variable in the stack ({have})")
    return data.drop_vars(labels), data[labels]


def check_labels(labels, source):
    """The label image as flat int64 over the stack's pixels (C order of its pixel dimensions),
    checked in one-line errors: the pixel shape, integer values, none negative, a label > 0."""
    if hasattr(labels, "dims") and set(map(str, labels.dims)) == set(source.dims):
        labels = labels.transpose(*source.dims)
    a = np.asarray(labels)
    if a.shape != tuple(source.shape):
        dims = ", ".join(f"{d} {s}" for d, s in zip(source.dims, source.shape))
        raise ValueError(f"labels: shape {a.shape} does not match the stack's pixel dimensions ({dims})")
    if a.dtype.kind == "b" or a.dtype.kind not in "iuf":
        raise ValueError(f"labels: must be integers (0: not fitted), got dtype {a.dtype}")
    if a.dtype.kind == "f":
        bad = ~np.isfinite(a) | (a != np.round(a))
        if bad.any():
            i = np.unravel_index(int(np.argmax(bad)), a.shape)
            raise ValueError(f"labels: must be integers (0: not fitted), got {a[i].item()!r} at index "
                             f"{tuple(map(int, i))}")
    a = a.astype(np.int64).ravel()
    if (a < 0).any():
        i = int(np.argmax(a < 0))
        raise ValueError(f"labels: must be >= 0 (0: not fitted), got {a[i]} at index "
                         f"{tuple(map(int, np.unravel_index(i, source.shape)))}")
    if not (a > 0).any():
        raise ValueError("labels: no pixel has a label > 0 (0: not fitted): nothing to fit")
    return a


def label_shared(setup, shared):
    """The parameters the pixels of a label share, varied by the label stage (model order), from
    ``shared`` as :func:`~pbrdf_cl.fitting.setup.check_shared` reads it for every fit (None: the
    default :data:`DEFAULT_SHARED`, less what is fixed; empty: nothing).  A named parameter also
    fixed is held at its value for every pixel, so it is left out here; refused in one line: kd
    where intensities make the fit's kd the ratio kd/ks, and every free parameter (none left per
    pixel).  An empty answer means every pixel is fitted on its own."""
    names = tuple(n for n in check_shared(shared, setup.model, DEFAULT_SHARED) if n not in setup.fixed)
    if "kd" in names and getattr(setup, "use_f00", False):
        raise ValueError("shared: kd cannot be shared when intensities are fitted (the fit's kd is then kd/ks)")
    if names and len(names) == len(setup.free):
        said = "" if shared is not None else f" (the default of shared for the {setup.model} model)"
        raise ValueError(f"shared: every free parameter ({', '.join(setup.free)}) is shared{said}: none is left per "
                         "pixel; fit the label's pixels as one data set (pbrdf_cl.fit) instead, or fix one")
    return names


class LabelJob(BatchJob):
    """A :class:`~pbrdf_cl.fitting.images.job.BatchJob` whose pixels share parameters by label.

    Parameters
    ----------
    data, model, bounds, fixed, shadowing, memory_budget, n_starts, grid_shape
        As for :class:`~pbrdf_cl.fitting.images.job.BatchJob`.
    labels : array-like or str
        Integer label image over the pixel dimensions (0: not fitted), or the name of such a
        variable of the stack.
    shared : sequence of str or str, optional
        The parameters the pixels of a label share (``"n,k"`` also; :func:`label_shared`); by
        default ("n", "k"), less a fixed one.

    Examples
    --------
    >>> job = LabelJob(stack, labels=L)  # doctest: +SKIP
    >>> job.prepare(engine)  # doctest: +SKIP
    >>> job.result.theta  # doctest: +SKIP
    """

    def __init__(self, data, model="six-param", bounds=None, fixed=None, shadowing="paper", *, labels,
                 shared=None, memory_budget=BLOCK_BUDGET, n_starts=N_STARTS, grid_shape=None):
        data, given = read_labels(data, labels)
        super().__init__(data, model, bounds, fixed, shadowing, memory_budget=memory_budget, n_starts=n_starts,
                         grid_shape=grid_shape)
        self.shared = label_shared(self.setup, shared)
        if not self.shared:
            raise ValueError("shared: names nothing to share (fit the stack without labels: pbrdf_cl.fit_batch "
                             "fits every pixel on its own)")
        self.own = [n for n in self.names if n not in self.shared]
        self.labels = check_labels(given, self.source)
        self.label_ids = np.unique(self.labels[self.labels > 0])
        self.label_index = np.where(self.labels > 0, np.searchsorted(self.label_ids, self.labels), -1)
        self.min_label_pixels = MIN_LABEL_PIXELS
        #: replicates of the label stage's parametric bootstrap of the bias (0: no correction, the
        #: intervals then leave out the incidental parameters' bias; see docs/joint_images.md)
        self.bias_replicates = label_search.BOOT_REPLICATES
        #: correct the labels' values by their integrated likelihood (default; False: the profile's
        #: values, biased; :func:`~pbrdf_cl.fitting.images.label_adjust.integrated_correction`,
        #: docs/joint_images.md)
        self.integrated = label_adjust.INTEGRATED
        self._check_counts()
        held = held_setup(self.setup, self.shared, np.zeros(len(self.shared)))
        self.order_own, self.rstart_own = regions(grid_values(held), held.free)
        #: the label stage's :class:`~pbrdf_cl.fitting.images.label_stage.LabelResult` (:meth:`prepare`)
        self.result = None

    def _check_counts(self):
        """Refuse a label with fewer than MIN_LABEL_PIXELS pixels (not masked)."""
        lab = self.labels
        mask = self.source.vars.get("mask")
        if mask is not None:
            m = np.broadcast_to(np.asarray(getattr(mask, "values", mask), bool), self.source.shape).ravel()
            lab = np.where(m, lab, 0)
        counts = np.bincount(np.searchsorted(self.label_ids, lab[lab > 0]), minlength=self.label_ids.size)
        few = np.flatnonzero(counts < self.min_label_pixels)
        if few.size:
            L = int(self.label_ids[few[0]])
            raise ValueError(f"labels: label {L} has {int(counts[few[0]])} pixel(s) to fit; a label needs at least "
                             f"{self.min_label_pixels} (merge it into another, or set it to 0: not fitted)")

    prepares = True

    def prepare(self, eng, progress=False, client=None, device=None, backend="auto"):
        """Run the label stage (the shared values of every label) before any block: its passes over
        the blocks with ``eng``, or with ``client`` on the cluster's workers (each with its engine
        for ``device`` and ``backend``, :mod:`pbrdf_cl.fitting.images.label_workers`; the same
        result), the rest (the subsample's search, the intervals) with ``eng``."""
        if client is None:
            self.result = run_label_stage(self, eng, progress)
        else:
            with WorkerBlocks(client, self, device, backend) as blocks:
                self.result = run_label_stage(self, eng, progress, blocks)
        return self.result

    def fit_rows(self, eng, r0, r1):
        """Fit the pixels of rows r0..r1 with their label's shared values held, each from its own
        parameters as the label stage left them (``LabelResult.beta``) and the grid's best
        (:func:`~pbrdf_cl.fitting.images.pixel_fit.fit_block`'s ``starts``): a dict of flat
        per-pixel result arrays (those of :meth:`BatchJob.fit_rows`, and ``label``)."""
        if self.result is None:
            raise RuntimeError("internal: LabelJob.prepare() must run before its blocks")
        raw = self.read_rows(r0, r1)
        p = raw["dop"].shape[0]
        off = r0 * int(np.prod(self.source.shape[1:], dtype=np.int64))
        lab = self.label_index[off:off + p]
        out = self.empty_outputs(r1 - r0)
        out["status"][:] = -1
        out["label"][:] = self.labels[off:off + p]
        res, names = self.result, self.names
        si, bi = [names.index(n) for n in self.shared], [names.index(n) for n in self.own]
        for L in np.unique(lab[lab >= 0]):
            idx = np.flatnonzero(lab == L)
            if res.status[L] == -2:
                out["status"][idx] = -2
                continue
            held = held_setup(self.setup, self.shared, res.theta[L])
            starts = None if res.beta is None else res.beta[off + idx][:, [self.own.index(n) for n in held.free]]
            o = fit_block(eng, held, take(raw, idx), self.order_own, self.rstart_own, self.own, starts)
            for k, v in o.items():
                if k in ("x", "stderr", "ci95", "determined"):
                    out[k][idx[:, None], bi] = v
                else:
                    out[k][idx] = v
            ok = idx[o["status"] >= 0]
            out["x"][ok[:, None], si] = res.theta[L]
            out["stderr"][ok[:, None], si] = res.stderr[L]
            out["ci95"][ok[:, None], si] = res.ci95[L]
            out["determined"][ok[:, None], si] = res.determined[L]
        return out

    def empty_outputs(self, rows):
        """:meth:`BatchJob.empty_outputs` and the pixels' ``label``."""
        p = rows * int(np.prod(self.source.shape[1:], dtype=np.int64))
        return {**empty_outputs(p, len(self.names)), "label": np.zeros(p, np.int64)}

    def dataset(self, out, seconds=None):
        """The result Dataset: :meth:`BatchJob.dataset`'s, the pixels' ``labels`` and the labels'
        variables over a ``label`` dimension (:func:`label_variables`)."""
        ds = make_dataset(self, out, seconds)
        ds["labels"] = (self.source.dims, out["label"].reshape(self.source.shape),
                        {"long_name": "label of the pixel (0: not fitted)"})
        return label_variables(ds, self)

    def store_settings(self):
        """What a store's settings add for this job: the shared parameters, the label image's SHA-256
        and the label stage's values (a resumed store must have been fitted with the same)."""
        res = self.result
        return {"shared": list(self.shared), "labels_sha256": hashlib.sha256(self.labels.tobytes()).hexdigest(),
                "label_values": None if res is None else np.asarray(res.theta, float).round(12).tolist()}


class UnsharedLabelJob(BatchJob):
    """The job of ``fit_batch(stack, labels=L, shared=())``: nothing is shared, so every pixel is
    fitted on its own, as without labels, but label 0 still means "not fitted" (it is masked) and a
    note says so."""

    def __init__(self, data, model="six-param", bounds=None, fixed=None, shadowing="paper", *, labels, **settings):
        super().__init__(data, model, bounds, fixed, shadowing, **settings)
        self.labels = check_labels(labels, self.source)
        mask = self.labels.reshape(self.source.shape) > 0
        given = self.source.vars.get("mask")
        if given is not None:
            mask &= np.broadcast_to(np.asarray(getattr(given, "values", given), bool), mask.shape)
        self.source.vars["mask"] = mask
        self.notes.append("shared names nothing: every pixel is fitted on its own (the labels only mark label 0 "
                          "as not fitted)")

    def store_settings(self):
        """The label image's SHA-256 (it masks pixels) and the empty shared list."""
        return {"shared": [], "labels_sha256": hashlib.sha256(self.labels.tobytes()).hexdigest()}


#: What the labels' intervals leave out (the result's ``label_interval_note``; the CLI prints it).
LABEL_INTERVAL_NOTE = ("the label values are corrected for the bias that the pixels' many own parameters give the "
                       "shared ones (their integrated likelihood); what bias remains does not shrink with the "
                       "label's pixels, so a label of more than 96 pixels has the interval of 96 of them; the "
                       "intervals covered the truth 48 of 48 times on the two-material bench (128 pixels a label) "
                       "and 177 of 192 on stacks of 72 and 128 pixels a label at DOP noise 0.006-0.01 "
                       "(docs/joint_images.md)")
#: ... and with ``LabelJob.integrated`` off: the profile's values.
PROFILE_INTERVAL_NOTE = ("the label intervals leave out the bias that the pixels' many own parameters give the shared "
                         "ones: on the two-material bench they covered the truth 16 of 16 times at DOP noise 0.003, "
                         "14 of 16 at 0.006 and 9 of 16 at 0.01 (docs/joint_images.md)")


def label_variables(ds, job):
    """``ds`` with the labels' variables of ``job``'s label stage over a ``label`` dimension:
    ``label_<name>``, ``label_<name>_stderr``, ``label_<name>_ci95``, ``label_<name>_outside_ci95``
    for each shared parameter, ``label_corr`` (label, shared_param, shared_param_2), ``label_pixels``,
    ``label_chi2``, ``label_sse``, ``label_dof``, ``label_p_value``, ``label_fits_data`` and
    ``label_status``; attrs: the labels' goodness of fit (:func:`label_goodness_summary`) and
    ``label_cov_note`` where a label's covariance was projected or is NaN."""
    res = job.result
    dims = ("label",)
    new = {}  # assigned at once: one merge, not one per variable
    for j, n in enumerate(res.shared):
        new[f"label_{n}"] = (dims, res.theta[:, j], {"units": "1", "long_name": f"{n} shared by the label's pixels"})
        new[f"label_{n}_stderr"] = (dims, res.stderr[:, j], {"units": "1", "long_name": f"standard error of label {n}"})
        new[f"label_{n}_ci95"] = (dims + ("bound",), res.ci95[:, j],
                                 {"units": "1", "long_name": f"95% interval of label {n} (+- 1.96 standard errors cut "
                                                             "at the bounds, k's holding k^2's; widened to the "
                                                             "profile's nodes it allows)"})
        new[f"label_{n}_outside_ci95"] = (dims, outside_interval(res.theta[:, j], res.ci95[:, j, 0], res.ci95[:, j, 1]),
                                         {"long_name": OUTSIDE_FOOTNOTE})
    new["label_corr"] = (dims + ("shared_param", "shared_param_2"), res.corr,
                        {"units": "1", "long_name": "correlation of the label's shared parameters (NaN where it "
                                                    "cannot be computed; see label_cov_note)"})
    new["label_pixels"] = (dims, res.pixels, {"long_name": "pixels fitted in the label stage"})
    new["label_chi2"] = (dims, res.chi2, {"long_name": "weighted sum of squared residuals over the label's pixels"})
    new["label_sse"] = (dims, res.sse, {"units": "1", "long_name": "sum of squared DOP residuals over the label's "
                                                                  "pixels"})
    new["label_dof"] = (dims, res.dof, {"long_name": "degrees of freedom: residuals less every fitted parameter"})
    new["label_p_value"] = (dims, res.p_value, {"units": "1", "long_name": "p-value of the label's goodness-of-fit "
                                               "test: " + _LABEL_TESTS[res.goodness_test][1]})
    new["label_fits_data"] = (dims, res.fits_data, {
        "long_name": f"whether the label's shared values describe its pixels' data: label_p_value >= {GOODNESS_P:g}",
        "flag_values": [1, 0, -1], "flag_meanings": "fits does_not_fit not_tested"})
    new["label_status"] = (dims, res.status, {
        "long_name": "label fit status", "flag_values": list(LABEL_STATUS),
        "status_codes": "; ".join(f"{c}: {n} ({m})" for c, (n, m) in LABEL_STATUS.items()),
        "flag_meanings": " ".join(n for n, _ in LABEL_STATUS.values())})
    ds = ds.assign(new)
    ds = ds.assign_coords(label=res.ids, shared_param=list(res.shared), shared_param_2=list(res.shared))
    ds.attrs.update(shared=" ".join(res.shared), label_rounds=int(res.rounds),
                    shared_note=("the pixels of a label share " + ", ".join(res.shared) + ": their per-pixel values, "
                                 "stderr and intervals are the label's; the other parameters' intervals hold the "
                                 "shared ones at the label's values"),
                    label_interval_note=LABEL_INTERVAL_NOTE if job.integrated else PROFILE_INTERVAL_NOTE,
                    **label_goodness_summary(res))
    notes = [n for n in res.cov_notes if n]
    if notes:
        ds.attrs["label_cov_note"] = "\n".join(notes)  # one note a line
    return ds


#: The labels' goodness-of-fit tests (``LabelResult.goodness_test``): (name, what it is).
_LABEL_TESTS = {"chi2": ("chi2 test", "chi2 for its degrees of freedom (label_chi2, label_dof)"),
                "F": ("F test against the pixels' own fits", "F test of its shared values against each pixel's own on "
                      f"a subsample of at most {label_search.SUBSAMPLE} of its pixels (without dop_std, or f00_std "
                      "with intensities, the chi2 has no known scale)")}


def label_goodness_summary(res):
    """Whether each label's shared values describe its pixels' data: the attrs
    :func:`pbrdf_cl.fit_batch` adds to a result with labels.

    Each pixel's own parameters absorb the misfit of shared values that do not fit it (two
    materials under one label), so every pixel passes its own test: only the label's tells.

    Parameters
    ----------
    res : pbrdf_cl.fitting.images.label_stage.LabelResult
        The label stage's result (its ``p_value``, ``fits_data``, ``goodness_test``, ``chi2``,
        ``dof``).

    Returns
    -------
    dict
        ``label_goodness`` (a line: how many of the tested labels fail, which, their chi2 and
        p-values) and, where a label fails, ``label_goodness_warning`` (a WARNING line naming the
        labels, with the usual causes, ``pbrdf_cl.fitting.common.LABEL_MISTAKE_CAUSES``).

    Examples
    --------
    >>> res = fit_batch(stack, labels=L)  # doctest: +SKIP
    >>> res.attrs["label_goodness_warning"][:40]  # doctest: +SKIP
    'WARNING: the shared n, k of label 1 do n'
    """
    tested = res.fits_data >= 0
    bad = np.flatnonzero(res.fits_data == 0)
    out = {"label_goodness": f"label goodness of fit: {bad.size} of {int(tested.sum())} tested labels fail the "
                             f"{_LABEL_TESTS[res.goodness_test][0]} (p < {GOODNESS_P:g})"}
    if bad.size:
        chi2 = res.goodness_test == "chi2"
        what = "; ".join(f"label {res.ids[i]}: " + (f"chi2 {res.chi2[i]:.4g} for {res.dof[i]} degrees of freedom, "
                                                     if chi2 else "") + f"p = {res.p_value[i]:.2g}" for i in bad)
        names = ", ".join(str(res.ids[i]) for i in bad)
        out["label_goodness"] += f" ({what})"
        out["label_goodness_warning"] = (
            f"WARNING: the shared {', '.join(res.shared)} of label{'s' if bad.size > 1 else ''} {names} do not "
            f"describe {'their' if bad.size > 1 else 'its'} pixels' data ({what}; label_fits_data = 0): each pixel's "
            "own parameters absorb the misfit, so the pixels' own tests pass, but the label's values and intervals are "
            f"not to be trusted; usual causes: {LABEL_MISTAKE_CAUSES}")
    return out
