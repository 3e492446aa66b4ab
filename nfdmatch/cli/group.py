"""The ``nfdmatch`` click group; the commands register on it from their modules."""

from __future__ import annotations

import click

from .. import __version__
from .options import NfdGroup, verbosity_options


def _print_version(ctx: click.Context, param: click.Parameter, value: bool) -> None:
    """The version and which kernels this installation runs (ahead-of-time, just-in-time or
    numpy, with the reason): what a bug report needs first."""
    if not value or ctx.resilient_parsing:
        return
    from ..matching.kernels import current

    click.echo(f"nfdmatch, version {__version__}")
    click.echo(f"kernels: {current().describe()}")
    ctx.exit()


@click.group(cls=NfdGroup, context_settings={"help_option_names": ["-h", "--help"]})
@click.option(
    "--version",
    is_flag=True,
    expose_value=False,
    is_eager=True,
    callback=_print_version,
    help="Show the version and which kernels compute (ahead-of-time, just-in-time, numpy), and exit.",
)
@verbosity_options
def main() -> None:
    """Find which stored closed 3-D curves look most like a query curve.

    Curves are read from CSV/TSV/TXT (x,y,z or x,y), OBJ (`l` polylines) and VTK
    (.vtk/.vtp/.vtu line cells). FILE#I selects curve I (0-based) of a multi-curve file;
    `-` reads one file from stdin (give --input-format).

    \b
    Examples:
      nfdmatch distance a.csv b.obj#2
      nfdmatch index build curves/ --index curves.h5
      nfdmatch query q.csv --index curves.h5 --top 5 -o matches.csv
      nfdmatch show q.csv --index curves.h5 -o matches.png
      nfdmatch extract part.stl --sections 20 -o contours/

    Every command: -q errors only, -v more detail (stderr); data on stdout, or with
    -o FILE written whole and only on success (an identical file keeps its bytes and
    gets a fresh mtime, so Make settles); -o - is stdout.

    Exit codes, as grep's: 0 found, 1 nothing matched (a filter left every query
    empty), 2 error (usage, or nothing could be read), 3 some inputs failed (each named
    on stderr; the rest was answered), 130/143 interrupted/terminated.
    """
