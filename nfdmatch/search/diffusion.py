"""Personalised PageRank on the stored neighbour graph by local push (docs/rerank.md).

The walk of :mod:`nfdmatch.search.rerank`: from node u, to each of its k nearest rows v
with weight ``exp(-d_uv^2 / (s_u s_v))`` (``s`` a node's k-th distance), or back to u with
weight 1, each row divided by its total. The personalised PageRank of a source q is
``(1 - alpha) sum_t alpha^t e_q P^t``, the row q of ``(1 - alpha) (I - alpha P)^-1``.

Computed by push (Andersen, Chung & Lang 2006): every source starts with residual 1 on
itself; a push of node u moves ``(1 - alpha) r_u`` into the estimate and spreads
``alpha r_u`` over u's row (the self loop's share, which would come straight back to u,
summed at once: ``(1 - alpha) r_u / (1 - alpha P_uu)`` kept, ``alpha r_u P_uv / (1 - alpha
P_uu)`` to each other v). Only residuals of at least ``tolerance`` are pushed, so only the
nodes that receive that much mass are touched: the cost depends on the tolerance and the
graph's local structure, not on the number of rows. Pushes are made in rounds (every
residual above the tolerance at once, for every source at once: a few numpy operations per
round). What is left is below the tolerance per node: the estimate p of a source's
PageRank pi satisfies ``0 <= pi - p`` and ``sum(pi - p) <= (residual left)``.

The numpy push (:meth:`GraphWalk._push`) is the reference. The process's compiled kernels
(:func:`nfdmatch.matching.kernels.graph_push`: ahead of time, or numba's) push the same
rounds source by source with the same arithmetic in the same order, so they give the same
doubles, ~5x faster (:mod:`nfdmatch.matching._graph_kernels`); the rows of the walk stay
numpy's, computed here as the push reaches them. The compiled push of a block of at least
:data:`_THREAD_SOURCES` sources is split over the threads a kernel call may use
(:meth:`~nfdmatch.matching.kernels.Kernels.workers`), in rounds: each thread's sources pushed
until they are done or need rows of the walk not computed yet, then, every thread stopped,
those rows computed here; the same doubles (no source's push depends on the others').
Test hook: ``graph_push`` (this module's name for it), replaced by tests/test_diffusion.py
to push with numpy under compiled kernels.

:class:`GraphWalk` reads the graph rows it needs, once, through a reader
``rows -> (neighbour, distance)`` (the index's checked reader), and lets a query's rows be
laid over it for one query (:meth:`GraphWalk.overlay`).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import contextmanager
from functools import partial
from typing import TYPE_CHECKING

import numpy as np

from ..matching._threads import run_all
from ..matching.kernels import current, graph_push

if TYPE_CHECKING:
    from numpy.typing import ArrayLike, NDArray

    from ..matching.kernels import Kernels

    #: ``rows -> (neighbour (m, K) int64, distance (m, K) float64)``
    GraphReader = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]
    #: ``rows -> (count (m,) int64, source int64)``: the rows naming each row, concatenated
    ReverseReader = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]

__all__ = ["GraphWalk", "TOLERANCE", "REVERSE_TOLERANCE", "SCALE_FLOOR", "row_scales", "sorted_unique", "sum_by_key"]

#: residual below which a node is not pushed (per source, whose total mass is 1)
TOLERANCE = 1e-5
#: the same for the walk backwards (:meth:`GraphWalk.reverse_pagerank`), which only ranks
#: the rows that reach a source most
REVERSE_TOLERANCE = 1e-4
#: the smallest scale a node gets. The descriptors are stored as complex64 (~1e-7 of their
#: unit norm), so one distance measured by two paths (the stored graph, the query's row, the
#: matrix's float64) differs by up to ~5e-8, and a curve and its exact copy lie 1e-11 to 4e-8
#: apart: a node with more copies than k took its scale, and so every affinity near it, from
#: that noise (the mesh sections: scores 0.6 apart between query --rerank and matrix
#: --rerank). At a scale of at least 1e-4, a change d of a distance moves its affinity
#: exp(-d^2 / s^2) by at most ~0.86 d / s < 5e-4; the development collections' k-th
#: distances are >= 0.06 but for such copies, whose affinities this makes ~1
SCALE_FLOOR = 1e-4
#: sources pushed together (bounds the memory of one push: sources x touched nodes entries)
_SOURCE_BLOCK = 2048
#: sources from which a block's compiled push is split over threads (as the exact distance's
#: rows are: :meth:`~nfdmatch.matching.kernels.Kernels.workers`). At 100,000 curves on 2
#: cores, a fresh walk (its rounds stop for rows of the walk, computed on one thread) takes
#: 1.1x one thread's time on 2 at 8-16 sources, 1.0x at 24-32, 0.9x from 48, 0.74x at
#: 2,048; with its rows known, 0.75x at 8 and 0.55x from 32 (docs/rerank.md)
_THREAD_SOURCES = 32
_NO_NODES, _NO_VALUES = np.zeros(0, np.int64), np.zeros(0)


def row_scales(distances: np.ndarray, k: int) -> np.ndarray:
    """Each row's scale: the k-th finite entry of its ascending distances (the last finite
    one when fewer; 1 when none), at least :data:`SCALE_FLOOR`."""
    distances = np.asarray(distances, dtype=np.float64)
    finite = np.isfinite(distances)
    count = finite.sum(axis=1)
    if not distances.shape[1]:
        return np.ones(len(distances))
    col = np.clip(np.minimum(count, k) - 1, 0, None)
    s = distances[np.arange(len(distances)), col]
    s = np.where(count > 0, s, 1.0)
    return np.maximum(s, SCALE_FLOOR)


def _rounds(r_key: np.ndarray, r_val: np.ndarray, tolerance: float, step) -> tuple[np.ndarray, np.ndarray]:
    """The rounds of a push, either way: every residual (``r_val`` at keys ``r_key``, src * (N
    + 1) + node, unique) of at least ``tolerance`` pushed at once by ``step(key, value) ->
    (kept, spread_key, spread_value)``, what it spreads added to what was left, until none is.
    Returns the kept mass summed by key, keys ascending (empty arrays when nothing was)."""
    kept_keys, kept_vals = [], []
    while True:
        active = r_val >= tolerance
        if not active.any():
            break
        a_key, a_val = r_key[active], r_val[active]
        kept, spread_key, spread_val = step(a_key, a_val)
        kept_keys.append(a_key)
        kept_vals.append(kept)
        r_key, r_val = sum_by_key(
            np.concatenate([r_key[~active], spread_key]), np.concatenate([r_val[~active], spread_val])
        )
    if not kept_keys:
        return _NO_NODES, _NO_VALUES
    return sum_by_key(np.concatenate(kept_keys), np.concatenate(kept_vals))


class GraphWalk:
    """The random walk over ``N`` stored rows plus one extra node ``N`` (a query laid over
    the graph with :meth:`overlay`); rows are read through ``reader`` on first use.

    Parameters
    ----------
    reader : ``rows -> (neighbour (m, K) int64, distance (m, K) float64)``, ascending lists,
        -1 / inf padding (the index's checked :func:`~nfdmatch.index.graph.read_graph_rows`).
    N : rows in the graph.
    k : neighbours per node in the walk (the first k of each stored list).
    alpha : probability of following an edge.
    reverse : the stored lists turned round (the index's
        :meth:`~nfdmatch.index.Index.graph_reverse_reader`), for :meth:`reverse_pagerank`;
        None: turned round here from every row's list (:meth:`reverse_lists`).
    """

    def __init__(self, reader: GraphReader, N: int, k: int, alpha: float, reverse: ReverseReader | None = None) -> None:
        self.reader, self.N, self.k, self.alpha = reader, int(N), int(k), float(alpha)
        self.reverse = reverse
        size = self.N + 1
        # full-size arrays, written only where rows are read (untouched pages cost nothing)
        self._nb = np.empty((size, k), dtype=np.int64)
        self._d = np.empty((size, k), dtype=np.float64)
        self._scale = np.empty(size, dtype=np.float64)
        self._known = np.zeros(size, dtype=bool)
        # each node's row of the walk, once computed (not while a query is laid over the graph)
        self._targets = np.empty((size, k + 1), dtype=np.int64)
        self._prob = np.empty((size, k + 1), dtype=np.float64)
        self._walk_known = np.zeros(size, dtype=bool)
        self._overlaid = False
        self._slots = []  # the compiled push's work arrays, one per thread: (N + 1,) int64
        self._reverse: tuple[np.ndarray, np.ndarray] | None = None
        # the in-edges read from the index so far (:meth:`_read_in_edges`)
        self._in_first: np.ndarray | None = None
        self._in_count = _NO_NODES
        self._in_source = _NO_NODES
        self.rows_read = 0

    # -- rows
    def ensure(self, nodes: np.ndarray) -> None:
        """Read the rows of ``nodes`` not read yet (their lists and scales)."""
        nodes = np.asarray(nodes, dtype=np.int64)
        missing = nodes[~self._known[nodes]]
        if not len(missing):
            return
        missing = sorted_unique(missing)
        nb, d = self.reader(missing)
        k = self.k
        nb, d = nb[:, :k], d[:, :k]
        if nb.shape[1] < k:  # a graph of fewer neighbours (pads)
            pad = k - nb.shape[1]
            nb = np.pad(nb, ((0, 0), (0, pad)), constant_values=-1)
            d = np.pad(d, ((0, 0), (0, pad)), constant_values=np.inf)
        self._nb[missing], self._d[missing] = nb, d
        self._scale[missing] = row_scales(d, k)
        self._known[missing] = True
        self.rows_read += len(missing)

    def scales(self, nodes: ArrayLike) -> NDArray[np.float64]:
        """Each node's scale (its k-th distance)."""
        nodes = np.asarray(nodes, dtype=np.int64)
        self.ensure(nodes)
        return self._scale[nodes].copy()

    def transitions(self, nodes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(targets, probabilities)``, (m, k + 1) each: node u's row of the walk, the self
        loop first; a padded target is u itself with probability 0."""
        nodes = np.asarray(nodes, dtype=np.int64)
        if self._overlaid:
            return self._transitions(nodes)
        self._walk_rows(nodes)
        return self._targets[nodes], self._prob[nodes]

    def _walk_rows(self, nodes: np.ndarray) -> None:
        """Compute and keep the rows of the walk of ``nodes`` not computed yet (a node's row
        is the same doubles whichever nodes are computed with it: element-wise operations
        and per-row sums)."""
        new = nodes[~self._walk_known[nodes]]
        if len(new):
            new = sorted_unique(new)
            self._targets[new], self._prob[new] = self._transitions(new)
            self._walk_known[new] = True

    def _transitions(self, nodes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        self.ensure(nodes)
        nb, d = self._nb[nodes], self._d[nodes]
        real = nb >= 0
        self.ensure(nb[real])
        s_u = self._scale[nodes]
        s_v = np.where(real, self._scale[np.where(real, nb, 0)], 1.0)
        with np.errstate(over="ignore", invalid="ignore"):
            w = np.where(real, np.exp(-(np.where(real, d, 0.0) ** 2) / (s_u[:, None] * s_v)), 0.0)
        w = np.concatenate([np.ones((len(nodes), 1)), w], axis=1)
        w /= w.sum(axis=1, keepdims=True)
        targets = np.concatenate([nodes[:, None], np.where(real, nb, nodes[:, None])], axis=1)
        return targets, w

    @contextmanager
    def overlay(self, rows: np.ndarray, neighbour: np.ndarray, distance: np.ndarray) -> Iterator[GraphWalk]:
        """For the duration of the block, the lists of ``rows`` (which may include the extra
        node N, the query) are ``neighbour`` / ``distance`` ((m, k), ascending, -1 / inf
        padding; neighbour N is the query), and their scales follow; restored afterwards."""
        rows = np.asarray(rows, dtype=np.int64)
        stored = rows[rows < self.N]
        self.ensure(stored)
        saved = (self._nb[rows].copy(), self._d[rows].copy(), self._scale[rows].copy(), self._known[rows].copy())
        try:
            self._overlaid = True
            self._nb[rows], self._d[rows] = neighbour, distance
            self._scale[rows] = row_scales(distance, self.k)
            self._known[rows] = True
            yield self
        finally:
            self._nb[rows], self._d[rows], self._scale[rows], self._known[rows] = saved
            self._overlaid = False

    # -- the walk backwards
    def reverse_lists(self) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
        """``(start, source)``: the rows whose lists hold row v (its in-edges) are
        ``source[start[v]:start[v + 1]]``, ascending; from every stored row's list, read once
        (all N rows: O(N k) memory and time, once per walk)."""
        if self._reverse is None:
            if self._overlaid:
                raise RuntimeError("the reverse lists are of the stored graph: not while a query is laid over it")
            every = np.arange(self.N, dtype=np.int64)
            self.ensure(every)
            target = self._nb[: self.N].reshape(-1)
            source = np.repeat(every, self.k)
            real = target >= 0
            source, target = source[real], target[real]
            order = np.argsort(target, kind="stable")
            start = np.concatenate([[0], np.cumsum(np.bincount(target, minlength=self.N))]).astype(np.int64)
            self._reverse = (start, source[order])
        return self._reverse

    def in_edges(self, rows: np.ndarray) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
        """``(count, source)``: the stored rows whose lists name each of ``rows`` (count (m,)),
        concatenated in that order; read from the index when it stores them (each row's
        once per walk: :meth:`_read_in_edges`), else from :meth:`reverse_lists`."""
        if self.reverse is None:
            start, source = self.reverse_lists()
            first, counts = start[rows], start[rows + 1] - start[rows]
        else:
            self._read_in_edges(rows)
            first, counts, source = self._in_first[rows], self._in_count[rows], self._in_source
        at = np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts) + np.repeat(first, counts)
        return counts, source[at]

    def _read_in_edges(self, rows: np.ndarray) -> None:
        """Read from the index the in-edges of the ``rows`` not read yet, kept: a walk
        backwards pushes a row in many of its rounds (on 200 queries of 1,400 curves, 262,000
        rows asked for in 37 rounds were 1,400 rows; reading each round's cost a third of the
        walk). Row v's sources are ``_in_source[_in_first[v]:][:_in_count[v]]``."""
        if self._in_first is None:
            self._in_first = np.full(self.N + 1, -1, dtype=np.int64)
            self._in_count = np.zeros(self.N + 1, dtype=np.int64)
        missing = rows[self._in_first[rows] < 0]
        if not len(missing):
            return
        missing = sorted_unique(missing)
        counts, source = self.reverse(missing)  # type: ignore[misc]
        self._in_first[missing] = len(self._in_source) + np.cumsum(counts) - counts
        self._in_count[missing] = counts
        self._in_source = np.concatenate([self._in_source, source])

    def reverse_pagerank(
        self, owner: np.ndarray, node: np.ndarray, residual: np.ndarray, tolerance: float = REVERSE_TOLERANCE
    ) -> tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.float64]]:
        """How much each row's walk reaches each source: an estimate of the source's column of
        the PageRank matrix, ``c_u ~ pi_u(source)``, by reverse push (Andersen, Borgs, Chayes,
        Hopcroft, Mirrokni & Teng 2007) over the stored graph's in-edges
        (:meth:`reverse_lists`). A push of v keeps ``(1 - alpha) r_v`` and gives each row u
        that lists v ``alpha P_uv r_v`` (the self loop summed at once, as in :meth:`_push`);
        only residuals of at least ``tolerance`` are pushed, and every estimate is below its
        value by less than ``tolerance``.

        owner, node, residual : (m,) the starting residuals: source ``owner[i]`` (0, 1, ...)
            puts ``residual[i]`` on ``node[i]`` (a stored row: 1 on itself; a query laid over
            the graph: ``alpha P_uq`` on each row u whose list it enters).

        Returns ``(owner, node, mass)``, sorted by (owner, node): the rows reached."""
        size, alpha = self.N + 1, self.alpha

        def step(key, value):
            src, v = np.divmod(key, size)
            targets, prob = self.transitions(v)
            stay = value / (1.0 - alpha * prob[:, 0])
            counts, u = self.in_edges(v)
            edge = np.repeat(np.arange(len(v)), counts)
            u_targets, u_prob = self.transitions(u)
            p_uv = (u_prob[:, 1:] * (u_targets[:, 1:] == v[edge][:, None])).sum(axis=1)
            return (1 - alpha) * stay, src[edge] * size + u, alpha * stay[edge] * p_uv

        start = sum_by_key(np.asarray(owner, np.int64) * size + node, np.asarray(residual, np.float64))
        key, val = _rounds(*start, tolerance, step)
        src, node = np.divmod(key, size)
        return src, node, val

    # -- the push
    def pagerank(
        self, sources: ArrayLike, tolerance: float = TOLERANCE, kernels: Kernels | None = None
    ) -> tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.float64]]:
        """The personalised PageRank of each source, by push.

        ``kernels``: which push computes (a :class:`~nfdmatch.matching.kernels.Kernels`;
        default the process's, :func:`~nfdmatch.matching.kernels.current`): the compiled
        push of the numba or ahead-of-time kernels, else (numpy kernels, or numba cannot
        compile it) the numpy push; both give the same doubles.

        Returns ``(start, node, value)``: source i's estimate is ``value[start[i]:start[i+1]]``
        over nodes ``node[start[i]:start[i+1]]`` (ascending, only the nodes it reached)."""
        sources = np.asarray(sources, dtype=np.int64).reshape(-1)
        kernels = kernels or current()
        # (while a query is laid over the graph the rows of the walk are not kept: numpy)
        compiled = None if self._overlaid or not len(sources) else graph_push(kernels)
        starts, nodes, values = [0], [], []
        for a in range(0, len(sources), _SOURCE_BLOCK):
            block = sources[a : a + _SOURCE_BLOCK]
            if compiled is None:
                src, node, value = self._push(block, tolerance)
            else:
                workers = kernels.workers(len(block), least=_THREAD_SOURCES)
                src, node, value = self._push_compiled(compiled, block, tolerance, workers)
            nodes.append(node)
            values.append(value)
            starts.extend((starts[-1] + np.cumsum(np.bincount(src, minlength=len(block)))).tolist())
        if not nodes:
            return np.zeros(1, np.int64), np.zeros(0, np.int64), np.zeros(0)
        return np.asarray(starts, dtype=np.int64), np.concatenate(nodes), np.concatenate(values)

    def _push_compiled(self, push, sources: np.ndarray, tolerance: float, workers: int = 1):
        """:meth:`_push` by the compiled push ``push``
        (:func:`nfdmatch.matching._graph_kernels.push_sources`): the same (src, node, value).
        It pushes every source until it is done or needs a row of the walk not computed yet;
        those rows are computed here, for every stopped source at once, and it goes on.

        Over ``workers`` threads: the sources in as many parts (contiguous, in order), each
        pushed by its own calls with its own work array. Every round runs each unfinished
        part's call to its stop; only once all have returned (no kernel reads the rows of the
        walk then) are the rows they need computed, and those stopped go on. A source's
        estimate does not depend on the sources pushed with it, so the parts' estimates in
        order are the same doubles as one call's."""
        sources, tolerance = np.ascontiguousarray(sources, dtype=np.int64), float(tolerance)
        n = len(sources)
        bounds = [n * t // workers for t in range(workers + 1)]
        parts = [_SourcesPush(sources[lo:hi]) for lo, hi in zip(bounds, bounds[1:]) if hi > lo]
        if not parts:
            return _NO_NODES, _NO_NODES, _NO_VALUES
        while len(self._slots) < len(parts):  # -1 everywhere between calls
            self._slots.append(np.full(self.N + 1, -1, dtype=np.int64))
        walk = (self._targets, self._prob, self._walk_known)
        going = parts
        while going:
            calls = [
                partial(part.push, push, *walk, slot, self.alpha, tolerance) for part, slot in zip(going, self._slots)
            ]
            run_all(calls)
            going = [part for part in going if len(part.missing)]
            if going:
                self._walk_rows(np.concatenate([part.missing for part in going]))
        counts, node, value = zip(*(part.estimates() for part in parts))
        src = np.repeat(np.arange(n, dtype=np.int64), np.concatenate(counts))
        return src, np.concatenate(node), np.concatenate(value)

    def _push(self, sources: np.ndarray, tolerance: float):
        """(src, node, value) sorted by (src, node): the estimates of a block of sources (the
        numpy push: the reference, the same doubles as the compiled one)."""
        size = self.N + 1
        alpha = self.alpha

        def step(key, value):
            src, node = np.divmod(key, size)
            targets, prob = self.transitions(node)
            # the self loop's returns summed at once: r_u (1 - alpha) / (1 - alpha P_uu) kept,
            # r_u alpha P_uv / (1 - alpha P_uu) to each other v
            stay = 1.0 / (1.0 - alpha * prob[:, 0])
            spread_key = (src[:, None] * size + targets[:, 1:]).reshape(-1)
            spread_val = (alpha * (value * stay)[:, None] * prob[:, 1:]).reshape(-1)
            return ((1 - alpha) * value) * stay, spread_key, spread_val

        # residuals and estimates as keys src * size + node, one entry per key
        start = np.arange(len(sources), dtype=np.int64) * size + sources
        key, val = _rounds(start, np.ones(len(sources)), tolerance, step)
        src, node = np.divmod(key, size)
        return src, node, val


class _SourcesPush:
    """Some sources of a block, pushed by the compiled push, and their state between its calls
    (:func:`nfdmatch.matching._graph_kernels.push_sources`'s state in and out)."""

    def __init__(self, sources: np.ndarray):
        n = len(sources)
        self.sources = sources  # (n,) int64, contiguous
        self.state = (np.zeros(n, np.int64), np.zeros(n + 1, np.int64), _NO_NODES, _NO_VALUES)
        self.state += (np.zeros(n + 1, np.int64), _NO_NODES, _NO_VALUES)
        self.missing = _NO_NODES  # the rows of the walk its last call stopped for

    def push(self, push, targets, prob, known, slot, alpha: float, tolerance: float) -> None:
        """One call of ``push``: every source not done pushed until it is done or needs a row
        of the walk not ``known`` (those rows then in ``missing``, ascending, unique)."""
        *state, self.missing = push(self.sources, *self.state, targets, prob, known, slot, alpha, tolerance)
        self.state = tuple(state)

    def estimates(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(count, node, value)`` once every source is done: entries per source ((n,)
        int64), then each source's estimate in order (nodes ascending, int64; float64)."""
        start, node, value = self.state[4:]  # type: ignore[misc]
        return np.diff(start), node[: start[-1]], value[: start[-1]]


def sorted_unique(values: np.ndarray) -> np.ndarray:
    """Sorted unique values (np.unique imports numpy.ma: ~50 ms the first time)."""
    values = np.sort(values)
    keep = np.ones(len(values), dtype=bool)
    keep[1:] = values[1:] != values[:-1]
    return values[keep]


def sum_by_key(keys: np.ndarray, values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unique ascending keys and the sum of the values of each."""
    order = np.argsort(keys, kind="stable")
    keys, values = keys[order], values[order]
    first = np.ones(len(keys), dtype=bool)
    first[1:] = keys[1:] != keys[:-1]
    starts = np.flatnonzero(first)
    return keys[starts], np.add.reduceat(values, starts) if len(values) else values
