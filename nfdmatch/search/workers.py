"""A search's tasks over forked worker processes, or here (:func:`run_tasks`): the k-NN
graph's blocks of rows, the distance matrix's runs of rows."""

from __future__ import annotations

from collections.abc import Callable, Sequence

from .._fork import can_fork, fork_map
from ..matching.kernels import before_fork, set_call_threads

__all__ = ["run_tasks"]


def run_tasks(
    tasks: Sequence,
    compute: Callable,
    collect: Callable,
    processes: int,
    *,
    prepare: Callable[[], None] | None = None,
    close_fds: Sequence[int] = (),
) -> int:
    """``collect(number, compute(task, threads))`` for every task, in any order.

    With ``processes`` > 1 and more than one task, the tasks go to that many forked
    workers (:func:`nfdmatch._fork.fork_map`) when this process may fork once the kernels'
    idle thread pool is stopped: ``prepare()`` runs first (read what the workers will need:
    they never read a file), each worker computes with ``threads`` = 1 and its calls on one
    thread (:func:`~nfdmatch.matching.kernels.set_call_threads`). The tasks no worker
    finished (workers died) and, without workers, all of them, are computed here with
    ``threads`` = None. Returns the workers used (0: none). ``close_fds``: descriptors a
    worker must not keep (the index lock).
    """
    left, used = range(len(tasks)), 0
    if processes > 1 and len(tasks) > 1:
        before_fork()
        if can_fork():
            if prepare is not None:
                prepare()
            used = min(processes, len(tasks))

            def work(task):
                set_call_threads(1)  # one thread per worker: its siblings have the other cores
                return compute(task, 1)

            left = fork_map(work, tasks, used, collect, close_fds=close_fds)
    for number in left:
        collect(number, compute(tasks[number], None))
    return used
