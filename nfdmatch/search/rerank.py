"""Re-ranking by diffusion over the neighbour graph of a collection (docs/rerank.md).

A single distance ranks each stored curve against the query alone; diffusion also asks
whether a curve is near the query's neighbours. The method (chosen by measurement,
``benchmarks/bench_rerank.py``):

1. affinities on the k-nearest-neighbour graph, k = :data:`SCALE_NEIGHBOURS`:
   ``w_ij = exp(-d_ij^2 / (s_i s_j))`` with ``s_i`` the distance of i's k-th neighbour
   (a self-tuning scale: no parameter in distance units), a self-loop of weight 1, each
   row divided by its total weight;
2. personalised PageRank of every node, ``A = (1 - alpha) (I - alpha P)^-1``,
   alpha = :data:`ALPHA`;
3. the score of j for query q: the cosine of their PageRank rows, plus :data:`MIX` times
   the direct affinity ``w_qj`` (which keeps a near-duplicate first when the collection
   has no class structure).

:func:`diffused_similarity` does this on a full distance matrix (``matrix --rerank``);
:func:`rerank_index` on a query's exact top M joined to an index's stored graph
(``query --rerank``).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING

import numpy as np

from ..defaults import DEFAULT_RERANK_DEPTH
from ..errors import IndexFormatError, ParameterError

if TYPE_CHECKING:
    from numpy.typing import ArrayLike

    from ..curve import Curve
    from ..records import RankedMatch
    from .index_search import SearchStats

__all__ = [
    "diffused_similarity",
    "rerank_scores",
    "rerank_index",
    "SCALE_NEIGHBOURS",
    "ALPHA",
    "MIX",
    "MIN_DEPTH",
    "DEFAULT_DEPTH",
]

#: neighbours per node in the affinity graph; the k-th one's distance is the node's scale
SCALE_NEIGHBOURS = 8
#: personalised PageRank: probability of following an edge rather than returning to the start
ALPHA = 0.8
#: weight of the direct affinity added to the diffused cosine
MIX = 0.2
#: a query's exact candidates (--rerank-depth): at least, and by default (defined with the CLI's defaults)
MIN_DEPTH = DEFAULT_DEPTH = DEFAULT_RERANK_DEPTH
#: scores closer than this are ties, ordered by exact distance then id
_SCORE_TIE = 1e-12


def _scales(sorted_distances: np.ndarray, k: int) -> np.ndarray:
    """Each row's scale: the k-th finite entry of its ascending distances (the last finite
    one when fewer), floored so that a duplicate (distance 0) cannot divide by zero."""
    finite = np.isfinite(sorted_distances)
    count = finite.sum(axis=1)
    col = np.clip(np.minimum(count, k) - 1, 0, None)
    s = sorted_distances[np.arange(len(sorted_distances)), col] if sorted_distances.shape[1] else np.zeros(0)
    s = np.where(count > 0, s, 1.0)
    return np.maximum(s, 1e-12)


def _pagerank_cosine(P: np.ndarray, alpha: float) -> np.ndarray:
    """(n, n) cosines between the rows of ``(1 - alpha) (I - alpha P)^-1``."""
    n = len(P)
    A = (1 - alpha) * np.linalg.solve(np.eye(n) - alpha * P, np.eye(n))
    norm = np.linalg.norm(A, axis=1)
    norm[norm == 0] = 1.0
    A /= norm[:, None]
    return A @ A.T


def diffused_similarity(
    distances: ArrayLike, *, k: int = SCALE_NEIGHBOURS, alpha: float = ALPHA, mix: float = MIX
) -> np.ndarray:
    """The re-ranked similarity of every pair of a collection.

    Parameters
    ----------
    distances : (N, N) float, symmetric exact distances with a zero diagonal.

    Returns
    -------
    (N, N) float64, symmetric, higher is closer: 1 on the diagonal, at most 1 elsewhere
    (a cosine and an affinity, both at most 1, mixed). O(N^3) time (one dense N x N solve), O(N^2) memory.
    """
    D = np.array(distances, dtype=np.float64)
    N = len(D)
    if D.ndim != 2 or D.shape != (N, N):
        raise ParameterError(f"expected a square distance matrix, got shape {D.shape}")
    if N == 0:
        return np.zeros((0, 0))
    off = D.copy()
    np.fill_diagonal(off, np.inf)
    order = np.argsort(off, axis=1, kind="stable")[:, : min(k, N - 1)]
    s = _scales(np.take_along_axis(off, order, axis=1), k)
    W = np.exp(-(D**2) / (s[:, None] * s[None, :]))
    mask = np.zeros((N, N), dtype=bool)
    mask[np.arange(N)[:, None], order] = True
    np.fill_diagonal(mask, True)
    P = np.where(mask, W, 0.0)
    P /= P.sum(axis=1, keepdims=True)
    S = (1 - mix) * _pagerank_cosine(P, alpha) + mix * W
    return (S + S.T) / 2  # symmetric to rounding: the cosine and W are, up to round-off


def rerank_scores(
    query_distances,
    candidates,
    graph_rows,
    graph_distances,
    *,
    merged=None,
    outside_scale=None,
    k: int = SCALE_NEIGHBOURS,
    alpha: float = ALPHA,
    mix: float = MIX,
) -> np.ndarray:
    """Diffused scores of a query's candidates, from its exact distances and the stored graph.

    Parameters
    ----------
    query_distances : (M,) float, exact distances from the query to the candidates (its
        exact top M, so its own k nearest are among them).
    candidates : (M,) int64, the candidates' rows in the collection.
    graph_rows, graph_distances : (M, G) int64 / float, each candidate's G >= k nearest
        other rows and their distances, ascending (-1 / inf pad).
    merged : (M,) bool or None: candidates that are the query itself (a stored copy: its
        edges become the query's; its score is not used).
    outside_scale : callable ``rows -> (len(rows),) float`` giving the scale of rows outside
        the candidates that the candidates link to (their k-th stored distance); None
        treats such edges as having the linking node's own scale.

    Returns
    -------
    (M,) float64 scores, higher is closer (NaN for merged candidates).

    The local graph holds the query and the candidates; a candidate's edges are its stored
    neighbours that are candidates (an edge leaving the set still counts in the row's total
    weight, so its walk mass leaks instead of being redistributed) plus the query when the
    query is among its k nearest. One (M+1) x (M+1) solve.
    """
    qd = np.asarray(query_distances, dtype=np.float64)
    cand = np.asarray(candidates, dtype=np.int64)
    gr = np.asarray(graph_rows, dtype=np.int64)
    gd = np.asarray(graph_distances, dtype=np.float64)
    M = len(cand)
    merged = np.zeros(M, dtype=bool) if merged is None else np.asarray(merged, dtype=bool)
    if M == 0:
        return np.zeros(0)
    # local nodes: 0 the query (and its stored copies), then the other candidates
    keep = np.flatnonzero(~merged)
    node_of = {int(r): 0 for r in cand[merged]}
    node_of.update({int(cand[c]): i + 1 for i, c in enumerate(keep)})
    n = len(keep) + 1
    # each node's k nearest: (node or -1 outside, row, distance)
    lists = []
    qorder = keep[np.argsort(qd[keep], kind="stable")][:k]
    lists.append([(node_of[int(cand[c])], int(cand[c]), float(qd[c])) for c in qorder])
    for c in keep:
        entries = [(node_of.get(int(r), -1), int(r), float(d)) for r, d in zip(gr[c], gd[c]) if r >= 0]
        if not merged.any():
            entries.append((0, -1, float(qd[c])))
        entries.sort(key=lambda e: e[2])  # stable: the stored order breaks ties
        lists.append(entries[:k])
    s = np.array([max(lst[-1][2], 1e-12) if lst else 1.0 for lst in lists])
    outside = sorted({row for lst in lists for node, row, _ in lst if node < 0})
    s_out = {}
    if outside and outside_scale is not None:
        s_out = dict(zip(outside, np.maximum(np.asarray(outside_scale(np.array(outside)), dtype=np.float64), 1e-12)))
    P = np.zeros((n, n))
    total = np.ones(n)  # the self-loop, weight 1
    for i, lst in enumerate(lists):
        P[i, i] = 1.0
        for node, row, d in lst:
            sj = s[node] if node >= 0 else s_out.get(row, s[i])
            w = np.exp(-d * d / (s[i] * sj))
            total[i] += w
            if node >= 0:
                P[i, node] += w
    P /= total[:, None]
    cos = _pagerank_cosine(P, alpha)[0, 1:]
    direct = np.exp(-(qd[keep] ** 2) / (s[0] * s[1:]))
    out = np.full(M, np.nan)
    out[keep] = (1 - mix) * cos + mix * direct
    return out


def rerank_index(
    index,
    queries: Sequence[Curve],
    *,
    top: int = 10,
    depth: int = DEFAULT_DEPTH,
    exclude_self: bool = False,
    progress: Callable[[int, int], None] | None = None,
    threads: int | None = None,
) -> tuple[list[list[RankedMatch]], SearchStats]:
    """k best curves of an index for each query by diffused score.

    Parameters
    ----------
    index : an open :class:`nfdmatch.index.Index` with a graph (``index build --graph``).
    queries : sequence of :class:`~nfdmatch.curve.Curve`.
    top : matches per query (at most ``depth``).
    depth : M, the query's exact candidates (the pruned exact search's top M), >= 100.
    exclude_self : the query's own curve (:func:`~nfdmatch.search.knn.is_self`) is merged
        with the query in the graph and left out of the results.
    progress, threads : as in :func:`~nfdmatch.search.search_index`.

    Returns
    -------
    ``(results, stats)``: ``results[i]`` lists query i's matches as
    :class:`~nfdmatch.records.RankedMatch` es with their ``score``, sorted by ``score`` (higher
    is closer; ties by exact distance, then id); ``distance`` is the exact distance. ``stats`` is the
    exact search's :class:`~nfdmatch.search.SearchStats` with ``seconds`` covering both steps.

    Raises
    ------
    IndexFormatError : the index has no graph, or one of fewer than 8 neighbours per row.
    ParameterError : depth below 100, top above depth.

    Deterministic: the same index and queries give the same rows and scores.
    """
    from .index_search import search_index
    from .knn import is_self

    if isinstance(depth, bool) or not isinstance(depth, (int, np.integer)) or depth < MIN_DEPTH:
        raise ParameterError(f"rerank depth must be an integer of at least {MIN_DEPTH}, got {depth!r}")
    if top < 1 or top > depth:
        raise ParameterError(f"top must be between 1 and the rerank depth ({depth}), got {top}")
    t0 = time.perf_counter()
    reader = index.graph_reader()
    if reader is None:
        raise IndexFormatError(
            "the index has no neighbour graph, which --rerank needs: build it with "
            f"`nfdmatch index build ... --index {index.path} --graph`",
            path=index.path,
        )
    stored_k = index.graph_k()
    if stored_k < SCALE_NEIGHBOURS:
        raise IndexFormatError(
            f"the index's graph holds {stored_k} neighbours per curve; --rerank needs at least "
            f"{SCALE_NEIGHBOURS}: rebuild it with `nfdmatch index build ... --index {index.path} "
            f"--graph {SCALE_NEIGHBOURS}` or more",
            path=index.path,
        )
    exact, stats = search_index(index, queries, top=depth, progress=progress, threads=threads)
    locate = getattr(index, "locate", None)
    results = []
    for q, found in zip(queries, exact):
        if not found:
            results.append([])
            continue
        rows = np.array([m.row for m in found], dtype=np.int64)
        qd = np.array([m.distance for m in found])
        merged = np.array([exclude_self and is_self(q.id, m.id, locate) for m in found], dtype=bool)
        gr, gd = reader(rows)
        scores = rerank_scores(
            qd, rows, gr, gd, merged=merged, outside_scale=lambda r: _kth(reader(r)[1], SCALE_NEIGHBOURS)
        )
        idx = [i for i in range(len(found)) if not merged[i]]
        idx.sort(key=lambda i: (-round(float(scores[i]) / _SCORE_TIE), found[i].rank))
        results.append(
            [found[i].replace(rank=rank, score=float(scores[i])) for rank, i in enumerate(idx[:top], start=1)]
        )
    stats.seconds = time.perf_counter() - t0
    return results, stats


def _kth(distances: np.ndarray, k: int) -> np.ndarray:
    return _scales(distances, k)
