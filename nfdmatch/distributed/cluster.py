"""The client side: :func:`connect` and :class:`Cluster` (build and search on the workers)."""

from __future__ import annotations

import os
import time

import numpy as np

from ..matching import EXACT, INVARIANT
from .._version import __version__
from ..errors import NfdError
from ..search.engine import BestRows
from .build_tasks import batches, compute_batches, failed_answer, file_size
from .search_tasks import (
    HeldDescriptors,
    forget_index,
    graph_part,
    index_ranges,
    index_stamp,
    pairs_part,
    ranked,
    search_range,
)
from .settings import (
    PIN_CHECK_SECONDS,
    QUERY_BLOCK,
    RANGE_BYTES,
    RETRIES,
    TABLE_ROW_BYTES,
    WINDOW_ROWS,
    ClusterError,
    first_line,
    worker_info,
)

__all__ = ["Cluster"]


class Cluster:
    """A connected Dask client whose workers run this nfdmatch (see :func:`connect`).

    Attributes: ``client`` (distributed.Client), ``address`` (what was asked for),
    ``workers`` (list of worker addresses), ``threads`` (total worker threads).
    A context manager: closing shuts down a LocalCluster it started.
    """

    def __init__(self, client, owned_client: bool, owned_cluster, address: str):
        self.client = client
        self._owned_client = owned_client
        self._owned_cluster = owned_cluster
        self.address = address
        self.workers: list[str] = []
        self.threads = 0
        self._held = None  # during a query over several ranges: descriptors sent back

    def __enter__(self) -> "Cluster":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        if self._owned_client and self.client is not None:
            try:
                self.client.close()
            except Exception:
                pass
        if self._owned_cluster is not None:
            try:
                self._owned_cluster.close()
            except Exception:
                pass
        self.client = self._owned_cluster = None

    def _check_workers(self, timeout: float) -> None:
        try:
            self.client.wait_for_workers(1, timeout=timeout)
        except Exception:
            raise ClusterError(
                f"no Dask worker joined the scheduler at {self.address} within {timeout:g} s; "
                f"start some with `dask worker {self.address}`"
            ) from None
        try:
            info = self.client.run(worker_info)
        except Exception as exc:  # nfdmatch not importable on a worker, ...
            raise ClusterError(
                f"the Dask workers cannot run nfdmatch ({type(exc).__name__}: "
                f"{first_line(exc)}); install nfdmatch {__version__} on every worker"
            ) from None
        mine = worker_info()
        bad = [
            f"{addr} runs nfdmatch {w.get('nfdmatch')} (index format {w.get('format_version')}, "
            f"Python {w.get('python')})"
            for addr, w in sorted(info.items())
            if (w.get("nfdmatch"), w.get("format_version"), w.get("python"))
            != (mine["nfdmatch"], mine["format_version"], mine["python"])
        ]
        if bad:
            raise ClusterError(
                f"the workers must run nfdmatch {mine['nfdmatch']} (index format "
                f"{mine['format_version']}, Python {mine['python']}) like this client: "
                + "; ".join(bad[:5])
                + (f"; and {len(bad) - 5} more" if len(bad) > 5 else "")
            )
        self.workers = sorted(info)
        threads = self.client.nthreads()
        self.threads = int(sum(threads.get(w, 1) for w in self.workers)) or 1

    # ----------------------------------------------------------------------- build

    def build_index(self, sources, index_path=None, **options):
        """:func:`nfdmatch.index.build_index` with the files computed on the workers, and
        the rows of its graph (``graph=K``) searched there.

        Same arguments (``jobs`` is ignored) and the same result: the plan and the writing
        stay here, the index written is the one a local build writes (the graph too, the
        same bytes). The workers read the graph's rows from the new index file by its path
        (a temporary file beside the index): the index's folder must be on storage every
        worker sees, under the same path."""
        from ..index import build_index

        options.pop("jobs", None)
        return build_index(
            sources, index_path, jobs=1, runner=self._run_build_tasks, graph_runner=self._run_graph_tasks, **options
        )

    def _run_graph_tasks(self, path: str, blocks: list, k: int, store) -> tuple[str, int]:
        """The build's graph searcher on the cluster (the ``graph_runner`` of
        :func:`nfdmatch.index.build_index`): one task per block of rows, each worker
        reading the closed new index file at ``path``; ``store(number, neighbour,
        distance)`` as blocks finish. Afterwards every worker closes the file (it is about
        to be written and moved). Returns ``(scheduler address, workers)``."""
        from distributed import as_completed

        from ..index import open_index

        path = os.path.abspath(path)
        with open_index(path) as idx:
            stamp = index_stamp(idx)
        futures = {}
        try:
            for number, block in enumerate(blocks):
                fut = self.client.submit(graph_part, path, stamp, block, int(k), retries=RETRIES, pure=False)
                futures[fut] = number
            for fut in as_completed(list(futures), loop=self.client.loop):
                answer = _task_result(fut, "graph")
                store(futures.pop(fut), answer["neighbour"], answer["distance"])
        finally:
            if futures:
                self.client.cancel(list(futures))
            try:
                self.client.run(forget_index, path)
            except Exception:  # a worker gone: its process, and the file it held, went with it
                pass
        return self.address, len(self.workers)

    def _run_build_tasks(self, tasks: list[tuple], jobs, lock_fd):
        """The build's task runner on the cluster: yield ``(task_number, result)`` as
        batches finish (the contract of ``nfdmatch.index.pool.run_tasks``)."""
        from distributed import as_completed

        from ..index import pool

        # the local pool's batches (each described by one call, as locally, so a cluster build
        # writes the same bits), grouped into Dask tasks of bounded size
        local = pool._batches(tasks)
        groups = batches(
            [tasks[b[0]] for b in local],
            self.threads,
            sizes=[sum(file_size(tasks[i][0]) for i in b) for b in local],
            counts=[len(b) for b in local],
        )
        futures = {}
        try:
            for group in groups:
                grouped = [local[g] for g in group]
                fut = self.client.submit(
                    compute_batches,
                    [[(i, tasks[i]) for i in b] for b in grouped],
                    os.getcwd(),
                    retries=RETRIES,
                    pure=False,
                )
                futures[fut] = [i for b in grouped for i in b]
            for fut in as_completed(list(futures), loop=self.client.loop):
                batch = futures.pop(fut)
                try:
                    results = fut.result()
                except Exception as exc:  # KilledWorker after every retry, a lost scheduler
                    results = [
                        failed_answer(
                            tasks[i][0],
                            f"the Dask task reading it failed on every try: {type(exc).__name__}: {first_line(exc)}",
                        )
                        for i in batch
                    ]
                for i, res in zip(batch, results):
                    yield i, res
        finally:
            if futures:
                self.client.cancel(list(futures))

    # ----------------------------------------------------------------------- query

    def search_index(
        self,
        index,
        queries,
        *,
        top: int | None = 10,
        max_distance: float | None = None,
        method: str = EXACT,
        direction: str = INVARIANT,
        mirror: bool = False,
        prune: bool = True,
        progress=None,
        parts: int | None = None,
        window: int | None = None,
        exclude_self: bool = False,
    ):
        """:func:`nfdmatch.search.search_index` over ranges of the index on the workers.

        Parameters
        ----------
        index : the index path, or an open :class:`nfdmatch.index.Index` (its ``path`` is
            what the workers open: a path every worker sees).
        queries, top, max_distance, method, direction, mirror, prune, exclude_self : as in
            :func:`~nfdmatch.search.search_index`.
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

    # ----------------------------------------------------------------------- self-join

    def pairs_within(self, index, max_distance: float, cascade, *, rows=None, progress=None, parts=None):
        """:func:`nfdmatch.search.join.pairs_within` of an open index on the workers, split
        by ranges of its search cells (a task joins the rows of its cells with every row
        after them; tasks taken as workers free up): the same pairs as a local run.

        progress : ``progress(cells_done, cells)``; parts : tasks (default: 4 per worker
        thread, so that the uneven ranges even out). Returns ``(a, b, distance, stats)``
        as that function."""
        from distributed import as_completed

        from ..search.join import JoinStats

        t0 = time.perf_counter()
        path = os.path.abspath(index.path)
        stamp = index_stamp(index)
        C = index.search_table().n_cells
        stats = JoinStats(rows=index.n_curves, cells=C)
        stats.left = index.n_curves if rows is None else len(np.unique(rows))
        n_parts = max(1, min(int(parts or 4 * max(1, self.threads)), C)) if C else 0
        edges = np.unique(np.round(np.linspace(0, C, n_parts + 1)).astype(np.int64)) if C else np.zeros(0, np.int64)
        found = []
        futures = {}
        done = 0
        if progress is not None:
            progress(0, C)
        try:
            for first, stop in zip(edges[:-1].tolist(), edges[1:].tolist()):
                fut = self.client.submit(
                    pairs_part,
                    path,
                    stamp,
                    first,
                    stop,
                    float(max_distance),
                    cascade,
                    rows,
                    retries=RETRIES,
                    pure=False,
                )
                futures[fut] = stop - first
            for fut in as_completed(list(futures), loop=self.client.loop):
                cells = futures.pop(fut)
                answer = _task_result(fut, "pairs")
                found.append(answer["pairs"])
                for key in ("cell_pairs", "bounded", "truncated", "fine", "exact"):
                    setattr(stats, key, getattr(stats, key) + int(answer[key]))
                done += cells
                if progress is not None:
                    progress(done, C)
        finally:
            if futures:
                self.client.cancel(list(futures))
        a, b, d = (
            (np.concatenate([f[i] for f in found]) for i in range(3))
            if found
            else (
                np.zeros(0, np.int64),
                np.zeros(0, np.int64),
                np.zeros(0),
            )
        )
        order = np.lexsort((b, a))
        stats.seconds = time.perf_counter() - t0
        return a[order], b[order], d[order], stats

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
                    answer = _task_result(fut, "search")
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


def _task_result(fut, what: str):
    """A finished task's answer; a task that failed on every retry is a ClusterError (an
    NfdError it raised stays what it is)."""
    try:
        return fut.result()
    except NfdError:
        raise
    except Exception as exc:
        raise ClusterError(f"a {what} task failed on every try: {type(exc).__name__}: {first_line(exc)}") from None
