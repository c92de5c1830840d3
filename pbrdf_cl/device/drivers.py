"""OpenCL drivers that pip installs, and the environment problems that hide a driver.

- **Intel's CPU runtime** (``pip install 'pbrdf-cl[intel-cpu]'``: the ``intel-opencl-rt`` and
  ``intel-cmplr-lib-rt`` wheels) is found and registered by :func:`register_pip_drivers`, which
  runs before this process makes its first OpenCL call.  Its wheel ships an ICD file naming a
  placeholder path (``/opt/anaconda1anaconda2anaconda3/lib/libintelocl.so``), in a folder no
  loader reads.  We write an ICD file naming the real ``libintelocl.so`` into a vendors folder of
  our own, beside copies of the ICD files the loader would have read anyway (``OCL_ICD_VENDORS``
  if set, else ``/etc/OpenCL/vendors``), and point this process's ``OCL_ICD_VENDORS`` there: the
  system's drivers (an NVIDIA GPU, a system PoCL) stay visible, and so do the drivers that
  pyopencl's own loader finds in its package folder (the bundled PoCL, Oclgrind).  The runtime's
  libraries (libimf, libsvml, libirng, libintlc, libtbb) are loaded first, globally, so the
  driver links whichever folder pip put them in.
- **PoCL's kernel cache**: PoCL lists no device at all when its cache folder cannot be written
  (:func:`pocl_cache_problem` says so instead).

Set ``PBRDF_CL_NO_DRIVER_REGISTRATION=1`` to leave the loader's environment alone.
"""
from __future__ import annotations

import ctypes
import dataclasses
import hashlib
import json
import os
import re
import tempfile
import threading
from pathlib import Path

#: The remedies named wherever no OpenCL device can be used.
REMEDIES = ("`apt-get install pocl-opencl-icd` (a system PoCL; in conda: `conda install -c conda-forge pocl`), "
            "`pip install 'pbrdf-cl[intel-cpu]'` (Intel's CPU runtime, registered by pbrdf-cl itself), or the numpy "
            "backend (--backend numpy, backend=\"numpy\")")

SYSTEM_VENDORS = "/etc/OpenCL/vendors"
#: Libraries of Intel's runtime and of the compiler runtime it links, loaded before the driver.
INTEL_DEPENDENCIES = ("libintlc.so.5", "libimf.so", "libsvml.so", "libirng.so", "libtbb.so.12")

_registered = None  # what register_pip_drivers did in this process (None: not run yet)


def _cache_folder(env, name):
    """``$env`` if set, else ``$XDG_CACHE_HOME/name``, else ``~/.cache/name``."""
    if os.environ.get(env):
        return Path(os.environ[env])
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / name


def cache_dir() -> Path:
    """pbrdf-cl's own cache folder: ``PBRDF_CL_CACHE_DIR``, else ``$XDG_CACHE_HOME/pbrdf-cl``,
    else ``~/.cache/pbrdf-cl``."""
    return _cache_folder("PBRDF_CL_CACHE_DIR", "pbrdf-cl")


def writable_dir(path) -> str | None:
    """None if ``path`` is (or can be made) a folder this process can write into, else why not."""
    path = Path(path)
    try:
        path.mkdir(parents=True, exist_ok=True)
        fd, name = tempfile.mkstemp(prefix=".pbrdf-cl-write-test-", dir=path)
        os.close(fd)
        os.unlink(name)
    except OSError as exc:
        return exc.strerror or str(exc)
    return None


def _dist_files(name):
    from importlib import metadata
    try:
        dist = metadata.distribution(name)
    except metadata.PackageNotFoundError:
        return None, []
    return dist, list(dist.files or [])


def find_intel_runtime():
    """``(libintelocl.so path, [dependency paths])`` of a pip-installed Intel CPU runtime, or None."""
    dist, files = _dist_files("intel-opencl-rt")
    lib = None
    for f in files:
        if f.name == "libintelocl.so":
            lib = Path(dist.locate_file(f)).resolve()
            break
    if lib is None or not lib.is_file():
        return None
    folders = [lib.parent]
    for name in ("intel-cmplr-lib-rt", "tbb"):
        d, fs = _dist_files(name)
        folders += [Path(d.locate_file(f)).resolve().parent for f in fs if f.name.startswith("lib") and ".so" in f.name]
    deps = []
    for dep in INTEL_DEPENDENCIES:
        for folder in dict.fromkeys(folders):
            if (folder / dep).is_file():
                deps.append(folder / dep)
                break
    return lib, deps


def _vendor_sources():
    """The ICD files the loader would read without us: ``OCL_ICD_VENDORS`` (a folder, or one
    driver library) if set, else the system folder.  Returns (name, content) pairs."""
    where = os.environ.get("OCL_ICD_VENDORS") or SYSTEM_VENDORS
    p = Path(where)
    if p.is_dir():
        out = []
        for f in sorted(p.iterdir()):
            if f.suffix == ".icd":
                try:
                    out.append((f.name, f.read_text()))
                except OSError:
                    continue
        return out
    if p.exists():  # the loader takes a file here as one driver library
        return [("user-driver.icd", str(p) + "\n")]
    return []


def _write_vendors(entries):
    """A vendors folder holding ``entries`` (name, content), content-addressed in the cache (or a
    temporary folder if the cache cannot be written); returns its path."""
    digest = hashlib.sha256(repr(sorted(entries)).encode()).hexdigest()[:16]
    for base in (cache_dir() / "icd", Path(tempfile.gettempdir()) / f"pbrdf-cl-icd-{os.getuid()}"):
        folder = base / digest
        try:
            folder.mkdir(parents=True, exist_ok=True)
            for name, content in entries:
                target = folder / name
                if not target.is_file() or target.read_text() != content:
                    tmp = folder / f".{name}.{os.getpid()}"
                    tmp.write_text(content)
                    os.replace(tmp, target)
            return folder
        except OSError:
            continue
    return None


def register_pip_drivers():
    """Make a pip-installed Intel CPU runtime visible to this process's OpenCL loader (see the
    module docstring).  Call before the first OpenCL call; idempotent.  Returns a dict saying
    what was done (``{}`` when there was nothing to do)."""
    global _registered
    if _registered is not None:
        return _registered
    _registered = {}
    if os.environ.get("PBRDF_CL_NO_DRIVER_REGISTRATION"):
        return _registered
    found = find_intel_runtime()
    if found is None:
        return _registered
    lib, deps = found
    loaded, failed = [], []
    for dep in deps:
        try:
            ctypes.CDLL(str(dep), mode=ctypes.RTLD_GLOBAL)
            loaded.append(str(dep))
        except OSError as exc:
            failed.append(f"{dep.name}: {exc}")
    entries = [e for e in _vendor_sources() if e[0] != "pbrdf-cl-intel-cpu.icd"]
    entries.append(("pbrdf-cl-intel-cpu.icd", f"{lib}\n"))
    folder = _write_vendors(entries)
    if folder is None:
        _registered = dict(intel_cpu=str(lib), error="no writable folder for the ICD file")
        return _registered
    previous = os.environ.get("OCL_ICD_VENDORS")
    os.environ["OCL_ICD_VENDORS"] = str(folder)
    _registered = dict(intel_cpu=str(lib), vendors=str(folder), previous_vendors=previous, preloaded=loaded,
                       preload_failed=failed)
    return _registered


def pocl_cache_dir() -> Path:
    """The folder PoCL caches compiled kernels in: ``POCL_CACHE_DIR``, else
    ``$XDG_CACHE_HOME/pocl``, else ``~/.cache/pocl``."""
    return _cache_folder("POCL_CACHE_DIR", "pocl")


def pocl_cache_problem() -> str | None:
    """A one-line description of what is wrong with PoCL's cache folder, or None."""
    folder = pocl_cache_dir()
    why = writable_dir(folder)
    if why is None:
        return None
    var = "POCL_CACHE_DIR" if os.environ.get("POCL_CACHE_DIR") else "PoCL's default cache folder"
    return (f"{var} {str(folder)!r} cannot be written ({why}), and PoCL then lists no devices; point "
            f"POCL_CACHE_DIR at a writable folder (e.g. POCL_CACHE_DIR=$PWD/.pocl-cache)")


class RecordStore:
    """A JSON file of records (dataclass instances by key) in :func:`cache_dir`: the device probe's
    results and the trial builds' verdicts.  Read again only when the file changed; written
    whole, atomically (a temporary file renamed over it), under an advisory lock on
    ``<name>.lock``, so that processes of one machine (pytest-xdist or dask workers) add records
    side by side.  A record that cannot be read back as ``cls`` is ignored; the store only saves
    work, so a folder that cannot be written is harmless."""

    def __init__(self, name, cls):
        self.name, self.cls = name, cls
        self._seen = {}  # path -> ((mtime_ns, size), entries)

    @property
    def path(self) -> Path:
        return cache_dir() / self.name

    def entries(self):
        """key -> the record's fields, as stored."""
        path = self.path
        try:
            st = path.stat()
            stamp = (st.st_mtime_ns, st.st_size)
            seen = self._seen.get(path)
            if seen is not None and seen[0] == stamp:
                return seen[1]
            data = json.loads(path.read_text())
        except (OSError, ValueError):
            return {}
        data = data if isinstance(data, dict) else {}
        self._seen[path] = (stamp, data)
        return data

    def get(self, key, **extra):
        """The record under ``key`` (with the fields ``extra`` set, e.g. ``cached=True``), or None."""
        entry = self.entries().get(key)
        if entry is None:
            return None
        try:
            return self.cls(**{**entry, **extra})
        except TypeError:
            return None

    def records(self, **extra):
        """Every record that reads back as ``cls``."""
        return [r for r in (self.get(k, **extra) for k in self.entries()) if r is not None]

    def put(self, key, record, skip=()):
        """Store ``record`` under ``key`` (without the fields ``skip``)."""
        path = self.path
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            with _FileLock(path.with_name(path.name + ".lock")):
                entries = dict(self.entries())
                entries[key] = {k: v for k, v in dataclasses.asdict(record).items() if k not in skip}
                tmp = path.with_name(f".{path.name}.{os.getpid()}.{threading.get_ident()}")
                tmp.write_text(json.dumps(entries, indent=1))
                os.replace(tmp, path)
        except OSError:
            pass

    def clear(self):
        """Delete the file (and forget what was read)."""
        self._seen.clear()
        try:
            self.path.unlink()
        except OSError:
            pass


class _FileLock:
    """An advisory lock on a file (``fcntl.flock``); a no-op where locking is unavailable."""

    def __init__(self, path):
        self.path = path

    def __enter__(self):
        self.fd = None
        try:
            import fcntl
            self.fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
            fcntl.flock(self.fd, fcntl.LOCK_EX)
        except (OSError, ImportError):
            if self.fd is not None:
                os.close(self.fd)
            self.fd = None
        return self

    def __exit__(self, *exc):
        if self.fd is not None:
            os.close(self.fd)  # releases the lock
        return False


def first_error_line(text) -> str:
    """The line of a build log or driver message that says what went wrong (one line)."""
    # source locations ("/.../kcache/tempfile_x.cl:1:2: " from PoCL, "77:1:2: " from Intel's compiler)
    lines = [re.sub(r"(?:\S+\.cl|(?<!\S)\d+):\d+:\d+:\s*", "", ln.strip()) for ln in str(text).splitlines()
             if ln.strip()]
    noise = re.compile(r"clBuildProgram failed|^Build on <|^\(options:|^\(source saved|^=+$", re.I)
    useful = [ln for ln in lines if not noise.search(ln)]
    for ln in useful:
        if re.search(r"\berror\b", ln, re.I):
            return ln[:300]
    return (useful or lines or ["unknown error"])[0][:300]


def describe(dev) -> str:
    """``"platform / device"`` of a ``cl.Device``."""
    return f"{dev.platform.name.strip()} / {dev.name.strip()}"
