"""Build tasks on the workers: files grouped into tasks, each task's files read and described."""

from __future__ import annotations

from typing import TYPE_CHECKING

import os

from .settings import TASK_BYTES, TASK_FILES, TASKS_PER_THREAD

if TYPE_CHECKING:
    from collections.abc import Sequence


def file_size(path: str) -> int:
    try:
        return os.stat(path).st_size
    except OSError:
        return 0


def batches(
    tasks: list[tuple], threads: int, *, sizes: Sequence[int] | None = None, counts: Sequence[int] | None = None
) -> list[list[int]]:
    """Items grouped in order into Dask tasks of at most TASK_BYTES (a bigger item is a task
    alone) and TASK_FILES files. An item is a task (one file: its size on disk), or, with
    ``sizes`` and ``counts``, a local batch of ``counts[i]`` files and ``sizes[i]`` bytes."""
    sizes = [file_size(t[0]) for t in tasks] if sizes is None else list(sizes)
    counts = [1] * len(sizes) if counts is None else list(counts)
    files = sum(counts)
    # small builds still give every worker thread a few tasks
    limit = max(1, min(TASK_BYTES, sum(sizes) // max(1, threads * TASKS_PER_THREAD)))
    per_files = max(1, min(TASK_FILES, -(-files // max(1, threads * TASKS_PER_THREAD))))
    batches, current, nbytes, nfiles = [], [], 0, 0
    for i, (size, count) in enumerate(zip(sizes, counts)):
        if current and (nbytes + size > limit or nfiles + count > per_files):
            batches.append(current)
            current, nbytes, nfiles = [], 0, 0
        current.append(i)
        nbytes += size
        nfiles += count
    if current:
        batches.append(current)
    return batches


def failed_answer(path: str, message: str) -> dict:
    return {"path": path, "size": 0, "mtime_ns": 0, "sha256": "", "status": "failed", "error": f"{path}: {message}"}


def compute_batches(batches: list[list[tuple[int, tuple]]], cwd: str) -> list[dict]:
    """On a worker: each local batch (``(task_number, task)`` pairs) read and described by
    :func:`nfdmatch.index.pool._compute_batch`, as the local pool does (it never raises for
    a bad file); one result per task, in order. Returns dicts of builtins and numpy arrays.

    A relative path is the client's (its working folder ``cwd``, which the worker need not
    share): the file is read by its absolute name and the result speaks of the path as
    given, so ids and messages are those of a local build."""
    from ..errors import escape_name
    from ..index import pool
    from ..names import encode_name

    out = []
    for batch in batches:
        given = [task[0] for _, task in batch]
        full = [p if os.path.isabs(p) else os.path.join(cwd, p) for p in given]
        # looked up on the module at each call, not bound at import
        results, arrays = pool._compute_batch([(n, (f, *task[1:])) for (n, task), f in zip(batch, full)])
        for res, path, fpath in zip(pool._split(results, arrays), given, full):
            if fpath != path:
                res["path"] = path
                # ids encode a name (nfdmatch.names), messages escape it (errors.escape_name)
                names = [(escape_name(fpath), escape_name(path)), (fpath, path)]
                if "ids" in res:
                    old, new = encode_name(fpath), encode_name(path)
                    res["ids"] = [new + i[len(old) :] if i.startswith(old) else i for i in res["ids"]]
                for old, new in names:
                    if old in res["error"]:
                        res["error"] = res["error"].replace(old, new, 1)
                        break
            out.append(res)
    return out
