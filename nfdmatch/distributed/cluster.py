"""The client side: :func:`connect` and :class:`Cluster` (build and search on the workers;
the search's methods in :mod:`.cluster_search`)."""

from __future__ import annotations

from typing import Any, TYPE_CHECKING

import os
import time

import numpy as np

from .._version import __version__
from .build_tasks import batches, compute_batches, failed_answer, file_size
from .cluster_search import ClusterSearch
from .search_tasks import forget_index, graph_part, index_stamp, pairs_part
from .settings import CLEANUP_TIMEOUT, RETRIES, ClusterError, first_line, task_result, worker_info

if TYPE_CHECKING:
    import os
    from collections.abc import Callable, Sequence
    from ..index.build import BuildReport
    from ..index.reader import Index
    from ..search.engine import Cascade
    from ..search.join import JoinStats

__all__ = ["Cluster"]


class Cluster(ClusterSearch):
    """A connected Dask client whose workers run this nfdmatch (see :func:`connect`).

    Attributes: ``client`` (distributed.Client), ``address`` (what was asked for),
    ``workers`` (list of worker addresses), ``threads`` (total worker threads).
    A context manager: closing shuts down a LocalCluster it started. Its queries:
    :class:`~.cluster_search.ClusterSearch`.
    """

    def __init__(self, client: Any, owned_client: bool, owned_cluster: Any, address: str) -> None:
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
            info = self.client.run(worker_info, callback_timeout=timeout)
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

    def build_index(
        self,
        sources: str | os.PathLike[str] | Sequence[str | os.PathLike[str]] | None,
        index_path: str | os.PathLike[str] | None = None,
        **options: Any,
    ) -> BuildReport:
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
                answer = task_result(fut, "graph")
                store(futures.pop(fut), answer["neighbour"], answer["distance"])
        finally:
            if futures:
                self.client.cancel(list(futures))
            try:
                self.client.run(forget_index, path, callback_timeout=CLEANUP_TIMEOUT)
            except Exception:  # a worker gone (its process, and the file it held, went with it) or stuck
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

    # ----------------------------------------------------------------------- self-join

    def pairs_within(
        self,
        index: Index,
        max_distance: float,
        cascade: Cascade,
        *,
        rows: np.ndarray | None = None,
        progress: Callable[[int, int], None] | None = None,
        parts: int | None = None,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, JoinStats]:
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
                answer = task_result(fut, "pairs")
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
