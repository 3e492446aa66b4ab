"""The k-nearest-neighbour graph of an index: each row's K nearest other rows, exactly.

Computed by a build (:func:`nfdmatch.index.graph_build.write_graph` stores it in ``/graph``)
with the self-join (:func:`nfdmatch.search.join.nearest_others`: the rows against each
other cell by cell, each pair's distance once for both rows). Incremental: rows copied
unchanged from the old index keep their lists when none of their neighbours was removed or
changed, and only the new rows can enter them (a search of the new rows for each such
row); every other row's list comes from the join restricted to those rows. The result
equals a from-scratch build (each list is an exact top K, ties by id).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from .bounds import feature_vector, head_harmonics
from .engine import TIE, Cascade, BestRows, search_block
from .table import SearchTable
from .workers import run_tasks

#: ``rows -> their (m, K, 3) complex descriptors`` (or statistics), read from the index
RowReader = Callable[[np.ndarray], np.ndarray]

__all__ = ["GraphLists", "neighbour_lists", "graph_blocks", "nearest_others", "update_copied", "fused_lists"]


#: rows searched per block (their descriptors and lists held at once)
_BLOCK_ROWS = 1024


@dataclass
class GraphLists:
    """A graph's lists being computed, and which rows to compute: ``neighbour`` /
    ``distance`` ((N, k) int64 / float64, filled in place), ``todo`` ((N,) bool: rows to
    search in the whole table), ``check`` (int array: rows whose lists were copied from an
    old graph), ``fresh_rows`` (int array: new or changed rows, which may enter the copied
    lists) with their (m, D) invariant ``features`` (None when nothing is to check)."""

    neighbour: np.ndarray
    distance: np.ndarray
    todo: np.ndarray
    check: np.ndarray
    fresh_rows: np.ndarray
    features: np.ndarray | None = None


def neighbour_lists(
    table: SearchTable,
    read_coefficients: RowReader,
    ids: Sequence[str],
    lists: GraphLists,
    k: int,
    samples: int,
    *,
    threads: int | None = None,
    processes: int = 1,
    close_fds: Sequence[int] = (),
    progress: Callable[[int, int], None] | None = None,
) -> tuple[int, int, int]:
    """Fill ``lists`` with each row's k nearest other rows of ``table``: the rows in
    ``lists.todo`` searched in the whole table, the rows in ``lists.check`` updated where
    one of ``lists.fresh_rows`` enters them. ``ids``: the rows' ids (ties).
    Returns ``(searched, updated, processes)``: rows searched, copied lists that changed,
    worker processes that searched (0: this process did).

    Every row is a query of :func:`~nfdmatch.search.engine.search_block` asking for k + 1
    (the row finds itself), its list the k nearest others, ties by id as a query orders them;
    rows in the table's order (cell by cell), in blocks that share the cells they read. (The
    self-join of :mod:`.join` gives the same lists, but was slower at 100,000 curves: 818 s
    against this search's 484 s then, 77 s now over two processes; docs/selfjoin.md.)

    ``processes`` > 1: the blocks are searched by that many forked processes, each on one
    thread, when this process may fork (:func:`nfdmatch._fork.can_fork`) and the table hands
    out every harmonic (it is read whole first: the workers never read the file); else
    here, on ``threads``. The lists are the same either way (each row's search is its own).
    ``close_fds``: descriptors a worker must not keep (the index lock). ``progress(done,
    total)``: rows searched, (0, total) first.
    """
    neighbour, distance = lists.neighbour, lists.distance
    cascade = Cascade(samples)
    blocks = graph_blocks(table, lists.todo)
    queries = _Queries(blocks, read_coefficients)

    total, done = sum(len(block) for block in blocks), 0
    if progress is not None:
        progress(0, total)

    def store(number, got):
        nonlocal done
        block, nb, d = got
        neighbour[block], distance[block] = nb, d
        done += len(block)
        if progress is not None:
            progress(done, total)

    complete = table.stored_harmonics >= table.harmonics  # else workers would read the file
    processes = run_tasks(
        queries,
        lambda task, worker_threads: nearest_others(table, task, ids, k, cascade, worker_threads or threads),
        store,
        processes if complete else 1,
        prepare=table.read_whole,
        close_fds=close_fds,
    )
    updated = update_copied(table, read_coefficients, ids, lists, k, cascade, threads)
    return sum(len(block) for block in blocks), updated, processes


def graph_blocks(table: SearchTable, todo: np.ndarray) -> list[np.ndarray]:
    """The rows to search (``todo`` (N,) bool) in blocks of at most :data:`_BLOCK_ROWS`,
    in the table's order (cell by cell): a block's rows share the cells they read."""
    N = len(todo)
    searched = np.flatnonzero(todo)
    if len(searched) > 1 and table.n_cells:
        positions, rows, _, _ = table.open_cells(np.arange(table.n_cells))
        at = np.empty(N, dtype=np.int64)
        at[rows] = positions
        searched = searched[np.argsort(at[searched], kind="stable")]
    return [searched[a : a + _BLOCK_ROWS] for a in range(0, len(searched), _BLOCK_ROWS)]


class _Queries:
    """The blocks of rows to search, each with its rows' descriptors read when asked for
    (in this process: a worker never reads the index)."""

    def __init__(self, blocks, read_coefficients):
        self.blocks, self.read = blocks, read_coefficients

    def __len__(self) -> int:
        return len(self.blocks)

    def __getitem__(self, number: int):
        block = self.blocks[number]
        return block, np.asarray(self.read(block), dtype=np.complex128)


def nearest_others(
    table: SearchTable, task: tuple[np.ndarray, np.ndarray], ids: Sequence[str], k: int, cascade: Cascade,
    threads: int | None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # fmt: skip
    """``(block, neighbour, distance)``: the lists ((m, k) int64 / float64) of the m rows of
    ``task`` ``(block, their (m, K, 3) complex128 descriptors)``, each from one search."""
    block, q = task
    got = [BestRows(k + 1, None) for _ in block]
    search_block(table, q, feature_vector(q), got, cascade, threads=threads)
    nb = np.empty((len(block), k), dtype=np.int64)
    d = np.empty((len(block), k))
    for j, (i, tk) in enumerate(zip(block, got)):
        nb[j], d[j] = _ordered(int(i), tk.rows, tk.dist, ids, k)
    return block, nb, d


def update_copied(
    table: SearchTable, read_coefficients: RowReader, ids: Sequence[str], lists: GraphLists, k: int,
    cascade: Cascade, threads: int | None,
) -> int:  # fmt: skip
    """Update the copied lists of the rows ``lists.check`` where one of ``lists.fresh_rows``
    enters them (see :func:`neighbour_lists`); returns how many changed."""
    neighbour, distance, check, fresh_rows = lists.neighbour, lists.distance, lists.check, lists.fresh_rows
    features = lists.features
    changed = 0
    if not (len(check) and len(fresh_rows)):
        return changed
    K = table.harmonics
    head = read_coefficients(fresh_rows)[:, : head_harmonics(K)]
    small = SearchTable.single_cell(K, features, head, lambda r: read_coefficients(fresh_rows[r]))
    for a in range(0, len(check), _BLOCK_ROWS):
        block = check[a : a + _BLOCK_ROWS]
        q = np.asarray(read_coefficients(block), dtype=np.complex128)
        # a copied list changes only where a fresh row comes within its k-th distance
        got = [BestRows(k, float(distance[i, -1]) + TIE) for i in block]
        search_block(small, q, feature_vector(q), got, cascade, threads=threads)
        for i, tk in zip(block, got):
            if len(tk.rows):
                before = neighbour[i].copy()
                neighbour[i], distance[i] = _ordered(
                    int(i),
                    np.concatenate([neighbour[i], fresh_rows[tk.rows]]),
                    np.concatenate([distance[i], tk.dist]),
                    ids,
                    k,
                )
                changed += not np.array_equal(before, neighbour[i])
    return changed


def _ordered(i, rows, d, ids, k):
    """Row i's list ``(neighbour (k,) int64, distance (k,) float64)``: the k nearest of
    ``rows`` other than i, ties (1e-9) by id, as a query orders them; padded with -1 / inf."""
    rows, d = np.asarray(rows, dtype=np.int64), np.asarray(d, dtype=np.float64)
    keep = (rows != i) & (rows >= 0)
    rows, d = rows[keep], d[keep]
    order = sorted(range(len(rows)), key=lambda j: (round(float(d[j]) / TIE), ids[rows[j]]))[:k]
    nb = np.full(k, -1, dtype=np.int64)
    dist = np.full(k, np.inf)
    nb[: len(order)] = rows[order]
    dist[: len(order)] = d[order]
    return nb, dist


def fused_lists(
    read_coefficients: RowReader, read_statistics: RowReader, ids: Sequence[str], candidates: np.ndarray, k: int,
    samples: int, *, blocks: Sequence[np.ndarray] | None = None, processes: int = 1, close_fds: Sequence[int] = (),
) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """A fused graph's lists (``index build --graph K --elastic``): of each row's candidates
    (``candidates``: (N, m) int64, its exact m nearest, -1 padded), the ``k`` of least fused
    distance (:func:`nfdmatch.matching.fused.fused_rows`, at each pair's exact optimum), ties
    within ``TIE`` by id. ``read_coefficients(rows)``, ``read_statistics(rows)``: the rows'
    descriptors and shape statistics; ``ids``: every row's id. Returns ``(neighbour (N, k)
    int64, distance (N, k) float64)``, -1 and inf padded.

    ``blocks``: the rows, in the blocks they are computed in (default: in row order, in
    blocks of :data:`_BLOCK_ROWS`); a block reads its rows' candidates once, so blocks of
    rows whose candidates are shared (the search table's order, :func:`graph_blocks`) read
    fewer. ``processes`` > 1: the blocks are computed by that many forked workers
    (:func:`~nfdmatch.search.workers.run_tasks`; this process reads each block's rows for
    them), each closing ``close_fds``. The lists are the same either way: each row's is
    computed from its own candidates alone."""
    N = len(candidates)
    neighbour = np.full((N, k), -1, dtype=np.int64)
    distance = np.full((N, k), np.inf)
    if blocks is None:
        blocks = [np.arange(a, min(N, a + _BLOCK_ROWS)) for a in range(0, N, _BLOCK_ROWS)]

    def store(number, got):
        rows, nb, d = got
        neighbour[rows], distance[rows] = nb, d

    run_tasks(
        _FusedBlocks(blocks, candidates, read_coefficients, read_statistics),
        lambda task, threads: _fused_block(task, ids, k, samples),
        store,
        processes,
        close_fds=close_fds,
    )
    return neighbour, distance


class _FusedBlocks:
    """The blocks of a fused graph's rows, each with what its lists are computed from, read
    when asked for (in this process: a worker never reads the index): ``(rows, their
    candidates, the rows' descriptors and statistics, the distinct candidates (sorted), their
    descriptors and statistics)``."""

    def __init__(self, blocks, candidates, read_coefficients, read_statistics):
        self.blocks, self.candidates = blocks, candidates
        self.read_coefficients, self.read_statistics = read_coefficients, read_statistics

    def __len__(self) -> int:
        return len(self.blocks)

    def __getitem__(self, number: int):
        rows = np.asarray(self.blocks[number], dtype=np.int64)
        block = self.candidates[rows]
        every = np.unique(block[block >= 0])
        return (
            rows,
            block,
            np.asarray(self.read_coefficients(rows), dtype=np.complex128),
            self.read_statistics(rows),
            every,
            np.asarray(self.read_coefficients(every), dtype=np.complex128),
            self.read_statistics(every),
        )


def _fused_block(task, ids: Sequence[str], k: int, samples: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(rows, neighbour (m, k), distance (m, k))``: the fused lists of one block of
    :class:`_FusedBlocks`, each row's from one exact search and one fused call over its
    candidates."""
    from ..matching.exact import exact_search
    from ..matching.fused import fused_rows

    rows, block, mine, mine_statistics, every, theirs, their_statistics = task
    neighbour = np.full((len(rows), k), -1, dtype=np.int64)
    distance = np.full((len(rows), k), np.inf)
    for i in range(len(rows)):
        found = block[i][block[i] >= 0]
        if not len(found):
            continue
        at = np.searchsorted(every, found)
        rigid = exact_search(mine[i], theirs[at], samples)
        terms = fused_rows(
            mine[i], theirs[at], rigid, samples, query_statistics=mine_statistics[i],
            row_statistics=their_statistics[at],
        )  # fmt: skip
        key = np.round(terms.fused / TIE)
        order = sorted(range(len(found)), key=lambda j: (key[j], ids[found[j]]))[:k]
        neighbour[i, : len(order)] = found[order]
        distance[i, : len(order)] = terms.fused[order]
    return rows, neighbour, distance
