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
   has no class structure);
4. a score below :data:`SCORE_FLOOR` is 0: the diffusion says nothing there (walks that
   barely meet), and those curves follow in the exact distance's order (then id).

:func:`diffused_similarity` does this on a full distance matrix (``matrix --rerank``);
:func:`rerank_index` orders a query's exact top M by the same scores computed on the
index's whole stored graph, the PageRank rows by local push (:mod:`.diffusion`), the query
joining the graph through its exact k nearest (``query --rerank``).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

from ..defaults import (
    DEFAULT_GRAPH_K,
    DEFAULT_RERANK_CANDIDATES,
    DEFAULT_RERANK_DEPTH,
    FUSED_CANDIDATES,
    MIN_RERANK_DEPTH,
    RERANK_CANDIDATES,
)
from ..errors import IndexFormatError, ParameterError
from ..records import RankedMatch
from .diffusion import GraphWalk, row_scales, sorted_unique
from .engine import TIE
from .index_search import UNSET, k_or_top
from .rerank_candidates import PageRankVectors, gather_candidates, query_joined, self_flags
from .selfmatch import self_rule

if TYPE_CHECKING:
    from numpy.typing import ArrayLike

    from .index_search import SearchStats

__all__ = [
    "diffused_similarity",
    "fused_graph_lists",
    "rerank_index",
    "SCALE_NEIGHBOURS",
    "ALPHA",
    "MIX",
    "SCORE_FLOOR",
    "WALK_NEAREST",
    "MIN_DEPTH",
    "MATRIX_TOLERANCE",
    "DEFAULT_DEPTH",
    "CANDIDATES",
]

#: neighbours per node in the affinity graph; the k-th one's distance is the node's scale
SCALE_NEIGHBOURS = 8
#: personalised PageRank: probability of following an edge rather than returning to the start
ALPHA = 0.8
#: weight of the direct affinity added to the diffused cosine
MIX = 0.2
#: the scores kept: one below is 0, its curve ordered by exact distance then id. In the tail
#: of a list (the mesh sections' top 40 hold ~3 curves of the query's mesh) the cosines of
#: walks that barely meet are ~1e-13 to 1e-2 and crowded, set by the push's tolerance as much
#: as by the shapes: ``query --rerank`` and ``matrix --rerank`` ordered them differently (the
#: same top 40 at 84.9% of the mesh sections' places); with the floor 98.6%, and the
#: bull's-eye of every development collection within 0.004 (docs/rerank.md)
SCORE_FLOOR = 0.05
#: a walk's candidates start from the query's exact ``WALK_NEAREST x top`` nearest. Below the
#: score floor the matrix orders by exact distance, so the tail of its top ``top`` comes from
#: the exact top ``2 top``; the third ``top`` holds the scored rows near in distance that
#: neither walk reaches. The same top 40 as ``matrix --rerank`` on the psb cut loops (spread
#: classes, low cosines) at 95.5% / 98.8% / 99.9% of the places for 1 / 2 / 3, for ~1.15x
#: the batch of 1 (docs/rerank.md)
WALK_NEAREST = 3
#: a query's candidates (--rerank-depth): at least, and by default (defined with the CLI's defaults)
MIN_DEPTH, DEFAULT_DEPTH = MIN_RERANK_DEPTH, DEFAULT_RERANK_DEPTH
#: ``query --rerank`` of a stored curve with ``exclude_self`` against ``matrix --rerank`` (given
#: the ids): every score within this (the push leaves residuals below
#: :data:`~.diffusion.TOLERANCE` per node; measured at most 8e-5 to 2e-4 on Kimia-99, the
#: mesh sections and generated families: ``bench_rerank.py --skip-timing``), so the two orders
#: agree but for scores closer than twice this
MATRIX_TOLERANCE = 1e-3
#: scores closer than this are ties, ordered by exact distance then id
_SCORE_TIE = 1e-12
#: where a query's candidates come from (``rerank_index(candidates=...)``): ``"walk"`` (the
#: default) its exact k nearest, the M stored rows of largest personalised-PageRank mass from
#: its first step and the M / 2 whose own PageRank reaches it most, each given its exact
#: distance; ``"exact"`` its exact top M
CANDIDATES = RERANK_CANDIDATES


def _pagerank_cosine(P: np.ndarray, alpha: float) -> np.ndarray:
    """(n, n) cosines between the rows of ``(1 - alpha) (I - alpha P)^-1``."""
    n = len(P)
    A = (1 - alpha) * np.linalg.solve(np.eye(n) - alpha * P, np.eye(n))
    norm = np.linalg.norm(A, axis=1)
    norm[norm == 0] = 1.0
    A /= norm[:, None]
    return A @ A.T


def diffused_similarity(
    distances: ArrayLike,
    *,
    k: int = SCALE_NEIGHBOURS,
    alpha: float = ALPHA,
    mix: float = MIX,
    ids: Sequence[str] | None = None,
    lists: np.ndarray | None = None,
) -> np.ndarray:
    """The re-ranked similarity of every pair of a collection.

    Parameters
    ----------
    distances : (N, N) float, symmetric exact distances with a zero diagonal.
    ids : the N curves' ids: a row's k nearest are taken as the stored graph takes them
        (distances within the search's ``TIE`` are ties, ordered by id), so that
        ``query --rerank`` of a stored curve agrees with this; None: ties by position.
    lists : (N, >= k) int, each row's neighbours in order (the first k walked), instead of
        its k nearest: a fused graph's (:func:`fused_graph_lists`; ``matrix --rerank
        --elastic``).

    Returns
    -------
    (N, N) float64, symmetric, higher is closer: 1 on the diagonal, at most 1 elsewhere
    (a cosine and an affinity, both at most 1, mixed), 0 below :data:`SCORE_FLOOR` (rank
    those by exact distance, then id, as ``query --rerank`` does). O(N^3) time (one dense
    N x N solve), O(N^2) memory.
    """
    D = np.array(distances, dtype=np.float64)
    N = len(D)
    if D.ndim != 2 or D.shape != (N, N):
        raise ParameterError(f"expected a square distance matrix, got shape {D.shape}")
    if ids is not None and len(ids) != N:
        raise ParameterError(f"expected {N} ids, one per curve, got {len(ids)}")
    if N == 0:
        return np.zeros((0, 0))
    off = D.copy()
    np.fill_diagonal(off, np.inf)
    tie_rank = np.arange(N) if ids is None else np.argsort(np.argsort(np.asarray(ids, dtype=object), kind="stable"))
    if lists is None:
        order = np.lexsort((np.broadcast_to(tie_rank, (N, N)), np.round(off / TIE)))[:, : min(k, N - 1)]
    else:
        order = np.asarray(lists, dtype=np.int64)[:, : min(k, N - 1)]
    s = row_scales(np.take_along_axis(off, order, axis=1), k)
    W = np.exp(-(D**2) / (s[:, None] * s[None, :]))
    mask = np.zeros((N, N), dtype=bool)
    mask[np.arange(N)[:, None], order] = True
    np.fill_diagonal(mask, True)
    P = np.where(mask, W, 0.0)
    P /= P.sum(axis=1, keepdims=True)
    S = (1 - mix) * _pagerank_cosine(P, alpha) + mix * W
    S = (S + S.T) / 2  # symmetric to rounding: the cosine and W are, up to round-off
    return np.where(S >= SCORE_FLOOR, S, 0.0)


def fused_graph_lists(
    exact: ArrayLike, fused: ArrayLike, ids: Sequence[str] | None = None, k: int = DEFAULT_GRAPH_K
) -> np.ndarray:
    """Each row's list in the graph ``index build --graph k --elastic`` stores, from full
    matrices: of its exact ``max(FUSED_CANDIDATES, 3 k)`` nearest (ties within ``TIE`` by
    id), the ``k`` of least fused distance (ties by id), as
    :func:`nfdmatch.search.graph.fused_lists` takes them; so that ``matrix --rerank
    --elastic`` walks the graph ``query --rerank`` walks.

    exact, fused : (N, N) float, the exact and the fused distances (``distance_matrix``
        without and with ``elastic``); ids : as :func:`diffused_similarity`'s.
    Returns (N, min(k, N - 1)) int64 positions."""
    T, F = np.array(exact, dtype=np.float64), np.array(fused, dtype=np.float64)
    N = len(T)
    if T.shape != (N, N) or F.shape != (N, N):
        raise ParameterError(f"expected two square matrices of one size, got {T.shape} and {F.shape}")
    tie_rank = np.arange(N) if ids is None else np.argsort(np.argsort(np.asarray(ids, dtype=object), kind="stable"))
    np.fill_diagonal(T, np.inf)
    m = min(max(FUSED_CANDIDATES, 3 * k), N - 1)
    ties = np.broadcast_to(tie_rank, (N, N))
    candidates = np.lexsort((ties, np.round(T / TIE)))[:, :m]
    f = np.take_along_axis(F, candidates, axis=1)
    pick = np.lexsort((tie_rank[candidates], np.round(f / TIE)))[:, : min(k, N - 1)]
    return np.take_along_axis(candidates, pick, axis=1)


def rerank_index(
    index: Any,
    queries: Any,
    *,
    k: int = 10,
    depth: int = DEFAULT_DEPTH,
    exclude_self: bool = False,
    progress: Callable[[int, int], None] | None = None,
    threads: int | None = None,
    candidates: str = DEFAULT_RERANK_CANDIDATES,
    top: Any = UNSET,
) -> tuple[list[list[RankedMatch]], SearchStats]:
    """k best curves of an index for each query by diffused score.

    Parameters
    ----------
    index : an open :class:`nfdmatch.index.Index` with a graph (``index build --graph``).
    queries : what :func:`~nfdmatch.search.knn.as_queries` takes (as ``Index.search``): one
        or a sequence of :class:`~nfdmatch.curve.Curve`, (n, 3) arrays and paths.
    k : matches per query (at most ``depth``); ``top`` is its deprecated older name.
    depth : M, the query's candidates besides its nearest (see ``candidates``), >= 100.
    exclude_self : the query's own curve (:func:`~nfdmatch.search.knn.is_self`) is the
        query in the graph (its stored row and PageRank) and is left out of the results;
        the scores are then ``matrix --rerank``'s within :data:`MATRIX_TOLERANCE`.
    progress, threads : as in :func:`~nfdmatch.search.search_index`.
    candidates : ``"walk"`` (the default: the query's exact ``max(3 top, 8)`` nearest, the
        ``depth`` stored rows of largest mass in its first-step PageRank and the ``depth // 2``
        whose PageRank reaches it most (:meth:`GraphWalk.reverse_pagerank`), each with its
        exact distance; no exact top-M search) or ``"exact"`` (the query's exact top ``depth``: ~4x
        the time of a batch at 100,000 curves, docs/rerank.md). On a graph of fused distances
        (``index build --graph K --elastic``): the query's exact ``max(3 top, 30)`` nearest (the
        exact nearest a stored row's list is cut from; ``"exact"``: its top ``depth``) plus
        the rows of its walks, each candidate given its fused distance (the elastic stage's),
        the matches their ``elastic`` and ``fused``.

    Returns
    -------
    ``(results, stats)``: ``results[i]`` lists query i's matches as
    :class:`~nfdmatch.records.RankedMatch` es with their ``score``, sorted by ``score`` (higher
    is closer, 0 below :data:`SCORE_FLOOR`; ties by exact distance, then id); ``distance`` is
    the exact distance. ``stats`` is the exact search's :class:`~nfdmatch.search.SearchStats`
    with ``seconds`` covering both steps.

    Raises
    ------
    IndexFormatError : the index has no graph, one of fewer than 8 neighbours per row, or a
        graph row the walk reads is damaged or not a valid list (docs/index-format.md).
    ParameterError : depth below 100, top above depth.

    Deterministic: the same index and queries give the same rows and scores, and a query
    gets the same scores alone as in any batch (each source's push is independent).
    """
    from .index_search import query_descriptors
    from .knn import as_queries

    top = k_or_top(k, top, "rerank_index")
    t0 = time.perf_counter()
    queries = as_queries(queries)
    if candidates not in CANDIDATES:
        raise ParameterError(f"candidates must be one of {', '.join(CANDIDATES)}, got {candidates!r}")
    reader = _checked_graph(index, top, depth)
    if not len(queries):  # nothing to rank: no search, no walk (as search_index answers no queries)
        from .index_search import SearchStats

        return [], SearchStats(rows=index.n_curves, seconds=time.perf_counter() - t0)
    is_self = self_rule(getattr(index, "locate", None))
    N = index.n_curves
    reverse = getattr(index, "graph_reverse_reader", lambda: None)()
    walk = GraphWalk(reader, N, SCALE_NEIGHBOURS, ALPHA, reverse)
    qcoef = query_descriptors(index, queries)
    fused = getattr(index, "graph_distance", lambda: "exact")() == "fused"
    if candidates == "exact":
        nearest = depth
    elif fused:  # the walk starts from the exact nearest a stored row's fused list is cut from
        nearest = max(WALK_NEAREST * top, FUSED_CANDIDATES, walk.k)
    else:  # one more with exclude_self: its own curve
        nearest = max(WALK_NEAREST * top, walk.k) + (1 if exclude_self else 0)
    found, stats, vectors = gather_candidates(
        index, walk, queries, qcoef, (nearest, depth), exclude_self, is_self, fused, candidates == "walk" or fused,
        progress=progress, threads=threads,
    )  # fmt: skip
    merged = self_flags(index, queries, found, exclude_self, is_self)
    results = _answers(index, walk, vectors, found, merged, top)
    stats.seconds = time.perf_counter() - t0
    return results, stats


def _answers(index, walk: GraphWalk, vectors: "PageRankVectors", found, merged, top: int) -> list[list[RankedMatch]]:
    """Each query's ``top`` candidates of highest score, as :class:`RankedMatch` es: ``found``
    its candidates (a ranked :class:`~nfdmatch.search.engine.BestRows`), ``merged`` which of
    them are its own stored curve (left out); scores closer than ``_SCORE_TIE`` are ties,
    ordered as the candidates are (exact distance, then id)."""
    picks, work = [], (np.zeros(walk.N + 1), np.zeros(walk.N + 1, dtype=bool))
    for tk, mine in zip(found, merged):
        if not len(tk.rows):
            picks.append((np.zeros(0, np.int64), None))
            continue
        scores = _query_scores(walk, vectors, tk.rows, tk.dist, mine, work)
        kept = np.flatnonzero(~mine)
        order = kept[np.lexsort((kept, -np.round(scores[kept] / _SCORE_TIE)))][:top]
        picks.append((order, scores))
    reported = [tk.rows[order] for tk, (order, _) in zip(found, picks)]
    ids = index.ids_at(np.concatenate(reported)) if reported else []
    results, at = [], 0
    for tk, (order, scores) in zip(found, picks):
        fused = "exact" in tk.extra  # then dist is the fused distance
        # each column as Python values at once (a numpy scalar per field cost ~4 us a match)
        picked = {key: v[order].tolist() for key, v in tk.extra.items()}
        dist, rows, score = (
            tk.dist[order].tolist(),
            tk.rows[order].tolist(),
            scores[order].tolist() if len(order) else [],
        )
        results.append(
            [
                RankedMatch(
                    rank=n + 1,
                    id=ids[at + n],
                    distance=picked["exact"][n] if fused else dist[n],
                    shift=picked["shift"][n],
                    reversed=picked["reversed"][n],
                    mirrored=picked["mirrored"][n],
                    row=rows[n],
                    score=score[n],
                    elastic=picked["elastic"][n] if "elastic" in picked else None,
                    fused=dist[n] if fused else None,
                )
                for n in range(len(order))
            ]
        )
        at += len(order)
    return results


def _checked_graph(index, top: int, depth: int):
    """The index's graph reader, once :func:`rerank_index`'s arguments and the graph are
    checked."""
    if isinstance(depth, bool) or not isinstance(depth, (int, np.integer)) or depth < MIN_DEPTH:
        raise ParameterError(f"rerank depth must be an integer of at least {MIN_DEPTH}, got {depth!r}")
    if top < 1 or top > depth:
        raise ParameterError(f"k must be between 1 and the rerank depth ({depth}), got {top}")
    reader = index.graph_reader()
    if reader is None:
        raise IndexFormatError(
            "the index has no neighbour graph, which --rerank needs: build it with "
            f"`nfdmatch index build ... --index {index.path} --graph`",
            path=index.path,
        )
    stored_k = index.graph_k()
    if stored_k < SCALE_NEIGHBOURS:
        # the rebuild keeps what the graph's distances are: a fused graph stays fused
        fused = " --elastic" if getattr(index, "graph_distance", lambda: "exact")() == "fused" else ""
        raise IndexFormatError(
            f"the index's graph holds {stored_k} neighbours per curve; --rerank needs at least "
            f"{SCALE_NEIGHBOURS}: rebuild it with `nfdmatch index build ... --index {index.path} "
            f"--graph {SCALE_NEIGHBOURS}{fused}` or more",
            path=index.path,
        )
    return reader


def _query_scores(walk: GraphWalk, vectors: PageRankVectors, rows, qd, merged, work) -> np.ndarray:
    """Scores of one query's candidates ``rows`` (exact distances ``qd``, ascending; ``merged``:
    the candidates that are the query's own stored curve, whose score is NaN). ``work``:
    ``(dense, entered)``, (N + 1,) float64 zeros and bool False, work arrays (left so)."""
    N, alpha = walk.N, walk.alpha
    dense, entered = work
    out = np.full(len(rows), np.nan)
    keep = np.flatnonzero(~merged)
    if not len(keep):
        return out
    cand = rows[keep]
    owner, node, value = vectors.entries(cand)
    back = np.zeros(len(keep))  # the candidates' own PageRank at the query (first order)
    if merged.any():
        # the query is a stored row: its PageRank is that row's, its scale that row's
        self_row = rows[np.flatnonzero(merged)[0]]
        _, q_node, q_val = vectors.entries(np.array([self_row]))
        dense[q_node] = q_val
        s_q, s_cand = walk.scales([self_row])[0], walk.scales(cand)
    else:
        # the query joins the graph as node N: its k nearest (exact), and the candidates
        # whose k nearest it enters (their lists and scales change while it is there)
        with query_joined(walk, cand, qd[keep]) as into:
            s_q = walk.scales([N])[0]
            s_cand = walk.scales(cand)
            q_targets, q_prob = walk.transitions(np.array([N]))
            targets, prob = walk.transitions(into)
        # first order: a candidate's walk reaches the query through the rows it entered
        to_q = (prob * (targets == N)).sum(axis=1)
        dense[into] = alpha * to_q
        # summed over the entries at those rows alone: the others add +0.0, which changes no sum
        entered[into] = True
        at_into = np.flatnonzero(entered[node])
        entered[into] = False
        back = np.bincount(owner[at_into], weights=dense[node[at_into]] * value[at_into], minlength=len(cand))
        dense[into] = 0.0
        # the query's PageRank from its first step: pi_q = ((1 - alpha) e_q + alpha sum_v P_qv
        # pi_v) / (1 - alpha P_qq), each neighbour's pi_v its stored vector plus its mass at q
        self_p = float(q_prob[0, 0])  # the self loop comes first
        nbrs, p_nb = q_targets[0, 1:], q_prob[0, 1:]
        real = nbrs != N
        nbrs, p_nb = nbrs[real], p_nb[real]
        by_row = np.argsort(cand, kind="stable")
        at = by_row[np.searchsorted(cand[by_row], nbrs)]  # the query's neighbours are candidates
        v_owner, v_node, v_value = vectors.entries(nbrs)
        norm = 1.0 / (1 - alpha * self_p)
        np.add.at(dense, v_node, alpha * p_nb[v_owner] * v_value * norm)
        dense[N] = ((1 - alpha) + alpha * float((p_nb * back[at]).sum())) * norm
        q_node = np.concatenate([sorted_unique(v_node), [N]])
        q_val = dense[q_node]
    dot = np.bincount(owner, weights=dense[node] * value, minlength=len(cand)) + dense[N] * back
    norm_c = np.sqrt(vectors.norms(cand) ** 2 + back**2)
    norm_q = max(float(np.sqrt((q_val**2).sum())), 1e-300)
    dense[q_node] = 0.0
    cos = dot / (norm_q * np.maximum(norm_c, 1e-300))
    direct = np.exp(-(qd[keep] ** 2) / (s_q * s_cand))
    score = (1 - MIX) * cos + MIX * direct
    out[keep] = np.where(score >= SCORE_FLOOR, score, 0.0)
    return out
