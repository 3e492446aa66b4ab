"""What every command shares: output formats and the row writer, the input-format,
descriptor and matching options, the index option, error reporting and exit codes.

stdout carries data only; messages, warnings and errors go to stderr. Exit codes: 0 ok,
1 error (bad input or any NfdError), 2 usage error, 3 partial success (some inputs
failed, the rest was output).
"""

from __future__ import annotations

import csv
import io
import json
import sys
from functools import wraps

import click

from ..errors import NfdError

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
        write_delimited(columns, ([_cell_text(row.get(c)) for c in columns] for row in rows), fmt)
    elif fmt == "json":
        click.echo(json.dumps([{c: row.get(c) for c in columns} for row in rows], indent=2))
    elif fmt == "jsonl":
        for row in rows:
            click.echo(json.dumps({c: row.get(c) for c in columns}))
    else:  # pragma: no cover - click restricts the choices
        raise click.UsageError(f"unknown format {fmt}")


def write_delimited(header: list[str], rows, fmt: str) -> None:
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
    from ..formats import FORMATS

    return click.option("--input-format", "input_format", type=click.Choice(sorted(FORMATS)), default=None,
                        help="Read inputs as this format whatever their extension.")(f)


def descriptor_options(f):
    from ..descriptors import DEFAULT_HARMONICS, DEFAULT_SAMPLES, DEFAULT_SCALE, SCALES

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


def report_errors(errors) -> None:
    """Name every input that failed on stderr (the messages name the file and line)."""
    for exc in errors:
        click.echo(f"Error: {exc}", err=True)


def match_columns(details: bool) -> list[str]:
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



def index_option(f):
    return click.option("--index", "index_path", envvar="NFDMATCH_INDEX", default="nfdmatch.h5",
                        show_default="$NFDMATCH_INDEX or nfdmatch.h5", type=click.Path(dir_okay=False),
                        help="The index file.")(f)


def progress_bar(description: str):
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


def read_sources(sources, glob_pattern, input_format):
    """(curves, errors, files) of the files and folders given; errors named on stderr.
    Exits 1 when no curve could be read; no curve file at all is an error of its own."""
    from ..errors import NoCurvesError
    from ..sources import find_curve_files, read_all

    files = find_curve_files(sources, glob=glob_pattern)
    if not files:
        raise NoCurvesError("no curve files found" + (f" matching {glob_pattern!r}" if glob_pattern else ""),
                            path=", ".join(str(s) for s in sources))
    curves, errors = read_all(files, format=input_format)
    report_errors(errors)
    if not curves:
        sys.exit(EXIT_ERROR)
    return curves, errors, files


def optional_descriptor_options(f):
    """samples/harmonics/scale without defaults: an index fixes them, files take the defaults."""
    from ..descriptors import SCALES

    f = click.option("--scale", type=click.Choice(SCALES), default=None,
                     help="Scale normalization (with --against; default rms).")(f)
    f = click.option("--harmonics", "-k", type=click.IntRange(min=1), default=None,
                     help="Harmonics K (with --against; default 16).")(f)
    f = click.option("--samples", "-n", type=click.IntRange(min=3), default=None,
                     help="Arc-length samples (with --against; default 128).")(f)
    return f

