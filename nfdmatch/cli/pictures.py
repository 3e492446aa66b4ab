"""The picture commands: ``show`` (a query and its matches) and ``matrix`` (all pairs)."""

from __future__ import annotations

import json
from typing import TYPE_CHECKING, Any

import click

from .inputs import read_inputs
from .options import (
    F,
    comparison_options,
    elastic_options,
    finish,
    format_option,
    glob_options,
    index_option,
    input_format_option,
    matching_options,
    note,
    optional_descriptor_options,
    exclude_self_option,
    nothing_matched,
    output_option,
    paths_option,
    refuse_input_as_output,
    some_failed,
)
from .output import (
    delimited_fields,
    delimited_text,
    delimiter,
    deliver,
    path_speller,
    progress_bar,
    resolve_format,
    split_outputs,
    write_rows,
)
from .group import main
from .picture_files import check_pictures, not_written, picture_names, report_picture
from .show_meshes import show_meshes

if TYPE_CHECKING:
    from collections.abc import Callable, Iterable

    import numpy as np

    from ..curve import Curve
    from ..records import ShownMatch
    from ..search.stages import ElasticStage, Stage
    from .options import Comparison


def _parse_size(value: str) -> tuple[int, int]:
    from ..render import MAX_SIDE, MIN_SIDE

    try:
        width, height = (int(v) for v in value.lower().split("x"))
    except ValueError:
        raise click.BadParameter(f"expected WIDTHxHEIGHT in pixels, e.g. 1600x900, got {value!r}") from None
    if not (MIN_SIDE <= width <= MAX_SIDE and MIN_SIDE <= height <= MAX_SIDE):
        raise click.BadParameter(f"width and height must be {MIN_SIDE}..{MAX_SIDE} pixels, got {value!r}")
    return width, height


def _renderer_option(f: F) -> F:
    return click.option(
        "--renderer",
        type=click.Choice(["auto", "matplotlib", "pyvista"]),
        default="auto",
        show_default=True,
        help="Drawing library; auto uses the default and falls back to the other one.",
    )(f)


@main.command()
@click.argument("query_spec", metavar="QUERY")
@click.argument("sources", nargs=-1, metavar="[QUERY...|SOURCE...]")
@click.option(
    "--against",
    is_flag=True,
    help="Rank the files or folders SOURCE... (after the one QUERY) instead of searching an index.",
)
@index_option
@click.option("--top", type=click.IntRange(min=1, max=23), default=5, show_default=True, help="Matches to draw.")
@click.option("--max-distance", type=click.FloatRange(min=0), default=None, help="Only draw matches at most this far.")
@exclude_self_option
@paths_option
@output_option(
    help="The picture to write (.png, .svg or .pdf); for several queries a pattern with {stem} "
    "or {n}, e.g. 'matches-{stem}.png'. Another -o FILE (not a picture) gets the rows drawn.",
    multiple=True,
    required=True,
)
@click.option("--size", default="1600x900", show_default=True, help="Picture size WIDTHxHEIGHT in pixels.")
@_renderer_option
@glob_options(extra=" With --against.")
@elastic_options
@matching_options
@optional_descriptor_options("with --against")
@input_format_option
@format_option(
    help_extra=" of the rows drawn (default: by the extension of their -o, else a table on a "
    "terminal and CSV otherwise)"
)
def show(
    query_spec: str,
    sources: tuple[str, ...],
    against: bool,
    index_path: str,
    top: int,
    max_distance: float | None,
    exclude_self: bool,
    paths: str,
    output: tuple[str, ...],
    size: str,
    renderer: str,
    glob_pattern: str | None,
    stage: ElasticStage | None,
    matching: dict[str, Any],
    descriptor: dict[str, Any],
    input_format: str | None,
    output_format: str | None,
) -> None:
    """Draw each query and its best matches, aligned onto the query, into one picture per query.

    The matches come from the index (--index, as `query` finds them; every QUERY... is a
    query: files, FILE#I, folders) or, with --against, from ranking the curves in
    SOURCE... (then QUERY is the first argument: a file, or a folder of queries). Every
    match is drawn in the query's frame with the rotation, scale, start shift and
    direction of its match: the query in grey under it, start points marked, direction
    of travel shown. Planar curves get a 2-D view. PNG, SVG or PDF by the extension.
    The rows drawn are printed on stdout (query, rank, match, distance, source), or
    written to the -o FILE that is not a picture. --elastic draws the matches of the
    elastic stage (as `query --elastic` orders them) and adds the columns elastic, fused.
    A mesh QUERY against an index of objects draws its contours beside each best object's
    matched contours, all in their principal frames; rows gain curves (docs/objects.md).

    \b
    Examples:
      nfdmatch show sample_curves/queries/trefoil-posed.obj --index demo.h5 -o matches.png
      nfdmatch show q.csv --against library/ --top 8 -o q.svg -o q.csv
      nfdmatch show sample_curves/queries --index demo.h5 -o 'matches-{stem}.png'
      nfdmatch show new_part.stl --index parts.h5 --top 4 -o new_part.png
    """
    pictures, rows_output = split_outputs(output, fmt=output_format)
    output_format = resolve_format(output_format, rows_output)
    width_height = _check_show_arguments(pictures, size, against, sources, (*descriptor.values(), glob_pattern))
    drawing = dict(top=top, max_distance=max_distance, exclude_self=exclude_self, paths=paths, size=width_height,
                   renderer=renderer, stage=stage, matching=matching)  # fmt: skip
    outputs = (pictures[0], rows_output, output_format)
    if not against and show_meshes([query_spec, *sources], index_path, input_format, drawing, outputs):
        return
    query_inputs = read_inputs([query_spec] + ([] if against else list(sources)), input_format=input_format)
    queries = query_inputs.curves
    names = picture_names(pictures[0], queries)
    check_pictures(names)
    chosen = {"max_distance": max_distance, "exclude_self": exclude_self}
    if against:
        source_inputs = read_inputs(sources, glob=glob_pattern, input_format=input_format)
        shown = _ranked_drawn(queries, source_inputs.curves, top, descriptor, {**matching, **chosen}, stage)
        spell_match = path_speller(paths)
    else:
        source_inputs = None
        shown, spell_match = _searched_drawn(
            queries, index_path, top, input_format, {**matching, **chosen}, stage, paths
        )
    spell_query = path_speller(paths)
    for path in [*names, rows_output]:
        refuse_input_as_output(path)
    results = _pictures(queries, shown, names, width_height, renderer)
    stage_columns = list(stage.columns) if stage is not None else []
    write_rows(_drawn_rows(queries, shown, spell_query, spell_match, stage_columns),
               ["query", "rank", "match", "distance", *stage_columns, "source"], output_format, rows_output,
               group_by="query")  # fmt: skip
    for result in results:
        report_picture(result)
    failed = query_inputs.errors + (source_inputs.errors if source_inputs else [])
    finish(len(failed), query_inputs.total + (source_inputs.total if source_inputs else 0))
    nothing_matched(sum(len(drawn) for drawn in shown))


def _pictures(
    queries: list[Curve], shown: list[list[ShownMatch]], names: list[str], size: tuple[int, int], renderer: str
) -> list:
    """Each query's picture drawn (none when some input could not be read)."""
    from ..render import render_matches

    if some_failed():
        return not_written(names)
    return [
        render_matches(q.points, q.id, drawn, name, size=size, renderer=renderer)
        for q, drawn, name in zip(queries, shown, names)
    ]


def _drawn_rows(
    queries: list[Curve],
    shown: list[list[ShownMatch]],
    spell_query: Callable[[str], str],
    spell_match: Callable[[str], str],
    stage_columns: Iterable[str] = (),
) -> list[dict]:
    """The rows of what show drew: query, rank, match, distance, the stage's columns, source
    (ids as --paths says)."""
    return [
        {"query": spell_query(q.id), "rank": s.rank, "match": spell_match(s.id), "distance": s.distance,
         **{name: getattr(s.match, name) for name in stage_columns}, "source": s.source}
        for q, drawn in zip(queries, shown)
        for s in drawn
    ]  # fmt: skip


def _check_show_arguments(
    pictures: list[str], size: str, against: bool, sources: tuple[str, ...], against_only: tuple
) -> tuple[int, int]:
    """show's usage errors, in this order: one picture -o, --size (returned parsed),
    SOURCE... with --against, and the options that go with --against only
    (``against_only``: samples, harmonics, scale, glob)."""
    if len(pictures) != 1:
        raise click.UsageError(
            "show draws one picture per query: give one -o FILE.png (.svg, .pdf), a pattern for several queries"
        )
    width_height = _parse_size(size)
    if against and not sources:
        raise click.UsageError("--against needs at least one SOURCE file or folder")
    if not against and any(against_only):
        raise click.UsageError(
            "--samples/--harmonics/--scale/--glob go with --against: the index fixes its own parameters and curves"
        )
    return width_height


def _ranked_drawn(
    queries: list[Curve], curves: list[Curve], top: int, descriptor: dict, match: dict, stage: Stage | None = None
) -> list[list[ShownMatch]]:
    """What show draws per query with --against: its ``top`` matches among ``curves``."""
    from ..show import show_ranked

    return [show_ranked(q, curves, k=top, stage=stage, **descriptor, **match) for q in queries]


def _searched_drawn(
    queries: list[Curve],
    index_path: str,
    top: int,
    input_format: str | None,
    match: dict,
    stage: Stage | None = None,
    paths: str = "id",
) -> tuple[list[list[ShownMatch]], Callable[[str], str]]:
    """What show draws per query from the index: its ``top`` matches, their curves read
    back from their files (notes on stderr for those that cannot be); and how --paths
    spells their ids (``id -> str``, resolved while the index is open)."""
    from functools import partial

    from ..formats import read_curve
    from ..index import open_index
    from ..show import show_searched

    shown = []
    with open_index(index_path) as idx:
        for q in queries:
            drawn, notes = show_searched(
                q, idx, k=top, read_curve=partial(read_curve, format=input_format), stage=stage, **match
            )
            shown.append(drawn)
            for message in notes:
                note(message)
        speller = path_speller(paths, idx.locate)
        spelled = {s.id: speller(s.id) for drawn in shown for s in drawn}
    return shown, spelled.__getitem__


@main.command()
@click.argument("sources", nargs=-1, required=True, metavar="FILE_OR_FOLDER...")
@output_option(
    help="FILE.png: draw the matrix as a shaded picture (darker = more similar); any other FILE: "
    "write the matrix there instead of stdout. Give -o twice for both.",
    multiple=True,
)
@glob_options()
@comparison_options
@click.option(
    "--order",
    type=click.Choice(["input", "similar"]),
    default="input",
    show_default=True,
    help="Row order: as found, or similar curves next to each other (average-linkage tree).",
)
@click.option(
    "--rerank",
    is_flag=True,
    help="The diffused similarity over the curves' neighbour graph instead of the distance "
    "(higher is closer; docs/rerank.md).",
)
@click.option(
    "--elastic",
    is_flag=True,
    help="The elastic stage's fused distance (exact, elastic and shape statistics at each pair's "
    "exact optimum; docs/elastic.md) instead of the exact distance; with --rerank, its diffusion.",
)
@format_option(("csv", "tsv", "json"), help_extra=" of the matrix [default: by the extension of -o, else csv]")
def matrix(
    sources: tuple[str, ...],
    output: tuple[str, ...],
    glob_pattern: str | None,
    comparison: Comparison,
    order: str,
    rerank: bool,
    elastic: bool,
    output_format: str | None,
) -> None:
    """The distance between every pair of curves in FILE_OR_FOLDER... .

    Rows (stdout, or -o FILE.csv/.tsv/.json): CSV/TSV with a header row
    `id,<id 1>,<id 2>,...` then one row per curve, its id first; or JSON
    {"ids": [...], "distances": [[...], ...]}. Symmetric, zero diagonal, curves in the
    order found (files sorted, curves in file order), or with --order similar grouped by
    similarity. With -o FILE.png, also a grey-level picture like the paper's Figure 7.
    With --rerank the entries are the re-ranked similarity of every pair (diffusion over
    the curves' 8-nearest-neighbour graph, 1 on the diagonal, higher is closer; JSON key
    "scores"), what `query --rerank` ranks by. With --elastic the entries are the fused
    distance of the elastic stage (what `query --elastic` ranks by; docs/elastic.md).

    \b
    Examples:
      nfdmatch matrix sample_curves/library -o matrix.png > matrix.csv
      nfdmatch matrix sample_curves/library -o matrix.png -o matrix.json
    """
    from ..search import distance_matrix, similarity_order

    formats = ("csv", "tsv", "json")
    pictures, rows_output = split_outputs(output, formats, output_format)
    check_pictures(pictures)  # before the O(N^2) work, not after it
    fmt = resolve_format(output_format, rows_output, formats, terminal="csv")
    inputs = read_inputs(sources, glob=glob_pattern, input_format=comparison.input_format)
    for path in [*pictures, rows_output]:
        refuse_input_as_output(path)
    curves = inputs.curves
    progress, finish_bar = progress_bar("distances")
    try:
        distances = distance_matrix(curves, progress=progress, elastic=elastic, **comparison.keywords())
    finally:
        finish_bar()
    ids = [c.id for c in curves]
    what = "fused elastic" if elastic else comparison.matching["method"]
    title = f"{what} distance, {len(ids)} curves"
    values = distances
    if rerank:
        lists = None
        if elastic:  # the graph `index build --graph --elastic` stores: fused lists of exact candidates
            from ..search.rerank import fused_graph_lists

            lists = fused_graph_lists(distance_matrix(curves, **comparison.keywords()), distances, ids)
        values, distances = _reranked(distances, ids, lists)
        title = f"re-ranked similarity ({what} distance), {len(ids)} curves"
    if order == "similar":
        permutation = similarity_order(distances)
        distances = distances[permutation][:, permutation]
        values = values[permutation][:, permutation]
        ids = [ids[i] for i in permutation]
    text = _matrix_text(ids, values, fmt, rerank)
    deliver(text, rows_output)
    if some_failed():
        pictures = not_written(pictures)
    if pictures:
        from ..render import render_matrix

        for path in pictures:
            report_picture(render_matrix(distances, ids, path, title=title))
    inputs.finish()


def _reranked(distances: np.ndarray, ids: list[str], lists: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """``(similarity, dissimilarity)``: the diffused similarity of every pair (ties among a
    curve's neighbours by ``ids``, as the stored graph orders them; ``lists``: a fused graph's
    lists, with --elastic) and, for the pictures and the similarity order, 1 - it (0 on the
    diagonal)."""
    import numpy as np

    from ..search.rerank import diffused_similarity

    values = diffused_similarity(distances, ids=ids, lists=lists)
    distances = np.clip(1 - values, 0, None)
    np.fill_diagonal(distances, 0.0)
    return values, distances


def _matrix_text(ids: list[str], values: np.ndarray, fmt: str, rerank: bool) -> str:
    """The matrix as JSON (``ids`` and ``distances``, or ``scores`` with --rerank) or as
    CSV/TSV rows (a header row of ids, then each curve's id and row). The ids are written
    as the file names they encode (:func:`~nfdmatch.names.decode_name`), as every row format does."""
    from ..names import decode_name

    ids = [decode_name(i) for i in ids]
    if fmt == "json":
        return json.dumps({"ids": ids, ("scores" if rerank else "distances"): values.tolist()}, indent=1) + "\n"
    # the entries are float reprs, which never need quoting: each row is joined directly
    # (the csv writer took 1.3 s for the 2 M entries of 1,400 curves); only the ids go
    # through the writer's quoting
    sep = delimiter(fmt)
    lines = [delimited_text(["id"] + ids, [], fmt)]
    lines += [
        f"{field}{sep}{entries}\n" for field, entries in zip(delimited_fields(ids, fmt), _entry_rows(values, sep))
    ]
    return "".join(lines)


def _entry_rows(values: np.ndarray, sep: str) -> list[str]:
    """Each row's entries as text joined by ``sep`` (``repr``: the shortest that reads back
    the same float); a symmetric matrix's entries are written out once for both triangles
    (2 M entries of 1,400 curves: half of the formatting time)."""
    import numpy as np

    N = len(values)
    if not np.array_equal(values, values.T):
        return [sep.join(map(repr, row)) for row in values.tolist()]
    upper = np.triu_indices(N)
    texts = list(map(repr, values[upper].tolist()))
    grid = np.empty((N, N), dtype=object)
    grid[upper] = texts
    grid.T[upper] = texts
    return [sep.join(row) for row in grid.tolist()]
