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
numpy's, computed here as the push reaches them. Test hook: ``graph_push`` (this module's
name for it), replaced by tests/test_diffusion.py to push with numpy under compiled kernels.

:class:`GraphWalk` reads the graph rows it needs, once, through a reader
``rows -> (neighbour, distance)`` (the index's checked reader), and lets a query's rows be
laid over it for one query (:meth:`GraphWalk.overlay`).
"""

from __future__ import annotations

from contextlib import contextmanager

import numpy as np

from ..matching.kernels import graph_push

__all__ = ["GraphWalk", "TOLERANCE", "row_scales", "sorted_unique", "sum_by_key"]

#: residual below which a node is not pushed (per source, whose total mass is 1)
TOLERANCE = 1e-5
#: sources pushed together (bounds the memory of one push: sources x touched nodes entries)
_SOURCE_BLOCK = 2048
_NO_NODES, _NO_VALUES = np.zeros(0, np.int64), np.zeros(0)


def row_scales(distances: np.ndarray, k: int) -> np.ndarray:
    """Each row's scale: the k-th finite entry of its ascending distances (the last finite
    one when fewer; 1 when none), floored at 1e-12 (a duplicate cannot divide by zero)."""
    distances = np.asarray(distances, dtype=np.float64)
    finite = np.isfinite(distances)
    count = finite.sum(axis=1)
    if not distances.shape[1]:
        return np.ones(len(distances))
    col = np.clip(np.minimum(count, k) - 1, 0, None)
    s = distances[np.arange(len(distances)), col]
    s = np.where(count > 0, s, 1.0)
    return np.maximum(s, 1e-12)


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
    """

    def __init__(self, reader, N: int, k: int, alpha: float):
        self.reader, self.N, self.k, self.alpha = reader, int(N), int(k), float(alpha)
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
        self._slot = None
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

    def scales(self, nodes) -> np.ndarray:
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
    def overlay(self, rows: np.ndarray, neighbour: np.ndarray, distance: np.ndarray):
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

    # -- the push
    def pagerank(self, sources, tolerance: float = TOLERANCE, kernels=None):
        """The personalised PageRank of each source, by push.

        ``kernels``: which push computes (a :class:`~nfdmatch.matching.kernels.Kernels`;
        default the process's, :func:`~nfdmatch.matching.kernels.current`): the compiled
        push of the numba or ahead-of-time kernels, else (numpy kernels, or numba cannot
        compile it) the numpy push; both give the same doubles.

        Returns ``(start, node, value)``: source i's estimate is ``value[start[i]:start[i+1]]``
        over nodes ``node[start[i]:start[i+1]]`` (ascending, only the nodes it reached)."""
        sources = np.asarray(sources, dtype=np.int64).reshape(-1)
        # (while a query is laid over the graph the rows of the walk are not kept: numpy)
        compiled = None if self._overlaid or not len(sources) else graph_push(kernels)
        starts, nodes, values = [0], [], []
        for a in range(0, len(sources), _SOURCE_BLOCK):
            block = sources[a : a + _SOURCE_BLOCK]
            if compiled is None:
                src, node, value = self._push(block, tolerance)
            else:
                src, node, value = self._push_compiled(compiled, block, tolerance)
            nodes.append(node)
            values.append(value)
            starts.extend((starts[-1] + np.cumsum(np.bincount(src, minlength=len(block)))).tolist())
        if not nodes:
            return np.zeros(1, np.int64), np.zeros(0, np.int64), np.zeros(0)
        return np.asarray(starts, dtype=np.int64), np.concatenate(nodes), np.concatenate(values)

    def _push_compiled(self, push, sources: np.ndarray, tolerance: float):
        """:meth:`_push` by the compiled push ``push``
        (:func:`nfdmatch.matching._graph_kernels.push_sources`): the same (src, node, value).
        It pushes every source until it is done or needs a row of the walk not computed yet;
        those rows are computed here, for every stopped source at once, and it goes on."""
        sources = np.ascontiguousarray(sources, dtype=np.int64)
        n = len(sources)
        if self._slot is None:  # its work array, -1 everywhere between calls
            self._slot = np.full(self.N + 1, -1, dtype=np.int64)
        state = (np.zeros(n, np.int64), np.zeros(n + 1, np.int64), _NO_NODES, _NO_VALUES)
        state += (np.zeros(n + 1, np.int64), _NO_NODES, _NO_VALUES)
        while True:
            *state, missing = push(
                sources, *state, self._targets, self._prob, self._walk_known, self._slot, self.alpha, float(tolerance)
            )
            if not len(missing):
                break
            self._walk_rows(missing)
        _, _, _, _, start, node, value = state
        return np.repeat(np.arange(n, dtype=np.int64), np.diff(start)), node[: start[-1]], value[: start[-1]]

    def _push(self, sources: np.ndarray, tolerance: float):
        """(src, node, value) sorted by (src, node): the estimates of a block of sources (the
        numpy push: the reference, the same doubles as the compiled one)."""
        size = self.N + 1
        alpha = self.alpha
        # residuals and estimates as keys src * size + node, one entry per key
        r_key = np.arange(len(sources), dtype=np.int64) * size + sources
        r_val = np.ones(len(sources))
        p_keys, p_vals = [], []
        while True:
            active = r_val >= tolerance
            if not active.any():
                break
            a_key, a_val = r_key[active], r_val[active]
            p_keys.append(a_key)
            p_vals.append((1 - alpha) * a_val)
            src, node = np.divmod(a_key, size)
            targets, prob = self.transitions(node)
            # the self loop's returns summed at once: r_u (1 - alpha) / (1 - alpha P_uu) kept,
            # r_u alpha P_uv / (1 - alpha P_uu) to each other v
            stay = 1.0 / (1.0 - alpha * prob[:, 0])
            p_vals[-1] *= stay
            spread_key = (src[:, None] * size + targets[:, 1:]).reshape(-1)
            spread_val = (alpha * (a_val * stay)[:, None] * prob[:, 1:]).reshape(-1)
            r_key, r_val = sum_by_key(
                np.concatenate([r_key[~active], spread_key]), np.concatenate([r_val[~active], spread_val])
            )
        if not p_keys:
            return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0)
        key, val = sum_by_key(np.concatenate(p_keys), np.concatenate(p_vals))
        src, node = np.divmod(key, size)
        return src, node, val


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
