"""The index commands: ``index build``, ``index info``, ``index verify``, ``index ls`` and ``index export``."""

from __future__ import annotations

import json
import sys
from datetime import datetime, timezone
from typing import TYPE_CHECKING, Any

import click

from ..defaults import DEFAULT_GRAPH_K
from ..errors import NfdError
from .options import (
    EXIT_ERROR,
    EXIT_NOTHING,
    error,
    finish,
    format_option,
    glob_options,
    index_option,
    input_format_option,
    int_option,
    note,
    optional_descriptor_options,
    output_option,
    rows_format_option,
    say,
)
from .output import deliver, progress_bar, resolve_format, write_rows
from .cluster import open_cluster, scheduler_options
from .group import main

if TYPE_CHECKING:
    from collections.abc import Callable

    from ..index.build import BuildReport
    from ..index.graph import GraphSpec, GraphStats
    from .options import F


@main.group()
def index() -> None:
    """Build and inspect the HDF5 index of curve descriptors.

    \b
    Examples:
      nfdmatch index build curves/ --index curves.h5
      nfdmatch index info --index curves.h5
      nfdmatch index ls --index curves.h5 --status failed
      nfdmatch index verify --index curves.h5
      nfdmatch index export --index curves.h5 -o descriptors.npz
    """


#: the options of every command that writes the index (build, add, remove), defined once
_JOBS = int_option("--jobs", "-j", help="Parallel workers [default: all cores].")
_WAIT = click.option(
    "--wait",
    type=click.FloatRange(min=0),
    default=0.0,
    show_default=True,
    help="Seconds to wait for another build's lock (0: fail at once).",
)


def _summary_format(help_extra: str) -> Callable[[F], F]:
    """--format text|json of the summary of every command that writes the index."""
    return format_option(("text", "json"), default="text", help_extra=help_extra)


@index.command("build")
@click.argument("sources", nargs=-1, required=False, metavar="[SOURCE...]")
@index_option
@glob_options(extra=" Recorded with the sources.")
@click.option("--rebuild", is_flag=True, help="Recompute every curve, even unchanged files.")
@click.option("--dry-run", is_flag=True, help="Print what would change (on stdout) and write nothing.")
@_JOBS
@_WAIT
@click.option(
    "--strict",
    is_flag=True,
    help="When any file fails, write nothing (exit 3, the index as it was): a Makefile then runs "
    "the build again until every file reads, instead of taking an index with a failed file for done.",
)
@click.option(
    "--allow-shrink",
    is_flag=True,
    help="Allow a build that removes more than half of the index's files (or all of them).",
)
@click.option(
    "--file-timeout",
    type=click.FloatRange(min=0, max=1e9),
    default=600.0,
    show_default=True,
    metavar="SECONDS",
    help="A file still being read after this long fails alone (0: no limit). Files are read in "
    "worker processes, also with --jobs 1, so a stuck or crashing reader cannot stop the build.",
)
@click.option(
    "--graph",
    "graph_k",
    type=click.IntRange(min=0),
    is_flag=False,
    flag_value=DEFAULT_GRAPH_K,
    default=None,
    metavar="[K]",
    help=f"Store each curve's K nearest curves, for query --rerank (K = {DEFAULT_GRAPH_K} when not given: "
    "then put --graph after the sources or before another option); 0 drops the graph; with "
    "--scheduler its rows are searched by the cluster's workers "
    "[default: keep the index's graph, if it has one].",
)
@int_option(
    "--sections",
    metavar="N",
    help="Meshes among the sources (STL, PLY, OFF, GLB/GLTF, OBJ with faces) are indexed as objects, "
    "cut by N planes per principal axis at area quantiles (docs/objects.md) [default: the index's "
    "rule, 7 for a new index].",
)
@click.option(
    "--elastic",
    "graph_elastic",
    is_flag=True,
    help="With --graph: the graph holds the elastic stage's fused distances (each curve's K of least "
    "fused distance among its exact 30 nearest; docs/elastic.md), and query --rerank ranks by them.",
)
@optional_descriptor_options("the index's")
@input_format_option
@scheduler_options
@_summary_format(": text, a summary on stderr; json, one summary object on stdout")
def index_build(
    sources: tuple[str, ...],
    index_path: str,
    glob_pattern: str | None,
    rebuild: bool,
    dry_run: bool,
    jobs: int | None,
    wait: float,
    strict: bool,
    allow_shrink: bool,
    file_timeout: float,
    graph_k: int | None,
    sections: int | None,
    graph_elastic: bool,
    descriptor: dict[str, Any],
    input_format: str | None,
    scheduler: str | None,
    scheduler_timeout: float,
    output_format: str,
) -> None:
    """Index the curves in SOURCE... (files or folders, recursively); meshes (STL, PLY, OFF,
    GLB/GLTF, OBJ with faces) as objects, their contours MESH#I (docs/objects.md).

    Without SOURCE, the sources (and --glob) of the index's last build are re-scanned:
    the index records them. Files are stored relative to the index's folder (absolute
    when outside it), so the same files are the same rows whatever the working
    directory or the spelling of the sources.

    Incremental: unchanged files (same size and mtime, or same SHA-256) are not
    recomputed, changed files are, files no longer under the sources are removed. A
    build that would remove more than half of the index's files, or all of them (an
    empty or unmounted folder), refuses (exit 2) unless --allow-shrink is given.
    The index is written to a temporary file and moved into place when complete, so
    an interrupted build leaves the previous index intact and queries keep working.
    Bad files are named on stderr and recorded as failed; the rest is indexed.
    Files are read in worker processes: a worker that dies is replaced and its files read
    again; a file that kills a worker twice, or takes longer than --file-timeout, fails
    alone. Ctrl-C or SIGTERM stops the build at once and leaves the previous index.
    The JSON summary: index, started (UTC), sources, added, updated, removed, unchanged,
    failed, failures (path and error of each failed file), skipped (folders that could not
    be listed, whose indexed files are kept, and non-regular files), curves, seconds; and shrink
    ({removed, of, allowed}) when the build removes (or refused to remove) more than half;
    with --graph, also graph: {k, searched, updated, kept, processes, seconds, where,
    scheduler, workers} (rows searched in the whole index, copied rows a new curve entered,
    copied rows kept as they were, worker processes that searched: --jobs, 0 when this
    process or a cluster did; where: local or cluster, and the cluster's scheduler and
    workers). With --scheduler the graph's rows are searched by the cluster's workers,
    which read them from the new index file (beside the index, closed meanwhile): the
    index's folder must be on storage every worker sees.

    Exit codes: 0 every file indexed, 3 index written but some files failed,
    1 nothing written (bad arguments, lock held, unreadable old index, shrink refused,
    workers kept dying), 130 interrupted (SIGINT), 143 terminated (SIGTERM).

    \b
    Examples:
      nfdmatch index build sample_curves/library --index demo.h5
      nfdmatch index build --index demo.h5          # again, from its recorded sources
      nfdmatch index build scans/ --glob '*.vtp' --jobs 2 --wait 600 --format json
      nfdmatch index build library/ --index library.h5 --graph
      nfdmatch index build library/ --index library.h5 --graph 10 --elastic
      nfdmatch index build /shared/scans --index /shared/scans.h5 --scheduler tcp://head:8786
      nfdmatch index build --index /shared/scans.h5 --graph 10 --scheduler tcp://head:8786
    """
    if "-" in sources:
        raise click.UsageError(
            "index build reads files and folders, not stdin ('-'): an index records each file to "
            "rebuild it incrementally; save the curve to a file and index that"
        )
    graph_k = _graph_asked(graph_k, graph_elastic)
    started = datetime.now(timezone.utc)
    options = dict(
        **descriptor, glob=glob_pattern, input_format=input_format, rebuild=rebuild, dry_run=dry_run, wait=wait,
        allow_shrink=allow_shrink, graph=graph_k, strict=strict, sections=sections,
    )  # fmt: skip
    report = _run_build(
        list(sources), index_path, options, jobs, file_timeout, (scheduler, scheduler_timeout), output_format, started
    )
    _say_build_result(report, index_path, dry_run, allow_shrink, output_format, started, strict)


def _graph_asked(graph_k: int | None, elastic: bool) -> int | GraphSpec | None:
    """The build's ``graph`` of --graph K and --elastic: K (exact), a ``GraphSpec`` of fused
    distances, or None (keep the index's)."""
    if elastic and not graph_k:
        raise click.UsageError("--elastic needs --graph K: it says what the graph's distances are")
    if not elastic:
        return graph_k
    from ..index.graph import GraphSpec

    return GraphSpec(graph_k, "fused")


def _run_build(
    sources: list[str],
    index_path: str,
    options: dict[str, Any],
    jobs: int | None,
    file_timeout: float,
    cluster_at: tuple[str | None, float],
    output_format: str,
    started: datetime,
) -> BuildReport:
    """The build, here or on the cluster ``cluster_at`` (``--scheduler`` and its timeout),
    under a progress bar. A build that fails or is interrupted still prints its JSON line
    (with ``--format json``) before the error goes on."""
    from ..errors import NfdError
    from ..index import build_index

    scheduler, scheduler_timeout = cluster_at
    cluster = None
    progress, finish_bar = progress_bar("indexing files")
    graph_bar = []

    def graph_progress(done: int, total: int | None) -> None:  # the files' bar gives way to the graph's (one at a time)
        if not graph_bar:
            finish_bar()
            graph_bar.extend(progress_bar("searching the graph"))
        if graph_bar[0] is not None:
            graph_bar[0](done, total)

    try:
        if scheduler and not options["dry_run"]:  # a dry run reads locally: nothing for workers to do
            if jobs is not None:
                note("--jobs is ignored with --scheduler (the cluster's workers compute the files)")
            cluster = open_cluster(scheduler, scheduler_timeout)
        if cluster is None:
            return build_index(
                sources,
                index_path,
                jobs=jobs,
                file_timeout=file_timeout or None,
                progress=progress,
                graph_progress=graph_progress,
                **options,
            )
        return cluster.build_index(sources, index_path, progress=progress, graph_progress=graph_progress, **options)
    except (NfdError, KeyboardInterrupt) as exc:
        _say_failed_build(exc, index_path, started, output_format)
        raise
    finally:
        finish_bar()
        if graph_bar:
            graph_bar[1]()
        if cluster is not None:
            cluster.close()


def _say_build_result(
    report: BuildReport,
    index_path: str,
    dry_run: bool,
    allow_shrink: bool,
    output_format: str,
    started: datetime,
    strict: bool = False,
) -> None:
    """Notices and failures on stderr, the summary (or a dry run's changes) on stdout, and
    the exit: 2 for a dry run its build would refuse, else by the failed files."""
    for notice in report.notices:
        note(notice, prefix="Notice: ")
    for _path, message in report.skipped + report.failures:
        error(message)
    if output_format == "json":
        deliver(json.dumps(_build_summary(report, index_path, started, allow_shrink)) + "\n", None)
    else:
        if dry_run:
            from ..names import decode_name
            from .output import tsv_field

            changed = [(action, path) for action, path in report.changes if action != "unchanged"]
            deliver("".join(f"{action}\t{tsv_field(decode_name(path))}\n" for action, path in changed), None)
        _say_build(report, index_path, allow_shrink, strict)
    if dry_run and report.shrink and not allow_shrink:  # the build would refuse: so does its dry run
        error(
            f"{index_path}: a build would refuse to remove {report.shrink[0]} of {report.shrink[1]} files "
            f"(pass --allow-shrink)"
        )
        sys.exit(EXIT_ERROR)
    # a skipped folder or FIFO counts as a failed input: exit 3, so cron mails it (a dry run
    # exits as its build would)
    finish(
        report.failed + len(report.skipped),
        report.added + report.updated + report.unchanged + report.failed + len(report.skipped),
        "files",
    )


def _say_failed_build(exc: BaseException, index_path: str, started: datetime, output_format: str) -> None:
    """With --format json, the JSON line of a build that wrote nothing on stdout (cron logs
    one line per run: it says why nothing was written); the error itself goes on."""
    if output_format == "json":
        deliver(json.dumps(_failed_build_record(exc, index_path, started)) + "\n", None)


def _failed_build_record(exc: BaseException, index_path: str, started: datetime) -> dict:
    """The JSON line of a build that wrote nothing (an error, an interruption)."""
    from ..errors import ShrinkRefusedError

    record = {"index": index_path, "started": started.strftime("%Y-%m-%dT%H:%M:%SZ"), "written": False}
    if isinstance(exc, KeyboardInterrupt):
        record["error"] = "terminated (SIGTERM)" if type(exc).__name__ == "Terminated" else "interrupted"
    else:
        record["error"] = str(exc)
    if isinstance(exc, ShrinkRefusedError):
        record["refused"] = str(exc)
        record["shrink"] = {"removed": exc.removed, "of": exc.of, "allowed": False}
    return record


def _build_summary(report: BuildReport, index_path: str, started: datetime, allow_shrink: bool) -> dict:
    """The JSON line of a build that ran (or of its dry run)."""
    summary = {
        "index": index_path,
        "started": started.strftime("%Y-%m-%dT%H:%M:%SZ"),
        "sources": report.sources,
        "added": report.added,
        "updated": report.updated,
        "removed": report.removed,
        "unchanged": report.unchanged,
        "failed": report.failed,
        "failures": [{"path": path, "error": message} for path, message in report.failures],
        "skipped": [{"path": path, "error": message} for path, message in report.skipped],
        "curves": report.curves,
        "seconds": round(report.seconds, 3),
    }
    if report.shrink:
        summary["shrink"] = {"removed": report.shrink[0], "of": report.shrink[1], "allowed": bool(allow_shrink)}
    if report.graph.k:
        g = report.graph
        summary["graph"] = {
            "distance": g.distance,
            "k": g.k,
            "searched": g.searched,
            "updated": g.updated,
            "kept": g.kept,
            "processes": g.processes,
            "seconds": round(g.seconds, 3),
            # where the rows were searched: here (this process, or --jobs forked ones), or
            # by the workers of a Dask cluster (--scheduler)
            "where": "cluster" if g.scheduler else "local",
            "scheduler": g.scheduler or None,
            "workers": g.workers,
        }
    if report.dry_run:
        summary["dry_run"] = True
        summary["changes"] = [{"action": a, "path": p} for a, p in report.changes if a != "unchanged"]
    return summary


def _say_build(report: BuildReport, index_path: str, allow_shrink: bool, strict: bool = False) -> None:
    """The build's summary in words, on stderr."""
    verb = (
        "would change"
        if report.dry_run
        else (
            f"indexed into {index_path}"
            if report.written
            else (
                f"{index_path} not written (--strict)" if strict and report.failures else f"{index_path} is up to date"
            )
        )
    )
    shrunk = (
        ""
        if not report.shrink
        else (
            f" ({report.shrink[0]} of {report.shrink[1]} files removed: --allow-shrink)"
            if allow_shrink
            else f" (a build would refuse to remove {report.shrink[0]} of {report.shrink[1]} files)"
        )
    )
    say(
        f"{verb}: {report.added} added, {report.updated} updated, {report.removed} removed, "
        f"{report.unchanged} unchanged, {report.failed} failed files; {report.curves} curves; "
        f"{report.seconds:.2f} s{shrunk}"
    )
    if report.graph.k:
        g = report.graph
        kind = " (fused distances)" if g.distance == "fused" else ""
        say(
            f"graph of {g.k} neighbours{kind}: {g.searched} rows searched, {g.updated} updated by new curves, "
            f"{g.kept} kept; {g.seconds:.2f} s" + _graph_where(g)
        )


def _graph_where(g: GraphStats) -> str:
    """Where the graph's rows were searched, for the summary line ("" : this process)."""
    if g.scheduler:
        return f" on the cluster at {g.scheduler} ({g.workers} worker{'s' if g.workers != 1 else ''})"
    return f" on {g.processes} processes" if g.processes else ""


def _edit_command(name: str, verb: str, doc: str) -> Callable[[Callable[..., BuildReport]], click.Command]:
    """``index add`` and ``index remove``: the same options, one library function each."""

    def decorate(run: Callable[..., BuildReport]) -> click.Command:
        @index.command(name, help=doc)
        @click.argument("files", nargs=-1, required=True, metavar="FILE...")
        @index_option
        @_JOBS
        @_WAIT
        @click.option("--strict", is_flag=True, help="When any file fails, write nothing (exit 3).")
        @input_format_option
        @_summary_format(" of the summary (json: one line, as index build's)")
        def command(
            files: tuple[str, ...],
            index_path: str,
            jobs: int | None,
            wait: float,
            strict: bool,
            input_format: str | None,
            output_format: str,
        ) -> None:
            started = datetime.now(timezone.utc)
            if "-" in files:
                raise click.UsageError(f"index {name} takes files and folders, not stdin ('-')")
            progress, finish_bar = progress_bar(verb)
            try:
                report = run(
                    list(files), index_path, jobs=jobs, wait=wait, strict=strict, input_format=input_format,
                    progress=progress,
                )  # fmt: skip
            except (NfdError, KeyboardInterrupt) as exc:
                _say_failed_build(exc, index_path, started, output_format)
                raise
            finally:
                finish_bar()
            _say_build_result(report, index_path, False, True, output_format, started, strict)

        return command

    return decorate


@_edit_command(
    "add",
    "adding files",
    """Add FILE... (files or folders) to the index; every other file stays.

    The recorded sources follow (a FILE outside them becomes one of them, an excluded one
    is excluded no more), so the next `nfdmatch index build --index X` without SOURCE
    agrees. A missing index is built from FILE... . Exit codes as index build's.

    \b
    Example:
      nfdmatch index add extra/one.csv --index lib.h5
    """,
)
def index_add(files: list[str], index_path: str, **options: Any) -> BuildReport:
    from ..index.build import add_files

    return add_files(files, index_path, **options)


@_edit_command(
    "remove",
    "removing files",
    """Remove FILE... (files, or folders: every file below) from the index; every other
    file stays.

    The recorded sources follow (a FILE that is a source is dropped, a file found in a
    source folder is recorded as excluded from its walk), so the next `nfdmatch index
    build --index X` without SOURCE agrees. A FILE that is not in the index is an error.
    The file itself is not touched.

    \b
    Example:
      nfdmatch index remove lib/old/one.csv --index lib.h5
    """,
)
def index_remove(files: list[str], index_path: str, **options: Any) -> BuildReport:
    from ..index.build import remove_files

    return remove_files(files, index_path, **options)


@index.command("info")
@index_option
@format_option(("text", "json"), help_extra=" [default: by the extension of -o (.json, .txt), else text]")
@output_option()
def index_info(index_path: str, output_format: str | None, output: str | None) -> None:
    """Describe an index: sources, files, curves, failed files with reasons, parameters, format, times, size.

    `graph` is the number of nearest curves stored per curve for `query --rerank` (0: no
    graph; `index build --graph` adds it); `objects` the number of meshes indexed as
    objects (their contours are among the curves).

    \b
    Example:
      nfdmatch index info --index demo.h5 --format json -o info.json
    """
    from ..index import open_index

    from ..index.graph import graph_k

    output_format = resolve_format(output_format, output, ("text", "json"), terminal="text", piped="text")
    with open_index(index_path) as idx:
        info = idx.info()
        info["graph"] = graph_k(idx)  # neighbours per curve stored for --rerank; 0: none
        info["objects"] = len(idx.object_ids())  # meshes indexed as objects (docs/objects.md)
        if info["graph"]:
            info["graph_distance"] = idx.graph_distance()
            if idx.graph_fused_version() is not None:  # the fused distance's definition (docs/elastic.md)
                info["graph_fused_version"] = idx.graph_fused_version()
        if idx.excluded():  # left out of the sources' walk by `index remove`
            info["excluded"] = idx.excluded()
    if output_format == "json":
        deliver(json.dumps(info, indent=2) + "\n", output)
        return
    sources = info.get("sources")
    lines = [f"path\t{info.get('path')}", f"sources\t{'(not recorded)' if sources is None else ' '.join(sources)}"]
    if info.get("excluded"):
        lines.append(f"excluded\t{' '.join(info['excluded'])}")
    lines += [
        f"{key}\t{info.get(key)}"
        for key in (
            "format",
            "format_version",
            "metadata",
            "nfdmatch_version",
            "files",
            "curves",
            "samples",
            "harmonics",
            "scale",
            "graph",
            "objects",
            *(["graph_distance"] if "graph_distance" in info else []),
            *(["graph_fused_version"] if "graph_fused_version" in info else []),
            "created",
            "updated",
            "size_bytes",
        )
    ]
    failed = info.get("failed", [])
    lines.append(f"failed\t{len(failed)}")
    lines += [f"  {item['path']}\t{item['error']}" for item in failed]
    deliver("".join(line + "\n" for line in lines), output)


@index.command("verify")
@index_option
@format_option(("text", "json"), default="text")
def index_verify(index_path: str, output_format: str) -> None:
    """Check a whole index: every checksum, every value finite, the search cells consistent.

    Reads every chunk of every dataset (a query reads and checks only what it needs) and
    lists what is bad on stdout, one line per finding: dataset, rows (or positions), what.
    A summary goes to stderr. An index of format 1 (or one written before checksums) has
    no checksums to check: verify says so and checks the rest.

    Exit codes: 0 the index is sound, 1 something is bad (or the file is not an index).

    \b
    Example:
      nfdmatch index verify --index demo.h5
    """
    from ..index.verify import verify_index

    report = verify_index(index_path)
    if output_format == "json":
        deliver(
            json.dumps(
                {
                    "index": report.path,
                    "ok": report.ok,
                    "format_version": report.format_version,
                    "checksums": report.checksums,
                    "datasets": report.datasets,
                    "curves": report.curves,
                    "findings": [{"dataset": f.dataset, "rows": f.rows, "what": f.what} for f in report.findings],
                }
            )
            + "\n",
            None,
        )
    else:
        deliver("".join(f"bad\t{f.dataset}\t{f.rows}\t{f.what}\n" for f in report.findings), None)
    if not report.checksums:
        note(
            f"{report.path} has no checksums (format {report.format_version}, or written before they were "
            f"added): values and consistency checked only; `nfdmatch index build --rebuild` adds them"
        )
    if report.ok:
        say(
            f"{report.path}: ok ({report.datasets} datasets, {report.curves} curves"
            f"{', every checksum verified' if report.checksums else ''})"
        )
        return
    error(
        f"{report.path}: {len(report.findings)} problem{'s' if len(report.findings) != 1 else ''} found "
        f"in {len({f.dataset for f in report.findings})} dataset(s); rebuild it with "
        f"`nfdmatch index build --rebuild`"
    )
    sys.exit(EXIT_NOTHING)  # as cmp and diff: 1 the answer "they differ", 2 trouble


@index.command("ls")
@index_option
@click.option("--status", type=click.Choice(["ok", "failed"]), default=None, help="Only files with this status.")
@click.option("--curves", "list_curves", is_flag=True, help="One row per curve (id, file) instead of per file.")
@rows_format_option
@output_option()
def index_ls(
    index_path: str, status: str | None, list_curves: bool, output_format: str | None, output: str | None
) -> None:
    """List the files of an index (file, status, curves, error) or, with --curves, its curves (id, file).

    \b
    Examples:
      nfdmatch index ls --index demo.h5
      nfdmatch index ls --index demo.h5 --status failed --format json
      nfdmatch index ls --index demo.h5 --curves -o ids.csv
    """
    from ..index import open_index

    output_format = resolve_format(output_format, output)
    with open_index(index_path) as idx:
        files = [r for r in idx.files() if status is None or r.status == status]
        if list_curves:
            ids = idx.ids()
            rows: list[dict[str, Any]] = [
                {"id": ids[row], "file": r.path}
                for r in files
                for row in range(r.curve_start, r.curve_start + r.curve_count)
            ]
            columns = ["id", "file"]
        else:
            rows = [{"file": r.path, "status": r.status, "curves": r.curve_count, "error": r.error} for r in files]
            columns = ["file", "status", "curves", "error"]
    write_rows(rows, columns, output_format, output, names=("id", "file"))
