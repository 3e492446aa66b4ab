"""All-pairs distance matrices of curves, and an order that groups similar curves."""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

from ..matching import EXACT, METHODS, MatchParameters, exact_search, paper_search
from ..matching.fused import fused_rows, require_exact
from ..matching.statistics import curve_statistics
from ..errors import ParameterError
from .workers import run_tasks

if TYPE_CHECKING:
    from numpy.typing import ArrayLike, NDArray

    from ..curve import Curve

#: rows matched per vectorized batch: bounds the (rows x shifts x 9) working set
BATCH_ROWS = 2048
#: runs of rows handed to worker processes (of about as many pairs each: progress, and the
#: balance between workers)
_MATRIX_TASKS = 64
#: pairs from which worker processes are forked (fewer take less than a fork costs)
_FORK_FROM_PAIRS = 20_000


def distance_matrix(
    curves: Sequence[Curve | np.ndarray],
    *,
    progress: Callable[[int, int], None] | None = None,
    processes: int | None = None,
    elastic: bool = False,
    **parameters: Any,
) -> NDArray[np.float64]:
    """All-pairs distances of ``curves``.

    Parameters
    ----------
    curves : sequence of N :class:`~nfdmatch.curve.Curve` or (n_i, 3) arrays.
    progress : optional callable ``progress(pairs_done, pairs_total)``.
    processes : forked worker processes sharing the rows (None: the cores; 1: this
        process, each row's call split over the kernels' threads). Workers are used when
        this process may fork (:func:`nfdmatch._fork.can_fork`); every entry is the same
        either way (each is computed by itself).
    elastic : the fused distance of the elastic stage (rigid, elastic and statistics terms at
        each pair's rigid optimum: :func:`nfdmatch.matching.fused.fused_rows`) instead of the
        exact distance (``matrix --elastic``; docs/elastic.md).
    samples, harmonics, scale, method, direction, mirror, weights : by keyword, as in
        :func:`nfdmatch.distance` (the fields of :class:`~nfdmatch.matching.MatchParameters`).

    Returns
    -------
    (N, N) float64, symmetric with a zero diagonal: entry ``(i, j)`` for ``i < j`` is
    ``distance(curves[i], curves[j])`` and is mirrored below the diagonal. The exact
    distance is symmetric in itself (to ~1e-9); the paper's step is not, and its matrix
    takes the row curve as the reference.

    One vectorized call per row against all later rows (in batches of :data:`BATCH_ROWS`),
    N (N - 1) / 2 pairs.
    """
    from ..descriptors import descriptors_batch

    p = MatchParameters(**parameters)
    if p.method not in METHODS:
        raise ParameterError(f"method must be exact or paper, got {p.method!r}")
    if elastic:
        require_exact(p.method)
    batch = descriptors_batch(curves, **p.descriptor)
    statistics = curve_statistics(batch.coefficients) if elastic else None
    N = len(batch)
    matrix = np.zeros((N, N))
    search = exact_search if p.method == EXACT else paper_search
    total, done = N * (N - 1) // 2, 0

    def collect(number, values):
        nonlocal done
        a, b = tasks[number]
        at = 0
        for i in range(a, b):
            matrix[i, i + 1 :] = values[at : at + N - 1 - i]
            at += N - 1 - i
        done += at
        if progress is not None:
            progress(done, total)

    processes = (os.cpu_count() or 1) if processes is None else int(processes)
    spread = processes > 1 and total >= _FORK_FROM_PAIRS
    tasks = _row_blocks(N, _MATRIX_TASKS if spread else N)
    rows = lambda task, _: _upper_rows(batch, search, p, task, statistics)  # noqa: E731
    run_tasks(tasks, rows, collect, processes if spread else 1)
    return matrix + matrix.T


def cross_distances(
    A: np.ndarray,
    B: np.ndarray,
    samples: int,
    *,
    processes: int = 1,
    direction: str = "invariant",
    mirror: bool = False,
    weights: ArrayLike | None = None,
) -> NDArray[np.float64]:
    """(len A, len B) exact distances between two sets of stored descriptors ``A`` (m, K, 3)
    and ``B`` (n, K, 3) (complex; each row against every column, in batches of
    :data:`BATCH_ROWS` as :func:`distance_matrix` does, over ``processes`` forked workers
    when there are enough pairs). What an object's loops are compared with (docs/objects.md)."""
    A, B = np.asarray(A), np.asarray(B)
    m, n = len(A), len(B)
    out = np.zeros((m, n))
    if m == 0 or n == 0:
        return out
    spread = processes > 1 and m * n >= _FORK_FROM_PAIRS
    edges = np.linspace(0, m, (min(m, _MATRIX_TASKS) if spread else 1) + 1).astype(int)
    tasks = [(int(a), int(b)) for a, b in zip(edges[:-1], edges[1:]) if b > a]

    def compute(task, _threads):
        a, b = task
        rows = np.empty((b - a, n))
        for i in range(a, b):
            for start in range(0, n, BATCH_ROWS):
                r = exact_search(
                    A[i], B[start : start + BATCH_ROWS], samples, weights=weights, direction=direction, mirror=mirror
                )
                rows[i - a, start : start + BATCH_ROWS] = r["distance"]
        return rows

    def collect(number, rows):
        a, b = tasks[number]
        out[a:b] = rows

    run_tasks(tasks, compute, collect, processes if spread else 1)
    return out


def _upper_rows(batch, search, p: MatchParameters, task, statistics=None) -> np.ndarray:
    """Rows ``a..b-1`` of the upper triangle (task ``(a, b)``), each against every later
    curve of ``batch``, concatenated; with ``statistics`` ((N, LENGTH): the curves'
    statistics vectors), the fused distances of the elastic stage."""
    a, b = task
    N = len(batch)
    out = []
    for i in range(a, b):
        # at most BATCH_ROWS rows per call: bounds the working set (rows x shifts x 9)
        for start in range(i + 1, N, BATCH_ROWS):
            r = search(
                batch.coefficients[i],
                batch.coefficients[start : min(start + BATCH_ROWS, N)],
                p.samples,
                weights=p.weights,
                direction=p.direction,
                mirror=p.mirror,
            )
            if statistics is None:
                out.append(r["distance"])
                continue
            stop = min(start + BATCH_ROWS, N)
            terms = fused_rows(
                batch.coefficients[i], batch.coefficients[start:stop], r, p.samples,
                query_statistics=statistics[i], row_statistics=statistics[start:stop], direction=p.direction,
                mirror=p.mirror, weights=p.weights,
            )  # fmt: skip
            out.append(terms.fused)
    return np.concatenate(out) if out else np.zeros(0)


def _row_blocks(N: int, parts: int) -> list[tuple[int, int]]:
    """Rows 0..N-2 as up to ``parts`` runs ``(a, b)`` of about as many pairs each (row i
    has N - 1 - i pairs: the runs grow towards the end)."""
    if N < 2:
        return []
    pairs_before = np.concatenate([[0], np.cumsum(np.arange(N - 1, 0, -1))])  # (N,)
    cuts = np.searchsorted(pairs_before, np.linspace(0, pairs_before[-1], parts + 1)[1:-1])
    edges = np.unique(np.concatenate([[0], cuts, [N - 1]]))
    return [(int(a), int(b)) for a, b in zip(edges[:-1], edges[1:])]


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
