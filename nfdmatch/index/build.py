"""Building and updating an index: the plan (what each file needs) and the build itself."""

from __future__ import annotations

import enum
import os
import time
from dataclasses import dataclass, field

import h5py
import numpy as np

from .._version import __version__
from ..descriptors import DEFAULT_HARMONICS, DEFAULT_SAMPLES, DEFAULT_SCALE, validate_parameters
from ..errors import IndexFormatError, InputError, NfdError, ParameterError, ReadError, ShrinkRefusedError, WriteError
from ..formats import format_of, split_selector
from ..sources import _irregular, find_curve_files
from .lock import _Lock
from .paths import curve_ids, found_location, index_file, openable, source_location, stored
from .pool import _run_tasks, _sha256
from .reader import Index
from .changes import write_changes
from .graph import GraphStats, graph_changes, write_graph
from .search_group import write_search_group
from .schema import FORMAT_VERSION, INDEX_FORMAT, FileRecord, _open_checked, _Problem, _short, default_index_path
from .writer import _CopyRun, _CurveWriter, _fsync_path, _remove_stale_temps, _Space, _write_files_table, _write_sources


def _utcnow() -> str:
    return time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())


class Action(enum.Enum):
    """What a build does with one found file (decided from the old index's /files row)."""

    #: unchanged size and mtime, indexed before: copy its rows from the old index
    COPY = "copy"
    #: unchanged size and mtime, failed before: keep its failure, do not read it again
    KEEP_FAILED = "keep_failed"
    #: same size, another mtime: hash it; same contents are kept as they were, else computed
    HASH = "hash"
    #: new, resized, unreadable by stat, or every file is recomputed: read and describe it
    COMPUTE = "compute"

    @property
    def reads_file(self) -> bool:
        """True when the file is opened (a task of the worker pool; counted in progress)."""
        return self in (Action.HASH, Action.COMPUTE)


@dataclass(frozen=True)
class PlanItem:
    """One found file in the build plan: its stored ``path`` (docs/index-format.md, "Paths
    and ids"), the ``action``, its ``old`` /files record (None for a file new to the index),
    the number of its pool ``task`` (None unless ``action.reads_file``) and ``file``, the
    path that opens it from the working directory (as the walk found it)."""

    path: str
    action: Action
    old: FileRecord | None
    task: int | None
    file: str = ""


@dataclass
class BuildReport:
    """What :func:`build_index` did (or, for a dry run, would do).

    ``added, updated, removed, unchanged, failed`` count FILES; ``curves`` is the number of
    rows in the index after the build (dry run: in the existing index); ``failures`` lists
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
        h5, meta, files = _open_checked(index_path)
    except ReadError:
        if not os.path.exists(index_path):  # nothing there (or a link to a file to be made)
            return None
        raise
    except _Problem as exc:
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
    sources=None,
    index_path=None,
    *,
    samples=None,
    harmonics=None,
    scale=None,
    glob=None,
    input_format=None,
    rebuild=False,
    dry_run=False,
    jobs=None,
    wait=0.0,
    progress=None,
    allow_shrink=False,
    file_timeout=None,
    graph=None,
    runner=None,
) -> BuildReport:
    """Build or update the index of every curve under ``sources``.

    Parameters
    ----------
    sources : path or list of paths: files (taken whatever their extension) or folders
        (recursive; known extensions; hidden files and folders skipped). None or empty:
        the sources the index records (its last build's), re-scanned.
    index_path : the index file (None: :func:`default_index_path`). Its folder must exist. A
        symbolic link is followed: its target is replaced (the link stays) and locked.
    samples, harmonics, scale : descriptor parameters; None keeps the existing index's value
        (defaults 128, 16, "rms" for a new index). An explicit value that differs from the
        index's recomputes every curve (with a notice).
    glob : fnmatch pattern on file names found in folders (None with no ``sources``: the
        recorded one).
    input_format : force this reader for every file (not recorded in the index).
    rebuild : recompute every file, even unchanged ones.
    dry_run : only plan: stat, hash files whose mtime changed, report; write nothing.
    jobs : worker processes (None: ``os.cpu_count()``; 1: in this process, unless
        ``file_timeout`` is given).
    wait : seconds to wait for another build's lock (0: fail at once).
    graph : store each row's ``graph`` nearest rows (``/graph``, for ``query --rerank``);
        None keeps an existing graph's K (no graph for an index without one), 0 drops it.
    progress : optional ``progress(done_files, total_files)``, called with (0, total) first and
        then as files finish; total counts the files that must be read or hashed (unchanged
        files are not counted).
    allow_shrink : allow a build that removes more than half of the index's files, or all.

    Files are stored, and compared with the index's, by the rule of docs/index-format.md
    ("Paths and ids"): relative to the index's folder, whatever the working directory and
    the spelling of the sources.
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
    t0 = time.perf_counter()
    index_path = default_index_path() if index_path is None else str(os.fspath(index_path))
    if sources is None:
        sources = []
    elif isinstance(sources, (str, bytes, os.PathLike)):
        sources = [sources]
    sources = [os.fsdecode(os.fspath(s)) for s in sources]
    if jobs is None:
        jobs = os.cpu_count() or 1
    if isinstance(jobs, bool) or not isinstance(jobs, (int, np.integer)) or jobs < 1:
        raise ParameterError(f"jobs must be an integer >= 1, got {jobs!r}")
    if file_timeout is not None and (
        isinstance(file_timeout, bool)
        or not isinstance(file_timeout, (int, float))
        or not file_timeout >= 0
        or file_timeout == float("inf")
    ):
        raise ParameterError(f"file_timeout must be a finite number of seconds >= 0, got {file_timeout!r}")
    if input_format is not None:
        format_of("x", input_format)  # an unknown format name fails before any work
    for name, value in (("samples", samples), ("harmonics", harmonics)):
        if value is not None and (isinstance(value, bool) or not isinstance(value, (int, np.integer))):
            raise ParameterError(f"{name} must be an integer, got {value!r}")
    if os.path.isdir(index_path):
        raise ReadError("is a directory, not an index file", path=index_path)
    # the real file: a link at index_path is followed, so that its target is what is locked,
    # read and replaced (two names of one index are one index)
    real_index = index_file(index_path)
    base = os.path.dirname(real_index)
    folder = os.path.dirname(index_path) or "."
    if not os.path.isdir(folder) or not os.path.isdir(base):
        raise WriteError(
            f"cannot write the index: no folder {folder if not os.path.isdir(folder) else base}", path=index_path
        )

    report = BuildReport(dry_run=bool(dry_run))
    lock = None if dry_run else _Lock(real_index, wait, name=index_path)
    old = None
    try:
        old = _load_old(index_path, rebuild, report.notices)
        recorded = None if old is None else old.sources()
        if not sources:
            if old is None:
                raise InputError(
                    "no SOURCE given and no index to take them from; name the files or folders to index",
                    path=index_path,
                )
            if recorded is None:
                raise InputError(
                    "no SOURCE given and the index does not record its sources (it was built by an "
                    "older nfdmatch); name them once, later builds remember them",
                    path=index_path,
                )
            sources = [openable(s, base) for s in recorded[0]]
            if glob is None:
                glob = recorded[1]
        found, opens, stored_sources, unseen = _find(sources, glob, base, report.skipped)
        report.sources = stored_sources
        if not found and old is None:
            raise InputError(f"no curve files found under {', '.join(sources) or '(no sources)'}")

        # parameters
        given = {"samples": samples, "harmonics": harmonics, "scale": scale}
        defaults = {"samples": DEFAULT_SAMPLES, "harmonics": DEFAULT_HARMONICS, "scale": DEFAULT_SCALE}
        params = {}
        changed = []
        for name in given:
            previous = getattr(old, name) if old is not None else None
            params[name] = (
                given[name] if given[name] is not None else (previous if previous is not None else defaults[name])
            )
            if old is not None and given[name] is not None and given[name] != previous:
                changed.append(f"{name} {previous} -> {given[name]}")
        params["samples"], params["harmonics"] = int(params["samples"]), int(params["harmonics"])
        validate_parameters(params["samples"], params["harmonics"], params["scale"])
        if changed:
            report.notices.append(f"parameters changed ({', '.join(changed)}): recomputing all curves")
        recompute_all = bool(rebuild) or bool(changed) or old is None
        if not found and old is not None:
            report.notices.append(
                f"no curve files found under {', '.join(sources)}: every file would be removed from the index"
            )

        # the plan. An index that does not record its sources stored paths relative to its
        # build's working directory: they are mapped to the stored rule from this one, so
        # that its unchanged files keep their rows (with new ids) instead of all being
        # removed and added again
        old_files = [] if old is None else old.files()
        rekey = old is not None and recorded is None
        old_rows = {}
        for i, r in enumerate(old_files):
            key = stored(source_location(r.path), base) if rekey else r.path
            old_rows.setdefault(key, (i, r))
        found_set = set(found)
        # a folder that could not be listed this time (permissions, I/O) keeps its files'
        # rows as they were: a fault of the machine must not remove curves
        held = {
            key
            for key, (_, r) in old_rows.items()
            if key not in found_set and any(key == u or key.startswith(u.rstrip("/") + "/") for u in unseen)
        }
        items: list[PlanItem] = []
        tasks = []
        for path in sorted(found_set | held):
            entry = old_rows.get(path)
            r = entry[1] if entry else None
            if path in held:
                items.append(
                    PlanItem(
                        path, Action.COPY if r.status == "ok" else Action.KEEP_FAILED, r, None, openable(path, base)
                    )
                )
                continue
            file = opens[path]
            try:
                st = os.stat(file)
                size, mtime = int(st.st_size), int(st.st_mtime_ns)
            except OSError:
                size = mtime = None
            if r is None or recompute_all or size is None:
                action, old_sha = Action.COMPUTE, None
            elif size == r.size and mtime == r.mtime_ns:
                action, old_sha = (Action.COPY if r.status == "ok" else Action.KEEP_FAILED), None
            elif size == r.size and r.sha256:
                action, old_sha = Action.HASH, r.sha256
            else:
                action, old_sha = Action.COMPUTE, None
            task = None
            if action.reads_file:
                task = len(tasks)
                tasks.append((file, input_format, params["samples"], params["harmonics"], params["scale"], old_sha))
            items.append(PlanItem(path, action, r, task, file))
        removed = [r.path for key, (_, r) in old_rows.items() if key not in found_set and key not in held]

        # an empty or unmounted source folder must not wipe an index from cron
        if old_files and (len(removed) == len(old_files) or 2 * len(removed) > len(old_files)):
            report.shrink = (len(removed), len(old_files))
            what = (
                f"would remove {'all' if len(removed) == len(old_files) else len(removed)} of the "
                f"index's {len(old_files)} files"
            )
            if dry_run and not allow_shrink:
                report.notices.append(f"a build {what}: it will refuse unless --allow-shrink is given")
            elif not allow_shrink:
                cause = (
                    "no curve files found under " + ", ".join(sources)
                    if not found
                    else f"{len(found)} files found under {', '.join(sources)}"
                )
                refused = ShrinkRefusedError(
                    f"refusing to build: it {what} ({cause}; an empty or unmounted "
                    f"folder?); pass --allow-shrink to remove them",
                    path=index_path,
                )
                refused.removed, refused.of = report.shrink
                raise refused
            else:
                report.notices.append(f"removing {len(removed)} of the index's {len(old_files)} files (--allow-shrink)")

        if dry_run:
            _dry_run_report(report, items, removed, old, progress)
            report.seconds = time.perf_counter() - t0
            return report

        stale = _remove_stale_temps(real_index)
        if stale:
            report.notices.append(
                f"removed {len(stale)} temporary file(s) left by an interrupted build: {', '.join(stale)}"
            )
        # a format-1 index is rewritten as format 2 (with its cells) even when nothing changed
        upgrade = old is not None and old.format_version < FORMAT_VERSION
        if upgrade:
            report.notices.append(f"upgrading the index from format {old.format_version} to {FORMAT_VERSION}")
        new_sources = (stored_sources, glob or None)
        needs_write = (
            old is None
            or recompute_all
            or bool(tasks)
            or bool(removed)
            or upgrade
            or recorded != new_sources
            or graph_changes(old, graph)
            or any(it.path != it.old.path for it in items if it.old)
        )
        if not needs_write:
            if progress is not None:
                progress(0, 0)
            for item in items:
                if item.action is Action.COPY:
                    report.unchanged += 1
                    report.changes.append(("unchanged", item.path))
                else:
                    report.failed += 1
                    report.changes.append(("failed", item.path))
                    report.failures.append((item.file or item.path, item.old.error))
            report.curves = old.n_curves
            report.seconds = time.perf_counter() - t0
            return report

        _write(
            report,
            real_index,
            items,
            tasks,
            removed,
            old,
            params,
            jobs,
            lock,
            progress,
            file_timeout,
            sources=new_sources,
            name=index_path,
            graph=graph,
            recompute_all=recompute_all,
            runner=runner,
        )
    finally:
        if old is not None:
            old.close()
        if lock is not None:
            lock.release()
    report.seconds = time.perf_counter() - t0
    return report


def _find(sources: list[str], glob, base: str, skipped: list):
    """The curve files under ``sources`` by stored path: ``(sorted stored paths, {stored path:
    path that opens it, as found}, stored sources, stored paths of folders that could not be
    listed)``. Two spellings of one file (``lib`` and ``/abs/lib``, a link to ``lib``) are one
    file, the first spelling opens it. What a walk skips (folders it cannot list, FIFOs and
    other non-regular files) is appended to ``skipped`` as ``(path, message)``."""
    opens: dict[str, str] = {}
    stored_sources: list[str] = []
    unseen: list[str] = []
    for source in sources:
        real = source_location(source)
        is_folder = os.path.isdir(source)
        problems: list = []
        files = find_curve_files([source], glob=glob, problems=problems)  # ReadError: a missing source
        kind = None if is_folder else _irregular(split_selector(source)[0])
        if kind is not None:  # a FIFO named directly: opening it would block the build
            files = []
            if any(path == source for path, _ in skipped):
                continue
            skipped.append((source, str(ReadError(f"is {kind}, not a regular file; skipped", path=source))))
        key = stored(real, base)
        if key not in stored_sources:
            stored_sources.append(key)
        for file in files:
            opens.setdefault(stored(found_location(file, source, real, is_folder), base), file)
        for problem in problems:
            if any(path == problem.path for path, _ in skipped):
                continue  # named once, however many sources reach it
            skipped.append((problem.path, str(problem)))
            if problem.path and os.path.isdir(problem.path):
                unseen.append(stored(found_location(problem.path, source, real, is_folder), base))
    return sorted(opens), opens, stored_sources, unseen


def _dry_run_report(report: BuildReport, items: list[PlanItem], removed, old, progress) -> None:
    total = len([it for it in items if it.action.reads_file])
    done = 0
    if progress is not None:
        progress(0, total)
    actions = {}
    for item in items:
        path, r = item.path, item.old
        if item.action is Action.COPY:
            actions[path] = "unchanged"
        elif item.action is Action.KEEP_FAILED:
            actions[path] = "failed"
            report.failures.append((item.file or path, r.error))
        elif item.action is Action.COMPUTE:
            actions[path] = "added" if r is None else "updated"
            done += 1
        else:  # Action.HASH
            try:
                same = _sha256(item.file or path) == r.sha256
            except OSError:
                same = False
            if same and r.status == "ok":
                actions[path] = "unchanged"
            elif same:
                actions[path] = "failed"
                report.failures.append((item.file or path, r.error))
            else:
                actions[path] = "updated"
            done += 1
        if progress is not None and item.action.reads_file:
            progress(done, total)
    for path in removed:
        actions[path] = "removed"
    for path in sorted(actions):
        action = actions[path]
        report.changes.append((action, path))
        setattr(report, action, getattr(report, action) + 1)
    report.curves = 0 if old is None else old.n_curves


def _write(
    report: BuildReport,
    index_path: str,
    items: list[PlanItem],
    tasks,
    removed,
    old,
    params,
    jobs,
    lock,
    progress,
    file_timeout=None,
    *,
    sources=((), None),
    name=None,
    graph=None,
    recompute_all=True,
    runner=None,
):
    """Write the new index beside ``index_path`` (the real file) and move it into place;
    ``sources`` ``(stored paths, glob)`` go to /sources; ``name``: the index as the user named
    it (messages)."""
    shown = index_path if name is None else name
    folder = os.path.dirname(index_path) or "."
    name = os.path.basename(index_path)
    import secrets

    tmp = os.path.join(folder, f".{name}.tmp-{os.getpid()}-{secrets.token_hex(4)}.h5")
    K = params["harmonics"]
    results: dict[int, dict] = {}
    total = len(tasks)
    if progress is not None:
        progress(0, total)
    lock_fd = None if lock is None else lock.fd
    stream = _run_tasks(tasks, jobs, lock_fd, file_timeout or None) if runner is None else runner(tasks, jobs, lock_fd)
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

    records: list[FileRecord] = []
    fresh: list[tuple[int, int]] = []  # (start, count): rows added or recomputed (/changes)
    actions: dict[str, str] = {p: "removed" for p in removed}
    now = _utcnow()
    try:
        space = None
        try:
            h5 = h5py.File(tmp, "w", locking=False)
        except Exception as exc:
            raise WriteError(f"cannot write the index: {_short(exc)}", path=shown) from None
        try:
            space = _Space(h5)
            space.reserve(0)  # the superblock, attributes, small tables
            attrs = h5.attrs
            attrs["format"] = INDEX_FORMAT
            attrs["format_version"] = np.int64(FORMAT_VERSION)
            attrs["nfdmatch_version"] = __version__
            attrs["samples"] = np.int64(params["samples"])
            attrs["harmonics"] = np.int64(params["harmonics"])
            attrs["scale"] = params["scale"]
            attrs["created"] = old.created if old is not None and old.created else now
            attrs["updated"] = now
            writer = _CurveWriter(h5, K, space)
            run = _CopyRun(old, writer)
            for item in items:
                path, r = item.path, item.old
                file_row = len(records)
                start = writer.rows + writer.pending_rows + run.rows
                # a file whose stored path changed (an index upgraded to recorded sources)
                # keeps its rows under ids made from the new path
                new_ids = None if r is None or r.path == path else curve_ids(path, r.curve_count)
                if item.action is Action.COPY:
                    run.add(r.curve_start, r.curve_count, file_row, new_ids)
                    records.append(FileRecord(path, r.size, r.mtime_ns, r.sha256, "ok", "", start, r.curve_count))
                    actions[path] = "unchanged"
                    continue
                if item.action is Action.KEEP_FAILED:
                    records.append(FileRecord(path, r.size, r.mtime_ns, r.sha256, "failed", r.error, start, 0))
                    actions[path] = "failed"
                    report.failures.append((item.file or path, r.error))
                    continue
                res = result_of(item.task)
                if res["status"] == "same":  # mtime changed, contents did not
                    if r.status == "ok":
                        run.add(r.curve_start, r.curve_count, file_row, new_ids)
                        records.append(
                            FileRecord(path, res["size"], res["mtime_ns"], r.sha256, "ok", "", start, r.curve_count)
                        )
                        actions[path] = "unchanged"
                    else:
                        records.append(
                            FileRecord(path, res["size"], res["mtime_ns"], r.sha256, "failed", r.error, start, 0)
                        )
                        actions[path] = "failed"
                        report.failures.append((item.file or path, r.error))
                    continue
                run.flush()
                if res["status"] == "ok":
                    n = len(res["ids"])
                    piece = dict(res["arrays"])
                    piece["id"] = np.asarray(curve_ids(path, n), dtype=object)
                    piece["file"] = np.full(n, file_row, dtype=np.int32)
                    writer.append(piece)
                    records.append(FileRecord(path, res["size"], res["mtime_ns"], res["sha256"], "ok", "", start, n))
                    fresh.append((start, n))
                    actions[path] = "added" if r is None else "updated"
                else:
                    records.append(
                        FileRecord(path, res["size"], res["mtime_ns"], res["sha256"], "failed", res["error"], start, 0)
                    )
                    actions[path] = "failed"
                    report.failures.append((item.file or path, res["error"]))
            run.flush()
            writer.flush()
            _write_files_table(h5, records, space)
            _write_sources(h5, *sources)
            write_changes(h5, fresh)
            # the cells: features, squared norms, row numbers and first harmonics of every row
            space.reserve(writer.rows * (8 * (2 * K + 3) + 24 * K + 160))
            report.cells = write_search_group(h5, K, id_crcs=writer.id_crcs())
            report.graph = write_graph(h5, old, graph, reuse=not recompute_all)
            report.curves = writer.rows
        except BaseException:
            if space is not None:
                space.abandon()  # HDF5 cannot close a file it failed to write
            raise
        finally:
            stream.close()  # shuts the worker pool down
            try:
                h5.close()
            except Exception:
                if space is None or not space.abandoned:
                    raise
        _Space.release(tmp)
        _fsync_path(tmp, strict=True)  # a full disk may show only here: never replace then
        os.replace(tmp, index_path)
        _fsync_path(folder, directory=True)
    except BaseException as exc:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        # h5py reports a failed write (disk full, quota, file-size limit) as OSError, or as
        # RuntimeError when it surfaces while closing the file
        if isinstance(exc, (OSError, RuntimeError)) and not isinstance(exc, NfdError):
            why = exc.strerror if isinstance(exc, OSError) and exc.strerror else _short(exc)
            raise WriteError(f"cannot write the index: {why}", path=shown) from None
        raise
    report.written = True
    for path in sorted(actions):
        action = actions[path]
        report.changes.append((action, path))
        setattr(report, action, getattr(report, action) + 1)
