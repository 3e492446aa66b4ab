"""The ``nfdmatch`` click group; the commands register on it from their modules."""

from __future__ import annotations

import click

from .. import __version__
from .options import NfdGroup, verbosity_options


@click.group(cls=NfdGroup, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="nfdmatch")
@verbosity_options
def main():
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

    Exit codes: 0 ok, 1 error (nothing could be read), 2 usage error, 3 some inputs
    failed (each named on stderr; the rest was answered).
    """
