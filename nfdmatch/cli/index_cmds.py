"""The index commands: ``index build``, ``index info``, ``index ls``, ``index export`` and ``query``."""

from __future__ import annotations

import json
from datetime import datetime, timezone

import click

from .common import (deliver, error, exclude_self, exclude_self_option, format_option,
                     finish, index_option, input_format_option, match_columns, matching, matching_options, note,
                     optional_descriptor_options, output_option, progress_bar, read_inputs, rows_format_option,
                     say, write_rows)
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
      nfdmatch index export --index curves.h5 -o descriptors.npz
    """


@index.command("build")
@click.argument("sources", nargs=-1, required=True, metavar="SOURCE...")
@index_option
@click.option("--glob", "glob_pattern", default=None, help="Only files in folders whose name matches, e.g. '*.obj'.")
@click.option("--rebuild", is_flag=True, help="Recompute every curve, even unchanged files.")
@click.option("--dry-run", is_flag=True, help="Print what would change (on stdout) and write nothing.")
@click.option("--jobs", "-j", type=click.IntRange(min=1), default=None, help="Parallel workers [default: all cores].")
@click.option("--wait", type=click.FloatRange(min=0), default=0.0, show_default=True,
              help="Seconds to wait for another build's lock (0: fail at once).")
@optional_descriptor_options("the index's")
@input_format_option
@scheduler_options
@format_option(("text", "json"), default="text",
               help_extra=": text, a summary on stderr; json, one summary object on stdout")
def index_build(sources, index_path, glob_pattern, rebuild, dry_run, jobs, wait, samples, harmonics, scale,
                input_format, scheduler, scheduler_timeout, output_format):
    """Index the curves in SOURCE... (files or folders, recursively).

    Incremental: unchanged files (same size and mtime, or same SHA-256) are not
    recomputed, changed files are, files no longer under the sources are removed.
    The index is written to a temporary file and moved into place when complete, so
    an interrupted build leaves the previous index intact and queries keep working.
    Bad files are named on stderr and recorded as failed; the rest is indexed.
    The JSON summary: index, started (UTC), added, updated, removed, unchanged, failed,
    failures (path and error of each failed file), curves, seconds.

    Exit codes: 0 every file indexed, 3 index written but some files failed,
    1 nothing written (bad arguments, lock held, unreadable old index).

    \b
    Examples:
      nfdmatch index build sample_curves/library --index demo.h5
      nfdmatch index build scans/ --glob '*.vtp' --jobs 2 --wait 600 --format json
      nfdmatch index build /shared/scans --index /shared/scans.h5 --scheduler tcp://head:8786
    """
    from ..index import build_index

    started = datetime.now(timezone.utc)
    cluster = None
    if scheduler and not dry_run:          # a dry run only plans: nothing for workers to do
        if jobs is not None:
            note("--jobs is ignored with --scheduler (the cluster's workers compute the files)")
        cluster = open_cluster(scheduler, scheduler_timeout)
    progress, finish_bar = progress_bar("indexing files")
    try:
        options = dict(samples=samples, harmonics=harmonics, scale=scale, glob=glob_pattern,
                       input_format=input_format, rebuild=rebuild, dry_run=dry_run, wait=wait, progress=progress)
        if cluster is None:
            report = build_index(list(sources), index_path, jobs=jobs, **options)
        else:
            report = cluster.build_index(list(sources), index_path, **options)
    finally:
        finish_bar()
        if cluster is not None:
            cluster.close()
    for notice in report.notices:
        note(notice, prefix="Notice: ")
    for path, message in report.failures:
        error(message)
    if output_format == "json":
        summary = {"index": index_path, "started": started.strftime("%Y-%m-%dT%H:%M:%SZ"),
                   "added": report.added, "updated": report.updated, "removed": report.removed,
                   "unchanged": report.unchanged, "failed": report.failed,
                   "failures": [{"path": path, "error": message} for path, message in report.failures],
                   "curves": report.curves, "seconds": round(report.seconds, 3)}
        if dry_run:
            summary["dry_run"] = True
            summary["changes"] = [{"action": a, "path": p} for a, p in report.changes if a != "unchanged"]
        deliver(json.dumps(summary) + "\n", None)
    else:
        if dry_run:
            deliver("".join(f"{action}\t{path}\n" for action, path in report.changes if action != "unchanged"),
                    None)
        verb = "would change" if dry_run else (f"indexed into {index_path}" if report.written
                                                 else f"{index_path} is up to date")
        say(f"{verb}: {report.added} added, {report.updated} updated, {report.removed} removed, "
            f"{report.unchanged} unchanged, {report.failed} failed files; {report.curves} curves; "
            f"{report.seconds:.2f} s")
    if not dry_run:
        finish(report.failed, report.added + report.updated + report.unchanged + report.failed, "files")


@index.command("info")
@index_option
@format_option(("text", "json"), default="text")
@output_option()
def index_info(index_path, output_format, output):
    """Describe an index: files, curves, failed files with reasons, parameters, format, times, size.

    \b
    Example:
      nfdmatch index info --index demo.h5 --format json -o info.json
    """
    from ..index import open_index

    with open_index(index_path) as idx:
        info = idx.info()
    if output_format == "json":
        deliver(json.dumps(info, indent=2) + "\n", output)
        return
    lines = [f"{key}\t{info.get(key)}" for key in (
        "path", "format", "format_version", "nfdmatch_version", "files", "curves", "samples", "harmonics",
        "scale", "created", "updated", "size_bytes")]
    failed = info.get("failed", [])
    lines.append(f"failed\t{len(failed)}")
    lines += [f"  {item['path']}\t{item['error']}" for item in failed]
    deliver("".join(line + "\n" for line in lines), output)


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
            rows = [{"id": ids[row], "file": r.path} for r in files
                    for row in range(r.curve_start, r.curve_start + r.curve_count)]
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

    fmt = output_format or {".csv": "csv", ".jsonl": "jsonl", ".npz": "npz"}.get(
        os.path.splitext(output)[1].lower())
    if fmt is None:
        raise click.UsageError(f"cannot tell the export format from {output!r}: use .csv, .jsonl or .npz, "
                               "or --format")
    with open_index(index_path) as idx:
        rows = idx.read_rows(0, idx.n_curves, ["coefficients", "rotation", "centroid", "scale",
                                                "plane_degenerate", "file"])
        ids = idx.ids()
        paths = [r.path for r in idx.files()]
        params = {"samples": idx.samples, "harmonics": idx.harmonics, "scale_mode": idx.scale}
    files = [paths[i] for i in rows["file"]]
    frequencies = np.arange(1, params["harmonics"] + 1)
    if fmt == "npz":
        buf = io.BytesIO()
        np.savez_compressed(buf, ids=np.array(ids, dtype=str), files=np.array(files, dtype=str),
                            scale=rows["scale"], plane_degenerate=rows["plane_degenerate"],
                            centroid=rows["centroid"], rotation=rows["rotation"],
                            coefficients=rows["coefficients"], frequencies=frequencies,
                            **{k: np.array(v) for k, v in params.items()})
        _deliver_bytes(buf.getvalue(), output)
        return
    records = []
    for i, curve_id in enumerate(ids):
        records.append({"id": curve_id, "file": files[i], **params, "scale": float(rows["scale"][i]),
                        "plane_degenerate": bool(rows["plane_degenerate"][i]),
                        "centroid": rows["centroid"][i].tolist(), "rotation": rows["rotation"][i].tolist(),
                        "frequencies": frequencies.tolist(),
                        "coefficients": [[[float(c.real), float(c.imag)] for c in row]
                                         for row in rows["coefficients"][i]]})
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
@click.option("--max-distance", type=click.FloatRange(min=0), default=None,
              help="Only list matches at most this far.")
@click.option("--glob", "glob_pattern", default=None, help="Only query files in folders whose name matches.")
@click.option("--details", is_flag=True, help="Add the columns shift, reversed, mirrored.")
@exclude_self_option
@click.option("--exhaustive", is_flag=True,
              help="Compute every exact distance, no pruning (to check a result: the pruned search "
                   "returns the same rows and distances).")
@click.option("--stats", "show_stats", is_flag=True,
              help="Print on stderr how many exact distances the search needed.")
@matching_options
@input_format_option
@scheduler_options
@ranges_option
@rows_format_option
@output_option()
def query(queries, index_path, top, max_distance, glob_pattern, details, exclude_self_, exhaustive, show_stats,
          method, strict_direction, mirror, input_format, scheduler, scheduler_timeout, ranges, output_format, output):
    """Find the curves of the index most similar to each curve in QUERY... .

    QUERY: files (FILE#I for one curve of a multi-curve file; `-` for stdin) or folders;
    every curve in them is a query, answered with the index's own samples, harmonics and
    scale. Rows: query, rank, match, distance (ties ordered by id). The search is exact:
    rows are visited in increasing order of proven lower bounds (cells of the index, then
    invariant features, then the first harmonics) and the search stops when the next bound
    exceeds the K-th distance; --exhaustive computes every distance instead (same answer).
    Inputs that cannot be read are named on stderr and the others answered (exit 3).

    \b
    Examples:
      nfdmatch query sample_curves/queries/trefoil-posed.obj --index demo.h5 --top 5
      nfdmatch query new_scans/ --index curves.h5 --top 1 --format jsonl -o matches.jsonl
      nfdmatch query library/ --index library.h5 --exclude-self --top 3
      nfdmatch query batch/ --index /shared/scans.h5 --scheduler tcp://head:8786 -o matches.csv
    """
    from ..index import FORMAT_VERSION, open_index
    from ..search import search_index

    with open_index(index_path) as idx:
        if idx.format_version < FORMAT_VERSION and not exhaustive:
            note(f"{idx.path} is an index of format {idx.format_version}, without search cells: every row is "
                 f"bounded for each query (slower on large indexes); `nfdmatch index build --index "
                 f"{idx.path}` upgrades it")
        inputs = read_inputs(queries, glob=glob_pattern, input_format=input_format)
        if ranges is not None and not scheduler:
            raise click.UsageError("--ranges needs --scheduler")
        cluster = open_cluster(scheduler, scheduler_timeout) if scheduler else None
        progress, finish_bar = progress_bar("searching")
        try:
            extra = {} if cluster is None else {"parts": ranges}
            run = search_index if cluster is None else cluster.search_index
            results, stats = run(idx, inputs.curves, top=top + exclude_self_, max_distance=max_distance,
                                 progress=progress, prune=not exhaustive, **extra,
                                 **matching(method, strict_direction, mirror))
        finally:
            finish_bar()
            if cluster is not None:
                cluster.close()
    if exclude_self_:
        results = [exclude_self(q.id, res, top) for q, res in zip(inputs.curves, results)]
    write_rows([{"query": q.id, **row} for q, res in zip(inputs.curves, results) for row in res],
               match_columns(details), output_format, output, group_by="query")
    if show_stats:
        say(f"{stats.queries} queries x {stats.rows} rows: {stats.exact} exact distances "
            f"({stats.exact_fraction:.2%}), {stats.seconds:.3f} s"
            + ("" if not stats.pruned else
               f"; per query: {stats.per_query(stats.scanned):.0f} rows bounded in "
               f"{stats.per_query(stats.cells):.1f} of {stats.cell_count} cells, "
               f"{stats.per_query(stats.truncated):.0f} truncated-harmonic bounds, "
               f"{stats.per_query(stats.exact):.0f} exact distances, "
               f"{stats.per_query(stats.bytes_read) / 2**20:.2f} MiB read"))
    inputs.finish()
