"""Stores that verify themselves (issue 39): a sweep store and an image-fit store damaged in every
way a disk, a person or a dead process damages them (deleted, truncated, overwritten and zeroed
chunks, deleted metadata, an edited coordinate, deleted digests and done marks) are found by
``pbrdf-cl verify`` and, resumed, end bit for bit the store of an uninterrupted run (or are
refused in one line); one writer at a time; the device of every unit; small metadata for long
axes; ENOSPC/EFBIG lines; no store left by a run that failed before its first unit."""
import errno
import json
import os
import shutil
import signal
import subprocess
import sys
import warnings

import numpy as np
import pytest
import xarray as xr

import pbrdf_cl
from pbrdf_cl import cli
from pbrdf_cl.analysis import sweeps as S
from pbrdf_cl.fitting.images import batch
from pbrdf_cl.fitting.images.store import open_result, status_counts
from pbrdf_cl.store import lock, runner
from pbrdf_cl.store import verify as V
from pbrdf_cl.store import zarr as zarr_store

from test_batch_store import budget_for, make_stack
from test_sweep import PACKAGE_ROOT, files

SPEC = dict(axes=dict(theta_r="0:80:10", sigma=[0.2, 0.5, 0.8]), fixed=dict(theta_i=40, n=1.6, k=2.1, c=-0.3),
            chunks=dict(theta_r=2))  # 5 chunks, the last one short
STACK = make_stack((8, 4))
BUDGET = budget_for(STACK, 2)  # 4 blocks of 2 rows


def sweep(store, **kw):
    return pbrdf_cl.sweep(SPEC, store, progress=False, backend="numpy", **kw)


def fit(store, data=STACK):
    return batch.fit_batch(data, store=store, memory_budget=BUDGET, backend="numpy")


@pytest.fixture(scope="module")
def sweep_ref(tmp_path_factory):
    store = tmp_path_factory.mktemp("sref") / "ref.zarr"
    assert sweep(store).complete
    return store


@pytest.fixture(scope="module")
def fit_ref(tmp_path_factory):
    store = tmp_path_factory.mktemp("fref") / "ref.zarr"
    assert fit(store).attrs["batch_complete"]
    return store


def corrupt(path, how):
    data = path.read_bytes()
    if how == "delete":
        path.unlink()
    elif how == "truncate":
        path.write_bytes(data[: len(data) // 2])
    elif how == "random":
        path.write_bytes(np.random.default_rng(1).integers(0, 256, len(data), dtype=np.uint8).tobytes())
    elif how == "zero16":  # 16 bytes in the middle of the compressed values
        mid = len(data) // 2
        path.write_bytes(data[:mid] + bytes(16) + data[mid + 16:])
    elif how == "edit":  # a coordinate: float64 values, no compressor
        a = np.frombuffer(data, "<f8").copy()
        a[1] += 0.5
        path.write_bytes(a.tobytes())


SWEEP_DAMAGE = {  # the file, how, what verify says
    "deleted chunk": ("dop/1.0", "delete", "do not match their digests"),
    "truncated chunk": ("dop/2.0", "truncate", "do not match their digests"),
    "random chunk": ("dop/0.0", "random", "do not match their digests"),
    "zeroed 16 bytes": ("dop/3.0", "zero16", "do not match their digests"),
    "deleted .zarray": ("dop/.zarray", "delete", "metadata file(s) missing or altered: dop/.zarray"),
    "edited coordinate": ("theta_r/0", "edit", "coordinate or label array(s) missing or altered: theta_r"),
    "deleted digest": ("_sweep/digest/4.0", "delete", "do not match their digests"),
    "deleted done mark": ("_sweep/done/2", "delete", "marked complete (sweep_complete) but 1 of 5 units"),
}


def run_verify(store, capsys):
    rc = cli.main(["verify", str(store)])
    out, err = capsys.readouterr()
    return rc, out, err


@pytest.mark.parametrize("case", SWEEP_DAMAGE)
def test_a_damaged_sweep_store_is_found_and_resumed_bit_for_bit(case, sweep_ref, tmp_path, capsys):
    key, how, said = SWEEP_DAMAGE[case]
    store = tmp_path / "s.zarr"
    shutil.copytree(sweep_ref, store)
    corrupt(store / key, how)
    rc, out, err = run_verify(store, capsys)
    assert rc == 1 and said in err, err
    assert all(line.startswith("pbrdf-cl:") for line in err.splitlines())
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        res = sweep(store)
    assert res.complete
    said = [str(w.message) for w in seen if issubclass(w.category, pbrdf_cl.StoreWarning)]
    if case != "deleted done mark":  # a lost mark is a chunk not done: computed like any other
        assert len(said) == 1 and said[0].startswith(f"{store}: "), said
    assert files(store) == files(sweep_ref)
    assert run_verify(store, capsys)[0] == 0


def test_verify_of_an_intact_store_and_a_leftover_partial(sweep_ref, tmp_path, capsys):
    store = tmp_path / "s.zarr"
    shutil.copytree(sweep_ref, store)
    rc, out, err = run_verify(store, capsys)
    assert rc == 0 and out == f"{store}: intact (5 of 5 units verified against their digests)\n" and not err
    (store / "dop" / "1.0.abc.partial").write_bytes(b"half a chunk")  # a Dask worker killed mid-write
    rc, out, err = run_verify(store, capsys)
    assert rc == 0 and f"note: {store}: removed 1 .partial file(s) left by interrupted writes" in out
    assert files(store) == files(sweep_ref)


def test_damaged_root_attrs_are_refused_in_one_line(sweep_ref, tmp_path, capsys):
    store = tmp_path / "s.zarr"
    shutil.copytree(sweep_ref, store)
    corrupt(store / ".zattrs", "random")
    rc, out, err = run_verify(store, capsys)
    assert rc == 1 and "the root attributes (.zattrs) are missing or unreadable" in err
    before = files(store)
    with pytest.raises(pbrdf_cl.StoreError) as e:
        sweep(store)
    assert str(e.value).startswith(f"{store}: its root attributes (.zattrs) are missing or unreadable")
    assert "\n" not in str(e.value) and files(store) == before
    # the spec's text edited: it no longer matches its SHA-256
    shutil.rmtree(store)
    shutil.copytree(sweep_ref, store)
    attrs = json.loads((store / ".zattrs").read_text())
    attrs["sweep_spec"] = attrs["sweep_spec"].replace('"quantity":"dop"', '"quantity":"f00"')
    (store / ".zattrs").write_text(json.dumps(attrs))
    with pytest.raises(pbrdf_cl.StoreError) as e:
        sweep(store)
    assert "\n" not in str(e.value) and str(e.value).startswith(f"{store}: its root attributes are damaged")


def test_complete_is_never_set_on_a_damaged_store(sweep_ref, tmp_path, monkeypatch):
    """A chunk damaged between its write and the end of the run: the run does not call the store complete."""
    store = tmp_path / "s.zarr"
    real = runner.Writer.run

    def run_then_damage(self, eng, i, *args):
        out = real(self, eng, i, *args)
        if int(i) == 3:
            (store / "dop" / "3.0").unlink()
        return out
    monkeypatch.setattr(runner.Writer, "run", run_then_damage)
    with pytest.warns(pbrdf_cl.StoreWarning, match="1 chunks were damaged after they were written"):
        res = sweep(store)
    assert not res.complete and zarr_store.read_root_attrs(store)["sweep_complete"] is False
    monkeypatch.undo()
    assert sweep(store).chunks_computed == 1
    assert files(store) == files(sweep_ref)


FIT_DAMAGE = {
    "deleted status chunk": ("status/1.0", "delete"),
    "deleted n chunk": ("n/2.0", "delete"),
    "zeroed n chunk": ("n/0.0", "zero16"),
    "truncated chunk": ("chi2/3.0", "truncate"),
    "deleted input digest": ("_sweep/input_sha256/2.0", "delete"),
}


@pytest.mark.parametrize("case", FIT_DAMAGE)
def test_a_damaged_fit_store_is_found_and_resumed_bit_for_bit(case, fit_ref, tmp_path, capsys):
    key, how = FIT_DAMAGE[case]
    store = tmp_path / "f.zarr"
    shutil.copytree(fit_ref, store)
    corrupt(store / key, how)
    if case == "deleted status chunk":  # xarray reads the fill value: not computed, never a status
        ds = xr.open_zarr(store)
        assert int(ds.status.isnull().sum()) == 8
        assert status_counts(ds)["not_computed"] == 8
        assert status_counts(open_result(store))["not_computed"] == 8
    rc, out, err = run_verify(store, capsys)
    assert rc == 1 and "1 of 4 done units' values do not match their digests" in err, err
    with pytest.warns(pbrdf_cl.StoreWarning, match="1 of 4 done blocks were damaged"):
        ds = fit(store)
    assert ds.attrs["blocks_computed"] == 1 and ds.status.dtype == np.int8
    assert status_counts(ds) == status_counts(open_result(fit_ref))
    assert files(store) == files(fit_ref)


def test_fit_store_records_the_whole_input(fit_ref):
    attrs = zarr_store.read_root_attrs(fit_ref)
    hashes = np.asarray(zarr_store.open_group(fit_ref, "r")["_sweep/input_sha256"][:], np.uint8)
    assert hashes.shape == (4, 32) and hashes.any(axis=1).all()
    import hashlib
    assert attrs["batch_input_sha256"] == hashlib.sha256(hashes.tobytes()).hexdigest()


def test_devices_of_every_unit_and_a_resume_on_another_backend(tmp_path):
    store = tmp_path / "s.zarr"
    res = sweep(store)
    desc = pbrdf_cl.NumpyEngine().description
    key = zarr_store.device_key(desc)
    g = zarr_store.open_group(store, "r")
    assert (g["_sweep/device"][:] == key).all() and g.attrs["store_devices"] == {str(key): desc}
    assert res.complete
    (store / "dop" / "1.0").unlink()
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        pbrdf_cl.sweep(SPEC, store, progress=False, engine=OtherEngine())
    said = [str(w.message) for w in seen if issubclass(w.category, pbrdf_cl.StoreWarning)]
    assert any(f"resumed on {OtherEngine.description}; its other chunks were computed on {desc}" in m
               for m in said), said
    g = zarr_store.open_group(store, "r")
    other = zarr_store.device_key(OtherEngine.description)
    assert list(g["_sweep/device"][:]) == [key, other, key, key, key]
    assert set(g.attrs["store_devices"].values()) == {desc, OtherEngine.description}


class OtherEngine(pbrdf_cl.NumpyEngine):
    """The numpy reference under another description: a second device."""
    description = "another device (test)"


def holder(store):
    """A process holding the store's lock; returns it once it holds it."""
    code = ("import sys, time; from pbrdf_cl.store import lock\n"
            f"with lock.holding({str(store)!r}):\n print('ready', flush=True); time.sleep(120)")
    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True,
                            env=dict(os.environ, PYTHONPATH=PACKAGE_ROOT))
    assert proc.stdout.readline().strip() == "ready"
    return proc


def test_one_writer_at_a_time_and_a_dead_writers_lock(sweep_ref, tmp_path, capsys):
    store = tmp_path / "s.zarr"
    proc = holder(store)
    try:
        with pytest.raises(pbrdf_cl.StoreError) as e:
            sweep(store)
        msg = str(e.value)
        assert msg.startswith(f"{store} is being written by another run (pid {proc.pid} on ") and "started 20" in msg
        assert "\n" not in msg and not store.exists()
        # the CLI: one line
        spec = tmp_path / "spec.toml"
        spec.write_text('[axes]\ntheta_r = "0:80:10"\nsigma = [0.2, 0.5, 0.8]\n[fixed]\ntheta_i = 40\nn = 1.6\n'
                        'k = 2.1\nc = -0.3\n[chunks]\ntheta_r = 2\n')
        assert cli.main(["sweep", str(spec), "--out", str(store), "--quiet", "--backend", "numpy"]) == 1
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and f"pid {proc.pid}" in err
        proc.send_signal(signal.SIGKILL)  # the holder dies: its record stays in the lock file
        proc.wait(10)
        (tmp_path / f"s.zarr.creating-{proc.pid}-0123abcd").mkdir()  # as a killed creation leaves
        with pytest.warns(pbrdf_cl.StoreWarning) as seen:
            assert sweep(store).complete
        said = [str(w.message) for w in seen]
        assert any(f"took over the lock of a run that is no longer running (pid {proc.pid} on " in m for m in said)
        assert any("removed 1 folder(s) s.zarr.creating-*" in m for m in said)
        assert sorted(os.listdir(tmp_path)) == ["s.zarr", "s.zarr.lock", "spec.toml"]
        assert lock.lock_path(store).read_text() == ""  # released normally: an empty record
        assert files(store) == files(sweep_ref)
    finally:
        proc.kill()


def test_a_store_replaced_under_a_running_sweep_is_never_written_into(tmp_path, monkeypatch):
    store = tmp_path / "s.zarr"
    other = S.load_spec(dict(SPEC, dtype="float64"))
    real = S.compute_chunk
    calls = []

    def compute_then_replace(spec, eng, i):
        calls.append(i)
        if len(calls) == 2:  # another run deletes the store and creates its own
            shutil.rmtree(store)
            S.open_store(other, store)
        return real(spec, eng, i)
    monkeypatch.setattr(S, "compute_chunk", compute_then_replace)
    with pytest.raises(pbrdf_cl.StoreError) as e:
        sweep(store)
    assert str(e.value).startswith(f"{store} no longer holds this run's job (sweep_spec_sha256 {other.sha256[:12]} now")
    written = [p for p in store.rglob("*") if p.is_file() and p.name[0].isdigit() and p.parent.name != "theta_r"
               and p.parent.name != "sigma"]
    assert not written and zarr_store.read_root_attrs(store)["sweep_spec_sha256"] == other.sha256


def test_a_run_that_fails_before_its_first_unit_leaves_no_store(tmp_path, monkeypatch):
    store = tmp_path / "s.zarr"

    def refuse(spec, eng, i):
        raise ValueError("an input refused while computing")
    monkeypatch.setattr(S, "compute_chunk", refuse)
    with pytest.raises(ValueError, match="an input refused"):
        sweep(store)
    assert not store.exists()
    monkeypatch.undo()
    assert sweep(store).complete


@pytest.mark.parametrize("code,said", [
    (errno.ENOSPC, "disk full writing {store}; free space and run the same command again to resume"),
    (errno.EFBIG, "a file would pass the file-size limit writing {store} (ulimit -f, or the file system's); raise "
                  "the limit and run the same command again to resume")], ids=["ENOSPC", "EFBIG"])
def test_disk_full_and_file_too_large_name_the_store_and_how_to_resume(code, said, tmp_path, monkeypatch, capsys):
    store = tmp_path / "s.zarr"
    sweep(store)
    (store / "dop" / "2.0").unlink()

    def full(pieces):
        raise OSError(code, os.strerror(code))
    monkeypatch.setattr(V, "values_sha256", full)  # the write of a unit fails
    spec = tmp_path / "spec.toml"
    spec.write_text('[axes]\ntheta_r = "0:80:10"\nsigma = [0.2, 0.5, 0.8]\n[fixed]\ntheta_i = 40\nn = 1.6\n'
                    'k = 2.1\nc = -0.3\n[chunks]\ntheta_r = 2\n')
    rc = cli.main(["sweep", str(spec), "--out", str(store), "--quiet", "--backend", "numpy"])
    err = capsys.readouterr().err.splitlines()
    assert rc == 1 and err[-1] == f"pbrdf-cl: error: {said.format(store=store)}", err
    assert len([ln for ln in err if "error" in ln]) == 1


def test_a_long_axis_keeps_the_metadata_small(tmp_path):
    """10^6 values on one axis: the canonical spec holds its count, ends and SHA-256, the values
    are in the chunked coordinate array only."""
    spec = dict(axes=dict(theta_r="0:85@1000000"), fixed=dict(theta_i=40, n=1.6, k=2.1, sigma=0.5))
    res = pbrdf_cl.sweep(spec, tmp_path / "long.zarr", progress=False, backend="numpy")
    assert res.complete
    store = tmp_path / "long.zarr"
    assert (store / ".zattrs").stat().st_size < 16 << 10 and (store / ".zmetadata").stat().st_size < 32 << 10
    axis = json.loads(json.loads((store / ".zattrs").read_text())["sweep_spec"])["axes"]["theta_r"]
    assert axis["count"] == 10 ** 6 and axis["first"] == 0.0 and axis["last"] == 85.0
    assert json.loads((store / "theta_r" / ".zarray").read_text())["chunks"] == [min(10 ** 6, S.COORD_CHUNK)]
    np.testing.assert_array_equal(xr.open_zarr(store).theta_r.values, np.linspace(0, 85, 10 ** 6))
    # another axis of the same count and ends: the message stays readable
    with pytest.raises(pbrdf_cl.SpecError) as e:
        pbrdf_cl.sweep(dict(spec, axes=dict(theta_r=np.linspace(0, 85, 10 ** 6) ** 1.0001 / 85 ** 0.0001)),
                       store, progress=False, backend="numpy")
    assert "axes.theta_r: 1000000 values 0..85 (sha256 " in str(e.value) and len(str(e.value)) < 600


def test_a_fit_refused_at_its_first_block_leaves_no_store(tmp_path, monkeypatch, fit_ref):
    """An input refused while its first block is fitted: no store is left to block the corrected rerun."""
    store = tmp_path / "f.zarr"

    def refuse(self, eng, r0, r1):
        raise ValueError("row 0: an input refused while fitting")
    monkeypatch.setattr(batch.BatchJob, "fit_rows", refuse)
    with pytest.raises(ValueError, match="an input refused"):
        fit(store)
    assert not store.exists() and sorted(os.listdir(tmp_path)) == ["f.zarr.lock"]
    monkeypatch.undo()
    ds = fit(store)
    assert ds.attrs["batch_complete"] and files(store) == files(fit_ref)
    desc = pbrdf_cl.NumpyEngine().description
    g = zarr_store.open_group(store, "r")
    assert (g["_sweep/device"][:] == zarr_store.device_key(desc)).all()
    assert list(g.attrs["store_devices"].values()) == [desc]
