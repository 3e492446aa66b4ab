"""The best-first loop: one query's exact k nearest rows of a :class:`SearchTable`.

Rows are taken in increasing lower-bound order across the whole table: cells in the order
of their own bound, the rows of opened cells merged by their invariant bound, exact
distances in growing batches (each batch first filtered by the truncated-harmonic bound
once a k-th distance exists), until the next bound -- of a pending row or of an unopened
cell -- exceeds the current k-th distance. Nothing is skipped that a bound does not rule
out, so the result is the exhaustive one; the order only decides how little is computed.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .bounds import cell_lower_bounds, row_lower_bounds, truncated_lower_bounds

__all__ = ["TopK", "QueryWork", "search_one", "margin"]

#: a bound prunes a row only when it exceeds the k-th distance by this much: the exact
#: distance is a numerical optimum, the stored features are float32
_PRUNE_RELATIVE, _PRUNE_ABSOLUTE = 1e-5, 1e-6
#: distances closer than this are ties, ordered by id (below the pipeline's numerical noise)
TIE = 1e-9
#: rows per batch: the first exact batch sets a k-th distance; truncated bounds are computed
#: in batches growing to MAX_BATCH, exact distances (in truncated-bound order) to EXACT_BATCH
FIRST_BATCH, MAX_BATCH, EXACT_BATCH = 32, 2048, 256
#: positions a query opens at least per step (cells are cheap to open in bulk)
_OPEN_ROWS = 1024
#: batches this small go straight to the exact distance (the truncated bound would not pay)
_TRUNCATE_FROM = 8


def margin(threshold: float) -> float:
    """The distance a bound must exceed to prune against ``threshold`` (rounding slack)."""
    return threshold * (1 + _PRUNE_RELATIVE) + _PRUNE_ABSOLUTE


class TopK:
    """The best rows seen so far for one query: every row within the k-th distance (ties kept)."""

    def __init__(self, k: int | None, max_distance: float | None):
        self.k, self.max_distance = k, max_distance
        self.dist = np.zeros(0)
        self.rows = np.zeros(0, dtype=np.int64)
        self.extra = {key: np.zeros(0, dtype=t) for key, t in
                      (("shift", float), ("reversed", bool), ("mirrored", bool))}

    def threshold(self) -> float:
        limit = np.inf if self.max_distance is None else self.max_distance
        if self.k is not None and len(self.dist) >= self.k:
            limit = min(limit, float(np.partition(self.dist, self.k - 1)[self.k - 1]))
        return limit

    def add(self, dist, rows, result) -> None:
        keep = dist <= (np.inf if self.max_distance is None else self.max_distance)
        self.dist = np.concatenate([self.dist, dist[keep]])
        self.rows = np.concatenate([self.rows, rows[keep]])
        for key in self.extra:
            self.extra[key] = np.concatenate([self.extra[key], result[key][keep]])
        t = self.threshold()
        if np.isfinite(t):
            inside = self.dist <= t + TIE
            self.dist, self.rows = self.dist[inside], self.rows[inside]
            self.extra = {key: v[inside] for key, v in self.extra.items()}


@dataclass
class QueryWork:
    """What one query's search did: positions whose invariant bound was computed
    (``scanned``), cells opened, truncated bounds, exact distances."""

    scanned: int = 0
    cells: int = 0
    truncated: int = 0
    exact: int = 0
    extra: dict = field(default_factory=dict)


class _Descriptors:
    """The descriptors of the rows a query has opened, appended block by block (amortized
    doubling) and addressed by slot, so that the queues carry 8-byte slots and never copy
    descriptors when they merge."""

    def __init__(self):
        self._data = None
        self._used = 0

    def append(self, block: np.ndarray) -> np.ndarray:
        """Store ``block`` (m, K'', 3); returns its (m,) int64 slots."""
        m = len(block)
        if self._data is None:
            self._data = np.empty((max(m, 1024),) + block.shape[1:], dtype=block.dtype)
        elif self._used + m > len(self._data):
            grown = np.empty((max(2 * len(self._data), self._used + m),) + self._data.shape[1:],
                             dtype=self._data.dtype)
            grown[:self._used] = self._data[:self._used]
            self._data = grown
        self._data[self._used:self._used + m] = block
        slots = np.arange(self._used, self._used + m, dtype=np.int64)
        self._used += m
        return slots

    def __getitem__(self, slots: np.ndarray) -> np.ndarray:
        return self._data[slots]


class _Sorted:
    """Rows waiting in increasing order of a bound, consumed from the front, each with the
    slot of its descriptors in the query's :class:`_Descriptors`."""

    def __init__(self):
        self.bound = np.zeros(0)
        self.rows = np.zeros(0, dtype=np.int64)
        self.slots = np.zeros(0, dtype=np.int64)
        self.pos = 0

    def head(self) -> float:
        return float(self.bound[self.pos]) if self.pos < len(self.bound) else np.inf

    def __len__(self) -> int:
        return len(self.bound) - self.pos

    def merge(self, bound, rows, slots, limit: float) -> None:
        """Add rows; every waiting row bounded above ``limit`` (the current pruning
        threshold, which only decreases) is dropped: it can never be needed."""
        keep = self.bound[self.pos:] <= limit
        b = np.concatenate([self.bound[self.pos:][keep], bound])
        order = np.argsort(b, kind="stable")        # two sorted runs: linear
        self.bound = b[order]
        self.rows = np.concatenate([self.rows[self.pos:][keep], rows])[order]
        self.slots = np.concatenate([self.slots[self.pos:][keep], slots])[order]
        self.pos = 0

    def take(self, count: int, limit: float):
        """Up to ``count`` rows from the front with a bound at most ``limit`` (at least one):
        ``(bound, rows, slots)``."""
        stop = min(self.pos + count, int(np.searchsorted(self.bound, limit, side="right")))
        stop = max(stop, self.pos + 1)
        sl = slice(self.pos, stop)
        self.pos = stop
        return self.bound[sl], self.rows[sl], self.slots[sl]


def search_one(query_coefficients: np.ndarray, query_features: np.ndarray, table, top: "TopK", *,
               search, method: str, direction: str, mirror: bool, samples: int,
               truncate: bool = True) -> QueryWork:
    """Fill ``top`` with the query's exact nearest rows of ``table``.

    Parameters
    ----------
    query_coefficients : (K, 3) complex128; query_features : (D,) float64.
    table : :class:`~nfdmatch.search.table.SearchTable`.
    top : :class:`TopK` to fill (its k and max_distance set the threshold).
    search : the distance function (``exact_search`` or ``paper_search``).
    truncate : use the truncated-harmonic bound between the invariant bound and the exact
        distance.

    Three queues in one best-first order: unopened cells (by cell bound), rows of opened
    cells (by invariant bound), rows with a truncated bound (by that bound). Each step works
    on the queue with the smallest head: opens cells, computes truncated bounds for a batch,
    or computes exact distances for a batch; the search ends when every head exceeds the
    k-th distance.
    """
    work = QueryWork()
    cb = cell_lower_bounds(query_features, table.split, table.centre, table.radius)
    corder = np.argsort(cb, kind="stable")
    cbs = cb[corder]
    sizes = (table.start[1:] - table.start[:-1])[corder]
    n_cells = len(corder)
    ci = 0
    store = _Descriptors()      # descriptors of the opened rows
    rows_q = _Sorted()          # opened, by invariant bound
    tight_q = _Sorted()         # by truncated bound
    # a table that hands out every harmonic with the cell needs no other read for the exact
    # distances (format 2, memory); else their rows' descriptors are read on demand
    complete = None
    bound_batch, exact_batch = FIRST_BATCH, FIRST_BATCH
    while True:
        thr = margin(top.threshold())
        cell_head = cbs[ci] if ci < n_cells else np.inf
        row_head, tight_head = rows_q.head(), tight_q.head()
        head = min(cell_head, row_head, tight_head)
        if head > thr or head == np.inf:          # every row bounded above the k-th, or none left
            break
        if cell_head <= row_head and cell_head <= tight_head:
            # open every cell that may hold a row bounded below the next pending row (none
            # when nothing is pending), and at least _OPEN_ROWS positions; never a cell the
            # threshold rules out
            j, opened = ci, 0
            limit = min(row_head, tight_head)         # inf: nothing pending
            while j < n_cells and cbs[j] <= thr and (opened < _OPEN_ROWS or cbs[j] <= limit < np.inf):
                opened += sizes[j]
                j += 1
            cells = corder[ci:j]
            ci = j
            work.cells += len(cells)
            rows, F, sq, coefficients = table.cell_rows(cells)
            if complete is None:
                complete = coefficients.shape[1] == query_coefficients.shape[0]
            work.scanned += len(rows)
            b = row_lower_bounds(query_features, table.split, F, sq)
            keep = np.flatnonzero(b <= thr)
            rows_q.merge(b[keep], rows[keep], store.append(coefficients[keep]), thr)
            continue
        if row_head < tight_head:
            # rows by invariant bound -> truncated bound (or straight to exact when the
            # truncated bound is off or no k-th distance exists yet)
            limit = min(thr, cell_head)
            _, rows, slots = rows_q.take(bound_batch, limit)
            if truncate and np.isfinite(thr) and len(rows) >= _TRUNCATE_FROM:
                tb = truncated_lower_bounds(query_coefficients, store[slots], direction=direction,
                                            mirror=mirror)
                work.truncated += len(rows)
                keep = tb <= thr
                tight_q.merge(tb[keep], rows[keep], slots[keep], thr)
                bound_batch = min(bound_batch * 2, MAX_BATCH)
                continue
            coefficients = store[slots] if complete else table.coefficients(rows)
            _exact(query_coefficients, rows, coefficients, top, work, search, method, direction, mirror, samples, thr)
            continue
        limit = min(thr, cell_head, row_head)
        _, rows, slots = tight_q.take(exact_batch, limit)
        coefficients = store[slots] if complete else table.coefficients(rows)
        _exact(query_coefficients, rows, coefficients, top, work, search, method, direction, mirror, samples, thr)
        exact_batch = min(exact_batch * 2, EXACT_BATCH)
    return work


def _exact(query_coefficients, rows, coefficients, top, work, search, method, direction, mirror, samples, thr):
    extra = {"refine_below": thr} if method == "exact" else {}
    r = search(query_coefficients, coefficients, samples, direction=direction, mirror=mirror, **extra)
    work.exact += len(rows)
    top.add(r["distance"], rows, r)
