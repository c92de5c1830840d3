"""Ctrl-C during runs that write a store: an interrupt Python swallows still stops a sweep or an
image fit (``pbrdf_cl.store.interrupt``), and the writes an interrupt leaves running in Zarr's I/O
thread land before the CLI reports what the store holds (``pbrdf_cl.store.zarr.settle``)."""
import asyncio
import signal
import sys
import threading
import time

import pytest

import pbrdf_cl
from pbrdf_cl.fitting.images import batch
from pbrdf_cl.fitting.images.store import read_progress
from pbrdf_cl.store import interrupt
from pbrdf_cl.store import zarr as zarr_store

from test_batch_store import BUDGET, make_stack
from test_sweep import files, n_done, reference, spec_file  # noqa: F401 - fixtures

pytestmark = pytest.mark.skipif(threading.current_thread() is not threading.main_thread(),
                                reason="signal handlers are installed from the main thread only")


class _SwallowedInterrupt:
    """Sends this process SIGINT from a finaliser: Python raises the KeyboardInterrupt there,
    prints "Exception ignored" and carries on."""

    def __del__(self):
        signal.raise_signal(signal.SIGINT)
        time.sleep(0)  # the handler runs here, inside the finaliser


def swallow_an_interrupt(monkeypatch):
    """A SIGINT lost in a finaliser; returns the exceptions Python reported as ignored."""
    ignored = []
    monkeypatch.setattr(sys, "unraisablehook", lambda u: ignored.append(u.exc_type))
    obj = _SwallowedInterrupt()
    del obj
    return ignored


def test_without_recording_a_swallowed_interrupt_is_lost(monkeypatch):
    """The fault being mended: Python's own handler loses the interrupt, and check() (outside the
    CLI's recording) leaves the caller's run alone."""
    assert swallow_an_interrupt(monkeypatch) == [KeyboardInterrupt]
    interrupt.check()  # does not raise


def test_a_swallowed_interrupt_stops_a_sweep_after_its_chunk(spec_file, reference, tmp_path, monkeypatch):
    store = tmp_path / "s.zarr"
    with interrupt.recording():
        assert signal.getsignal(signal.SIGINT) is not signal.default_int_handler
        assert swallow_an_interrupt(monkeypatch) == [KeyboardInterrupt]
        with pytest.raises(KeyboardInterrupt):
            pbrdf_cl.sweep(spec_file, store, progress=False)
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
    assert n_done(store) == 1  # the chunk in progress was finished and marked, then the run stopped
    interrupt.check()  # the record ends with the block
    res = pbrdf_cl.sweep(spec_file, store, progress=False)
    assert res.complete and res.chunks_computed == 39
    assert files(store) == files(reference)


def test_a_swallowed_interrupt_stops_an_image_fit_after_its_block(tmp_path, monkeypatch):
    store = tmp_path / "f.zarr"
    with interrupt.recording():
        swallow_an_interrupt(monkeypatch)
        with pytest.raises(KeyboardInterrupt):
            batch.fit_batch(make_stack(), store=store, memory_budget=BUDGET)
    assert read_progress(store) == (1, 4)


def test_settle_waits_for_the_writes_left_in_zarrs_thread(tmp_path):
    from zarr.core import sync
    g = zarr_store.open_group(tmp_path / "x.zarr", "w")  # starts Zarr's I/O loop
    g.attrs["a"] = 1
    loop = sync.loop[0]
    assert loop is not None and loop.is_running()
    landed = []

    async def slow_write():
        await asyncio.sleep(0.3)
        landed.append(True)
    asyncio.run_coroutine_threadsafe(slow_write(), loop)  # what an interrupted sync() leaves behind
    zarr_store.settle()
    assert landed == [True]
