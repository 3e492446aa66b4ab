"""The index commands: ``index build``, ``index info`` and ``query``."""

from __future__ import annotations

import json
import sys

import click

from .common import (EXIT_ERROR, EXIT_PARTIAL, handle_errors, index_option, input_format_option, match_columns,
                     matching_options, output_option, progress_bar, report_errors, write_rows)
from .group import main


@main.group()
def index():
    """Build and inspect the HDF5 index of curve descriptors.

    \b
    Examples:
      nfdmatch index build curves/ --index curves.h5
      nfdmatch index info --index curves.h5
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
@click.option("--samples", "-n", type=click.IntRange(min=3), default=None,
              help="Arc-length samples [default: the index's, else 128].")
@click.option("--harmonics", "-k", type=click.IntRange(min=1), default=None,
              help="Harmonics K [default: the index's, else 16].")
@click.option("--scale", type=click.Choice(["rms", "a1"]), default=None,
              help="Scale normalization [default: the index's, else rms].")
@input_format_option
@click.option("--format", "output_format", type=click.Choice(["text", "json"]), default="text", show_default=True,
              help="text: summary on stderr; json: one summary object on stdout.")
@handle_errors
def index_build(sources, index_path, glob_pattern, rebuild, dry_run, jobs, wait, samples, harmonics, scale,
                input_format, output_format):
    """Index the curves in SOURCE... (files or folders, recursively).

    Incremental: unchanged files (same size and mtime, or same SHA-256) are not
    recomputed, changed files are, files no longer under the sources are removed.
    The index is written to a temporary file and moved into place when complete, so
    an interrupted build leaves the previous index intact and queries keep working.
    Bad files are named on stderr and recorded as failed; the rest is indexed.

    Exit codes: 0 every file indexed, 3 index written but some files failed,
    1 nothing written (bad arguments, lock held, unreadable old index).

    \b
    Examples:
      nfdmatch index build sample_curves/library --index demo.h5
      nfdmatch index build scans/ --glob '*.vtp' --jobs 2 --wait 600 --format json
    """
    from ..index import build_index

    progress, finish = progress_bar("indexing files")
    try:
        report = build_index(list(sources), index_path, samples=samples, harmonics=harmonics, scale=scale,
                             glob=glob_pattern, input_format=input_format, rebuild=rebuild, dry_run=dry_run,
                             jobs=jobs, wait=wait, progress=progress)
    finally:
        finish()
    for notice in report.notices:
        click.echo(f"Notice: {notice}", err=True)
    for path, message in report.failures:
        click.echo(f"Error: {message}", err=True)
    summary = {"added": report.added, "updated": report.updated, "removed": report.removed,
               "unchanged": report.unchanged, "failed": report.failed, "curves": report.curves,
               "seconds": round(report.seconds, 3)}
    if dry_run and output_format == "text":
        for action, path in report.changes:
            if action != "unchanged":
                click.echo(f"{action}\t{path}")
    if output_format == "json":
        if dry_run:
            summary["dry_run"] = True
            summary["changes"] = [{"action": a, "path": p} for a, p in report.changes if a != "unchanged"]
        click.echo(json.dumps(summary))
    else:
        verb = "would change" if dry_run else (f"indexed into {index_path}" if report.written
                                                 else f"{index_path} is up to date")
        click.echo(f"{verb}: {report.added} added, {report.updated} updated, {report.removed} removed, "
                   f"{report.unchanged} unchanged, {report.failed} failed files; {report.curves} curves; "
                   f"{report.seconds:.2f} s", err=True)
    if report.failed and not dry_run:
        sys.exit(EXIT_PARTIAL)


@index.command("info")
@index_option
@click.option("--format", "output_format", type=click.Choice(["text", "json"]), default="text", show_default=True,
              help="Output format on stdout.")
@handle_errors
def index_info(index_path, output_format):
    """Describe an index: files, curves, failed files with reasons, parameters, format, times, size.

    \b
    Example:
      nfdmatch index info --index demo.h5 --format json
    """
    from ..index import open_index

    with open_index(index_path) as idx:
        info = idx.info()
    if output_format == "json":
        click.echo(json.dumps(info, indent=2))
        return
    for key in ("path", "format", "format_version", "nfdmatch_version", "files", "curves", "samples",
                "harmonics", "scale", "created", "updated", "size_bytes"):
        click.echo(f"{key}\t{info.get(key)}")
    failed = info.get("failed", [])
    click.echo(f"failed\t{len(failed)}")
    for item in failed:
        click.echo(f"  {item['path']}\t{item['error']}")


@main.command()
@click.argument("queries", nargs=-1, required=True, metavar="QUERY...")
@index_option
@click.option("--top", type=click.IntRange(min=1), default=10, show_default=True, help="Matches per query.")
@click.option("--max-distance", type=click.FloatRange(min=0), default=None,
              help="Only list matches at most this far.")
@click.option("--glob", "glob_pattern", default=None, help="Only query files in folders whose name matches.")
@click.option("--details", is_flag=True, help="Add the columns shift, reversed, mirrored.")
@click.option("--stats", "show_stats", is_flag=True,
              help="Print on stderr how many exact distances the search needed.")
@matching_options
@input_format_option
@output_option(help_extra=" (default: a table on a terminal, CSV otherwise)")
@handle_errors
def query(queries, index_path, top, max_distance, glob_pattern, details, show_stats, method, strict_direction,
          mirror, input_format, output_format):
    """Find the curves of the index most similar to each curve in QUERY... .

    QUERY: files (FILE#I for one curve of a multi-curve file) or folders; every curve in
    them is a query, answered with the index's own samples, harmonics and scale. Rows:
    query, rank, match, distance (ties ordered by id). The search is exact: lower bounds
    prune rows that cannot enter the top K, the rest get the exact distance.

    \b
    Examples:
      nfdmatch query sample_curves/queries/trefoil-posed.obj --index demo.h5 --top 5
      nfdmatch query new_scans/ --index curves.h5 --top 1 --format jsonl
    """
    from ..index import open_index
    from ..search import search_index
    from ..sources import find_curve_files, read_all

    files = find_curve_files(queries, glob=glob_pattern)
    with open_index(index_path) as idx:
        curves, errors = read_all(files, format=input_format)
        report_errors(errors)
        if not curves:
            sys.exit(EXIT_ERROR)
        results, stats = search_index(idx, curves, top=top, max_distance=max_distance, method=method,
                                      direction="strict" if strict_direction else "invariant", mirror=mirror)
    columns = match_columns(details)
    write_rows([{"query": q.id, **row} for q, res in zip(curves, results) for row in res], columns, output_format)
    if show_stats:
        click.echo(f"{stats.queries} queries x {stats.rows} rows: {stats.exact} exact distances "
                   f"({stats.exact_fraction:.2%}), {stats.seconds:.3f} s", err=True)
    if errors:
        click.echo(f"{len(errors)} of {len(files)} query files could not be read", err=True)
        sys.exit(EXIT_PARTIAL)
