"""The whole collection against itself, exactly: every stored row's k nearest other rows
(:func:`nearest_others`), or every pair of rows within a distance (:func:`pairs_within`).

A query searches the collection row by row; a self-join works on the collection as a
whole (docs/selfjoin.md):

* **cells against cells.** The rows of one cell are the queries of one step; a cell of
  the table is opened for them only when the bound of the pair of cells
  (:func:`~nfdmatch.search.bounds.cell_pair_lower_bounds`, from both centres and radii)
  does not exceed the thresholds of the rows involved. The opened rows are bounded
  against all the step's queries in one matrix product
  (:func:`~nfdmatch.search.bounds.row_lower_bounds_many`), then, per query, by the
  truncated-harmonic stages (:func:`~nfdmatch.search.bounds.truncated_lower_bounds`)
  and the exact distance of the :class:`~nfdmatch.search.engine.Cascade`.
* **each pair once.** A pair of rows is taken up by the step of its first row in the
  table's order (positions: cell-major); the exact distance is symmetric, so it serves
  both rows.
* **shared thresholds.** A row's threshold is its k-th distance so far (or the distance
  asked for); a pair is pruned only when its bound exceeds both its rows' thresholds,
  and every distance computed lowers both rows' thresholds. Before the cells are
  joined, each row gets seed distances to the k rows of its own cell nearest by the
  invariant bound, so no step starts without thresholds.

Nothing is pruned that a proven bound does not rule out (the same bounds and margin as a
query: :func:`~nfdmatch.search.engine.margin`), so the result equals the brute-force one:
every pair's exact distance by :func:`~nfdmatch.matching.exact_search`.

``rows`` restricts one side of the join: only pairs with at least one row in it, and
only those rows' lists (a build's new rows; ``pairs --new``).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import os
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ..errors import ParameterError
from .bounds import (
    cell_pair_lower_bounds,
    feature_vector,
    query_radius,
    row_lower_bounds_many,
    truncated_lower_bounds,
    truncated_stages,
)
from .engine import EXACT_BATCH, FIRST_BATCH, TIE, Cascade, margin
from .limits import check_limits

if TYPE_CHECKING:
    from .table import SearchTable

__all__ = ["JoinStats", "join_input", "nearest_others", "pairs_within"]

#: entries of the (queries x opened rows) bound matrix computed at once: small enough that
#: its float64 temporaries stay in cache (4M entries were memory-bound at ~200 ns an entry)
_MATRIX_ENTRIES = 1 << 16
#: rows whose query features are computed at once (bounds the complex128 copy)
_FEATURE_BLOCK = 8192
#: a truncated stage runs on at least this many candidates (else they go on to the next
#: stage or the exact distance): the first stage from 8 as a query's search; the later
#: ones cost a call per row for few rows here (a family's members left by the first stage
#: are mostly within the thresholds: the (8, 48) stage kept ~90% of them at 20,000 curves)
_TRUNCATE_FROM = (8, 64)


@dataclass
class JoinStats:
    """What a self-join did: ``rows`` (in the table), ``left`` (rows on the restricted
    side: all of them unless ``rows`` was given), ``cells``, ``cell_pairs`` (pairs of cells
    opened), ``bounded`` (row pairs whose invariant bound was computed), ``truncated`` /
    ``fine`` (truncated bounds, first and later stages), ``exact`` (exact distances: each
    pair at most once), ``seconds``."""

    rows: int = 0
    left: int = 0
    cells: int = 0
    cell_pairs: int = 0
    bounded: int = 0
    truncated: int = 0
    fine: int = 0
    exact: int = 0
    seconds: float = 0.0


class _Collection:
    """Every row of a search table in memory, in the table's (cell-major) order: index row,
    stored features and their squared norms, descriptors, and query features (computed
    from the descriptors, as a query's are)."""

    def __init__(self, table, read_coefficients):
        self.split = table.split
        C = table.n_cells
        self.start, self.centre, self.radius = table.start, table.centre, table.radius
        if C == 0:
            D = table.centre.shape[1] if table.centre.ndim == 2 else 2 * table.harmonics + 3
            self.row = np.zeros(0, dtype=np.int64)
            self.F = np.zeros((0, D), dtype=np.float32)
            self.sq = np.zeros((0, 2))
            self.coef = np.zeros((0, table.harmonics, 3), dtype=np.complex128)
            self.fq = np.zeros((0, D))
            return
        positions, self.row, self.F, self.sq = table.open_cells(np.arange(C))
        if table.stored_harmonics >= table.harmonics:
            self.coef = table.coefficients_at_positions(positions)
        else:  # the table holds the first harmonics only (format 1): every row's, read once
            self.coef = np.asarray(read_coefficients(self.row))
        N = len(self.row)
        self.fq = np.empty((N, self.F.shape[1]))
        for a in range(0, N, _FEATURE_BLOCK):
            self.fq[a : a + _FEATURE_BLOCK] = feature_vector(
                np.asarray(self.coef[a : a + _FEATURE_BLOCK], dtype=np.complex128)
            )

    @property
    def n(self) -> int:
        return len(self.row)


class _Join:
    """One self-join: thresholds per position (``tau``: the k-th distance so far or the
    distance asked for on the restricted side, -inf elsewhere: such a row needs no pair for
    itself), the pairs computed, and the steps."""

    def __init__(self, col: _Collection, cascade: Cascade, left: np.ndarray, k: int | None, max_distance, threads: int):
        self.col, self.cascade, self.left, self.k, self.threads = col, cascade, left, k, threads
        self._lock = threading.Lock()
        N = col.n
        self.tau = np.where(left, np.inf if max_distance is None else float(max_distance), -np.inf)
        self.best = None if k is None else np.full((N, k), np.inf)
        self.found: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
        self.stats = JoinStats(rows=N, left=int(left.sum()), cells=len(col.start) - 1)
        self.stages = truncated_stages(col.coef.shape[1], col.coef.shape[1]) if cascade.truncate else []
        self.seeded = np.zeros(0, dtype=np.int64)  # keys a * N + b of the seed pairs, sorted
        # set when the join ends early (Ctrl-C, a fault): the steps still running return at
        # their next batch, their work thrown away (a step may take seconds)
        self.stopping = threading.Event()

    # ------------------------------------------------------------------ distances

    def _count(self, name: str, n: int) -> None:
        with self._lock:
            setattr(self.stats, name, getattr(self.stats, name) + int(n))

    def _exact(self, a: int, bs: np.ndarray, thr: np.ndarray) -> None:
        """Exact distances of query position ``a`` to positions ``bs``, shared by both rows;
        ``thr`` the pairs' thresholds (only distances below them need refining)."""
        cascade = self.cascade
        limit = float(margin(thr).max()) if len(thr) else np.inf  # type: ignore[attr-defined]
        extra = {"refine_below": limit} if cascade.method == "exact" and np.isfinite(limit) else {}
        A = np.asarray(self.col.coef[a], dtype=np.complex128)
        r = cascade.distance(
            A, self.col.coef[bs], cascade.samples, direction=cascade.direction, mirror=cascade.mirror, **extra
        )
        self._count("exact", len(bs))
        self._found(a, bs, np.asarray(r["distance"], dtype=np.float64))

    def _found(self, a: int, bs: np.ndarray, d: np.ndarray) -> None:
        with self._lock:  # steps on threads: one row's list is updated by one at a time
            self._found_locked(a, bs, d)

    def _found_locked(self, a: int, bs: np.ndarray, d: np.ndarray) -> None:
        tau = self.tau
        keep = d <= np.maximum(tau[a], tau[bs]) + TIE  # the others can be in no list
        if keep.any():
            self.found.append((np.full(int(keep.sum()), a, dtype=np.int64), bs[keep], d[keep]))
        if self.best is None:
            return
        k = self.k
        if self.left[a]:
            merged = np.sort(np.concatenate([self.best[a], d]))[:k]
            self.best[a] = merged
            tau[a] = merged[k - 1]
        sel = self.left[bs] & (d < tau[bs])
        if sel.any():
            b = bs[sel]  # distinct positions
            merged = np.concatenate([self.best[b], d[sel, None]], axis=1)
            merged.sort(axis=1)
            self.best[b] = merged[:, :k]
            tau[b] = merged[:, k - 1]

    # ------------------------------------------------------------------ steps

    def seed(self) -> None:
        """Each restricted row's exact distances to the k rows of its own cell nearest by
        the invariant bound (each pair once): thresholds before the cells are joined."""
        col, k, left = self.col, self.k, self.left
        N = col.n
        pairs = []
        for c in range(len(col.start) - 1):
            lo, hi = int(col.start[c]), int(col.start[c + 1])
            q = lo + np.flatnonzero(left[lo:hi])
            if len(q) == 0 or hi - lo < 2:
                continue
            for a0 in range(0, len(q), max(1, _MATRIX_ENTRIES // (hi - lo))):
                qa = q[a0 : a0 + max(1, _MATRIX_ENTRIES // (hi - lo))]
                L = row_lower_bounds_many(col.fq[qa], col.split, col.F[lo:hi], col.sq[lo:hi])
                L[np.arange(len(qa)), qa - lo] = np.inf
                self._count("bounded", L.size)
                take = min(k, hi - lo - 1)
                near = np.argpartition(L, take - 1, axis=1)[:, :take] + lo
                a = np.repeat(qa, take)
                b = near.reshape(-1)
                # oriented as the join takes the pair up (see _step): from a, unless b is
                # on the restricted side too and comes first
                flip = left[b] & (b < a)
                pairs.append(np.where(flip, b, a) * N + np.where(flip, a, b))
        if not pairs:
            return
        keys = np.unique(np.concatenate(pairs))
        self.seeded = keys
        qs, bs = keys // N, keys % N
        cuts = np.flatnonzero(np.diff(qs)) + 1

        def one(part):
            part_q, part_b = part
            a = int(part_q[0])
            self._exact(a, part_b, np.maximum(self.tau[a], self.tau[part_b]))

        self._map(one, list(zip(np.split(qs, cuts), np.split(bs, cuts))))

    def _map(self, fn, items, done=None) -> None:
        """``fn(item)`` for every item, on ``threads`` threads (the kernels release the GIL);
        ``done(i)`` after item i, on the calling thread, in order."""
        if self.threads > 1 and len(items) > 1:
            from concurrent.futures import ThreadPoolExecutor

            with ThreadPoolExecutor(self.threads) as pool:
                try:
                    for i, _ in enumerate(pool.map(fn, items)):
                        if done is not None:
                            done(i)
                except BaseException:
                    self.stopping.set()  # before the pool waits for the running steps
                    raise
        else:
            for i, item in enumerate(items):
                fn(item)
                if done is not None:
                    done(i)

    def run(self, progress: Callable[[int, int], None] | None = None, cells: tuple[int, int] | None = None) -> None:
        """The seeds (k nearest only), then every cell's step in the table's order (only
        the steps of the cells ``[first, stop)`` when ``cells`` is given)."""
        from threadpoolctl import threadpool_limits

        # one BLAS thread: the products are small, and idle OpenBLAS workers spin and
        # steal the core the rest of the join runs on
        from ..matching.kernels import current

        if not current().threads:
            self.threads = 1  # kernels built holding the GIL: threads would take turns
        with threadpool_limits(1, user_api="blas"):
            if self.k is not None:
                self.seed()
            self._run(progress, cells)

    def _run(self, progress, cells) -> None:
        col = self.col
        C = len(col.start) - 1
        first, stop = (0, C) if cells is None else cells
        has_other = np.add.reduceat(~self.left, col.start[:-1]) > 0 if C else np.zeros(0, bool)

        def step(c):
            lo, hi = int(col.start[c]), int(col.start[c + 1])
            q = lo + np.flatnonzero(self.left[lo:hi])
            if len(q):
                self._step(c, q, has_other)

        # the steps may run at once: a pair is taken up by one step only, and a step reads
        # thresholds that only decrease (a stale one prunes less, never wrongly)
        steps = list(range(first, stop))
        self._map(step, steps, None if progress is None else (lambda i: progress(i + 1, len(steps))))

    def _step(self, c: int, q: np.ndarray, has_other: np.ndarray) -> None:
        """The queries ``q`` (restricted positions of cell c) against every row they pair
        with: rows of later cells, later rows of cell c, and rows off the restricted side
        anywhere (the pairs of two restricted rows are taken up by the first one's step)."""
        col, tau, left = self.col, self.tau, self.left
        C = len(col.start) - 1
        reach = query_radius(col.fq[q], col.split, col.centre[c])
        cb = cell_pair_lower_bounds(col.centre[c], reach, col.split, col.centre, col.radius)
        tau_cell = np.maximum.reduceat(tau, col.start[:-1])
        opened = cb <= margin(np.maximum(tau[q].max(), tau_cell))
        before = np.arange(C) < c
        opened &= ~before | has_other
        cells = np.flatnonzero(opened)
        self._count("cell_pairs", len(cells))
        cand = np.concatenate([np.arange(col.start[e], col.start[e + 1]) for e in cells] or [np.zeros(0, np.int64)])
        cand = cand[~left[cand] | (cand > q[0])]
        if len(cand) == 0:
            return
        chunk = max(1, _MATRIX_ENTRIES // len(cand))
        for a0 in range(0, len(q), chunk):
            if self.stopping.is_set():
                return
            qa = q[a0 : a0 + chunk]
            L = row_lower_bounds_many(col.fq[qa], col.split, col.F[cand], col.sq[cand])
            self._count("bounded", L.size)
            need = L <= margin(np.maximum(tau[qa][:, None], tau[cand][None, :]))
            need &= ~left[cand][None, :] | (cand[None, :] > qa[:, None])
            if len(self.seeded):
                ii, jj = np.nonzero(need)
                keys = qa[ii] * col.n + cand[jj]
                at = np.minimum(np.searchsorted(self.seeded, keys), len(self.seeded) - 1)
                done = self.seeded[at] == keys
                need[ii[done], jj[done]] = False
            for i, a in enumerate(qa):
                js = np.flatnonzero(need[i])
                if len(js) and not self.stopping.is_set():
                    self._pairs_of(int(a), cand[js], L[i, js])

    def _pairs_of(self, a: int, bs: np.ndarray, bound: np.ndarray) -> None:
        """Query position ``a`` against positions ``bs`` (invariant bounds ``bound``): the
        truncated stages, then exact distances in growing batches of increasing bound, each
        batch first filtered by the thresholds as they stand."""
        tau, col = self.tau, self.col
        order = np.argsort(bound, kind="stable")
        bs, bound = bs[order], bound[order]
        size = FIRST_BATCH
        if not np.isfinite(tau[a]):  # no threshold yet: the nearest by bound first
            self._exact(a, bs[:size], np.maximum(tau[a], tau[bs[:size]]))
            bs, bound = bs[size:], bound[size:]
            size = min(2 * size, EXACT_BATCH)
        A = None
        for stage, (Kp, grid) in enumerate(self.stages):
            thr = np.maximum(tau[a], tau[bs])
            keep = bound <= margin(thr)
            bs, bound, thr = bs[keep], bound[keep], thr[keep]
            limit = float(thr.max()) if len(thr) else np.inf
            if len(bs) < _TRUNCATE_FROM[min(stage, 1)] or not np.isfinite(limit):
                break
            if A is None:
                A = np.asarray(col.coef[a], dtype=np.complex128)
            tb = truncated_lower_bounds(
                A,
                col.coef[bs, :Kp],
                direction=self.cascade.direction,
                mirror=self.cascade.mirror,
                harmonics=Kp,
                grid=grid,
                limit=float(margin(limit)),
            )
            if stage == 0:
                self._count("truncated", len(bs))
            else:
                self._count("fine", len(bs))
            bound = np.maximum(bound, tb)
            order = np.argsort(bound, kind="stable")
            bs, bound = bs[order], bound[order]
        while len(bs) and not self.stopping.is_set():
            thr = np.maximum(tau[a], tau[bs])
            keep = bound <= margin(thr)
            bs, bound, thr = bs[keep], bound[keep], thr[keep]
            if not len(bs):
                break
            self._exact(a, bs[:size], thr[:size])
            bs, bound = bs[size:], bound[size:]
            size = min(2 * size, EXACT_BATCH)

    # ------------------------------------------------------------------ results

    def pairs(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Positions (a, b) and distances of every pair computed (each once)."""
        if not self.found:
            return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0)
        a, b, d = (np.concatenate([f[i] for f in self.found]) for i in range(3))
        return a, b, d


def _threads(threads: int | None) -> int:
    return max(1, threads or min(os.cpu_count() or 1, 4))


def join_input(table: SearchTable, read_coefficients: Callable[[np.ndarray], np.ndarray]) -> _Collection:
    """What a join reads, read once: every row's features and descriptors. A join given it
    instead of the table reads nothing (the several parts of one join on a worker)."""
    return _Collection(table, read_coefficients)


def _prepare(table, read_coefficients, cascade: Cascade, rows) -> tuple[_Collection, np.ndarray]:
    col = table if isinstance(table, _Collection) else _Collection(table, read_coefficients)
    if rows is None:
        left = np.ones(col.n, dtype=bool)
    else:
        marked = np.zeros(max(int(col.row.max(initial=-1)) + 1, 0), dtype=bool)
        rows = np.asarray(rows, dtype=np.int64).reshape(-1)
        if len(rows) and (rows.min() < 0 or rows.max() >= len(marked)):
            raise ParameterError("rows must be rows of the table")
        marked[rows] = True
        left = marked[col.row]
    return col, left


def nearest_others(
    table: SearchTable | _Collection,
    read_coefficients: Callable[[np.ndarray], np.ndarray],
    k: int,
    cascade: Cascade,
    *,
    rows: np.ndarray | None = None,
    tie_key: np.ndarray | None = None,
    progress: Callable[[int, int], None] | None = None,
    threads: int | None = None,
) -> tuple[np.ndarray, np.ndarray, JoinStats]:
    """Every row's k nearest other rows of ``table``, exactly.

    Parameters
    ----------
    table : :class:`~nfdmatch.search.table.SearchTable` (read whole: the join needs every
        row's features and descriptors).
    read_coefficients : ``rows -> (m, K, 3)`` complex, for a table holding the first
        harmonics only (format 1).
    k : neighbours per row (>= 1).
    cascade : :class:`~nfdmatch.search.engine.Cascade`: the distance and its options.
    rows : index rows whose lists are wanted (None: every row); the others' lists stay
        empty, and pairs of two other rows are never computed.
    tie_key : (N,) int, the order of distances within ``TIE`` of each other (default: the
        row number); an index's graph orders them by id.
    progress : ``progress(cells_done, cells)``.
    threads : cells joined at once (default: the cores, at most 4).

    Returns ``(neighbour, distance, stats)``: (N, k) int64 index rows (-1 past the last
    other row) and float64 distances (inf there), sorted by distance (ties by
    ``tie_key``), N the table's rows; :class:`JoinStats`.
    """
    check_limits(k, top_name="k")
    t0 = time.perf_counter()
    col, left = _prepare(table, read_coefficients, cascade, rows)
    join = _Join(col, cascade, left, k, None, _threads(threads))
    join.run(progress)
    N = col.n
    neighbour, distance = np.full((N, k), -1, dtype=np.int64), np.full((N, k), np.inf)
    pa, pb, d = join.pairs()
    # both orientations, each kept for a row on the restricted side within its k-th (+ ties)
    owner, other, dist = np.concatenate([pa, pb]), np.concatenate([pb, pa]), np.concatenate([d, d])
    keep = left[owner] & (dist <= join.tau[owner] + TIE)
    owner, other, dist = col.row[owner[keep]], col.row[other[keep]], dist[keep]
    key = np.arange(N) if tie_key is None else np.asarray(tie_key)
    order = np.lexsort((key[other], np.rint(dist / TIE), owner))
    owner, other, dist = owner[order], other[order], dist[order]
    first = np.searchsorted(owner, owner, side="left")
    rank = np.arange(len(owner)) - first
    inside = rank < k
    neighbour[owner[inside], rank[inside]] = other[inside]
    distance[owner[inside], rank[inside]] = dist[inside]
    join.stats.seconds = time.perf_counter() - t0
    return neighbour, distance, join.stats


def pairs_within(
    table: SearchTable | _Collection,
    read_coefficients: Callable[[np.ndarray], np.ndarray],
    max_distance: float,
    cascade: Cascade,
    *,
    rows: np.ndarray | None = None,
    progress: Callable[[int, int], None] | None = None,
    threads: int | None = None,
    cells: tuple[int, int] | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, JoinStats]:
    """Every pair of rows of ``table`` at most ``max_distance`` apart, exactly, each once.

    Arguments as :func:`nearest_others` (``table`` may also be a :func:`join_input`);
    ``rows``: only pairs with at least one row among them; ``cells``: ``(first, stop)``,
    only the pairs whose first row (in the table's order) lies in those cells: the parts of
    a join split by cells (``--scheduler``), whose pairs together are the whole join's.
    Returns ``(a, b, distance, stats)``: index rows with a < b, sorted by (a, b), and
    the distances (float64).
    """
    check_limits(max_distance=max_distance)
    t0 = time.perf_counter()
    col, left = _prepare(table, read_coefficients, cascade, rows)
    join = _Join(col, cascade, left, None, max_distance, _threads(threads))
    join.run(progress, cells)
    pa, pb, d = join.pairs()
    keep = d <= max_distance
    ra, rb, d = col.row[pa[keep]], col.row[pb[keep]], d[keep]
    a, b = np.minimum(ra, rb), np.maximum(ra, rb)
    order = np.lexsort((b, a))
    join.stats.seconds = time.perf_counter() - t0
    return a[order], b[order], d[order], join.stats


# --------------------------------------------------------------------------- an index
