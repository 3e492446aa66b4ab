"""A query's candidates for ``query --rerank`` (docs/rerank.md): its exact nearest, the rows
its walks reach forward and backwards on the stored graph, each given its exact distance
(and, on a graph of fused distances, its fused distance), and the PageRank vector of every
candidate, computed once for the batch; :mod:`.rerank` scores them.

The work is spread over the kernels' threads: each query's distances on one thread, a
PageRank push beside them when it costs about as much (:func:`gather_candidates`)."""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from functools import partial
from typing import TYPE_CHECKING, Any

import numpy as np

from .diffusion import GraphWalk, sorted_unique, sum_by_key
from .engine import TIE, BestRows, Cascade
from .stages import fused_terms, fused_threads, rank_by_fused, rigid_of, statistics_of_queries

if TYPE_CHECKING:
    from ..curve import Curve
    from .index_search import SearchStats

__all__ = ["PageRankVectors", "gather_candidates", "query_joined", "self_flags", "union_rows", "walk_backwards"]

#: fused distances per source from which a PageRank push runs beside them (:func:`_beside`):
#: a row's fused distance costs ~50 us, a source's push ~100 us (100,000 curves) to ~650 us
#: (1,400 in families of 20); beside fewer the push, left one thread, took longest (one query
#: of the 1,400: 150 ms against 117 ms with the push after, over both threads)
_BESIDE_ROWS = 8


def union_rows(tops: Sequence[BestRows]) -> np.ndarray:
    """Every row of the :class:`~nfdmatch.search.engine.BestRows` ``tops``, ascending and unique."""
    return sorted_unique(np.concatenate([tk.rows for tk in tops])) if tops else np.zeros(0, np.int64)


def _positions(tops, rows) -> np.ndarray:
    """Where the search table holds each of ``rows`` (ascending, unique, every one found by a
    query of ``tops``): the ``extra["position"]`` the search gave it."""
    found = np.concatenate([tk.rows for tk in tops])
    positions = np.concatenate([tk.extra["position"] for tk in tops])
    order = np.argsort(found, kind="stable")
    return positions[order][np.searchsorted(found[order], rows)]


def self_flags(
    index: Any,
    queries: Sequence[Curve],
    tops: Sequence[BestRows],
    exclude_self: bool,
    is_self: Callable[[str, str], bool],
) -> list[np.ndarray]:
    """Per query, (m,) bool: which of its rows in ``tops`` are its own stored curve (under
    ``exclude_self``; none otherwise)."""
    if not exclude_self:
        return [np.zeros(len(tk.rows), dtype=bool) for tk in tops]
    every = union_rows(tops)
    ids = index.ids_at(every) if len(every) else []
    return [
        np.array([is_self(q.id, ids[p]) for p in np.searchsorted(every, tk.rows).tolist()], dtype=bool)
        for q, tk in zip(queries, tops)
    ]


def gather_candidates(
    index: Any,
    walk: GraphWalk,
    queries: Sequence[Curve],
    qcoef: np.ndarray,
    depths: tuple[int, int],
    exclude_self: bool,
    is_self: Callable[[str, str], bool],
    fused: bool,
    walks: bool,
    *,
    progress: Callable[[int, int], None] | None,
    threads: int | None,
) -> tuple[list[BestRows], SearchStats, PageRankVectors]:
    """``(found, stats, vectors)``: each query's candidates as a
    :class:`~nfdmatch.search.engine.BestRows` ranked as the search ranks its rows (exact
    distance, ties by id: :func:`~nfdmatch.search.index_search.rank_rows`): its exact top
    ``depths[0]``, on a graph of fused distances each given its fused distance (the elastic
    stage's, which it joins the graph by), and with ``walks`` the rows of its walks added
    (:func:`_add_walk_rows`, ``depths[1]`` of them forward; their distances as the graph's);
    ``vectors`` every candidate's PageRank, once for the batch. (qcoef: (Q, K, 3)
    complex128, the queries' descriptors.)"""
    from .index_search import found_rows

    nearest, depth = depths
    # the exact distance, invariant to direction, no mirror; the rows' figures computed on the
    # threads (_measure) with their PageRank, which needs none of them: the rows found, with
    # any tied past the nearest (a source's PageRank does not depend on the others pushed)
    found, stats, table = found_rows(
        index, qcoef, Cascade(index.samples), top=nearest, progress=progress, threads=threads
    )  # fmt: skip
    union = union_rows(found)
    read = _Read(index, union, table, _positions(found, union))
    push = partial(walk.pagerank, union)
    beside = _beside(push, fused, len(union), sum(len(tk.rows) for tk in found))
    # on a fused graph, each batch's fused distances (the queries' statistics computed once)
    terms_of = partial(fused_terms, query_statistics=statistics_of_queries(qcoef)) if fused else None
    pushed = _measure(index, qcoef, found, terms_of, beside, read=read, ranked=nearest)
    vectors = PageRankVectors(union, *(pushed if beside else push()))
    if walks:
        forward, backwards = _forward_rows(index, walk, queries, found, vectors, depth, exclude_self, is_self)
        computed, vectors = _add_walk_rows(index, walk, qcoef, found, vectors, (forward, backwards), depth, terms_of)
        stats.exact += computed
    return found, stats, vectors


def _add_walk_rows(index, walk: GraphWalk, qcoef, found, vectors: "PageRankVectors", walked, depth: int, terms_of):
    """Merge into each query's candidates ``found[i]`` the rows of its walks, ``walked``: the
    rows its walk forward adds and where its walk backwards starts (:func:`_forward_rows`);
    the walk backwards adds the ``depth // 2`` rows whose PageRank reaches it most
    (:func:`_reaching_rows`). Each row is given its exact distance and, on a fused graph
    (``terms_of`` not None: as :func:`_measure` takes it), its fused distance; each list
    ranked again (:func:`_merge_rows`).
    Returns how many exact distances it computed, and ``vectors`` with the PageRank of the
    rows added.

    The walk backwards (numpy) runs on the threads with the distances of the rows forward
    (compiled kernels), the PageRank of the rows added with the distances of the rows
    backwards: each row's distances are computed alone, the same digits as all at once."""
    forward, backwards = walked
    fused = terms_of is not None
    reached = _measure(index, qcoef, forward, terms_of, partial(walk_backwards, walk, backwards))
    backward = _reaching_rows(found, forward, backwards, reached, depth // 2)
    added = sorted_unique(np.concatenate([union_rows(forward), union_rows(backward)]))
    push, sources = partial(vectors.with_rows, walk, added), len(added) - int(np.isin(added, vectors.union).sum())
    beside = _beside(push, fused, sources, sum(len(tk.rows) for tk in backward))
    measured = _measure(index, qcoef, backward, terms_of, beside)
    vectors = measured if beside else push()
    more = [_joined_rows(ahead, behind, fused) for ahead, behind in zip(forward, backward)]
    _merge_rows(index, found, more, fused)
    return sum(len(extra.rows) for extra in more), vectors


def _forward_rows(index, walk: GraphWalk, queries, near, vectors: "PageRankVectors", depth, exclude_self, is_self):
    """``(forward, backwards)``: per query, a :class:`~nfdmatch.search.engine.BestRows` of the
    rows its walk forward adds to its candidates ``near[i]`` (:func:`_unmeasured`): the
    ``depth`` stored rows other than itself of largest mass in its PageRank (a stored
    query's: its row's; any other: from its first step, as :mod:`.rerank` scores it), ties by
    row; and per query with candidates ``(query, (node, residual), left out)``: where its walk
    backwards starts (:func:`walk_backwards`). ``vectors``: the PageRank of every row of
    ``near``."""
    N, alpha = walk.N, walk.alpha
    forward, backwards = [], []
    for qi, (tk, merged) in enumerate(zip(near, self_flags(index, queries, near, exclude_self, is_self))):
        rows, qd = tk.rows, tk.dist
        forward.append(_unmeasured(np.zeros(0, np.int64)))
        if not len(rows):
            continue
        if merged.any():
            self_row = int(rows[np.flatnonzero(merged)[0]])
            _, node, mass = vectors.entries(np.array([self_row]))
            exclude, start = self_row, (np.array([self_row]), np.ones(1))
        else:
            with query_joined(walk, rows, qd) as into:
                q_targets, q_prob = walk.transitions(np.array([N]))
                in_targets, in_prob = walk.transitions(into)
            nbrs, p_nb = q_targets[0, 1:], q_prob[0, 1:]
            real = nbrs != N
            nbrs, p_nb = nbrs[real], p_nb[real]
            v_owner, v_node, v_value = vectors.entries(nbrs)
            node, mass = sum_by_key(v_node, alpha * p_nb[v_owner] * v_value)
            # the rows whose lists the query entered reach it first: where its column starts
            exclude, start = N, (into, alpha * (in_prob * (in_targets == N)).sum(axis=1))
        other = node != exclude
        node, mass = node[other], mass[other]
        picked = node[np.lexsort((node, -mass))[:depth]]
        forward[-1] = _unmeasured(sorted_unique(picked[~np.isin(picked, rows)]))
        backwards.append((qi, start, exclude))
    return forward, backwards


def _beside(push: Callable[[], Any], fused: bool, sources: int, rows: int) -> Callable[[], Any] | None:
    """A PageRank push of ``sources`` sources to run on the threads with a batch's distances
    to ``rows`` rows in all (:func:`_measure`), or None: it runs after them, over the threads
    (beside them it has one). Beside a fused graph's distances when they are at least
    :data:`_BESIDE_ROWS` per source, so cost about as much as the push (200 queries of 1,400
    curves: 17 a source; one query: ~1); never beside an exact graph's few exact distances."""
    return push if fused and rows >= _BESIDE_ROWS * sources else None


def _unmeasured(rows: np.ndarray) -> BestRows:
    """A :class:`~nfdmatch.search.engine.BestRows` of ``rows`` (ascending) whose distances are
    not computed yet (:func:`_measure`): zeros, no position in a search table (-1)."""
    tk = BestRows(None, None)
    tk.rows, tk.dist = rows, np.zeros(len(rows))
    tk.extra = {key: np.full(len(rows), -1 if key == "position" else 0, dtype=v.dtype) for key, v in tk.extra.items()}
    return tk


def _measure(index, qcoef, parts, terms_of, alongside: Callable[[], Any] | None, *, read=None, ranked=None) -> Any:
    """Give each query's rows ``parts[i]`` (:func:`_unmeasured`, or as the search found them)
    their exact distance (computed alone, as the search computes the rows it found:
    :func:`~nfdmatch.search.index_search.recompute_reported`, descriptors from ``read``, a
    :class:`_Read` of every row, made here when None; rows then ascending), with ``ranked``
    ranked as the search ranks its rows and cut to that many
    (:func:`~nfdmatch.search.index_search.rank_rows`) and, on a fused graph, their fused
    distance (ranked by it: :func:`rank_by_fused`; ``terms_of``: :func:`fused_terms` with the
    queries' statistics, None on an exact graph); each query's on one of the kernels'
    threads (:func:`~nfdmatch.matching._threads.run_spread`), the call ``alongside`` (which
    needs none of them; None: no call) started first. Returns what it returned."""
    from ..matching._threads import run_spread
    from ..matching.kernels import current
    from .index_search import rank_rows, recompute_reported

    total = sum(len(tk.rows) for tk in parts)
    alongside = alongside or _nothing
    if not total:
        return alongside()
    read, cascade = read or _Read(index, union_rows(parts)), Cascade(index.samples)
    terms = terms_of(index, qcoef, [tk.rows for tk in parts]) if terms_of is not None else None

    def one(qi: int) -> None:
        tk = parts[qi]
        if len(tk.rows):
            recompute_reported(
                read, qcoef[qi : qi + 1], [tk], cascade.distance, direction=cascade.direction, mirror=cascade.mirror,
                weights=None,
            )  # fmt: skip
            if ranked is not None:
                rank_rows(index, [tk], ranked)  # (reads ids only for tied distances)
            if terms is not None:
                rank_by_fused(tk, terms(qi, tk.rows, rigid_of(tk)))

    threads = fused_threads(total) if terms is not None else current().workers(total)
    return run_spread([alongside, *(partial(one, qi) for qi in range(len(parts)))], threads)[0]


def _nothing() -> None:
    """No work (:func:`_measure` without a call alongside)."""


def walk_backwards(walk: GraphWalk, backwards: list) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """The walks backwards of the batch's queries (``backwards``: ``(query, (node, residual),
    left out)`` per query with candidates) at once, by :meth:`GraphWalk.reverse_pagerank`:
    ``(query, row, mass)`` sorted by (query, row); None when no query has candidates."""
    if not backwards:
        return None
    owner = np.concatenate([np.full(len(start[0]), qi, np.int64) for qi, start, _ in backwards])
    node = np.concatenate([start[0] for _, start, _ in backwards])
    residual = np.concatenate([start[1] for _, start, _ in backwards])
    return walk.reverse_pagerank(owner, node, residual)


def _reaching_rows(near, forward, backwards, reached, count: int) -> list[BestRows]:
    """Per query, a :class:`~nfdmatch.search.engine.BestRows` (:func:`_unmeasured`) of the
    ``count`` rows whose own walks reach it most (``reached``: :func:`walk_backwards`), other
    than its nearest (``near[i].rows``), the rows its walk forward adds (``forward[i].rows``)
    and the node left out; ties by row. Such a row's PageRank overlaps the query's though
    the query's walk hardly reaches it (docs/rerank.md, "Depth")."""
    backward = [_unmeasured(np.zeros(0, np.int64)) for _ in near]
    if reached is None or count < 1:
        return backward
    src, reached_rows, mass = reached
    bounds = np.searchsorted(src, np.arange(len(near) + 1))
    for qi, _, exclude in backwards:
        rows, their = reached_rows[bounds[qi] : bounds[qi + 1]], mass[bounds[qi] : bounds[qi + 1]]
        new = (rows != exclude) & ~np.isin(rows, near[qi].rows) & ~np.isin(rows, forward[qi].rows)
        rows, their = rows[new], their[new]
        backward[qi] = _unmeasured(sorted_unique(rows[np.lexsort((rows, -their))[:count]]))
    return backward


def _joined_rows(ahead: BestRows, behind: BestRows, fused: bool) -> BestRows:
    """One query's walk rows, forward and backwards (disjoint, each measured: :func:`_measure`),
    as one :class:`~nfdmatch.search.engine.BestRows` ordered as measuring them together orders
    them: by row; on a fused graph by fused distance (within TIE), exact distance, then row."""
    if not len(behind.rows) or not len(ahead.rows):
        return ahead if len(ahead.rows) else behind
    rows, dist = np.concatenate([ahead.rows, behind.rows]), np.concatenate([ahead.dist, behind.dist])
    extra = {key: np.concatenate([v, behind.extra[key]]) for key, v in ahead.extra.items()}
    order = np.lexsort((rows, extra["exact"], np.round(dist / TIE))) if fused else np.argsort(rows)
    joined = BestRows(None, None)
    joined.rows, joined.dist, joined.extra = rows[order], dist[order], {key: v[order] for key, v in extra.items()}
    return joined


def _merge_rows(index, found, more, fused: bool) -> None:
    """Merge each query's measured walk rows ``more[i]`` into its candidates ``found[i]``,
    each list ranked again: by distance, ties by id (fused: ties by exact distance, then as
    found)."""
    from .index_search import rank_rows

    for tk, extra in zip(found, more):
        tk.rows, tk.dist = np.concatenate([tk.rows, extra.rows]), np.concatenate([tk.dist, extra.dist])
        tk.extra = {key: np.concatenate([v, extra.extra.get(key, v[:0])]) for key, v in tk.extra.items()}
        if fused and len(tk.rows):  # no candidates (an index of no curves): no fused columns to rank by
            order = np.lexsort((tk.extra["exact"], np.round(tk.dist / TIE)))
            tk.rows, tk.dist = tk.rows[order], tk.dist[order]
            tk.extra = {key: v[order] for key, v in tk.extra.items()}
    if not fused:
        rank_rows(index, found)


class _Read:
    """The descriptors of the batch's candidates ``rows`` (ascending, unique), read in one
    read, served as :meth:`Index.coefficients_at` would (one read per query cost ~5 ms each
    at 100,000 curves): from the search's ``table`` at the rows' ``positions`` when it holds
    them all (as :func:`~nfdmatch.search.index_search.recompute_reported` reads them), else
    from the index. Read here, on the calling thread (a table reads what it does not hold
    yet); then served to any thread."""

    def __init__(self, index, rows, table=None, positions=None):
        self.samples, self.rows = index.samples, rows
        from_table = table is not None and positions is not None and len(rows) and positions.min() >= 0
        self.coef = table.coefficients_at_positions(positions) if from_table else index.coefficients_at(rows)

    def coefficients_at(self, rows):
        return self.coef[np.searchsorted(self.rows, rows)]


@contextmanager
def query_joined(walk: GraphWalk, cand: np.ndarray, qd: np.ndarray) -> Iterator[np.ndarray]:
    """For the duration of the block, the query is node N of ``walk``, joined to the graph
    through the candidates ``cand`` (exact distances ``qd``): its list is its k nearest
    candidates (padded), and the candidates whose k nearest it enters (yielded, ``into``)
    have their new lists (:meth:`GraphWalk.overlay`)."""
    k, N = walk.k, walk.N
    order = np.argsort(qd, kind="stable")[:k]
    q_nb = np.full((1, k), -1, dtype=np.int64)
    q_d = np.full((1, k), np.inf)
    q_nb[0, : len(order)], q_d[0, : len(order)] = cand[order], qd[order]
    walk.ensure(cand)
    kth = walk._d[cand, -1]  # inf when the list is padded: the query enters it
    enter = np.flatnonzero(qd < kth)
    into = cand[enter]
    nb = np.concatenate([walk._nb[into], np.full((len(into), 1), N)], axis=1)
    d = np.concatenate([walk._d[into], qd[enter, None]], axis=1)
    pick = np.argsort(d, axis=1, kind="stable")[:, :k]
    nb, d = np.take_along_axis(nb, pick, axis=1), np.take_along_axis(d, pick, axis=1)
    with walk.overlay(np.concatenate([[N], into]), np.concatenate([q_nb, nb]), np.concatenate([q_d, d])):
        yield into


class PageRankVectors:
    """The PageRank vectors of the stored rows ``union`` (ascending), as returned by
    :meth:`GraphWalk.pagerank`, with their norms."""

    def __init__(self, union: np.ndarray, start: np.ndarray, node: np.ndarray, value: np.ndarray) -> None:
        self.union, self.start, self.node, self.value = union, start, node, value
        sq = value**2
        self.norm = np.sqrt(np.add.reduceat(sq, start[:-1])) if len(value) else np.zeros(0)

    def entries(self, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(owner, node, value)``: the entries of the rows' vectors, ``owner`` the position
        in ``rows`` each entry belongs to."""
        pos = np.searchsorted(self.union, rows)
        a, b = self.start[pos], self.start[pos + 1]
        lengths = b - a
        owner = np.repeat(np.arange(len(rows)), lengths)
        first = np.concatenate([[0], np.cumsum(lengths)[:-1]])
        at = np.arange(lengths.sum()) + np.repeat(a - first, lengths)
        return owner, self.node[at], self.value[at]

    def norms(self, rows: np.ndarray) -> np.ndarray:
        return self.norm[np.searchsorted(self.union, rows)]

    def with_rows(self, walk: GraphWalk, rows: np.ndarray) -> PageRankVectors:
        """These vectors and those of ``rows`` (ascending, unique) not among them, pushed now."""
        new = rows[~np.isin(rows, self.union)]
        if not len(new):
            return self
        start, node, value = walk.pagerank(new)
        union = np.concatenate([self.union, new])
        lengths = np.concatenate([np.diff(self.start), np.diff(start)])
        first = np.concatenate([self.start[:-1], start[:-1] + len(self.node)])
        nodes, values = np.concatenate([self.node, node]), np.concatenate([self.value, value])
        order = np.argsort(union, kind="stable")
        lengths, first = lengths[order], first[order]
        offsets = np.concatenate([[0], np.cumsum(lengths)])
        at = np.arange(offsets[-1]) - np.repeat(offsets[:-1], lengths) + np.repeat(first, lengths)
        return PageRankVectors(union[order], offsets.astype(np.int64), nodes[at], values[at])
