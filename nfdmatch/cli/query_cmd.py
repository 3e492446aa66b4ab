"""`nfdmatch query`: the k nearest curves of an index for every query curve."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import click

from ..defaults import DEFAULT_ELASTIC_DEPTH
from ..matching import DEFAULT_DIRECTION, DEFAULT_METHOD
from .inputs import read_inputs
from .options import (
    query_batch_options,
    count_failures,
    note,
    error,
    finish,
    nothing_matched,
    output_option,
    rows_format_option,
    say,
)
from .output import match_columns, match_row, path_speller, progress_bar, resolve_format, write_rows
from .cluster import open_cluster, ranges_option, scheduler_options
from .group import main

if TYPE_CHECKING:
    from collections.abc import Callable, Iterable

    from ..curve import Curve
    from ..index import Index
    from ..records import RankedMatch
    from ..search.index_search import SearchResults, SearchStats
    from ..search.stages import Stage
    from .inputs import Inputs
    from .options import QueryBatch, MatchListing, Rerank


@main.command()
@query_batch_options(
    "Matches per query.",
    " Of the QUERY folders.",
    "Compute every exact distance, no pruning (to check a result: the pruned search "
    "returns the same rows and distances).",
    click.option(
        "--stats", "show_stats", is_flag=True, help="Print on stderr how many exact distances the search needed."
    ),
)
@scheduler_options
@ranges_option
@rows_format_option
@output_option()
def query(
    batch: QueryBatch,
    show_stats: bool,
    scheduler: str | None,
    scheduler_timeout: float,
    ranges: int | None,
    output_format: str | None,
    output: str | None,
) -> None:
    """Find the curves of the index most similar to each curve in QUERY... .

    QUERY: files (FILE#I for one curve of a multi-curve file; `-` for stdin) or folders;
    every curve in them is a query, answered with the index's own samples, harmonics and
    scale. Rows: query, rank, match, distance (ties ordered by id). The search is exact:
    rows are visited in increasing order of proven lower bounds (cells of the index, then
    invariant features, then the first harmonics) and the search stops when the next bound
    exceeds the K-th distance; --exhaustive computes every distance instead (same answer).
    Inputs that cannot be read are named on stderr and the others answered (exit 3). A mesh
    QUERY (STL, PLY, OFF, GLB/GLTF, OBJ with faces) ranks an index's objects: rows query,
    rank, match, distance, curves (docs/objects.md); a curve's rows gain object.

    --rerank: the query joins the neighbour graph stored in the index through its exact 8
    nearest; its candidates (its nearest and the M curves its personalised PageRank over the
    graph reaches most, --rerank-depth) are ordered by a diffusion over the whole graph, the
    top K by the diffused score (docs/rerank.md). Rows gain the column score; deterministic.

    --elastic: the elastic stage (docs/elastic.md): the exact top M (--elastic-depth)
    ordered by a fused distance of the exact distance, an elastic distance (the best
    correspondence that bends) and pose-free shape statistics. Rows gain the columns elastic
    and fused (what they are ranked by); distance stays the exact distance. On an index
    whose graph holds fused distances (`index build --graph K --elastic`), --rerank diffuses
    over them, the query's candidates given theirs; --elastic --rerank then adds the columns
    elastic and fused to score.

    \b
    Examples:
      nfdmatch query sample_curves/queries/trefoil-posed.obj --index demo.h5 --top 5
      nfdmatch query new_scans/ --index curves.h5 --top 1 --format jsonl -o matches.jsonl
      nfdmatch query library/ --index library.h5 --exclude-self --top 3
      nfdmatch query library/ --index library.h5 --exclude-self --rerank --top 3
      nfdmatch query scans/ --index library.h5 --elastic --top 5
      nfdmatch query batch/ --index /shared/scans.h5 --scheduler tcp://head:8786 -o matches.csv
    """
    from ..index import open_index

    output_format = resolve_format(output_format, output)
    check_search_options(batch, scheduler)
    with open_index(batch.index_path) as idx:
        if _query_meshes(idx, batch, scheduler, (output_format, output)):
            return
        inputs, (results, stats) = answer_queries(idx, batch, (scheduler, scheduler_timeout, ranges))
        columns = row_columns(batch.listing.details, batch.rerank, batch.stage)
        rows, columns = _curve_rows(idx, inputs.curves, results, batch.listing, columns)
    write_rows(rows, columns, output_format, output, group_by="query")
    if show_stats:
        say(_stats_line(stats))
    inputs.finish()
    nothing_matched(len(rows), f"no match for any of the {len(inputs.curves)} queries")


def _curve_rows(
    idx: Index, curves: list[Curve], results: list[list[RankedMatch]], listing: MatchListing, columns: list[str]
) -> tuple[list[dict], list[str]]:
    """The rows and columns of a curve query's answers (the match spelled while the index is
    open); an index of objects adds the column object (the mesh of a matched contour)."""
    spell_query, spell_match = path_speller(listing.paths), path_speller(listing.paths, idx.locate)
    match_spelling = {m.id: spell_match(m.id) for res in results for m in res}
    object_of = _objects_of(idx, match_spelling, spell_match)
    rows = [
        {**match_row(spell_query(q.id), m), "match": match_spelling[m.id], "object": (object_of or {}).get(m.id, "")}
        for q, res in zip(curves, results)
        for m in res
    ]
    return rows, columns + (["object"] if object_of is not None else [])


def _query_meshes(idx: Index, batch: QueryBatch, scheduler: str | None, output_at: tuple[str, str | None]) -> bool:
    """Answer a query of meshes (:func:`_query_objects`) and say so; False for a query of
    curves (nothing done)."""
    meshes = mesh_queries(idx, batch.queries, batch.listing.glob, batch.input_format)
    if meshes:
        _query_objects(idx, meshes, batch, scheduler, *output_at)
    return bool(meshes)


def answer_queries(
    idx: Index, batch: QueryBatch, cluster_at: tuple[str | None, float | None, int | None]
) -> tuple[Inputs, SearchResults]:
    """The curves of the batch's QUERY... read and searched in the open index ``idx``
    (:func:`search_queries`), after the notes on an old index and the options checked
    against it; ``cluster_at``: --scheduler, its timeout, --ranges."""
    scheduler, _, ranges = cluster_at
    note_old_format(idx, batch.exhaustive, batch.stage, rerank=batch.rerank is not None)
    check_stage_options(batch, scheduler, idx)
    inputs = read_inputs(batch.queries, glob=batch.listing.glob, input_format=batch.input_format)
    if ranges is not None and not scheduler:
        raise click.UsageError("--ranges needs --scheduler")
    return inputs, search_queries(idx, inputs.curves, batch, cluster_at)


def mesh_queries(idx: Index, queries: Iterable[str], glob: str | None, input_format: str | None) -> list[str]:
    """The query meshes among QUERY... (files named directly; in folders too when the index
    holds objects), or [] for a query of curves. A mix of meshes and curve files is a usage
    error: their rows differ."""
    import os

    from ..mesh.objects import is_mesh_file
    from ..sources import UniquePaths, find_curve_files

    if input_format is not None:
        return []
    has_objects = idx.object_rule() is not None
    found, curves, in_folders = UniquePaths(), [], []  # a mesh given twice is one query
    for q in queries:
        if q != "-" and os.path.isdir(q) and has_objects:
            for f in find_curve_files([q], glob=glob, meshes=True):
                if is_mesh_file(f):
                    found.add(f)
                else:
                    in_folders.append(f)
        elif q != "-" and os.path.isfile(q) and is_mesh_file(q):
            found.add(q)
        else:
            curves.append(q)
    meshes = found.paths
    if not meshes:
        return []
    if in_folders:
        note(f"{len(in_folders)} curve file(s) in the folders left out: the query is of meshes (e.g. {in_folders[0]})")
    if curves:
        raise click.UsageError(
            f"query meshes and curves in separate runs (a mesh ranks objects, a curve ranks curves): "
            f"{meshes[0]} is a mesh, {curves[0]} is not"
        )
    return meshes


def require_objects(idx: Index) -> None:
    """Raise InputError unless the index holds mesh objects (what a mesh query ranks)."""
    from ..errors import InputError

    if idx.object_rule() is None:
        raise InputError(
            "the index holds no mesh objects: a mesh query ranks objects; build the index from meshes",
            path=idx.path,
        )


def report_mesh_failures(failures: list, meshes: list[str]) -> None:
    """Name each query mesh that failed (``failures``: (mesh, NfdError) pairs) and count it
    as a failed input (``-o`` is then not written; the JSON record lists it); raise
    NothingRead when every mesh failed."""
    from .options import NothingRead

    for _, exc in failures:
        error(exc)
    count_failures(len(failures), [exc for _, exc in failures])
    if len(failures) == len(meshes):
        raise NothingRead()


def _query_objects(
    idx: Index, meshes: list[str], batch: QueryBatch, scheduler: str | None, output_format: str, output: str | None
) -> None:
    """Rank the index's objects for each query mesh (docs/objects.md): rows query, rank,
    match (the object's mesh), distance, curves (its contours that were the nearest of some
    query contour). Bad meshes are named and the others answered (exit 3)."""
    listing = batch.listing
    for name, on in (
        ("--rerank", batch.rerank is not None),
        ("--elastic", batch.stage is not None),
        ("--scheduler", scheduler),
        ("--details", listing.details),
        ("--method, --strict-direction or --mirror", batch.matching != _default_matching()),
    ):
        if on:
            raise click.UsageError(f"{name} does not apply to a mesh query (it ranks objects)")
    require_objects(idx)
    failures: list = []
    results = idx.search_objects(
        meshes, k=listing.top, max_distance=listing.max_distance, exclude_self=listing.exclude_self,
        failures=failures, prune=not batch.exhaustive,
    )  # fmt: skip
    report_mesh_failures(failures, meshes)
    spell_query, spell_match = path_speller(listing.paths), path_speller(listing.paths, idx.locate)
    rows = [
        {
            "query": spell_query(q),
            "rank": m.rank,
            "match": spell_match(m.id),
            "distance": m.distance,
            "curves": " ".join("#" + c.rsplit("#", 1)[1] for c in m.curves),
        }
        for q, res in zip(meshes, results)
        for m in res
    ]
    write_rows(rows, ["query", "rank", "match", "distance", "curves"], output_format, output, group_by="query")
    finish(len(failures), len(meshes), "meshes")
    nothing_matched(len(rows), f"no object matched any of the {len(meshes)} query meshes")


def _objects_of(idx: Index, match_spelling: dict[str, str], spell_match: Callable[[str], str]) -> dict[str, str] | None:
    """For an index holding objects: each matched curve id's object (its mesh, spelled as a
    match is; absent for a curve of a curve file), else None (no object column)."""
    from ..errors import IndexFormatError

    try:
        if idx.object_rule() is None:
            return None
        objects = set(idx.object_ids())
    except IndexFormatError as exc:  # the curves answer without it: /objects is only their tag
        note(f"{exc}; the object column is left out (`nfdmatch index verify` lists what is bad)")
        return None
    found = {}
    for curve_id in match_spelling:
        mesh = curve_id.rsplit("#", 1)[0]
        if "#" in curve_id and mesh in objects:
            found[curve_id] = spell_match(mesh)
    return found


def _default_matching() -> dict[str, Any]:
    from ..matching import DEFAULT_DIRECTION, DEFAULT_METHOD

    return {"method": DEFAULT_METHOD, "direction": DEFAULT_DIRECTION, "mirror": False}


def row_columns(details: bool, rerank: Rerank | None, stage: Stage | None = None) -> list[str]:
    """The columns of the match rows; with --rerank the score follows the distance, with a
    stage its columns."""
    columns = match_columns(details, stage)
    if rerank is not None:
        columns.insert(columns.index("distance") + 1, "score")
    return columns


def note_old_format(idx: Index, exhaustive: bool, stage: Stage | None = None, *, rerank: bool = False) -> None:
    """A note that a format-1 index (no search cells) bounds every row for each query, that
    an index before format 3 has its statistics computed on read by the elastic stage, that
    a graph of fused distances of an older definition is diffused over by ``--rerank``, and
    that an older file (not ``checked_metadata``) is read whole at each open."""
    from ..errors import IndexFormatError
    from ..index import FORMAT_VERSION
    from ..matching.fused import FUSED_VERSION

    try:
        stored = idx.graph_fused_version() if rerank else None
    except IndexFormatError:  # a damaged graph: --rerank says so when it reads it
        stored = None
    if stored is not None and stored != FUSED_VERSION:
        note(
            f"{idx.path}'s graph holds fused distances of an older definition (version {stored}; this "
            f"nfdmatch computes version {FUSED_VERSION}, docs/elastic.md): --rerank diffuses over them, the "
            f"query's candidates given today's; `nfdmatch index build --index {idx.path}` computes it afresh"
        )

    if idx.format_version < 3 and stage is not None:
        note(
            f"{idx.path} is an index of format {idx.format_version}, without stored shape statistics: "
            f"--elastic computes them for each query's candidates; `nfdmatch index build --index {idx.path}` "
            f"upgrades it to format {FORMAT_VERSION}"
        )
    if idx.format_version < 2 and not exhaustive:
        note(
            f"{idx.path} is an index of format {idx.format_version}, without search cells: every row is "
            f"bounded for each query (slower on large indexes); `nfdmatch index build --index "
            f"{idx.path}` upgrades it"
        )
    if not idx.checked_metadata and idx.format_version >= 2:
        note(
            f"{idx.path} was written before its metadata was checked: every open reads the whole "
            f'file first (docs/index-format.md, "Global heap collections"); `nfdmatch index build '
            f"--index {idx.path}` rewrites it"
        )


def search_queries(
    idx: Index, curves: list[Curve], batch: QueryBatch, cluster_at: tuple[str | None, float | None, int | None]
) -> SearchResults:
    """``(results, stats)`` of the queries under a progress bar, as ``batch`` asks:
    re-ranked (``batch.rerank``; the stage then left to the graph's distances), or searched
    here or on the cluster ``cluster_at`` (--scheduler, its timeout, --ranges)."""
    from ..search import search_index

    rerank, listing = batch.rerank, batch.listing
    scheduler, scheduler_timeout, ranges = cluster_at
    cluster = open_cluster(scheduler, scheduler_timeout) if scheduler else None
    progress, finish_bar = progress_bar("searching")
    try:
        if rerank is not None:
            from ..search.rerank import rerank_index

            return rerank_index(
                idx, curves, k=listing.top, depth=rerank.depth, progress=progress, exclude_self=listing.exclude_self,
                candidates=rerank.candidates,
            )  # fmt: skip
        extra = {} if cluster is None else {"parts": ranges}
        if batch.stage is not None:
            extra["stage"] = batch.stage
        run = search_index if cluster is None else cluster.search_index
        return run(
            idx, curves, progress=progress, prune=not batch.exhaustive, **listing.search(), **extra, **batch.matching
        )
    finally:
        finish_bar()
        if cluster is not None:
            cluster.close()


def check_search_options(batch: QueryBatch, scheduler: str | None) -> None:
    """Usage errors of the search options (:func:`check_rerank_options`,
    :func:`check_stage_options`) before the index is opened."""
    check_rerank_options(batch, scheduler)
    check_stage_options(batch, scheduler)


def check_stage_options(batch: QueryBatch, scheduler: str | None, idx: Index | None = None) -> None:
    """Usage errors of --elastic (``batch.stage``) with --rerank and --scheduler; given the
    open index ``idx``, --elastic --rerank needs its graph to hold fused distances."""
    stage, rerank = batch.stage, batch.rerank
    if stage is None:
        return
    if rerank is not None and stage.depth != DEFAULT_ELASTIC_DEPTH:
        raise click.UsageError("--elastic-depth does not go with --rerank: give --rerank-depth")
    if scheduler:
        raise click.UsageError("--elastic runs on this machine: drop --scheduler")
    if idx is not None and rerank is not None and idx.graph_distance() != "fused":
        raise click.UsageError(
            f"--elastic with --rerank needs a graph of fused distances: build it with `nfdmatch index build "
            f"--index {idx.path} --graph 10 --elastic` (--rerank alone diffuses over the exact graph)"
        )


def check_rerank_options(batch: QueryBatch, scheduler: str | None) -> None:
    """Usage errors for options that --rerank (``batch.rerank``) cannot take."""
    rerank, listing, matching = batch.rerank, batch.listing, batch.matching
    if rerank is None:
        return
    for given, name in (
        (batch.exhaustive, "--exhaustive"),
        (listing.max_distance is not None, "--max-distance"),
        (matching["method"] != DEFAULT_METHOD, f"--method {matching['method']}"),
        (matching["direction"] != DEFAULT_DIRECTION, "--strict-direction"),
        (matching["mirror"], "--mirror"),
    ):
        if given:
            raise click.UsageError(
                f"--rerank cannot be combined with {name}: the stored graph holds exact, "
                f"direction-invariant distances without mirror images"
            )
    if listing.top > rerank.depth:
        raise click.UsageError(f"--top {listing.top} is more than --rerank-depth {rerank.depth}")
    if scheduler:
        raise click.UsageError("--rerank runs on this machine (the graph and the top M are small): drop --scheduler")


def _stats_line(stats: SearchStats) -> str:
    """What ``--stats`` says of a search (:class:`~nfdmatch.search.SearchStats`)."""
    line = (
        f"{stats.queries} queries x {stats.rows} rows: {stats.exact} exact distances "
        f"({stats.exact_fraction:.2%}), {stats.seconds:.3f} s"
    )
    if stats.pruned:
        line += (
            f"; per query: {stats.per_query(stats.scanned):.0f} rows bounded in "
            f"{stats.per_query(stats.cells):.1f} of {stats.cell_count} cells, "
            f"{stats.per_query(stats.truncated):.0f} truncated-harmonic bounds "
            f"(+{stats.per_query(stats.fine):.0f} finer), "
            f"{stats.per_query(stats.exact):.0f} exact distances, "
            f"{stats.per_query(stats.bytes_read) / 2**20:.2f} MiB read"
        )
    return line + (f"; kernels: {stats.kernels}" if stats.kernels else "")
