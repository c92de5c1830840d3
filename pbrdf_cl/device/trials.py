"""Trial builds in a child process: no OpenCL driver may take the user's process down.

A driver can crash, abort or hang while it compiles one of our programs (PyPI's PoCL 3.0, whose
LLVM 14 aborts with ``LLVM ERROR: Do not know how to scalarize this operator's operand!`` or
segfaults on 512-bit vector code on AVX-512 hosts; see docs/guide/devices.md).  Such a
failure cannot be caught in the process that suffers it.  So before a process first builds a
program on a device, the program is built there, and each of its kernels launched once, in a child
process (:mod:`pbrdf_cl.device._trial_child`), with a time limit.  The child's answer is a *verdict*:
usable, or not and why (the build log's first error line, the child's last line and the signal
that killed it, or "timed out after 120 s").  Verdicts are stored on disk beside the probe cache
(``verdicts-v1.json`` in :func:`pbrdf_cl.device.drivers.cache_dir`), keyed by the driver, the device, the
kernel sources, the program and its build options, so a later process trusts them without a
child.  One verdict stands for a family of builds that differ only in sizes (``-DPB_NNK=...``,
see :func:`family`).  The device probe runs in the same child.

One child serves a process's requests one after another (started on the first, restarted after
a crash, gone when idle for 10 minutes or when the process ends).  It compiles into a PoCL cache
folder of its own; what a successful trial compiled is moved into ``POCL_CACHE_DIR`` afterwards
(one rename per program), so the parent's build finds it, and what a crashed trial half wrote is
deleted with its folder: nothing a crash leaves behind is trusted later.

Environment:

- ``PBRDF_CL_TRIAL_TIMEOUT``: the time limit of one trial, seconds (default 120);
- ``PBRDF_CL_TRIALS=0``: build in the process itself, without trials or stored verdicts (at the
  risk the trials exist to remove);
- ``PBRDF_CL_FAKE_TRIAL_CRASH=<device>:<program>:<how>`` (tests): the child dies as a broken
  driver would (``how``: ``segv``, ``abort``, ``llvm`` = an LLVM ERROR line then abort, ``hang``,
  ``exit``) when it tries a program whose label contains ``<program>`` on a device whose
  "platform / device" name contains ``<device>`` (case-insensitive substrings; empty matches all).
"""
from __future__ import annotations

import atexit
import dataclasses
import hashlib
import json
import os
import re
import select
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

from ..errors import TrialError
from . import drivers

TIMEOUT_ENV = "PBRDF_CL_TRIAL_TIMEOUT"
ENABLE_ENV = "PBRDF_CL_TRIALS"
FAKE_ENV = "PBRDF_CL_FAKE_TRIAL_CRASH"
DEFAULT_TIMEOUT = 120.0
VERDICT_CACHE_VERSION = 1
#: Build options (-D names) that only size a program: one verdict stands for all their values of
#: the same class (see :func:`family`).
SIZE_DEFINES = ("PB_NNK", "PB_NM", "PB_NI", "PB_ROW_LEN")
FAKE_WAYS = ("segv", "abort", "llvm", "hang", "exit")

#: What this process did, for tests and ``pbrdf-cl devices``: children started, trials run.
STATS = {"children": 0, "trials": 0}


@dataclasses.dataclass
class Verdict:
    """Whether a device can build and run one program.  ``reason``: what the trial found, one line
    (why not: a build error, the child's last line and signal, a timeout); ``program``: the
    program's label (file, precision, the options that choose code); ``seconds``: how long the
    trial took; ``cached``: read from the disk store."""

    usable: bool
    reason: str
    program: str = ""
    device: str = ""
    seconds: float = 0.0
    when: str = ""
    cached: bool = False
    device_key: str = ""


def enabled() -> bool:
    return os.environ.get(ENABLE_ENV, "1").strip().lower() not in ("0", "no", "off", "false")


def timeout() -> float:
    text = os.environ.get(TIMEOUT_ENV, "").strip()
    if not text:
        return DEFAULT_TIMEOUT
    try:
        value = float(text)
    except ValueError:
        raise ValueError(f"{TIMEOUT_ENV}={text!r} is not a number of seconds") from None
    if not value > 0:
        raise ValueError(f"{TIMEOUT_ENV}={text!r} must be a positive number of seconds")
    return value


def fake_way(device_name: str, label: str):
    """The way the test switch makes the child die for this device and program, or None."""
    text = os.environ.get(FAKE_ENV, "").strip()
    if not text:
        return None
    parts = text.split(":")
    if len(parts) != 3 or parts[2].strip().lower() not in FAKE_WAYS:
        raise ValueError(f"{FAKE_ENV}={text!r}: expected <device>:<program>:<how> with how one of "
                         f"{', '.join(FAKE_WAYS)}")
    dev, prog, how = (p.strip().lower() for p in parts)
    return how if dev in device_name.lower() and prog in label.lower() else None


# ---------------------------------------------------------------------------------------------
# verdict keys: a family of builds

def _size_class(value, width):
    """Which sizes build the same code paths: 1; below the vector width (no vector loop); a whole
    multiple of it (no remainder loop); larger and not a multiple (both loops)."""
    try:
        v = int(value)
    except ValueError:
        return value
    if v <= 1:
        return "1"
    if v < width:
        return "<vw"
    return "n*vw" if v % width == 0 else ">vw"


def family(options, prefix=""):
    """The build options (and prepended source) with the sizes replaced by their class and the
    include folder dropped (the sources' hash is in the key): builds of one family share a verdict."""
    opts = list(options)
    width = 16
    for o in opts:
        m = re.fullmatch(r"-DPB_VW=(\d+)", o)
        if m:
            width = int(m.group(1))
    out, skip = [], False
    for o in opts:
        if skip:
            skip = False
            continue
        if o == "-I":
            skip = True
            continue
        if o.startswith("-I"):
            continue
        m = re.fullmatch(r"-D(\w+)=(.*)", o)
        if m and m.group(1) in SIZE_DEFINES:
            o = f"-D{m.group(1)}={_size_class(m.group(2), width)}"
        out.append(o)
    prefix_family = re.sub(r"\b\d+\b", "#", prefix)
    return out, prefix_family


def label(filename, dtype, options):
    """``pbrdf_grid.cl (float32, PB_OBJECTIVE, PB_ROW_LEVEL=1)``: the file, the precision and the
    options that choose code (not sizes, not the shared ones), for messages."""
    keep = []
    for o in options:
        m = re.fullmatch(r"-D(\w+)(?:=(.*))?", o)
        if not m or m.group(1) in SIZE_DEFINES or m.group(1) in ("PBRDF_DOUBLE", "PB_VW"):
            continue
        keep.append(o[2:])
    return f"{filename} ({', '.join([dtype] + keep)})"


def device_key(dev):
    """A short hash of the device and its driver (the verdicts of :func:`stored_verdicts` carry it)."""
    return hashlib.sha256(json.dumps(device_identity(dev), sort_keys=True).encode()).hexdigest()[:16]


def device_identity(dev):
    plat = dev.platform
    return dict(platform=plat.name.strip(), platform_version=plat.version.strip(), device=dev.name.strip(),
                vendor=dev.vendor.strip(), driver=dev.driver_version.strip(), version=dev.version.strip())


def program_key(filename, options, prefix=""):
    """A program family's key, the same on every device (whatever vector width each builds it with)."""
    opts, pre = family(options, prefix)
    opts = [o for o in opts if not o.startswith("-DPB_VW=")]
    return hashlib.sha256(json.dumps([filename, opts, pre]).encode()).hexdigest()[:24]


def verdict_key(dev, kernels_sha, filename, source, options, prefix, fake):
    opts, pre = family(options, prefix)
    parts = dict(device=device_identity(dev), kernels=kernels_sha, program=filename, options=opts, prefix=pre,
                 source=hashlib.sha256(source.encode()).hexdigest(), fake=fake, v=VERDICT_CACHE_VERSION)
    return hashlib.sha256(json.dumps(parts, sort_keys=True).encode()).hexdigest()


# ---------------------------------------------------------------------------------------------
# the store on disk (beside the probe cache)

_MEMORY = {}
_STORE_LOCK = threading.Lock()
STORE = drivers.RecordStore(f"verdicts-v{VERDICT_CACHE_VERSION}.json", Verdict)


def store_file() -> Path:
    return STORE.path


def stored_verdicts(dev=None):
    """The verdicts on disk (of device ``dev`` only, if given), as a list of :class:`Verdict`, oldest first."""
    want = device_key(dev) if dev is not None else None
    out = [v for v in STORE.records(cached=True) if want is None or v.device_key == want]
    return sorted(out, key=lambda v: v.when)


def forget(disk=False):
    """Forget this process's verdicts (and, with ``disk``, the stored ones)."""
    with _STORE_LOCK:
        _MEMORY.clear()
        if disk:
            STORE.clear()


# ---------------------------------------------------------------------------------------------
# the child

def _signal_name(code):
    try:
        return f"signal {code} ({signal.Signals(code).name})"
    except ValueError:
        return f"signal {code}"


class _Child:
    """One child process and its private PoCL cache folder."""

    def __init__(self):
        # PoCL keeps programs in $POCL_CACHE_DIR/XX/..., or in <its default folder>/kcache/XX/...
        folder = drivers.pocl_cache_dir()
        self.shared_cache = folder if os.environ.get("POCL_CACHE_DIR") else folder / "kcache"
        base = folder if drivers.writable_dir(folder) is None else Path(tempfile.gettempdir())
        self.private_cache = Path(tempfile.mkdtemp(prefix=f"pbrdf-trial-{os.getpid()}-", dir=base))
        self.stderr = tempfile.TemporaryFile(mode="w+b")
        env = dict(os.environ)
        env["POCL_CACHE_DIR"] = str(self.private_cache)
        env["PBRDF_CL_TRIAL_PRELOAD"] = json.dumps((drivers.register_pip_drivers() or {}).get("preloaded", []))
        script = Path(__file__).with_name("_trial_child.py")
        try:
            self.proc = subprocess.Popen([sys.executable, str(script)], stdin=subprocess.PIPE,
                                         stdout=subprocess.PIPE, stderr=self.stderr, env=env,
                                         start_new_session=True, close_fds=True)
        except OSError as exc:
            self._remove_cache()
            raise TrialError(f"cannot start the trial process ({exc})") from None
        STATS["children"] += 1

    def alive(self):
        return self.proc.poll() is None

    def ask(self, request, limit):
        """Send one request; the answer (a dict), or None with ``self.death`` saying why there is none.
        ``self.text``: what the child printed to stderr meanwhile (its drivers' messages)."""
        offset = self.offset = self.stderr.seek(0, os.SEEK_END)
        try:
            self.proc.stdin.write((json.dumps(request) + "\n").encode())
            self.proc.stdin.flush()
        except OSError:
            pass  # it died already: the read below says how
        deadline = time.monotonic() + limit
        fd = self.proc.stdout.fileno()
        while True:
            left = deadline - time.monotonic()
            if left <= 0:
                self.kill()
                self.death = f"timed out after {limit:g} s"
                return None
            ready, _, _ = select.select([fd], [], [], min(left, 1.0))
            if ready:
                line = self.proc.stdout.readline()
                if line:
                    return json.loads(line)
                break  # end of file: the child is gone
        code = self.proc.wait()
        last = self._last_line(offset)
        how = _signal_name(-code) if code < 0 else f"exit status {code}"
        self.death = f"{last}; {how}" if last else f"the child died, {how}"
        return None

    def text_since(self, offset):
        """What the child printed to stderr after ``offset``, without its own request lines."""
        try:
            self.stderr.seek(offset)
            text = self.stderr.read().decode(errors="replace")
        except (OSError, ValueError):
            return ""
        return "\n".join(ln for ln in text.splitlines() if not ln.startswith("pbrdf-cl trial:"))

    def _last_line(self, offset):
        lines = [ln.strip() for ln in self.text_since(offset).splitlines() if ln.strip()]
        return lines[-1][:300] if lines else ""

    def adopt_cache(self):
        """Move what the child compiled into the shared PoCL cache (whole program folders
        ``XX/<rest of the hash>``, renamed: a reader sees all of one or none of it)."""
        for bucket in self.private_cache.iterdir():
            if len(bucket.name) != 2 or not bucket.is_dir():
                continue
            for entry in bucket.iterdir():
                target = self.shared_cache / bucket.name / entry.name
                try:
                    if not target.exists():
                        target.parent.mkdir(parents=True, exist_ok=True)
                        os.rename(entry, target)
                except OSError:
                    pass
            shutil.rmtree(bucket, ignore_errors=True)

    def kill(self):
        try:
            os.killpg(self.proc.pid, signal.SIGKILL)
        except (OSError, ProcessLookupError):
            pass
        try:
            self.proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            pass

    def close(self):
        try:
            self.proc.stdin.close()
        except OSError:
            pass
        try:
            self.proc.wait(timeout=5)
        except subprocess.TimeoutExpired:
            self.kill()
        self._remove_cache()
        self.stderr.close()

    def _remove_cache(self):
        shutil.rmtree(self.private_cache, ignore_errors=True)


_CHILD = None
_CHILD_LOCK = threading.Lock()


def _close_child():
    global _CHILD
    if _CHILD is not None:
        _CHILD.close()
        _CHILD = None


atexit.register(_close_child)


_LAST_TEXT = [""]


def last_child_text():
    """What the child printed to stderr during the last request (the drivers' messages)."""
    return _LAST_TEXT[0]


def _ask(request, limit):
    """Run one request in the child (started if needed); (answer or None, why none)."""
    global _CHILD
    STATS["trials"] += 1
    _LAST_TEXT[0] = ""
    for attempt in range(2):
        if _CHILD is not None and not _CHILD.alive():  # gone idle, or killed by someone
            _CHILD.close()
            _CHILD = None
        if _CHILD is None:
            _CHILD = _Child()
        child = _CHILD
        answer = child.ask(request, limit)
        _LAST_TEXT[0] = child.text_since(child.offset)
        if answer is not None:
            if answer.get("ok"):
                child.adopt_cache()
            return answer, ""
        _CHILD = None
        child.close()
        if attempt == 0 and child.death.endswith("exit status 0") and not request.get("fake"):
            continue  # it went idle just as we asked: ask a fresh one
        return None, child.death
    return None, "the trial process exited without answering"


def device_spec(dev, index=None):
    ident = device_identity(dev)
    return dict(platform=ident["platform"], device=ident["device"], driver=ident["driver"],
                index=list(index) if index else [-1, -1])


def _now():
    return time.strftime("%Y-%m-%dT%H:%M:%S")


def check_program(dev, index, kernels_sha, filename, dtype, source, options, prefix=""):
    """The verdict on building ``prefix + source`` with ``options`` on ``dev``: from this process's
    memory, else the disk store, else a trial in the child (stored afterwards)."""
    name = drivers.describe(dev)
    what = label(filename, dtype, options)
    fake = fake_way(name, what)
    key = verdict_key(dev, kernels_sha, filename, source, options, prefix, fake)
    with _STORE_LOCK:
        if key in _MEMORY:
            return _MEMORY[key]
        verdict = STORE.get(key, cached=True)
        if verdict is not None:
            _MEMORY[key] = verdict
            return verdict
    with _CHILD_LOCK:
        with _STORE_LOCK:  # another thread may have tried it meanwhile
            if key in _MEMORY:
                return _MEMORY[key]
        limit = timeout()
        request = dict(op="program", label=f"{what} on {name}", device=device_spec(dev, index),
                       source=prefix + source, options=list(options), fake=fake)
        t0 = time.perf_counter()
        answer, death = _ask(request, limit)
        seconds = time.perf_counter() - t0
        if answer is None:
            verdict = Verdict(False, death, what, name, seconds, _now())
        elif answer.get("ok"):
            verdict = Verdict(True, f"built and launched {len(answer.get('kernels', []))} kernels", what, name,
                              seconds, _now())
        else:
            verdict = Verdict(False, _answer_error(answer), what, name, seconds, _now())
        verdict.device_key = device_key(dev)
        with _STORE_LOCK:
            _MEMORY[key] = verdict
        STORE.put(key, verdict, skip=("cached",))
        return verdict


def run_probe(dev, index, source, options_by_dtype, dtypes, points):
    """Build and run the device probe in the child: (values per dtype or None, why not)."""
    name = drivers.describe(dev)
    fake = fake_way(name, "pbrdf_probe.cl")
    request = dict(op="probe", label=f"pbrdf_probe.cl on {name}", device=device_spec(dev, index), source=source,
                   options=options_by_dtype, dtypes=list(dtypes), points=[list(map(float, p)) for p in points],
                   fake=fake)
    with _CHILD_LOCK:
        answer, death = _ask(request, timeout())
    if answer is None:
        return None, f"the probe crashed the driver: {death}"
    if not answer.get("ok"):
        return answer.get("values") or None, _answer_error(answer)
    return answer["values"], ""


def _answer_error(answer):
    """One line from a failed answer: its error, and the first line of the driver's log that says why."""
    error = answer.get("error", "failed")
    return f"{error}: {drivers.first_error_line(answer['log'])}" if answer.get("log") else error
