"""The checks of test_fork.py, each run in a new Python process: forking is safe only in a
process with one thread, and a test process keeps the threads of earlier tests (a Dask
client's IO loop). ``python fork_checks.py NAME [FOLDER]`` runs one; exit 0: it held."""

from __future__ import annotations

import os
import sys
import threading

import numpy as np

from nfdmatch._fork import can_fork, fork_map
from nfdmatch.errors import WorkerError


def check_every_task_is_computed_once_in_a_worker_and_collected_here(folder):
    got = {}
    lost = fork_map(lambda x: (x * x, os.getpid()), list(range(25)), 2, lambda i, r: got.setdefault(i, r))
    assert lost == []
    assert {i: r[0] for i, r in got.items()} == {i: i * i for i in range(25)}
    pids = {r[1] for r in got.values()}
    assert os.getpid() not in pids and 1 <= len(pids) <= 2


def check_the_tasks_of_a_worker_that_died_are_returned_to_the_caller(folder):
    got = {}

    def work(x):
        if x == 3:
            os._exit(9)  # as a worker killed for memory vanishes
        return x

    lost = fork_map(work, list(range(8)), 2, lambda i, r: got.setdefault(i, r))
    assert 3 in lost
    assert sorted(set(got) | set(lost)) == list(range(8))
    assert not set(got) & set(lost)
    assert all(got[i] == i for i in got)


def check_a_failing_task_raises_here_with_the_workers_traceback(folder):
    def work(x):
        if x == 2:
            raise ValueError("no good: 2")
        return x

    try:
        fork_map(work, list(range(5)), 2, lambda i, r: None)
    except WorkerError as exc:  # a RuntimeError, and an NfdError: the CLI says it in one line
        assert str(exc) == "a worker process failed: ValueError: no good: 2"
        assert "Traceback" in exc.detail and "no good: 2" in exc.detail
    else:
        raise AssertionError("no error")
    assert can_fork()  # nothing left running here


def check_a_fork_that_fails_leaves_the_tasks_to_the_workers_forked_or_to_the_caller(folder):
    """A fork refused (EAGAIN: ``ulimit -u``, memory) is no error: the workers forked
    before it do every task, and with none forked every task goes back to the caller."""
    import errno

    real, forks = os.fork, []

    def fork(allowed):
        def fork():
            forks.append(1)
            if len(forks) > allowed:
                raise BlockingIOError(errno.EAGAIN, os.strerror(errno.EAGAIN))
            return real()

        return fork

    for allowed in (1, 0):
        forks.clear()
        os.fork = fork(allowed)
        got = {}
        try:
            lost = fork_map(lambda x: x * x, list(range(10)), 3, lambda i, r: got.setdefault(i, r))
        finally:
            os.fork = real
        if allowed:
            assert (lost, got) == ([], {i: i * i for i in range(10)})
        else:
            assert (lost, got) == (list(range(10)), {})
    assert can_fork()


def check_a_worker_closes_the_descriptors_it_must_not_keep(folder):
    fd = os.open(os.path.join(folder, "lock"), os.O_CREAT | os.O_RDWR)

    def is_open(_):
        try:
            os.fstat(fd)
            return True
        except OSError:
            return False

    got = {}
    fork_map(is_open, [0, 1], 2, lambda i, r: got.setdefault(i, r), close_fds=[fd])
    assert got == {0: False, 1: False}
    os.fstat(fd)  # still open here


def check_no_garbage_of_the_parent_is_finalized_in_a_worker(folder):
    """An object of the parent's waiting for the cycle collector (an h5py file would be
    flushed and closed by its finalizer) is finalized in the parent only, once."""
    import gc

    log = os.path.join(folder, "finalized")

    class Held:
        def __del__(self):
            with open(log, "a") as f:
                f.write(f"{os.getpid()}\n")

    gc.disable()  # until the fork: the cycle below stays uncollected
    a, b = Held(), Held()
    a.other, b.other = b, a  # a cycle: only the collector frees it
    del a, b

    def work(x):
        gc.collect()  # what a worker's allocations would do in time
        return x

    fork_map(work, list(range(4)), 2, lambda i, r: None)
    gc.enable()
    gc.collect()
    with open(log) as f:
        pids = f.read().split()
    assert pids == [str(os.getpid())] * 2, pids


def check_no_garbage_of_the_parent_is_finalized_in_a_build_worker(folder):
    """The same for the worker processes of a build (index/pool.py, forked when the process
    has one thread): the parent's uncollected cycle is finalized in the parent only."""
    import gc

    from nfdmatch import write_curves
    from nfdmatch.index import build_index, pool

    log = os.path.join(folder, "finalized")
    os.mkdir(os.path.join(folder, "c"))
    for i in range(6):
        write_curves(os.path.join(folder, "c", f"c{i}.csv"), np.random.default_rng(i).normal(size=(20, 3)))

    class Held:
        def __del__(self):
            with open(log, "a") as f:
                f.write(f"{os.getpid()}\n")

    compute = pool._compute_batch

    def collecting(batch, slot=None):  # the test hook: what a worker's allocations do in time
        gc.collect()
        return compute(batch, slot)

    pool._compute_batch = collecting
    pool._batches = lambda tasks: [[i] for i in range(len(tasks))]  # one file a batch: both workers busy
    gc.disable()
    a, b = Held(), Held()
    a.other, b.other = b, a
    del a, b
    build_index([os.path.join(folder, "c")], os.path.join(folder, "i.h5"), jobs=2)
    gc.enable()
    gc.collect()
    with open(log) as f:
        pids = f.read().split()
    assert pids == [str(os.getpid())] * 2, pids


def check_no_fork_while_another_thread_runs(folder):
    assert can_fork()
    stop = threading.Event()
    t = threading.Thread(target=stop.wait)
    t.start()
    try:
        assert not can_fork()
    finally:
        stop.set()
        t.join()
    assert can_fork()


def check_the_graph_searched_by_worker_processes_is_the_graph_of_one_process(folder):
    """A build with jobs=2 searches the graph's rows in two forked processes (blocks of 16
    rows here, so that there are many) and stores the same bytes as a build searching them
    in its own process; the worker count is in the report."""
    import h5py

    from nfdmatch import write_curves
    from nfdmatch.index import build_index
    from nfdmatch.search import graph
    from test_join import family_curves

    graph._BLOCK_ROWS = 16
    curves = family_curves(np.random.default_rng(5), 20, 6, 0.02)
    os.mkdir(os.path.join(folder, "c"))
    write_curves(os.path.join(folder, "c", "all.obj"), curves)
    stored = []
    for jobs in (1, 2):
        index = os.path.join(folder, f"i{jobs}.h5")
        report = build_index([os.path.join(folder, "c")], index, jobs=jobs, graph=8)
        assert report.graph.searched == len(curves)
        assert report.graph.processes == (0 if jobs == 1 else 2), report.graph
        with h5py.File(index, "r") as f:
            stored.append((f["graph/neighbour"][...], f["graph/distance"][...]))
    np.testing.assert_array_equal(stored[0][0], stored[1][0])
    np.testing.assert_array_equal(stored[0][1], stored[1][1])


def check_the_matrix_of_worker_processes_is_the_matrix_of_one_process(folder):
    """distance_matrix over two forked workers: the same entries, bit for bit, as in one
    process (each entry is computed by itself), progress counting every pair once."""
    from nfdmatch import Curve
    from nfdmatch.search import distance_matrix, workers

    forked = []
    real = workers.fork_map
    workers.fork_map = lambda *a, **kw: forked.append(a[2]) or real(*a, **kw)

    rng = np.random.default_rng(3)
    t = np.linspace(0, 2 * np.pi, 40, endpoint=False)
    curves = []
    for i in range(240):
        r = 1 + 0.2 * rng.standard_normal(3) @ np.array([np.cos(2 * t), np.sin(3 * t), np.cos(5 * t)])
        curves.append(Curve(np.c_[r * np.cos(t), r * np.sin(t), 0.1 * rng.standard_normal() * np.sin(t)], id=f"c{i}"))
    seen = []
    one = distance_matrix(curves, processes=1, harmonics=8)
    two = distance_matrix(curves, processes=2, harmonics=8, progress=lambda done, total: seen.append((done, total)))
    np.testing.assert_array_equal(one, two)
    assert forked == [2]
    assert seen[-1] == (240 * 239 // 2, 240 * 239 // 2)
    assert [d for d, _ in seen] == sorted(d for d, _ in seen)


CHECKS = sorted(name for name in dir() if name.startswith("check_"))

if __name__ == "__main__":
    globals()[sys.argv[1]](sys.argv[2])
