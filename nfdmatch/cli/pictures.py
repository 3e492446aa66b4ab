"""The picture commands: ``show`` (a query and its matches) and ``matrix`` (all pairs)."""

from __future__ import annotations

import json
import sys

import click

from .common import (EXIT_OK, EXIT_PARTIAL, handle_errors, index_option, input_format_option,
                     matching_options, descriptor_options, optional_descriptor_options, output_option,
                     progress_bar, read_sources, write_delimited, write_rows)
from .group import main


def _parse_size(value: str) -> tuple[int, int]:
    from ..render import MAX_SIDE, MIN_SIDE

    try:
        width, height = (int(v) for v in value.lower().split("x"))
    except ValueError:
        raise click.BadParameter(f"expected WIDTHxHEIGHT in pixels, e.g. 1600x900, got {value!r}")
    if not (MIN_SIDE <= width <= MAX_SIDE and MIN_SIDE <= height <= MAX_SIDE):
        raise click.BadParameter(f"width and height must be {MIN_SIDE}..{MAX_SIDE} pixels, got {value!r}")
    return width, height



def _renderer_option(f):
    return click.option("--renderer", type=click.Choice(["auto", "matplotlib", "pyvista"]), default="auto",
                        show_default=True,
                        help="Drawing library; auto uses the default and falls back to the other one.")(f)



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
@optional_descriptor_options
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
    from ..descriptors import DEFAULT_HARMONICS, DEFAULT_SAMPLES, DEFAULT_SCALE
    from ..formats import read_curve
    from ..render import MatchPanel, render_matches

    width_height = _parse_size(size)
    direction = "strict" if strict_direction else "invariant"
    query = read_curve(query_spec, format=input_format)
    notes: list[str] = []
    exit_code = EXIT_OK
    if against:
        if not sources:
            raise click.UsageError("--against needs at least one SOURCE file or folder")
        from ..search import rank_curves
        from ..show import matches_from_curves

        curves, errors, _ = read_sources(sources, glob_pattern, input_format)
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

        from ..index import open_index
        from ..search import search_index
        from ..show import matches_from_index

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
    from ..search import distance_matrix, similarity_order

    if output:
        from ..render import check_output

        check_output(output)                  # before the O(N^2) work, not after it
    curves, errors, files = read_sources(sources, glob_pattern, input_format)
    progress, finish = progress_bar("distances")
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
        write_delimited(["id"] + ids, ([curve_id] + [repr(float(v)) for v in row]
                                        for curve_id, row in zip(ids, distances)), output_format)
    if output:
        from ..render import render_matrix

        _report_picture(render_matrix(distances, ids, output,
                                      title=f"{method} distance, {len(ids)} curves"))
    if errors:
        click.echo(f"{len(errors)} of {len(files)} files could not be read", err=True)
        sys.exit(EXIT_PARTIAL)

