"""The plan of a build: what each found file needs (:class:`Action`), decided from the old
index's ``/files`` row, and the checks made before anything is read or written (parameters,
sources, a shrink). :func:`nfdmatch.index.build.build_index` carries the plan out."""

from __future__ import annotations

from typing import Any, TYPE_CHECKING

import enum
import os
from dataclasses import dataclass, field

import numpy as np

from ..descriptors import DEFAULT_HARMONICS, DEFAULT_SAMPLES, DEFAULT_SCALE, validate_parameters
from ..errors import InputError, ParameterError, ReadError, ShrinkRefusedError
from ..formats import format_of, split_selector
from ..mesh.objects import ObjectRule, is_mesh_file
from ..sources import _irregular, find_curve_files
from ..names import decode_name
from .paths import found_location, openable, source_location, stored
from .schema import FileRecord

if TYPE_CHECKING:
    from collections.abc import Sequence
    from .build import BuildReport
    from .reader import Index

__all__ = [
    "Action",
    "PlanItem",
    "Plan",
    "check_arguments",
    "recorded_sources",
    "find_files",
    "parameters",
    "plan_files",
    "check_shrink",
]


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
class Plan:
    """Every found file's :class:`PlanItem` in stored-path order, the pool ``tasks`` (one per
    file that is read: ``(file, input_format, samples, harmonics, scale, old sha256, object
    rule tuple)``), the
    stored paths ``removed`` from the index, and the descriptor ``params`` with whether every
    curve is recomputed (``recompute_all``)."""

    items: list[PlanItem] = field(default_factory=list)
    tasks: list[tuple] = field(default_factory=list)
    removed: list[str] = field(default_factory=list)
    params: dict = field(default_factory=dict)
    recompute_all: bool = False


def check_arguments(
    jobs: int | None, file_timeout: float | None, input_format: str | None, samples: int | None, harmonics: int | None
) -> int:
    """Raise ParameterError for a bad argument of a build, before any work; returns ``jobs``
    (None: the cores)."""
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
    return int(jobs)


def recorded_sources(
    old: Index | None, recorded: tuple[Sequence[str], str | None] | None, index_path: str, real_index: str, base: str
) -> list[str]:
    """The sources a build without SOURCE takes: those the old index records, opened from
    here. Raises InputError when there is no index or it records none, ReadError when a
    recorded relative source no longer resolves (the index was moved)."""
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
    for s, kept in zip(sources, recorded[0]):
        if not os.path.lexists(split_selector(s)[0]) and not os.path.isabs(kept):
            raise ReadError(
                f"no such file or folder: the index records the source {kept!r} relative to its "
                f"folder {os.path.dirname(real_index)}; was the index moved? Move it back, or name "
                "the sources and rebuild it there (--rebuild --allow-shrink)",
                path=s,
            )
    return sources


def find_files(
    sources: list[str], glob: str | None, base: str, skipped: list[tuple[str, str]]
) -> tuple[list[str], dict[str, str], list[str], list[str]]:
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
        files = find_curve_files([source], glob=glob, problems=problems, meshes=True)  # ReadError: a missing source
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
                # normalized: the source folder itself ("lib" found as "lib/.") holds every row under it
                unseen.append(stored(os.path.normpath(found_location(problem.path, source, real, is_folder)), base))
    return sorted(opens), opens, stored_sources, unseen


def parameters(
    old: Index | None,
    samples: int | None,
    harmonics: int | None,
    scale: str | None,
    notices: list[str],
    sections: int | None = None,
) -> tuple[dict[str, Any], bool]:
    """The descriptor parameters of the build (given, else the old index's, else the
    defaults) and whether they changed from the old index's (every curve then recomputed;
    a notice says so). ``params["objects"]``: the object rule (``sections`` given, else
    the old index's, else the default) as :meth:`ObjectRule.as_tuple`."""
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
    old_rule = old.object_rule() if old is not None else None
    rule = ObjectRule(sections=sections) if sections is not None else (old_rule or ObjectRule())
    if old_rule is not None and rule != old_rule:
        changed.append(f"sections {old_rule.sections} -> {rule.sections}")
    params["objects"] = rule.as_tuple()
    if changed:
        notices.append(f"parameters changed ({', '.join(changed)}): recomputing all curves")
    return params, bool(changed)


def plan_files(
    old: Index | None,
    old_files: Sequence[FileRecord],
    recorded: tuple[Sequence[str], str | None] | None,
    found: list[str],
    opens: dict[str, str],
    unseen: list[str],
    base: str,
    params: dict[str, Any],
    recompute_all: bool,
    input_format: str | None,
) -> Plan:
    """What each found file needs, from its old ``/files`` row and a stat.

    An index that does not record its sources stored paths relative to its build's working
    directory: they are mapped to the stored rule from this one, so that its unchanged files
    keep their rows (with new ids) instead of all being removed and added again. A folder
    that could not be listed this time (``unseen``: permissions, I/O) keeps its files' rows
    as they were: a fault of the machine must not remove curves."""
    plan = Plan(params=params, recompute_all=recompute_all)
    rekey = old is not None and recorded is None
    # a mesh failed as a curve file before meshes were objects (format < 3): cut it now
    retry_meshes = old is not None and old.format_version < 3
    old_rows = {}
    for i, r in enumerate(old_files):
        key = stored(source_location(decode_name(r.path)), base) if rekey else r.path
        old_rows.setdefault(key, (i, r))
    found_set = set(found)
    held = {
        key
        for key, (_, r) in old_rows.items()
        if key not in found_set and any(key == u or key.startswith(u.rstrip("/") + "/") for u in unseen)
    }
    for path in sorted(found_set | held):
        entry = old_rows.get(path)
        r = entry[1] if entry else None
        if path in held:
            action = Action.COPY if r.status == "ok" else Action.KEEP_FAILED
            plan.items.append(PlanItem(path, action, r, None, openable(path, base)))
            continue
        file = opens[path]
        action, old_sha = _action(file, r, recompute_all)
        if action is Action.KEEP_FAILED and retry_meshes and input_format is None and is_mesh_file(file):
            action = Action.COMPUTE
        task = None
        if action.reads_file:
            task = len(plan.tasks)
            descriptor = (params["samples"], params["harmonics"], params["scale"])
            plan.tasks.append((file, input_format, *descriptor, old_sha, params["objects"]))
        plan.items.append(PlanItem(path, action, r, task, file))
    plan.removed = [r.path for key, (_, r) in old_rows.items() if key not in found_set and key not in held]
    return plan


def _action(file: str, r: FileRecord | None, recompute_all: bool) -> tuple[Action, str | None]:
    """A found file's action from its old record and a stat, and the sha256 to compare with
    (HASH only)."""
    try:
        st = os.stat(file)
        size, mtime = int(st.st_size), int(st.st_mtime_ns)
    except OSError:
        size = mtime = None
    if r is None or recompute_all or size is None:
        return Action.COMPUTE, None
    if size == r.size and mtime == r.mtime_ns:
        return (Action.COPY if r.status == "ok" else Action.KEEP_FAILED), None
    if size == r.size and r.sha256:
        return Action.HASH, r.sha256
    return Action.COMPUTE, None


def check_shrink(
    report: BuildReport,
    old_files: Sequence[FileRecord],
    plan: Plan,
    found: list[str],
    sources: Sequence[str],
    index_path: str,
    real_index: str,
    dry_run: bool,
    allow_shrink: bool,
) -> None:
    """An empty or unmounted source folder must not wipe an index from cron: a build that
    removes more than half of the index's files (or all) raises ShrinkRefusedError unless
    ``allow_shrink`` (a dry run notes it instead); ``report.shrink`` records it."""
    removed = plan.removed
    if not old_files or not (len(removed) == len(old_files) or 2 * len(removed) > len(old_files)):
        return
    report.shrink = (len(removed), len(old_files))
    what = (
        f"would remove {'all' if len(removed) == len(old_files) else len(removed)} of the "
        f"index's {len(old_files)} files"
    )
    if allow_shrink:
        report.notices.append(f"removing {len(removed)} of the index's {len(old_files)} files (--allow-shrink)")
        return
    if dry_run:
        report.notices.append(f"a build {what}: it will refuse unless --allow-shrink is given")
        return
    cause = (
        "no curve files found under " + ", ".join(sources)
        if not found
        else f"{len(found)} files found under {', '.join(sources)}"
    )
    moved = _moved_index(old_files, removed, found, real_index)
    if report.skipped:  # the walk could not read some folders: say which and why
        guess = f"{report.skipped[0][1]}{' ...' if len(report.skipped) > 1 else ''}"
    else:
        guess = "an empty or unmounted folder?"
    if moved:
        message = (
            f"refusing to build: the index's {len(old_files)} stored paths are relative to "
            f"its folder and no longer lead to its files from {os.path.dirname(real_index)} "
            f"(e.g. {moved}): was the index moved? Move it back, or rebuild it here with "
            f"`nfdmatch index build {' '.join(sources)} --index {index_path} --rebuild "
            "--allow-shrink`"
        )
    else:
        message = f"refusing to build: it {what} ({cause}; {guess}); pass --allow-shrink to remove them"
    refused = ShrinkRefusedError(message, path=index_path)
    refused.removed, refused.of = report.shrink
    raise refused


def _moved_index(old_files, removed, found, real_index: str) -> str | None:
    """A removed relative path (as stored) when the index looks moved away from its files:
    every path it would remove is relative and none of them opens from the index's folder
    any more, while files were found. None otherwise."""
    if not found or not removed or len(removed) != len(old_files):
        return None
    folder = os.path.dirname(real_index)
    if any(os.path.isabs(p) for p in removed):
        return None
    if any(os.path.lexists(os.path.join(folder, p)) for p in removed[:50]):
        return None
    return removed[0]
