"""Building and updating an index: the plan (what each file needs) and the build itself.

:func:`build_index` in full
---------------------------

Parameters
----------
sources : path or list of paths: files (taken whatever their extension) or folders
    (recursive; known extensions; hidden files and folders skipped). None or empty:
    the sources the index records (its last build's), re-scanned. Or curves in memory
    (:class:`~nfdmatch.Curve` s or (n, 3) arrays): written first, in order, into one OBJ
    file, ``curves_file`` (default: the index's path with ``.curves.obj`` for its
    extension), which the index then records as its source: row i is curve i, and the
    file is there for ``show`` and later builds.
index_path : the index file (None: :func:`default_index_path`). Its folder must exist. A
    symbolic link is followed: its target is replaced (the link stays) and locked.
samples, harmonics, scale : descriptor parameters; None keeps the existing index's value
    (defaults 128, 16, "rms" for a new index). An explicit value that differs from the
    index's recomputes every curve (with a notice).
glob : fnmatch pattern on file names found in folders (None with no ``sources``: the
    recorded one).
input_format : force this reader for every file (not recorded in the index).
rebuild : recompute every file, even unchanged ones.
dry_run : report what the build would do and write nothing: files are read and
    described as the build would (a broken file is ``failed``, ``curves`` is the
    result's count), no lock is taken, a shrink is a notice instead of an error.
jobs : worker processes (None: ``os.cpu_count()``; 1: in this process, unless
    ``file_timeout`` is given).
wait : seconds to wait for another build's lock (0: fail at once).
exclude : stored paths (docs/index-format.md "Paths and ids"; a folder: everything below
    it) the walk leaves out, recorded with the sources (None: the recorded ones when no
    ``sources`` are given, else none). :func:`add_files` and :func:`remove_files` set it.
strict : when any file fails (newly or still), write nothing: the index stays as it was
    (``written`` False, ``failures`` and ``changes`` as the build would have had them), so
    that Make runs the build again until every file reads.
graph : store each row's ``graph`` nearest rows (``/graph``, for ``query --rerank``);
    None keeps an existing graph's K and distance (no graph for an index without one), 0
    drops it; a :class:`~nfdmatch.index.graph.GraphSpec` ``(k, "fused")`` stores each row's
    k of least fused distance (the elastic stage's) among its exact nearest.
progress : optional ``progress(done_files, total_files)``, called with (0, total) first and
    then as files finish; total counts the files that must be read or hashed (unchanged
    files are not counted).
graph_progress : optional ``graph_progress(done_rows, total_rows)`` for the graph's search
    (``graph``), here or by ``graph_runner``: (0, total) first, then as blocks of rows finish.
allow_shrink : allow a build that removes more than half of the index's files, or all.
file_timeout : seconds one file may take to be read and hashed (None or 0: no limit);
    a file over it fails alone (its worker is killed), the build goes on. With a limit,
    files are always read in worker processes, even at ``jobs`` 1: a reader stuck in C
    code cannot be interrupted in this process (the CLI's default is 600 s).
    Independently of it, a worker process that dies (a reader's crash, the OOM killer)
    is replaced and its files read again; a file that kills a worker twice fails alone,
    and deaths that no file explains stop the build (``WorkerError``, nothing written).
runner : what computes the files to read (None: the local pool); called as
    ``runner(tasks, jobs, lock_fd)``, it yields ``(task_number, result of
    pool._compute_file(*task))`` in any order (``nfdmatch.distributed`` plugs Dask in).
graph_runner : what searches the rows of the graph (None: this process and ``jobs``
    forked workers); called as ``graph_runner(path, blocks, k, store)`` once the new
    index file at ``path`` (its temporary name beside the index) is complete but for
    ``/graph`` and closed, so that other processes can open it read-only by that path:
    for each block (an int64 array of rows) it searches each row's ``k`` nearest others
    as :func:`nfdmatch.search.graph.nearest_others` does and calls ``store(block_number,
    neighbour (m, k) int64, distance (m, k) float64)``, in any order; it returns ``(where,
    workers)``, what searched (reported in ``BuildReport.graph``). The file is then
    reopened to write the graph, and moved into place as always.
sections : planes per principal axis of the rule meshes are cut by (docs/objects.md;
    None keeps the index's recorded rule, 7 for a new one). A mesh file (STL, PLY, OFF,
    GLB/GLTF, an OBJ with faces; not with ``input_format``) is indexed as an object: its
    contours are its rows (``path#i``), tied to it in ``/objects``. A value that differs
    from the index's recorded one recomputes every file (with a notice).

Files are stored, and compared with the index's, by the rule of docs/index-format.md
("Paths and ids"): relative to the index's folder, whatever the working directory and
the spelling of the sources.

Returns
-------
:class:`BuildReport`.

Raises
------
ReadError : a source that does not exist; the index path is a directory.
InputError : no curve files under the sources and no existing index; no sources given
    and none recorded.
ShrinkRefusedError : the build would remove more than half of the index's files (or
    all) and ``allow_shrink`` is False; nothing is written.
ParameterError : invalid parameters or jobs.
IndexLockedError : another build holds the lock (after ``wait`` seconds).
IndexFormatError : the existing file is not a readable index (see docs/index-format.md for
    which files ``rebuild`` may replace; an HDF5 file of another kind never is).
WriteError : the index cannot be written (missing folder, no permission, disk full).
WorkerError : worker processes kept dying for no file's fault (nothing written).
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, TYPE_CHECKING

from ..errors import IndexFormatError, InputError, ReadError, WriteError
from .commit import write_new_index
from .curves_in_memory import memory_sources
from .lock import Lock
from ..formats import split_selector
from .paths import index_file, openable, source_location, stored
from .plan import (
    Action,
    Plan,
    check_arguments,
    check_shrink,
    find_files,
    parameters,
    plan_files,
    recorded_sources,
)
from .pool import run_tasks
from .reader import Index
from .graph import GraphStats, asked_graph, graph_changes, graph_distance, old_graph_k, stale_fused_graph
from .schema import FORMAT_VERSION, open_checked, Problem, default_index_path
from .writer import remove_stale_temps

if TYPE_CHECKING:
    from collections.abc import Sequence


@dataclass
class BuildReport:
    """What :func:`build_index` did (or, for a dry run, would do).

    ``added, updated, removed, unchanged, failed`` count FILES; ``curves`` is the number of
    rows in the index after the build (dry run: in the index the build would write); ``failures`` lists
    ``(file, message)`` of every failed file (new failures and files that stay failed), the
    file as it was opened from the working directory, as its message names it;
    ``changes`` lists ``(action, path)`` for every file, in stored-path order (the path as
    stored, docs/index-format.md "Paths and ids"), with action one of
    ``added, updated, removed, unchanged, failed``; ``notices`` are messages for the user;
    ``written`` is True when a new index file was moved into place (False for a dry run and
    for a build that found nothing to change); ``cells`` is the number of search cells the
    written index holds (0 when nothing was written).
    """

    added: int = 0
    updated: int = 0
    removed: int = 0
    unchanged: int = 0
    failed: int = 0
    curves: int = 0
    seconds: float = 0.0
    failures: list = field(default_factory=list)
    changes: list = field(default_factory=list)
    notices: list = field(default_factory=list)
    written: bool = False
    dry_run: bool = False
    cells: int = 0
    #: the stored sources of this build (those given, or the recorded ones re-scanned)
    sources: list = field(default_factory=list)
    #: ``(path, message)`` of what the walk of the sources skipped: folders that could not be
    #: listed (their files already in the index keep their rows) and non-regular files
    skipped: list = field(default_factory=list)
    #: ``(removed, of)`` files when the build removes more than half of the index's files
    #: (or all): refused unless ``allow_shrink``; None otherwise
    shrink: tuple | None = None
    graph: GraphStats = field(default_factory=GraphStats)


def _load_old(index_path: str, rebuild: bool, notices: list):
    """The existing index (an :class:`Index`), or None when there is none or it may be replaced."""
    try:
        h5, meta, files = open_checked(index_path)
    except ReadError:
        if not os.path.exists(index_path):  # nothing there (or a link to a file to be made)
            return None
        raise
    except Problem as exc:
        if exc.kind == "empty":
            notices.append(f"replacing the empty file at {index_path}")
            return None
        # a file that does not open as HDF5 cannot be shown to be an index: never replaced
        if exc.kind in ("foreign", "not_hdf5", "unopenable"):
            raise IndexFormatError(
                f"{exc.message}; refusing to overwrite it: move it away or choose another --index", path=index_path
            ) from None
        if rebuild:
            notices.append(f"replacing {index_path}: {exc.message}")
            return None
        raise IndexFormatError(
            f"{exc.message}; move it away or pass --rebuild to replace it", path=index_path
        ) from None
    return Index(index_path, h5, meta, files)


def build_index(
    sources: Any = None,
    index_path: str | os.PathLike[str] | None = None,
    *,
    samples: int | None = None,
    harmonics: int | None = None,
    scale: str | None = None,
    glob: str | None = None,
    input_format: str | None = None,
    rebuild: bool = False,
    dry_run: bool = False,
    jobs: int | None = None,
    wait: float = 0.0,
    progress: Callable[[int, int], None] | None = None,
    allow_shrink: bool = False,
    file_timeout: float | None = None,
    graph: Any = None,
    runner: Callable[..., Any] | None = None,
    graph_runner: Callable[..., Any] | None = None,
    strict: bool = False,
    exclude: Any = None,
    graph_progress: Callable[[int, int], None] | None = None,
    sections: Any = None,
    curves_file: str | os.PathLike[str] | None = None,
) -> BuildReport:
    """Build or update the index of every curve under ``sources`` (files, and folders
    walked; None or empty: the sources the index records) in ``index_path`` (None:
    :func:`default_index_path`); returns a :class:`BuildReport`.

    ``samples, harmonics, scale``: None keeps the index's values; ``dry_run``: read and describe, write nothing;
    ``jobs``: worker processes; ``wait``: seconds for another build's lock; ``graph``: /graph's K (None keeps
    it, 0 drops it); ``progress(done, total)``; ``file_timeout``: seconds one file may take; ``runner``,
    ``graph_runner``: compute the tasks, search the graph's rows; ``graph_progress(done, total)``: its rows;
    ``sections``: the meshes' planes per axis; ``curves_file``: see ``sources`` (all in full, with the paths and
    the errors, in this module's docstring).
    """
    t0 = time.perf_counter()
    index_path = default_index_path() if index_path is None else str(os.fspath(index_path))
    sources = _as_paths(memory_sources(sources, index_path, curves_file))
    jobs = check_arguments(jobs, file_timeout, input_format, samples, harmonics)
    real_index, base = _index_location(index_path)
    report = BuildReport(dry_run=bool(dry_run))
    lock = None if dry_run else Lock(real_index, wait, name=index_path)
    old = None
    try:
        old = _load_old(index_path, rebuild, report.notices)
        recorded = None if old is None else old.sources()
        sources, glob, exclude, (found, opens, stored_sources, unseen) = _walk(
            sources, glob, exclude, old, recorded, (index_path, real_index, base), report
        )
        if not found and old is None:
            raise InputError(f"no curve files found under {', '.join(sources) or '(no sources)'}")
        params, changed = parameters(old, samples, harmonics, scale, report.notices, sections)
        if not found and old is not None and not unseen:
            report.notices.append(
                f"no curve files found under {', '.join(sources)}: every file would be removed from the index"
            )
        old_files = [] if old is None else old.files()
        plan = plan_files(
            old, old_files, recorded, found, opens, unseen, base, params, bool(rebuild) or changed or old is None,
            input_format,
        )  # fmt: skip
        check_shrink(report, old_files, plan, found, sources, index_path, real_index, dry_run, allow_shrink)
        if dry_run:
            _dry_run_report(report, plan, old, progress, jobs, file_timeout, runner)
        elif _needs_write(old, plan, recorded, (stored_sources, glob or None, exclude), graph, real_index, report):
            write_new_index(
                report, real_index, plan, old, jobs, lock, progress, file_timeout,
                sources=(stored_sources, glob or None, exclude), name=index_path, graph=graph, runner=runner,
                graph_runner=graph_runner, strict=strict, graph_progress=graph_progress,
            )  # fmt: skip
        else:
            _unchanged(report, plan, old, real_index, progress, strict)
    finally:
        if old is not None:
            old.close()
        if lock is not None:  # a build that never wrote the index leaves no lock of its own
            lock.release(remove=lock.created and not os.path.lexists(real_index))
    report.seconds = time.perf_counter() - t0
    return report


def _walk(sources, glob, exclude, old, recorded, where, report):
    """``(sources, glob, exclude, (found, opens, stored sources, unseen))``: the files a
    build reads, from its sources or the recorded ones (``where``: the index path as given,
    its real path and folder), the excluded paths left out."""
    index_path, real_index, base = where
    if not sources:
        sources, glob, exclude = _recorded_walk(old, recorded, glob, exclude, index_path, real_index, base)
    exclude = list(exclude or [])  # a build naming its sources drops the recorded exclusions
    found, opens, stored_sources, unseen = find_files(sources, glob, base, report.skipped)
    found, report.sources = [f for f in found if not _under(f, exclude)], stored_sources
    return sources, glob, exclude, (found, opens, stored_sources, unseen)


def _recorded_walk(old, recorded, glob, exclude, index_path: str, real_index: str, base: str):
    """``(sources, glob, exclude)`` of a build given no sources: the recorded ones (the
    glob and exclusions unless given)."""
    sources = recorded_sources(old, recorded, index_path, real_index, base)
    return sources, recorded[1] if glob is None else glob, old.excluded() if exclude is None else exclude


def _under(path: str, places) -> bool:
    """Whether the stored ``path`` is one of ``places`` or below one of them."""
    return any(path == p or path.startswith(p.rstrip("/") + "/") for p in places)


def add_files(
    files: str | os.PathLike[str] | Sequence[str | os.PathLike[str]],
    index_path: str | os.PathLike[str] | None = None,
    **options: Any,
) -> BuildReport:
    """Add ``files`` (files or folders) to the index and keep every other file: a build of
    the recorded sources plus those not under one of them, with the recorded glob, and the
    recorded exclusions less those files; so the next plain build (no sources) agrees. A
    missing index is built from ``files``. ``options``: those of :func:`build_index`."""
    index_path = default_index_path() if index_path is None else str(os.fspath(index_path))
    files = _as_paths(files)
    real_index, base = _index_location(index_path)
    old = _load_old(index_path, False, [])
    if old is None:
        return build_index(files, index_path, **options)
    with old:
        recorded, excluded = _recorded(old, index_path), old.excluded()
    sources, glob = list(recorded[0]), recorded[1]
    for file in files:
        key = stored(source_location(file), base)
        if not os.path.lexists(split_selector(file)[0]):
            raise ReadError("no such file or folder", path=file)
        excluded = [e for e in excluded if not _under(e, [key]) and not _under(key, [e])]
        if not _under(key, sources):
            sources.append(key)
    return build_index([openable(s, base) for s in sources], index_path, glob=glob, exclude=excluded, **options)


def remove_files(
    files: str | os.PathLike[str] | Sequence[str | os.PathLike[str]],
    index_path: str | os.PathLike[str] | None = None,
    **options: Any,
) -> BuildReport:
    """Remove ``files`` (files or folders: every file below) from the index and keep every
    other file: a named source is dropped from the recorded sources, a file found in a
    source folder is recorded as excluded from its walk; so the next plain build agrees.
    Each must be in the index (``InputError`` naming it otherwise). ``options``: those of
    :func:`build_index` (a removal is never refused as a shrink: it was asked for)."""
    index_path = default_index_path() if index_path is None else str(os.fspath(index_path))
    files = _as_paths(files)
    real_index, base = _index_location(index_path)
    old = _load_old(index_path, False, [])
    if old is None:
        raise InputError("no index to remove files from", path=index_path)
    with old:
        recorded, excluded = _recorded(old, index_path), old.excluded()
        held = [r.path for r in old.files()]
    sources, glob = list(recorded[0]), recorded[1]
    for file in files:
        key = stored(source_location(file), base)
        if not any(_under(h, [key]) for h in held) and key not in sources:
            raise InputError("not in the index: nothing to remove", path=file)
        if key in sources:
            sources.remove(key)
        elif not _under(key, excluded):
            excluded.append(key)
    options.setdefault("allow_shrink", True)
    if not sources:
        raise InputError("removing every source would leave the index empty; delete the file instead", path=index_path)
    return build_index([openable(s, base) for s in sources], index_path, glob=glob, exclude=excluded, **options)


def _recorded(old, index_path: str) -> tuple:
    recorded = old.sources()
    if recorded is None:
        raise InputError(
            "the index does not record its sources (it was built by an older nfdmatch); rebuild it once "
            "with its sources named",
            path=index_path,
        )
    return recorded


def _as_paths(sources) -> list[str]:
    """``sources`` (None, one path, or several; str, bytes or path-like) as a list of str."""
    if sources is None:
        sources = []
    elif isinstance(sources, (str, bytes, os.PathLike)):
        sources = [sources]
    return [os.fsdecode(os.fspath(s)) for s in sources]


def _index_location(index_path: str) -> tuple[str, str]:
    """The real index file (a link at ``index_path`` is followed, so that its target is what
    is locked, read and replaced: two names of one index are one index) and its folder.
    Raises ReadError for a folder, WriteError when the folder is missing."""
    if os.path.isdir(index_path):
        raise ReadError("is a directory, not an index file", path=index_path)
    real_index = index_file(index_path)
    base = os.path.dirname(real_index)
    folder = os.path.dirname(index_path) or "."
    if not os.path.isdir(folder) or not os.path.isdir(base):
        raise WriteError(
            f"cannot write the index: no folder {folder if not os.path.isdir(folder) else base}", path=index_path
        )
    return real_index, base


def _needs_write(old, plan: Plan, recorded, new_sources, graph, real_index: str, report: BuildReport) -> bool:
    """Whether the build must write a new index file (temporary files of an interrupted
    build are removed first; an upgrade of format 1 is noted). ``recorded``: the old
    index's ``(sources, glob)``; ``new_sources``: this build's ``(sources, glob, exclude)``."""
    if recorded is not None:
        recorded = (*recorded, old.excluded())
    stale = remove_stale_temps(real_index)
    if stale:
        report.notices.append(
            f"removed {len(stale)} temporary file(s) left by an interrupted build: {', '.join(stale)}"
        )
    stale = stale_fused_graph(old)
    if stale is not None and asked_graph(old, graph) == (old_graph_k(old), "fused"):
        from ..matching.fused import FUSED_VERSION

        report.notices.append(
            f"the graph's fused distances are of an older definition (version {stale}): computed afresh "
            f"(version {FUSED_VERSION}, docs/elastic.md)"
        )
    if graph is not None and old is not None:
        k, distance = asked_graph(old, graph)
        old_k = old_graph_k(old)
        if old_k and k != old_k:
            report.notices.append(
                f"the neighbour graph changes from {old_k} to {k} neighbours: every row is searched again"
                if k
                else f"the neighbour graph ({old_k} neighbours) is dropped"
            )
        if k and old_k and distance != graph_distance(old):
            how = "give --elastic to keep it" if distance == "exact" else "without --elastic it is exact again"
            report.notices.append(
                f"the neighbour graph changes from {graph_distance(old)} to {distance} distances ({how})"
            )
    # an index of an older format is rewritten in today's (cells, statistics) even when nothing changed
    upgrade = old is not None and old.format_version < FORMAT_VERSION
    if upgrade:
        report.notices.append(f"upgrading the index from format {old.format_version} to {FORMAT_VERSION}")
    # a file whose metadata HDF5 parses unchecked is rewritten in the checked kind
    rewrite = old is not None and not upgrade and not old.checked_metadata
    if rewrite:
        report.notices.append("rewriting the index with checked metadata (older HDF5 structures or heap attributes)")
    return (
        old is None
        or plan.recompute_all
        or bool(plan.tasks)
        or bool(plan.removed)
        or upgrade
        or rewrite
        or recorded != new_sources
        or graph_changes(old, graph)
        or any(it.path != it.old.path for it in plan.items if it.old)
    )


def _unchanged(report: BuildReport, plan: Plan, old, real_index: str, progress, strict: bool = False) -> None:
    """Nothing to change: the index is not rewritten, but it is made newer than its sources
    (under the build's lock), as Make expects of a command that succeeded: else a rule
    ``index.h5: $(CURVES)`` reruns after every ``touch``, forever. ``strict`` with a file
    that stays failed: not touched either (the build did not succeed)."""
    stays_failed = any(item.action is not Action.COPY for item in plan.items)
    try:
        if not (strict and stays_failed):
            os.utime(real_index)
    except OSError:
        pass  # not ours to touch (read-only, another owner): the index is still right
    if progress is not None:
        progress(0, 0)
    for item in plan.items:
        if item.action is Action.COPY:
            report.unchanged += 1
            report.changes.append(("unchanged", item.path))
        else:
            report.failed += 1
            report.changes.append(("failed", item.path))
            report.failures.append((item.file or item.path, item.old.error))
    report.curves = old.n_curves


def _dry_run_report(report: BuildReport, plan: Plan, old, progress, jobs, file_timeout, runner) -> None:
    """What the build would do, writing nothing: the files it would read are read and
    described as the build reads them (the same tasks, in worker processes), so that a
    broken file is reported ``failed`` (not ``added``) and ``curves`` is the count the
    written index would hold."""
    items, tasks, removed = plan.items, plan.tasks, plan.removed
    total = len(tasks)
    if progress is not None:
        progress(0, total)
    results: dict[int, dict] = {}
    stream = run_tasks(tasks, jobs, None, file_timeout or None) if runner is None else runner(tasks, jobs, None)
    for i, res in stream:
        results[i] = res
        if progress is not None:
            progress(len(results), total)
    actions = {}
    curves = 0
    for item in items:
        path, r = item.path, item.old
        if item.action is Action.COPY:
            actions[path] = "unchanged"
            curves += r.curve_count
            continue
        if item.action is Action.KEEP_FAILED:
            actions[path] = "failed"
            report.failures.append((item.file or path, r.error))
            continue
        res = results[item.task]
        if res["status"] == "same":  # mtime changed, contents did not
            if r.status == "ok":
                actions[path] = "unchanged"
                curves += r.curve_count
            else:
                actions[path] = "failed"
                report.failures.append((item.file or path, r.error))
        elif res["status"] == "ok":
            actions[path] = "added" if r is None else "updated"
            curves += len(res["ids"])
        else:
            actions[path] = "failed"
            report.failures.append((item.file or path, res["error"]))
    for path in removed:
        actions[path] = "removed"
    for path in sorted(actions):
        action = actions[path]
        report.changes.append((action, path))
        setattr(report, action, getattr(report, action) + 1)
    report.curves = curves
