"""The search engine: every query's exact k nearest rows of a :class:`SearchTable`, for a
block of queries (:func:`search_block`). Every search of the package runs here: a batch of
queries (:func:`~nfdmatch.search.search_index`), the k-NN graph of an index
(:mod:`.graph`), a range of cells on a Dask worker (:mod:`nfdmatch.distributed`); they
differ only in their inputs (the table, the queries, rows already known, cells to skip).

Rows are taken in increasing lower-bound order across the whole table: cells in the order
of their own bound, the rows of opened cells merged by their invariant bound, exact
distances in growing batches (each batch first filtered by the truncated-harmonic bound
once a k-th distance exists), until the next bound -- of a pending row or of an unopened
cell -- exceeds the current k-th distance. Nothing is skipped that a bound does not rule
out, so the result is the exhaustive one; the order only decides how little is computed.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, fields

import numpy as np

from ..matching import EXACT, INVARIANT
from .bounds import row_lower_bounds, truncated_lower_bounds, truncated_stages

if TYPE_CHECKING:
    from .table import SearchTable

__all__ = ["BestRows", "QueryWork", "Cascade", "search_block", "margin", "TIE"]

#: a bound prunes a row only when it exceeds the k-th distance by this much: the exact
#: distance is a numerical optimum, the stored features are float32
_PRUNE_RELATIVE, _PRUNE_ABSOLUTE = 1e-5, 1e-6
#: distances closer than this are ties, ordered by id (below the pipeline's numerical noise)
TIE = 1e-9
#: rows per batch: the first exact batch sets a k-th distance; truncated bounds are computed
#: in batches growing to MAX_BATCH, exact distances (in truncated-bound order) to EXACT_BATCH
FIRST_BATCH, MAX_BATCH, EXACT_BATCH = 32, 2048, 256
#: positions a query opens at least per step (cells are cheap to open in bulk), doubling
#: with every step up to _MAX_OPEN_ROWS: a query that keeps opening cells (no near
#: neighbours) does it in few large steps, a query with near neighbours stops after one
_OPEN_ROWS, _MAX_OPEN_ROWS = 1024, 16384
#: batches this small go straight to the exact distance: a truncated-bound call costs about
#: 150 us of numpy calls whatever its rows (some ten exact distances), so a batch of fewer
#: rows would have to lose a third of them to pay; a family's members (the k-NN graph of a
#: collection of families) pass it all (8 -> 32: the graph's rows 15-25% less CPU, the same
#: exact distances; random queries, whose batches are large, unchanged)
_TRUNCATE_FROM = 32


def margin(threshold: float) -> float:
    """The distance a bound must exceed to prune against ``threshold`` (rounding slack)."""
    return threshold * (1 + _PRUNE_RELATIVE) + _PRUNE_ABSOLUTE


class BestRows:
    """The best rows seen so far for one query: every row within the k-th distance (ties kept).

    ``extra`` holds per row the alignment (shift, reversed, mirrored) and ``position``: where
    the search table holds the row's descriptors (-1 when added from elsewhere), so that
    they can be read again without a scattered read of the index."""

    def __init__(self, k: int | None, max_distance: float | None) -> None:
        self.k, self.max_distance = k, max_distance
        self.dist = np.zeros(0)
        self.rows = np.zeros(0, dtype=np.int64)
        self.extra = {
            key: np.zeros(0, dtype=t)
            for key, t in (("shift", float), ("reversed", bool), ("mirrored", bool), ("position", np.int64))
        }

    def threshold(self) -> float:
        limit = np.inf if self.max_distance is None else self.max_distance
        if self.k is not None and len(self.dist) >= self.k:
            limit = min(limit, float(np.partition(self.dist, self.k - 1)[self.k - 1]))
        return limit

    def add(self, dist: np.ndarray, rows: np.ndarray, result: dict[str, np.ndarray]) -> None:
        keep = dist <= (np.inf if self.max_distance is None else self.max_distance)
        self.dist = np.concatenate([self.dist, dist[keep]])
        self.rows = np.concatenate([self.rows, rows[keep]])
        for key in self.extra:
            values = result[key] if key in result else np.full(len(dist), -1, dtype=self.extra[key].dtype)
            self.extra[key] = np.concatenate([self.extra[key], np.asarray(values)[keep]])
        t = self.threshold()
        if np.isfinite(t):
            inside = self.dist <= t + TIE
            self.dist, self.rows = self.dist[inside], self.rows[inside]
            self.extra = {key: v[inside] for key, v in self.extra.items()}


@dataclass
class QueryWork:
    """What one query's search did: positions whose invariant bound was computed
    (``scanned``), cells opened, truncated bounds (``truncated``: the first stage, ``fine``:
    the later ones), exact distances."""

    scanned: int = 0
    cells: int = 0
    truncated: int = 0
    fine: int = 0
    exact: int = 0
    extra: dict = field(default_factory=dict)

    def add(self, other: "QueryWork") -> None:
        """Count ``other``'s work in this one."""
        for f in fields(self):
            if f.name != "extra":
                setattr(self, f.name, getattr(self, f.name) + getattr(other, f.name))


@dataclass(frozen=True)
class Cascade:
    """What a search computes, the same for every query of a block: the distance
    (``method``, ``direction``, ``mirror`` as in :func:`nfdmatch.distance`; ``samples``: n of
    the index) and whether the truncated-harmonic bounds run between the invariant bound and
    the exact distance (``truncate``: an option for measuring their effect)."""

    samples: int
    method: str = EXACT
    direction: str = INVARIANT
    mirror: bool = False
    truncate: bool = True

    @property
    def distance(self) -> Callable[..., dict[str, np.ndarray]]:
        """The distance function of ``method``: ``exact_search`` or ``paper_search``."""
        from ..matching import exact_search, paper_search

        return exact_search if self.method == EXACT else paper_search


def search_block(
    table: SearchTable,
    query_coefficients: np.ndarray,
    query_features: np.ndarray,
    nearest: Sequence[BestRows],
    cascade: Cascade,
    *,
    skip_cells: Sequence[np.ndarray | None] | None = None,
    threads: int | None = None,
    done: Callable[[int, QueryWork], None] | None = None,
    expect_more: bool = True,
) -> QueryWork:
    """Fill ``nearest[i]`` with query i's exact nearest rows of ``table``; returns the work
    of all queries summed.

    Parameters
    ----------
    table : :class:`~nfdmatch.search.table.SearchTable`.
    query_coefficients : (Q, K, 3) complex128; query_features : (Q, D) float64
        (:func:`~nfdmatch.search.bounds.feature_vector`).
    nearest : Q :class:`BestRows` (their k and max_distance set each threshold). A BestRows may hold
        rows already (seeds found elsewhere: they count towards its k-th distance from the
        start, so the search prunes as if it had seen them).
    cascade : :class:`Cascade`.
    skip_cells : per query, cells never to open (searched before, their rows accounted for
        in the query's BestRows already), or None.
    threads : queries answered in parallel (default: the cores, at most 4).
    done : ``done(i, work)`` after query i, on the calling thread, in query order when one
        thread answers, else as queries finish.
    expect_more : the first query is answered alone, and what it read the table repeats for
        the rest of the block in one read
        (:meth:`~nfdmatch.search.table.SearchTable.expect_more`); False when the queries
        read unlike parts of the table (each its own window of cells).
    """
    from ..matching.kernels import current

    Q = len(nearest)
    total = QueryWork()
    threads = threads or min(os.cpu_count() or 1, 4)

    def answer(qi):
        return _search_one(
            query_coefficients[qi],
            query_features[qi],
            table,
            nearest[qi],
            cascade,
            None if skip_cells is None else skip_cells[qi],
        )

    def account(qi, work):
        total.add(work)
        if qi == 0 and Q > 1 and expect_more:
            # what one query read, times the queries left: read whole now what the block
            # would read most of in runs
            table.expect_more(Q - 1)
        if done is not None:
            done(qi, work)

    if Q == 0:
        return total
    account(0, answer(0))
    rest = range(1, Q)
    if not current().threads:
        threads = 1  # kernels built holding the GIL (aot.py): threads would take turns
    if threads > 1 and len(rest) > 1:
        from concurrent.futures import ThreadPoolExecutor

        from threadpoolctl import threadpool_limits

        # one BLAS thread per query thread: idle OpenBLAS workers spin and steal the cores
        with threadpool_limits(1, user_api="blas"), ThreadPoolExecutor(threads) as pool:
            for qi, work in zip(rest, pool.map(answer, rest)):
                account(qi, work)
    else:
        for qi in rest:
            account(qi, answer(qi))
    return total


class _Sorted:
    """Rows waiting in increasing order of a bound, each with its position in the search
    table (where its descriptors are): sorted runs, one per batch added, taken from the
    front in one merged order. Adding a batch sorts the batch only (the queue of opened rows
    holds tens of thousands; re-sorting it per batch cost more than the bounds); the runs
    are compacted into one when they pile up."""

    _MAX_RUNS = 16

    def __init__(self):
        self._runs: list[list] = []  # [bound, rows, positions, front]

    def head(self) -> float:
        best = np.inf
        for bound, _, _, front in self._runs:
            if bound[front] < best:
                best = bound[front]
        return float(best)

    def __len__(self) -> int:
        return sum(len(r[0]) - r[3] for r in self._runs)

    def merge(self, bound, rows, positions, limit: float) -> None:
        """Add rows; every waiting row bounded above ``limit`` (the current pruning
        threshold, which only decreases) may be dropped: it can never be needed."""
        if len(bound):
            order = np.argsort(bound, kind="stable")
            self._runs.append([bound[order], rows[order], positions[order], 0])
        if len(self._runs) > self._MAX_RUNS:
            runs = self._runs
            b = np.concatenate([r[0][r[3] :] for r in runs])
            keep = np.flatnonzero(b <= limit)
            order = keep[np.argsort(b[keep], kind="stable")]
            self._runs = (
                [
                    [
                        b[order],
                        np.concatenate([r[1][r[3] :] for r in runs])[order],
                        np.concatenate([r[2][r[3] :] for r in runs])[order],
                        0,
                    ]
                ]
                if len(order)
                else []
            )

    def take(self, count: int, limit: float):
        """Up to about ``count`` rows from the front with a bound at most ``limit`` (at least
        one): ``(bound, rows, positions)``; ties at the cut may add a few."""
        ends = []
        total = 0
        for bound, _, _, front in self._runs:
            end = min(front + count, int(np.searchsorted(bound, limit, side="right")))
            ends.append(end)
            total += end - front
        if total == 0:  # nothing within limit: the single smallest
            i = int(np.argmin([r[0][r[3]] for r in self._runs]))
            ends = [r[3] for r in self._runs]
            ends[i] += 1
        elif total > count:
            # the count smallest of the runs' fronts: a prefix of each run
            cut = np.partition(np.concatenate([r[0][r[3] : e] for r, e in zip(self._runs, ends)]), count - 1)[count - 1]
            ends = [r[3] + int(np.searchsorted(r[0][r[3] : e], cut, side="right")) for r, e in zip(self._runs, ends)]
        parts = [(r[0][r[3] : e], r[1][r[3] : e], r[2][r[3] : e]) for r, e in zip(self._runs, ends) if e > r[3]]
        for r, e in zip(self._runs, ends):
            r[3] = e
        self._runs = [r for r in self._runs if r[3] < len(r[0])]
        if len(parts) == 1:
            return parts[0]
        return tuple(np.concatenate([p[i] for p in parts]) for i in range(3))


def _search_one(
    query_coefficients: np.ndarray,
    query_features: np.ndarray,
    table,
    top: "BestRows",
    cascade: Cascade,
    skip_cells: np.ndarray | None = None,
) -> QueryWork:
    """Fill ``top`` with one query's exact nearest rows of ``table`` (arguments: one query of
    :func:`search_block`).

    Queues in one best-first order: unopened cells (by cell bound), rows of opened cells
    (by invariant bound), then one queue per truncated-harmonic stage
    (:func:`~nfdmatch.search.bounds.truncated_stages`, by that stage's bound). Each step
    works on the queue with the smallest head: opens cells, computes the next stage's bound
    for a batch of rows, or (from the last queue) exact distances; the search ends when
    every head exceeds the k-th distance. Nothing is skipped that a bound does not rule
    out, so the result is the exhaustive one; the order only decides how little is computed.
    """
    one = _OneQuery(query_coefficients, query_features, table, top, cascade, skip_cells)
    while True:
        thr = margin(top.threshold())
        cell_head = one.cells.head()
        heads = [q.head() for q in one.queues]
        q_at = int(np.argmin(heads))
        head = min(cell_head, heads[q_at])
        if head > thr or head == np.inf:  # every row bounded above the k-th, or none left
            break
        if cell_head <= heads[q_at]:
            one.open_cells(thr, heads[q_at])
            continue
        # a batch never reaches past the head of a cheaper queue or of the cells: what is
        # pending there may lower the k-th distance before its rows are needed; except the
        # first bound stage's (its bound is cheap next to a step per few rows)
        stages = len(one.stages)
        limit = thr if q_at == 0 < stages else min(thr, cell_head, min(heads[:q_at], default=np.inf))
        if q_at < stages and np.isfinite(thr):
            # the next stage's bound for a batch of this queue's rows (straight to exact
            # while no k-th distance exists: nothing could be pruned yet)
            _, rows, positions = one.queues[q_at].take(one.batch[q_at], limit)
            if len(rows) >= _TRUNCATE_FROM or q_at > 0:
                one.bound_stage(q_at, rows, positions, thr)
                continue
        else:
            rows, positions = one.take_exact(q_at, limit)
        one.exact(rows, positions, thr)
    return one.work


class _CellQueue:
    """A query's unopened cells in increasing order of their bound, sorted a slice at a
    time: a query opens a few of thousands of cells, and sorting them all cost more than
    their bounds (an argsort of 7,800 cells per row of a 1,000,000-curve graph build).

    Each slice is the next smallest bounds (a partition, then a sort of the slice only;
    every cell left has a bound at least the slice's largest), doubling from 64 cells. The
    order is that of the bounds before they are raised to 0 (the same order where they are
    positive): of the cells holding the query, the one it lies deepest in comes first,
    whatever their numbers (with many such cells, the first opened decides how soon the
    k-th distance falls)."""

    _FIRST = 64

    def __init__(self, table, query_features, skip_cells):
        self.bounds = table.cell_bounds(query_features, clip=False)
        self.sizes = table.start[1:] - table.start[:-1]
        self.rest = np.arange(len(self.bounds))
        if skip_cells is not None and len(skip_cells):
            self.bounds[skip_cells] = np.inf  # (positions_within never counts them)
            keep = np.ones(len(self.rest), dtype=bool)
            keep[skip_cells] = False
            self.rest = self.rest[keep]
        self.order = self.rest[:0]
        self.sorted = self.bounds[:0]
        self.next = 0
        self.slice = self._FIRST

    def head(self) -> float:
        """The smallest bound of a cell not taken yet (inf: none left)."""
        if self.next == len(self.order):
            self._sort_next()
        return max(float(self.sorted[self.next]), 0.0) if self.next < len(self.order) else np.inf

    def _sort_next(self) -> None:
        rest = self.rest
        if not len(rest):
            return
        b = self.bounds[rest]
        if len(rest) > self.slice:
            part = np.argpartition(b, self.slice)
            first, self.rest = part[: self.slice], rest[part[self.slice :]]
            first = first[np.argsort(b[first], kind="stable")]
        else:
            first, self.rest = np.argsort(b, kind="stable"), rest[:0]
        self.order, self.sorted, self.next = rest[first], b[first], 0
        self.slice *= 2

    def take(self, thr: float, pending: float, open_rows: int) -> np.ndarray:
        """The cells to open next, in bound order: every cell that may hold a row bounded
        below the next pending row (bound ``pending``; none pending: inf), and at least
        ``open_rows`` positions; never a cell bounded above ``thr``."""
        taken, opened = [], 0
        while True:
            head = self.head()
            if self.next == len(self.order) or not (head <= thr and (opened < open_rows or head <= pending < np.inf)):
                break
            cell = int(self.order[self.next])
            self.next += 1
            taken.append(cell)
            opened += int(self.sizes[cell])
        return np.asarray(taken, dtype=np.int64)

    def positions_within(self, thr: float) -> int:
        """Positions in the cells (opened or not, skipped ones aside) bounded at most ``thr``."""
        return int(self.sizes[self.bounds <= thr].sum())


class _OneQuery:
    """The state of one query's search (:func:`_search_one`): its cells in bound order, the
    queues, the truncated stages and batch sizes, and the work done."""

    def __init__(self, query_coefficients, query_features, table, top, cascade, skip_cells):
        self.q, self.features, self.table, self.top, self.cascade = (
            query_coefficients,
            query_features,
            table,
            top,
            cascade,
        )
        self.work = QueryWork()
        self.cells = _CellQueue(table, query_features, skip_cells)
        self.queues = [_Sorted()]  # [0]: opened, by invariant bound; [i > 0]: by stage i's bound
        self.stages = None  # the truncated stages, once the first cell shows what is stored
        # a table that hands out every harmonic with the cell needs no other read for the
        # exact distances (format 2, memory); else their rows' descriptors are read on demand
        self.complete = None
        self.batch = [FIRST_BATCH]
        self.exact_batch = FIRST_BATCH
        self.open_rows = _OPEN_ROWS

    def open_cells(self, thr: float, pending: float) -> None:
        """Open every cell that may hold a row bounded below the next pending row (bound
        ``pending``; none when nothing is pending), and at least ``open_rows`` positions;
        never a cell the threshold rules out."""
        cells = self.cells.take(thr, pending, self.open_rows)
        self.open_rows = min(2 * self.open_rows, _MAX_OPEN_ROWS)
        self.work.cells += len(cells)
        # the positions this search may still open (every cell bounded below the k-th
        # distance so far): a table reads itself whole early when that is most of it
        expect = self.cells.positions_within(thr) if np.isfinite(thr) else 0
        table = self.table
        positions, rows, F, sq = table.open_cells(cells, expect=expect)
        if self.stages is None:
            stored = table.stored_harmonics
            self.complete = stored == self.q.shape[0]
            self.stages = truncated_stages(self.q.shape[0], stored) if self.cascade.truncate else []
            self.queues += [_Sorted() for _ in self.stages]
            self.batch += [FIRST_BATCH] * len(self.stages)
        self.work.scanned += len(rows)
        b = row_lower_bounds(self.features, table.split, F, sq)
        keep = np.flatnonzero(b <= thr)
        self.queues[0].merge(b[keep], rows[keep], positions[keep], thr)

    def bound_stage(self, q_at: int, rows, positions, thr: float) -> None:
        """Stage ``q_at``'s truncated-harmonic bound of a batch of its queue's rows; the rows
        it does not rule out go on to the next queue."""
        cascade = self.cascade
        Kp, grid = self.stages[q_at]
        tb = truncated_lower_bounds(
            self.q,
            self.table.coefficients_at_positions(positions, Kp, expect=len(rows) + len(self.queues[q_at])),
            direction=cascade.direction,
            mirror=cascade.mirror,
            harmonics=Kp,
            grid=grid,
            limit=thr,
        )
        if q_at == 0:
            self.work.truncated += len(rows)
        else:
            self.work.fine += len(rows)
        keep = tb <= thr
        self.queues[q_at + 1].merge(tb[keep], rows[keep], positions[keep], thr)
        self.batch[q_at] = min(self.batch[q_at] * 2, MAX_BATCH)

    def take_exact(self, q_at: int, limit: float):
        """``(rows, positions)``: the next batch of queue ``q_at`` for exact distances."""
        last = q_at == len(self.stages) and q_at > 0
        size = self.exact_batch if last else self.batch[q_at]
        _, rows, positions = self.queues[q_at].take(size, limit)
        if last:
            self.exact_batch = min(self.exact_batch * 2, EXACT_BATCH)
        elif q_at < len(self.stages):
            self.batch[q_at] = min(self.batch[q_at] * 2, MAX_BATCH)
        return rows, positions

    def exact(self, rows, positions, thr: float) -> None:
        """The exact distances of ``rows`` into the query's :class:`BestRows` (rows that
        cannot beat ``thr`` are not refined)."""
        c = self.cascade
        if self.complete:
            coefficients = self.table.coefficients_at_positions(positions)
        else:
            coefficients = self.table.coefficients(rows)
        extra = {"refine_below": thr} if c.method == EXACT else {}
        r = c.distance(self.q, coefficients, c.samples, direction=c.direction, mirror=c.mirror, **extra)
        if self.complete:
            r["position"] = positions
        self.work.exact += len(rows)
        self.top.add(r["distance"], rows, r)
