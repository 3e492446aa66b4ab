"""The index commands: ``index build``, ``index info``, ``index ls``, ``index export`` and ``query``."""

from __future__ import annotations

import json
import sys
from datetime import datetime, timezone

import click

from ..defaults import DEFAULT_GRAPH_K, DEFAULT_RERANK_DEPTH
from ..matching import DEFAULT_METHOD
from .common import (
    EXIT_ERROR,
    deliver,
    error,
    exclude_self_option,
    format_option,
    finish,
    index_option,
    input_format_option,
    match_columns,
    match_row,
    matching,
    matching_options,
    note,
    optional_descriptor_options,
    output_option,
    progress_bar,
    read_inputs,
    rows_format_option,
    say,
    write_rows,
)
from .cluster import open_cluster, ranges_option, scheduler_options
from .group import main


@main.group()
def index():
    """Build and inspect the HDF5 index of curve descriptors.

    \b
    Examples:
      nfdmatch index build curves/ --index curves.h5
      nfdmatch index info --index curves.h5
      nfdmatch index ls --index curves.h5 --status failed
      nfdmatch index verify --index curves.h5
      nfdmatch index export --index curves.h5 -o descriptors.npz
    """


@index.command("build")
@click.argument("sources", nargs=-1, required=False, metavar="[SOURCE...]")
@index_option
@click.option("--glob", "glob_pattern", default=None, help="Only files in folders whose name matches, e.g. '*.obj'.")
@click.option("--rebuild", is_flag=True, help="Recompute every curve, even unchanged files.")
@click.option("--dry-run", is_flag=True, help="Print what would change (on stdout) and write nothing.")
@click.option("--jobs", "-j", type=click.IntRange(min=1), default=None, help="Parallel workers [default: all cores].")
@click.option(
    "--wait",
    type=click.FloatRange(min=0),
    default=0.0,
    show_default=True,
    help="Seconds to wait for another build's lock (0: fail at once).",
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
    "then put --graph after the sources or before another option); 0 drops the graph "
    "[default: keep the index's graph, if it has one].",
)
@optional_descriptor_options("the index's")
@input_format_option
@scheduler_options
@format_option(
    ("text", "json"), default="text", help_extra=": text, a summary on stderr; json, one summary object on stdout"
)
def index_build(
    sources,
    index_path,
    glob_pattern,
    rebuild,
    dry_run,
    jobs,
    wait,
    allow_shrink,
    file_timeout,
    graph_k,
    samples,
    harmonics,
    scale,
    input_format,
    scheduler,
    scheduler_timeout,
    output_format,
):
    """Index the curves in SOURCE... (files or folders, recursively).

    Without SOURCE, the sources (and --glob) of the index's last build are re-scanned:
    the index records them. Files are stored relative to the index's folder (absolute
    when outside it), so the same files are the same rows whatever the working
    directory or the spelling of the sources.

    Incremental: unchanged files (same size and mtime, or same SHA-256) are not
    recomputed, changed files are, files no longer under the sources are removed. A
    build that would remove more than half of the index's files, or all of them (an
    empty or unmounted folder), refuses (exit 1) unless --allow-shrink is given.
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
    with --graph, also graph: {k, searched, updated, kept, seconds} (rows searched in the whole index, copied
    rows a new curve entered, copied rows kept as they were).

    Exit codes: 0 every file indexed, 3 index written but some files failed,
    1 nothing written (bad arguments, lock held, unreadable old index, shrink refused,
    workers kept dying), 130 interrupted (SIGINT), 143 terminated (SIGTERM).

    \b
    Examples:
      nfdmatch index build sample_curves/library --index demo.h5
      nfdmatch index build --index demo.h5          # again, from its recorded sources
      nfdmatch index build scans/ --glob '*.vtp' --jobs 2 --wait 600 --format json
      nfdmatch index build library/ --index library.h5 --graph
      nfdmatch index build /shared/scans --index /shared/scans.h5 --scheduler tcp://head:8786
    """
    from ..errors import ShrinkRefusedError
    from ..index import build_index

    started = datetime.now(timezone.utc)
    cluster = None
    if scheduler and not dry_run:  # a dry run only plans: nothing for workers to do
        if jobs is not None:
            note("--jobs is ignored with --scheduler (the cluster's workers compute the files)")
        cluster = open_cluster(scheduler, scheduler_timeout)
    progress, finish_bar = progress_bar("indexing files")
    try:
        options = dict(
            samples=samples,
            harmonics=harmonics,
            scale=scale,
            glob=glob_pattern,
            input_format=input_format,
            rebuild=rebuild,
            dry_run=dry_run,
            wait=wait,
            progress=progress,
            allow_shrink=allow_shrink,
            graph=graph_k,
        )
        if cluster is None:
            report = build_index(list(sources), index_path, jobs=jobs, file_timeout=file_timeout or None, **options)
        else:
            report = cluster.build_index(list(sources), index_path, **options)
    except ShrinkRefusedError as exc:
        if output_format == "json":  # cron logs the summary: it says what was refused
            deliver(
                json.dumps(
                    {
                        "index": index_path,
                        "started": started.strftime("%Y-%m-%dT%H:%M:%SZ"),
                        "refused": str(exc),
                        "written": False,
                        "shrink": {"removed": exc.removed, "of": exc.of, "allowed": False},
                    }
                )
                + "\n",
                None,
            )
        raise
    finally:
        finish_bar()
        if cluster is not None:
            cluster.close()
    for notice in report.notices:
        note(notice, prefix="Notice: ")
    for _path, message in report.skipped + report.failures:
        error(message)
    if output_format == "json":
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
                "k": g.k,
                "searched": g.searched,
                "updated": g.updated,
                "kept": g.kept,
                "seconds": round(g.seconds, 3),
            }
        if dry_run:
            summary["dry_run"] = True
            summary["changes"] = [{"action": a, "path": p} for a, p in report.changes if a != "unchanged"]
        deliver(json.dumps(summary) + "\n", None)
    else:
        if dry_run:
            deliver("".join(f"{action}\t{path}\n" for action, path in report.changes if action != "unchanged"), None)
        verb = (
            "would change"
            if dry_run
            else (f"indexed into {index_path}" if report.written else f"{index_path} is up to date")
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
            say(
                f"graph of {g.k} neighbours: {g.searched} rows searched, {g.updated} updated by new curves, "
                f"{g.kept} kept; {g.seconds:.2f} s"
            )
    if not dry_run:
        # a skipped folder or FIFO counts as a failed input: exit 3, so cron mails it
        finish(
            report.failed + len(report.skipped),
            report.added + report.updated + report.unchanged + report.failed + len(report.skipped),
            "files",
        )


@index.command("info")
@index_option
@format_option(("text", "json"), default="text")
@output_option()
def index_info(index_path, output_format, output):
    """Describe an index: sources, files, curves, failed files with reasons, parameters, format, times, size.

    `graph` is the number of nearest curves stored per curve for `query --rerank` (0: no
    graph; `index build --graph` adds it).

    \b
    Example:
      nfdmatch index info --index demo.h5 --format json -o info.json
    """
    from ..index import open_index

    from ..index.graph import graph_k

    with open_index(index_path) as idx:
        info = idx.info()
        info["graph"] = graph_k(idx)  # neighbours per curve stored for --rerank; 0: none
    if output_format == "json":
        deliver(json.dumps(info, indent=2) + "\n", output)
        return
    sources = info.get("sources")
    lines = [f"path\t{info.get('path')}", f"sources\t{'(not recorded)' if sources is None else ' '.join(sources)}"]
    lines += [
        f"{key}\t{info.get(key)}"
        for key in (
            "format",
            "format_version",
            "nfdmatch_version",
            "files",
            "curves",
            "samples",
            "harmonics",
            "scale",
            "graph",
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
def index_verify(index_path, output_format):
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
    sys.exit(EXIT_ERROR)


@index.command("ls")
@index_option
@click.option("--status", type=click.Choice(["ok", "failed"]), default=None, help="Only files with this status.")
@click.option("--curves", "list_curves", is_flag=True, help="One row per curve (id, file) instead of per file.")
@rows_format_option
@output_option()
def index_ls(index_path, status, list_curves, output_format, output):
    """List the files of an index (file, status, curves, error) or, with --curves, its curves (id, file).

    \b
    Examples:
      nfdmatch index ls --index demo.h5
      nfdmatch index ls --index demo.h5 --status failed --format json
      nfdmatch index ls --index demo.h5 --curves -o ids.csv
    """
    from ..index import open_index

    with open_index(index_path) as idx:
        files = [r for r in idx.files() if status is None or r.status == status]
        if list_curves:
            ids = idx.ids()
            rows = [
                {"id": ids[row], "file": r.path}
                for r in files
                for row in range(r.curve_start, r.curve_start + r.curve_count)
            ]
            columns = ["id", "file"]
        else:
            rows = [{"file": r.path, "status": r.status, "curves": r.curve_count, "error": r.error} for r in files]
            columns = ["file", "status", "curves", "error"]
    write_rows(rows, columns, output_format, output)


@index.command("export")
@index_option
@format_option(("csv", "jsonl", "npz"), help_extra=" [default: by the extension of -o]")
@output_option(help="The file to write (.csv, .jsonl or .npz), whole and only on success.", required=True)
def index_export(index_path, output_format, output):
    """Export the stored descriptors and poses of every curve, for use without h5py.

    Per curve: id, file, the index's samples, harmonics and scale_mode, then scale and
    centroid (input units), rotation (3 x 3, as in nfdmatch.Descriptors), plane_degenerate
    and the normalized coefficients of frequencies +1..+K (x, y, z; those of -k are their
    complex conjugates). CSV flattens them into columns (centroid_x, rotation_01,
    k+1_x_re, ...); JSONL nests them; NPZ holds the arrays ids (n,), files (n,), scale (n,),
    plane_degenerate (n,), centroid (n, 3), rotation (n, 3, 3), coefficients (n, K, 3)
    complex128, frequencies (K,) and the parameters.

    \b
    Example:
      nfdmatch index export --index demo.h5 -o demo.npz
    """
    import io
    import os

    import numpy as np

    from ..index import open_index

    fmt = output_format or {".csv": "csv", ".jsonl": "jsonl", ".npz": "npz"}.get(os.path.splitext(output)[1].lower())
    if fmt is None:
        raise click.UsageError(f"cannot tell the export format from {output!r}: use .csv, .jsonl or .npz, or --format")
    with open_index(index_path) as idx:
        rows = idx.read_rows(
            0, idx.n_curves, ["coefficients", "rotation", "centroid", "scale", "plane_degenerate", "file"]
        )
        ids = idx.ids()
        paths = [r.path for r in idx.files()]
        params = {"samples": idx.samples, "harmonics": idx.harmonics, "scale_mode": idx.scale_mode}
    files = [paths[i] for i in rows["file"]]
    frequencies = np.arange(1, params["harmonics"] + 1)
    if fmt == "npz":
        buf = io.BytesIO()
        np.savez_compressed(
            buf,
            ids=np.array(ids, dtype=str),
            files=np.array(files, dtype=str),
            scale=rows["scale"],
            plane_degenerate=rows["plane_degenerate"],
            centroid=rows["centroid"],
            rotation=rows["rotation"],
            coefficients=rows["coefficients"],
            frequencies=frequencies,
            **{k: np.array(v) for k, v in params.items()},
        )
        _deliver_bytes(buf.getvalue(), output)
        return
    records = []
    for i, curve_id in enumerate(ids):
        records.append(
            {
                "id": curve_id,
                "file": files[i],
                **params,
                "scale": float(rows["scale"][i]),
                "plane_degenerate": bool(rows["plane_degenerate"][i]),
                "centroid": rows["centroid"][i].tolist(),
                "rotation": rows["rotation"][i].tolist(),
                "frequencies": frequencies.tolist(),
                "coefficients": [[[float(c.real), float(c.imag)] for c in row] for row in rows["coefficients"][i]],
            }
        )
    if fmt == "jsonl":
        columns = list(records[0]) if records else ["id"]
        write_rows(records, columns, "jsonl", output)
        return
    flat = []
    for r in records:
        row = {k: r[k] for k in ("id", "file", "samples", "harmonics", "scale_mode", "scale", "plane_degenerate")}
        row.update({f"centroid_{ax}": v for ax, v in zip("xyz", r["centroid"])})
        row.update({f"rotation_{i}{j}": r["rotation"][i][j] for i in range(3) for j in range(3)})
        for f, coeff in zip(r["frequencies"], r["coefficients"]):
            for ax, (re, im) in zip("xyz", coeff):
                row[f"k{f:+d}_{ax}_re"] = re
                row[f"k{f:+d}_{ax}_im"] = im
        flat.append(row)
    write_rows(flat, list(flat[0]) if flat else ["id"], "csv", output)


def _deliver_bytes(data: bytes, output: str) -> None:
    from .common import detail, write_if_changed

    detail(f"wrote {output}" if write_if_changed(output, data) else f"{output} unchanged")


@main.command()
@click.argument("queries", nargs=-1, required=True, metavar="QUERY...")
@index_option
@click.option("--top", type=click.IntRange(min=1), default=10, show_default=True, help="Matches per query.")
@click.option("--max-distance", type=click.FloatRange(min=0), default=None, help="Only list matches at most this far.")
@click.option("--glob", "glob_pattern", default=None, help="Only query files in folders whose name matches.")
@click.option("--details", is_flag=True, help="Add the columns shift, reversed, mirrored.")
@exclude_self_option
@click.option(
    "--exhaustive",
    is_flag=True,
    help="Compute every exact distance, no pruning (to check a result: the pruned search "
    "returns the same rows and distances).",
)
@click.option("--stats", "show_stats", is_flag=True, help="Print on stderr how many exact distances the search needed.")
@click.option(
    "--rerank",
    is_flag=True,
    help="Order the matches by a diffusion over the index's neighbour graph (needs `index build "
    "--graph`); adds the column score (higher is closer), distance stays the exact distance.",
)
@click.option(
    "--rerank-depth",
    type=click.IntRange(min=DEFAULT_RERANK_DEPTH),
    default=DEFAULT_RERANK_DEPTH,
    show_default=True,
    metavar="M",
    help="With --rerank: the query's exact top M that the diffusion re-orders.",
)
@matching_options
@input_format_option
@scheduler_options
@ranges_option
@rows_format_option
@output_option()
def query(
    queries,
    index_path,
    top,
    max_distance,
    glob_pattern,
    details,
    exclude_self_,
    exhaustive,
    show_stats,
    rerank,
    rerank_depth,
    method,
    strict_direction,
    mirror,
    input_format,
    scheduler,
    scheduler_timeout,
    ranges,
    output_format,
    output,
):
    """Find the curves of the index most similar to each curve in QUERY... .

    QUERY: files (FILE#I for one curve of a multi-curve file; `-` for stdin) or folders;
    every curve in them is a query, answered with the index's own samples, harmonics and
    scale. Rows: query, rank, match, distance (ties ordered by id). The search is exact:
    rows are visited in increasing order of proven lower bounds (cells of the index, then
    invariant features, then the first harmonics) and the search stops when the next bound
    exceeds the K-th distance; --exhaustive computes every distance instead (same answer).
    Inputs that cannot be read are named on stderr and the others answered (exit 3).

    --rerank: the query's exact top M (--rerank-depth) re-ordered by a personalised-PageRank
    diffusion over the whole neighbour graph stored in the index (the query joins it through
    its exact 8 nearest), then the top K by the diffused score (docs/rerank.md). Rows gain
    the column score; deterministic.

    \b
    Examples:
      nfdmatch query sample_curves/queries/trefoil-posed.obj --index demo.h5 --top 5
      nfdmatch query new_scans/ --index curves.h5 --top 1 --format jsonl -o matches.jsonl
      nfdmatch query library/ --index library.h5 --exclude-self --top 3
      nfdmatch query library/ --index library.h5 --exclude-self --rerank --top 3
      nfdmatch query batch/ --index /shared/scans.h5 --scheduler tcp://head:8786 -o matches.csv
    """
    from ..index import FORMAT_VERSION, open_index
    from ..search import search_index

    if rerank:
        for given, name in (
            (exhaustive, "--exhaustive"),
            (max_distance is not None, "--max-distance"),
            (method != DEFAULT_METHOD, f"--method {method}"),
            (strict_direction, "--strict-direction"),
            (mirror, "--mirror"),
        ):
            if given:
                raise click.UsageError(
                    f"--rerank cannot be combined with {name}: the stored graph holds exact, "
                    f"direction-invariant distances without mirror images"
                )
        if top > rerank_depth:
            raise click.UsageError(f"--top {top} is more than --rerank-depth {rerank_depth}")
        if scheduler:
            raise click.UsageError(
                "--rerank runs on this machine (the graph and the top M are small): drop --scheduler"
            )
    elif rerank_depth != DEFAULT_RERANK_DEPTH:
        raise click.UsageError("--rerank-depth needs --rerank")

    with open_index(index_path) as idx:
        if idx.format_version < FORMAT_VERSION and not exhaustive:
            note(
                f"{idx.path} is an index of format {idx.format_version}, without search cells: every row is "
                f"bounded for each query (slower on large indexes); `nfdmatch index build --index "
                f"{idx.path}` upgrades it"
            )
        inputs = read_inputs(queries, glob=glob_pattern, input_format=input_format)
        if ranges is not None and not scheduler:
            raise click.UsageError("--ranges needs --scheduler")
        cluster = open_cluster(scheduler, scheduler_timeout) if scheduler else None
        progress, finish_bar = progress_bar("searching")
        try:
            if rerank:
                from ..search.rerank import rerank_index

                results, stats = rerank_index(
                    idx,
                    inputs.curves,
                    top=top,
                    depth=rerank_depth,
                    progress=progress,
                    exclude_self=exclude_self_,
                )
            else:
                extra = {} if cluster is None else {"parts": ranges}
                run = search_index if cluster is None else cluster.search_index
                results, stats = run(
                    idx,
                    inputs.curves,
                    top=top,
                    max_distance=max_distance,
                    progress=progress,
                    prune=not exhaustive,
                    exclude_self=exclude_self_,
                    **extra,
                    **matching(method, strict_direction, mirror),
                )
        finally:
            finish_bar()
            if cluster is not None:
                cluster.close()
    columns = match_columns(details)
    if rerank:
        columns.insert(columns.index("distance") + 1, "score")
    write_rows(
        [match_row(q.id, m) for q, res in zip(inputs.curves, results) for m in res],
        columns,
        output_format,
        output,
        group_by="query",
    )
    if show_stats:
        say(
            f"{stats.queries} queries x {stats.rows} rows: {stats.exact} exact distances "
            f"({stats.exact_fraction:.2%}), {stats.seconds:.3f} s"
            + (
                ""
                if not stats.pruned
                else f"; per query: {stats.per_query(stats.scanned):.0f} rows bounded in "
                f"{stats.per_query(stats.cells):.1f} of {stats.cell_count} cells, "
                f"{stats.per_query(stats.truncated):.0f} truncated-harmonic bounds "
                f"(+{stats.per_query(stats.fine):.0f} finer), "
                f"{stats.per_query(stats.exact):.0f} exact distances, "
                f"{stats.per_query(stats.bytes_read) / 2**20:.2f} MiB read"
            )
            + (f"; kernels: {stats.kernels}" if stats.kernels else "")
        )
    inputs.finish()
