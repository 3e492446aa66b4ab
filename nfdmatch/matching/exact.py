"""The exact search: the global optimum over start shift x rotation for one query against
many rows (all integer shifts as one matrix product, the Kabsch optimum in closed form, the
best local maxima refined to a sub-sample shift), and its integer stage alone on a grid
(:func:`grid_maximum`, for the truncated-harmonic bound)."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from .common import INVARIANT
from .common import (
    REFINE_CANDIDATES,
    check_direction,
    direction_variants,
    integer_shift_basis,
    kabsch_rotation,
    search_inputs,
    shift_basis,
    trace_soa,
)
from .kernels import Kernels, folded_basis, current

if TYPE_CHECKING:
    from numpy.typing import ArrayLike


# --------------------------------------------------------------------------- exact

_REFINE_MID_OFFSETS = np.array([-2.0, -1.0, 0.0, 1.0, 2.0]) / 16.0  # around the first estimate
_REFINE_FINE_STEP = 1e-3  # spacing of the last parabola


def _parabola(x, h, f_minus, f_0, f_plus):
    """Maximum of the parabola through (x-h, x, x+h) within [x-h, x+h]: (location, value, concave).

    Not concave: x itself. The value is the parabola's at the (clipped) location, a
    model estimate that callers trust only at spacings where the model is exact to rounding.
    """
    curvature = f_plus - 2.0 * f_0 + f_minus
    slope = 0.5 * (f_plus - f_minus)
    concave = curvature < 0
    safe = np.where(concave, curvature, -1.0)
    t = np.where(concave, np.clip(-slope / safe, -1.0, 1.0), 0.0)
    value = f_0 + t * slope + 0.5 * t * t * np.where(concave, curvature, 0.0)
    return x + t * h, value, concave


def _refine_shifts(Pc, s0, f_minus, f_0, f_plus, n, mirror):
    """Continuous start shift around integer local maxima s0 (C,) with integer-shift values
    f(s0-1), f(s0), f(s0+1) (C,) each; products Pc (C, 9, 2K).

    The objective is smooth with its maximum within one sample of s0. Three parabolic
    steps with shrinking spacing (1 sample, 1/16, 1e-3) land within ~1e-9 samples: the
    error of a parabolic vertex is cubic in spacing and offset. Every evaluated point
    competes, so the result is never worse than s0. Returns (shift (C,), value (C,)).
    """
    C = len(s0)
    K = Pc.shape[2] // 2
    rows = np.arange(C)

    def evaluate(points):  # (C, m) -> (C, m)
        M = np.matmul(Pc, shift_basis(points, K, n))  # (C, 9, m)
        # one formula whatever the batch (LAPACK's SVD was faster below ~32 matrices, but
        # gave other last digits: a row's reported distance then depended on how many rows
        # it was recomputed with, e.g. on --top)
        return trace_soa(np.moveaxis(M, 1, 0), mirror)

    x1, _, _ = _parabola(s0, 1.0, f_minus, f_0, f_plus)
    mid = x1[:, None] + _REFINE_MID_OFFSETS
    fm = evaluate(mid)
    j = np.clip(np.argmax(fm, axis=1), 1, len(_REFINE_MID_OFFSETS) - 2)
    x2, _, _ = _parabola(
        mid[rows, j], _REFINE_MID_OFFSETS[1] - _REFINE_MID_OFFSETS[0], fm[rows, j - 1], fm[rows, j], fm[rows, j + 1]
    )
    h = _REFINE_FINE_STEP
    fine = x2[:, None] + np.array([-h, 0.0, h])
    ff = evaluate(fine)
    x3, f3, concave = _parabola(x2, h, ff[:, 0], ff[:, 1], ff[:, 2])
    # at this spacing the parabola is exact to rounding; where it is not concave, x3 = x2
    points = np.concatenate([s0[:, None], mid, fine, x3[:, None]], axis=1)
    values = np.concatenate([f_0[:, None], fm, ff, np.where(concave, f3, -np.inf)[:, None]], axis=1)
    best = np.argmax(values, axis=1)
    return points[rows, best], values[rows, best]


def exact_search(
    A: np.ndarray,
    B: np.ndarray,
    samples: int,
    *,
    weights: ArrayLike | None = None,
    direction: str = INVARIANT,
    mirror: bool = False,
    refine: bool = True,
    refine_below: float | None = None,
    kernels: Kernels | None = None,
) -> dict[str, np.ndarray]:
    """The global optimum over start shift x rotation for one query against many rows.

    Parameters
    ----------
    A : (K, 3) complex, the query's normalized half-band.
    B : (N, K, 3) complex, the rows' normalized half-bands (any rotation of each curve).
    samples : n, the sample count the descriptors were computed with.
    weights : (K,) float or None.
    direction : ``"invariant"`` (also score reversed traversal) or ``"strict"``.
    mirror : allow reflections.
    refine : refine the best integer shifts continuously (sub-sample start point).
    refine_below : only refine rows whose refined distance could be at most this (a search's
        current k-th distance); the others keep their integer-shift distance, which is then
        known to stay above ``refine_below``. The bound: refining gains at most C2/8 on the
        objective, C2 = sum_k 2 w_k (2 pi k / n)^2 |A_k| |B_k| bounding |F''(s)|.
    kernels : :class:`~nfdmatch.matching.kernels.Kernels` to compute with (default: the
        process's, :func:`~nfdmatch.matching.kernels.current`); ``kernels.NUMPY`` gives
        the reference digits.

    Returns
    -------
    dict of arrays over the N rows: ``distance`` (N,) float64, ``shift`` (N,) float64 in
    [0, n), ``rotation`` (N, 3, 3) float64 mapping B onto A, ``reversed`` (N,) bool,
    ``mirrored`` (N,) bool.

    Method: ``M(s)`` for every integer shift is one real matrix product with the
    2K x n DFT basis; the Kabsch optimum of each is a closed form; the best few local
    maxima per row are refined continuously; the final distance is the direct residual
    at the optimal rotation (no cancellation).
    """
    A, B, w, n = search_inputs(A, B, samples, weights, direction)
    N, K, _ = B.shape
    D = 2 if direction == INVARIANT else 1
    C = min(REFINE_CANDIDATES if refine else 1, D * n)
    Aw = np.conj(A) * w[:, None]
    kernels = kernels or current()
    if N and kernels.module is not None:
        # compiled: every stage per row in one call (F per row stays in cache)
        workers = kernels.workers(N)
        limit = _squared_limit(refine_below) if refine else np.inf
        basis, quarter = folded_basis(K, n)
        dist, shift, R, reversed_, mirrored = kernels.module.exact_rows(  # type: ignore[attr-defined]
            np.ascontiguousarray(A),
            np.ascontiguousarray(Aw),
            np.ascontiguousarray(w, dtype=np.float64),
            np.ascontiguousarray(B),
            D,
            basis,
            quarter,
            n,
            bool(mirror),
            C,
            bool(refine),
            float(limit),
            workers,
        )
        return {"distance": dist, "shift": shift, "rotation": R, "reversed": reversed_, "mirrored": mirrored}
    # the numpy path takes the query per row, so that a row's digits are the same whichever
    # rows come with it
    return _exact_numpy(np.repeat(A[None], N, axis=0), B, w, n, direction, mirror, C, refine, refine_below)


def _squared_limit(refine_below: float | None) -> float:
    """The squared distance below which a row is refined, with its margin; inf for no
    limit, and for a limit whose square overflows (above ~1.3e154: no distance is that far,
    so it limits nothing, as inf)."""
    if refine_below is None:
        return np.inf
    with np.errstate(over="ignore", invalid="ignore"):
        limit = float(np.float64(refine_below) ** 2 * (1 + 1e-9) + 1e-12)
    return limit if np.isfinite(limit) else np.inf


def _exact_numpy(A, B, w, n, direction, mirror, C, refine, refine_below):
    """The numpy path of :func:`exact_search` (the reference) with the query given per row:
    A, B (N, K, 3) complex128, w (K,) float64; C candidates per row."""
    N, K, _ = B.shape
    D = 2 if direction == INVARIANT else 1
    Aw = np.conj(A) * w[None, :, None]  # (N, K, 3)
    Bv = np.stack([v for v, _ in direction_variants(B, direction)])  # (D, N, K, 3)
    # P[j, i, d, r, k] = 2 w_k B_k[j] conj(A_k[i]): M(s)[j, i] = Re sum_k P e^{2 pi i k s / n}
    P = np.einsum("drkj,rki->jidrk", Bv, Aw)
    Pcat = np.concatenate([P.real, P.imag], axis=-1).reshape(9, D, N, 2 * K)
    # one (9 D, 2K) x (2K, n) product per row: a single product of every row at once let BLAS
    # block the rows by their count (OpenBLAS 0.3.31), so a row's last digits depended on how
    # many rows came with it
    per_row = np.ascontiguousarray(Pcat.transpose(2, 0, 1, 3).reshape(N, 9 * D, 2 * K))
    M = np.matmul(per_row, integer_shift_basis(K, n)).reshape(N, 9, D, n).transpose(1, 2, 0, 3)
    F = trace_soa(M, mirror).transpose(1, 0, 2)  # (N, D, n)

    local_max = (F >= np.roll(F, 1, axis=2)) & (F >= np.roll(F, -1, axis=2))
    Fm = np.where(local_max, F, -np.inf).reshape(N, D * n)
    cand = np.argpartition(-Fm, C - 1, axis=1)[:, :C]
    values = np.take_along_axis(Fm, cand, axis=1)
    Fmax = Fm.max(axis=1)
    dirs = (cand // n).reshape(-1)
    rows = np.repeat(np.arange(N), C)
    s_int = (cand % n).reshape(-1)
    shifts = s_int.astype(np.float64)
    values = values.reshape(-1)
    if refine:
        todo = np.ones(N * C, dtype=bool)
        if np.isfinite(_squared_limit(refine_below)):
            k = np.arange(1, K + 1)
            norm_a = np.linalg.norm(A, axis=2)  # (N, K)
            norm_b = np.linalg.norm(B, axis=2)
            curvature = (2.0 * w * (2.0 * np.pi * k / n) ** 2 * norm_a * norm_b).sum(axis=1)
            squared = 2.0 * (w * norm_a**2).sum(axis=1) + 2.0 * (w * norm_b**2).sum(axis=1)
            lower2 = squared - 2.0 * (Fmax + curvature / 8.0)
            todo = np.repeat(lower2 <= _squared_limit(refine_below), C)
        if todo.any():
            sel = np.flatnonzero(todo)
            Pc = Pcat[:, dirs[sel], rows[sel], :].transpose(1, 0, 2)  # (m, 9, 2K)
            Fr = F.reshape(N, D * n)
            base = cand.reshape(-1)[sel] - s_int[sel]
            shifts[sel], values[sel] = _refine_shifts(
                Pc,
                shifts[sel],
                Fr[rows[sel], base + (s_int[sel] - 1) % n],
                values[sel],
                Fr[rows[sel], base + (s_int[sel] + 1) % n],
                n,
                mirror,
            )
    values = np.where(np.isfinite(Fmax).repeat(C), values, -np.inf).reshape(N, C)
    pick = np.arange(N) * C + np.argmax(values, axis=1)
    shift, direction_idx = shifts[pick], dirs[pick]

    Bsel = np.where((direction_idx == 1)[:, None, None], np.conj(B), B)  # (N, K, 3)
    Bs = Bsel * np.exp((2j * np.pi / n) * np.outer(shift, np.arange(1, K + 1)))[:, :, None]
    Mbest = 2.0 * np.einsum("nkj,nki->nji", Bs, Aw).real
    R = kabsch_rotation(Mbest, mirror)
    resid = A - np.einsum("nij,nkj->nki", R, Bs)
    dist = np.sqrt(2.0 * np.einsum("k,nk->n", w, np.sum(resid.real**2 + resid.imag**2, axis=2)))
    mirrored = np.linalg.det(R) < 0
    shift = np.mod(shift, n)
    shift = np.where(np.abs(shift - np.round(shift)) < 1e-9, np.round(shift), shift) % n  # 127.99999.. -> 0
    return {
        "distance": dist,
        "shift": shift,
        "rotation": R,
        "reversed": direction_idx == 1,  # variants: (B, False), (conj(B), True)
        "mirrored": mirrored,
    }


def grid_maximum(
    A: np.ndarray, B: np.ndarray, grid: int, *, direction: str = INVARIANT, mirror: bool = False
) -> np.ndarray:
    """max over ``grid`` equally spaced start shifts, both directions (when ``direction`` is
    invariant) and all rotations of the correlation objective, per row.

    Parameters
    ----------
    A : (K, 3) complex, the query's half-band; B : (N, K, 3) complex rows.
    grid : shifts s = g n / grid, g = 0..grid-1 (the objective is evaluated as if the curves
        had ``grid`` samples; 2K < grid).

    Returns
    -------
    (N,) float64: max_g F(g), F = max_R tr(R M(g)) with M(g) = sum_k 2 Re(conj(A_k) B_k^T
    e^{2 pi i k g / grid}) (the exact search's objective, unit weights):
    ``2 |A|^2 + 2 |B|^2 - 2 max F`` is the squared distance at the best grid shift.
    The integer stage of :func:`exact_search` alone (no refinement, no rotation).
    """
    N = np.shape(B)[0]
    zero = np.zeros(N)
    return grid_bound(A, B, grid, zero, zero, np.full(N, -np.inf), ratio=1, direction=direction, mirror=mirror)


def grid_bound(
    A: np.ndarray,
    B: np.ndarray,
    grid: int,
    slack_coarse: np.ndarray,
    slack_fine: np.ndarray,
    need: np.ndarray,
    *,
    ratio: int = 3,
    direction: str = INVARIANT,
    mirror: bool = False,
    kernels: Kernels | None = None,
) -> np.ndarray:
    """Per row, the largest of F over a coarse grid plus a slack, with the coarse points that
    matter replaced by the fine grid around them (a coarse-to-fine maximum).

    Parameters
    ----------
    A : (K, 3) complex, the query's half-band; B : (N, K, 3) complex rows.
    grid : n, the fine grid's shifts (as :func:`grid_maximum`); ``ratio`` (odd, dividing n):
        the coarse grid is every ratio-th of them, c = 0, ratio, 2 ratio, ...
    slack_coarse, slack_fine : (N,) float64 added to F at coarse / fine points.
    need : (N,) float64: a coarse point c whose F + slack_coarse reaches need (or is NaN) is
        *refined*: its interval's fine points c - ratio // 2 .. c + ratio // 2 (mod n) count,
        each with F + slack_fine, instead.

    Returns
    -------
    (N,) float64: max(F(c) + slack_coarse over coarse points not refined, F(s) + slack_fine
    over the fine points of refined ones), both directions when ``direction`` is invariant.
    With need = -inf every point is refined: the fine grid's max of F + slack_fine. NaN
    propagates. What makes it an upper bound of F over all shifts is the caller's slack
    (:func:`nfdmatch.search.bounds.truncated_lower_bounds`). ``kernels`` as
    :func:`exact_search`.
    """
    A = np.asarray(A, dtype=np.complex128)
    B = np.asarray(B, dtype=np.complex128)
    N, K, _ = B.shape
    check_direction(direction)
    if grid % ratio or ratio % 2 == 0:
        raise ValueError(f"ratio must be odd and divide grid, got ratio {ratio}, grid {grid}")
    D = 2 if direction == INVARIANT else 1
    Aw = np.conj(A)
    slack_coarse, slack_fine, need = (
        np.ascontiguousarray(x, dtype=np.float64) for x in (slack_coarse, slack_fine, need)
    )
    kernels = kernels or current()
    if N and kernels.module is not None:
        workers = kernels.workers(N)
        return kernels.module.grid_bound_rows(  # type: ignore[attr-defined]
            np.ascontiguousarray(Aw),
            np.ascontiguousarray(B),
            D,
            np.array(integer_shift_basis(K, grid)),  # writable, as the compiled signatures take
            int(ratio),
            bool(mirror),
            slack_coarse,
            slack_fine,
            need,
            workers,
        )
    if not N:
        return np.zeros(0)
    Bv = np.stack([v for v, _ in direction_variants(B, direction)])  # (D, N, K, 3)
    P = np.einsum("drkj,ki->jidrk", Bv, Aw)
    Pcat = np.concatenate([P.real, P.imag], axis=-1).reshape(9, D, N, 2 * K)
    F = trace_soa((Pcat.reshape(-1, 2 * K) @ integer_shift_basis(K, grid)).reshape(9, D, N, grid), mirror)
    coarse = F[:, :, ::ratio]  # (D, N, n / ratio)
    refined = (coarse + slack_coarse[None, :, None] >= need[None, :, None]) | np.isnan(coarse)
    owner = ((np.arange(grid) + ratio // 2) // ratio) % (grid // ratio)  # fine point -> its interval
    fine_part = np.where(refined[:, :, owner], F + slack_fine[None, :, None], -np.inf)
    coarse_part = np.where(refined, -np.inf, coarse + slack_coarse[None, :, None])
    return np.maximum(fine_part.max(axis=(0, 2)), coarse_part.max(axis=(0, 2)))
