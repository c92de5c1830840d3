"""Host work spread over forked processes (``pbrdf_cl.fitting.processes``): the same results as in
one process, whatever a child does (fails, hangs, is interrupted), and no child left behind."""
import os
import sys
import time

import numpy as np
import pytest

from pbrdf_cl.fitting import processes as P

linux = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="forked processes on Linux only")


def squares(share):
    """Each item's square and the process that computed it."""
    return [(i * i, os.getpid()) for i in share]


@pytest.fixture
def forked(monkeypatch):
    """The pids of the children ``spread`` forks."""
    pids, fork = [], P._fork

    def spy(fn, share):
        pid, fd = fork(fn, share)
        pids.append(pid)
        return pid, fd
    monkeypatch.setattr(P, "_fork", spy)
    return pids


def gone(pid):
    """Whether the child ``pid`` has ended and been reaped."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    return False


def test_shares_are_balanced_in_order_and_never_empty():
    assert P.shares([128, 128], 2) == [[0], [1]]
    assert P.shares([5, 1, 1, 1, 1, 1], 2) == [[0], [1, 2, 3, 4, 5]]
    assert P.shares([1, 1, 1], 8) == [[0], [1], [2]]
    assert P.shares([3, 2, 2, 1], 1) == [[0, 1, 2, 3]]
    parts = P.shares(list(range(1, 11)), 3)
    assert sorted(i for s in parts for i in s) == list(range(10)) and all(s == sorted(s) for s in parts)
    loads = [sum(i + 1 for i in s) for s in parts]
    assert max(loads) - min(loads) <= 1


@linux
def test_children_compute_their_shares_and_are_reaped(forked):
    out = P.spread(squares, range(7), processes=3)
    assert [v for v, _ in out] == [i * i for i in range(7)]
    where = {pid for _, pid in out}
    assert os.getpid() in where and len(where) == 3 and len(forked) == 2 and where - {os.getpid()} == set(forked)
    assert all(gone(pid) for pid in forked)


@linux
def test_a_failing_child_is_computed_here(forked):
    parent = os.getpid()

    def fails_in_child(share):
        if os.getpid() != parent:
            raise RuntimeError("the child fails")
        return squares(share)
    out = P.spread(fails_in_child, range(4), processes=2)
    assert [v for v, _ in out] == [0, 1, 4, 9] and {pid for _, pid in out} == {parent}
    assert all(gone(pid) for pid in forked)


@linux
def test_a_child_that_does_not_answer_in_time_is_killed_and_computed_here(forked, monkeypatch):
    monkeypatch.setattr(P, "WAIT_MIN", 0.3)
    parent = os.getpid()

    def hangs_in_child(share):
        if os.getpid() != parent:
            time.sleep(60)
        return squares(share)
    t = time.monotonic()
    out = P.spread(hangs_in_child, range(4), processes=2)
    assert time.monotonic() - t < 10
    assert [v for v, _ in out] == [0, 1, 4, 9] and {pid for _, pid in out} == {parent}
    assert all(gone(pid) for pid in forked)


@linux
def test_an_interrupt_here_ends_the_children(forked):
    parent = os.getpid()

    def interrupted_here(share):
        if os.getpid() == parent:
            raise KeyboardInterrupt
        time.sleep(60)
        return squares(share)
    with pytest.raises(KeyboardInterrupt):
        P.spread(interrupted_here, range(4), processes=2)
    assert forked and all(gone(pid) for pid in forked)


@linux
def test_large_results_come_back_whole():
    out = P.spread(lambda share: [np.full(200_000, float(i)) for i in share], range(4), processes=2)
    assert [float(a[0]) for a in out] == [0.0, 1.0, 2.0, 3.0] and all(a.size == 200_000 for a in out)


def test_the_environment_bounds_the_processes(monkeypatch):
    monkeypatch.setenv(P.ENV, "1")
    assert P.host_processes() == 1
    pid = os.getpid()
    assert {p for _, p in P.spread(squares, range(5))} == {pid}
    monkeypatch.setenv(P.ENV, "two")
    with pytest.raises(ValueError, match="PBRDF_CL_HOST_PROCESSES: 'two' is not a whole number"):
        P.host_processes()
    monkeypatch.delenv(P.ENV)
    assert P.host_processes() >= 1
    monkeypatch.setattr(P.sys, "platform", "darwin")
    assert P.host_processes() == 1


@linux
def test_without_a_process_to_be_had_the_share_is_computed_here(monkeypatch):
    def no_fork():
        raise BlockingIOError(11, "Resource temporarily unavailable")
    monkeypatch.setattr(P.os, "fork", no_fork)
    opened = len(os.listdir("/proc/self/fd"))
    out = P.spread(squares, range(5), processes=2)
    assert [v for v, _ in out] == [0, 1, 4, 9, 16] and {pid for _, pid in out} == {os.getpid()}
    assert len(os.listdir("/proc/self/fd")) == opened  # the pipe closed


@linux
def test_spread_from_a_thread_forks_too(forked):
    """Called from a thread other than the main one (an app's worker thread), a child still
    computes its share."""
    import threading
    out = []
    t = threading.Thread(target=lambda: out.append(P.spread(squares, range(4), processes=2)))
    t.start()
    t.join(60)
    assert [v for v, _ in out[0]] == [0, 1, 4, 9] and len({pid for _, pid in out[0]}) == 2
    assert all(gone(pid) for pid in forked)


@linux
def test_a_pipe_numbered_above_1024_is_read(forked):
    """Processes with many open files (a cluster's sockets, stores) get pipes numbered above
    select()'s limit of 1024: the results come back all the same."""
    import resource
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if hard != resource.RLIM_INFINITY and hard < 1200:
        pytest.skip("the open-file limit is below 1200")
    resource.setrlimit(resource.RLIMIT_NOFILE, (max(soft, 1200), hard))
    held = []
    try:
        while not held or held[-1] < 1030:
            held.append(os.open(os.devnull, os.O_RDONLY))
        out = P.spread(squares, range(4), processes=2)
    finally:
        for fd in held:
            os.close(fd)
        resource.setrlimit(resource.RLIMIT_NOFILE, (soft, hard))
    assert [v for v, _ in out] == [0, 1, 4, 9] and len({pid for _, pid in out}) == 2
