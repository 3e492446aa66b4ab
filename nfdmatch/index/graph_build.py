"""The build side of ``/graph``: which rows' lists a build keeps, which it computes (the
k-NN graph is a search: :func:`nfdmatch.search.graph.neighbour_lists`), and the writing of
the group into the new index file. Loaded by a build only (a query reads /graph through
:mod:`.graph`)."""

from __future__ import annotations

from typing import Any, TYPE_CHECKING

import time
from dataclasses import dataclass

import numpy as np

from ..errors import IndexFormatError
from ..search.engine import Cascade
from ..defaults import FUSED_CANDIDATES
from ..search.graph import GraphLists, fused_lists, graph_blocks, neighbour_lists, update_copied
from .arrays import unique_rows
from .graph import (
    GRAPH_CHECKSUMS,
    GRAPH_CHUNK_ROWS,
    reverse_of,
    IN_MEMORY_ROWS,
    GraphStats,
    asked_graph,
    graph_distance,
    old_graph_k,
    read_graph,
)
from .schema import create_checked, set_text
from .search_group import search_table

if TYPE_CHECKING:
    from collections.abc import Sequence
    import h5py
    from numpy.typing import NDArray
    from .reader import Index

__all__ = ["write_graph", "plan_graph", "blocks_to_search", "store_graph", "GraphPlan", "FUSED_CANDIDATES"]


@dataclass
class GraphPlan:
    """A graph being computed in a new index file: ``stats`` (what is done so far, its
    clock started), ``k``, the lists ``lists`` (:class:`~nfdmatch.search.graph.GraphLists`:
    the copied ones filled, the rows to search marked), what the search reads (``table``,
    ``read_coefficients``, the rows' ``ids``; ``table`` None for an index without rows) and
    the index's ``samples``; ``t0`` when it began."""

    stats: GraphStats
    k: int
    t0: float
    samples: int = 0
    lists: GraphLists | None = None
    table: object = None
    read_coefficients: object = None
    ids: object = None
    #: what the stored distances are (``"exact"`` or ``"fused"``); a fused graph's search
    #: finds each row's exact ``k`` nearest (the candidates) and keeps its ``final_k`` of
    #: least fused distance
    distance: str = "exact"
    final_k: int = 0
    read_statistics: object = None

    def store(self, rows: NDArray[np.int64], neighbour: NDArray[np.int64], distance: NDArray[np.float64]) -> None:
        """The lists ((m, k) int64 / float64) of ``rows``, searched elsewhere."""
        self.lists.neighbour[rows], self.lists.distance[rows] = neighbour, distance


def write_graph(
    h5: h5py.File,
    old: Index | None,
    k: int | None,
    *,
    reuse: bool,
    threads: int | None = None,
    processes: int = 1,
    close_fds: Sequence[int] = (),
    progress: Any = None,
) -> GraphStats:
    """Write ``/graph`` into the new index file ``h5`` (``/curves``, ``/files``, ``/search``
    complete); returns :class:`GraphStats`.

    old : the previous :class:`~nfdmatch.index.Index` (open) or None.
    k : neighbours per row; None keeps the old index's graph K (no graph when it had none);
        0 writes no graph.
    reuse : False searches every row (the curves were recomputed: --rebuild, new parameters).
    threads, processes, close_fds : how the rows are searched
        (:func:`~nfdmatch.search.graph.neighbour_lists`): ``processes`` forked workers (a
        build's ``jobs``), each closing ``close_fds`` (the index lock), else ``threads``.
    progress : ``progress(done_rows, total_rows)`` as the rows are searched.
    """
    plan = plan_graph(h5, old, k, reuse=reuse)
    if plan is None:
        return GraphStats()
    stats = plan.stats
    if plan.table is not None:
        stats.searched, stats.updated, stats.processes = neighbour_lists(
            plan.table,
            plan.read_coefficients,
            plan.ids,
            plan.lists,
            plan.k,
            plan.samples,
            threads=threads,
            processes=processes,
            close_fds=[fd for fd in close_fds if fd is not None],
            progress=progress,
        )
        stats.kept = len(plan.lists.check) - stats.updated
    return store_graph(h5, plan, processes=processes, close_fds=[fd for fd in close_fds if fd is not None])


def plan_graph(h5: h5py.File, old: Index | None, k: int | None, *, reuse: bool) -> GraphPlan | None:
    """What :func:`write_graph` computes in the new index file ``h5``, before any search: the
    lists kept from ``old`` and the rows to search (arguments as that function's). None
    when no graph is to be written (``k`` 0, or None and the old index had none)."""
    t0 = time.perf_counter()
    k, kind = asked_graph(old, k)
    if k <= 0:
        return None
    curves = h5["curves"]
    N = curves["coefficients"].shape[0]
    final_k = k
    if kind == "fused":
        # the candidates of a row's fused list: its exact nearest; a fused list is no exact
        # top K, so an old one is never reused (a row's candidates may change with any row)
        k = min(max(FUSED_CANDIDATES, 3 * final_k), max(N - 1, final_k))
        reuse = False
    elif graph_distance(old) != "exact":
        reuse = False
    plan = GraphPlan(GraphStats(k=final_k, distance=kind), k, t0, distance=kind, final_k=final_k)
    K = int(h5.attrs["harmonics"])
    plan.samples = int(h5.attrs["samples"])
    plan.ids = np.asarray(curves["id"].asstr()[...], dtype=object)
    neighbour = np.full((N, k), -1, dtype=np.int64)
    distance = np.full((N, k), np.inf)

    todo, check, fresh = _keep_old_lists(h5, old, k, reuse, neighbour, distance)
    plan.lists = GraphLists(neighbour, distance, todo, check, np.flatnonzero(fresh))
    if not N:
        return plan
    read_coefficients = _coefficient_reader(h5)

    def fail(message):
        raise IndexFormatError(f"corrupted nfdmatch index being written: {message}")

    plan.read_coefficients = read_coefficients
    if kind == "fused":
        statistics = curves["statistics"][...]
        plan.read_statistics = lambda rows: statistics[np.asarray(rows, dtype=np.int64)].astype(np.float64)
    plan.table = search_table(h5, N, K, read_coefficients, fail)
    fresh_rows = plan.lists.fresh_rows
    if len(check) and len(fresh_rows):
        plan.lists.features = np.concatenate(
            [curves["inv_sv"][...][fresh_rows], curves["inv_block"][...][fresh_rows]], axis=1
        )
    return plan


def blocks_to_search(plan: GraphPlan, threads: int | None = None) -> list[np.ndarray]:
    """For a graph whose rows are searched elsewhere (a Dask cluster's workers, which can
    open the new file only once it is closed): the part computed here, from the open file,
    and what is left. The copied lists are updated where a new row enters them (a search
    of the new rows alone, on ``threads``: here, as in a local build) and the rows to
    search are returned in blocks, in the table's order
    (:func:`~nfdmatch.search.graph.graph_blocks`); each block's lists go in with
    :meth:`GraphPlan.store`. The plan then holds nothing that reads the file."""
    if plan.table is None:
        return []
    lists = plan.lists
    blocks = graph_blocks(plan.table, lists.todo)
    cascade = Cascade(plan.samples)
    stats = plan.stats
    stats.updated = update_copied(plan.table, plan.read_coefficients, plan.ids, lists, plan.k, cascade, threads)
    stats.kept = len(lists.check) - stats.updated
    stats.searched = sum(len(block) for block in blocks)
    plan.table = plan.read_coefficients = None
    return blocks


def store_graph(
    h5: h5py.File, plan: GraphPlan, *, processes: int = 1, close_fds: Sequence[int] = ()
) -> GraphStats:  # fmt: skip
    """Write the lists of ``plan`` (complete) as ``/graph`` of the new index file ``h5``;
    returns its stats, their time taken. A fused graph's lists of exact candidates (searched
    here or elsewhere) are cut to its rows of least fused distance first, on ``processes``
    forked workers closing ``close_fds`` (:func:`~nfdmatch.search.graph.fused_lists`)."""
    if plan.distance == "fused":
        # in the search table's order when there is one: a block's rows then share their
        # candidates (a family sits in a few cells), so each block reads fewer of them
        blocks = None if plan.table is None else graph_blocks(plan.table, np.ones(len(plan.ids), dtype=bool))
        # a graph searched elsewhere comes back to a reopened file: its rows are read from it
        read_coefficients = plan.read_coefficients if plan.read_coefficients is not None else _coefficient_reader(h5)
        plan.lists.neighbour, plan.lists.distance = fused_lists(
            read_coefficients, plan.read_statistics, plan.ids, plan.lists.neighbour, plan.final_k, plan.samples,
            blocks=blocks, processes=processes, close_fds=close_fds,
        )  # fmt: skip
        plan.k = plan.stats.k = plan.final_k
    _write_group(h5, plan.k, plan.lists.neighbour, plan.lists.distance, plan.distance)
    plan.stats.seconds = time.perf_counter() - plan.t0
    return plan.stats


def _coefficient_reader(h5: h5py.File):
    """``rows -> their (m, K, 3) descriptors`` from the new index file ``h5`` (the array held
    whole up to :data:`~nfdmatch.index.graph.IN_MEMORY_ROWS` rows; beyond, each call reads
    its distinct rows)."""
    dataset = h5["curves"]["coefficients"]
    coefficients = dataset[...] if dataset.shape[0] <= IN_MEMORY_ROWS else None

    def read_coefficients(rows):
        rows = np.asarray(rows, dtype=np.int64)
        if coefficients is not None:
            return coefficients[rows]
        uniq, inverse = unique_rows(rows)
        return dataset[uniq][inverse]

    return read_coefficients


def _keep_old_lists(h5, old, k: int, reuse: bool, neighbour, distance):
    """Copy into ``neighbour``/``distance`` the old graph's lists of the rows whose curves
    did not change (when ``reuse`` and the old K is ``k``). Returns ``todo`` (rows to
    search), ``check`` (copied rows whose lists only new rows can change) and ``fresh``
    (rows not copied from the old index)."""
    N = len(neighbour)
    old_to_new = _copied_rows(h5, old) if reuse and old_graph_k(old) == k else {}
    if old_to_new:
        try:
            old_nb, old_d = read_graph(old)  # type: ignore[misc]  # not None: its K is k > 0
        except IndexFormatError:  # a damaged old graph: computed afresh
            old_to_new = {}
    todo = np.ones(N, dtype=bool)
    check = []  # copied rows whose list only new rows can change
    if old_to_new:
        remap = np.full(old.n_curves + 1, -1, dtype=np.int64)  # index -1 (padding) maps to -1
        for o, n in old_to_new.items():
            remap[o] = n
        fresh = np.ones(N, dtype=bool)
        fresh[list(old_to_new.values())] = False
        for o, n in old_to_new.items():
            lst = remap[old_nb[o]]
            # a list with padding or a neighbour that left is no longer the top K among the
            # kept rows: search that row again
            if (old_nb[o] >= 0).all() and (lst >= 0).all():
                neighbour[n], distance[n] = lst, old_d[o]
                todo[n] = False
                check.append(n)
        check = np.asarray(check, dtype=np.int64)
    else:
        fresh = np.ones(N, dtype=bool)
    return todo, check, fresh


def _write_group(h5, k: int, neighbour, distance, kind: str = "exact") -> None:
    """The /graph group: its attributes and checked datasets."""
    g = h5.create_group("graph")
    g.attrs["k"] = np.int64(k)
    if kind != "exact":
        set_text(g.attrs, "distance", kind)
    if kind == "fused":
        from ..matching.fused import FUSED_VERSION

        g.attrs["fused_version"] = np.int64(FUSED_VERSION)
    set_text(g.attrs, "method", "exact")
    set_text(g.attrs, "direction", "invariant")
    g.attrs["mirror"] = np.int64(0)
    set_text(g.attrs, "checksums", GRAPH_CHECKSUMS)
    create_checked(g, "neighbour", neighbour, chunk_rows=GRAPH_CHUNK_ROWS)
    create_checked(g, "distance", distance, chunk_rows=GRAPH_CHUNK_ROWS)
    # the lists turned round: what the walk backwards of query --rerank reads (docs/rerank.md)
    start, source = reverse_of(neighbour, len(neighbour))
    create_checked(g, "reverse_start", start, chunk_rows=GRAPH_CHUNK_ROWS * 8)
    create_checked(g, "reverse_source", source, chunk_rows=GRAPH_CHUNK_ROWS * 8)


def _copied_rows(h5, old) -> dict:
    """old row -> new row for every curve of a file whose contents did not change (same path
    and SHA-256, indexed both times): its descriptors are the same."""
    files = h5["files"]
    paths = files["path"].asstr()[...]
    sha = files["sha256"][...]
    status = files["status"][...]
    start = files["curve_start"][...]
    count = files["curve_count"][...]
    new = {str(p): (bytes(s), int(st), int(a), int(c)) for p, s, st, a, c in zip(paths, sha, status, start, count)}
    out = {}
    for r in old.files():
        got = new.get(r.path)
        if got is None or r.status != "ok" or got[1] != 0 or got[3] != r.curve_count or not r.sha256:
            continue
        if got[0].decode("ascii") != r.sha256:
            continue
        for j in range(r.curve_count):
            out[r.curve_start + j] = got[2] + j
    return out
