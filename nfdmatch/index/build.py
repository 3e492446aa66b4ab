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
from ..errors import IndexFormatError, InputError, NfdError, ParameterError, ReadError, WriteError
from ..formats import format_of
from ..sources import find_curve_files
from .lock import _Lock
from .pool import _run_tasks, _sha256
from .reader import Index
from .search_group import write_search_group
from .schema import FORMAT_VERSION, INDEX_FORMAT, FileRecord, _open_checked, _Problem, _short, default_index_path
from .writer import _CopyRun, _CurveWriter, _fsync_path, _remove_stale_temps, _write_files_table


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
    """One found file in the build plan: its ``path``, the ``action``, its ``old`` /files
    record (None for a file new to the index) and the number of its pool ``task`` (None
    unless ``action.reads_file``)."""

    path: str
    action: Action
    old: FileRecord | None
    task: int | None


@dataclass
class BuildReport:
    """What :func:`build_index` did (or, for a dry run, would do).

    ``added, updated, removed, unchanged, failed`` count FILES; ``curves`` is the number of
    rows in the index after the build (dry run: in the existing index); ``failures`` lists
    ``(path, message)`` of every failed file (new failures and files that stay failed);
    ``changes`` lists ``(action, path)`` for every file, in path order, with action one of
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


def _load_old(index_path: str, rebuild: bool, notices: list):
    """The existing index (an :class:`Index`), or None when there is none or it may be replaced."""
    try:
        h5, meta, files = _open_checked(index_path)
    except ReadError:
        if not os.path.lexists(index_path):
            return None
        raise
    except _Problem as exc:
        if exc.kind == "empty":
            notices.append(f"replacing the empty file at {index_path}")
            return None
        if exc.kind in ("foreign", "not_hdf5"):
            raise IndexFormatError(f"{exc.message}; refusing to overwrite it: move it away or choose "
                                   f"another --index", path=index_path) from None
        if rebuild:
            notices.append(f"replacing {index_path}: {exc.message}")
            return None
        raise IndexFormatError(f"{exc.message}; move it away or pass --rebuild to replace it",
                               path=index_path) from None
    return Index(index_path, h5, meta, files)


def build_index(sources, index_path=None, *, samples=None, harmonics=None, scale=None, glob=None,
                input_format=None, rebuild=False, dry_run=False, jobs=None, wait=0.0,
                progress=None, runner=None) -> BuildReport:
    """Build or update the index of every curve under ``sources``.

    Parameters
    ----------
    sources : path or list of paths: files (taken whatever their extension) or folders
        (recursive; known extensions; hidden files and folders skipped).
    index_path : the index file (None: :func:`default_index_path`). Its folder must exist.
    samples, harmonics, scale : descriptor parameters; None keeps the existing index's value
        (defaults 128, 16, "rms" for a new index). An explicit value that differs from the
        index's recomputes every curve (with a notice).
    glob : fnmatch pattern on file names found in folders.
    input_format : force this reader for every file (not recorded in the index).
    rebuild : recompute every file, even unchanged ones.
    dry_run : only plan: stat, hash files whose mtime changed, report; write nothing.
    jobs : worker processes (None: ``os.cpu_count()``; 1: in this process).
    wait : seconds to wait for another build's lock (0: fail at once).
    progress : optional ``progress(done_files, total_files)``, called with (0, total) first and
        then as files finish; total counts the files that must be read or hashed (unchanged
        files are not counted).
    runner : what computes the files to read (None: the local pool); called as
        ``runner(tasks, jobs, lock_fd)``, it yields ``(task_number, result of
        pool._compute_file(*task))`` in any order (``nfdmatch.distributed`` plugs Dask in).

    Returns
    -------
    :class:`BuildReport`.

    Raises
    ------
    ReadError : a source that does not exist; the index path is a directory.
    InputError : no curve files under the sources and no existing index.
    ParameterError : invalid parameters or jobs.
    IndexLockedError : another build holds the lock (after ``wait`` seconds).
    IndexFormatError : the existing file is not a readable index (see docs/index-format.md for
        which files ``rebuild`` may replace; an HDF5 file of another kind never is).
    WriteError : the index cannot be written (missing folder, no permission, disk full).
    """
    t0 = time.perf_counter()
    index_path = default_index_path() if index_path is None else str(os.fspath(index_path))
    if isinstance(sources, (str, bytes, os.PathLike)):
        sources = [sources]
    sources = [str(os.fspath(s)) for s in sources]
    if jobs is None:
        jobs = os.cpu_count() or 1
    if isinstance(jobs, bool) or not isinstance(jobs, (int, np.integer)) or jobs < 1:
        raise ParameterError(f"jobs must be an integer >= 1, got {jobs!r}")
    if input_format is not None:
        format_of("x", input_format)              # an unknown format name fails before any work
    for name, value in (("samples", samples), ("harmonics", harmonics)):
        if value is not None and (isinstance(value, bool) or not isinstance(value, (int, np.integer))):
            raise ParameterError(f"{name} must be an integer, got {value!r}")
    if os.path.isdir(index_path):
        raise ReadError("is a directory, not an index file", path=index_path)
    folder = os.path.dirname(index_path) or "."
    if not os.path.isdir(folder):
        raise WriteError(f"cannot write the index: no folder {folder}", path=index_path)

    found = sorted({os.path.normpath(p) for p in find_curve_files(sources, glob=glob)})
    report = BuildReport(dry_run=bool(dry_run))
    lock = None if dry_run else _Lock(index_path, wait)
    old = None
    try:
        old = _load_old(index_path, rebuild, report.notices)
        if not found and old is None:
            raise InputError(f"no curve files found under {', '.join(sources) or '(no sources)'}")

        # parameters
        given = {"samples": samples, "harmonics": harmonics, "scale": scale}
        defaults = {"samples": DEFAULT_SAMPLES, "harmonics": DEFAULT_HARMONICS, "scale": DEFAULT_SCALE}
        params = {}
        changed = []
        for name in given:
            previous = getattr(old, name) if old is not None else None
            params[name] = given[name] if given[name] is not None else (
                previous if previous is not None else defaults[name])
            if old is not None and given[name] is not None and given[name] != previous:
                changed.append(f"{name} {previous} -> {given[name]}")
        params["samples"], params["harmonics"] = int(params["samples"]), int(params["harmonics"])
        validate_parameters(params["samples"], params["harmonics"], params["scale"])
        if changed:
            report.notices.append(f"parameters changed ({', '.join(changed)}): recomputing all curves")
        recompute_all = bool(rebuild) or bool(changed) or old is None
        if not found and old is not None:
            report.notices.append(f"no curve files found under {', '.join(sources)}: "
                                  f"every file is removed from the index")

        # the plan
        old_rows = {}
        old_files = [] if old is None else old.files()
        for i, r in enumerate(old_files):
            old_rows[r.path] = (i, r)
        found_set = set(found)
        items: list[PlanItem] = []
        tasks = []
        for path in found:
            entry = old_rows.get(path)
            r = entry[1] if entry else None
            try:
                st = os.stat(path)
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
                tasks.append((path, input_format, params["samples"], params["harmonics"], params["scale"], old_sha))
            items.append(PlanItem(path, action, r, task))
        removed = [r.path for r in old_files if r.path not in found_set]

        if dry_run:
            _dry_run_report(report, items, removed, old, progress)
            report.seconds = time.perf_counter() - t0
            return report

        stale = _remove_stale_temps(index_path)
        if stale:
            report.notices.append(f"removed {len(stale)} temporary file(s) left by an interrupted build: "
                                  f"{', '.join(stale)}")
        # a format-1 index is rewritten as format 2 (with its cells) even when nothing changed
        upgrade = old is not None and old.format_version < FORMAT_VERSION
        if upgrade:
            report.notices.append(f"upgrading the index from format {old.format_version} to {FORMAT_VERSION}")
        needs_write = old is None or recompute_all or bool(tasks) or bool(removed) or upgrade
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
                    report.failures.append((item.path, item.old.error))
            report.curves = old.n_curves
            report.seconds = time.perf_counter() - t0
            return report

        _write(report, index_path, items, tasks, removed, old, params, jobs, lock, progress, runner)
    finally:
        if old is not None:
            old.close()
        if lock is not None:
            lock.release()
    report.seconds = time.perf_counter() - t0
    return report


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
            report.failures.append((path, r.error))
        elif item.action is Action.COMPUTE:
            actions[path] = "added" if r is None else "updated"
            done += 1
        else:                                   # Action.HASH
            try:
                same = _sha256(path) == r.sha256
            except OSError:
                same = False
            if same and r.status == "ok":
                actions[path] = "unchanged"
            elif same:
                actions[path] = "failed"
                report.failures.append((path, r.error))
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


def _write(report: BuildReport, index_path: str, items: list[PlanItem], tasks, removed, old, params, jobs, lock,
           progress, runner=None):
    folder = os.path.dirname(index_path) or "."
    name = os.path.basename(index_path)
    import secrets

    tmp = os.path.join(folder, f".{name}.tmp-{os.getpid()}-{secrets.token_hex(4)}.h5")
    K = params["harmonics"]
    results: dict[int, dict] = {}
    total = len(tasks)
    if progress is not None:
        progress(0, total)
    stream = (runner or _run_tasks)(tasks, jobs, None if lock is None else lock.fd)
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
    actions: dict[str, str] = {p: "removed" for p in removed}
    now = _utcnow()
    try:
        try:
            h5 = h5py.File(tmp, "w", locking=False)
        except Exception as exc:
            raise WriteError(f"cannot write the index: {_short(exc)}", path=index_path) from None
        try:
            attrs = h5.attrs
            attrs["format"] = INDEX_FORMAT
            attrs["format_version"] = np.int64(FORMAT_VERSION)
            attrs["nfdmatch_version"] = __version__
            attrs["samples"] = np.int64(params["samples"])
            attrs["harmonics"] = np.int64(params["harmonics"])
            attrs["scale"] = params["scale"]
            attrs["created"] = (old.created if old is not None and old.created else now)
            attrs["updated"] = now
            writer = _CurveWriter(h5, K)
            run = _CopyRun(old, writer)
            for item in items:
                path, r = item.path, item.old
                file_row = len(records)
                start = writer.rows + writer.pending_rows + run.rows
                if item.action is Action.COPY:
                    run.add(r.curve_start, r.curve_count, file_row)
                    records.append(FileRecord(path, r.size, r.mtime_ns, r.sha256, "ok", "", start, r.curve_count))
                    actions[path] = "unchanged"
                    continue
                if item.action is Action.KEEP_FAILED:
                    records.append(FileRecord(path, r.size, r.mtime_ns, r.sha256, "failed", r.error, start, 0))
                    actions[path] = "failed"
                    report.failures.append((path, r.error))
                    continue
                res = result_of(item.task)
                if res["status"] == "same":            # mtime changed, contents did not
                    if r.status == "ok":
                        run.add(r.curve_start, r.curve_count, file_row)
                        records.append(FileRecord(path, res["size"], res["mtime_ns"], r.sha256, "ok", "", start,
                                                  r.curve_count))
                        actions[path] = "unchanged"
                    else:
                        records.append(FileRecord(path, res["size"], res["mtime_ns"], r.sha256, "failed", r.error,
                                                  start, 0))
                        actions[path] = "failed"
                        report.failures.append((path, r.error))
                    continue
                run.flush()
                if res["status"] == "ok":
                    n = len(res["ids"])
                    piece = dict(res["arrays"])
                    piece["id"] = np.asarray(res["ids"], dtype=object)
                    piece["file"] = np.full(n, file_row, dtype=np.int32)
                    writer.append(piece)
                    records.append(FileRecord(path, res["size"], res["mtime_ns"], res["sha256"], "ok", "", start, n))
                    actions[path] = "added" if r is None else "updated"
                else:
                    records.append(FileRecord(path, res["size"], res["mtime_ns"], res["sha256"], "failed",
                                              res["error"], start, 0))
                    actions[path] = "failed"
                    report.failures.append((path, res["error"]))
            run.flush()
            writer.flush()
            _write_files_table(h5, records)
            report.cells = write_search_group(h5, K)
            report.curves = writer.rows
        finally:
            stream.close()                          # shuts the worker pool down
            h5.close()
        _fsync_path(tmp)
        os.replace(tmp, index_path)
        _fsync_path(folder, directory=True)
    except BaseException as exc:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        if isinstance(exc, OSError) and not isinstance(exc, NfdError):
            raise WriteError(f"cannot write the index: {exc.strerror or _short(exc)}", path=index_path) from exc
        raise
    report.written = True
    for path in sorted(actions):
        action = actions[path]
        report.changes.append((action, path))
        setattr(report, action, getattr(report, action) + 1)
