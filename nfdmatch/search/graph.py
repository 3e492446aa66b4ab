"""The k-nearest-neighbour graph of an index: each row's K nearest other rows, exactly.

Computed by a build (:func:`nfdmatch.index.graph.write_graph` stores it in ``/graph``).
Incremental: rows copied unchanged from the old index keep their lists when none of their
neighbours was removed or changed, and only the new rows can enter them; every other row is
searched in the new index. The result equals a from-scratch build (each list is an exact
top K, ties by id).
"""

from __future__ import annotations

import os

import numpy as np

from ..matching import dispatch, exact_search
from .bounds import feature_vector, head_harmonics, row_lower_bounds, truncated_lower_bounds, truncated_stages
from .engine import TIE, TopK, margin, search_one
from .table import SearchTable

__all__ = ["neighbour_lists"]


def neighbour_lists(
    table, read_coefficients, ids, neighbour, distance, todo, check, fresh_rows, features, k, samples, threads
) -> tuple[int, int]:
    """Fill ``neighbour`` / ``distance`` ((N, k) int64 / float64) with each row's k nearest
    other rows of ``table``: the rows in ``todo`` ((N,) bool) searched in the whole table,
    the rows in ``check`` (int array: lists copied from an old graph) updated where one of
    ``fresh_rows`` (new or changed rows, with their ``features``) enters them. Returns
    ``(searched, updated)``: rows searched, copied lists that changed."""
    N = len(todo)
    K = table.harmonics
    searched = np.flatnonzero(todo)
    helpers = None
    if len(searched) > 1 and table.n_cells:
        # rows in the table's order (cell by cell): a row's near rows were searched just
        # before it, and their bounds serve it (_Helpers)
        positions, rows, _, _ = table.open_cells(np.arange(table.n_cells))
        at = np.empty(N, dtype=np.int64)
        at[rows] = positions
        searched = searched[np.argsort(at[searched], kind="stable")]
        helpers = _Helpers(table.n_positions, at)
    _run(
        searched,
        lambda i: _search_seeded(i, read_coefficients, table, k + 1, samples, helpers),
        threads,
        lambda i, rows, d: _store(i, rows, d, ids, neighbour, distance, k),
    )
    if len(check) and len(fresh_rows):
        head = read_coefficients(fresh_rows)[:, : head_harmonics(K)]
        small = SearchTable.single_cell(K, features, head, lambda r: read_coefficients(fresh_rows[r]))
        changed = 0

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

        _run(check, lambda i: _search(i, read_coefficients, small, k, samples, distance[i, -1]), threads, merge)
        return len(searched), changed
    return len(searched), 0


def _search(i, read_coefficients, table, top, samples, max_distance):
    """Row i's nearest rows of ``table`` (its own row left out): (rows, distances)."""
    q = np.asarray(read_coefficients([i])[0], dtype=np.complex128)
    tk = TopK(top, None if max_distance is None else float(max_distance) + TIE)
    search_one(
        q,
        feature_vector(q[None])[0],
        table,
        tk,
        search=exact_search,
        method="exact",
        direction="invariant",
        mirror=False,
        samples=samples,
    )
    return tk.rows, tk.dist


#: positions whose invariant bound picks a row's seeds (the cells of smallest bound: its own first)
_SEED_POSITIONS = 256
#: seeds per list entry: the rows of smallest invariant bound whose exact distances set the
#: threshold before the search proper
_SEEDS_PER_ENTRY = 3
#: rows in the first chunk of the first truncated stage (doubling after)
_FIRST_CHUNK = 512


class _Helpers:
    """Lower bounds of the exact distance from recently searched rows to every position of
    the table, for the triangle inequality: d(i, x) >= d(h, x) - d(i, h) for a searched row
    h. A row's vector holds the best bound its search computed per position (exact distance,
    truncated or invariant bound) and its final top-th distance U_h where it computed none
    (every such position had a bound above the threshold, itself at least U_h). Kept for the
    last rows searched, as float32 rounded down, within a memory budget."""

    _BUDGET = 1 << 25  # bytes

    def __init__(self, n_positions: int, at):
        import threading
        from collections import OrderedDict

        self.n_positions = n_positions
        self.at = at  # row -> position
        self.capacity = max(8, min(256, self._BUDGET // max(4 * n_positions, 1)))
        self._rows: OrderedDict = OrderedDict()
        self._lock = threading.Lock()

    def get(self, row):
        with self._lock:
            return self._rows.get(int(row))

    def put(self, row, bound: np.ndarray, nearest: np.ndarray) -> None:
        b32 = bound.astype(np.float32)
        up = b32 > bound
        b32[up] = np.nextafter(b32[up], np.float32(-np.inf))
        with self._lock:
            self._rows[int(row)] = (b32, nearest)
            while len(self._rows) > self.capacity:
                self._rows.popitem(last=False)


#: searched rows nearest a row whose bounds prune for it (_Helpers)
_HELPERS = 2


def _search_seeded(i, read_coefficients, table, top, samples, helpers=None):
    """Row i's nearest ``top`` rows of ``table`` (itself among them), as :func:`_search`, in
    two passes with a threshold known from the start.

    Seeds: the ``_SEEDS_PER_ENTRY * top`` rows of smallest invariant bound among the first
    ``_SEED_POSITIONS`` positions of the cells nearest the row; their top-th exact distance U
    bounds the row's top-th distance from above. Then every row whose bounds (cell,
    invariant, each truncated stage in turn) do not exceed U (with the search's rounding
    margin) gets its exact distance: all at once per stage, a few calls per row instead of
    the best-first loop's dozens of steps (the loop discovers its threshold while it goes;
    for a graph row the top-th neighbour is often far, and the loop's steps dominated).
    With ``helpers`` (:class:`_Helpers`, rows searched in table order): the list of the
    nearest seed already searched joins the seeds, and the seeds already searched bound
    every row through the triangle inequality, d(i, x) >= L_h(x) - d(i, h), before any
    kernel runs (docs/rerank.md, Cost).
    Exact: a row within the top-th distance has every bound at most U, so it is computed;
    the result holds every row within U (ties kept), from which :func:`_store` takes the
    list as a query's top would."""
    q = np.asarray(read_coefficients([i])[0], dtype=np.complex128)
    qf = feature_vector(q[None])[0]
    cb = table.cell_bounds(qf)
    corder = np.argsort(cb, kind="stable")
    sizes = (table.start[1:] - table.start[:-1])[corder]
    # every cell of bound 0 (the row's own cell is one, and several overlap) and at least
    # _SEED_POSITIONS positions
    first = max(int(np.searchsorted(np.cumsum(sizes), _SEED_POSITIONS)) + 1, int((cb <= 0).sum()))
    positions, rows, F, sq = table.open_cells(corder[:first])
    K = q.shape[0]
    complete = table.stored_harmonics == K

    def exact(pos, r, below):
        if not len(r):
            return np.zeros(0)
        c = table.coefficients_at_positions(pos) if complete else table.coefficients(r)
        return exact_search(q, c, samples, direction="invariant", mirror=False, refine_below=below)["distance"]

    lb = row_lower_bounds(qf, table.split, F, sq)
    n_seeds = min(len(rows), _SEEDS_PER_ENTRY * top)
    if n_seeds < top:
        return _search(i, read_coefficients, table, top, samples, None)
    seed = np.argpartition(lb, n_seeds - 1)[:n_seeds] if n_seeds < len(rows) else np.arange(len(rows))
    seed_pos, seed_rows = positions[seed], rows[seed]
    seed_d = exact(seed_pos, seed_rows, None)
    U = float(np.partition(seed_d, top - 1)[top - 1])
    known = np.full(table.n_positions, -np.inf) if helpers is not None else None  # best bound per position
    if known is not None:
        known[seed_pos] = seed_d
    # the searched rows nearest this one among the seeds: their bounds, less their distance
    near = []
    if helpers is not None:
        for j in np.argsort(seed_d, kind="stable"):
            if seed_rows[j] != i and (got := helpers.get(seed_rows[j])) is not None:
                near.append((got, float(seed_d[j])))
                if len(near) == _HELPERS:
                    break
        if near:
            # the nearest searched row's own list: near this row too (d(i, x) <= d(i, h) +
            # d(h, x)); their exact distances lower U before any bound is computed
            extra = np.setdiff1d(near[0][0][1], seed_rows)
            if len(extra):
                extra_pos = helpers.at[extra]
                extra_d = exact(extra_pos, extra, None)
                seed_pos = np.concatenate([seed_pos, extra_pos])
                seed_rows = np.concatenate([seed_rows, extra])
                seed_d = np.concatenate([seed_d, extra_d])
                known[extra_pos] = extra_d
                U = float(np.partition(seed_d, top - 1)[top - 1])
        near = [(h[0], dh) for h, dh in near]
    got_rows, got_d = [seed_rows], [seed_d]  # (after the helpers' rows joined the seeds)

    def tighten(pos, r, bound):
        """Exact distances of the ``top`` rows of smallest ``bound``; the lowered threshold."""
        nonlocal U
        pick = np.argsort(bound, kind="stable")[:top]
        below = margin(U)
        d = exact(pos[pick], r[pick], below)
        if known is not None:  # a row left unrefined is known to be above ``below``
            known[pos[pick]] = np.minimum(d, below * (1 - 1e-8))
        got_rows.append(r[pick])
        got_d.append(d)
        U = min(U, float(np.partition(np.concatenate(got_d), top - 1)[top - 1]))
        rest = np.ones(len(r), dtype=bool)
        rest[pick] = False
        return rest

    cells = corder[cb[corder] <= margin(U)]
    positions, rows, F, sq = table.open_cells(cells)
    lb = row_lower_bounds(qf, table.split, F, sq)
    if near:
        # the triangle inequality through the nearest searched rows: a bound on d(i, x)
        # for every position at no kernel cost
        tri = np.max([h[positions] - dh for h, dh in near], axis=0)
        lb = np.maximum(lb, tri)
    keep = lb <= margin(U)
    keep[np.isin(positions, seed_pos)] = False
    if known is not None:
        known[positions[~keep]] = np.maximum(known[positions[~keep]], lb[~keep])
    order = np.flatnonzero(keep)
    order = order[np.argsort(lb[order], kind="stable")]
    positions, rows, lb = positions[order], rows[order], lb[order]
    stages = truncated_stages(K, table.stored_harmonics)
    if stages:
        # the first stage in chunks of growing size, in invariant-bound order, each chunk's
        # best rows computed exactly: the threshold falls while the chunks go
        Kp, grid = stages[0]
        parts, a, size = [], 0, _FIRST_CHUNK
        while a < len(rows) and lb[a] <= margin(U):
            b = int(np.searchsorted(lb, margin(U), side="right"))
            b = min(b, a + size)
            pos, r = positions[a:b], rows[a:b]
            tb = truncated_lower_bounds(
                q,
                table.coefficients_at_positions(pos, Kp),
                direction="invariant",
                mirror=False,
                harmonics=Kp,
                grid=grid,
            )
            if known is not None:
                known[pos] = np.maximum(lb[a:b], tb)
            k = tb <= margin(U)
            pos, r, tb = pos[k], r[k], tb[k]
            rest = tighten(pos, r, tb)
            parts.append((pos[rest], r[rest], tb[rest]))
            a, size = b, 2 * size
        positions = np.concatenate([p[0] for p in parts]) if parts else positions[:0]
        rows = np.concatenate([p[1] for p in parts]) if parts else rows[:0]
        bound = np.concatenate([p[2] for p in parts]) if parts else lb[:0]
        for Kp, grid in stages[1:]:
            k = bound <= margin(U)
            positions, rows, bound = positions[k], rows[k], bound[k]
            if not len(rows):
                break
            bound = np.maximum(
                bound,
                truncated_lower_bounds(
                    q,
                    table.coefficients_at_positions(positions, Kp),
                    direction="invariant",
                    mirror=False,
                    harmonics=Kp,
                    grid=grid,
                ),
            )
            if known is not None:
                known[positions] = bound
            k = bound <= margin(U)
            positions, rows, bound = positions[k], rows[k], bound[k]
            rest = tighten(positions, rows, bound)
            positions, rows, bound = positions[rest], rows[rest], bound[rest]
        k = bound <= margin(U)
        positions, rows = positions[k], rows[k]
    below = margin(U)
    d = exact(positions, rows, below)
    got_d.append(d)
    got_rows.append(rows)
    if known is not None:
        known[positions] = np.minimum(d, below * (1 - 1e-8))
        # positions never bounded here: every one was ruled out above the threshold, itself
        # at least the final U
    d, rows = np.concatenate(got_d), np.concatenate(got_rows)
    inside = d <= U + TIE
    if known is not None:
        helpers.put(i, np.where(known == -np.inf, U, known), rows[inside])
    return rows[inside], d[inside]


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


#: graph rows from which a build on several threads loads the just-in-time kernels
_THREADED_ROWS = 64


def _run(rows, work, threads, done):
    """``done(i, *work(i))`` for every row, ``work`` in threads (one BLAS thread each)."""
    threads = threads or min(os.cpu_count() or 1, 4)
    if threads > 1 and not dispatch.threads_help():
        # kernels compiled ahead of time holding the GIL (aot.py): threads need the just-in-time
        # ones, worth their import (~0.45 s) for a graph of more than a few rows
        if len(rows) < _THREADED_ROWS or not dispatch.load_threaded_kernels():
            threads = 1
    if threads > 1 and len(rows) > 1:
        from concurrent.futures import ThreadPoolExecutor

        from threadpoolctl import threadpool_limits

        with threadpool_limits(1, user_api="blas"), ThreadPoolExecutor(threads) as pool:
            for i, res in zip(rows, pool.map(work, rows)):
                done(int(i), *res)
    else:
        for i in rows:
            done(int(i), *work(int(i)))
