"""Host work spread over this machine's cores in forked processes (:func:`spread`).

Some of the fits' host work is many small numpy operations on independent problems (a label's
integrated correction: a few hundred calls of the reference model on a few hundred rows each).
Such work holds the GIL for most of its time, so threads add no speed; forked processes do.
:func:`spread` splits the items into shares, one per usable core (at most), computes the first
share here and each other share in a child forked for it, which sends its results back through a
pipe and ends with ``os._exit`` (no exit handlers, no finalisers).

Where this is safe and where it is used: on Linux only (``os.fork``), for work of numpy on the
host alone: a child never calls the OpenCL driver, whose threads it does not have, nor anything
that another thread of this process may hold a lock of (it imports nothing, logs nothing, prints
nothing; its garbage collector is off).  Whatever a child does not deliver (it failed, or it did
not answer in time: ``WAIT_FACTOR`` times as long as this process's own share took, at least
``WAIT_MIN`` seconds) is computed here after all, so the results are the same either way, only
slower.  ``PBRDF_CL_HOST_PROCESSES=1`` keeps all the work in this process (another number: at most
that many processes).

What a fork costs: a few milliseconds, and some more in this process's host work after it
(measured on a 2-core Xeon, 0.18 s fits: one of the first two ``pbrdf_cl.fit`` calls after a fork
took 40-60 ms longer, the later ones not; the cause not found: not the page faults of copy on
write, a few thousand, nor OpenBLAS's threads).  So only work of a hundred milliseconds and more that splits evenly is
spread: the labels' integrated correction (a 32x32 two-label fit 35 ms faster, end to end, the
cost included).  :func:`pbrdf_cl.fit_joint`'s separate fits were tried and lost more than
they gained (their lockstep batching too): they stay in one process.
"""
from __future__ import annotations

import gc
import os
import pickle
import select
import signal
import sys
import time
import warnings

#: How long a child's share is waited for, once this process's own is done: this many times as
#: long as that took, and at least WAIT_MIN seconds; then it is computed here.
WAIT_FACTOR = 10.0
WAIT_MIN = 30.0
#: The environment variable that bounds the processes (1: all the work here).
ENV = "PBRDF_CL_HOST_PROCESSES"


def host_processes():
    """How many processes :func:`spread` may use: the cores this process may run on (1 where
    ``os.fork`` is not available or the platform is not Linux), at most ``PBRDF_CL_HOST_PROCESSES``."""
    if not sys.platform.startswith("linux") or not hasattr(os, "fork"):
        return 1
    try:
        cores = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        cores = os.cpu_count() or 1
    limit = os.environ.get(ENV, "").strip()
    if limit:
        try:
            cores = min(cores, int(limit))
        except ValueError:
            raise ValueError(f"{ENV}: {limit!r} is not a whole number of processes") from None
    return max(1, cores)


def shares(weights, n):
    """The items (indices of ``weights``, the work of each) split into at most ``n`` shares of
    about equal weight (the heaviest first, each to the lightest share), each share's items in
    ascending order; no empty share."""
    n = max(1, min(int(n), len(weights)))
    load, out = [0.0] * n, [[] for _ in range(n)]
    for i in sorted(range(len(weights)), key=lambda i: (-float(weights[i]), i)):
        s = min(range(n), key=lambda s: (load[s], s))
        load[s] += float(weights[i])
        out[s].append(i)
    return [sorted(s) for s in out if s]


def spread(fn, items, weights=None, processes=None):
    """``fn(share)`` of every share of ``items`` (:func:`shares` by ``weights``, default equal),
    the first here, the others in forked children where :func:`host_processes` (or
    ``processes``) allows more than one: ``fn`` takes a list of items and returns a list of as
    many results (picklable).  Returns the results in the order of ``items``: the same as
    ``fn(items)`` gives where ``fn``'s result for an item does not depend on the other items of
    its share."""
    items = list(items)
    n = host_processes() if processes is None else processes
    parts = shares([1.0] * len(items) if weights is None else weights, n)
    if len(parts) < 2:
        return list(fn(items))
    children = {}  # share -> (pid, fd)
    try:
        for s, part in enumerate(parts[1:], start=1):
            try:
                children[s] = _fork(fn, [items[i] for i in part])
            except OSError:  # no process or pipe to be had (a limit): computed here
                pass
        t0 = time.monotonic()
        results = {0: list(fn([items[i] for i in parts[0]]))}
        deadline = time.monotonic() + max(WAIT_MIN, WAIT_FACTOR * (time.monotonic() - t0))
        for s, part in enumerate(parts[1:], start=1):
            got = _receive(children[s][1], deadline) if s in children else None
            results[s] = got if got is not None and len(got) == len(part) else list(fn([items[i] for i in part]))
    finally:
        for pid, fd in children.values():
            _end(pid, fd)
    out = [None] * len(items)
    for s, part in enumerate(parts):
        for i, r in zip(part, results[s]):
            out[i] = r
    return out


def _fork(fn, share):
    """A child computing ``fn(share)``: (its pid, the read end of its pipe); OSError where none
    can be made."""
    r, w = os.pipe()
    try:
        with warnings.catch_warnings():  # Python 3.12+ warns of fork in a process with threads: see the module
            warnings.simplefilter("ignore", DeprecationWarning)
            pid = os.fork()
    except OSError:
        os.close(r)
        os.close(w)
        raise
    if pid == 0:  # the child: compute, send, and end without running anything of the parent's
        try:
            os.close(r)
            gc.disable()
            try:  # an interrupt ends the child at once (this process recomputes nothing then: it stops too)
                signal.signal(signal.SIGINT, signal.SIG_DFL)
            except ValueError:  # not the main thread (an embedding that forbids it): the default stays
                pass
            payload = pickle.dumps(list(fn(share)), protocol=pickle.HIGHEST_PROTOCOL)
            view = memoryview(payload)
            while view:
                view = view[os.write(w, view):]
        finally:
            os._exit(0)
    os.close(w)
    return pid, r


def _receive(fd, deadline):
    """The results a child sent through its pipe ``fd``, or None where it sent none complete by
    ``deadline``."""
    chunks = []
    poll = select.poll()  # (not select.select: no limit on the descriptor's number)
    poll.register(fd, select.POLLIN | select.POLLHUP)
    while True:
        left = deadline - time.monotonic()
        if left <= 0 or not poll.poll(left * 1000.0):
            return None
        chunk = os.read(fd, 1 << 20)
        if not chunk:
            break
        chunks.append(chunk)
    try:
        return pickle.loads(b"".join(chunks))
    except Exception:  # a child that ended before it sent everything
        return None


def _end(pid, fd):
    """Close the pipe, and end and reap the child (killed where it has not ended)."""
    try:
        os.close(fd)
    except OSError:
        pass
    try:
        done, _ = os.waitpid(pid, os.WNOHANG)
        if done == 0:
            os.kill(pid, signal.SIGKILL)
            os.waitpid(pid, 0)
    except (ChildProcessError, ProcessLookupError):
        pass
