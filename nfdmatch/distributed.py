"""Building and querying on a Dask cluster (``--scheduler``; docs/distributed.md).

The client keeps everything that decides the result: the build plan (stat, hash), the
writing of the index (temp file, atomic replace, lock), the merge of a query's per-range
top K. The workers only do the bulk work on files and index ranges they read from a path
every machine sees, and return plain numpy arrays, lists and dicts of builtins (never
pickled nfdmatch objects), so that what crosses the network does not depend on the
classes of either side -- only on the nfdmatch and index format versions, which
:func:`connect` checks.

Dask (``dask`` and ``distributed``, the ``distributed`` extra) is imported only here and
only when a cluster is asked for.

Library use::

    with connect("local:2") as cluster:            # or "tcp://host:8786", or a dask Client
        report = cluster.build_index(["curves/"], "curves.h5")
        results, stats = cluster.search_index("curves.h5", queries, top=10)

Test hook: a worker reports ``nfdmatch._version.__version__`` as its version (read when
:func:`connect` asks); tests change it on workers to act out a version mismatch.
"""

from __future__ import annotations

import os
import time

import numpy as np

from ._version import __version__
from .errors import NfdError, ParameterError
from .search.engine import TopK

__all__ = ["ClusterError", "Cluster", "connect", "DEFAULT_TIMEOUT", "TASK_BYTES", "INSTALL_HINT"]

#: seconds to reach the scheduler and see a worker before giving up (``--scheduler-timeout``)
DEFAULT_TIMEOUT = 10.0
#: bytes of input files per build task at most: big enough that a task's overhead (~1 ms on
#: the scheduler, a round trip) is small next to reading and describing, small enough that
#: a retried task redoes little and that every worker gets several tasks
TASK_BYTES = 16 << 20
#: files per build task at most (many tiny files: keeps progress and retries fine-grained)
TASK_FILES = 2048
#: build tasks per worker thread at least, when the files allow (load balance)
_TASKS_PER_THREAD = 4
#: queries per search task at most: progress granularity and the size of one task's answer
QUERY_BLOCK = 256
#: positions of a query's first-round window (its cells of lowest bound over the whole
#: index): enough to hold its near neighbours, whose distances then seed every range
WINDOW_ROWS = 2048
#: a search table (features, norms, first harmonics, row numbers of every row) up to this
#: size is searched whole by each worker; a bigger one is split in ranges, one per thread
RANGE_BYTES = 2 << 30
#: bytes per index row of a search table held in memory, at K = 16 (35 float32 features,
#: 2 float64 norms, 4 x 3 complex64 harmonics, an int64 row)
_TABLE_ROW_BYTES = 260
#: seconds between checks, while a query waits for its range tasks, that the workers they
#: are pinned to are still there
_PIN_CHECK_SECONDS = 2.0
#: times Dask re-runs a task that raised (a worker that died is rescheduled by the scheduler
#: itself, up to ``distributed.scheduler.allowed-failures`` times)
RETRIES = 2
INSTALL_HINT = "pip install 'nfdmatch[distributed]' (dask and distributed)"


class ClusterError(NfdError, RuntimeError):
    """The cluster cannot be used: dask missing, scheduler unreachable, no workers, workers
    running another nfdmatch or index format version, a task that failed on every retry."""


def _import_distributed():
    try:
        import distributed  # noqa: F401
    except ImportError:
        raise ClusterError(f"--scheduler needs dask and distributed, which are not installed: {INSTALL_HINT}") from None
    return distributed


# --------------------------------------------------------------------------- connecting


def _worker_info() -> dict:
    """Run on each worker at connect: what must equal the client's (read at call time)."""
    import sys

    from . import _version
    from .index.schema import FORMAT_VERSION

    return {
        "nfdmatch": _version.__version__,
        "format_version": int(FORMAT_VERSION),
        "python": "%d.%d" % sys.version_info[:2],
    }


#: Dask settings for a cluster nfdmatch starts on this machine (``local:N``): its scheduler,
#: nannies and workers wake up less often (event-loop tick 20 ms -> 1 s, worker memory check
#: 100 ms -> 2 s, system monitor 500 ms -> 5 s, no statistical profiler). Idle, a 2-worker
#: cluster slowed a local build on the same 2 cores by 16% with Dask's defaults, 10% with
#: these (benchmarks/bench_distributed.py; docs/distributed.md). What they give up: the
#: dashboard's fine-grained figures and a worker's reaction to a memory spike within 2 s
#: instead of 0.1 s (a task holds at most TASK_BYTES of files).
_LOCAL_CLUSTER_CONFIG = {
    "distributed.admin.tick.interval": "1s",
    "distributed.worker.memory.monitor-interval": "2s",
    "distributed.admin.system-monitor.interval": "5s",
    "distributed.worker.profile.enabled": False,
}


def connect(scheduler, timeout: float = DEFAULT_TIMEOUT) -> "Cluster":
    """Connect to a Dask cluster and check its workers.

    Parameters
    ----------
    scheduler : ``"local:N"`` (start a LocalCluster of N single-threaded worker processes
        on this machine; ``"local"``: one per core), a scheduler address
        (``"tcp://host:8786"``, ``"host:8786"``), or an existing ``distributed.Client``
        (not closed by :meth:`Cluster.close`).
    timeout : seconds to reach the scheduler and to see at least one worker.

    Raises
    ------
    ClusterError : dask not installed; scheduler unreachable or no worker within
        ``timeout``; a worker whose nfdmatch, index format or Python version differs from
        this process's.
    ParameterError : a malformed ``local:N``, a timeout not > 0.
    """
    if isinstance(timeout, bool) or not isinstance(timeout, (int, float)) or not timeout > 0:
        raise ParameterError(f"the scheduler timeout must be a number of seconds > 0, got {timeout!r}")
    _import_distributed()
    import logging

    from distributed import Client, LocalCluster

    owned_cluster = None
    if isinstance(scheduler, Client):
        client, owned_client = scheduler, False
        where = str(scheduler.scheduler.address if scheduler.scheduler else scheduler)
    else:
        where = str(scheduler).strip()
        if where == "local" or where.startswith("local:"):
            n = where.partition(":")[2]
            try:
                workers = int(n) if n else (os.cpu_count() or 1)
            except ValueError:
                workers = 0
            if workers < 1:
                raise ParameterError(f"--scheduler local:N needs a number of workers N >= 1, got {where!r}")
            import dask

            try:
                # its processes share this machine's cores with the work: fewer wake-ups
                with dask.config.set(_LOCAL_CLUSTER_CONFIG):
                    owned_cluster = LocalCluster(
                        n_workers=workers,
                        threads_per_worker=1,
                        processes=True,
                        # its HTTP routes on a free port: None still binds 8787, and
                        # warns when another cluster on this machine holds it
                        dashboard_address=":0",
                        silence_logs=logging.ERROR,
                    )
            except Exception as exc:
                raise ClusterError(
                    f"cannot start a local Dask cluster of {workers} workers: {type(exc).__name__}: {exc}"
                ) from None
            target = owned_cluster
        else:
            target = where
        try:
            client = Client(target, timeout=timeout, set_as_default=False)
        except Exception as exc:  # OSError / TimeoutError: nothing listening, wrong host
            if owned_cluster is not None:
                owned_cluster.close()
            raise ClusterError(
                f"cannot reach the Dask scheduler at {where} within {timeout:g} s "
                f"({type(exc).__name__}: {_first_line(exc)}); start one with "
                f"`dask scheduler` or use --scheduler local:N"
            ) from None
        owned_client = True
    cluster = Cluster(client, owned_client, owned_cluster, where)
    try:
        cluster._check_workers(timeout)
    except BaseException:
        cluster.close()
        raise
    return cluster


def _first_line(exc) -> str:
    text = str(exc).strip().splitlines()
    return text[0] if text else type(exc).__name__


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
            info = self.client.run(_worker_info)
        except Exception as exc:  # nfdmatch not importable on a worker, ...
            raise ClusterError(
                f"the Dask workers cannot run nfdmatch ({type(exc).__name__}: "
                f"{_first_line(exc)}); install nfdmatch {__version__} on every worker"
            ) from None
        mine = _worker_info()
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
        """:func:`nfdmatch.index.build_index` with the files computed on the workers.

        Same arguments (``jobs`` is ignored) and the same result: the plan and the writing
        stay here, the index written is the one a local build writes."""
        from .index import build_index

        options.pop("jobs", None)
        return build_index(sources, index_path, jobs=1, runner=self._run_build_tasks, **options)

    def _run_build_tasks(self, tasks: list[tuple], jobs, lock_fd):
        """The build's task runner on the cluster: yield ``(task_number, result)`` as
        batches finish (the contract of ``nfdmatch.index.pool._run_tasks``)."""
        from distributed import as_completed

        from .index import pool

        # the local pool's batches (each described by one call, as locally, so a cluster build
        # writes the same bits), grouped into Dask tasks of bounded size
        local = pool._batches(tasks)
        groups = _batches(
            [tasks[b[0]] for b in local],
            self.threads,
            sizes=[sum(_size(tasks[i][0]) for i in b) for b in local],
            counts=[len(b) for b in local],
        )
        futures = {}
        try:
            for group in groups:
                batches = [local[g] for g in group]
                fut = self.client.submit(
                    _compute_batches,
                    [[(i, tasks[i]) for i in b] for b in batches],
                    os.getcwd(),
                    retries=RETRIES,
                    pure=False,
                )
                futures[fut] = [i for b in batches for i in b]
            for fut in as_completed(list(futures), loop=self.client.loop):
                batch = futures.pop(fut)
                try:
                    results = fut.result()
                except Exception as exc:  # KilledWorker after every retry, a lost scheduler
                    results = [
                        _failed(
                            tasks[i][0],
                            f"the Dask task reading it failed on every try: {type(exc).__name__}: {_first_line(exc)}",
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
        method: str = "exact",
        direction: str = "invariant",
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
        from .index import open_index
        from .search import SearchStats

        from .search.index_search import check_search_parameters

        check_search_parameters(top, max_distance, method)
        t0 = time.perf_counter()
        asked = top
        if exclude_self and top is not None:
            top += 1  # the query's own curve is dropped below
        own = not hasattr(index, "search_table")
        idx = open_index(index) if own else index
        try:
            from .descriptors import descriptors_batch
            from .search.engine import TopK

            path = os.path.abspath(idx.path)
            stamp = (idx.n_curves, idx.updated, idx.samples, idx.harmonics, idx.scale_mode)
            stats = SearchStats(queries=len(queries), rows=idx.n_curves, pruned=prune)
            tops = [TopK(top, max_distance) for _ in queries]
            if idx.n_curves and len(queries):
                qcoef = descriptors_batch(
                    queries, samples=idx.samples, harmonics=idx.harmonics, scale=idx.scale_mode
                ).coefficients
                if parts:
                    n_parts = int(parts)
                else:
                    n_parts = 1 if idx.n_curves * _TABLE_ROW_BYTES <= RANGE_BYTES else self.threads
                ranges, stats.cell_count = _ranges(idx, n_parts, prune)
                params = dict(
                    top=top,
                    max_distance=max_distance,
                    method=method,
                    direction=direction,
                    mirror=mirror,
                    window=int(window or WINDOW_ROWS),
                )
                # one range: each query is answered whole by one task, whose worker also
                # recomputes the distances it reports on the reference path (as a local
                # search does, from the descriptors it holds), so the client merges nothing
                params["final"] = len(ranges) == 1
                self._search_ranges(path, stamp, ranges, qcoef, tops, stats, progress, params)
                if not params["final"]:
                    # the reported distances from the reference path, as a local search does,
                    # from the descriptors the workers sent with their rows (else read here)
                    from .matching import exact_search, paper_search
                    from .search.index_search import _recompute

                    search = exact_search if method == "exact" else paper_search
                    held = [_Held(self._held[qi][0]) if self._held[qi][0] else None for qi in range(len(tops))]
                    _recompute(idx, qcoef, tops, search, direction=direction, mirror=mirror, weights=None, tables=held)
                    self._held = None
            results = _ranked(idx, tops, top)
            if exclude_self:
                from .search.index_search import without_self

                results = without_self(idx, queries, results, asked)
        finally:
            if own:
                idx.close()
        stats.seconds = time.perf_counter() - t0
        return results, stats

    # ----------------------------------------------------------------------- self-join

    def pairs_within(self, index, max_distance: float, cascade, *, rows=None, progress=None, parts=None):
        """:func:`nfdmatch.search.join.pairs_within` of an open index on the workers, split
        by ranges of its search cells (a task joins the rows of its cells with every row
        after them; tasks taken as workers free up): the same pairs as a local run.

        progress : ``progress(cells_done, cells)``; parts : tasks (default: 4 per worker
        thread, so that the uneven ranges even out). Returns ``(a, b, distance, stats)``
        as that function."""
        from distributed import as_completed

        from .search.join import JoinStats

        t0 = time.perf_counter()
        path = os.path.abspath(index.path)
        stamp = (index.n_curves, index.updated, index.samples, index.harmonics, index.scale_mode)
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
                    _pairs_part,
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
                try:
                    answer = fut.result()
                except NfdError:
                    raise
                except Exception as exc:
                    raise ClusterError(
                        f"a pairs task failed on every try: {type(exc).__name__}: {_first_line(exc)}"
                    ) from None
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
            found = [TopK(params["top"], params["max_distance"]) for _ in range(Q)]
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
                        _search_range,
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
                    if time.monotonic() - checked > _PIN_CHECK_SECONDS:
                        for again in self._unpin_lost(futures, pinned):
                            arriving.add(again)
                        checked = time.monotonic()
                    time.sleep(0.01)
                    continue
                for fut in arriving.next_batch(block=True):
                    if fut not in futures:  # cancelled and submitted again
                        continue
                    block = futures.pop(fut)
                    try:
                        answer = fut.result()
                    except NfdError:
                        raise
                    except Exception as exc:
                        raise ClusterError(
                            f"a search task failed on every try: {type(exc).__name__}: {_first_line(exc)}"
                        ) from None
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


# --------------------------------------------------------------------------- build tasks


def _size(path: str) -> int:
    try:
        return os.stat(path).st_size
    except OSError:
        return 0


def _batches(tasks: list[tuple], threads: int, *, sizes=None, counts=None) -> list[list[int]]:
    """Items grouped in order into Dask tasks of at most TASK_BYTES (a bigger item is a task
    alone) and TASK_FILES files. An item is a task (one file: its size on disk), or, with
    ``sizes`` and ``counts``, a local batch of ``counts[i]`` files and ``sizes[i]`` bytes."""
    sizes = [_size(t[0]) for t in tasks] if sizes is None else list(sizes)
    counts = [1] * len(sizes) if counts is None else list(counts)
    files = sum(counts)
    # small builds still give every worker thread a few tasks
    limit = max(1, min(TASK_BYTES, sum(sizes) // max(1, threads * _TASKS_PER_THREAD)))
    per_files = max(1, min(TASK_FILES, -(-files // max(1, threads * _TASKS_PER_THREAD))))
    batches, current, nbytes, nfiles = [], [], 0, 0
    for i, (size, count) in enumerate(zip(sizes, counts)):
        if current and (nbytes + size > limit or nfiles + count > per_files):
            batches.append(current)
            current, nbytes, nfiles = [], 0, 0
        current.append(i)
        nbytes += size
        nfiles += count
    if current:
        batches.append(current)
    return batches


def _failed(path: str, message: str) -> dict:
    return {"path": path, "size": 0, "mtime_ns": 0, "sha256": "", "status": "failed", "error": f"{path}: {message}"}


def _compute_batches(batches: list[list[tuple[int, tuple]]], cwd: str) -> list[dict]:
    """On a worker: each local batch (``(task_number, task)`` pairs) read and described by
    :func:`nfdmatch.index.pool._compute_batch`, as the local pool does (it never raises for
    a bad file); one result per task, in order. Returns dicts of builtins and numpy arrays.

    A relative path is the client's (its working folder ``cwd``, which the worker need not
    share): the file is read by its absolute name and the result speaks of the path as
    given, so ids and messages are those of a local build."""
    from .errors import escape_name
    from .index import pool

    out = []
    for batch in batches:
        given = [task[0] for _, task in batch]
        full = [p if os.path.isabs(p) else os.path.join(cwd, p) for p in given]
        # looked up on the module at each call, not bound at import
        results, arrays = pool._compute_batch([(n, (f, *task[1:])) for (n, task), f in zip(batch, full)])
        for res, path, fpath in zip(pool._split(results, arrays), given, full):
            if fpath != path:
                res["path"] = path
                names = [(escape_name(fpath), escape_name(path)), (fpath, path)]  # ids and messages escape
                if "ids" in res:
                    res["ids"] = [
                        next((new + i[len(old) :] for old, new in names if i.startswith(old)), i) for i in res["ids"]
                    ]
                for old, new in names:
                    if old in res["error"]:
                        res["error"] = res["error"].replace(old, new, 1)
                        break
            out.append(res)
    return out


# --------------------------------------------------------------------------- search tasks


def _ranges(idx, parts: int, prune: bool):
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
    from .index import open_index

    key = (path, stamp)
    entry = _OPEN.get(key)
    if entry is None:
        for old_key in [k for k in _OPEN if k[0] == path]:  # a replaced index: drop the old one
            _OPEN.pop(old_key)[0].close()
        idx = open_index(path)
        got = (idx.n_curves, idx.updated, idx.samples, idx.harmonics, idx.scale_mode)
        if got != tuple(stamp):
            idx.close()
            raise ClusterError(
                "the index a worker opened is not the one the client opened (replaced by a "
                "build meanwhile, or another file at that path on the worker): query again",
                path=path,
            )
        entry = _OPEN[key] = [idx, None, {}]
    return entry


def _pairs_part(path: str, stamp: tuple, first: int, stop: int, max_distance: float, cascade, rows) -> dict:
    """On a worker: the pairs within ``max_distance`` whose first row lies in the search
    cells ``[first, stop)`` (:func:`nfdmatch.search.join.pairs_within`); the index's rows
    are read once per worker process and kept for its other parts.

    Returns ``{"pairs": (a, b, distance) arrays, cell_pairs, bounded, truncated, fine,
    exact}``."""
    from .search.join import join_input, pairs_within

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


class _SeededTopK(TopK):
    """A TopK holding rows found elsewhere (seeds) from the start: a row of this range that
    is also a seed is not added twice (it would count twice towards the K-th distance)."""

    def __init__(self, k, max_distance, seed: dict | None):
        super().__init__(k, max_distance)
        self._seen = np.zeros(0, dtype=np.int64)
        if seed is not None and len(seed["rows"]):
            super().add(
                np.asarray(seed["dist"], dtype=np.float64),
                np.asarray(seed["rows"], dtype=np.int64),
                {key: np.asarray(seed[key]) for key in self.extra if key in seed},
            )
            self._seen = np.sort(np.asarray(seed["rows"], dtype=np.int64))

    def add(self, dist, rows, result) -> None:
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


def _search_range(path: str, stamp: tuple, rng, qcoef: np.ndarray, seeds, params: dict) -> dict:
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
    from .search.bounds import feature_vector
    from .search.engine import Cascade, search_block

    entry = _worker_index(path, stamp)
    idx, cache = entry[0], entry[2]
    cascade = Cascade(idx.samples, params["method"], params["direction"], params["mirror"])
    search = cascade.distance
    tops = [
        _SeededTopK(params["top"], params["max_distance"], None if seeds is None else seeds[q])
        for q in range(len(qcoef))
    ]
    out = {"exact": 0, "truncated": 0, "fine": 0, "scanned": 0, "cells": 0, "bytes_read": 0}
    searched = None  # the table searched, when one range holds every row
    # per query: the descriptors of its rows (for the client's recomputation), taken right
    # after its search. Holding each query's table until the end instead kept every query's
    # cells alive at once: a block of 256 queries over half of a 1M-curve index grew a
    # worker past 11 GB
    held = [None] * len(tops)
    want_coef = not params.get("final")

    def own_rows(q):
        """Which of query q's rows this task found (not seeds found elsewhere)."""
        tk = tops[q]
        if seeds is None:
            return np.ones(len(tk.rows), dtype=bool)
        return ~_member(tk.rows, np.sort(np.asarray(seeds[q]["rows"], dtype=np.int64)))

    def keep_descriptors(qi, table):
        if want_coef and len(tops[qi].rows):
            positions = tops[qi].extra["position"][own_rows(qi)]
            if len(positions) and positions.min() >= 0:
                held[qi] = table.coefficients_at_positions(positions)

    if rng is not None and rng[0] == "rows":
        from .search.index_search import EXHAUSTIVE_ROWS

        kind, lo, hi = rng
        for a in range(lo, hi, EXHAUSTIVE_ROWS * 8):
            b = min(hi, a + EXHAUSTIVE_ROWS * 8)
            coefficients = idx.read_rows(a, b, ("coefficients",), upcast=False)["coefficients"]
            out["bytes_read"] += coefficients.nbytes
            rows = np.arange(a, b)
            for qi, tk in enumerate(tops):
                for s in range(0, len(rows), EXHAUSTIVE_ROWS):
                    r = search(
                        qcoef[qi],
                        coefficients[s : s + EXHAUSTIVE_ROWS],
                        idx.samples,
                        direction=params["direction"],
                        mirror=params["mirror"],
                    )
                    tk.add(r["distance"], rows[s : s + EXHAUSTIVE_ROWS], r)
        out["exact"] = (hi - lo) * len(tops)
    else:
        if entry[1] is None:
            entry[1] = idx.search_table()
        table = entry[1]
        qfeat = feature_vector(qcoef)
        if rng is None:  # the window round
            # each query over its window's cells of the whole table (the other cells
            # skipped), through the one table's reads and cache: a table of its own per
            # query copied every cell it opened
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
                done=lambda qi, _: keep_descriptors(qi, table),
                expect_more=False,
            )
            _account(out, work)
            out["bytes_read"] += table.bytes_read - before
        else:
            _, lo, hi = rng
            key = ("range", lo, hi)
            if (lo, hi) == (0, table.n_cells):
                sub = table  # the whole index: no second table
            else:
                if key not in cache:
                    cache[key] = table.subset((lo, hi))
                sub = cache[key]
            searched = sub
            before = sub.bytes_read
            asked, skips = [], []
            for qi in range(len(tops)):
                skip = None
                if seeds is not None:
                    # the window's cells were searched in the first round: their rows within
                    # the K-th are all among the seeds already (skipped, not copied out into
                    # a table of the other cells per query: at 1M that copy was most of a
                    # query's time)
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
                done=lambda i, _: keep_descriptors(asked[i], sub),
            )
            _account(out, work)
            out["bytes_read"] = sub.bytes_read - before
    if params.get("final"):
        # this task's answer is the query's answer: its distances from the reference path,
        # exactly as search_index reports them (from the descriptors of the table searched)
        from .search.index_search import _recompute

        _recompute(
            idx,
            qcoef,
            tops,
            search,
            direction=params["direction"],
            mirror=params["mirror"],
            weights=None,
            tables=searched,
        )
    out["tops"] = []
    for q, tk in enumerate(tops):
        keep = own_rows(q)
        out["tops"].append(
            {
                "rows": tk.rows[keep].astype(np.int64),
                "dist": np.asarray(tk.dist[keep], np.float64),
                "shift": np.asarray(tk.extra["shift"][keep], dtype=np.float64),
                "reversed": np.asarray(tk.extra["reversed"][keep], dtype=bool),
                "mirrored": np.asarray(tk.extra["mirrored"][keep], dtype=bool),
            }
        )
        if held[q] is not None:
            # the rows' descriptors, for the client's recomputation (no scattered index reads)
            out["tops"][-1]["coef"] = held[q]
    return out


class _Held:
    """A query's descriptors sent by the workers, behind the one method of a search table
    that :func:`nfdmatch.search.index_search._recompute` uses."""

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


def _ranked(idx, tops, top) -> list[list]:
    """The :class:`~nfdmatch.records.RankedMatch` es of :func:`nfdmatch.search.search_index`
    from merged TopKs (the same code)."""
    from .search.index_search import ranked_rows

    return ranked_rows(idx, tops, top)
