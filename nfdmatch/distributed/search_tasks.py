"""Search tasks on the workers: a block of queries over a range of an index's cells (or, for
the first round, over each query's window of cells), answered by the one search engine."""

from __future__ import annotations

from typing import Any, TYPE_CHECKING

import numpy as np

from ..search.bounds import feature_vector
from ..search.engine import BestRows, Cascade, QueryWork, search_block
from ..errors import ReadError
from .settings import ClusterError

if TYPE_CHECKING:
    from ..index.reader import Index
    from ..search.engine import BestRows, Cascade
    from ..records import RankedMatch
    from collections.abc import Sequence


def index_ranges(idx: Index, parts: int, prune: bool) -> tuple[list[tuple[str, int, int]], int]:
    """``(ranges, cell_count)``: the index split into at most ``parts`` ranges of about equal
    rows. A pruned search takes ranges of search cells ``("cells", first, stop)`` (format
    2; format 1 has one cell holding every row), an exhaustive one ranges of rows
    ``("rows", start, stop)``."""
    N = idx.n_curves
    if not prune:
        edges = np.linspace(0, N, min(parts, N) + 1).round().astype(np.int64)
        return [("rows", int(a), int(b)) for a, b in zip(edges[:-1], edges[1:]) if b > a], 0
    if idx.format_version < 2:
        return [("cells", 0, 1)], 1
    start = np.asarray(idx._read(lambda: idx._h5["search"]["cell_start"][...]), dtype=np.int64)
    C = len(start) - 1
    parts = max(1, min(parts, C))
    # cut where the cumulative positions pass each 1/parts of the rows
    cuts = np.searchsorted(start, np.linspace(0, N, parts + 1)[1:-1], side="left")
    edges = np.unique(np.concatenate([[0], cuts, [C]]))
    return [("cells", int(a), int(b)) for a, b in zip(edges[:-1], edges[1:]) if b > a], C


#: per worker process: open indexes and their search tables, keyed by path and stamp, so the
#: blocks of queries of one batch (and the next batches) reuse the cells already read
_OPEN: dict = {}


def _worker_index(path: str, stamp: tuple):
    from ..index import open_index

    key = (path, stamp)
    entry = _OPEN.get(key)
    if entry is None:
        for old_key in [k for k in _OPEN if k[0] == path]:  # a replaced index: drop the old one
            _OPEN.pop(old_key)[0].close()
        idx = open_index(path)
        if index_stamp(idx) != tuple(stamp):
            idx.close()
            raise ClusterError(
                "the index a worker opened is not the one the client opened (replaced by a "
                "build meanwhile, or another file at that path on the worker): query again",
                path=path,
            )
        entry = _OPEN[key] = [idx, None, {}]
    return entry


def pairs_part(
    path: str, stamp: tuple, first: int, stop: int, max_distance: float, cascade: Cascade, rows: np.ndarray | None
) -> dict:
    """On a worker: the pairs within ``max_distance`` whose first row lies in the search
    cells ``[first, stop)`` (:func:`nfdmatch.search.join.pairs_within`); the index's rows
    are read once per worker process and kept for its other parts.

    Returns ``{"pairs": (a, b, distance) arrays, cell_pairs, bounded, truncated, fine,
    exact}``."""
    from ..search.join import join_input, pairs_within

    entry = _worker_index(path, stamp)
    idx, cache = entry[0], entry[2]
    if "join" not in cache:
        if entry[1] is None:
            entry[1] = idx.search_table()
        cache["join"] = join_input(entry[1], idx.coefficients_at)
    a, b, d, stats = pairs_within(
        cache["join"], idx.coefficients_at, max_distance, cascade, rows=rows, cells=(first, stop), threads=1
    )
    out = {key: getattr(stats, key) for key in ("cell_pairs", "bounded", "truncated", "fine", "exact")}
    out["pairs"] = (a, b, d)
    return out


def index_stamp(idx: Index) -> tuple:
    """What a worker checks that the index it opened is the client's: rows, time of
    writing, descriptor parameters."""
    return (idx.n_curves, idx.updated, idx.samples, idx.harmonics, idx.scale_mode)


def graph_part(path: str, stamp: tuple, block: np.ndarray, k: int) -> dict:
    """On a worker: the neighbour lists of one block of rows of an index being built (its
    temporary file, complete but for ``/graph``, closed by the client until every block is
    answered): each row's ``k`` nearest other rows by
    :func:`nfdmatch.search.graph.nearest_others`, the search of a local build, so the
    lists are the same bytes. The search table is read whole once per worker process (a
    worker's blocks reach most of it) and kept for its other blocks.

    Returns ``{"neighbour": (m, k) int64, "distance": (m, k) float64}``."""
    from ..search.graph import nearest_others

    try:
        entry = _worker_index(path, stamp)
    except ReadError as exc:
        raise ClusterError(
            f"a Dask worker cannot read the index being built ({exc.message}): the index's folder must be on "
            "storage every worker sees under the same path, for --graph with --scheduler (docs/distributed.md)",
            path=path,
        ) from None
    idx, cache = entry[0], entry[2]
    if "graph" not in cache:
        if entry[1] is None:
            entry[1] = idx.search_table()
        entry[1].read_whole()
        cache["graph"] = (np.asarray(idx.ids(), dtype=object), Cascade(idx.samples))
    ids, cascade = cache["graph"]
    block = np.asarray(block, dtype=np.int64)
    task = (block, np.asarray(idx.coefficients_at(block), dtype=np.complex128))
    _, neighbour, distance = nearest_others(entry[1], task, ids, int(k), cascade, 1)
    return {"neighbour": neighbour, "distance": distance}


def forget_index(path: str) -> None:
    """Run on every worker once a build's graph is searched: close the index file at
    ``path`` (the client is about to write into it, then move it into place) and drop what
    was read from it."""
    for key in [key for key in _OPEN if key[0] == path]:
        _OPEN.pop(key)[0].close()


class SeededBestRows(BestRows):
    """A BestRows holding rows found elsewhere (seeds) from the start: a row of this range that
    is also a seed is not added twice (it would count twice towards the K-th distance)."""

    def __init__(self, k: int | None, max_distance: float | None, seed: dict | None) -> None:
        super().__init__(k, max_distance)
        self._seen = np.zeros(0, dtype=np.int64)
        if seed is not None and len(seed["rows"]):
            super().add(
                np.asarray(seed["dist"], dtype=np.float64),
                np.asarray(seed["rows"], dtype=np.int64),
                {key: np.asarray(seed[key]) for key in self.extra if key in seed},
            )
            self._seen = np.sort(np.asarray(seed["rows"], dtype=np.int64))

    def add(self, dist: np.ndarray, rows: np.ndarray, result: dict[str, np.ndarray]) -> None:
        if len(self._seen):
            new = ~_member(rows, self._seen)
            dist, rows = dist[new], rows[new]
            result = {key: result[key][new] for key in self.extra if key in result}
        super().add(dist, rows, result)


def _member(rows: np.ndarray, sorted_rows: np.ndarray) -> np.ndarray:
    """(m,) bool: which ``rows`` are in ``sorted_rows`` (ascending)."""
    if len(sorted_rows) == 0:
        return np.zeros(len(rows), dtype=bool)
    at = np.minimum(np.searchsorted(sorted_rows, rows), len(sorted_rows) - 1)
    return sorted_rows[at] == rows


def search_range(
    path: str,
    stamp: tuple,
    rng: tuple[str, int, int] | None,
    qcoef: np.ndarray,
    seeds: Sequence[Any] | None,
    params: dict,
) -> dict:
    """On a worker: each query's exact top K among the rows of one range of the index.

    rng : ``("cells", first, stop)``, ``("rows", start, stop)`` (exhaustive), or None: the
        window round (each query over its own :data:`WINDOW_ROWS` positions of lowest cell
        bound, for seeds).
    qcoef : (Q, K, 3) complex128 query descriptors; seeds : None or per query a dict like
        one entry of the answer (rows found elsewhere: they count towards the K-th distance,
        so the search prunes as if it had seen them; only this range's rows are returned).

    Returns ``{"tops": [per query {rows (m,) int64, dist (m,) float64, shift (m,) float64,
    reversed (m,) bool, mirrored (m,) bool}], exact, truncated, scanned, cells,
    bytes_read}`` (plain arrays and ints)."""
    entry = _worker_index(path, stamp)
    idx = entry[0]
    cascade = Cascade(idx.samples, params["method"], params["direction"], params["mirror"])
    tops = [
        SeededBestRows(params["top"], params["max_distance"], None if seeds is None else seeds[q])
        for q in range(len(qcoef))
    ]
    # per query: the descriptors of its rows (for the client's recomputation), taken right
    # after its search. Holding each query's table until the end instead kept every query's
    # cells alive at once: a block of 256 queries over half of a 1M-curve index grew a
    # worker past 11 GB
    held = [None] * len(tops)
    want_coef = not params.get("final")

    def own_rows(q):
        return _own_rows(tops[q], None if seeds is None else seeds[q])

    def keep_descriptors(qi, table):
        if want_coef and len(tops[qi].rows):
            positions = tops[qi].extra["position"][own_rows(qi)]
            if len(positions) and positions.min() >= 0:
                held[qi] = table.coefficients_at_positions(positions)

    out, searched = _search_one_range(entry, rng, qcoef, tops, seeds, cascade, params, keep_descriptors)
    if params.get("final"):
        # this task's answer is the query's answer: its distances computed in full,
        # exactly as search_index reports them (from the descriptors of the table searched)
        from ..search.index_search import recompute_reported

        recompute_reported(
            idx,
            qcoef,
            tops,
            cascade.distance,
            direction=params["direction"],
            mirror=params["mirror"],
            weights=None,
            tables=searched,
        )
    out["tops"] = [_answer(tk, own_rows(q), held[q]) for q, tk in enumerate(tops)]
    return out


def _own_rows(tk, seed) -> np.ndarray:
    """Which of a query's rows this task found (not the ``seed`` rows found elsewhere)."""
    if seed is None:
        return np.ones(len(tk.rows), dtype=bool)
    return ~_member(tk.rows, np.sort(np.asarray(seed["rows"], dtype=np.int64)))


def _search_one_range(entry, rng, qcoef, tops, seeds, cascade: Cascade, params, keep_descriptors):
    """Search the range ``rng`` of the worker's index ``entry`` into ``tops``: its rows
    exhaustively, or its cells (None: the window round). Returns the work counts and the
    table searched when one range holds every row (else None)."""
    idx, cache = entry[0], entry[2]
    out = {"exact": 0, "truncated": 0, "fine": 0, "scanned": 0, "cells": 0, "bytes_read": 0}
    searched = None
    if rng is not None and rng[0] == "rows":
        out["exact"], out["bytes_read"] = _rows_round(idx, rng, qcoef, tops, cascade)
        return out, searched
    if entry[1] is None:
        entry[1] = idx.search_table()
    table = entry[1]
    qfeat = feature_vector(qcoef)
    if rng is None:
        work = _window_round(table, qcoef, qfeat, tops, cascade, params, keep_descriptors)
    else:
        searched, work = _cells_round(table, cache, rng, qcoef, qfeat, tops, seeds, cascade, params, keep_descriptors)
    _account(out, work)
    out["bytes_read"] = work.extra["bytes_read"]
    return out, searched


def _answer(tk, keep: np.ndarray, coef) -> dict:
    """One query's answer: the rows this task found, as plain arrays, with their
    descriptors ``coef`` when the client recomputes the distances (no scattered reads)."""
    answer = {
        "rows": tk.rows[keep].astype(np.int64),
        "dist": np.asarray(tk.dist[keep], np.float64),
        "shift": np.asarray(tk.extra["shift"][keep], dtype=np.float64),
        "reversed": np.asarray(tk.extra["reversed"][keep], dtype=bool),
        "mirrored": np.asarray(tk.extra["mirrored"][keep], dtype=bool),
    }
    if coef is not None:
        answer["coef"] = coef
    return answer


def _rows_round(idx, rng, qcoef, tops, cascade: Cascade) -> tuple[int, int]:
    """Every exact distance to the rows ``("rows", lo, hi)`` (an exhaustive search):
    ``(distances, bytes read)``."""
    from ..search.index_search import EXHAUSTIVE_ROWS, exhaustive_rows

    _, lo, hi = rng
    step = EXHAUSTIVE_ROWS * 8
    chunks = (
        (a, idx.read_rows(a, min(hi, a + step), ("coefficients",), upcast=False)["coefficients"])
        for a in range(lo, hi, step)
    )
    return exhaustive_rows(
        qcoef, tops, chunks, cascade.distance, idx.samples, direction=cascade.direction, mirror=cascade.mirror
    )


def _window_round(table, qcoef, qfeat, tops, cascade: Cascade, params: dict, keep) -> QueryWork:
    """The first round: each query over its window's cells of the whole table (the other
    cells skipped), through the one table's reads and cache (a table of its own per query
    copied every cell it opened). ``work.extra["bytes_read"]``: what it read."""
    before = table.bytes_read
    everything = np.arange(table.n_cells)
    outside = [
        np.setdiff1d(everything, _window(table, qfeat[qi], params["window"]), assume_unique=True)
        for qi in range(len(tops))
    ]
    work = search_block(
        table,
        qcoef,
        qfeat,
        tops,
        cascade,
        skip_cells=outside,
        threads=1,
        done=lambda qi, _: keep(qi, table),
        expect_more=False,
    )
    work.extra["bytes_read"] = table.bytes_read - before
    return work


def _cells_round(table, cache, rng, qcoef, qfeat, tops, seeds, cascade: Cascade, params: dict, keep):
    """The queries over the cells ``("cells", lo, hi)``; with seeds, each query skips the
    cells of its window (searched in the first round: their rows within the K-th are all
    among the seeds already). Returns ``(the range's table, work)``, ``work.extra
    ["bytes_read"]`` what it read."""
    _, lo, hi = rng
    if (lo, hi) == (0, table.n_cells):
        sub = table  # the whole index: no second table
    else:
        if ("range", lo, hi) not in cache:
            cache["range", lo, hi] = table.subset((lo, hi))
        sub = cache["range", lo, hi]
    before = sub.bytes_read
    asked, skips = [], []
    for qi in range(len(tops)):
        skip = None
        if seeds is not None:
            # skipped, not copied out into a table of the other cells per query: at 1M that
            # copy was most of a query's time
            window = _window(table, qfeat[qi], params["window"])
            inside = window[(window >= lo) & (window < hi)]
            if len(inside) == hi - lo:
                continue
            skip = inside - lo
        asked.append(qi)
        skips.append(skip)
    work = search_block(
        sub,
        qcoef[asked],
        qfeat[asked],
        [tops[qi] for qi in asked],
        cascade,
        skip_cells=skips,
        threads=1,
        done=lambda i, _: keep(asked[i], sub),
    )
    work.extra["bytes_read"] = sub.bytes_read - before
    return sub, work


class HeldDescriptors:
    """A query's descriptors sent by the workers, behind the one method of a search table
    that :func:`nfdmatch.search.index_search.recompute_reported` uses."""

    def __init__(self, parts: list) -> None:
        self._coef = np.concatenate(parts)

    def coefficients_at_positions(self, positions: np.ndarray) -> np.ndarray:
        return self._coef[positions]


def _window(table, query_features: np.ndarray, positions: int) -> np.ndarray:
    """Ascending numbers of the cells of lowest bound for the query holding at least
    ``positions`` rows (or every cell): the first round's window, the same on every worker."""
    sizes = table.start[1:] - table.start[:-1]
    order = np.argsort(table.cell_bounds(query_features), kind="stable")
    n = int(np.searchsorted(np.cumsum(sizes[order]), positions)) + 1
    return np.sort(order[:n])


def _account(out: dict, work) -> None:
    for key in ("exact", "truncated", "fine", "scanned", "cells"):
        out[key] += getattr(work, key)


def ranked(idx: Index, tops: Sequence[BestRows], top: int | None) -> list[list[RankedMatch]]:
    """The :class:`~nfdmatch.records.RankedMatch` es of :func:`nfdmatch.search.search_index`
    from merged BestRows objects (the same code)."""
    from ..search.index_search import ranked_rows

    return ranked_rows(idx, tops, top)
