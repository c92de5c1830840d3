"""How the per-point inputs reach the kernels and the results come back (:meth:`Engine.evaluate
<pbrdf_cl.device.opencl.Engine.evaluate>`'s work): each input's index rule (:func:`input_plan`: one
value, one per point, or a broadcast axis sent once as a table with its rule, issue #12), the
kernels' rule tables (:func:`rule_table`), the launches over host memory read and written in place
on a CPU device (inputs converted or gathered launch by launch only where they must be), and the
transfer pipeline of a device with its own memory (pinned staging, copies overlapped with compute);
:func:`aligned_empty`, the page-aligned arrays every driver writes in place."""
from __future__ import annotations

import dataclasses
import math

import numpy as np

from ..model import quantities
from .sources import DTYPES, POINT_INPUTS, POINT_LOCAL_SIZE, cl

#: Points per kernel launch; bounds the temporary device memory of one call.
LAUNCH_POINTS = 1 << 22
#: The most points of a launch of the broadcast kernels: their 32-bit index arithmetic counts on
#: it (see :data:`RULE_MAX`).
RULE_LAUNCH_MAX = 1 << 22
#: Points per launch when inputs must be converted or gathered first (another dtype, a broadcast
#: view that is not one run of axes): bounds the host memory of the converted copies (9 inputs x
#: 2^19 x 8 bytes = 38 MB).
CONVERT_POINTS = 1 << 19
#: The most values of a broadcast input's table (:func:`broadcast_table`, a copy sent once): a
#: larger one is gathered launch by launch instead, so that memory stays within the same bound.
TABLE_POINTS = 1 << 19


def vector_kernel(quantity, flat):
    """The stem of the vector per-point kernels of ``quantity`` for the inputs ``flat`` (name ->
    values, one value where it is the same at every point): ``dop_conductor`` for the DOP where kd
    is one value, 0 (a conductor: the DOP then depends on neither the shadowing nor sigma nor ks,
    and that kernel does not compute them; the same values bit for bit), else the quantity's name."""
    kd = flat.get("kd")
    if quantity == "dop" and kd is not None and np.size(kd) == 1 and float(np.ravel(kd)[0]) == 0.0:
        return "dop_conductor"
    return quantity


def evaluate(eng, quantity, inputs, shape, dtype, shadowing):
    """``quantity`` at every point of ``shape`` on the OpenCL engine ``eng``: the work of
    :meth:`pbrdf_cl.device.opencl.Engine.evaluate` (see there)."""
    npdt = np.dtype(DTYPES[dtype])
    q = quantities.get(quantity, "points")
    vec = eng.checks_domain(q.name)
    lanes = eng.vector_width[dtype] if vec else 1
    shape = tuple(int(n) for n in shape)
    size = math.prod(shape)
    width = q.width
    out = aligned_empty(size * width, npdt)  # page-aligned: every driver writes it in place
    if size == 0:
        return out.reshape(shape + q.trailing)
    plan, flat, values = point_inputs(eng, inputs, shape, npdt, lanes)
    name = vector_kernel(q.name, flat)
    if values:  # a broadcast input: the twin kernel, reading each input through its rule
        kern = (eng.kernel(f"{name}_bcast_points_vec", dtype, shadowing) if vec
                else eng.kernel("quantity_bcast_points", dtype, shadowing, q.name))
    else:
        kern = (eng.kernel(f"{name}_points_vec", dtype, shadowing) if vec
                else eng.kernel("quantity_points", dtype, shadowing, q.name))
        plan = None
    if eng.overlaps_transfers:
        _TransferPipeline(eng, kern, flat, values, plan, npdt, lanes, vec, width).run(size, out)
        return out.reshape(shape + q.trailing)
    host = eng.host_memory
    sent = {n: input_buffer(eng, v, npdt, host) for n, v in values.items()}  # once per call
    # inputs the device cannot read in place are converted launch by launch: smaller launches
    staged = [n for n, a in flat.items() if a.size != 1 and not eng.can_use_in_place(a, npdt)]
    step = min(CONVERT_POINTS if staged else LAUNCH_POINTS, _launch_limit(plan)) // lanes * lanes
    # page-aligned staging arrays, reused by every launch (each completes before the next is filled)
    stage = {n: aligned_empty(min(step, size) + lanes, npdt) for n in staged}

    def parts_of(s0, s1, padded):  # the inputs of points s0..s1, padded to ``padded`` points
        parts = dict(sent)
        for n, a in flat.items():
            if a.size == 1:
                parts[n] = a
                continue
            if n in stage:
                dst = stage[n][:padded]
                _gather(dst, a, s0, s1)
            else:
                if padded == s1 - s0:
                    parts[n] = a[s0:s1]
                    continue
                dst = np.empty(padded, npdt)
                dst[:s1 - s0] = a[s0:s1]
            dst[s1 - s0:] = dst[s1 - s0 - 1]  # padding: copies of the last point
            parts[n] = dst
        return parts
    for start in range(0, size, step):
        count = min(step, size - start)
        whole = count // lanes * lanes
        if whole:
            launch_points(eng, kern, parts_of(start, start + whole, whole), whole,
                          out[start * width:(start + whole) * width], npdt, lanes, vec, host,
                          None if plan is None else rule_table(plan, start))
        if whole < count:  # the last few points, padded to a whole vector
            tail = count - whole
            padded = lanes if vec else tail
            tmp = np.empty(padded * width, npdt)
            launch_points(eng, kern, parts_of(start + whole, start + count, padded), padded, tmp, npdt, lanes,
                          vec, host, None if plan is None else rule_table(plan, start + whole))
            out[(start + whole) * width:(start + count) * width] = tmp[:tail * width]
    return out.reshape(shape + q.trailing)


def point_inputs(eng, inputs, shape, npdt, lanes):
    """``(plan, flat, values)`` of :func:`evaluate`'s inputs for kernels of ``lanes`` points
    per work-item: each input's rule (:func:`input_plan`, the broadcast ones as
    :func:`broadcast_table` lays them out; without ``eng.index_rules`` one value or one per
    point, as before issue #12), ``flat`` the one-value (a 1-value array of ``npdt``) and
    per-point inputs (1-d, or a strided or broadcast view of ``shape``), ``values`` the
    broadcast ones' tables (contiguous, of ``npdt``)."""
    if eng.index_rules:
        plan = input_plan(shape, inputs)
    else:
        plan = {n: IndexRule(SINGLE if np.size(a) == 1 else PER_POINT) for n, a in inputs.items()}
    flat, values = {}, {}
    for name in POINT_INPUTS:
        a = np.asarray(inputs[name])
        if plan[name].kind == BROADCAST:
            laid = broadcast_table(plan[name], compact_values(a, len(shape)), shape, lanes, npdt)
            if laid is not None:
                plan[name], values[name] = laid
                continue
            plan[name] = IndexRule(PER_POINT)  # a large table: gathered instead
        if plan[name].kind == SINGLE:
            flat[name] = np.array([a[(0,) * a.ndim]], npdt)  # one value, even of a broadcast view
            continue
        b = a if a.shape == shape else np.broadcast_to(a, shape)
        flat[name] = b.reshape(-1) if b.flags.c_contiguous else b
    return plan, flat, values


def input_buffer(eng, a, npdt, host):
    """A read-only buffer of the contiguous 1-d array ``a`` of ``npdt``: over ``a`` itself on a
    CPU device, a device copy elsewhere (``a`` itself if it is a buffer already)."""
    if isinstance(a, cl.Buffer):
        return a
    if not host:
        return eng.to_device(a, npdt)
    a = np.ascontiguousarray(a, npdt)  # as it is, where evaluate has staged it
    return cl.Buffer(eng.context, cl.mem_flags.READ_ONLY | cl.mem_flags.USE_HOST_PTR, hostbuf=a)


def launch_points(eng, kern, parts, n, out, npdt, lanes, vec, host, rules=None):
    """One launch of a per-point kernel over ``n`` points (``parts``: name -> n values or one,
    or a buffer), its result in ``out`` (contiguous, n * width values) when this returns.
    ``rules``: the launch's :func:`rule_table`, for the broadcast twins (None: strides)."""
    out_buf, done = eng.output(out)
    args = [out_buf, np.int32(n // lanes)]
    for name in POINT_INPUTS:
        p = parts[name]
        args.append(input_buffer(eng, p, npdt, host))
        if rules is None:
            args.append(np.int32(0 if p.size == 1 else 1))
    if rules is not None:
        args.append(rules_buffer(eng, rules))
    # a small work-group (POINT_LOCAL_SIZE): PoCL keeps every work-item's private state of a
    # group on one thread's stack, and the vector kernels' state overflows it in the large groups
    # it picks itself
    eng.launch(kern, (n // lanes,), *args, local_size=(POINT_LOCAL_SIZE,) if vec else None)
    done()


def rules_buffer(eng, table):
    """A read-only device copy of a launch's :func:`rule_table` (a few hundred bytes)."""
    return cl.Buffer(eng.context, cl.mem_flags.READ_ONLY | cl.mem_flags.COPY_HOST_PTR, hostbuf=table)


class _TransferPipeline:
    """Per-point evaluation on a device with its own memory (a GPU): two slots, each a set of
    pinned (``ALLOC_HOST_PTR``, mapped) host staging arrays and device buffers; while the kernel of
    launch k runs on the engine's queue, a second queue uploads the inputs of launch k + 1 and
    reads back the result of launch k - 1, straight into its slice of the result.  A single value
    and a broadcast input's compact values (``values``, read through the rules of ``plan``) are
    uploaded once.  Memory beyond the inputs and the result: two launches' worth."""

    SLOTS = 2

    def __init__(self, eng, kern, flat, values, plan, npdt, lanes, vec, width):
        self.eng, self.kern, self.flat, self.npdt, self.plan = eng, kern, flat, npdt, plan
        self.lanes, self.vec, self.width = lanes, vec, width
        self.names = [n for n in POINT_INPUTS if n in flat and flat[n].size != 1]
        self.single = {n: eng.to_device(a, npdt) for n, a in {**flat, **values}.items() if n not in self.names}
        self.copies = eng.copy_queue

    def _slot(self, cap):
        mf, ctx, isz = cl.mem_flags, self.eng.context, self.npdt.itemsize
        pinned, host = {}, {}
        for n in self.names:
            pinned[n] = cl.Buffer(ctx, mf.READ_WRITE | mf.ALLOC_HOST_PTR, cap * isz)
            host[n], _ = cl.enqueue_map_buffer(self.copies, pinned[n], cl.map_flags.WRITE | cl.map_flags.READ, 0,
                                               (cap,), self.npdt)
        return dict(pinned=pinned, host=host, done=None,
                    dev={n: cl.Buffer(ctx, mf.READ_ONLY, cap * isz) for n in self.names},
                    out=cl.Buffer(ctx, mf.WRITE_ONLY, cap * self.width * isz))

    def run(self, size, out):
        step = min(LAUNCH_POINTS, _launch_limit(self.plan)) // self.lanes * self.lanes
        cap = min(step, size) + self.lanes
        slots = [self._slot(cap) for _ in range(self.SLOTS)]
        tails = []
        try:
            for k, start in enumerate(range(0, size, step)):
                slot = slots[k % self.SLOTS]
                if slot["done"] is not None:
                    slot["done"].wait()  # its last read is in: its staging and buffers are free
                count = min(step, size - start)
                padded = -(-count // self.lanes) * self.lanes
                uploads = []
                for n in self.names:
                    dst = slot["host"][n][:padded]
                    _gather(dst, self.flat[n], start, start + count)
                    dst[count:] = dst[count - 1]  # padding: copies of the last point
                    uploads.append(cl.enqueue_copy(self.copies, slot["dev"][n], dst, is_blocking=False))
                args = [slot["out"], np.int32(padded // self.lanes)]
                for n in POINT_INPUTS:
                    args.append(slot["dev"][n] if n in slot["dev"] else self.single[n])
                    if self.plan is None:
                        args.append(np.int32(1 if n in slot["dev"] else 0))
                if self.plan is not None:
                    args.append(rules_buffer(self.eng, rule_table(self.plan, start)))
                ran = self.eng.launch(self.kern, (padded // self.lanes,), *args,
                                      local_size=(POINT_LOCAL_SIZE,) if self.vec else None, wait_for=uploads)
                w = self.width
                if padded == count:
                    dst = out[start * w:(start + count) * w]
                else:  # the last few points: read whole vectors, keep the real ones
                    dst = np.empty(padded * w, self.npdt)
                    tails.append((dst, start, count))
                slot["done"] = cl.enqueue_copy(self.copies, dst, slot["out"], is_blocking=False, wait_for=[ran])
            self.copies.finish()
            for dst, start, count in tails:
                out[start * self.width:(start + count) * self.width] = dst[:count * self.width]
        finally:
            self.copies.finish()
            for slot in slots:
                for n in self.names:
                    slot["host"][n].base.release(self.copies)
            self.copies.finish()


def aligned_empty(n, dtype, align=4096):
    """``np.empty(n, dtype)`` whose data starts at a multiple of ``align`` bytes."""
    dtype = np.dtype(dtype)
    raw = np.empty(n * dtype.itemsize + align, np.uint8)
    skip = -raw.ctypes.data % align
    return raw[skip:skip + n * dtype.itemsize].view(dtype)


# ---------------------------------------------------------------------------------------------
# broadcast inputs: index rules (issue #12)

#: The kinds of :class:`IndexRule`: one value, one value per point, a broadcast rule.
SINGLE, PER_POINT, BROADCAST = 0, 1, 2
#: The largest ``div`` and ``mod`` of a broadcast rule: with launches of at most
#: :data:`RULE_LAUNCH_MAX` points every numerator of the kernels' index arithmetic stays below 2^31
#: (``PB_UDIV`` in pbrdf_points.cl).
RULE_MAX = 1 << 30
#: The fields of one input's row of the kernels' ``rules`` table, in order (``PB_R_*`` there).
RULE_FIELDS = ("kind", "div", "div_m", "div_s", "mod", "mod_m", "mod_s", "r0", "q0")


@dataclasses.dataclass(frozen=True)
class IndexRule:
    """How the kernels read one input at flat point t (C order) of the broadcast shape S.

    ``kind`` :data:`SINGLE` (0): its one value.  :data:`PER_POINT` (1): value t of the input as
    broadcast to S (read in place, or gathered launch by launch).  :data:`BROADCAST` (2): value
    ``(t // div) % mod`` of its compact values (:func:`compact_values`), where its axes other than
    1 are one run ``axes = (p, q)`` of S's axes, ``div = prod(S[q:])``, ``mod = prod(S[p:q])``."""

    kind: int
    div: int = 1
    mod: int = 1
    axes: tuple = ()


def _launch_limit(plan):
    """The most points of one launch: any number with strides, :data:`RULE_LAUNCH_MAX` with rules."""
    return RULE_LAUNCH_MAX if plan is not None else 1 << 62


def effective_shape(a, ndim):
    """``a``'s shape right-aligned to ``ndim`` axes, with 1 wherever it holds one value: an axis of
    length 1, or one of stride 0 (a broadcast view)."""
    a = np.asarray(a)
    lead = (1,) * (ndim - a.ndim)
    return lead + tuple(1 if n == 1 or st == 0 else n for n, st in zip(a.shape, a.strides))


def compact_values(a, ndim):
    """The values of ``a`` on its :func:`effective_shape` (a stride-0 axis taken once), a view of
    that shape: in C order they are the values a :data:`BROADCAST` rule indexes."""
    a = np.asarray(a)
    a = a.reshape((1,) * (ndim - a.ndim) + a.shape)
    return a[tuple(slice(0, 1) if st == 0 else slice(None) for st in a.strides)]


def input_plan(shape, arrays):
    """The :class:`IndexRule` of each array (by name) broadcast to ``shape``.

    An array (or broadcast view) that holds one value is :data:`SINGLE`; one with a value per
    point, :data:`PER_POINT`; one whose other axes are one contiguous run of ``shape``'s axes (a
    short axis ``theta_r[:, None]`` against ``sigma[None, :]``, a scalar per row or per column, a
    run like (1, B, C, 1) in (A, B, C, D)), :data:`BROADCAST`, sent once with its rule.  Any
    other pattern, (A, 1, C) in (A, B, C) for instance, and a rule whose ``div`` or ``mod``
    exceeds :data:`RULE_MAX`, stays :data:`PER_POINT`: gathered launch by launch, correct but not
    sent once.

    Examples
    --------
    >>> plan = input_plan((3, 4), dict(a=np.ones((3, 1)), b=np.ones(4), c=2.0, d=np.ones((3, 4))))
    >>> [(r.kind, r.div, r.mod) for r in plan.values()]
    [(2, 4, 3), (2, 1, 4), (0, 1, 1), (1, 1, 1)]
    """
    shape = tuple(int(n) for n in shape)
    return {name: _rule(shape, effective_shape(a, len(shape))) for name, a in arrays.items()}


def _rule(shape, eff):
    size = math.prod(eff)
    if size == 1:
        return IndexRule(SINGLE)
    if size == math.prod(shape):
        return IndexRule(PER_POINT)
    run = [j for j, n in enumerate(eff) if n != 1]
    p, q = run[0], run[-1] + 1
    if any(eff[j] != shape[j] for j in range(p, q)):
        return IndexRule(PER_POINT)  # not one run of axes
    div = math.prod(shape[q:])
    if div > RULE_MAX or size > RULE_MAX:
        return IndexRule(PER_POINT)
    return IndexRule(BROADCAST, div, size, (p, q))


def broadcast_table(rule, compact, shape, lanes, dtype):
    """``(rule, table)``: the values the kernels read for the :data:`BROADCAST` ``rule`` of an
    input whose :func:`compact_values` are ``compact``, and the rule they read them with; None
    when the table would hold more than :data:`TABLE_POINTS` values (gather that input instead).

    ``lanes`` = 1 (one point per work-item): the compact values as they are.  ``lanes`` = N (the
    vector kernels, N points per work-item) lays them out so that each work-item's N values are
    one vector load or a choice between two values (``pb_in_rule`` in pbrdf_points.cl): a rule
    with 1 < div < N is widened over its trailing axes to div = 1 (its values repeated div times,
    fewer than N-fold); a div = 1 table repeats its first N - 1 values at its end, a div >= N
    table its first value, so no read wraps or leaves the table.
    """
    p = rule.axes[0]
    if lanes > 1 and 1 < rule.div < lanes:
        compact = np.broadcast_to(compact[(0,) * p], shape[p:])
        rule = IndexRule(BROADCAST, 1, math.prod(shape[p:]), (p, len(shape)))
    halo = 0 if lanes == 1 else lanes - 1 if rule.div == 1 else 1
    if rule.mod + halo > TABLE_POINTS:
        return None
    flat = compact.reshape(-1)
    if halo:
        flat = flat[np.arange(rule.mod + halo) % rule.mod]
    return rule, np.array(flat, dtype)


def udiv_magic(d):
    """``(m, s)`` with ``n // d == ((2 n m) >> 32) >> s`` for every 0 <= n < 2^31 (1 <= d <= 2^31):
    ``s = ceil(log2 d)``, ``m = ceil(2^(31 + s) / d) < 2^32`` (Granlund and Montgomery 1994 with
    31-bit numerators), the kernels' ``PB_UDIV``."""
    s = (int(d) - 1).bit_length()
    return -(-(1 << (31 + s)) // int(d)), s


def rule_table(plan, start):
    """The kernels' ``rules`` table (uint32, :data:`RULE_FIELDS` per input of
    :data:`POINT_INPUTS`) for a launch whose first point is flat point ``start``: a broadcast
    rule's offsets ``r0 = start % div`` and ``q0 = (start // div) % mod`` computed here, exactly,
    so that the kernels' arithmetic stays within 32 bits at any ``start``."""
    table = np.zeros((len(POINT_INPUTS), len(RULE_FIELDS)), np.uint32)
    for j, name in enumerate(POINT_INPUTS):
        r = plan[name]
        table[j] = (r.kind, r.div, *udiv_magic(r.div), r.mod, *udiv_magic(r.mod), start % r.div,
                    (start // r.div) % r.mod)
    return table


def _gather(dst, a, start, stop):
    """Copy points start..stop of the array ``a`` (in C order, any strides: a broadcast view too)
    into the 1-d ``dst``, converting the dtype, without a temporary: the range is split into
    boxes of ``a``, each copied by ``np.copyto``."""
    for offset, box in _flat_boxes(a.shape, start, stop):
        view = a[box]
        np.copyto(dst[offset:offset + view.size].reshape(view.shape), view, casting="unsafe")


def _flat_boxes(shape, start, stop, lead=(), offset=0):
    """The flat range start..stop of an array of ``shape`` (C order) as boxes: yields
    ``(offset into the range, tuple of slices)``, at most 2 * len(shape) of them."""
    if start >= stop:
        return
    if not shape:
        yield offset, lead
        return
    inner = int(np.prod(shape[1:], dtype=np.int64))
    i0, r0 = divmod(start, inner)
    i1, r1 = divmod(stop, inner)
    if i0 == i1:
        yield from _flat_boxes(shape[1:], r0, r1, lead + (slice(i0, i0 + 1),), offset)
        return
    if r0:
        yield from _flat_boxes(shape[1:], r0, inner, lead + (slice(i0, i0 + 1),), offset)
        offset += inner - r0
        i0 += 1
    if i1 > i0:
        yield offset, lead + (slice(i0, i1),) + tuple(slice(0, n) for n in shape[1:])
        offset += (i1 - i0) * inner
    if r1:
        yield from _flat_boxes(shape[1:], 0, r1, lead + (slice(i1, i1 + 1),), offset)
