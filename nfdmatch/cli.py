"""The command-line interface: parses arguments, calls the library, formats the results.

The only module that imports click and rich. stdout carries data only; messages,
warnings and errors go to stderr. Exit codes: 0 ok, 1 error (bad input or any
NfdError), 2 usage error, 3 partial success (some inputs failed, the rest was output).
"""

from __future__ import annotations

import csv
import io
import json
import sys
from functools import wraps

import click

from . import __version__
from .errors import NfdError

EXIT_OK, EXIT_ERROR, EXIT_USAGE, EXIT_PARTIAL = 0, 1, 2, 3
ROW_FORMATS = ("table", "csv", "tsv", "json", "jsonl")


# --------------------------------------------------------------------------- output

def _stdout_is_terminal() -> bool:
    return sys.stdout.isatty()


def write_rows(rows: list[dict], columns: list[str], fmt: str | None) -> None:
    """Write rows to stdout as a rich table, CSV, TSV, JSON (a list) or JSON lines.

    ``fmt`` None means a table on a terminal and CSV otherwise. Machine formats carry
    no markup; floats keep full precision (repr).
    """
    if fmt is None:
        fmt = "table" if _stdout_is_terminal() else "csv"
    if fmt == "table":
        from rich.console import Console
        from rich.table import Table

        table = Table(show_header=True, header_style="bold")
        cells = [[_cell_text(row.get(c), pretty=True) for c in columns] for row in rows]
        for i, col in enumerate(columns):
            numeric = bool(rows) and isinstance(rows[0].get(col), (int, float)) \
                and not isinstance(rows[0].get(col), bool)
            table.add_column(col, justify="right" if numeric else "left", no_wrap=True)
        for row in cells:
            table.add_row(*row)
        # ids are long paths: never truncate them, let the table be as wide as it needs
        widths = [max([len(col)] + [len(r[i]) for r in cells]) for i, col in enumerate(columns)]
        console = Console(file=sys.stdout)
        console.width = max(console.width, sum(widths) + 3 * len(columns) + 1)
        console.print(table)
    elif fmt in ("csv", "tsv"):
        _write_delimited(columns, ([_cell_text(row.get(c)) for c in columns] for row in rows), fmt)
    elif fmt == "json":
        click.echo(json.dumps([{c: row.get(c) for c in columns} for row in rows], indent=2))
    elif fmt == "jsonl":
        for row in rows:
            click.echo(json.dumps({c: row.get(c) for c in columns}))
    else:  # pragma: no cover - click restricts the choices
        raise click.UsageError(f"unknown format {fmt}")


def _write_delimited(header: list[str], rows, fmt: str) -> None:
    """A header line then the rows (lists of str), as CSV or TSV on stdout."""
    buf = io.StringIO()
    writer = csv.writer(buf, delimiter="," if fmt == "csv" else "\t", lineterminator="\n")
    writer.writerow(header)
    writer.writerows(rows)
    click.echo(buf.getvalue(), nl=False)


def _cell_text(value, pretty: bool = False) -> str:
    if value is None:
        return ""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        return f"{value:.6g}" if pretty else repr(value)
    if isinstance(value, (list, dict)):
        return json.dumps(value)
    return str(value)


def output_option(formats=ROW_FORMATS, default=None, help_extra=""):
    """The one ``--format`` option shared by every command that prints rows."""
    return click.option("--format", "output_format", type=click.Choice(formats), default=default,
                        help="Output format on stdout" + help_extra + ".")


def input_format_option(f):
    from .formats import FORMATS

    return click.option("--input-format", "input_format", type=click.Choice(sorted(FORMATS)), default=None,
                        help="Read inputs as this format whatever their extension.")(f)


def descriptor_options(f):
    from .descriptors import DEFAULT_HARMONICS, DEFAULT_SAMPLES, DEFAULT_SCALE, SCALES

    f = click.option("--scale", type=click.Choice(SCALES), default=DEFAULT_SCALE, show_default=True,
                     help="Scale normalization: RMS radius (robust) or |A_1| (the paper).")(f)
    f = click.option("--harmonics", "-k", type=click.IntRange(min=1), default=DEFAULT_HARMONICS,
                     show_default=True, help="Harmonics K: frequencies +-1..+-K are compared.")(f)
    f = click.option("--samples", "-n", type=click.IntRange(min=3), default=DEFAULT_SAMPLES,
                     show_default=True, help="Arc-length samples per curve.")(f)
    return f


def matching_options(f):
    f = click.option("--mirror", is_flag=True, help="Also allow reflections (mirror images match).")(f)
    f = click.option("--strict-direction", is_flag=True,
                     help="Do not match a curve traversed in the opposite direction.")(f)
    f = click.option("--method", type=click.Choice(["exact", "paper"]), default="exact", show_default=True,
                     help="exact: global optimum over start shift x rotation; paper: the published step.")(f)
    return f


def _report_errors(errors) -> None:
    """Name every input that failed on stderr (the messages name the file and line)."""
    for exc in errors:
        click.echo(f"Error: {exc}", err=True)


def _match_columns(details: bool) -> list[str]:
    """Columns of the rows `rank` and `query` print."""
    return ["query", "rank", "match", "distance"] + (["shift", "reversed", "mirrored"] if details else [])


def handle_errors(func):
    """Map NfdError to 'Error: <message>' on stderr and exit code 1, never a traceback."""

    @wraps(func)
    def wrapper(*args, **kwargs):
        try:
            return func(*args, **kwargs)
        except NfdError as exc:
            click.echo(f"Error: {exc}", err=True)
            sys.exit(EXIT_ERROR)
        except BrokenPipeError:  # e.g. `nfdmatch describe ... | head`
            sys.stderr.close()
            sys.exit(EXIT_OK)

    return wrapper


# --------------------------------------------------------------------------- commands

@click.group(context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="nfdmatch")
def main():
    """Find which stored closed 3-D curves look most like a query curve.

    Curves are read from CSV/TSV/TXT (x,y,z or x,y), OBJ (`l` polylines) and VTK
    (.vtk/.vtp/.vtu line cells). FILE#I selects curve I (0-based) of a multi-curve file.

    \b
    Examples:
      nfdmatch distance a.csv b.obj#2
      nfdmatch index build curves/ --index curves.h5
      nfdmatch query q.csv --index curves.h5 --top 5
      nfdmatch show q.csv --index curves.h5 -o matches.png
      nfdmatch extract part.stl --sections 20 -o contours/

    Exit codes: 0 ok, 1 error, 2 usage error, 3 some inputs failed (the rest was output).
    """


@main.command()
@click.argument("curve_a", metavar="A")
@click.argument("curve_b", metavar="B")
@matching_options
@descriptor_options
@input_format_option
@click.option("--format", "output_format", type=click.Choice(["text", "json"]), default="text",
              show_default=True, help="Output format on stdout.")
@handle_errors
def distance(curve_a, curve_b, method, strict_direction, mirror, samples, harmonics, scale,
             input_format, output_format):
    """Similarity distance between two curves A and B, and the alignment of B onto A.

    A and B are files (FILE#I for curve I of a multi-curve file). The distance is 0 for
    the same shape whatever its position, size, orientation, start vertex, sampling
    and (unless --strict-direction) traversal direction.

    \b
    Example:
      nfdmatch distance sample_curves/library/trefoil.csv sample_curves/queries/trefoil-posed.obj --format json
    """
    from .formats import read_curve
    from .matching import distance as match_distance

    a = read_curve(curve_a, format=input_format)
    b = read_curve(curve_b, format=input_format)
    m = match_distance(a, b, samples=samples, harmonics=harmonics, scale=scale, method=method,
                       direction="strict" if strict_direction else "invariant", mirror=mirror)
    record = m.to_dict()
    if output_format == "json":
        click.echo(json.dumps({"a": a.id, "b": b.id, **record}, indent=2))
    else:
        click.echo(f"distance\t{m.distance:.10g}")
        click.echo(f"shift\t{m.shift:.6f}")
        click.echo(f"reversed\t{str(m.reversed).lower()}")
        click.echo(f"mirrored\t{str(m.mirrored).lower()}")
        click.echo(f"scale\t{m.scale:.10g}")
        click.echo("rotation\t" + json.dumps([[round(v, 12) for v in row] for row in record["rotation"]]))
        click.echo("translation\t" + json.dumps([round(v, 12) for v in record["translation"]]))
        click.echo(f"method\t{m.method}")


@main.command()
@click.argument("files", nargs=-1, required=True, metavar="FILE...")
@descriptor_options
@input_format_option
@click.option("--format", "output_format", type=click.Choice(["csv", "tsv", "json", "jsonl"]), default="csv",
              show_default=True, help="Output format on stdout.")
@handle_errors
def describe(files, samples, harmonics, scale, input_format, output_format):
    """Print the normalized Fourier descriptors of every curve in FILE....

    One row per curve: id, parameters, centroid and scale (input units), whether the
    limit plane is degenerate, then the normalized coefficients A_k for
    k = +1..+K, -1..-K: columns k+1_x_re, k+1_x_im, ..., k-K_z_im.
    FILE#I describes one curve of a multi-curve file; a bad file is reported on
    stderr and skipped (exit 3).

    \b
    Example:
      nfdmatch describe sample_curves/library/*.csv --harmonics 8 > descriptors.csv
    """
    from .descriptors import descriptors_batch, validate_parameters
    from .sources import read_all

    validate_parameters(samples, harmonics, scale)
    curves, errors = read_all(files, format=input_format)
    _report_errors(errors)
    failed = len(errors)
    batch = descriptors_batch(curves, samples=samples, harmonics=harmonics, scale=scale)
    rows = [_descriptor_row(batch.row(i, c.id)) for i, c in enumerate(curves)]
    if not rows and failed:
        sys.exit(EXIT_ERROR)
    if output_format in ("json", "jsonl"):
        columns = ["id", "samples", "harmonics", "scale", "scale_value", "centroid", "plane_degenerate",
                   "frequencies", "coefficients"]
        write_rows(rows, columns, output_format)
    else:
        flat = [_flatten_descriptor_row(r) for r in rows]
        columns = list(flat[0]) if flat else ["id"]
        write_rows(flat, columns, output_format)
    if failed:
        click.echo(f"{failed} of {len(files)} inputs failed", err=True)
        sys.exit(EXIT_PARTIAL)


@main.command()
@click.argument("query_spec", metavar="QUERY")
@click.argument("sources", nargs=-1, required=True, metavar="SOURCE...")
@click.option("--top", type=click.IntRange(min=1), default=10, show_default=True,
              help="Number of matches to list.")
@click.option("--max-distance", type=click.FloatRange(min=0), default=None,
              help="Only list matches at most this far.")
@click.option("--glob", "glob_pattern", default=None, help="Only files in folders whose name matches, e.g. '*.csv'.")
@click.option("--details", is_flag=True, help="Add the columns shift, reversed, mirrored.")
@matching_options
@descriptor_options
@input_format_option
@output_option(help_extra=" (default: a table on a terminal, CSV otherwise)")
@handle_errors
def rank(query_spec, sources, top, max_distance, glob_pattern, details, method, strict_direction, mirror,
         samples, harmonics, scale, input_format, output_format):
    """Rank the curves in SOURCE... (files or folders) by similarity to QUERY, without an index.

    QUERY is one curve (FILE or FILE#I). Folders are searched recursively for files with
    a known extension (hidden files skipped). Files that cannot be read are named on
    stderr and skipped (exit 3). Rows: query, rank, match, distance.

    \b
    Example:
      nfdmatch rank sample_curves/queries/trefoil-posed.obj sample_curves/library --top 5
    """
    from .formats import read_curve
    from .search import rank_curves
    from .sources import find_curve_files, read_all

    query = read_curve(query_spec, format=input_format)
    files = find_curve_files(sources, glob=glob_pattern)
    curves, errors = read_all(files, format=input_format)
    _report_errors(errors)
    if not curves and errors:
        sys.exit(EXIT_ERROR)
    ranked = rank_curves(query, curves, top=top, max_distance=max_distance, samples=samples,
                         harmonics=harmonics, scale=scale, method=method,
                         direction="strict" if strict_direction else "invariant", mirror=mirror)
    columns = _match_columns(details)
    write_rows([{"query": query.id, **row} for row in ranked], columns, output_format)
    if errors:
        click.echo(f"{len(errors)} of {len(files)} files could not be read", err=True)
        sys.exit(EXIT_PARTIAL)


# --------------------------------------------------------------------------- index

def index_option(f):
    return click.option("--index", "index_path", envvar="NFDMATCH_INDEX", default="nfdmatch.h5",
                        show_default="$NFDMATCH_INDEX or nfdmatch.h5", type=click.Path(dir_okay=False),
                        help="The index file.")(f)


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
    from .index import build_index

    progress, finish = _progress_bar("indexing files")
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
    from .index import open_index

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
    from .index import open_index
    from .search import search_index
    from .sources import find_curve_files, read_all

    files = find_curve_files(queries, glob=glob_pattern)
    with open_index(index_path) as idx:
        curves, errors = read_all(files, format=input_format)
        _report_errors(errors)
        if not curves:
            sys.exit(EXIT_ERROR)
        results, stats = search_index(idx, curves, top=top, max_distance=max_distance, method=method,
                                      direction="strict" if strict_direction else "invariant", mirror=mirror)
    columns = _match_columns(details)
    write_rows([{"query": q.id, **row} for q, res in zip(curves, results) for row in res], columns, output_format)
    if show_stats:
        click.echo(f"{stats.queries} queries x {stats.rows} rows: {stats.exact} exact distances "
                   f"({stats.exact_fraction:.2%}), {stats.seconds:.3f} s", err=True)
    if errors:
        click.echo(f"{len(errors)} of {len(files)} query files could not be read", err=True)
        sys.exit(EXIT_PARTIAL)


def _progress_bar(description: str):
    """(callback, finish) for a rich progress bar on stderr, only when stderr is a terminal."""
    if not sys.stderr.isatty():
        return None, lambda: None
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn
    from rich.console import Console

    # no auto-refresh thread: a running thread would force the build's workers off fork
    bar = Progress(TextColumn(description), BarColumn(), MofNCompleteColumn(), TimeRemainingColumn(),
                   console=Console(stderr=True), transient=True, auto_refresh=False)
    task = bar.add_task(description, total=None)
    bar.start()

    def update(done, total):
        bar.update(task, completed=done, total=total)
        bar.refresh()

    return update, bar.stop


def _descriptor_row(d) -> dict:
    freqs, coeffs = d.band()
    return {
        "id": d.id, "samples": d.samples, "harmonics": d.harmonics, "scale": d.scale_mode,
        "scale_value": float(d.scale), "centroid": [float(v) for v in d.centroid],
        "plane_degenerate": bool(d.plane_degenerate),
        "frequencies": [int(f) for f in freqs],
        # per frequency, per axis x, y, z: [real, imaginary]
        "coefficients": [[[float(c.real), float(c.imag)] for c in row] for row in coeffs],
    }


def _flatten_descriptor_row(row: dict) -> dict:
    flat = {k: row[k] for k in ("id", "samples", "harmonics", "scale", "scale_value", "plane_degenerate")}
    flat.update({f"centroid_{ax}": v for ax, v in zip("xyz", row["centroid"])})
    for f, coeff in zip(row["frequencies"], row["coefficients"]):
        for ax, (re, im) in zip("xyz", coeff):
            flat[f"k{f:+d}_{ax}_re"] = re
            flat[f"k{f:+d}_{ax}_im"] = im
    return flat



# --------------------------------------------------------------------------- pictures and reconstruction
# (show, matrix, reconstruct)

def _parse_size(value: str) -> tuple[int, int]:
    from .render import MAX_SIDE, MIN_SIDE

    try:
        width, height = (int(v) for v in value.lower().split("x"))
    except ValueError:
        raise click.BadParameter(f"expected WIDTHxHEIGHT in pixels, e.g. 1600x900, got {value!r}")
    if not (MIN_SIDE <= width <= MAX_SIDE and MIN_SIDE <= height <= MAX_SIDE):
        raise click.BadParameter(f"width and height must be {MIN_SIDE}..{MAX_SIDE} pixels, got {value!r}")
    return width, height


def _read_sources(sources, glob_pattern, input_format):
    """(curves, errors, files) of the files and folders given; errors named on stderr.
    Exits 1 when no curve could be read; no curve file at all is an error of its own."""
    from .errors import NoCurvesError
    from .sources import find_curve_files, read_all

    files = find_curve_files(sources, glob=glob_pattern)
    if not files:
        raise NoCurvesError("no curve files found" + (f" matching {glob_pattern!r}" if glob_pattern else ""),
                            path=", ".join(str(s) for s in sources))
    curves, errors = read_all(files, format=input_format)
    _report_errors(errors)
    if not curves:
        sys.exit(EXIT_ERROR)
    return curves, errors, files


def _renderer_option(f):
    return click.option("--renderer", type=click.Choice(["auto", "matplotlib", "pyvista"]), default="auto",
                        show_default=True,
                        help="Drawing library; auto uses the default and falls back to the other one.")(f)


def _optional_descriptor_options(f):
    """samples/harmonics/scale without defaults: an index fixes them, files take the defaults."""
    from .descriptors import SCALES

    f = click.option("--scale", type=click.Choice(SCALES), default=None,
                     help="Scale normalization (with --against; default rms).")(f)
    f = click.option("--harmonics", "-k", type=click.IntRange(min=1), default=None,
                     help="Harmonics K (with --against; default 16).")(f)
    f = click.option("--samples", "-n", type=click.IntRange(min=3), default=None,
                     help="Arc-length samples (with --against; default 128).")(f)
    return f


def _report_picture(result) -> None:
    if result.note:
        click.echo(f"Note: {result.note}", err=True)
    click.echo(f"wrote {result.path} ({result.renderer}, {result.seconds:.2f} s)", err=True)


@main.command()
@click.argument("query_spec", metavar="QUERY")
@click.argument("sources", nargs=-1, metavar="[SOURCE...]")
@click.option("--against", is_flag=True,
              help="Rank the files or folders SOURCE... instead of searching an index.")
@index_option
@click.option("--top", type=click.IntRange(min=1, max=23), default=5, show_default=True,
              help="Matches to draw.")
@click.option("--output", "-o", required=True, type=click.Path(dir_okay=False),
              help="The PNG file to write.")
@click.option("--size", default="1600x900", show_default=True, help="Picture size WIDTHxHEIGHT in pixels.")
@_renderer_option
@click.option("--glob", "glob_pattern", default=None,
              help="Only files in folders whose name matches (with --against).")
@matching_options
@_optional_descriptor_options
@input_format_option
@output_option(help_extra=" for the rows drawn (default: a table on a terminal, CSV otherwise)")
@handle_errors
def show(query_spec, sources, against, index_path, top, output, size, renderer, glob_pattern, method,
         strict_direction, mirror, samples, harmonics, scale, input_format, output_format):
    """Draw QUERY and its best matches, each aligned onto the query, into one PNG.

    The matches come from the index (--index, as `query` finds them) or, with --against,
    from ranking the curves in SOURCE... . Every match is drawn in the query's frame with
    the rotation, scale, start shift and direction of its match: the query in grey under
    it, start points marked, direction of travel shown. Planar curves get a 2-D view.
    The rows drawn are printed on stdout (query, rank, match, distance, source).

    \b
    Examples:
      nfdmatch show sample_curves/queries/trefoil-posed.obj --index demo.h5 -o matches.png
      nfdmatch show q.csv --against library/ --top 8 -o q.png
    """
    from .descriptors import DEFAULT_HARMONICS, DEFAULT_SAMPLES, DEFAULT_SCALE
    from .formats import read_curve
    from .render import MatchPanel, render_matches

    width_height = _parse_size(size)
    direction = "strict" if strict_direction else "invariant"
    query = read_curve(query_spec, format=input_format)
    notes: list[str] = []
    exit_code = EXIT_OK
    if against:
        if not sources:
            raise click.UsageError("--against needs at least one SOURCE file or folder")
        from .search import rank_curves
        from .show import matches_from_curves

        curves, errors, _ = _read_sources(sources, glob_pattern, input_format)
        if errors:
            exit_code = EXIT_PARTIAL
        params = dict(samples=samples or DEFAULT_SAMPLES, harmonics=harmonics or DEFAULT_HARMONICS,
                      scale=scale or DEFAULT_SCALE)
        ranked = rank_curves(query, curves, top=top, method=method, direction=direction, mirror=mirror, **params)
        shown = matches_from_curves(query, ranked, curves, method=method,
                                    direction=direction, mirror=mirror, **params)
    else:
        if sources:
            raise click.UsageError("SOURCE... is only read with --against (without it, the index is searched)")
        if samples or harmonics or scale or glob_pattern:
            raise click.UsageError("--samples/--harmonics/--scale/--glob go with --against: "
                                   "the index fixes its own parameters and curves")
        from functools import partial

        from .index import open_index
        from .search import search_index
        from .show import matches_from_index

        with open_index(index_path) as idx:
            results, _ = search_index(idx, [query], top=top, method=method, direction=direction, mirror=mirror)
            shown, notes = matches_from_index(query, results[0], idx, method=method, direction=direction,
                                              mirror=mirror, read_curve=partial(read_curve, format=input_format))
    for note in notes:
        click.echo(f"Note: {note}", err=True)
    panels = [MatchPanel(id=s.id, distance=s.distance, points=s.points, start=s.start, forward=s.forward,
                         reversed=s.reversed, mirrored=s.mirrored,
                         note="drawn from index harmonics" if s.source == "index" else None) for s in shown]
    result = render_matches(query.points, query.id, panels, output, size=width_height, renderer=renderer)
    write_rows([{"query": query.id, "rank": s.rank, "match": s.id, "distance": s.distance, "source": s.source}
                for s in shown], ["query", "rank", "match", "distance", "source"], output_format)
    _report_picture(result)
    sys.exit(exit_code)


@main.command()
@click.argument("sources", nargs=-1, required=True, metavar="FILE_OR_FOLDER...")
@click.option("--output", "-o", default=None, type=click.Path(dir_okay=False),
              help="Also draw the matrix as a shaded PNG (darker = more similar).")
@click.option("--glob", "glob_pattern", default=None, help="Only files in folders whose name matches.")
@matching_options
@descriptor_options
@input_format_option
@click.option("--order", type=click.Choice(["input", "similar"]), default="input", show_default=True,
              help="Row order: as found, or similar curves next to each other (average-linkage tree).")
@click.option("--format", "output_format", type=click.Choice(["csv", "tsv", "json"]), default="csv",
              show_default=True, help="Format of the matrix on stdout.")
@handle_errors
def matrix(sources, output, glob_pattern, method, strict_direction, mirror, samples, harmonics, scale,
           input_format, order, output_format):
    """The distance between every pair of curves in FILE_OR_FOLDER... .

    stdout: CSV/TSV with a header row `id,<id 1>,<id 2>,...` then one row per curve, its id
    first; or JSON {"ids": [...], "distances": [[...], ...]}. Symmetric, zero diagonal,
    curves in the order found (files sorted, curves in file order), or with --order similar
    grouped by similarity. With -o, also a grey-level picture like the paper's Figure 7.

    \b
    Example:
      nfdmatch matrix sample_curves/library -o matrix.png > matrix.csv
    """
    from .search import distance_matrix, similarity_order

    if output:
        from .render import check_output

        check_output(output)                  # before the O(N^2) work, not after it
    curves, errors, files = _read_sources(sources, glob_pattern, input_format)
    progress, finish = _progress_bar("distances")
    try:
        distances = distance_matrix(curves, samples=samples, harmonics=harmonics, scale=scale, method=method,
                                    direction="strict" if strict_direction else "invariant", mirror=mirror,
                                    progress=progress)
    finally:
        finish()
    ids = [c.id for c in curves]
    if order == "similar":
        permutation = similarity_order(distances)
        distances = distances[permutation][:, permutation]
        ids = [ids[i] for i in permutation]
    if output_format == "json":
        click.echo(json.dumps({"ids": ids, "distances": distances.tolist()}, indent=1))
    else:
        _write_delimited(["id"] + ids, ([curve_id] + [repr(float(v)) for v in row]
                                        for curve_id, row in zip(ids, distances)), output_format)
    if output:
        from .render import render_matrix

        _report_picture(render_matrix(distances, ids, output,
                                      title=f"{method} distance, {len(ids)} curves"))
    if errors:
        click.echo(f"{len(errors)} of {len(files)} files could not be read", err=True)
        sys.exit(EXIT_PARTIAL)


@main.command()
@click.argument("curve_spec", metavar="FILE")
@click.option("--harmonics", "-k", type=click.IntRange(min=1), required=True,
              help="Harmonics K kept: frequencies +-1..+-K.")
@click.option("--output", "-o", required=True, type=click.Path(dir_okay=False),
              help="The curve file to write; its extension picks the format (csv, obj, vtk, vtp, vtu).")
@click.option("--points", "-m", type=click.IntRange(min=3, max=10_000_000), default=None,
              help="Vertices of the rebuilt curve [default: the samples].")
@click.option("--samples", "-n", type=click.IntRange(min=3), default=None,
              help="Arc-length samples of the transform [default: max(128, 4K)].")
@click.option("--normalized", is_flag=True,
              help="Write the normalized curve (centred, unit scale, limit plane on z = 0), not the input pose.")
@input_format_option
@click.option("--output-format", "curve_format", default=None,
              help="Write this curve format whatever OUT's extension (csv, obj, vtk, vtp, vtu).")
@output_option(help_extra=" for the summary rows (default: a table on a terminal, CSV otherwise)")
@handle_errors
def reconstruct(curve_spec, harmonics, output, points, samples, normalized, input_format, curve_format,
                output_format):
    """Rebuild the curve(s) in FILE from their first K harmonics: what the descriptor sees.

    The rebuilt curve keeps the input's position, size and orientation (unless
    --normalized), and is written to OUT in the format of its extension (a multi-curve
    FILE gives a multi-curve OUT; CSV holds one curve, so select it with FILE#I). Rows on
    stdout: curve, harmonics, vertices, distance (from the rebuilt curve to the input,
    default matching parameters).

    \b
    Example:
      nfdmatch reconstruct sample_curves/library/knotess/5_2.csv -k 4 -o 5_2-k4.vtp
    """
    from .curve import Curve
    from .descriptors import descriptors, reconstruct as rebuild
    from .formats import write_curves
    from .matching import distance
    from .sources import read_all

    n = samples if samples is not None else max(128, 4 * harmonics)
    if 2 * harmonics >= n:
        raise click.BadParameter(f"harmonics ({harmonics}) must be below samples/2 ({n}/2)",
                                 param_hint="--harmonics")
    curves, errors = read_all([curve_spec], format=input_format)
    if errors:
        raise errors[0]
    rebuilt, rows = [], []
    for curve in curves:
        d = descriptors(curve, samples=n, harmonics=harmonics)
        pts = rebuild(d, points=points, normalized=normalized)
        rebuilt.append(Curve(pts, id=f"{curve.id} K={harmonics}"))
        rows.append({"curve": curve.id, "harmonics": harmonics, "vertices": len(pts),
                     "distance": None if normalized else float(distance(curve, pts).distance)})
    write_curves(output, rebuilt, format=curve_format)
    columns = ["curve", "harmonics", "vertices"] + ([] if normalized else ["distance"])
    write_rows(rows, columns, output_format)
    click.echo(f"wrote {output}", err=True)


# --------------------------------------------------------------------------- meshes -> contours
# (extract)

@main.command()
@click.argument("meshes", nargs=-1, required=True, metavar="MESH...")
@click.option("-o", "--output", "out_dir", required=True, type=click.Path(file_okay=False),
              help="Folder for the contour files (created if needed).")
@click.option("--sections", type=click.IntRange(min=0), default=10, show_default=True,
              help="Number N of section planes (0: boundaries only, with --boundaries).")
@click.option("--axis", type=click.Choice(["x", "y", "z", "auto"]), default="auto", show_default=True,
              help="Axis the planes are perpendicular to; auto: the longest side of the bounding box.")
@click.option("--boundaries", is_flag=True, help="Also extract the boundary loops of open meshes.")
@click.option("--output-format", "curve_format", type=click.Choice(["obj", "csv", "vtp"]), default="obj",
              show_default=True, help="Curve file format of the written contours.")
@output_option(help_extra=" for the list of written files (default: a table on a terminal, CSV otherwise)")
@handle_errors
def extract(meshes, out_dir, sections, axis, boundaries, curve_format, output_format):
    """Write closed contours of triangle meshes (STL, PLY, OBJ, OFF, GLB/GLTF) as curve files.

    Each MESH (a file, or a folder searched recursively for mesh files) is cut by N
    planes perpendicular to the axis, at the middles of N equal slabs of its bounding
    box: lo + (i + 0.5) * (hi - lo) / N. Every closed loop of every section is written
    to its own file in DIR, named <mesh>_section-<axis><i>_at<level>_loop<k>; with
    --boundaries also the boundary loops of open meshes, <mesh>_boundary_loop<k>.
    The folder is then ready for `nfdmatch index build DIR`.

    stdout lists the written files (file, mesh, kind, axis, level, loop, vertices).
    Notes on stderr: open section pieces skipped, meshes that gave nothing. A file
    that is not a readable mesh is named on stderr and skipped (exit 3); exit 1 when
    no mesh gave any contour.

    \b
    Examples:
      nfdmatch extract part.stl -o contours/ --sections 20
      nfdmatch extract scans/ -o contours/ --axis z --boundaries --output-format vtp
      nfdmatch index build contours/ --index parts.h5
    """
    from .errors import ParameterError
    from .extract import extract_contours, find_mesh_files, write_contours

    if sections == 0 and not boundaries:
        raise click.UsageError("nothing to extract: --sections 0 needs --boundaries")
    files = find_mesh_files(meshes, exclude=[out_dir])
    if not files:
        raise ParameterError(f"no mesh files found in {', '.join(meshes)}")
    results, errors = [], []
    for path in files:
        try:
            results.append(extract_contours(path, sections=sections, axis=axis, boundaries=boundaries))
        except NfdError as exc:
            errors.append(exc)
    _report_errors(errors)
    for result in results:
        for note in result.notes:
            click.echo(f"Note: {note}", err=True)
    contours = [c for result in results for c in result.contours]
    if not contours:
        if results:
            click.echo(f"Error: no closed contour in {'the mesh' if len(files) == 1 else 'any mesh'}; "
                       "nothing written", err=True)
        sys.exit(EXIT_ERROR)
    written = write_contours(contours, out_dir, format=curve_format)
    rows = [{"file": path, "mesh": c.mesh, "kind": c.kind, "axis": c.axis, "level": c.level, "loop": c.loop,
             "vertices": c.n_vertices} for path, c in zip(written, contours)]
    write_rows(rows, ["file", "mesh", "kind", "axis", "level", "loop", "vertices"], output_format)
    meshes_with = len({c.mesh for c in contours})
    click.echo(f"{len(written)} contours from {meshes_with} of {len(files)} meshes written to {out_dir}",
               err=True)
    if errors:
        click.echo(f"{len(errors)} of {len(files)} meshes could not be read", err=True)
        sys.exit(EXIT_PARTIAL)


if __name__ == "__main__":  # pragma: no cover
    main()
