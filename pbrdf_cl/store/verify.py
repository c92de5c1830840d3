"""Stores that verify themselves: what each unit's done mark carries, the skeleton's manifest, the
repair of a store being resumed, and :func:`verify_store` (``pbrdf-cl verify STORE``).

Why a digest of the decoded values, not a checksum codec: each unit of work (a sweep's chunk, an
image fit's block) is one Zarr chunk of several arrays; the runner writes the unit, then its
digest, then its done mark.  The digest (:data:`DIGEST`, 32 bytes per unit) is the SHA-256 of
the unit's *decoded* values of every variable (:func:`values_sha256`: names, dtypes, shapes and
bytes), so that one check covers every way a chunk can be damaged: a chunk file deleted (it reads
as the fill value), truncated or overwritten (Blosc fails to decode it, or decodes other values),
a few bytes zeroed, and metadata that decodes the bytes otherwise.  A chunk that fails to decode
counts as damaged, never as a crash.  The digest is independent of the codec (Zarr 2 and 3 write
the same chunks, a store keeps its compressor), costs one SHA-256 of the values (far less than
computing them), and needs no change to the arrays' metadata (a ``crc32c`` codec would checksum
the compressed bytes only, and exists in Zarr format 3 only).

The skeleton (every file written before any unit: metadata, coordinates, variables written whole)
is a function of the job (the spec, the settings): its files' SHA-256s are recorded in the root
attrs (:data:`MANIFEST`), which :func:`verify_store` checks without the job; a run resuming the
store writes a fresh skeleton from its job into a temporary folder and rewrites whatever differs
(:func:`repair_skeleton`: a deleted ``dop/.zarray``, an edited coordinate), so that the resumed
store is the store of an uninterrupted run, bit for bit.  Only a store whose identity (its root
attrs: the spec or settings and their SHA-256) cannot be read is refused.
"""
from __future__ import annotations

import contextlib
import hashlib
import json
import os
import tempfile
from pathlib import Path

import numpy as np

from ..errors import StoreError
from . import zarr as zarr_store

DIGEST = zarr_store.DIGEST
Files = zarr_store.Files
read_root_attrs = zarr_store.read_root_attrs
read_done = zarr_store.read_done
#: Root attribute: the skeleton's files (relative path -> SHA-256, metadata as canonical JSON).
MANIFEST = "store_manifest"
#: Root attribute: the units of work ({"count", "variables", "job", "complete"}).
UNITS = "store_units"
META = (".zarray", ".zattrs", ".zgroup")


def _canonical(key, data):
    """A file's bytes for comparing: metadata as sorted JSON (a Zarr version may format it
    otherwise), anything else as is."""
    if key.rsplit("/", 1)[-1] in META:
        try:
            return json.dumps(json.loads(data), sort_keys=True, separators=(",", ":")).encode()
        except ValueError:
            return b"\0unreadable\0" + data
    return data


def file_sha256(key, data):
    return hashlib.sha256(_canonical(key, data)).hexdigest()


def manifest(files):
    """The skeleton's files (all but the root attrs and the consolidated metadata) -> SHA-256."""
    return {k: file_sha256(k, files.get(k)) for k in files.keys()
            if k not in (".zattrs", ".zmetadata") and not k.endswith(".partial")}


def seal(where, attrs):
    """The last step of a skeleton: its root ``attrs`` with the :data:`MANIFEST` of the files
    written so far, then the consolidated metadata."""
    g = zarr_store.open_group(where, "r+")
    g.attrs.update({**attrs, MANIFEST: manifest(Files(where))})
    zarr_store.consolidate(where)


# ---------------------------------------------------------------------------------------------
# the units

def values_sha256(pieces):
    """SHA-256 (32 bytes) of a unit's values: ``pieces`` is [(name, array)] in the store's order."""
    h = hashlib.sha256()
    for name, a in pieces:
        a = np.ascontiguousarray(a)
        h.update(f"{name}:{a.dtype.str}:{a.shape}\0".encode())
        h.update(memoryview(a).cast("B"))
    return np.frombuffer(h.digest(), np.uint8)


def unit_region(arr, i):
    """The slices of unit ``i`` of an array: its ``i``-th chunk in C order over its chunk grid."""
    grid = [-(-s // c) for s, c in zip(arr.shape, arr.chunks)]
    idx = np.unravel_index(int(i), grid) if grid else ()
    return tuple(slice(j * c, min((j + 1) * c, s)) for j, c, s in zip(idx, arr.chunks, arr.shape))


class _Chunks:
    """The chunks of one array of a local store decoded one at a time straight from their files
    with the codec its ``.zarray`` names (one chunk's encoded and decoded bytes in memory, no
    more); an array of a store given by URL is read through zarr."""

    def __init__(self, name, var):
        self.arr = zarr_store.open_group(name, "r")[var]  # KeyError / ValueError: its metadata is gone
        self.shape, self.chunks = tuple(self.arr.shape), tuple(self.arr.chunks)
        self.folder = None
        if zarr_store.is_local(name):
            meta = json.loads(Path(zarr_store.store_name(name), var, ".zarray").read_bytes())
            if not meta.get("filters") and meta.get("order", "C") == "C":
                import numcodecs
                self.folder = Path(zarr_store.store_name(name), var)
                self.sep = meta.get("dimension_separator") or "."
                self.dtype = np.dtype(meta["dtype"])
                self.codec = numcodecs.get_codec(meta["compressor"]) if meta.get("compressor") else None

    def read(self, i):
        region = unit_region(self.arr, i)
        if self.folder is None:
            return self.arr[region]
        grid = [-(-s // c) for s, c in zip(self.shape, self.chunks)]
        idx = np.unravel_index(int(i), grid) if grid else ()
        path = self.folder / (self.sep.join(map(str, idx)) or "0")
        if not path.is_file():  # zarr writes no chunk that is all fill value: read it as zarr does
            return self.arr[region]
        data = path.read_bytes()
        raw = self.codec.decode(data) if self.codec is not None else data
        a = np.frombuffer(raw, self.dtype).reshape(self.chunks)  # a short chunk: ValueError
        return a[tuple(slice(0, r.stop - r.start) for r in region)]


def damaged_units(name, units, variables):
    """The units among ``units`` whose values do not match their digest (or fail to decode, or
    whose digest is unreadable): a sorted list."""
    try:
        arrays = [(v, _Chunks(name, v)) for v in variables]
        digest = zarr_store.open_group(name, "r")[DIGEST]
    except Exception:  # noqa: BLE001 - an array whose metadata is gone: no unit can be checked
        return sorted(int(i) for i in units)
    bad = []
    for i in units:
        try:
            ok = np.array_equal(values_sha256([(v, a.read(i)) for v, a in arrays]),
                                np.asarray(digest[int(i)], np.uint8))
        except Exception:  # noqa: BLE001 - a chunk that fails to decode is damaged
            ok = False
        if not ok:
            bad.append(int(i))
    return bad


def unmark(name, units):
    """Remove the done marks of ``units`` (to be computed again)."""
    g = zarr_store.open_group(name, "r+")
    for i in units:
        g[zarr_store.DONE][int(i)] = 0


def first(idx, n=5):
    """``[3, 7, 9, 12, 15, 20]`` -> ``"3, 7, 9, 12, 15, ..."``."""
    idx = list(idx)
    return ", ".join(map(str, idx[:n])) + (", ..." if len(idx) > n else "")


# ---------------------------------------------------------------------------------------------
# resuming: the skeleton rewritten from the job, the damaged units found

@contextlib.contextmanager
def fresh_skeleton(write):
    """A skeleton written by ``write(where)`` into a temporary folder: yields its :class:`Files`."""
    with tempfile.TemporaryDirectory(prefix="pbrdf-cl-skeleton-") as tmp:
        where = os.path.join(tmp, "s.zarr")
        write(where)
        yield Files(where)


def repair_skeleton(name, write, volatile):
    """Rewrite, from a fresh skeleton of the job (``write(where)``), every skeleton file of the
    store ``name`` that is missing or differs, and the root attrs that differ (except the keys in
    ``volatile``, which runs change: completion, devices, ...).  Returns what was rewritten (a
    list of array or attribute names)."""
    store = Files(name)
    fixed = []
    with fresh_skeleton(write) as fresh:
        for key in fresh.keys():
            if key in (".zattrs", ".zmetadata"):
                continue
            new, old = fresh.get(key), store.get(key)
            if old is None or _canonical(key, old) != _canonical(key, new):
                store.put(key, new)
                what = key.rsplit("/", 1)[0] if "/" in key else key
                what = f"{key}" if key.rsplit("/", 1)[-1] in META else f"{what} (values)"
                if what not in fixed:
                    fixed.append(what)
        want = json.loads(fresh.get(".zattrs"))
    have = read_root_attrs(name) or {}
    changed = {k: v for k, v in want.items() if k not in volatile and have.get(k) != v}
    if changed:
        zarr_store.open_group(name, "r+").attrs.update(changed)
        fixed += [f"attrs.{k}" for k in changed if k != MANIFEST]
    if fixed or changed:
        zarr_store.consolidate(name)
    return fixed


def check_units(name, n_units, variables):
    """The done marks of a store being resumed, after un-marking the units whose values do not
    match their digests: (done, damaged units)."""
    done = read_done(name, n_units)
    bad = damaged_units(name, np.flatnonzero(done), variables)
    if bad:
        unmark(name, bad)
        done[bad] = False
    return done, bad


def refuse_unidentified(name, attrs, key, what):
    """Refuse (one line) a store whose root attrs, which say what job it holds, are gone or
    damaged: nothing in it can be trusted or recomputed."""
    if attrs is None:
        raise StoreError(f"{name}: its root attributes (.zattrs) are missing or unreadable, so what it holds "
                         f"cannot be told; choose another --out, or delete {name} to start over")
    if key not in attrs:
        raise StoreError(f"{name} exists and is not {what} (or its creation was interrupted); choose another "
                         "--out or delete it")
    text = attrs.get(key.removesuffix("_sha256"))
    if not isinstance(text, str) or hashlib.sha256(text.encode()).hexdigest() != attrs[key]:
        raise StoreError(f"{name}: its root attributes are damaged ({key.removesuffix('_sha256')} does not match "
                         f"{key}); choose another --out, or delete {name} to start over")


# ---------------------------------------------------------------------------------------------
# pbrdf-cl verify

def _check_files(name, attrs):
    """Problems of the skeleton's files against the manifest, and of the consolidated metadata."""
    files = Files(name)
    meta, values = [], []
    for key, sha in (attrs.get(MANIFEST) or {}).items():
        data = files.get(key)
        if data is None or file_sha256(key, data) != sha:
            (meta if key.rsplit("/", 1)[-1] in META else values).append(key)
    out = []
    if MANIFEST not in attrs:
        out.append("no manifest of its files in the root attrs (written by an older pbrdf-cl, or its creation "
                   "was interrupted)")
    if meta:
        out.append(f"{len(meta)} metadata file(s) missing or altered: {first(meta)}")
    if values:
        arrays = sorted({k.rsplit('/', 1)[0] for k in values})
        out.append(f"the values of {len(arrays)} coordinate or label array(s) missing or altered: {first(arrays)}")
    cons = files.get(".zmetadata")
    try:
        stored = json.loads(cons)["metadata"] if cons is not None else None
    except (ValueError, KeyError, TypeError):
        stored = None
    if stored is None:
        out.append("the consolidated metadata (.zmetadata) is missing or unreadable")
    else:
        stale = [k for k, v in stored.items() if k.rsplit("/", 1)[-1] != ".zgroup"  # zarr 3 adds to those
                 and _canonical(k, files.get(k) or b"") != _canonical(k, json.dumps(v).encode())]
        if stale:
            out.append(f"the consolidated metadata (.zmetadata) differs from {len(stale)} file(s): {first(stale)}")
    return out


def verify_store(store):
    """Check a sweep or image-fit store without its spec: its files against the manifest in its
    root attrs, each done unit's values against its digest, the consolidated metadata and the
    completion mark; ``*.partial`` files of interrupted writes are removed (and said).

    Parameters
    ----------
    store : str or path
        A store of :func:`pbrdf_cl.sweep` or :func:`pbrdf_cl.fit_batch` (``store=``).

    Returns
    -------
    dict
        ``store``, ``units``, ``done``, ``damaged`` (the units whose values do not match their
        digests), ``problems`` (one line per kind of damage; empty when intact), ``notes``
        (lines that are not damage) and ``ok``.

    Raises
    ------
    StoreError
        Not a store of pbrdf-cl.

    Examples
    --------
    >>> verify_store("sigma_theta.zarr")["ok"]  # doctest: +SKIP
    True
    """
    name = zarr_store.store_name(store)
    if zarr_store.is_local(store) and not Path(name, ".zgroup").is_file():
        raise StoreError(f"{name} is not a Zarr store (no .zgroup)")
    attrs = read_root_attrs(name)
    notes, problems = [], []
    if zarr_store.is_local(store):
        n = zarr_store.clean_partials(name)
        if n:
            notes.append(f"removed {n} .partial file(s) left by interrupted writes")
    if attrs is None or not isinstance(attrs.get(UNITS), dict):
        what = "missing or unreadable" if attrs is None else "not those of a pbrdf-cl store (no store_units)"
        problems.append(f"the root attributes (.zattrs) are {what}; what it holds cannot be told")
        return dict(store=name, units=0, done=0, damaged=[], problems=problems, notes=notes, ok=False)
    units = attrs[UNITS]
    sha_key = f"{units['job']}_sha256"
    try:
        refuse_unidentified(name, attrs, sha_key, "a pbrdf-cl store")
    except StoreError:
        problems.append(f"the root attributes are damaged: {units['job']} does not match {sha_key}")
    problems += _check_files(name, attrs)
    n_units = int(units["count"])
    done = read_done(name, n_units)
    bad = damaged_units(name, np.flatnonzero(done), units["variables"])
    if bad:
        problems.append(f"{len(bad)} of {int(done.sum())} done units' values do not match their digests "
                        f"(missing, truncated or altered chunks): units {first(bad)}")
    missing = int((~done).sum())
    if attrs.get(units["complete"]) and missing:
        problems.append(f"marked complete ({units['complete']}) but {missing} of {n_units} units are not done: "
                        f"units {first(np.flatnonzero(~done))}")
    elif missing:
        notes.append(f"{missing} of {n_units} units not computed yet (run the same command again to resume)")
    return dict(store=name, units=n_units, done=int(done.sum()) - len(bad), damaged=bad, problems=problems,
                notes=notes, ok=not problems)


def complete(name, n_units, key, variables):
    """Set the root attribute ``key`` (``sweep_complete``, ``batch_complete``) when every unit is
    done and matches its digest, else make sure it is False (damaged units are un-marked, to be
    computed by the next run); consolidate the metadata.  Returns the damaged units."""
    done, bad = check_units(name, n_units, variables)
    g = zarr_store.open_group(name, "r+")
    ok = bool(done.all())
    if bool(g.attrs.get(key)) != ok:
        g.attrs[key] = ok
    zarr_store.consolidate(name)
    return bad


def record_device(name, description):
    """Add ``description`` to the store's devices (root attribute :data:`pbrdf_cl.store.zarr.DEVICES`,
    key -> description); returns the descriptions recorded before it when it is new, else None."""
    g = zarr_store.open_group(name, "r+")
    known = dict(g.attrs.get(zarr_store.DEVICES, {}))
    key = str(zarr_store.device_key(description))
    if key in known:
        return None
    g.attrs[zarr_store.DEVICES] = {**known, key: description}
    zarr_store.consolidate(name)
    return list(known.values())
