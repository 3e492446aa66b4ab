"""Lower bounds of the exact distance that a search prunes with, cheapest first.

1. **Invariant features** (:func:`feature_vector`): per harmonic the two singular values of
   ``[Re A_k, Im A_k]`` (Mirsky), and the three singular values of all harmonics side by
   side. Each group is unchanged by shift, rotation, reflection and reversal and moves by at
   most the coefficient change, so the Euclidean distance between two curves' feature
   vectors of one group is a lower bound of mu; a row's bound is the larger of the two.
   (The norm bound of format 1 is never larger than the singular-value one: the reverse
   triangle inequality on each harmonic's pair of singular values.)
2. **Cells** (:func:`cell_lower_bounds`): a whole cell of rows at once, from its centre
   and radius; for a self-join, a whole pair of cells at once
   (:func:`cell_pair_lower_bounds`, from both centres and radii).
3. **Truncated harmonics** (:func:`truncated_lower_bounds`): the exact distance over the
   first K' harmonics only, evaluated on a grid of start shifts with a proven slack; it
   never exceeds the full distance (dropping harmonics lowers the objective at every shift
   and rotation) and keeps the coupling between harmonics that the invariants lose.

Every bound here holds for the stored (rounded) values up to the rounding slack it adds
itself; the search compares it with the k-th distance through a small relative margin
(the exact distance is a numerical optimum).
"""

from __future__ import annotations

import numpy as np

from ..matching import INVARIANT

__all__ = [
    "feature_vector",
    "feature_split",
    "head_harmonics",
    "squared_norms",
    "cell_lower_bounds",
    "row_lower_bounds",
    "row_lower_bounds_many",
    "cell_pair_lower_bounds",
    "query_radius",
    "truncated_lower_bounds",
    "truncated_stages",
    "TRUNCATED_HARMONICS",
    "TRUNCATED_GRID",
    "TRUNCATED_STAGES",
]

#: harmonics kept by the truncated bound, and its shift grid (multiple of 4, > 2 K'):
#: on random smooth curves max(truncated, invariant) / exact has median ~0.93 at (4, 24),
#: for ~2 us per row against ~11 us for the exact distance at n = 128 (benchmarks/bench_search.py)
TRUNCATED_HARMONICS = 4
TRUNCATED_GRID = 24
#: the chain of truncated bounds a search applies in turn, (K', grid) each, cheapest first:
#: on 100,000 random smooth curves, of the ~20,000 rows whose invariant bound is below a
#: noisy copy's 10th distance, (4, 24) leaves 400-2,500 and (8, 48) then 25-60 for the exact
#: distance (~2 us, ~5 us and ~16 us per row; docs/performance.md)
TRUNCATED_STAGES = ((TRUNCATED_HARMONICS, TRUNCATED_GRID), (8, 48))
#: the coarse grid of the truncated bound takes every third shift of its fine grid
_COARSE_RATIO = 3
#: float32 and float64 unit roundoff
_U32 = 2.0**-24
_U64 = 2.0**-53
#: rows whose squared norms are computed at a time: bounds the float64 copy, small enough
#: to stay in cache (a 65,536-row block took 3x as long in a new process: page faults)
_NORM_BLOCK = 8192


def head_harmonics(harmonics: int) -> int:
    """K': the harmonics the truncated bound uses, stored per row beside the features."""
    return min(TRUNCATED_HARMONICS, harmonics)


def truncated_stages(harmonics: int, available: int) -> list[tuple[int, int]]:
    """The (K', grid) stages of :data:`TRUNCATED_STAGES` worth applying to descriptors of
    ``harmonics`` harmonics of which ``available`` are at hand: each stage keeps more
    harmonics than the one before and fewer than all (the exact distance is next)."""
    stages, kept = [], 0
    for Kp, grid in TRUNCATED_STAGES:
        Kp = min(Kp, harmonics)
        if kept < Kp <= available and (Kp < harmonics or not stages):
            stages.append((Kp, grid))
            kept = Kp
    return stages


def feature_split(harmonics: int) -> int:
    """Columns of the per-harmonic singular values in a feature vector (2K); the block
    singular values follow."""
    return 2 * harmonics


def feature_vector(coefficients: np.ndarray) -> np.ndarray:
    """Invariant features of normalized descriptors.

    Parameters
    ----------
    coefficients : (..., K, 3) complex, half-bands A_1..A_K.

    Returns
    -------
    (..., 2K + 3) float64: ``invariants()["sv"]`` then ``invariants()["block"]`` (uniform
    weights), the layout of ``/search/features``.
    """
    from ..matching import invariants

    inv = invariants(coefficients)
    return np.concatenate([inv["sv"], inv["block"]], axis=-1)


def squared_norms(features: np.ndarray, split: int) -> np.ndarray:
    """(m, 2) float64 squared norms of the two parts of float32 features (m, D), computed in
    float64 from the float32 values (what :func:`row_lower_bounds` expects)."""
    out = np.empty((len(features), 2))
    for a in range(0, len(features), _NORM_BLOCK):  # blocks: no (m, D) float64 copy
        F = np.asarray(features[a : a + _NORM_BLOCK], dtype=np.float64)
        out[a : a + _NORM_BLOCK, 0] = np.einsum("ij,ij->i", F[:, :split], F[:, :split])
        out[a : a + _NORM_BLOCK, 1] = np.einsum("ij,ij->i", F[:, split:], F[:, split:])
    return out


def cell_lower_bounds(
    query: np.ndarray,
    split: int,
    centre: np.ndarray,
    radius: np.ndarray,
    centre_sqnorm: np.ndarray | None = None,
    *,
    clip: bool = True,
) -> np.ndarray:
    """(C,) float64 lower bound of the invariant bound of every row of each cell (``clip``
    False: before it is raised to 0, so negative for a cell the query lies inside: how deep,
    an order among the cells of bound 0).

    query : (D,) float64 features; centre : (C, D) float64; radius : (C, 2) float64;
    centre_sqnorm : (C, 2) float64, the centres' squared norms in the two subspaces
    (:func:`squared_norms`; a search table keeps them), or None.

    With the norms, the distances come from ``|c|^2 + |q|^2 - 2 c.q`` (one matrix-vector
    product per subspace, no (C, D) difference array: ~2.5x faster), less a proven rounding
    slack: each of the three terms is within gamma_m (|c|^2 + |q|^2) of its value (the dot
    product's error is at most gamma_m |c| |q|), and the two additions add 4 u of it; so
    the result never exceeds the distance to the centre.
    """
    if centre_sqnorm is None:
        d = centre - query[None, :]
        a = np.sqrt(np.einsum("ij,ij->i", d[:, :split], d[:, :split])) - radius[:, 0]
        b = np.sqrt(np.einsum("ij,ij->i", d[:, split:], d[:, split:])) - radius[:, 1]
        out = np.maximum(a, b)
        return np.maximum(out, 0.0, out=out) if clip else out
    out = None
    for lo, hi, col in ((0, split, 0), (split, centre.shape[1], 1)):
        q = query[lo:hi]
        qq = float(q @ q)
        both = centre_sqnorm[:, col] + qq
        d2 = both - 2.0 * (centre[:, lo:hi] @ q)
        slack = (3.0 * _gamma64(hi - lo) + 4.0 * _U64) * 1.01 * both
        d = np.sqrt(np.maximum(d2 - slack, 0.0)) - radius[:, col]
        out = d if out is None else np.maximum(out, d)
    return np.maximum(out, 0.0, out=out) if clip else out


def _gamma64(n: int) -> float:
    """Higham's gamma_n for float64: the relative error bound of an n-term dot product."""
    return n * _U64 / (1 - n * _U64)


def _gamma(n: int) -> float:
    """Bound on the relative error of an n-term float32 dot product (Higham's gamma_n)."""
    return n * _U32 / (1 - n * _U32)


def row_lower_bounds(query: np.ndarray, split: int, features: np.ndarray, sqnorm: np.ndarray) -> np.ndarray:
    """(m,) float64 invariant lower bound of each row, from float32 features in one pass.

    Parameters
    ----------
    query : (D,) float64 features of the query.
    features : (m, D) float32 rows' features; sqnorm : (m, 2) float64, their squared norms
        in the two subspaces (computed in float64 from the float32 values at build time).

    The distances come from ``|x|^2 + |q|^2 - 2 x.q`` with the dot products in float32
    (memory speed); the float32 rounding of q and of the products is subtracted as a proven
    slack (gamma_D |x| |q|), so the result never exceeds the distance between the stored
    features.
    """
    q32 = query.astype(np.float32)
    q64 = q32.astype(np.float64)
    out = None
    for lo, hi, col in ((0, split, 0), (split, features.shape[1], 1)):
        qs = q64[lo:hi]
        qq = float(qs @ qs)
        dots = (features[:, lo:hi] @ q32[lo:hi]).astype(np.float64)
        xn = sqnorm[:, col]
        d2 = xn + qq - 2.0 * dots
        slack = 2.0 * _gamma(hi - lo) * np.sqrt(xn * qq) + 1e-15 * (xn + qq)
        d = np.sqrt(np.maximum(d2 - slack, 0.0))
        out = d if out is None else np.maximum(out, d)
    # q was rounded to float32: its features moved by at most u |q|
    out -= _U32 * float(np.sqrt(q64 @ q64)) * 1.01
    return np.maximum(out, 0.0, out=out)


def row_lower_bounds_many(queries: np.ndarray, split: int, features: np.ndarray, sqnorm: np.ndarray) -> np.ndarray:
    """(m, M) float64: :func:`row_lower_bounds` of each of m queries ((m, D) float64)
    against the same M rows, in one matrix product per feature part (a self-join bounds a
    cell's rows against the rows of other cells at once).

    The same proof as :func:`row_lower_bounds`, row by row: the float32 dot products are
    within gamma_D |x| |q| whatever the summation order, and each query's own float32
    rounding is subtracted as u |q|; so entry (i, j) never exceeds the distance between
    query i's features and row j's stored features.
    """
    Q32 = np.ascontiguousarray(queries, dtype=np.float32)
    Q64 = Q32.astype(np.float64)
    out = None
    for lo, hi, col in ((0, split, 0), (split, features.shape[1], 1)):
        qq = np.einsum("ij,ij->i", Q64[:, lo:hi], Q64[:, lo:hi])
        dots = (Q32[:, lo:hi] @ np.ascontiguousarray(features[:, lo:hi]).T).astype(np.float64)
        xn = sqnorm[:, col]
        d2 = xn[None, :] + qq[:, None] - 2.0 * dots
        d2 -= 2.0 * _gamma(hi - lo) * np.sqrt(xn[None, :] * qq[:, None]) + 1e-15 * (xn[None, :] + qq[:, None])
        d = np.sqrt(np.maximum(d2, 0.0, out=d2), out=d2)
        out = d if out is None else np.maximum(out, d, out=out)
    out -= (_U32 * 1.01) * np.sqrt(np.einsum("ij,ij->i", Q64, Q64))[:, None]
    return np.maximum(out, 0.0, out=out)


def query_radius(queries: np.ndarray, split: int, centre: np.ndarray) -> np.ndarray:
    """(2,) float64: the largest distance of ``queries`` ((m, D) float64 features) to
    ``centre`` ((D,) float64) in the two feature parts, rounded up (as a cell's radius):
    the radius of a cell as seen from its rows' query features (computed from their
    descriptors, not the stored float32 values the stored radius covers)."""
    if len(queries) == 0:
        return np.zeros(2)
    d = np.asarray(queries, dtype=np.float64) - centre[None, :]
    r = np.array(
        [
            np.sqrt(np.einsum("ij,ij->i", d[:, :split], d[:, :split]).max()),
            np.sqrt(np.einsum("ij,ij->i", d[:, split:], d[:, split:]).max()),
        ]
    )
    return r * (1 + 1e-12) + 1e-12


def cell_pair_lower_bounds(
    centre: np.ndarray, reach: np.ndarray, split: int, centres: np.ndarray, radii: np.ndarray
) -> np.ndarray:
    """(C,) float64 lower bound of the invariant bound (the distance between a query's
    features and a row's stored features, what :func:`row_lower_bounds` bounds from below)
    for every query of one cell against every row of each of C cells.

    centre : (D,) float64, the query cell's centre; reach : (2,) float64, the largest
    distance of its queries' features to it per part (:func:`query_radius`);
    centres : (C, D) float64; radii : (C, 2) float64, the cells' stored radii.

    Proof: for a query q of the first cell and a row x of cell c, per part p,
    ``|q - x|_p >= |centre - c|_p - |q - centre|_p - |x - c|_p >= |centre - c|_p - reach_p
    - radius_p`` (triangle inequality); the invariant bound of the pair is the larger part,
    so the larger of the two parts' right-hand sides bounds it too. The centre distance is
    computed from the differences directly: each difference, square, the sum of D terms
    and the square root round with a relative error of at most gamma_{D+3} together, which
    the result gives up (it never exceeds the true distance).
    """
    d = centres - centre[None, :]
    shrink = 1.0 - _gamma64(centres.shape[1] + 3)
    a = np.sqrt(np.einsum("ij,ij->i", d[:, :split], d[:, :split])) * shrink - reach[0] - radii[:, 0]
    b = np.sqrt(np.einsum("ij,ij->i", d[:, split:], d[:, split:])) * shrink - reach[1] - radii[:, 1]
    return np.maximum(np.maximum(a, b), 0.0)


def truncated_lower_bounds(
    A: np.ndarray,
    B: np.ndarray,
    *,
    direction: str = INVARIANT,
    mirror: bool = False,
    harmonics: int = TRUNCATED_HARMONICS,
    grid: int = TRUNCATED_GRID,
    limit: float | None = None,
) -> np.ndarray:
    """(m,) float64 lower bounds of the exact distance from the first harmonics only.

    Parameters
    ----------
    A : (K, 3) complex128 query half-band; B : (m, K, 3) complex rows.
    direction, mirror : as the search (the bound covers the same alignments).
    harmonics, grid : K' harmonics kept; start shifts evaluated on ``grid`` points.
    limit : only whether a bound exceeds ``limit`` matters (a search's k-th distance): a row
        whose coarse grid already proves it gets a bound above ``limit`` from the coarse grid
        alone (cheaper; still a lower bound). None: every row's fine-grid bound.

    Proof of the slack: F(s) = max_R tr(R^T H(s)) with H(s) = sum_{k<=K'} 2 Re(conj(B_k)
    A_k^T e^{2 pi i k s/n}). At the best shift s*, with its best rotation R*, f(s) =
    tr(R*^T H(s)) touches F from below at s*, so f'(s*) = 0, and |f''| <= L2 =
    sum_k 2 (2 pi k/n)^2 |A_k| |B_k| (each term's nuclear norm is at most 2 |A_k| |B_k|).
    A grid point g within h/2 = n/(2 G) of s* (G points) has F(g) >= f(g) >= F(s*) -
    L2 h^2/8, i.e. F(s*) <= F(g) + S_G with S_G = sum_k |A_k| |B_k| (pi k/G)^2. The truncated
    distance is d_S^2 = |A_S|^2 + |B_S|^2 - 2 F(s*) (both directions, mirrored when allowed),
    and d_S <= d.

    Coarse to fine (:func:`nfdmatch.matching.grid_bound`): the coarse grid is every third
    point of the fine one (G / 3 points), so its intervals [c - 1.5, c + 1.5] (in fine steps)
    cover the circle and each holds exactly the fine points c - 1, c, c + 1. s* lies in some
    coarse interval c*. If c* is refined, its fine points include one within half a fine step
    of s*: F(s*) <= that point's F + S_G. If not, F(s*) <= F(c*) + S_{G/3}. So the larger of
    the refined intervals' F + S_G and the other coarse points' F + S_{G/3} bounds F(s*),
    whichever intervals are refined; a coarse point is refined when its own value could
    bring the bound to ``limit``.
    """
    from ..matching import grid_bound

    B = np.asarray(B)
    if len(B) == 0:
        return np.zeros(0)
    Kp = min(harmonics, A.shape[0])
    As, Bs = np.asarray(A[:Kp], dtype=np.complex128), np.asarray(B[:, :Kp], dtype=np.complex128)
    k = np.arange(1, Kp + 1)
    na = np.sqrt((As.real**2 + As.imag**2).sum(axis=1))
    nb = np.sqrt(np.einsum("mkj,mkj->mk", Bs.real, Bs.real) + np.einsum("mkj,mkj->mk", Bs.imag, Bs.imag))
    slack = nb @ ((np.pi * k / grid) ** 2 * na)
    squared = 2.0 * (na**2).sum() + 2.0 * (nb**2).sum(axis=1)
    ratio = _COARSE_RATIO if grid % _COARSE_RATIO == 0 else 1
    # the bound exceeds limit once F + slack < need (the formula below)
    need = np.full(len(Bs), -np.inf) if limit is None else ((1.0 - 1e-12) * squared - limit * limit) / 2.0
    fmax = grid_bound(As, Bs, grid, slack * ratio**2, slack, need, ratio=ratio, direction=direction, mirror=mirror)
    # F is a sum of products accurate to rounding: a relative 1e-12 of the squares covers it
    d2 = squared - 2.0 * fmax - 1e-12 * squared
    return np.sqrt(np.maximum(d2, 0.0))
