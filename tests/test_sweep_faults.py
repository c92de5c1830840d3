"""Sweeps under real faults: the CLI on a local cluster, a worker process killed mid-sweep, a real
SIGINT to a running ``pbrdf-cl sweep``; each store ends bit-identical to an uninterrupted local run."""
import os
import signal
import subprocess
import sys
import threading
import time

import pytest

import pbrdf_cl
from pbrdf_cl.analysis import sweeps as S

from test_sweep import PACKAGE_ROOT, files, n_done, reference, spec_file  # noqa: F401 - fixtures

ENV = dict(os.environ, PYTHONPATH=PACKAGE_ROOT, PYTHONWARNINGS="ignore")


def sweep_cmd(spec_file, store, *extra):
    return [sys.executable, "-m", "pbrdf_cl", "sweep", str(spec_file), "--out", str(store), "--quiet", *extra]


def test_cli_sweep_on_two_workers_equals_the_local_store(spec_file, reference, tmp_path):
    pytest.importorskip("distributed")
    store = tmp_path / "w.zarr"
    proc = subprocess.run(sweep_cmd(spec_file, store, "--workers", "2"), env=ENV, capture_output=True, text=True,
                          timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "sweep: 40 of 40 chunks computed (0 already done)" in proc.stdout
    assert files(store) == files(reference)


def test_sigint_to_a_running_cli_sweep_then_resume(spec_file, reference, tmp_path):
    store = tmp_path / "int.zarr"
    proc = subprocess.Popen(sweep_cmd(spec_file, store), env=dict(ENV, **{S.DELAY_ENV: "0.1"}),
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 120
        while n_done(store) < 4 and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.01)
        assert proc.poll() is None, proc.communicate()
        proc.send_signal(signal.SIGINT)  # what Ctrl-C sends
        out, err = proc.communicate(timeout=60)
    finally:
        proc.kill()
    done = n_done(store)
    assert proc.returncode == 130, err
    assert err.strip().splitlines()[-1] == (f"pbrdf-cl: interrupted; {done} of 40 chunks are in {store}; run the same "
                                            "command again to resume")
    assert 4 <= done < 40
    again = subprocess.run(sweep_cmd(spec_file, store), env=ENV, capture_output=True, text=True, timeout=300)
    assert again.returncode == 0, again.stderr
    assert f"sweep: {40 - done} of 40 chunks computed ({done} already done)" in again.stdout
    assert files(store) == files(reference)


def test_a_worker_killed_mid_sweep(spec_file, reference, tmp_path, monkeypatch):
    """SIGKILL one of two worker processes while chunks are in flight: the cluster retries its chunks
    elsewhere, or the next run computes what is missing; the store ends bit-identical."""
    distributed = pytest.importorskip("distributed")
    monkeypatch.setenv(S.DELAY_ENV, "0.15")  # inherited by the worker processes: chunks take a while
    store = tmp_path / "k.zarr"
    cluster = distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None)
    client = distributed.Client(cluster)
    outcome = {}

    def run():
        try:
            outcome["result"] = pbrdf_cl.sweep(spec_file, store, client=client, progress=False)
        except Exception as exc:  # noqa: BLE001 - a lost worker may fail the run; the next run resumes
            outcome["error"] = exc
    try:
        pids = client.run(os.getpid)
        thread = threading.Thread(target=run)
        thread.start()
        deadline = time.monotonic() + 120
        while n_done(store) < 5 and thread.is_alive() and time.monotonic() < deadline:
            time.sleep(0.01)
        assert thread.is_alive(), outcome
        victim = sorted(pids.values())[0]
        os.kill(victim, signal.SIGKILL)
        thread.join(timeout=240)
        assert not thread.is_alive(), "the sweep hung after a worker was killed"
    finally:
        client.close()
        cluster.close()
    if "error" in outcome or not outcome["result"].complete:
        res = pbrdf_cl.sweep(spec_file, store, progress=False)  # the next run completes it
        assert res.complete and res.chunks_computed >= 1
    assert files(store) == files(reference)
