"""`nfdmatch report`: a batch of queries, their matches drawn and their rows, in one HTML page."""

from __future__ import annotations

import os
import shlex
import sys
import time
from typing import TYPE_CHECKING

import click

from .group import main
from .options import query_batch_options, say
from .output import match_row, path_speller, progress_bar
from .query_cmd import answer_queries, check_search_options, row_columns

if TYPE_CHECKING:
    from collections.abc import Callable

    from ..curve import Curve
    from ..index import Index
    from ..records import RankedMatch
    from ..report import ReportQuery
    from ..search.index_search import SearchStats
    from .options import QueryBatch


@main.command()
@query_batch_options(
    "Matches per query (each drawn).",
    "Only query files in folders whose name matches.",
    "Compute every exact distance, no pruning (as `query --exhaustive`).",
)
@click.option(
    "--output",
    "-o",
    "output",
    type=click.Path(dir_okay=False),
    required=True,
    metavar="FILE.html",
    help="The page to write (whole, and only when every query was read).",
)
@click.option("--title", default=None, help="The page's title [default: nfdmatch report of INDEX].")
def report(
    batch: QueryBatch,
    output: str,
    title: str | None,
) -> None:
    """Write one HTML page of a batch: each query drawn, its matches aligned onto it, its rows.

    The matches are those `query` finds with the same options (--top, --exclude-self,
    --rerank, --elastic, ...); each is drawn as `show` draws it, over the query in grey.
    The page is one self-contained file (pictures inline as SVG, no network): a summary,
    a table of the queries, then a section per query with its pictures and rows (the
    stage's columns included), linked to one another. A small inline script sorts the
    tables (click a heading) and filters by distance; the page reads the same without it.

    \b
    Examples:
      nfdmatch report sample_curves/queries --index demo.h5 --top 5 -o report.html
      nfdmatch report library/ --index library.h5 --exclude-self --rerank -o neighbours.html
      nfdmatch report scans/ --index library.h5 --elastic -o elastic.html
    """
    from ..index import open_index
    from ..report import write_report

    t0 = time.perf_counter()
    if os.path.splitext(output)[1].lower() not in (".html", ".htm"):
        raise click.UsageError(f"-o {output}: the report is an HTML page: name it FILE.html")
    check_search_options(batch, None)
    listing = batch.listing
    columns = [c for c in row_columns(listing.details, batch.rerank, batch.stage) if c != "query"] + ["source"]
    with open_index(batch.index_path) as idx:
        inputs, (results, stats) = answer_queries(idx, batch, (None, None, None))
        spell = path_speller(listing.paths), path_speller(listing.paths, idx.locate)
        pages = _pages(idx, inputs.curves, results, spell, batch.input_format, batch.matching)
        order = "fused distance (--elastic)" if batch.stage else "distance"
        if batch.rerank is not None:
            order = "diffused score (--rerank)"
        summary = _summary(idx, title or f"nfdmatch report of {batch.index_path or idx.path}", pages, order, stats)
    if inputs.errors:
        inputs.finish()  # exits: a page of part of a batch is not written
    summary["seconds"] = round(time.perf_counter() - t0, 3)
    size = write_report(output, pages, columns, summary)
    say(f"wrote {output} ({len(pages)} queries, {size / 2**20:.1f} MiB, {time.perf_counter() - t0:.2f} s)")
    inputs.finish()


def _pages(
    idx: Index,
    curves: list[Curve],
    results: list[list[RankedMatch]],
    spell: tuple[Callable[[str], str], Callable[[str], str]],
    input_format: str | None,
    matching: dict,
) -> list[ReportQuery]:
    """Each query of the report: its matches aligned onto it (their curves read once each),
    its rows as `query` spells them (``spell``: the query's and the matches' spellers)."""
    from functools import partial

    from ..formats import read_curve
    from ..report import cached_reader, report_query

    spell_query, spell_match = spell
    reader = cached_reader(partial(read_curve, format=input_format))
    progress, finish_bar = progress_bar("drawing")
    pages = []
    try:
        for n, (q, found) in enumerate(zip(curves, results), start=1):
            entry = report_query(q, found, idx, [], read_curve=reader, **matching)
            entry.id, entry.key = spell_query(q.id), _curve_key(q.id)
            entry.rows = [
                {
                    **match_row(entry.id, s.match),
                    "match": spell_match(s.id),
                    "source": s.source,
                    "key": _curve_key(idx.locate(s.id)),
                }
                for s in entry.shown
            ]
            pages.append(entry)
            if progress is not None:
                progress(n, len(curves))
    finally:
        finish_bar()
    return pages


def _summary(idx: Index, title: str, pages: list[ReportQuery], order: str, stats: SearchStats) -> dict:
    """The page's summary: what was searched, how, when, and how long it took."""
    return {
        "title": title,
        "index": idx.path,
        "curves in the index": idx.n_curves,
        "queries": len(pages),
        "matches": sum(len(p.rows) for p in pages),
        "order": order,
        "command": shlex.join(["nfdmatch", *sys.argv[1:]]) if sys.argv else "nfdmatch report",
        "written": time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime()),
        "search seconds": round(stats.seconds, 3),
    }


def _curve_key(spec: str) -> str:
    """A curve's name however its path is spelled (the file's real path, ``#i`` kept), so
    that a match links to the query that is the same curve."""
    from ..formats import split_selector

    path, selected = split_selector(spec)
    real = os.path.realpath(path)
    return real if selected is None else f"{real}#{selected}"
