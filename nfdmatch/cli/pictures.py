"""The picture commands: ``show`` (a query and its matches) and ``matrix`` (all pairs)."""

from __future__ import annotations

import json

import click

from .common import (descriptor_options, deliver, delimited_text, error, format_option, index_option,
                     input_format_option, matching, matching_options, note, optional_descriptor_options,
                     output_option, progress_bar, read_inputs, read_one, say, some_failed, split_outputs,
                     write_rows)
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
        note(result.note)
    say(f"wrote {result.path} ({result.renderer}, {result.seconds:.2f} s)")


def _not_written(pictures) -> list:
    """Pictures, like row files, are written only when every input was read."""
    for path in pictures:
        error(f"{path} not written: some inputs could not be read")
    return []


def _check_pictures(pictures) -> None:
    """Every picture path writable, before any long work."""
    from ..render import check_output

    for path in pictures:
        check_output(path)


@main.command()
@click.argument("query_spec", metavar="QUERY")
@click.argument("sources", nargs=-1, metavar="[SOURCE...]")
@click.option("--against", is_flag=True,
              help="Rank the files or folders SOURCE... instead of searching an index.")
@index_option
@click.option("--top", type=click.IntRange(min=1, max=23), default=5, show_default=True,
              help="Matches to draw.")
@output_option(help="The picture to write (.png); another -o FILE (not .png) gets the rows drawn.",
               multiple=True, required=True)
@click.option("--size", default="1600x900", show_default=True, help="Picture size WIDTHxHEIGHT in pixels.")
@_renderer_option
@click.option("--glob", "glob_pattern", default=None,
              help="Only files in folders whose name matches (with --against).")
@matching_options
@optional_descriptor_options("with --against")
@input_format_option
@format_option(help_extra=" of the rows drawn (default: by the extension of their -o, else a table on a "
                          "terminal and CSV otherwise)")
def show(query_spec, sources, against, index_path, top, output, size, renderer, glob_pattern, method,
         strict_direction, mirror, samples, harmonics, scale, input_format, output_format):
    """Draw QUERY and its best matches, each aligned onto the query, into one picture.

    The matches come from the index (--index, as `query` finds them) or, with --against,
    from ranking the curves in SOURCE... . Every match is drawn in the query's frame with
    the rotation, scale, start shift and direction of its match: the query in grey under
    it, start points marked, direction of travel shown. Planar curves get a 2-D view.
    The rows drawn are printed on stdout (query, rank, match, distance, source), or
    written to the -o FILE that is not a picture.

    \b
    Examples:
      nfdmatch show sample_curves/queries/trefoil-posed.obj --index demo.h5 -o matches.png
      nfdmatch show q.csv --against library/ --top 8 -o q.png -o q.csv
    """
    from functools import partial

    from ..render import render_matches
    from ..show import match_panels, show_ranked, show_searched

    pictures, rows_output = split_outputs(output)
    if len(pictures) != 1:
        raise click.UsageError("show draws one picture: give one -o FILE.png")
    width_height = _parse_size(size)
    if against and not sources:
        raise click.UsageError("--against needs at least one SOURCE file or folder")
    if not against and sources:
        raise click.UsageError("SOURCE... is only read with --against (without it, the index is searched)")
    if not against and (samples or harmonics or scale or glob_pattern):
        raise click.UsageError("--samples/--harmonics/--scale/--glob go with --against: "
                               "the index fixes its own parameters and curves")
    _check_pictures(pictures)
    query = read_one(query_spec, input_format)
    if against:
        inputs = read_inputs(sources, glob=glob_pattern, input_format=input_format)
        shown = show_ranked(query, inputs.curves, top=top, samples=samples, harmonics=harmonics, scale=scale,
                            **matching(method, strict_direction, mirror))
    else:
        from ..index import open_index
        from ..formats import read_curve

        inputs = None
        with open_index(index_path) as idx:
            shown, notes = show_searched(query, idx, top=top, read_curve=partial(read_curve, format=input_format),
                                         **matching(method, strict_direction, mirror))
        for message in notes:
            note(message)
    if some_failed():
        pictures = _not_written(pictures)
    result = None if not pictures else render_matches(query.points, query.id, match_panels(shown), pictures[0], size=width_height,
                            renderer=renderer)
    write_rows([{"query": query.id, "rank": s.rank, "match": s.id, "distance": s.distance, "source": s.source}
                for s in shown], ["query", "rank", "match", "distance", "source"], output_format, rows_output,
               group_by="query")
    if result is not None:
        _report_picture(result)
    if inputs is not None:
        inputs.finish()


@main.command()
@click.argument("sources", nargs=-1, required=True, metavar="FILE_OR_FOLDER...")
@output_option(help="FILE.png: draw the matrix as a shaded picture (darker = more similar); any other FILE: "
                    "write the matrix there instead of stdout. Give -o twice for both.", multiple=True)
@click.option("--glob", "glob_pattern", default=None, help="Only files in folders whose name matches.")
@matching_options
@descriptor_options
@input_format_option
@click.option("--order", type=click.Choice(["input", "similar"]), default="input", show_default=True,
              help="Row order: as found, or similar curves next to each other (average-linkage tree).")
@format_option(("csv", "tsv", "json"), help_extra=" of the matrix [default: by the extension of -o, else csv]")
def matrix(sources, output, glob_pattern, method, strict_direction, mirror, samples, harmonics, scale,
           input_format, order, output_format):
    """The distance between every pair of curves in FILE_OR_FOLDER... .

    Rows (stdout, or -o FILE.csv/.tsv/.json): CSV/TSV with a header row
    `id,<id 1>,<id 2>,...` then one row per curve, its id first; or JSON
    {"ids": [...], "distances": [[...], ...]}. Symmetric, zero diagonal, curves in the
    order found (files sorted, curves in file order), or with --order similar grouped by
    similarity. With -o FILE.png, also a grey-level picture like the paper's Figure 7.

    \b
    Examples:
      nfdmatch matrix sample_curves/library -o matrix.png > matrix.csv
      nfdmatch matrix sample_curves/library -o matrix.png -o matrix.json
    """
    from ..search import distance_matrix, similarity_order
    from .common import resolve_format

    pictures, rows_output = split_outputs(output)
    _check_pictures(pictures)                # before the O(N^2) work, not after it
    fmt = resolve_format(output_format, rows_output)
    fmt = "csv" if fmt not in ("csv", "tsv", "json") else fmt
    inputs = read_inputs(sources, glob=glob_pattern, input_format=input_format)
    curves = inputs.curves
    progress, finish_bar = progress_bar("distances")
    try:
        distances = distance_matrix(curves, samples=samples, harmonics=harmonics, scale=scale, progress=progress,
                                    **matching(method, strict_direction, mirror))
    finally:
        finish_bar()
    ids = [c.id for c in curves]
    if order == "similar":
        permutation = similarity_order(distances)
        distances = distances[permutation][:, permutation]
        ids = [ids[i] for i in permutation]
    if fmt == "json":
        text = json.dumps({"ids": ids, "distances": distances.tolist()}, indent=1) + "\n"
    else:
        text = delimited_text(["id"] + ids, ([curve_id] + [repr(float(v)) for v in row]
                                             for curve_id, row in zip(ids, distances)), fmt)
    deliver(text, rows_output)
    if some_failed():
        pictures = _not_written(pictures)
    if pictures:
        from ..render import render_matrix

        for path in pictures:
            _report_picture(render_matrix(distances, ids, path, title=f"{method} distance, {len(ids)} curves"))
    inputs.finish()
