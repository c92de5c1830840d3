"""The label stage on ``dask.distributed`` workers (issue #37 item 4): with ``workers=``,
``scheduler=`` or ``client=`` the label stage's passes over the blocks (profile, start, refinement,
subsample) run on the workers, one cluster serves the label stage and the per-pixel pass and is
closed at the end (on an error too), and the result is the in-memory one bit for bit."""
import numpy as np
import pytest

import pbrdf_cl
from pbrdf_cl.fitting.images import label_stage
from pbrdf_cl.fitting.images.job import BatchJob
from pbrdf_cl.fitting.images.labels import LabelJob

distributed = pytest.importorskip("distributed")

PASSES = ("profile", "evaluate", "gather")


@pytest.fixture
def stack():
    """Two materials, 8 x 6 pixels (3 unlabelled), in blocks of two rows: (data, labels, budget)."""
    from conftest import DEVICES
    if not DEVICES:
        pytest.skip("no OpenCL device")
    from test_batch_labels import two_materials
    data, lab = two_materials(8, 6, 0.003, seed=2, unlabelled=3)
    job = BatchJob(data)
    budget = job.fixed_bytes() + job.pixel_bytes() * 6 * 2
    assert len(LabelJob(data, labels=lab, memory_budget=budget).blocks()) == 4
    return data, lab, budget


@pytest.fixture
def clusters(monkeypatch):
    """The LocalClusters a run starts (distributed.LocalCluster, counted)."""
    made = []

    class Counted(distributed.LocalCluster):
        def __init__(self, *args, **kw):
            super().__init__(*args, **kw)
            made.append(self)
    monkeypatch.setattr(distributed, "LocalCluster", Counted)
    return made


def same(ds, mem):
    for name in mem.data_vars:
        np.testing.assert_array_equal(ds[name].values, mem[name].values, err_msg=name)


def test_labels_on_two_workers_equal_in_memory_block_by_block(stack, clusters, tmp_path):
    """A label fit in 4 blocks on 2 local workers (label stage and per-pixel pass there) equals the
    in-memory fit bit for bit, every variable; one LocalCluster served both steps and is closed."""
    data, lab, budget = stack
    mem = pbrdf_cl.fit_batch(data, labels=lab, memory_budget=budget)
    ds = pbrdf_cl.fit_batch(data, labels=lab, memory_budget=budget, store=tmp_path / "fit.zarr", workers=2)
    same(ds, mem)
    assert len(clusters) == 1 and clusters[0].status.name == "closed"


def test_the_label_stage_passes_run_on_the_workers(stack, monkeypatch, tmp_path):
    """Through a client, every block of every pass of the label stage is a task that a worker ran
    (dask's task stream), none was computed here (the block functions are counted in this
    process: the workers are other processes), and the result is the in-memory one."""
    data, lab, budget = stack
    mem = pbrdf_cl.fit_batch(data, labels=lab, memory_budget=budget)
    here = []
    for kind in PASSES:
        name = f"{kind}_block"
        original = getattr(label_stage.Passes, name)
        monkeypatch.setattr(label_stage.Passes, name,
                            lambda self, *a, _f=original, _k=kind: here.append(_k) or _f(self, *a))
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None) as lc, \
            distributed.Client(lc) as client, distributed.get_task_stream(client) as ts:
        ds = pbrdf_cl.fit_batch(data, labels=lab, memory_budget=budget, store=tmp_path / "fit.zarr", client=client)
        workers = set(client.nthreads())
    same(ds, mem)
    assert here == []
    tasks = [t for t in ts.data if str(t["key"]).startswith("pbrdf-labels-")]
    assert {t["worker"] for t in tasks} <= workers
    per = {k: sum(str(t["key"]).startswith(f"pbrdf-labels-{k}-") for t in tasks) for k in PASSES}
    # one pass of the profile, two gathers (the search's subsample and the default integrated
    # likelihood's pixels: the correction runs with the workers' data too); the start's pass and
    # the refinement's
    assert per["profile"] == 4 and per["gather"] == 8 and per["evaluate"] >= 8, per
    assert sum(per.values()) % 4 == 0 and sum(per.values()) == len(tasks)


def test_a_worker_error_is_one_line_and_closes_the_cluster(stack, clusters, tmp_path):
    """A value refused on a worker (in the profile pass's check of the block's rows) comes back as
    its one-line error; the LocalCluster started for the run is closed."""
    data, lab, budget = stack
    dop = data["dop"].copy()
    dop[5, 1, 3] = 1.5  # in the third block
    with pytest.raises(ValueError, match=r"^dop must be in \[0, 1\].*got 1\.5") as err:
        pbrdf_cl.fit_batch({**data, "dop": dop}, labels=lab, memory_budget=budget, store=tmp_path / "fit.zarr",
                           workers=2)
    assert "\n" not in str(err.value)
    assert len(clusters) == 1 and clusters[0].status.name == "closed"
