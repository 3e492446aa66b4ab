"""Exact k nearest curves of an index (or of curves in memory) for a batch of queries."""

from __future__ import annotations

import time
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, TypeAlias

import numpy as np

from ..errors import ParameterError
from ..matching import DEFAULT_DIRECTION, DEFAULT_METHOD, METHODS
from ..matching.fused import require_exact
from ..matching.kernels import current as current_kernels
from ..records import RankedMatch
from .engine import TIE, Cascade, BestRows, search_block
from .bounds import feature_vector
from .limits import check_limits
from .selfmatch import drop_self, self_rule

if TYPE_CHECKING:
    from collections.abc import Iterable
    from numpy.typing import ArrayLike

    from ..curve import Curve
    from .stages import Stage

__all__ = ["search_index", "SearchStats", "SearchResults", "EXHAUSTIVE_ROWS", "k_or_top"]

#: rows per exact call of the exhaustive search: bounds the (rows x shifts x 9) working set
EXHAUSTIVE_ROWS = 2048


@dataclass
class SearchStats:
    """What a search did, over all queries: ``queries``, ``rows`` (index rows),
    ``exact`` (exact distances computed), ``truncated`` (truncated-harmonic bounds, first
    stage), ``fine`` (truncated bounds of the later stages, on fewer rows),
    ``scanned`` (rows whose invariant bound was computed), ``cells`` (cells opened),
    ``bytes_read`` (features and descriptors read from the index), ``seconds``,
    ``pruned`` (False for an exhaustive search), ``cell_count`` (cells in the index: 1 when
    the index has none, e.g. format 1), ``kernels`` (which computed the exact distances,
    and why: :meth:`nfdmatch.matching.Kernels.describe`)."""

    queries: int = 0
    rows: int = 0
    exact: int = 0
    truncated: int = 0
    fine: int = 0
    scanned: int = 0
    cells: int = 0
    bytes_read: int = 0
    seconds: float = 0.0
    pruned: bool = True
    cell_count: int = 0
    kernels: str = ""

    @property
    def exact_fraction(self) -> float:
        """Fraction of (query, row) pairs that needed an exact distance."""
        total = self.queries * self.rows
        return self.exact / total if total else 0.0

    def per_query(self, value: float) -> float:
        return value / self.queries if self.queries else 0.0


#: what a search of an index returns (:func:`search_index`, ``Cluster.search_index``,
#: :func:`~nfdmatch.search.rerank.rerank_index`): ``(results, stats)``, each query's list of
#: matches, best first, and what the search did
SearchResults: TypeAlias = tuple[list[list[RankedMatch]], SearchStats]


#: ``top=``, the older name of ``k=`` (kept working, with a DeprecationWarning)
UNSET: Any = object()


def k_or_top(k: int | None, top: Any, where: str) -> int | None:
    """``k``, or ``top`` when a caller still spells it so (deprecated: ``k`` is the name in
    every search of the library)."""
    if top is UNSET:
        return k
    warnings.warn(f"{where}(top=) is deprecated: use k=", DeprecationWarning, stacklevel=3)
    return top


def check_search_parameters(top: int | None, max_distance: float | None, method: str) -> None:
    """The checks every search of an index makes on its arguments (local or on a cluster)."""
    if top is None and max_distance is None:
        raise ParameterError("give k or max_distance (or both)")
    check_limits(top, max_distance, top_name="k")
    if method not in METHODS:
        raise ParameterError(f"method must be one of {', '.join(METHODS)}, got {method!r}")


def search_index(
    index: Any,
    queries: Sequence[Curve],
    *,
    k: int | None = 10,
    max_distance: float | None = None,
    method: str = DEFAULT_METHOD,
    direction: str = DEFAULT_DIRECTION,
    mirror: bool = False,
    prune: bool = True,
    progress: Callable[[int, int], None] | None = None,
    weights: ArrayLike | None = None,
    threads: int | None = None,
    truncate: bool = True,
    exclude_self: bool = False,
    stage: Stage | None = None,
    top: Any = UNSET,
) -> SearchResults:
    """k nearest curves of an index for each query curve, exactly.

    Parameters
    ----------
    index : an open :class:`nfdmatch.index.Index` or a :class:`~nfdmatch.search.MemoryIndex`
        (anything with ``samples``, ``harmonics``, ``scale``, ``n_curves``, ``ids_at``,
        ``search_table()`` and ``iter_chunks``).
    queries : sequence of :class:`~nfdmatch.curve.Curve`; descriptors are computed with the
        index's own samples, harmonics and scale.
    k : matches per query (None: every row within ``max_distance``; ``top``: its old name).
    max_distance : only matches at most this far.
    method, direction, mirror : as in :func:`nfdmatch.distance`.
    prune : False computes every exact distance (``query --exhaustive``: the reference the
        pruned search must equal).
    progress : optional callable ``progress(queries_done, queries_total)``.
    weights : (K,) harmonic weights (the bounds are unweighted: needs ``prune=False``).
    threads : queries answered in parallel (default: the cores, at most 4).
    truncate : use the truncated-harmonic bound (an option for measuring its effect).
    exclude_self : drop each query's own curve from its matches (the same id, or the same
        curve of the same file however spelled: :func:`~nfdmatch.search.knn.self_rule`).
    stage : a :class:`~nfdmatch.search.stages.Stage` (e.g. ``ElasticStage(depth=100)``):
        the exact top :meth:`~nfdmatch.search.stages.Stage.candidates` of each query
        (within ``max_distance``, without its own curve) re-ordered by the stage, then cut
        to ``k``.

    Returns
    -------
    ``(results, stats)``: ``results[i]`` lists query i's matches as :class:`~nfdmatch.records.RankedMatch`
    (rank, id, distance, shift, reversed, mirrored, row: the match's row in the index) sorted
    by distance then id; ``stats`` a :class:`SearchStats`.

    Pruned search: one best-first order over the whole index per query (:func:`.engine.search_block`):
    cells by their bound, rows by their invariant bound, then the truncated-harmonic bound, then
    exact distances, stopping when the next bound exceeds the k-th distance. No false
    dismissals: every bound is proven never to exceed the exact distance.
    """
    top = k_or_top(k, top, "search_index")
    check_search_parameters(top, max_distance, method)
    if weights is not None and prune:
        raise ParameterError("pruning uses unweighted bounds: pass prune=False with weights")
    t0 = time.perf_counter()
    wanted = top
    if stage is not None:
        require_exact(method)
        top = stage.candidates(top)
    asked = top
    if exclude_self and top is not None:
        top += 1  # the query's own curve is dropped below
    qcoef = query_descriptors(index, queries)
    cascade = Cascade(index.samples, method, direction, mirror, truncate)
    tops, stats = search_rows(
        index, qcoef, cascade, top=top, max_distance=max_distance, prune=prune, progress=progress, weights=weights,
        threads=threads,
    )  # fmt: skip
    results = ranked_rows(index, tops, top)
    if exclude_self:
        results = without_self(index, queries, results, asked)
    if stage is not None:
        matching = {"direction": direction, "mirror": mirror, "weights": weights}
        results = [found[:wanted] for found in stage.reorder(index, qcoef, results, matching=matching)]
    stats.seconds = time.perf_counter() - t0
    return results, stats


def query_descriptors(index: Any, queries: Sequence[Curve]) -> np.ndarray:
    """(Q, K, 3) complex128: the queries' descriptors with the index's samples, harmonics and
    scale."""
    from ..descriptors import descriptors_batch

    return descriptors_batch(
        queries, samples=index.samples, harmonics=index.harmonics, scale=index.scale_mode
    ).coefficients


def search_rows(
    index: Any,
    qcoef: np.ndarray,
    cascade: Cascade,
    *,
    top: int | None,
    weights: ArrayLike | None = None,
    **options: Any,
) -> tuple[list[BestRows], SearchStats]:
    """:func:`search_index`'s search, its answer as rows: ``(tops, stats)``, ``tops[i]`` the
    :class:`~nfdmatch.search.engine.BestRows` of query i (descriptors ``qcoef[i]``, (K, 3)
    complex128) in no particular order, every row's figures computed alone
    (:func:`recompute_reported`); ``stats.seconds`` is left 0. ``cascade``: what is computed
    (the method, direction, mirror, truncation); ``options``: :func:`found_rows`'
    (``max_distance``, ``prune``, ``progress``, ``threads``); all as for
    :func:`search_index`, checked there."""
    tops, stats, table = found_rows(index, qcoef, cascade, top=top, weights=weights, **options)
    recompute_reported(
        index, qcoef, tops, cascade.distance, direction=cascade.direction, mirror=cascade.mirror, weights=weights,
        tables=table,
    )  # fmt: skip
    return tops, stats


def found_rows(
    index: Any,
    qcoef: np.ndarray,
    cascade: Cascade,
    *,
    top: int | None,
    max_distance: float | None = None,
    prune: bool = True,
    progress: Callable[[int, int], None] | None = None,
    weights: ArrayLike | None = None,
    threads: int | None = None,
) -> tuple[list[BestRows], SearchStats, Any]:
    """:func:`search_rows` but for its last step: ``(tops, stats, table)``, the rows found with
    their figures as the search left them (they depend on when it met each row), for a
    caller that computes them with :func:`recompute_reported` itself (``query --rerank``: on
    its threads, with other work); ``table``: the search table that holds the rows'
    descriptors (their ``extra["position"]``), or None."""
    tops = [BestRows(top, max_distance) for _ in range(len(qcoef))]
    stats = SearchStats(queries=len(qcoef), rows=index.n_curves, pruned=prune)
    table = None
    if not prune:
        stats.exact = _exhaustive(index, qcoef, tops, cascade, weights, progress)
    elif index.n_curves and len(qcoef):
        table = _pruned(index, qcoef, tops, cascade, stats, threads, progress)
    stats.kernels = current_kernels().describe()
    return tops, stats, table


def _exhaustive(index, qcoef, tops, cascade: Cascade, weights, progress) -> int:
    """Every exact distance of the queries to the index's rows (``query --exhaustive``: no
    bound consulted), into ``tops``; returns the number computed."""
    chunks = (
        (start, chunk["coefficients"])
        for start, chunk in index.iter_chunks(EXHAUSTIVE_ROWS * 8, ("coefficients",), upcast=False)
    )
    computed, _ = exhaustive_rows(
        qcoef, tops, chunks, cascade.distance, index.samples, direction=cascade.direction,
        mirror=cascade.mirror, weights=weights, progress=progress, total=index.n_curves,
    )  # fmt: skip
    return computed


def _pruned(index, qcoef, tops, cascade: Cascade, stats: SearchStats, threads, progress):
    """The pruned search of every query (:func:`~nfdmatch.search.engine.search_block`) over
    the index's search table, its work counted in ``stats``; returns the table (it holds the
    descriptors of the rows found)."""
    table = index.search_table()
    stats.cell_count = table.n_cells
    answered = 0

    def done(qi, work):
        nonlocal answered
        answered += 1
        if progress is not None:
            progress(answered, len(tops))

    work = search_block(table, qcoef, feature_vector(qcoef), tops, cascade, threads=threads, done=done)
    for key in ("exact", "truncated", "fine", "scanned", "cells"):
        setattr(stats, key, getattr(work, key))
    stats.bytes_read = table.bytes_read
    return table


def without_self(
    index: Any, queries: Sequence[Curve], results: list[list[RankedMatch]], top: int | None
) -> list[list[RankedMatch]]:
    """Each query's matches without its own curve (:func:`~nfdmatch.search.knn.drop_self`),
    at most ``top``: the answer of a search asked for ``top + 1``."""
    rule = self_rule(getattr(index, "locate", None))
    return [drop_self(q.id, found, top, rule=rule) for q, found in zip(queries, results)]


def ranked_rows(index: Any, tops: Sequence[BestRows], top: int | None) -> list[list[RankedMatch]]:
    """Each :class:`~nfdmatch.search.engine.BestRows` as the matches :func:`search_index`
    returns: sorted by distance, distances within ``TIE`` by id, at most ``top``
    (:func:`rank_rows`, which orders ``tops`` in place)."""
    rank_rows(index, tops, top)
    # every query's ids in one read (a read of strings costs the same for one row or many)
    found = np.concatenate([tk.rows for tk in tops]) if tops else np.zeros(0, dtype=np.int64)
    every_id = index.ids_at(found) if len(found) else []
    results, at = [], 0
    for tk in tops:
        ids, at = every_id[at : at + len(tk.rows)], at + len(tk.rows)
        shift, flipped, mirrored = tk.extra["shift"].tolist(), tk.extra["reversed"], tk.extra["mirrored"]
        results.append(
            [
                RankedMatch(
                    rank=i + 1,
                    id=ids[i],
                    distance=d,
                    shift=shift[i],
                    reversed=bool(flipped[i]),
                    mirrored=bool(mirrored[i]),
                    row=row,
                )
                for i, (d, row) in enumerate(zip(tk.dist.tolist(), tk.rows.tolist()))
            ]
        )
    return results


def rank_rows(index: Any, tops: Sequence[BestRows], top: int | None = None) -> None:
    """Order each :class:`~nfdmatch.search.engine.BestRows` of ``tops`` in place as
    :func:`ranked_rows` does (by distance, distances within ``TIE`` by id), keeping at most
    ``top``: its rows, distances and ``extra`` permuted. Ids are read only for the queries
    with such a tie (rare: duplicate curves)."""
    orders, tied = [], []
    for qi, tk in enumerate(tops):
        key = np.round(tk.dist / TIE)
        order = np.argsort(key, kind="stable")
        if len(order) > 1 and (key[order[1:]] == key[order[:-1]]).any():
            tied.append(qi)
        orders.append((key, order))
    if tied:
        ids = index.ids_at(np.concatenate([tops[qi].rows for qi in tied]))
        at = 0
        for qi in tied:
            key, m = orders[qi][0], len(tops[qi].rows)
            mine, at = ids[at : at + m], at + m
            orders[qi] = (key, np.array(sorted(range(m), key=lambda i: (key[i], mine[i])), dtype=np.int64))
    for tk, (_, order) in zip(tops, orders):
        if top is not None:
            order = order[:top]
        tk.rows, tk.dist = tk.rows[order], tk.dist[order]
        tk.extra = {key: v[order] for key, v in tk.extra.items()}


def recompute_reported(
    index: Any,
    queries: np.ndarray,
    tops: Sequence[BestRows],
    search: Callable[..., dict[str, np.ndarray]],
    *,
    direction: str,
    mirror: bool,
    weights: ArrayLike | None,
    tables: Any = None,
) -> None:
    """Replace the distances, shifts and flags of the rows the queries found by a full
    computation of each: refined at every candidate shift, whatever the threshold was when
    the search met the row.

    The search skips the refinement of rows that cannot beat its threshold, so a row's
    figures there depend on the moment it was met (on ``top`` and the other rows). Here
    each reported row is computed alone by the process's kernels
    (:mod:`nfdmatch.matching.kernels`: a row's digits do not depend on the other rows of a
    call, nor on the threads), so the printed digits are the same run to run on one
    install, whatever ``top``, ``max_distance`` and the other queries; two kinds of kernels
    agree to ~1e-15. Rows pushed past ``max_distance`` are dropped as the search would have.
    A query's rows are computed in pieces of up to ``EXHAUSTIVE_ROWS``, each piece's
    descriptors read for it alone (memory stays bounded however many rows match).

    queries : (Q, K, 3) descriptors; tops : Q :class:`BestRows`; search : the method's
    search (``exact_search`` or ``paper_search``); tables : None, one search table for
    every query, or one per query (or None): the descriptors come from the query's table
    (the search's, already read) when it holds them all, else from the index (a scattered
    read: up to a whole HDF5 chunk per row).
    """
    per_query = tables if isinstance(tables, (list, tuple)) else [tables] * len(tops)
    for qi, tk in enumerate(tops):
        if not len(tk.rows):
            continue
        order = np.argsort(tk.rows, kind="stable")
        rows, positions = tk.rows[order], tk.extra["position"][order]
        table = per_query[qi]
        from_table = table is not None and positions.min() >= 0
        pieces = []
        for a in range(0, len(rows), EXHAUSTIVE_ROWS):
            b = min(len(rows), a + EXHAUSTIVE_ROWS)
            if from_table:
                coefficients = table.coefficients_at_positions(positions[a:b])
            else:
                coefficients = index.coefficients_at(rows[a:b])
            pieces.append(
                search(queries[qi], coefficients, index.samples, direction=direction, mirror=mirror, weights=weights)
            )
        r = {key: np.concatenate([part[key] for part in pieces]) for key in pieces[0]}
        keep = r["distance"] <= (np.inf if tk.max_distance is None else tk.max_distance)
        tk.rows, tk.dist = rows[keep], r["distance"][keep]
        tk.extra = {key: (positions if key == "position" else r[key])[keep] for key in tk.extra}


def exhaustive_rows(
    qcoef: np.ndarray,
    tops: Sequence[BestRows],
    chunks: Iterable[tuple[int, np.ndarray]],
    search: Callable[..., dict[str, np.ndarray]],
    samples: int,
    *,
    direction: str,
    mirror: bool,
    weights: ArrayLike | None = None,
    progress: Callable[[int, int], None] | None = None,
    total: int | None = None,
) -> tuple[int, int]:
    """Every exact distance between the queries and the rows of ``chunks`` (no bound
    consulted): ``chunks`` yields ``(first row, (m, K, 3) descriptors)`` in order; each
    query's distances go into its :class:`BestRows` in ``tops``. Returns ``(distances,
    bytes read)``. ``progress(rows done, total)`` after each chunk."""
    done = nbytes = 0
    for start, coefficients in chunks:
        nbytes += coefficients.nbytes
        rows = np.arange(start, start + len(coefficients))
        for qi, tk in enumerate(tops):
            for a in range(0, len(rows), EXHAUSTIVE_ROWS):
                r = search(
                    qcoef[qi],
                    coefficients[a : a + EXHAUSTIVE_ROWS],
                    samples,
                    direction=direction,
                    mirror=mirror,
                    weights=weights,
                )
                tk.add(r["distance"], rows[a : a + EXHAUSTIVE_ROWS], r)
        done += len(rows)
        if progress is not None:
            progress(done, total)
    return done * len(tops), nbytes
