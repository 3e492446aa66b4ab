"""Rows of one kernel call shared over threads (the compiled kernels release the GIL; the
just-in-time ones always, the ahead-of-time ones when built so): plain Python, no numba, so
that both kernel modules use it."""

from __future__ import annotations

import atexit
import threading

__all__ = ["split_rows", "shutdown"]

_executor = None
_executor_workers = 0
_executor_lock = threading.Lock()


def split_rows(run, N: int, workers: int) -> None:
    """run(lo, hi) over rows 0..N: at once, or in ``workers`` blocks on a thread pool (the
    kernels release the GIL; the blocks write disjoint rows of the outputs)."""
    global _executor, _executor_workers
    if N == 0:
        return
    if workers <= 1 or N < 2 * workers:
        run(0, N)
        return
    with _executor_lock:
        if _executor_workers < workers - 1:
            from concurrent.futures import ThreadPoolExecutor  # (2-3 ms of a start-up otherwise)

            if _executor is not None:
                _executor.shutdown(wait=True)
            else:
                atexit.register(shutdown)
            _executor = ThreadPoolExecutor(workers - 1, thread_name_prefix="nfdmatch-kernels")
            _executor_workers = workers - 1
        pool = _executor
    bounds = [N * t // workers for t in range(workers + 1)]
    futures = [pool.submit(run, lo, hi) for lo, hi in zip(bounds[1:-1], bounds[2:])]
    run(bounds[0], bounds[1])  # the first block on the calling thread
    for future in futures:
        future.result()


def shutdown() -> None:
    """Stop the pool's threads (at exit, or by a program that is done with the kernels; a
    later call to :func:`split_rows` starts a new pool)."""
    global _executor, _executor_workers
    with _executor_lock:
        if _executor is not None:
            _executor.shutdown(wait=True)
        _executor, _executor_workers = None, 0
