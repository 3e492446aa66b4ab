"""Rows of one kernel call shared over threads (the compiled kernels release the GIL; the
just-in-time ones always, the ahead-of-time ones when built so): plain Python, no numba, so
that both kernel modules use it, down to the calls themselves (:func:`exact_rows`,
:func:`grid_bound_rows`: the compiled functions of both take the same arguments)."""

from __future__ import annotations

import atexit
import threading

import numpy as np

__all__ = ["exact_rows", "grid_bound_rows", "run_all", "run_spread", "split_rows", "shutdown"]


def exact_rows(kernel, A, Aw, w, B, D, basis, quarter, n, mirror, C, refine, refine_limit, workers, prune=True):
    """matching.exact_search's compiled path for all rows of B through ``kernel`` (the
    compiled ``_exact_rows`` of either kernel module, called per block of rows lo..hi).

    A, Aw = conj(A) w (K, 3) complex128; w (K,) float64; B (N, K, 3) complex128 (direction 1
    is conj(B)); basis, quarter from matching.folded_basis; C candidates per row;
    refine_limit: refine the rows whose refined distance^2 could be at most this (inf: all);
    ``workers``: threads sharing the rows (see :func:`split_rows`); ``prune``: refine only the
    candidates that can still win (the same result; False for the tests that show it).
    Returns (distance, shift, rotation, reversed, mirrored) over the rows.
    """
    N = B.shape[0]
    out = (np.empty(N), np.empty(N), np.empty((N, 3, 3)), np.zeros(N, dtype=np.bool_), np.zeros(N, dtype=np.bool_))
    # the scalars as the ahead-of-time signature takes them (the just-in-time kernel gets the
    # types it was always called with)
    scalars = (int(D), basis, bool(quarter), int(n), bool(mirror), int(C), bool(refine), float(refine_limit))
    args = (A, Aw, w, B, *scalars, bool(prune))
    split_rows(lambda lo, hi: kernel(*args, *out, lo, hi), N, workers)
    return out


def grid_bound_rows(kernel, Aw, B, D, basis, ratio, mirror, slack_coarse, slack_fine, need, workers):
    """matching.grid_bound's compiled path through ``kernel`` (a compiled grid bound of either
    kernel module, called per block of rows lo..hi): (N,) bound per row of B.

    Aw = conj(A[:K']) (K', 3) complex128; B (N, K', 3) complex128; basis (2K', n) float64
    from matching.integer_shift_basis; ratio divides n; slack_coarse, slack_fine, need
    (N,) float64; ``workers``: threads sharing the rows (see :func:`split_rows`)."""
    N = B.shape[0]
    out = np.empty(N)
    args = (Aw, B, int(D), basis, int(ratio), bool(mirror), slack_coarse, slack_fine, need, out)
    split_rows(lambda lo, hi: kernel(*args, lo, hi), N, workers)
    return out


_executor = None
_executor_workers = 0
_executor_lock = threading.Lock()


def split_rows(run, N: int, workers: int) -> None:
    """run(lo, hi) over rows 0..N: at once, or in ``workers`` blocks on a thread pool (the
    kernels release the GIL; the blocks write disjoint rows of the outputs)."""
    if N == 0:
        return
    if workers <= 1 or N < 2 * workers:
        run(0, N)
        return
    pool = _pool(workers - 1)
    bounds = [N * t // workers for t in range(workers + 1)]
    futures = [pool.submit(run, lo, hi) for lo, hi in zip(bounds[1:-1], bounds[2:])]
    run(bounds[0], bounds[1])  # the first block on the calling thread
    for future in futures:
        future.result()


def run_all(calls) -> list:
    """Every one of ``calls`` (callables of no argument) at once: the first on the calling
    thread, the others on the pool's threads (the compiled kernels release the GIL). Returns
    their results, in order, once all have returned. None of them runs on after this returns
    or raises: a call's exception is raised once every call is done (the callers write what
    the kernels read, after)."""
    if len(calls) <= 1:
        return [call() for call in calls]
    from concurrent.futures import wait

    futures = [_pool(len(calls) - 1).submit(call) for call in calls[1:]]
    try:
        first = calls[0]()
    finally:
        wait(futures)
    return [first] + [future.result() for future in futures]


def run_spread(calls, threads: int) -> list:
    """Every one of ``calls`` (callables of no argument) on ``threads`` of the pool's threads,
    each thread taking the next call, in order, once done with its last: calls of unequal
    lengths share the threads. Returns their results, in order, once all are done (a call's
    exception is raised then). ``threads`` <= 1: one after the other on the calling thread.

    None runs on the calling thread: off the main thread a kernel call does not split its
    own rows (:meth:`~.kernels.Kernels.workers`), so no call waits for a pool busy with the
    others, and each thread computes one call at a time."""
    if threads <= 1 or len(calls) <= 1:
        return [call() for call in calls]
    from concurrent.futures import wait

    results: list = [None] * len(calls)
    pending = iter(range(len(calls)))
    taking = threading.Lock()

    def work() -> None:
        while True:
            with taking:
                at = next(pending, None)
            if at is None:
                return
            results[at] = calls[at]()

    futures = [_pool(threads).submit(work) for _ in range(min(threads, len(calls)))]
    wait(futures)
    for future in futures:
        future.result()  # raises a call's exception
    return results


def _pool(threads: int):
    """The process's thread pool, with at least ``threads`` threads (started, or started
    again larger, on demand)."""
    global _executor, _executor_workers
    with _executor_lock:
        if _executor_workers < threads:
            from concurrent.futures import ThreadPoolExecutor  # (2-3 ms of a start-up otherwise)

            if _executor is not None:
                _executor.shutdown(wait=True)
            else:
                atexit.register(shutdown)
            _executor = ThreadPoolExecutor(threads, thread_name_prefix="nfdmatch-kernels")
            _executor_workers = threads
        return _executor


def shutdown() -> None:
    """Stop the pool's threads (at exit, or by a program that is done with the kernels; a
    later call to :func:`split_rows` starts a new pool)."""
    global _executor, _executor_workers
    with _executor_lock:
        if _executor is not None:
            _executor.shutdown(wait=True)
        _executor, _executor_workers = None, 0
