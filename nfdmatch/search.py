"""Exact k nearest curves: lower-bound pruning, then exact distances in batches, over an
index file or curves held in memory."""

from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np

from .descriptors import DEFAULT_HARMONICS, DEFAULT_SAMPLES, DEFAULT_SCALE, descriptors
from .errors import ParameterError
from .matching import exact_search, paper_search

__all__ = ["rank_curves", "search_index", "distance_matrix", "similarity_order", "SearchStats", "BATCH_ROWS", "CHUNK_ROWS"]

#: rows matched per vectorized batch: bounds the (rows x shifts x 9) working set
BATCH_ROWS = 2048


def rank_curves(query, curves, *, top: int | None = None, max_distance: float | None = None,
                samples: int = DEFAULT_SAMPLES, harmonics: int = DEFAULT_HARMONICS,
                scale: str = DEFAULT_SCALE, method: str = "exact", direction: str = "invariant",
                mirror: bool = False, weights=None) -> list[dict]:
    """Rank ``curves`` by distance to ``query``.

    Parameters
    ----------
    query : :class:`~nfdmatch.curve.Curve` (or (n, 3) array).
    curves : sequence of :class:`~nfdmatch.curve.Curve`.
    top : keep the best ``top`` (all when None).
    max_distance : drop matches farther than this.
    Other parameters as in :func:`nfdmatch.distance`.

    Returns
    -------
    list of dicts ``{rank, match, distance, shift, reversed, mirrored, row}`` sorted by
    distance, ties broken by id so the order is deterministic; ``rank`` is 1-based, ``row``
    the match's position in ``curves``.
    """
    from .curve import Curve

    if not isinstance(query, Curve):
        query = Curve(query, id="<query>")
    if not curves:
        if top is not None and top < 1:
            raise ParameterError(f"top must be at least 1, got {top}")
        descriptors(query, samples=samples, harmonics=harmonics, scale=scale)   # validates
        return []
    memory = MemoryIndex(curves, samples=samples, harmonics=harmonics, scale=scale)
    results, _ = search_index(memory, [query], top=top if top is not None or max_distance is not None
                              else len(curves), max_distance=max_distance, method=method,
                              direction=direction, mirror=mirror, weights=weights, prune=weights is None)
    return results[0]


def distance_matrix(curves, *, samples: int = DEFAULT_SAMPLES, harmonics: int = DEFAULT_HARMONICS,
                    scale: str = DEFAULT_SCALE, method: str = "exact", direction: str = "invariant",
                    mirror: bool = False, weights=None, progress=None) -> np.ndarray:
    """All-pairs distances of ``curves``.

    Parameters
    ----------
    curves : sequence of N :class:`~nfdmatch.curve.Curve` or (n_i, 3) arrays.
    progress : optional callable ``progress(pairs_done, pairs_total)``.
    Other parameters as in :func:`nfdmatch.distance`.

    Returns
    -------
    (N, N) float64, symmetric with a zero diagonal: entry ``(i, j)`` for ``i < j`` is
    ``distance(curves[i], curves[j])`` and is mirrored below the diagonal. The exact
    distance is symmetric in itself (to ~1e-9); the paper's step is not, and its matrix
    takes the row curve as the reference.

    One vectorized call per row against all later rows (in batches of :data:`BATCH_ROWS`),
    N (N - 1) / 2 pairs.
    """
    from .descriptors import descriptors_batch

    if method not in ("exact", "paper"):
        raise ParameterError(f"method must be exact or paper, got {method!r}")
    batch = descriptors_batch(curves, samples=samples, harmonics=harmonics, scale=scale)
    N = len(batch)
    matrix = np.zeros((N, N))
    search = exact_search if method == "exact" else paper_search
    total, done = N * (N - 1) // 2, 0
    for i in range(N - 1):
        # at most BATCH_ROWS rows per call: bounds the working set (rows x shifts x 9)
        for start in range(i + 1, N, BATCH_ROWS):
            stop = min(start + BATCH_ROWS, N)
            r = search(batch.coefficients[i], batch.coefficients[start:stop], samples, weights=weights,
                       direction=direction, mirror=mirror)
            matrix[i, start:stop] = r["distance"]
        done += N - 1 - i
        if progress is not None:
            progress(done, total)
    return matrix + matrix.T


def similarity_order(matrix: np.ndarray) -> np.ndarray:
    """An order of the curves that puts similar ones next to each other (for pictures).

    Parameters
    ----------
    matrix : (N, N) float, symmetric distances.

    Returns
    -------
    (N,) int64 permutation: the leaves of the average-linkage tree (UPGMA), each merge
    placing the earlier cluster first; ties broken by position, so the order is
    deterministic. O(N^2) memory, N - 1 merges of O(N^2) numpy work each.
    """
    D = np.array(matrix, dtype=np.float64)
    N = len(D)
    if D.shape != (N, N):
        raise ParameterError(f"expected a square matrix, got shape {D.shape}")
    if N <= 2:
        return np.arange(N, dtype=np.int64)
    np.fill_diagonal(D, np.inf)
    sizes = np.ones(N)
    members = [[i] for i in range(N)]
    alive = np.ones(N, dtype=bool)
    for _ in range(N - 1):
        flat = int(np.argmin(D))
        a, b = divmod(flat, N)
        a, b = min(a, b), max(a, b)
        # Lance-Williams update for the average linkage: the merged cluster lives at a
        merged = (sizes[a] * D[a] + sizes[b] * D[b]) / (sizes[a] + sizes[b])
        merged[~alive] = np.inf
        D[a], D[:, a] = merged, merged
        D[a, a] = np.inf
        D[b], D[:, b] = np.inf, np.inf
        alive[b] = False
        sizes[a] += sizes[b]
        members[a] = members[a] + members[b]
        members[b] = []
    return np.array(members[int(np.flatnonzero(alive)[0])], dtype=np.int64)


# --------------------------------------------------------------------------- index search

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

    from .descriptors import descriptors_batch
    from .matching import invariants

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


class MemoryIndex:
    """Curves held in memory with the same reading interface as :class:`nfdmatch.index.Index`
    (``samples``, ``harmonics``, ``scale``, ``n_curves``, ``iter_chunks``, ``ids_at``), so
    that :func:`search_index` serves both ``rank`` (no index file) and ``query``."""

    def __init__(self, curves, *, samples: int = DEFAULT_SAMPLES, harmonics: int = DEFAULT_HARMONICS,
                 scale: str = DEFAULT_SCALE):
        from .descriptors import descriptors_batch
        from .matching import invariants

        self.samples, self.harmonics, self.scale = samples, harmonics, scale
        batch = descriptors_batch(curves, samples=samples, harmonics=harmonics, scale=scale)
        self._ids = [c.id for c in curves]
        self._rows = {"coefficients": batch.coefficients,
                      **{f"inv_{k}": v.reshape(len(curves), -1) for k, v in invariants(batch.coefficients).items()}}
        self.n_curves = len(curves)

    def iter_chunks(self, rows: int = CHUNK_ROWS, columns=None, *, upcast: bool = True):
        for start in range(0, self.n_curves, rows):
            yield start, {k: v[start:start + rows] for k, v in self._rows.items()
                          if columns is None or k in columns}

    def ids_at(self, rows) -> list[str]:
        return [self._ids[int(r)] for r in rows]

    def coefficients_at(self, rows) -> np.ndarray:
        return self._rows["coefficients"][np.asarray(rows, dtype=np.int64)]
