"""Exact k nearest curves of an index: invariant lower bounds prune rows, exact distances in batches."""

from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np

from ..errors import ParameterError
from ..matching import exact_search, paper_search
from .matrix import BATCH_ROWS

#: rows read from the index at a time: bounds memory for indexes larger than RAM
CHUNK_ROWS = 65536
#: queries whose bounds are computed together (one GEMM per feature); bounds the (Q x rows) matrix
QUERY_GROUP = 64
#: a bound prunes a row only when it exceeds the k-th distance by this much: the features
#: are stored as float32 and the squared distances come from a GEMM
_PRUNE_RELATIVE, _PRUNE_ABSOLUTE = 1e-5, 1e-6
_FEATURES = ("inv_norm", "inv_sv", "inv_block")
#: distances closer than this are ties, ordered by id (below the pipeline's numerical noise)
_TIE = 1e-9
#: up to this many queries, descriptors are read row by row as needed instead of by chunk
_LAZY_QUERIES = 4


def _margin(threshold: float) -> float:
    """The distance a bound must exceed to prune against ``threshold`` (rounding slack)."""
    return threshold * (1 + _PRUNE_RELATIVE) + _PRUNE_ABSOLUTE


@dataclass
class SearchStats:
    """What a search did: ``queries``, ``rows`` (index rows per query), ``exact`` (exact
    distances computed, all queries), ``seconds``."""

    queries: int = 0
    rows: int = 0
    exact: int = 0
    seconds: float = 0.0

    @property
    def exact_fraction(self) -> float:
        """Fraction of (query, row) pairs that needed an exact distance."""
        total = self.queries * self.rows
        return self.exact / total if total else 0.0


def _lower_bounds(qf: dict, rf: dict, r_norms: dict | None = None) -> np.ndarray:
    """(Q, m) max of the three invariant lower bounds; features (Q, d_t) and (m, d_t) per type.

    Squared distances as |q|^2 + |r|^2 - 2 q.r (one GEMM each), accumulated in place: the
    (Q, m) matrices are the memory traffic of this step. ``r_norms`` caches |r|^2 per type.
    """
    best = None
    for key in _FEATURES:
        q, r = qf[key], rf[key]
        rn = r_norms[key] if r_norms is not None else np.einsum("ij,ij->i", r, r)
        d2 = q @ r.T
        d2 *= -2.0
        d2 += rn[None, :]
        d2 += np.einsum("ij,ij->i", q, q)[:, None]
        if best is None:
            best = d2
        else:
            np.maximum(best, d2, out=best)
    np.maximum(best, 0.0, out=best)
    return np.sqrt(best, out=best)


class _TopK:
    """The best rows seen so far for one query: every row within the k-th distance (ties kept)."""

    def __init__(self, k: int | None, max_distance: float | None):
        self.k, self.max_distance = k, max_distance
        self.dist = np.zeros(0)
        self.rows = np.zeros(0, dtype=np.int64)
        self.extra = {key: np.zeros(0, dtype=t) for key, t in
                      (("shift", float), ("reversed", bool), ("mirrored", bool))}

    def threshold(self) -> float:
        limit = np.inf if self.max_distance is None else self.max_distance
        if self.k is not None and len(self.dist) >= self.k:
            limit = min(limit, float(np.partition(self.dist, self.k - 1)[self.k - 1]))
        return limit

    def add(self, dist, rows, result):
        keep = dist <= (np.inf if self.max_distance is None else self.max_distance)
        self.dist = np.concatenate([self.dist, dist[keep]])
        self.rows = np.concatenate([self.rows, rows[keep]])
        for key in self.extra:
            self.extra[key] = np.concatenate([self.extra[key], result[key][keep]])
        t = self.threshold()
        if np.isfinite(t):
            inside = self.dist <= t + _TIE
            self.dist, self.rows = self.dist[inside], self.rows[inside]
            self.extra = {key: v[inside] for key, v in self.extra.items()}


def search_index(index, queries, *, top: int | None = 10, max_distance: float | None = None,
                 method: str = "exact", direction: str = "invariant", mirror: bool = False,
                 prune: bool = True, chunk_rows: int = CHUNK_ROWS, progress=None, weights=None,
                 threads: int | None = None):
    """k nearest curves of an index for each query curve, exactly.

    Parameters
    ----------
    index : an open :class:`nfdmatch.index.Index`.
    queries : sequence of :class:`~nfdmatch.curve.Curve`; descriptors are computed with the
        index's own samples, harmonics and scale.
    top : k (None: every row within ``max_distance``).
    max_distance : only matches at most this far.
    method, direction, mirror : as in :func:`nfdmatch.distance`.
    prune : False computes every exact distance (the reference the pruned search must equal).
    chunk_rows : index rows held in memory at a time.
    progress : optional callable ``progress(rows_done, rows_total)``.

    Returns
    -------
    ``(results, stats)``: ``results[i]`` lists query i's matches as dicts ``{rank, match,
    distance, shift, reversed, mirrored, row}`` (``row``: the match's row in the index)
    sorted by distance then id; ``stats`` a :class:`SearchStats`.

    Per query and chunk: the lower bound of every row at once (three small GEMMs over the
    invariant features), then exact distances in vectorized batches in bound order,
    stopping when the next bound exceeds the current k-th distance. No false dismissals:
    the bounds never exceed the exact distance.
    """
    import time

    from ..descriptors import descriptors_batch
    from ..matching import invariants

    if top is None and max_distance is None:
        raise ParameterError("give top or max_distance (or both)")
    if top is not None and top < 1:
        raise ParameterError(f"top must be at least 1, got {top}")
    if method not in ("exact", "paper"):
        raise ParameterError(f"method must be exact or paper, got {method!r}")
    threads = threads or min(os.cpu_count() or 1, 4)
    t0 = time.perf_counter()
    batch = descriptors_batch(queries, samples=index.samples, harmonics=index.harmonics, scale=index.scale)
    qcoef = batch.coefficients
    if weights is not None and prune:
        raise ParameterError("pruning uses unweighted bounds: pass prune=False with weights")
    qfeat = {f"inv_{k}": v.reshape(len(queries), -1) for k, v in invariants(qcoef).items()}
    tops = [_TopK(top, max_distance) for _ in queries]
    search = exact_search if method == "exact" else paper_search
    stats = SearchStats(queries=len(queries), rows=index.n_curves)
    n = index.samples
    done = 0
    # few queries touch few rows: read descriptors only for the rows that need an exact distance
    lazy = len(queries) <= _LAZY_QUERIES and hasattr(index, "coefficients_at")
    columns = _FEATURES if lazy else ("coefficients",) + _FEATURES
    for start, chunk in index.iter_chunks(chunk_rows, columns, upcast=False):
        m = len(chunk[_FEATURES[0]])
        rfeat = {k: chunk[k].reshape(m, -1).astype(np.float64) for k in _FEATURES}
        rows_global = np.arange(start, start + m)
        r_norms = {k: np.einsum("ij,ij->i", v, v) for k, v in rfeat.items()}
        for g in range(0, len(queries), QUERY_GROUP):
            group = range(g, min(g + QUERY_GROUP, len(queries)))
            lb = _lower_bounds({k: v[group.start:group.stop] for k, v in qfeat.items()}, rfeat, r_norms) \
                if prune else np.zeros((len(group), m))
            # each query's `first` lowest bounds, for all queries of the group in one call
            first = min(max(32, 2 * (top or 16)), m)
            lowest = np.argpartition(lb, first - 1, axis=1)[:, :first] if first < m else None

            def _answer(qi, bounds):
                n_exact = 0
                tk = tops[qi]
                size = max(32, 2 * (top or 16))
                pending = None
                if lowest is not None and not np.isfinite(tk.threshold()):
                    # start from the precomputed lowest bounds; the rest is filtered once the
                    # first batch has set a k-th distance
                    pending = lowest[qi - group.start]
                    cand = pending
                else:
                    cand = np.flatnonzero(bounds <= _margin(tk.threshold()))
                while len(cand):
                    if len(cand) > size:       # the `size` lowest bounds, without sorting them all
                        first = np.argpartition(bounds[cand], size - 1)[:size]
                        rest = np.ones(len(cand), dtype=bool)
                        rest[first] = False
                        take, cand = cand[first], cand[rest]
                    else:
                        take, cand = cand, cand[:0]
                    if prune:
                        take = take[bounds[take] <= _margin(tk.threshold())]
                        if len(take) == 0:
                            break
                    extra = {"refine_below": _margin(tk.threshold())} if method == "exact" and prune else {}
                    rows_b = index.coefficients_at(rows_global[take]) if lazy else chunk["coefficients"][take]
                    r = search(qcoef[qi], rows_b, n, direction=direction, mirror=mirror,
                               weights=weights, **extra)
                    n_exact += len(take)
                    tk.add(r["distance"], rows_global[take], r)
                    if pending is not None:       # first batch done: now every other row
                        seen = np.zeros(len(bounds), dtype=bool)
                        seen[pending] = True
                        cand = np.flatnonzero((bounds <= _margin(tk.threshold())) & ~seen)
                        pending = None
                    elif prune:
                        cand = cand[bounds[cand] <= _margin(tk.threshold())]
                    size = min(size * 2, BATCH_ROWS)
                return n_exact

            work = list(zip(group, lb))
            if threads > 1 and len(work) > 1:
                from concurrent.futures import ThreadPoolExecutor

                from threadpoolctl import threadpool_limits

                # one BLAS thread per query thread: idle OpenBLAS workers spin and steal the cores
                with threadpool_limits(1, user_api="blas"), ThreadPoolExecutor(threads) as pool:        # numpy releases the GIL in big kernels
                    for n_exact in pool.map(lambda item: _answer(item[0], item[1]), work):
                        stats.exact += n_exact
            else:
                for qi, bounds in work:
                    stats.exact += _answer(qi, bounds)
        done += m
        if progress is not None:
            progress(done, index.n_curves)

    results = []
    for tk in tops:
        ids = index.ids_at(tk.rows) if len(tk.rows) else []
        # distances equal to 1e-9 are ties (below the numerical noise of the pipeline): by id
        order = sorted(range(len(ids)), key=lambda i: (round(float(tk.dist[i]) / _TIE), ids[i]))
        if top is not None:
            order = order[:top]
        results.append([{"rank": rank, "match": ids[i], "distance": float(tk.dist[i]),
                         "shift": float(tk.extra["shift"][i]), "reversed": bool(tk.extra["reversed"][i]),
                         "mirrored": bool(tk.extra["mirrored"][i]), "row": int(tk.rows[i])}
                        for rank, i in enumerate(order, start=1)])
    stats.seconds = time.perf_counter() - t0
    return results, stats
