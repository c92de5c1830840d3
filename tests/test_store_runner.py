"""The one runner of the resumable stores (pbrdf_cl.store.runner), on both of its jobs: a sweep
and an image fit into a store take the same cluster options, checked by one function (issue #35:
the two copies had drifted apart, the sweep refusing numpy integers for ``workers`` and running
a cluster with ``engine=`` given, the image fit the opposite).  The unified rule: ``workers`` is
a positive integer, Python's or numpy's; ``engine=`` is for a local run, refused with a cluster,
whose workers build their own engines (``device=``, ``backend=``)."""
import numpy as np
import pytest

import pbrdf_cl
from pbrdf_cl.store import cluster

TI, TR = np.repeat([30.0, 40, 50], 10), np.tile(np.arange(20.0, 66, 5), 3)
STACK = dict(dop=np.broadcast_to(pbrdf_cl.dop(TI, TR, n=1.6, k=2.139, sigma=0.5, kd=0.15, c=-0.3, backend="numpy"),
                                 (2, 2, 30)), theta_i=TI, theta_r=TR)
SPEC = dict(axes=dict(theta_r="0:80:20", sigma=[0.2, 0.5]), fixed=dict(theta_i=40, n=1.6, k=2.1),
            chunks=dict(theta_r=2))
PATHS = {
    "sweep": lambda store, **kw: pbrdf_cl.sweep(SPEC, store, progress=False, **kw),
    "fit": lambda store, **kw: pbrdf_cl.fit_batch(STACK, store=store, **kw),
}


@pytest.fixture
def cluster_here(monkeypatch, tmp_path):
    """run_on_cluster replaced by a loop here over the same tasks (no cluster is started); returns
    the ``workers`` each run was given."""
    pytest.importorskip("distributed")  # the check refuses a cluster run without it
    monkeypatch.setenv("POCL_CACHE_DIR", str(tmp_path / "pocl"))  # what a worker's engine sets, undone after
    seen = []

    def in_process(task, shared, items, args_of, key, finished, *, workers=None, scheduler=None, client=None):
        seen.append(workers)
        for i in items:
            finished(task(shared, *args_of(i)))
    monkeypatch.setattr(cluster, "run_on_cluster", in_process)
    return seen


@pytest.mark.parametrize("path", PATHS)
def test_numpy_integer_workers_are_accepted_on_both_paths(path, cluster_here, tmp_path):
    PATHS[path](tmp_path / "s.zarr", workers=np.int64(2), backend="numpy")
    assert cluster_here == [2] and type(cluster_here[0]) is int
    assert pbrdf_cl.store.zarr.read_done(tmp_path / "s.zarr", 2 if path == "sweep" else 1).all()


@pytest.mark.parametrize("path", PATHS)
@pytest.mark.parametrize("workers", [0, np.int64(-1), 2.0, True, np.bool_(True), "2"], ids=repr)
def test_other_workers_are_refused_on_both_paths(path, workers, cluster_here, tmp_path):
    with pytest.raises(ValueError) as err:
        PATHS[path](tmp_path / "s.zarr", workers=workers, backend="numpy")
    assert str(err.value) == f"workers must be a positive integer, got {workers!r}"
    assert not cluster_here and not (tmp_path / "s.zarr").exists()


@pytest.mark.parametrize("path", PATHS)
@pytest.mark.parametrize("where", [dict(workers=2), dict(scheduler="tcp://nowhere:1")], ids=["workers", "scheduler"])
def test_an_engine_with_a_cluster_is_refused_on_both_paths(path, where, cluster_here, tmp_path):
    with pytest.raises(ValueError) as err:
        PATHS[path](tmp_path / "s.zarr", engine=pbrdf_cl.NumpyEngine(), **where)
    assert str(err.value) == "engine= is for a local run; every cluster worker builds its own (device=, backend=)"
    assert not cluster_here and not (tmp_path / "s.zarr").exists()


@pytest.mark.parametrize("path", PATHS)
def test_an_engine_runs_locally_on_both_paths(path, cluster_here, tmp_path):
    PATHS[path](tmp_path / "s.zarr", engine=pbrdf_cl.NumpyEngine())
    assert not cluster_here and pbrdf_cl.store.zarr.read_done(tmp_path / "s.zarr", 1).all()
