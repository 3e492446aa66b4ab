"""Cells over the invariant feature space: the structure that lets a search skip rows unread.

The invariant lower bound of a row is a Euclidean distance between feature vectors
(:mod:`nfdmatch.search.bounds`), so rows can be grouped by where their features lie: a
cell with centre ``c`` and radius ``r`` (the largest distance of a member's features to
``c``) holds only rows whose bound is at least ``|f(q) - c| - r`` (triangle inequality).
A search visits cells in the order of that cell bound and never opens a cell whose bound
exceeds its current k-th distance.

Cells come from k-means in two levels (coarse cells, then each coarse cell split), seeded,
so the same rows always give the same cells. Their quality only affects speed: any
partition with correct radii keeps the search exact.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["Cells", "build_cells", "ROWS_PER_CELL"]

#: target rows per cell: small enough that a query near a tight family reads little, large
#: enough that the cell centres (one distance each per query) stay a small fraction of the work
ROWS_PER_CELL = 128
#: rows assigned to centres per block (bounds the (rows x centres) float32 matrix)
_ASSIGN_BLOCK = 32768
_COARSE_ITERATIONS = 8
_FINE_ITERATIONS = 5
#: rows a coarse k-means is trained on (a sample: the coarse level only has to spread rows)
_COARSE_SAMPLE = 65536
#: rows per centre a fine k-means is trained on (a sample; every row is then assigned once,
#: and the radii are measured over every member, so the cells stay exact whatever the sample)
_FINE_SAMPLE_PER_CELL = 32


@dataclass(frozen=True)
class Cells:
    """A partition of the rows into cells, stored in cell-major order.

    Attributes
    ----------
    row : (N,) int64, the index row at each position; cell ``c`` holds positions
        ``start[c]:start[c + 1]``, rows ascending within a cell.
    start : (C + 1,) int64, ``start[0] = 0``, ``start[C] = N``.
    centre : (C, D) float64, the mean of the members' features.
    radius : (C, 2) float64, the largest distance of a member's features to the centre in
        the two feature subspaces (columns ``[:split]`` and ``[split:]``), rounded up.
    """

    row: np.ndarray
    start: np.ndarray
    centre: np.ndarray
    radius: np.ndarray

    @property
    def count(self) -> int:
        return len(self.start) - 1


def _assign(X: np.ndarray, centres: np.ndarray) -> np.ndarray:
    """(m,) int64 nearest centre of each row; X (m, D) float32, centres (c, D) float32."""
    sq = np.einsum("ij,ij->i", centres, centres)
    labels = np.empty(len(X), dtype=np.int64)
    minus_twice = np.ascontiguousarray((centres * np.float32(-2.0)).T)  # exact: a power of two
    for a in range(0, len(X), _ASSIGN_BLOCK):
        d = X[a : a + _ASSIGN_BLOCK] @ minus_twice
        d += sq[None, :]
        labels[a : a + _ASSIGN_BLOCK] = np.argmin(d, axis=1)
    return labels


def _kmeans(X: np.ndarray, k: int, rng: np.random.Generator, iterations: int, sample: int | None = None) -> np.ndarray:
    """(m,) int64 labels of Lloyd's k-means (random distinct rows as the start), trained on
    ``sample`` rows when given, then every row assigned once."""
    m = len(X)
    k = min(k, m)
    if k <= 1:
        return np.zeros(m, dtype=np.int64)
    train = X if sample is None or sample >= m else X[np.sort(rng.choice(m, sample, replace=False))]
    centres = train[rng.choice(len(train), k, replace=False)].astype(np.float32)
    for _ in range(iterations):
        labels = _assign(train, centres)
        counts = np.bincount(labels, minlength=k)
        filled = counts > 0
        # sums by label, a column at a time (np.add.at, and reduceat along axis 0, are far slower)
        sums = np.empty((k, X.shape[1]))
        for j in range(X.shape[1]):
            sums[:, j] = np.bincount(labels, weights=train[:, j], minlength=k)
        centres[filled] = (sums[filled] / counts[filled, None]).astype(np.float32)
    return _assign(X, centres)


def build_cells(features: np.ndarray, split: int, *, rows_per_cell: int = ROWS_PER_CELL, seed: int = 0) -> Cells:
    """Partition rows into cells of about ``rows_per_cell`` rows by their features.

    Parameters
    ----------
    features : (N, D) float32, the rows' invariant features (the search bounds use exactly
        these values).
    split : columns ``[:split]`` and ``[split:]`` are two feature vectors whose distances
        are bounds on their own; each gets its own radius.
    rows_per_cell, seed : cell size target; the k-means seed (fixed: same rows, same cells).

    Returns
    -------
    :class:`Cells`. Cost: a few passes of (rows x sqrt(cells)) float32 products.
    """
    X = np.ascontiguousarray(features, dtype=np.float32)
    N, D = X.shape
    if N == 0:
        return Cells(np.zeros(0, np.int64), np.zeros(1, np.int64), np.zeros((0, D)), np.zeros((0, 2)))
    rng = np.random.default_rng(seed)
    total = max(1, int(round(N / rows_per_cell)))
    coarse = max(1, int(round(np.sqrt(total))))
    coarse_labels = _kmeans(X, coarse, rng, _COARSE_ITERATIONS, sample=_COARSE_SAMPLE)
    members = []
    by_coarse = np.argsort(coarse_labels, kind="stable")
    bounds = np.searchsorted(coarse_labels[by_coarse], np.arange(coarse + 1))
    for g in range(coarse):
        rows = by_coarse[bounds[g] : bounds[g + 1]]
        if len(rows) == 0:
            continue
        k = max(1, int(round(len(rows) / rows_per_cell)))
        fine = _kmeans(X[rows], k, rng, _FINE_ITERATIONS, sample=_FINE_SAMPLE_PER_CELL * k)
        order = np.argsort(fine, kind="stable")  # rows stay ascending within a cell
        cuts = np.searchsorted(fine[order], np.arange(k + 1))
        for j in range(k):
            if cuts[j + 1] > cuts[j]:
                members.append(rows[order[cuts[j] : cuts[j + 1]]])
    sizes = np.array([len(m) for m in members], dtype=np.int64)
    start = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
    row = np.concatenate(members).astype(np.int64)
    del members
    F = X[row]
    # the members' mean, a column at a time (reduceat along axis 0 is ten times slower)
    centre = np.empty((len(sizes), D))
    for j in range(D):
        centre[:, j] = np.add.reduceat(F[:, j].astype(np.float64), start[:-1])
    centre /= sizes[:, None]
    cell_of = np.repeat(np.arange(len(sizes)), sizes)
    # squared distances to the centre per part, in blocks (no (N, D) float64 copy)
    d2 = np.empty((N, 2))
    for a in range(0, N, _ASSIGN_BLOCK):
        diff = F[a : a + _ASSIGN_BLOCK].astype(np.float64) - centre[cell_of[a : a + _ASSIGN_BLOCK]]
        d2[a : a + _ASSIGN_BLOCK, 0] = np.einsum("ij,ij->i", diff[:, :split], diff[:, :split])
        d2[a : a + _ASSIGN_BLOCK, 1] = np.einsum("ij,ij->i", diff[:, split:], diff[:, split:])
    radius = np.sqrt(np.maximum.reduceat(d2, start[:-1], axis=0))
    # rounded up: the float64 arithmetic above may land a few ulps below the true radius
    radius = radius * (1 + 1e-12) + 1e-12
    return Cells(row, start, centre, radius)
