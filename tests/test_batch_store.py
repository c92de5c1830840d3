"""Per-pixel fits into Zarr stores (pbrdf_cl.fitting.images.store, pbrdf-cl fit-image): equal to fit_batch in
memory, resumable after Ctrl-C and kill -9 with a byte-identical store, the same store from a dask
LocalCluster, refused when the settings or the input differ, a lazy stack read block by block,
and the command line (store, PNG, one-line errors)."""
import importlib
import os
import signal
import subprocess
import sys
import time
import tracemalloc
from pathlib import Path

import numpy as np
import pytest
import xarray as xr

import pbrdf_cl
from pbrdf_cl import cli
from pbrdf_cl.fitting.images import batch
from pbrdf_cl.fitting.images.store import StoreError, open_result, read_progress, status_counts

from test_sweep import files, n_done  # the sweep store's helpers: the fit store has its layout

BS = importlib.import_module("pbrdf_cl.fitting.images.store")
PACKAGE_ROOT = str(Path(pbrdf_cl.__file__).resolve().parent.parent)
STEEL = dict(k=2.139, sigma=0.5, kd=0.15, c=-0.3)
TI, TR = np.repeat([30.0, 40, 50], 10), np.tile(np.arange(20.0, 66, 5), 3)


def make_stack(shape=(16, 16), seed=0):
    """Shared geometry, n varying over the rows, noise, one pixel without data."""
    rng = np.random.default_rng(seed)
    n = np.linspace(1.3, 2.2, shape[0])[:, None] * np.ones(shape[1:])
    dop = pbrdf_cl.dop(TI, TR, n=n[..., None], **STEEL)
    dop = np.clip(dop + rng.normal(0, 0.002, dop.shape), 0, 1)
    dop[0, 0] = np.nan
    return dict(dop=dop, theta_i=TI, theta_r=TR)


def budget_for(data, rows, **kw):
    """The smallest memory budget (bytes) with blocks of ``rows`` rows (BatchJob sizes the blocks)."""
    def rows_of(b):
        try:
            return batch.BatchJob(data, memory_budget=b, **kw).rows_per_block()
        except ValueError:  # below one row
            return 0
    lo, hi = 1 << 16, 1 << 34
    while hi - lo > 1:
        mid = (lo + hi) // 2
        lo, hi = (mid, hi) if rows_of(mid) < rows else (lo, mid)
    assert rows_of(hi) == rows
    return hi


BUDGET = budget_for(make_stack(), 4)  # 4 blocks of 4 rows of the 16 x 16 stack


def assert_same_values(a, b):
    assert sorted(a.data_vars) == sorted(b.data_vars)
    for v in a.data_vars:
        assert a[v].dims == b[v].dims and a[v].dtype == b[v].dtype, v
        assert np.array_equal(a[v].values, b[v].values, equal_nan=True), v


@pytest.fixture(scope="module")
def stack():
    return make_stack()


@pytest.fixture(scope="module")
def reference(stack, tmp_path_factory):
    """An uninterrupted local run into a store (through fit_batch's store=)."""
    store = tmp_path_factory.mktemp("ref") / "ref.zarr"
    ds = batch.fit_batch(stack, memory_budget=BUDGET, store=store)
    assert ds.attrs["blocks_computed"] == 4 and ds.attrs["blocks_skipped"] == 0 and ds.attrs["batch_complete"]
    return store


def traced_peak(run):
    """(run(), the peak of host allocations during it, tracemalloc)."""
    tracemalloc.start()
    try:
        out = run()
        return out, tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()


def test_store_equals_fit_batch_in_memory(stack, reference):
    mem = batch.fit_batch(stack, memory_budget=BUDGET)
    ds = open_result(reference)  # status an integer (xr.open_zarr masks its fill value, not computed)
    assert_same_values(mem, ds)
    for v in mem.data_vars:
        assert ds[v].attrs == mem[v].attrs, v
        assert ds[v].encoding["chunks"][0] == 4 and ds[v].encoding["chunks"][1:] == mem[v].shape[1:]  # a block a chunk
    for c in ("bound", "param"):
        assert list(ds[c].values) == list(mem[c].values)
    assert {k: v for k, v in ds.attrs.items() if k in mem.attrs} == {k: v for k, v in mem.attrs.items()
                                                                       if k != "seconds"}
    assert ds.attrs["batch_blocks"] == 4 and ds.attrs["batch_block_rows"] == 4 and ds.attrs["batch_complete"] is True
    assert ds.attrs["sweep_kernels_sha256"] == pbrdf_cl.device.engine.kernels_sha256()
    assert read_progress(reference) == (4, 4)
    assert "_sweep" not in ds.variables
    # the returned Dataset is the store's, in fit_batch's order of variables
    again = batch.fit_batch(stack, store=reference, memory_budget=BUDGET)
    assert list(again.data_vars) == list(mem.data_vars)
    assert again.attrs["blocks_computed"] == 0 and again.attrs["blocks_skipped"] == 4
    counts = status_counts(again)
    assert sum(counts.values()) == 256 and counts["too_few"] == 1 and counts == status_counts(mem)


def test_lazy_zarr_and_netcdf_stacks_with_per_pixel_geometry(tmp_path):
    """synthetic_stack (angles per pixel, dop_std) from .zarr and .nc files, read lazily: the same
    values as fit_batch of the stack in memory."""
    from pbrdf_cl.io.imagestack import synthetic_stack
    stack = synthetic_stack(size=8, n_lights=30, seed=0)
    stack.to_zarr(tmp_path / "s.zarr", zarr_format=2)
    stack.to_netcdf(tmp_path / "s.nc")
    budget = budget_for(stack, 2)
    mem = batch.fit_batch(stack, memory_budget=budget)
    for path in ("s.zarr", "s.nc"):
        ds = batch.fit_batch(str(tmp_path / path), store=tmp_path / f"{path}.out.zarr", memory_budget=budget)
        assert ds.attrs["batch_blocks"] == 4 and ds.attrs["geometry"] == "per pixel"
        assert_same_values(mem, ds)


def test_ctrl_c_then_resume_is_byte_identical(stack, reference, tmp_path, monkeypatch):
    calls = []
    fit_rows = batch.BatchJob.fit_rows

    def interrupted(self, eng, r0, r1):
        calls.append((r0, r1))
        if len(calls) == 3:
            raise KeyboardInterrupt
        return fit_rows(self, eng, r0, r1)
    monkeypatch.setattr(batch.BatchJob, "fit_rows", interrupted)
    store = tmp_path / "s.zarr"
    with pytest.raises(KeyboardInterrupt):
        batch.fit_batch(stack, store=store, memory_budget=BUDGET)
    assert read_progress(store) == (2, 4) and not xr.open_zarr(store).attrs["batch_complete"]
    calls.clear()
    monkeypatch.setattr(batch.BatchJob, "fit_rows", lambda self, eng, r0, r1: calls.append((r0, r1))
                        or fit_rows(self, eng, r0, r1))
    ds = batch.fit_batch(stack, store=store, memory_budget=BUDGET)
    assert calls == [(8, 12), (12, 16)]  # only the blocks not marked done (the interrupted one included)
    assert ds.attrs["blocks_computed"] == 2 and ds.attrs["blocks_skipped"] == 2 and ds.attrs["batch_complete"]
    assert_same_values(ds, open_result(reference))
    assert files(store) == files(reference)


def test_written_but_unmarked_block_is_recomputed(stack, reference, tmp_path):
    """Write-then-mark: a block without its done mark counts as missing, whatever its chunks hold."""
    store = tmp_path / "s.zarr"
    batch.fit_batch(stack, store=store, memory_budget=BUDGET)
    (store / "n" / "1.0").write_bytes(b"torn write")
    (store / "status" / "1.0").unlink()
    (store / "_sweep" / "done" / "1").unlink()
    (store / "sigma" / "0.0.1f2e3d4c.partial").write_bytes(b"left by a kill")
    ds = batch.fit_batch(stack, store=store, memory_budget=BUDGET)
    assert ds.attrs["blocks_computed"] == 1 and ds.attrs["blocks_skipped"] == 3
    assert files(store) == files(reference)


def test_kill_9_then_resume_is_byte_identical(stack, reference, tmp_path):
    np.savez(tmp_path / "stack.npz", **stack)
    store = tmp_path / "killed.zarr"
    cmd = [sys.executable, "-m", "pbrdf_cl", "fit-image", str(tmp_path / "stack.npz"), "--out", str(store),
           "--memory-budget", str(BUDGET), "--no-progress"]
    env = dict(os.environ, PYTHONPATH=PACKAGE_ROOT, PYTHONWARNINGS="ignore")
    proc = subprocess.Popen(cmd, env=dict(env, **{BS.DELAY_ENV: "1.0"}), stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE)
    try:
        # kill it in the second block, between writing its values and marking it done (the
        # delay's second half): its last variable's chunk is there, its mark is not
        deadline = time.monotonic() + 120
        while not (n_done(store) == 1 and (store / "status" / "1.0").exists()) and proc.poll() is None \
                and time.monotonic() < deadline:
            time.sleep(0.005)
        assert proc.poll() is None, proc.communicate()
        os.kill(proc.pid, signal.SIGKILL)
    finally:
        proc.kill()
        proc.communicate()
    done = n_done(store)
    assert proc.returncode == -signal.SIGKILL and done == 1 and (store / "status" / "1.0").exists()
    again = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=300, check=False)
    assert again.returncode == 0, again.stderr
    assert f"fit-image: {(4 - done) * 64} of 256 pixels fitted" in again.stdout
    assert f"({done * 64} already in the store" in again.stdout
    assert not list(store.rglob("*.partial"))
    assert files(store) == files(reference)  # the .npz stack and the dict are the same job


def test_local_cluster_gives_the_same_store(stack, reference, tmp_path, monkeypatch):
    pytest.importorskip("distributed")
    store = tmp_path / "cluster.zarr"
    # start locally, stop after one block, finish on a 2-worker cluster: the blocks land in one store
    fit_rows = batch.BatchJob.fit_rows
    calls = []

    def interrupted(self, eng, r0, r1):
        calls.append(r0)
        if len(calls) > 1:
            raise KeyboardInterrupt
        return fit_rows(self, eng, r0, r1)
    monkeypatch.setattr(batch.BatchJob, "fit_rows", interrupted)
    with pytest.raises(KeyboardInterrupt):
        batch.fit_batch(stack, store=store, memory_budget=BUDGET)
    monkeypatch.undo()

    def timeout(*_):
        raise TimeoutError("the LocalCluster fit hung")
    old = signal.signal(signal.SIGALRM, timeout)
    signal.alarm(240)
    try:
        ds = batch.fit_batch(stack, memory_budget=BUDGET, store=store, workers=2)
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, old)
    assert ds.attrs["blocks_skipped"] == 1 and ds.attrs["blocks_computed"] == 3 and ds.attrs["batch_complete"]
    assert_same_values(ds, open_result(reference))
    assert files(store) == files(reference)


def _refusal(store, data, **kw):
    with pytest.raises(StoreError) as info:
        batch.fit_batch(data, store=store, **{"memory_budget": BUDGET, **kw})
    text = str(info.value)
    assert "\n" not in text
    return text


@pytest.mark.parametrize("change,message", [
    (dict(fixed={"c": -0.3}), 'fixed.c: (absent) in the store, -0.3 now'),
    (dict(bounds={"n": (1.0, 3.0)}), "bounds.n: [1.0, 5.0] in the store, [1.0, 3.0] now"),
    (dict(shadowing="smith"), 'shadowing: "paper" in the store, "smith" now'),
    (dict(n_starts=4), f"n_starts: {batch.N_STARTS} in the store, 4 now"),
    (dict(grid_shape={"n": 6}), "grid.n: 12 values 1..5 in the store, 6 values 1..5 now"),
    (dict(memory_budget="64 MiB"), "block_rows: 4 in the store, 16 now) (the blocks follow the memory budget: the "
                                   f"store's was {pbrdf_cl.sizes.human(BUDGET)})"),
], ids=["fixed", "bounds", "shadowing", "n_starts", "grid", "blocks"])
def test_other_settings_are_refused_naming_what_differs(stack, reference, change, message):
    text = _refusal(reference, stack, **change)
    assert f"{reference} was started with other settings (" in text and message in text, text
    assert text.endswith(f"choose another --out, or delete {reference} to start over")


def test_another_input_is_refused(stack, reference, tmp_path):
    before = files(reference)
    # a value in a row the settings' sample holds: refused before any work
    other = dict(stack, dop=stack["dop"].copy())
    other["dop"][8, 3, 7] += 1e-9
    text = _refusal(reference, other)
    assert "stack.sample_sha256: " in text and "..." in text, text
    # a value elsewhere (row 5 is not in the sample): found by the done block's input SHA-256
    other = dict(stack, dop=stack["dop"].copy())
    other["dop"][5, 3, 7] += 1e-9
    text = _refusal(reference, other)
    assert f"{reference}: the stack's rows 4..7 of y differ from those the store's block 1 was fitted from" in text
    # another shape
    text = _refusal(reference, make_stack((12, 16)))
    assert "stack.shape: [16, 16] in the store, [12, 16] now" in text, text
    assert files(reference) == before  # nothing was written



def test_other_stores_are_refused(stack, reference, tmp_path, monkeypatch):
    folder = tmp_path / "notes"
    folder.mkdir()
    (folder / "a.txt").write_text("x")
    assert "exists and is not a pbrdf-cl fit store" in _refusal(folder, stack)
    sweep = tmp_path / "sweep.zarr"
    pbrdf_cl.sweep(dict(axes=dict(theta_r="0:80:20"), fixed=dict(theta_i=40, n=1.6, k=2.1, sigma=0.3)), sweep,
                   progress=False)
    assert "exists and is a pbrdf-cl sweep store" in _refusal(sweep, stack)
    monkeypatch.setattr(pbrdf_cl.store.zarr, "kernels_sha256", lambda: "0" * 64)
    assert "was started with other OpenCL kernel sources" in _refusal(reference, stack)


def test_cluster_arguments(stack, tmp_path):
    with pytest.raises(ValueError, match="need store="):
        batch.fit_batch(stack, workers=2)
    with pytest.raises(ValueError, match="at most one of workers=, scheduler= and client="):
        batch.fit_batch(stack, store=tmp_path / "x.zarr", workers=2, scheduler="tcp://nowhere:1")
    with pytest.raises(ValueError, match="workers must be a positive integer"):
        batch.fit_batch(stack, store=tmp_path / "x.zarr", workers=0)
    assert not (tmp_path / "x.zarr").exists()


def test_lazy_stack_is_read_block_by_block(tmp_path, monkeypatch):
    """A Zarr stack of 15.7 MB, fitted from xarray.open_zarr: the store's path (reading, hashing,
    writing) holds about one block of it at a time.  The fit itself is replaced by a stand-in that
    reads its rows as BatchJob.fit_rows does (its own working memory is BatchJob's business)."""
    stack = make_stack((512, 64), seed=1)
    stack["dop_std"] = np.full(stack["dop"].shape, 0.002)
    xr.Dataset({"dop": (("y", "x", "m"), stack["dop"]), "dop_std": (("y", "x", "m"), stack["dop_std"]),
                "theta_i": (("m",), TI), "theta_r": (("m",), TR)}).chunk({"y": 8}).to_zarr(tmp_path / "in.zarr",
                                                                                          zarr_format=2)
    input_bytes = stack["dop"].nbytes + stack["dop_std"].nbytes
    del stack
    kw = dict(memory_budget="8 MiB", n_starts=2, grid_shape=dict(n=4, k=4, sigma=2, kd=2, c=2))
    rows = []

    def stand_in(self, eng, r0, r1):
        raw = self.source.rows(r0, r1)
        rows.append(r1 - r0)
        out = self.empty_outputs(r1 - r0)
        out["x"][:] = np.nansum(raw["dop"], axis=1)[:, None]
        out["n_valid"][:] = np.isfinite(raw["dop"]).sum(axis=1)
        out["status"][:] = 1
        return out
    monkeypatch.setattr(batch.BatchJob, "fit_rows", stand_in)
    job = batch.BatchJob(xr.open_zarr(tmp_path / "in.zarr"), **kw)
    n_blocks = len(job.blocks())
    assert n_blocks >= 10
    ds, peak = traced_peak(lambda: batch.fit_batch(xr.open_zarr(tmp_path / "in.zarr"), store=tmp_path / "m.zarr", **kw))
    assert ds.attrs["blocks_computed"] == n_blocks and max(rows) == job.rows_per_block()
    block_input = input_bytes // 512 * job.rows_per_block()
    assert peak < 4 * block_input < input_bytes / 4, (peak, block_input, input_bytes)
    assert np.array_equal(ds.n_valid.values[1:], np.full((511, 64), 30))
    # resuming re-reads the done blocks' input to check it, one block at a time too
    (tmp_path / "m.zarr" / "_sweep" / "done" / str(n_blocks - 1)).unlink()
    ds, peak = traced_peak(lambda: batch.fit_batch(xr.open_zarr(tmp_path / "in.zarr"), store=tmp_path / "m.zarr", **kw))
    assert ds.attrs["blocks_computed"] == 1 and peak < 4 * block_input, (peak, block_input)


def run_cli(*args):
    return subprocess.run([sys.executable, "-m", "pbrdf_cl", *args], capture_output=True, text=True, timeout=300,
                          env=dict(os.environ, PYTHONWARNINGS="ignore", PYTHONPATH=PACKAGE_ROOT))


def test_cli_fit_image_writes_the_store_and_the_png(stack, tmp_path):
    np.savez(tmp_path / "stack.npz", **stack)
    budget = str(budget_for(stack, 8, fixed={"kd": 0.15}, bounds={"n": (1, 3)}))
    proc = run_cli("fit-image", str(tmp_path / "stack.npz"), "--out", str(tmp_path / "p.zarr"), "--fix", "kd=0.15",
                   "--bounds", "n=1:3", "--png", str(tmp_path / "maps.png"), "--memory-budget", budget)
    assert proc.returncode == 0, proc.stderr
    lines = proc.stdout.strip().splitlines()
    assert lines[0].startswith("fit-image: 256 of 256 pixels fitted in ") and "pixels/s (0 already in" in lines[0]
    ds = open_result(tmp_path / "p.zarr")
    counts = status_counts(ds)
    assert lines[1] == "status: " + ", ".join(f"{n} {c}" for n, c in counts.items()) and "too_few 1" in lines[1]
    assert lines[2] == ds.attrs["goodness"] and lines[2].startswith("goodness of fit: 0 of 255 fitted pixels (0.0%)")
    from pbrdf_cl.io.measurements import PHI_DEFAULT_NOTE
    assert lines[3] == f"note: {PHI_DEFAULT_NOTE}"  # the stack has no phi
    # pixels whose best value lies outside its own interval: counted, with the note (issue #34 item 4)
    assert lines[4:-1] == ([f"note: {ds.attrs['outside_ci95_note']}"] if "outside_ci95_note" in ds.attrs else [])
    assert lines[-1] == f"store: {tmp_path / 'p.zarr'}; maps: {tmp_path / 'maps.png'}"
    assert ds.attrs["free"] == "n k sigma c" and ds.attrs["fixed_kd"] == 0.15 and ds.attrs["batch_complete"]
    assert float(ds.n_ci95.max()) <= 3.0
    assert ds.attrs["batch_blocks"] == 2
    mem = batch.fit_batch(stack, fixed={"kd": 0.15}, bounds={"n": (1, 3)}, memory_budget=budget)
    assert_same_values(mem, ds)
    import matplotlib.image
    img = matplotlib.image.imread(tmp_path / "maps.png")
    assert img.shape[0] > 1000 and img.shape[1] > 600  # 4 parameter rows and the status row, 2 columns
    again = run_cli("fit-image", str(tmp_path / "stack.npz"), "--out", str(tmp_path / "p.zarr"), "--fix",
                    "kd=0.15", "--bounds", "n=1:3", "--memory-budget", budget, "--no-progress")
    assert again.returncode == 0 and "fit-image: 0 of 256 pixels fitted" in again.stdout, again.stderr


@pytest.mark.parametrize("args,message", [
    (["missing.npz", "--out", "o.zarr"], "pbrdf-cl: error: stack 'missing.npz' does not exist"),
    (["STACK", "--out", "o.zarr", "--fix", "sigmaa=0.4"], "pbrdf-cl: error: --fix sigmaa=0.4: unknown name"),
    (["STACK", "--out", "o.zarr", "--fix", "n=high"], "pbrdf-cl: error: --fix n=high"),
    (["STACK", "--out", "o.zarr", "--bounds", "n=3:1"], "pbrdf-cl: error: --bounds n=3:1"),
    (["STACK", "--out", "o.zarr", "--memory-budget", "lots"], "pbrdf-cl: error: memory_budget: 'lots' is not a size"),
    (["STACK", "--out", "o.zarr", "--fix", "n=1.5", "k=2", "sigma=0.5", "kd=0.1", "c=-0.3"],
     "pbrdf-cl: error: every parameter is fixed: nothing to fit"),
], ids=["missing-stack", "fix-name", "fix-value", "bounds", "budget", "all-fixed"])
def test_cli_errors_are_one_line(stack, tmp_path, monkeypatch, capsys, args, message):
    np.savez(tmp_path / "stack.npz", **stack)
    monkeypatch.chdir(tmp_path)
    args = [str(tmp_path / "stack.npz") if a == "STACK" else a for a in args]
    rc = cli.main(["fit-image", *args, "--no-progress"])
    err = capsys.readouterr().err
    assert rc == 1 and err.startswith(message), err
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err
    assert not (tmp_path / "o.zarr").exists()


def test_cli_refuses_a_store_of_other_settings(stack, reference, tmp_path, capsys):
    np.savez(tmp_path / "stack.npz", **stack)
    rc = cli.main(["fit-image", str(tmp_path / "stack.npz"), "--out", str(reference), "--memory-budget", str(BUDGET),
                   "--shadowing", "none", "--no-progress"])
    err = capsys.readouterr().err
    assert rc == 1 and err.startswith(f"pbrdf-cl: error: {reference} was started with other settings (shadowing: "
                                      '"paper" in the store, "none" now)')
    assert len(err.strip().splitlines()) == 1
