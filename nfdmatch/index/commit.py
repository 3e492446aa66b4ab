"""The write step of a build: the new index file written beside the old one (rows copied
and computed, ``/files``, ``/search``, ``/graph``), synced, then moved into place under the
build's lock. The old file stays what queries read until the move. A graph whose rows are
searched elsewhere (a Dask cluster's workers, which open the new file by its path) is
searched while the new file is closed, complete but for ``/graph``; the file is then
reopened to write it."""

from __future__ import annotations

from typing import Any, TYPE_CHECKING

import os
import secrets
import time
from contextlib import contextmanager

import h5py
import numpy as np

from .._version import __version__
from ..errors import InputError, NfdError, WriteError, escape_name
from ..names import decode_name
from .changes import write_changes
from .graph import GraphStats
from ..mesh.objects import ObjectRule
from .objects_group import ObjectEntry, write_objects
from .graph_build import blocks_to_search, plan_graph, store_graph, write_graph
from .paths import curve_ids, id_collision
from .plan import Action, Plan
from .pool import run_tasks
from .schema import FORMAT_VERSION, INDEX_FORMAT, FileRecord, _short, set_text
from .search_group import write_search_group
from .writer import CopyRun, CurveWriter, Space, fsync_path, write_files_table, write_sources

if TYPE_CHECKING:
    from collections.abc import Callable, Sequence
    from .build import BuildReport
    from .lock import Lock
    from .reader import Index

__all__ = ["write_new_index"]


def _utcnow() -> str:
    return time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())


def write_new_index(
    report: BuildReport,
    index_path: str,
    plan: Plan,
    old: Index | None,
    jobs: int,
    lock: Lock | None,
    progress: Callable[[int, int], None] | None,
    file_timeout: float | None = None,
    *,
    sources: tuple[Sequence[str], str | None, Sequence[str]] = ((), None, ()),
    name: str | None = None,
    graph: Any = None,
    runner: Callable[..., Any] | None = None,
    graph_runner: Callable[..., Any] | None = None,
    strict: bool = False,
    graph_progress: Callable[[int, int], None] | None = None,
) -> None:
    """Write the new index beside ``index_path`` (the real file) and move it into place;
    ``sources`` ``(stored paths, glob, excluded paths)`` go to /sources; ``name``: the index as
    the user named it (messages); ``graph``, ``runner``, ``graph_runner``, ``graph_progress``:
    as :func:`nfdmatch.index.build_index` takes them (``graph_runner`` searches the graph's rows
    elsewhere, in the temporary file closed meanwhile). ``strict``: when a file failed, the
    temporary file is removed instead (``report.written`` False)."""
    shown = index_path if name is None else name
    folder = os.path.dirname(index_path) or "."
    name = os.path.basename(index_path)
    tmp = os.path.join(folder, f".{name}.tmp-{os.getpid()}-{secrets.token_hex(4)}.h5")
    stream, result_of = _start_tasks(plan.tasks, jobs, lock, progress, file_timeout, runner)
    actions: dict[str, str] = {p: "removed" for p in plan.removed}
    now = _utcnow()
    try:
        graph_job = (graph, jobs, None if lock is None else lock.fd, graph_runner, graph_progress)
        pending = _write_file(
            tmp, shown, plan, old, stream, result_of, report, actions, sources, graph_job, now, strict
        )
        if pending is not None:
            report.graph = _graph_elsewhere(tmp, shown, *pending, graph_runner, graph_progress)  # type: ignore[call-arg]
        Space.release(tmp)
        fsync_path(tmp, strict=True)  # a full disk may show only here: never replace then
        os.replace(tmp, index_path)
        fsync_path(folder, directory=True)
    except BaseException as exc:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        if isinstance(exc, _FailedStrictly):
            _count(report, actions)
            report.curves = 0 if old is None else old.n_curves  # the index as it was
            return
        # h5py reports a failed write (disk full, quota, file-size limit) as OSError, or as
        # RuntimeError when it surfaces while closing the file
        if isinstance(exc, (OSError, RuntimeError)) and not isinstance(exc, NfdError):
            raise WriteError(f"cannot write the index: {_write_cause(exc)}", path=shown) from None
        raise
    report.written = True
    _count(report, actions)


class _FailedStrictly(Exception):
    """A strict build's file failed: the new index is not written (never leaves this module)."""


def _count(report, actions: dict[str, str]) -> None:
    for path in sorted(actions):
        action = actions[path]
        report.changes.append((action, path))
        setattr(report, action, getattr(report, action) + 1)


def _start_tasks(tasks, jobs, lock, progress, file_timeout, runner):
    """Start the workers on the plan's tasks. Returns the stream of ``(task, result)`` (to be
    closed: that shuts the pool down) and ``result_of(task)``, which reads the stream until
    that task's result has come (they come in any order); progress counts each arrival."""
    results: dict[int, dict] = {}
    total = len(tasks)
    if progress is not None:
        progress(0, total)
    lock_fd = None if lock is None else lock.fd
    stream = run_tasks(tasks, jobs, lock_fd, file_timeout or None) if runner is None else runner(tasks, jobs, lock_fd)
    done = 0

    def result_of(task: int) -> dict:
        nonlocal done
        while task not in results:
            i, res = next(stream)
            results[i] = res
            done += 1
            if progress is not None:
                progress(done, total)
        return results.pop(task)

    return stream, result_of


def _write_file(tmp, shown, plan, old, stream, result_of, report, actions, sources, graph_job, now, strict=False):
    """Write the whole new index to ``tmp``: attributes, curve rows, /files, /sources,
    /changes, /search and /graph (``graph_job``: ``(K, processes, lock descriptor,
    graph_runner)``, see :func:`write_graph`). Closes the task stream and the file, also on
    failure. Returns None, or with a ``graph_runner`` and rows to search ``(plan, blocks)``:
    the graph still to search and write (:func:`_graph_elsewhere`)."""
    K = plan.params["harmonics"]
    pending = None
    try:
        with _new_file(tmp, shown, "w") as (h5, space):
            space.reserve(0)  # the superblock, attributes, small tables
            _write_attributes(h5.attrs, plan.params, old, now)
            writer = CurveWriter(h5, K, space)
            run = CopyRun(old, writer)
            objects = _OldObjects(old)
            records, fresh = _write_rows(plan.items, result_of, writer, run, report, actions, objects)
            if strict and report.failures:
                raise _FailedStrictly()
            _check_ids(records)
            run.flush()
            writer.flush()
            write_files_table(h5, records, space)
            write_objects(h5, ObjectRule.from_tuple(plan.params["objects"]), objects.entries, writer.rows)
            write_sources(h5, *sources)
            write_changes(h5, fresh)
            # the cells: features, squared norms, row numbers and first harmonics of every row
            space.reserve(writer.rows * (8 * (2 * K + 3) + 24 * K + 160))
            report.cells = write_search_group(h5, K, id_crcs=writer.id_crcs())
            graph, processes, lock_fd, graph_runner, graph_progress = graph_job
            reuse = not plan.recompute_all
            if graph_runner is None:
                report.graph = write_graph(
                    h5, old, graph, reuse=reuse, processes=processes, close_fds=(lock_fd,), progress=graph_progress
                )
            else:
                pending = _graph_here(h5, old, graph, reuse, space, report)
            report.curves = writer.rows
    finally:
        stream.close()  # shuts the worker pool down
    return pending


def _check_ids(records) -> None:
    """An InputError naming both files when two curves would share an id (the index keeps
    one row per id: one of them would be lost without a word)."""
    counts = {r.path: r.curve_count for r in records if r.status == "ok" and ("#" in r.path or r.curve_count > 1)}
    both = id_collision(counts)
    if both is not None:
        multi, single = (escape_name(decode_name(p)) for p in both)
        raise InputError(
            f"curve {single[len(multi) + 1 :]} of this file and the file {single} would share the id "
            f"{single}; rename one of them (ids are FILE and FILE#I)",
            path=decode_name(both[0]),
        )


def _graph_here(h5, old, graph, reuse: bool, space: Space, report):
    """The part of a graph searched elsewhere that is computed in the open file (see
    :func:`blocks_to_search`); the graph written now when no row is left to search.
    Returns None or ``(plan, blocks)``."""
    graph_plan = plan_graph(h5, old, graph, reuse=reuse)
    blocks = [] if graph_plan is None else blocks_to_search(graph_plan)
    if graph_plan is None:
        report.graph = GraphStats()
    elif not blocks:
        space.reserve(graph_plan.lists.neighbour.nbytes * 2)
        report.graph = store_graph(h5, graph_plan)
    else:
        return graph_plan, blocks
    return None


def _graph_elsewhere(tmp: str, shown: str, graph_plan, blocks: list, graph_runner, progress=None) -> GraphStats:
    """The graph's rows searched by ``graph_runner`` in ``tmp`` (closed: complete but for
    /graph, so that other processes and machines can open it by its path), then written
    into it (reopened for writing); ``progress(done_rows, total_rows)``. A failure leaves
    ``tmp`` to the caller (removed)."""
    total, done = sum(len(b) for b in blocks), 0
    if progress is not None:
        progress(0, total)

    def store(number, neighbour, distance):
        nonlocal done
        graph_plan.store(blocks[number], neighbour, distance)
        done += len(blocks[number])
        if progress is not None:
            progress(done, total)

    graph_plan.stats.scheduler, graph_plan.stats.workers = graph_runner(tmp, blocks, graph_plan.k, store)
    with _new_file(tmp, shown, "r+") as (h5, space):
        space.reserve(graph_plan.lists.neighbour.nbytes * 2)  # neighbours and distances, 8 bytes each
        return store_graph(h5, graph_plan)


@contextmanager
def _new_file(tmp: str, shown: str, mode: str):
    """The new index file open for writing (``mode`` "w": created; "r+": reopened, to add
    the graph) with its :class:`Space`; closed on leaving, also after a failed write."""
    try:
        # HDF5 1.10 structures: chunk indexes by position (fixed and extensible arrays,
        # no stored chunk offsets that a flipped byte could move) with checksums
        h5 = h5py.File(tmp, mode, locking=False, libver=("v110", "v110"))
    except Exception as exc:
        raise WriteError(f"cannot write the index: {_write_cause(exc)}", path=shown) from None
    space = None
    try:
        space = Space(h5)
        yield h5, space
    except BaseException:
        if space is not None:
            space.abandon()  # HDF5 cannot close a file it failed to write
        raise
    finally:
        try:
            h5.close()
        except Exception:
            if space is None or not space.abandoned:
                raise


class _OldObjects:
    """The objects of the new file as its rows are written: each computed mesh's record, and
    the old index's record of each copied one (by its old first row)."""

    def __init__(self, old):
        self.entries: list[ObjectEntry] = []
        self.old = None if old is None else old.objects()
        self.by_start = {}
        if self.old is not None:
            starts = old._files["curve_start"]
            self.by_start = {int(starts[f]): m for m, f in enumerate(self.old.file.tolist())}

    def copied(self, file_row: int, start: int, r) -> None:
        m = self.by_start.get(int(r.curve_start)) if r.curve_count else None
        if m is not None:
            record = self.old.record(m, int(r.curve_start), int(r.curve_count))
            self.entries.append(ObjectEntry(file_row, start, int(r.curve_count), record))

    def computed(self, file_row: int, start: int, n: int, res: dict) -> None:
        if "object" in res:
            self.entries.append(ObjectEntry(file_row, start, n, res["object"]))


def _write_rows(items, result_of, writer: CurveWriter, run: CopyRun, report, actions: dict[str, str], objects):
    """The curve rows of every file in plan order: copied from the old index (unchanged
    files, and files whose mtime changed over the same contents) or computed by the workers.
    Returns the /files records and the ``(start, count)`` runs of rows added or recomputed
    (/changes); ``actions`` gets each file's action, ``report.failures`` each failure."""
    records: list[FileRecord] = []
    fresh: list[tuple[int, int]] = []

    def failed(item, size, mtime_ns, sha256, error, start) -> None:
        records.append(FileRecord(item.path, size, mtime_ns, sha256, "failed", error, start, 0))
        actions[item.path] = "failed"
        report.failures.append((item.file or item.path, error))

    for item in items:
        path, r = item.path, item.old
        file_row = len(records)
        start = writer.rows + writer.pending_rows + run.rows
        # a file whose stored path changed (an index upgraded to recorded sources)
        # keeps its rows under ids made from the new path
        new_ids = None if r is None or r.path == path else curve_ids(path, r.curve_count)
        if item.action is Action.COPY:
            objects.copied(file_row, start, r)
            run.add(r.curve_start, r.curve_count, file_row, new_ids)
            records.append(FileRecord(path, r.size, r.mtime_ns, r.sha256, "ok", "", start, r.curve_count))
            actions[path] = "unchanged"
            continue
        if item.action is Action.KEEP_FAILED:
            failed(item, r.size, r.mtime_ns, r.sha256, r.error, start)
            continue
        res = result_of(item.task)
        if res["status"] == "same":  # mtime changed, contents did not
            if r.status == "ok":
                objects.copied(file_row, start, r)
                run.add(r.curve_start, r.curve_count, file_row, new_ids)
                records.append(FileRecord(path, res["size"], res["mtime_ns"], r.sha256, "ok", "", start, r.curve_count))
                actions[path] = "unchanged"
            else:
                failed(item, res["size"], res["mtime_ns"], r.sha256, r.error, start)
            continue
        run.flush()
        if res["status"] == "ok":
            n = len(res["ids"])
            piece = dict(res["arrays"])
            piece["id"] = np.asarray(curve_ids(path, n), dtype=object)
            piece["file"] = np.full(n, file_row, dtype=np.int32)
            writer.append(piece)
            objects.computed(file_row, start, n, res)
            records.append(FileRecord(path, res["size"], res["mtime_ns"], res["sha256"], "ok", "", start, n))
            fresh.append((start, n))
            actions[path] = "added" if r is None else "updated"
        else:
            failed(item, res["size"], res["mtime_ns"], res["sha256"], res["error"], start)
    return records, fresh


def _write_attributes(attrs, params: dict, old, now: str) -> None:
    """The root attributes of a new index file (docs/index-format.md)."""
    set_text(attrs, "format", INDEX_FORMAT)
    attrs["format_version"] = np.int64(FORMAT_VERSION)
    set_text(attrs, "nfdmatch_version", __version__)
    attrs["samples"] = np.int64(params["samples"])
    attrs["harmonics"] = np.int64(params["harmonics"])
    set_text(attrs, "scale", params["scale"])
    set_text(attrs, "created", old.created if old is not None and old.created else now)
    set_text(attrs, "updated", now)


def _write_cause(exc: BaseException) -> str:
    """Why a write failed, in the system's words ("No space left on device"), not HDF5's
    ("Unable to synchronously create file (file write failed: time = ..., errno = 28, ...)")."""
    import re

    code = getattr(exc, "errno", None)
    if not isinstance(code, int) or code <= 0:
        found = re.search(r"errno = (\d+)", str(exc))
        code = int(found.group(1)) if found else None
    if code:
        extra = ""
        if isinstance(exc, OSError) and exc.strerror and "ulimit" in exc.strerror:
            extra = exc.strerror[len(os.strerror(code)) :] if exc.strerror.startswith(os.strerror(code)) else ""
        return os.strerror(code) + extra
    if isinstance(exc, OSError) and exc.strerror:
        return exc.strerror
    return _short(exc)
