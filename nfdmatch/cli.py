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
        buf = io.StringIO()
        writer = csv.writer(buf, delimiter="," if fmt == "csv" else "\t", lineterminator="\n")
        writer.writerow(columns)
        for row in rows:
            writer.writerow([_cell_text(row.get(c)) for c in columns])
        click.echo(buf.getvalue(), nl=False)
    elif fmt == "json":
        click.echo(json.dumps([{c: row.get(c) for c in columns} for row in rows], indent=2))
    elif fmt == "jsonl":
        for row in rows:
            click.echo(json.dumps({c: row.get(c) for c in columns}))
    else:  # pragma: no cover - click restricts the choices
        raise click.UsageError(f"unknown format {fmt}")


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
      nfdmatch describe curves/*.csv --format json

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
    from .descriptors import descriptors, validate_parameters
    from .formats import read_curve, read_curves, split_selector

    validate_parameters(samples, harmonics, scale)
    rows, failed = [], 0
    for spec in files:
        try:
            path, index = split_selector(spec)
            curves = [read_curve(spec, format=input_format)] if index is not None \
                else read_curves(path, format=input_format)
            for curve in curves:
                d = descriptors(curve, samples=samples, harmonics=harmonics, scale=scale)
                rows.append(_descriptor_row(d))
        except NfdError as exc:
            failed += 1
            click.echo(f"Error: {exc}", err=True)
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
    for exc in errors:
        click.echo(f"Error: {exc}", err=True)
    if not curves and errors:
        sys.exit(EXIT_ERROR)
    ranked = rank_curves(query, curves, top=top, max_distance=max_distance, samples=samples,
                         harmonics=harmonics, scale=scale, method=method,
                         direction="strict" if strict_direction else "invariant", mirror=mirror)
    columns = ["query", "rank", "match", "distance"] + (["shift", "reversed", "mirrored"] if details else [])
    write_rows([{"query": query.id, **row} for row in ranked], columns, output_format)
    if errors:
        click.echo(f"{len(errors)} of {len(files)} files could not be read", err=True)
        sys.exit(EXIT_PARTIAL)


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


if __name__ == "__main__":  # pragma: no cover
    main()
