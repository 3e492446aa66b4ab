"""The client side's query: :class:`ClusterSearch`, the search methods of
:class:`~.cluster.Cluster` (its base class, whose client, workers and threads they use):
a search over ranges of the index on the workers, in rounds."""

from __future__ import annotations

import os
import time
from typing import Any, TYPE_CHECKING

import numpy as np

from ..matching import EXACT, INVARIANT
from ..search.engine import BestRows
from ..search.index_search import UNSET, k_or_top
from .search_tasks import HeldDescriptors, index_ranges, index_stamp, ranked, search_range
from .settings import (
    PIN_CHECK_SECONDS,
    QUERY_BLOCK,
    RANGE_BYTES,
    RETRIES,
    TABLE_ROW_BYTES,
    WINDOW_ROWS,
    task_result,
)

if TYPE_CHECKING:
    import os
    from collections.abc import Callable, Sequence
    from ..curve import Curve
    from ..index.reader import Index
    from ..search.index_search import SearchResults

__all__ = ["ClusterSearch"]


class ClusterSearch:
    """:class:`~.cluster.Cluster`'s queries (``search_index``), on its ``client``, ``workers``
    and ``threads``; ``_held`` (set by :class:`~.cluster.Cluster`: None) holds, during a
    query over several ranges, the descriptors the workers sent back."""

    # set by Cluster, the class that this one is the base of
    client: Any
    workers: Any
    threads: int
    _held: Any

    # ----------------------------------------------------------------------- query

    def search_index(
        self,
        index: str | os.PathLike[str] | Index,
        queries: Sequence[Curve],
        *,
        k: int | None = 10,
        max_distance: float | None = None,
        method: str = EXACT,
        direction: str = INVARIANT,
        mirror: bool = False,
        prune: bool = True,
        progress: Callable[[int, int], None] | None = None,
        parts: int | None = None,
        window: int | None = None,
        exclude_self: bool = False,
        top: Any = UNSET,
    ) -> SearchResults:
        """:func:`nfdmatch.search.search_index` over ranges of the index on the workers.

        Parameters
        ----------
        index : the index path, or an open :class:`nfdmatch.index.Index` (its ``path`` is
            what the workers open: a path every worker sees).
        queries, k, max_distance, method, direction, mirror, prune, exclude_self : as in
            :func:`~nfdmatch.search.search_index` (``top``: the deprecated older name of ``k``).
        progress : ``progress(done, total)`` in units of (query, range) pairs answered
            (with several ranges, the first round counts as one more range).
        parts : index ranges. Default: 1 (every worker searches the whole index for its
            blocks of queries: the least work) while the index's search table is at most
            :data:`RANGE_BYTES` (what a worker may end up caching), else one per worker
            thread (each worker reads and caches only its range; the ranges cost more
            work, see :meth:`_search_ranges`). Pruned search splits by ranges of search
            cells (format 2; a format-1 index is one range), exhaustive search by rows.

        Returns
        -------
        ``(results, stats)`` exactly as :func:`~nfdmatch.search.search_index`: the same
        rows, distances and order (ties by id). ``stats.bytes_read`` sums the workers'.
        """
        from ..index import open_index
        from ..search import SearchStats

        from ..search.index_search import check_search_parameters

        top = k_or_top(k, top, "Cluster.search_index")
        check_search_parameters(top, max_distance, method)
        t0 = time.perf_counter()
        asked = top
        if exclude_self and top is not None:
            top += 1  # the query's own curve is dropped below
        own = not hasattr(index, "search_table")
        idx = open_index(index) if own else index
        try:
            stats = SearchStats(queries=len(queries), rows=idx.n_curves, pruned=prune)
            tops = [BestRows(top, max_distance) for _ in queries]
            if idx.n_curves and len(queries):
                params = dict(
                    top=top,
                    max_distance=max_distance,
                    method=method,
                    direction=direction,
                    mirror=mirror,
                    window=int(window or WINDOW_ROWS),
                )
                self._search_parts(idx, queries, tops, stats, progress, params, prune, parts)
            results = ranked(idx, tops, top)
            if exclude_self:
                from ..search.index_search import without_self

                results = without_self(idx, queries, results, asked)
        finally:
            if own:
                idx.close()
        stats.seconds = time.perf_counter() - t0
        return results, stats

    def _search_parts(self, idx, queries, tops, stats, progress, params: dict, prune: bool, parts) -> None:
        """Search the index's ranges (``parts`` of them, see :meth:`search_index`) on the
        workers into ``tops``, then recompute the reported distances (several ranges)."""
        from ..descriptors import descriptors_batch

        path = os.path.abspath(idx.path)
        stamp = index_stamp(idx)
        qcoef = descriptors_batch(
            queries, samples=idx.samples, harmonics=idx.harmonics, scale=idx.scale_mode
        ).coefficients
        if parts:
            n_parts = int(parts)
        else:
            n_parts = 1 if idx.n_curves * TABLE_ROW_BYTES <= RANGE_BYTES else self.threads
        ranges, stats.cell_count = index_ranges(idx, n_parts, prune)
        # one range: each query is answered whole by one task, whose worker also
        # recomputes the distances it reports in full (as a local search does, from the
        # descriptors it holds), so the client merges nothing
        params["final"] = len(ranges) == 1
        self._search_ranges(path, stamp, ranges, qcoef, tops, stats, progress, params)
        if params["final"]:
            return
        # the reported distances computed in full, as a local search does, from the
        # descriptors the workers sent with their rows (else read here)
        from ..matching import exact_search, paper_search
        from ..search.index_search import recompute_reported

        search = exact_search if params["method"] == EXACT else paper_search
        held = [HeldDescriptors(self._held[qi][0]) if self._held[qi][0] else None for qi in range(len(tops))]
        recompute_reported(
            idx, qcoef, tops, search, direction=params["direction"], mirror=params["mirror"], weights=None, tables=held
        )
        self._held = None

    def _search_ranges(self, path, stamp, ranges, qcoef, tops, stats, progress, params) -> None:
        """Fill ``tops`` with each query's exact top K over every range.

        A range searched alone has its own K-th distance, far looser than the whole
        index's when the query's neighbours lie in other ranges, and computes many exact
        distances before its own K best are proven (generated families, 2 ranges: 15x the
        exact distances of a local search). So with several ranges a first round answers
        each query on a window of the whole index, its cells of lowest bound
        (``params["window"]`` positions); those rows join the answer, and their distances
        seed every range's search of its other cells (they count towards its K-th, so it
        prunes about as hard as one search over the whole index; each range returns only
        its own rows). Exact: the window's rows within the final K-th are all in the
        window's answer, and a range never prunes a row below the K-th distance of (seeds +
        range), which is never below the global K-th."""
        Q, P = len(qcoef), len(ranges)
        seeded = P > 1 and params["top"] is not None and ranges[0][0] == "cells"
        total, done = Q * (P + seeded), 0
        if progress is not None:
            progress(0, total)
        everyone = np.arange(Q)
        seeds = None
        # per query: the descriptors the workers sent with their rows, and their count
        self._held = [[[], 0] for _ in range(Q)]
        if seeded:
            found = [BestRows(params["top"], params["max_distance"]) for _ in range(Q)]
            done = self._round(
                [(None, everyone, None)], path, stamp, qcoef, found, stats, progress, total, done, params
            )
            seeds = [{"rows": tk.rows, "dist": tk.dist, **tk.extra} for tk in found]
            for tk, seed in zip(tops, seeds):
                if len(seed["rows"]):
                    tk.add(seed["dist"], seed["rows"], seed)
        self._round(
            [(rng, everyone, seeds) for rng in ranges], path, stamp, qcoef, tops, stats, progress, total, done, params
        )

    def _round(self, jobs, path, stamp, qcoef, tops, stats, progress, total, done, params) -> int:
        """Run ``jobs`` = [(range or None for the window round, query numbers, per-query
        seeds or None)] as tasks of at most QUERY_BLOCK queries and merge their answers
        into ``tops``; returns the progress count."""
        from distributed import as_completed

        futures = {}
        pinned = {}  # future -> (its task's arguments, the worker it is pinned to)
        # one job (the whole index, or the window round): blocks spread over every thread
        size = QUERY_BLOCK if len(jobs) > 1 else max(1, min(QUERY_BLOCK, -(-len(qcoef) // (4 * self.threads))))
        try:
            for p, (rng, qs, seeds) in enumerate(jobs):
                # a range stays on one worker, whose cache then holds its cells for every block
                where = [self.workers[p % len(self.workers)]] if self.workers and len(jobs) > 1 else None
                for a in range(0, len(qs), size):
                    block = qs[a : a + size]
                    args = (
                        search_range,
                        path,
                        stamp,
                        rng,
                        np.ascontiguousarray(qcoef[block]),
                        None if seeds is None else [seeds[q] for q in block],
                        params,
                    )
                    fut = self.client.submit(
                        *args, retries=RETRIES, pure=False, workers=where, allow_other_workers=where is not None
                    )
                    futures[fut] = block
                    if where is not None:
                        pinned[fut] = (args, where[0])
            arriving = as_completed(list(futures), loop=self.client.loop)
            checked = time.monotonic()
            while futures:
                if pinned and not arriving.has_ready():
                    # pinned tasks: look now and then for workers that left (see _unpin_lost)
                    if time.monotonic() - checked > PIN_CHECK_SECONDS:
                        for again in self._unpin_lost(futures, pinned):
                            arriving.add(again)
                        checked = time.monotonic()
                    time.sleep(0.01)
                    continue
                for fut in arriving.next_batch(block=True):
                    if fut not in futures:  # cancelled and submitted again
                        continue
                    block = futures.pop(fut)
                    answer = task_result(fut, "search")
                    for qi, part in zip(block, answer["tops"]):
                        if len(part["rows"]):
                            if "coef" in part and self._held is not None:
                                held = self._held[qi]
                                part["position"] = np.arange(held[1], held[1] + len(part["rows"]))
                                held[0].append(part.pop("coef"))
                                held[1] += len(part["rows"])
                            tops[qi].add(part["dist"], part["rows"], part)
                    for key in ("exact", "truncated", "fine", "scanned", "cells", "bytes_read"):
                        setattr(stats, key, getattr(stats, key) + int(answer[key]))
                    done += len(block)
                    if progress is not None:
                        progress(done, total)
        finally:
            if futures:
                self.client.cancel(list(futures))
        return done

    def _unpin_lost(self, futures: dict, pinned: dict) -> list:
        """Submit again, on any worker, the waiting tasks pinned to a worker that has left.
        Dask leaves such a task "unrunnable" for good when every worker was lost at once:
        workers that join later are checked against the old address, whatever
        ``allow_other_workers`` says (a 1M-curve query waited forever after an out-of-memory
        kill of both workers)."""
        alive = set(self.client.scheduler_info(n_workers=-1).get("workers", {}))
        if alive:
            self.workers = sorted(alive)
        resubmitted = []
        for fut in [f for f in futures if f in pinned and pinned[f][1] not in alive and f.status == "pending"]:
            args, _ = pinned.pop(fut)
            again = self.client.submit(*args, retries=RETRIES, pure=False)
            futures[again] = futures.pop(fut)
            fut.cancel()
            resubmitted.append(again)
        return resubmitted
