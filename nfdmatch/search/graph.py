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

import numpy as np

from .bounds import feature_vector, head_harmonics
from .engine import TIE, Cascade, BestRows, search_block
from .table import SearchTable

__all__ = ["neighbour_lists"]


#: rows searched per block (their descriptors and lists held at once)
_BLOCK_ROWS = 1024


def neighbour_lists(
    table, read_coefficients, ids, neighbour, distance, todo, check, fresh_rows, features, k, samples, threads
) -> tuple[int, int]:
    """Fill ``neighbour`` / ``distance`` ((N, k) int64 / float64) with each row's k nearest
    other rows of ``table``: the rows in ``todo`` ((N,) bool) searched in the whole table,
    the rows in ``check`` (int array: lists copied from an old graph) updated where one of
    ``fresh_rows`` (new or changed rows, with their (m, D) ``features``) enters them.
    Returns ``(searched, updated)``: rows searched, copied lists that changed.

    Every row is a query of :func:`~nfdmatch.search.engine.search_block` asking for k + 1
    (the row finds itself), its list the k nearest others, ties by id as a query orders them;
    rows in the table's order (cell by cell), in blocks that share the cells they read. (The
    self-join of :mod:`.join` gives the same lists, faster at 20,000 curves but slower at
    100,000: 818 s against 484 s, docs/selfjoin.md; the graph keeps the per-row search.)
    """
    N = len(todo)
    K = table.harmonics
    cascade = Cascade(samples)
    searched = np.flatnonzero(todo)
    if len(searched) > 1 and table.n_cells:
        positions, rows, _, _ = table.open_cells(np.arange(table.n_cells))
        at = np.empty(N, dtype=np.int64)
        at[rows] = positions
        searched = searched[np.argsort(at[searched], kind="stable")]

    def search(rows, in_table, tops, store):
        for a in range(0, len(rows), _BLOCK_ROWS):
            block = rows[a : a + _BLOCK_ROWS]
            q = np.asarray(read_coefficients(block), dtype=np.complex128)
            got = tops(block)
            search_block(in_table, q, feature_vector(q), got, cascade, threads=threads)
            for i, tk in zip(block, got):
                store(int(i), tk.rows, tk.dist)

    search(
        searched,
        table,
        lambda block: [BestRows(k + 1, None) for _ in block],
        lambda i, rows, d: _store(i, rows, d, ids, neighbour, distance, k),
    )
    changed = 0
    if len(check) and len(fresh_rows):
        head = read_coefficients(fresh_rows)[:, : head_harmonics(K)]
        small = SearchTable.single_cell(K, features, head, lambda r: read_coefficients(fresh_rows[r]))

        def merge(i, rows, d):
            nonlocal changed
            if len(rows):
                before = neighbour[i].copy()
                _store(
                    i,
                    np.concatenate([neighbour[i], fresh_rows[rows]]),
                    np.concatenate([distance[i], d]),
                    ids,
                    neighbour,
                    distance,
                    k,
                )
                changed += not np.array_equal(before, neighbour[i])

        # a copied list changes only where a fresh row comes within its k-th distance
        search(check, small, lambda block: [BestRows(k, float(distance[i, -1]) + TIE) for i in block], merge)
    return len(searched), changed


def _store(i, rows, d, ids, neighbour, distance, k):
    """Row i's list: the K nearest of ``rows`` other than i, ties (1e-9) by id, as a query orders them."""
    rows, d = np.asarray(rows, dtype=np.int64), np.asarray(d, dtype=np.float64)
    keep = (rows != i) & (rows >= 0)
    rows, d = rows[keep], d[keep]
    order = sorted(range(len(rows)), key=lambda j: (round(float(d[j]) / TIE), ids[rows[j]]))[:k]
    neighbour[i] = -1
    distance[i] = np.inf
    neighbour[i, : len(order)] = rows[order]
    distance[i, : len(order)] = d[order]
