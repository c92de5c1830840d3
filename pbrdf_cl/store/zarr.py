"""The Zarr layer of the resumable stores (:mod:`pbrdf_cl.analysis.sweeps`' sweeps,
:mod:`pbrdf_cl.fitting.images.store`'s image fits): opening and creating groups and arrays,
creating a store whole or not at all, the done marks, resuming.

The stores are Zarr format 2 with consolidated metadata (``xarray.open_zarr`` reads them), on
zarr 3 or zarr 2.  A job's unit of work (a sweep's chunk, an image fit's block of rows) is one
Zarr chunk of every variable, so no two writers ever share a Zarr chunk.  The record of the work
done is :data:`DONE`: one uint8 per unit, set to 1 only after that unit's values are written
(write, then mark: a unit without its mark is computed again).  The root attrs name the job
(its canonical settings and their SHA-256, the SHA-256 of the OpenCL sources under
``sweep_kernels_sha256``) and whether it is complete; the caller chooses their keys.

A store is a local path (``file://`` allowed) or the URL of an fsspec store.  Locally a new
store is written beside its place and renamed into it (:func:`create_in_place`), and the
``*.partial`` files of writes interrupted by a kill are removed on resuming (:func:`resume`).
Beside each done mark are the unit's digest (:data:`DIGEST`) and device (:data:`DEVICE`), which
:mod:`pbrdf_cl.store.verify` writes and checks; the groups are opened from their own files, not
from the consolidated metadata, which a damaged store may contradict.
"""
from __future__ import annotations

import json
import os
import uuid
from pathlib import Path

import numpy as np

from ..device.engine import kernels_sha256
from ..errors import SpecError

#: The done marks: one uint8 per unit of work (C order), 1 once its values are in the store.
DONE = "_sweep/done"
#: Per unit: the SHA-256 of its decoded values (:mod:`pbrdf_cl.store.verify`), written before its mark.
DIGEST = "_sweep/digest"
#: Per unit: the device that computed it, as a key of the root attribute :data:`DEVICES`
#: (the first 8 bytes of the SHA-256 of its description, as an int; 0: not recorded).
DEVICE = "_sweep/device"
#: The root attribute of the devices that computed units: key (a decimal string) -> description.
DEVICES = "store_devices"
#: The root attribute holding the SHA-256 of the OpenCL sources that wrote a store.
KERNELS_ATTR = "sweep_kernels_sha256"


def _zarr():
    import zarr
    return zarr


def _zarr3():
    return int(_zarr().__version__.split(".")[0]) >= 3


def settle(timeout=10.0):
    """Wait (up to ``timeout`` seconds) for the writes still running in Zarr's I/O thread.

    Zarr 3 writes from an event loop in a thread of its own while the caller waits; a Ctrl-C ends
    the wait, not the write.  A process that reports what its store holds after an interrupt
    calls this first, so that the report counts the writes that land, and the loop is idle when
    Python stops it at exit (instead of printing ``Task was destroyed but it is pending``).
    Does nothing on zarr 2 or before Zarr's loop has started."""
    import asyncio  # here, not at the top: every pbrdf-cl command imports this module
    try:
        from zarr.core import sync
    except ImportError:  # zarr 2 writes in the caller's thread
        return
    loop = sync.loop[0]
    if loop is None or loop.is_closed() or not loop.is_running():
        return

    async def rest():
        others = [t for t in asyncio.all_tasks() if t is not asyncio.current_task()]
        if others:
            await asyncio.wait(others, timeout=timeout)
    try:
        asyncio.run_coroutine_threadsafe(rest(), loop).result(timeout + 1.0)
    except Exception:  # noqa: BLE001 - a write that fails or hangs is counted as not written
        pass


def is_local(store):
    """Whether ``store`` (a path or URL) is a local path: a path, or a string without ``://``
    or starting ``file://``."""
    return isinstance(store, os.PathLike) or (isinstance(store, str) and ("://" not in store
                                                                         or store.startswith("file://")))


def store_name(store):
    """A local store as an absolute path (``file://`` dropped), any other URL unchanged."""
    if not is_local(store):
        return store
    path = os.fspath(store)
    return os.path.abspath(path.removeprefix("file://"))


def open_group(store, mode):
    """The root group of a Zarr format 2 store (``mode`` as :func:`zarr.open_group`'s)."""
    zarr = _zarr()
    if _zarr3():  # the files themselves, not the consolidated copy (which a damaged store may contradict)
        return zarr.open_group(store, mode=mode, zarr_format=2, **({} if mode == "w" else {"use_consolidated": False}))
    return zarr.open_group(store, mode=mode)


def create_array(group, name, shape, chunks, dtype, fill_value, compressor, attrs):
    """A new array ``name`` of ``group`` (replacing any of that name), with ``attrs``; ``compressor``
    None or :func:`compressor`."""
    if _zarr3():
        arr = group.create_array(name, shape=shape, chunks=chunks, dtype=dtype, fill_value=fill_value,
                                 compressors=compressor, overwrite=True)
    else:  # pragma: no cover - zarr 2
        arr = group.create_dataset(name, shape=shape, chunks=chunks, dtype=dtype, fill_value=fill_value,
                                   compressor=compressor, overwrite=True)
    arr.attrs.update(attrs)
    return arr


def compressor():
    """The stores' compressor: Blosc LZ4, level 5, byte shuffle (at most 2 GiB per chunk)."""
    from numcodecs import Blosc
    return Blosc(cname="lz4", clevel=5, shuffle=Blosc.SHUFFLE)


def consolidate(store):
    """Write the store's consolidated metadata (after its attrs changed)."""
    _zarr().consolidate_metadata(store)


def create_done(group, n_units):
    """The done marks (:data:`DONE`) of ``n_units`` units of work in ``group``, all 0, their
    digests (:data:`DIGEST`, 32 bytes each) and devices (:data:`DEVICE`)."""
    sub = group.require_group(DONE.split("/")[0])
    create_array(sub, DIGEST.split("/")[1], (n_units, 32), (1, 32), "u1", 0, None, {})
    create_array(sub, DEVICE.split("/")[1], (n_units,), (1,), "u8", 0, None, {})
    return create_array(sub, DONE.split("/")[1], (n_units,), (1,), "u1", 0, None, {})


def device_key(description):
    """The key of a device description in :data:`DEVICE` (an int of 63 bits, never 0)."""
    import hashlib
    return int.from_bytes(hashlib.sha256(description.encode()).digest()[:8], "little") >> 1 | 1


class Files:
    """The files (keys) of a store, read and written as bytes: a local folder, or an fsspec URL."""

    def __init__(self, name):
        self.local = is_local(name)
        if self.local:
            self.root = Path(store_name(name))
        else:
            import fsspec
            self.map = fsspec.get_mapper(name)

    def get(self, key):
        """The bytes of ``key``, or None."""
        try:
            if self.local:
                return (self.root / key).read_bytes()
            return self.map[key]
        except (OSError, KeyError):
            return None

    def put(self, key, data):
        """Write ``key`` (locally through a ``.partial`` file renamed into place)."""
        if self.local:
            path = self.root / key
            path.parent.mkdir(parents=True, exist_ok=True)
            tmp = path.with_name(path.name + ".partial")
            tmp.write_bytes(data)
            os.replace(tmp, path)
        else:
            self.map[key] = data

    def keys(self):
        """Every key, sorted."""
        if not self.local:
            return sorted(self.map.keys())
        return sorted(p.relative_to(self.root).as_posix() for p in self.root.rglob("*") if p.is_file())


def read_root_attrs(name):
    """The root attrs read from ``.zattrs`` itself (not the consolidated copy): a dict, or None
    when absent or unreadable."""
    data = Files(name).get(".zattrs")
    try:
        attrs = json.loads(data) if data is not None else None
    except ValueError:
        return None
    return attrs if isinstance(attrs, dict) else None


def check_kernels(name, attrs, error=SpecError):
    """Refuse (``error``, a one-line message) a store written by other OpenCL kernel sources than
    this process's (:data:`KERNELS_ATTR` of its root ``attrs``): its values would not match."""
    stored = attrs.get(KERNELS_ATTR)
    if stored != kernels_sha256():
        raise error(f"{name} was started with other OpenCL kernel sources (sha256 {str(stored)[:12]} in the "
                    f"store, {kernels_sha256()[:12]} here: another pbrdf-cl version?); its values would not "
                    f"match; choose another --out, or delete {name} to start over")


def differences(old, new):
    """What differs between two canonical settings (JSON-ready dicts, one level of sub-dicts), as
    readable lines ``"key.sub: <old> in the store, <new> now"``; long lists of floats, and axes
    given by their identity (count, ends, SHA-256), are shown by their count and ends."""
    def fmt(v):
        return f"{v:g}" if isinstance(v, float) else repr(v)

    def describe(v):
        if isinstance(v, list) and len(v) > 4 and all(isinstance(x, float) for x in v):
            return f"{len(v)} values {fmt(v[0])}..{fmt(v[-1])}"
        if isinstance(v, dict) and set(v) == {"count", "first", "last", "sha256"}:  # an axis by its identity
            return f"{v['count']} values {fmt(v['first'])}..{fmt(v['last'])} (sha256 {str(v['sha256'])[:12]})"
        return json.dumps(v)
    out = []
    for key in sorted(set(old) | set(new)):
        a, b = old.get(key), new.get(key)
        if isinstance(a, dict) and isinstance(b, dict):
            for sub in sorted(set(a) | set(b)):
                if a.get(sub) != b.get(sub):
                    out.append(f"{key}.{sub}: {describe(a.get(sub)) if sub in a else '(absent)'} in the store, "
                               f"{describe(b.get(sub)) if sub in b else '(absent)'} now")
        elif a != b:
            out.append(f"{key}: {describe(a)} in the store, {describe(b)} now")
    return out


def stored_differences(attrs, key, new):
    """:func:`differences` between the settings stored as JSON in ``attrs[key]`` and ``new``
    (none when the stored text is not JSON)."""
    try:
        return differences(json.loads(attrs.get(key, "{}")), new)
    except ValueError:
        return []


def local_is_empty(path):
    """Whether the local ``path`` is absent or an empty folder (a place for a new store)."""
    return not path.exists() or (path.is_dir() and not any(path.iterdir()))


def create_in_place(path, write):
    """Create the local store ``path`` (absent or an empty folder) with ``write(folder)``, built
    beside it and renamed into place, so that a store exists whole or not at all.  True when this
    call created it; False when another process created it meanwhile (``path`` then holds a Zarr
    group, for the caller to check)."""
    tmp = path.with_name(f"{path.name}.creating-{os.getpid()}-{uuid.uuid4().hex[:8]}")
    try:
        write(str(tmp))
        if path.exists():
            path.rmdir()
        os.rename(tmp, path)
        return True
    except OSError:
        if not (path / ".zgroup").exists():
            raise
        return False
    finally:
        if tmp.exists():
            import shutil
            shutil.rmtree(tmp, ignore_errors=True)


def create_or_read(store, write, not_a_store, unreadable=None):
    """Create the store ``store`` with ``write(where)`` (the whole skeleton, its root attrs last)
    if there is none yet, else read its root attrs.

    Parameters
    ----------
    store : str or path
        A local path or the URL of an fsspec store.
    write : callable
        ``write(where)`` writes the new store at ``where`` (a local one beside its place first:
        :func:`create_in_place`).
    not_a_store : callable
        ``not_a_store(name)`` -> the exception raised for a local path that exists and is
        neither an empty folder nor a Zarr group.
    unreadable : callable, optional
        ``unreadable(name)`` -> the exception raised for a local Zarr group whose attrs cannot
        be read; without it they read as ``{}``.

    Returns
    -------
    tuple
        (the store's name, :func:`store_name`; its root attrs as a dict (``{}`` when missing or
        unreadable), or None when this call created it).
    """
    name = store_name(store)
    if is_local(store):
        path = Path(name)
        if local_is_empty(path):
            if create_in_place(path, write):
                return name, None
            # else another process created it just now: read it below
        elif not (path / ".zgroup").exists():
            raise not_a_store(name)
    attrs = read_root_attrs(name)  # the file itself: the consolidated copy may contradict it
    if attrs is None and not is_local(store) and Files(name).get(".zgroup") is None:
        write(name)
        return name, None
    if attrs is None and unreadable is not None:
        raise unreadable(name)
    return name, attrs or {}


def clean_partials(name):
    """Remove the temporary files of writes interrupted by a kill (zarr writes ``*.partial`` then
    renames; a Dask worker killed mid-write leaves one); returns how many were removed."""
    n = 0
    for root, _, files in os.walk(name):
        for f in files:
            if f.endswith(".partial"):
                try:
                    os.unlink(os.path.join(root, f))
                    n += 1
                except OSError:
                    pass
    return n


def read_done(store, n_units):
    """Which of the ``n_units`` units of work are marked done (:data:`DONE`): a boolean array.  A
    local store's marks are read from its chunk files (a mark whose byte is not 1 is not done)."""
    name = store_name(store)
    done = np.zeros(n_units, bool)
    folder = Path(name, *DONE.split("/"))
    if is_local(store):
        for f in os.listdir(folder) if folder.is_dir() else ():
            if f.isdigit() and int(f) < n_units:
                try:
                    done[int(f)] = (folder / f).read_bytes() == b"\x01"
                except OSError:
                    pass
        return done
    try:
        return open_group(name, "r")[DONE][:] == 1
    except Exception:  # noqa: BLE001 - unreadable marks: nothing is done
        return done


def resume(store, name, n_units, existed):
    """The done marks of a store about to be (re)started (:func:`read_done`), after removing the
    ``*.partial`` files of interrupted writes from a local store that ``existed`` before (their
    digests are checked by :func:`pbrdf_cl.store.verify.check_units`)."""
    if existed and is_local(store):
        clean_partials(name)
    return read_done(name, n_units)
