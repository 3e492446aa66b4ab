"""The elastic distance: two closed curves compared point to point after the best
correspondence that bends (docs/elastic.md).

Each curve is read from its stored descriptor (the half-band ``(K, 3) complex``): the curve
low-passed to K harmonics, sampled at :data:`SAMPLES` points, so no vertex count or
tessellation zig-zag enters. At every point, for offsets of :data:`OFFSETS` samples ahead
and behind, the chord to the other point is described by the sines of its angles: along
``l = n x t`` (the in-plane normal: for a plane curve the signed height function) and along
``n`` (out of the plane), ``n`` the direction of the curve's vector area, ``t`` the unit
tangent; plus the distance to the centroid over the RMS radius. 25 numbers a point,
invariant to translation, scale and rotation by construction; a curve without oriented
area (a figure eight, a line) gets the unsigned distance from the tangent line instead.

A pair is compared at the rigid optimum's start shift and direction (the exact search's
pose: never searched twice) and, when the search is invariant to the direction, also at
the best rigid pose of the other direction (:func:`elastic_distances`: the lesser of the
two; a nearly symmetric shape bends best into its mirror-like pose as often as not): the
query sampled at ``-s/2``, the row at ``+s/2`` (so the distance is symmetric), then a
banded (``|i - j| <= BAND``) symmetric dynamic programme over the correspondence of the two
signatures, L1 costs, diagonal steps weighted twice, each step's cost the mean of its two
cells', leaving and closing at (0, 0) diagonally (so a closed path walked backwards is a
path of the same cost: reversed pairs are symmetric too), the total over 2N. Mirrored
(``--mirror``) rows are reflected first; the ``n`` components change sign under a
reflection, so a mirror image is not at 0 unless asked for.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from .common import INVARIANT, STRICT
from ._threads import split_rows
from .kernels import Kernels, current, elastic_kernel

if TYPE_CHECKING:
    from numpy.typing import ArrayLike

__all__ = [
    "SAMPLES",
    "BAND",
    "OFFSETS",
    "ORIENTED_AREA",
    "FEATURES",
    "posed_rows",
    "elastic_rows",
    "elastic_distances",
    "elastic_reference",
    "signature_reference",
]

#: points of a signature (>= 2 K + 1 for K = 16 harmonics: the sampled curve is the curve)
SAMPLES = 64
#: the correspondence may drift this many samples from the rigid optimum's
BAND = 4
#: chord offsets (samples ahead and behind): from the local bend to the opposite side
OFFSETS = (1, 2, 4, 8, 16, 32)
#: a curve whose vector area is below this share of its RMS radius squared has no orientation
ORIENTED_AREA = 1e-3
#: numbers a signature holds per point
FEATURES = 4 * len(OFFSETS) + 1
#: the fewest rows a call splits over threads (a row costs ~15 us: a split pays from ~30)
ELASTIC_THREAD_ROWS = 32


def posed_rows(B: np.ndarray, reversed_: np.ndarray, mirrored: np.ndarray) -> np.ndarray:
    """Rows' half-bands as the rigid optimum traverses them.

    B : (M, K, 3) complex; reversed_, mirrored : (M,) bool. Returns (M, K, 3) complex128,
    C-contiguous: reversed rows conjugated (the opposite traversal), mirrored rows reflected
    (z negated: any reflection, the signature being rotation invariant)."""
    out = np.array(B, dtype=np.complex128, order="C", copy=True)
    flip = np.asarray(mirrored, dtype=bool)
    out[flip, :, 2] *= -1.0
    back = np.asarray(reversed_, dtype=bool)
    out[back] = np.conj(out[back])
    return out


def elastic_rows(
    A: np.ndarray,
    B: np.ndarray,
    shift: np.ndarray,
    reversed_: np.ndarray,
    mirrored: np.ndarray,
    samples: int,
    *,
    kernels: Kernels | None = None,
) -> np.ndarray:
    """Elastic distances of one query to many rows, at the rigid optimum's pose.

    Parameters
    ----------
    A : (K, 3) complex, the query's half-band; B : (M, K, 3) complex, the rows'.
    shift : (M,) float, the rigid optimum's start shift of each row, in samples of ``samples``
        (``exact_search``'s ``shift``); reversed_, mirrored : (M,) bool, its direction and
        reflection.
    samples : n, the sample count the descriptors were computed with.
    kernels : which implementation (default: the process's; ``NUMPY``: the reference).

    Returns (M,) float64 >= 0, 0 for the same curve however posed, sampled or started.
    """
    A = np.ascontiguousarray(A, dtype=np.complex128)
    posed = posed_rows(B, reversed_, mirrored)
    # the shift as a fraction of the perimeter in [-1/2, 1/2): (a, b) and (b, a) then sample
    # the same points, and the distance is symmetric
    fractions = np.asarray(shift, dtype=np.float64) / float(samples)
    fractions = np.ascontiguousarray(np.mod(fractions + 0.5, 1.0) - 0.5)
    out = np.zeros(len(posed))
    if not len(posed):
        return out
    chosen = kernels or current()
    kernel = elastic_kernel(chosen)
    if kernel is None:
        for r in range(len(posed)):
            out[r] = elastic_reference(A, posed[r], fractions[r])
        return out
    offsets = _writable_offsets()
    # a row's distance is computed alone, so the digits do not depend on the split
    split_rows(
        lambda lo, hi: kernel(A, posed[lo:hi], fractions[lo:hi], offsets, SAMPLES, BAND, ORIENTED_AREA, out[lo:hi]),
        len(posed),
        chosen.workers(len(posed), ELASTIC_THREAD_ROWS),
    )
    return out


def elastic_distances(
    A: np.ndarray,
    B: np.ndarray,
    rigid: dict,
    samples: int,
    *,
    direction: str = INVARIANT,
    mirror: bool = False,
    weights: ArrayLike | None = None,
    kernels: Kernels | None = None,
) -> np.ndarray:
    """The elastic distances of one query to many rows: at each row's rigid optimum and, when
    ``direction`` is invariant, at the best rigid pose of the other traversal direction
    too, the lesser (docs/elastic.md: a shape near to its mirror image, as most silhouettes
    are, may bend best into the pose the rigid fit ranked second; on Kimia-99 the elastic
    term's bull's-eye goes from 0.965 to 0.985).

    A : (K, 3) complex, the query's half-band; B : (M, K, 3) complex, the rows'.
    rigid : the exact optimum of each row (``shift``, ``reversed``, ``mirrored`` (M,) arrays,
        as :func:`~nfdmatch.matching.exact.exact_search` returns them).
    samples : n of the descriptors; direction, mirror, weights : the exact search's (the
        other direction's pose is searched as the rigid one was).

    Returns (M,) float64 >= 0, symmetric in the pair."""
    from .exact import exact_search

    reversed_ = np.asarray(rigid["reversed"], dtype=bool)
    first = elastic_rows(A, B, rigid["shift"], reversed_, rigid["mirrored"], samples, kernels=kernels)
    if direction != INVARIANT or not len(first):
        return first
    # the rows traversed the other way: a reversed curve is its conjugate half-band
    other_way = np.where(reversed_[:, None, None], np.asarray(B), np.conj(B))
    other = exact_search(A, other_way, samples, weights=weights, direction=STRICT, mirror=mirror, kernels=kernels)
    second = elastic_rows(
        A, other_way, other["shift"], np.zeros(len(first), dtype=bool), other["mirrored"], samples, kernels=kernels
    )
    return np.minimum(first, second)


_offsets_copy: list[np.ndarray] = []


def _writable_offsets() -> np.ndarray:
    """The offsets as the compiled signature takes them (a writable array, made once)."""
    if not _offsets_copy:
        _offsets_copy.append(np.array(OFFSETS, dtype=np.int64))
    return _offsets_copy[0]


# --------------------------------------------------------------------------- numpy reference


def signature_reference(C: np.ndarray, phase: float) -> np.ndarray:
    """The signature of the curve of half-band ``C`` ((K, 3) complex) sampled at
    ``t_j = j / SAMPLES + phase`` (fractions of the perimeter): (SAMPLES, FEATURES) float64."""
    n = SAMPLES
    K = C.shape[0]
    t = np.arange(n) / n + phase
    k = np.arange(1, K + 1)
    e = np.exp(2j * np.pi * np.outer(t, k))
    points = 2.0 * np.real(e @ C)
    tangents = 2.0 * np.real((e * (2j * np.pi * k)) @ C)
    rms = np.sqrt((points**2).sum() / n)
    area = np.cross(points, tangents).sum(axis=0)
    length = np.linalg.norm(area)
    oriented = rms > 0 and 0.5 * length / n > ORIENTED_AREA * rms * rms
    normal = area / length if oriented else np.zeros(3)
    speed = np.linalg.norm(tangents, axis=1)
    unit = np.where(speed[:, None] > 0, tangents / np.where(speed > 0, speed, 1.0)[:, None], 0.0)
    side = np.cross(normal, unit)
    out = np.zeros((n, FEATURES))
    for g, d in enumerate(OFFSETS):
        for s, step in enumerate((d, -d)):
            chord = np.roll(points, -step, axis=0) - points
            size = np.linalg.norm(chord, axis=1)
            safe = np.where(size > 0, size, 1.0)
            if oriented:
                along = (chord * side).sum(1) / safe
                across = (chord @ normal) / safe
            else:
                projected = (chord * unit).sum(1)
                along = np.sqrt(np.maximum(size**2 - projected**2, 0.0)) / safe
                across = np.zeros(n)
            out[:, 4 * g + 2 * s] = np.where(size > 0, along, 0.0)
            out[:, 4 * g + 2 * s + 1] = np.where(size > 0, across, 0.0)
    radius = np.linalg.norm(points, axis=1)
    out[:, 4 * len(OFFSETS)] = radius / rms if rms > 0 else 0.0
    return out


def elastic_reference(A: np.ndarray, posed: np.ndarray, fraction: float) -> float:
    """One pair on the slow path: the full cost matrix, then the banded programme cell by
    cell. ``posed``: the row's half-band as :func:`posed_rows` gives it; ``fraction``: the
    start shift over the sample count, in [-1/2, 1/2)."""
    a = signature_reference(np.asarray(A, dtype=np.complex128), -0.5 * fraction)
    b = signature_reference(np.asarray(posed, dtype=np.complex128), 0.5 * fraction)
    cost = np.abs(a[:, None, :] - b[None, :, :]).sum(axis=2)
    n = SAMPLES
    total = np.full((n, n), np.inf)
    total[0, 0] = 0.0
    for i in range(1, n):
        for j in range(max(1, i - BAND), min(n, i + BAND + 1)):
            # row and column 0 hold only (0, 0): the path leaves it diagonally
            total[i, j] = min(
                total[i - 1, j - 1] + (cost[i - 1, j - 1] + cost[i, j]),
                total[i - 1, j] + 0.5 * (cost[i - 1, j] + cost[i, j]),
                total[i, j - 1] + 0.5 * (cost[i, j - 1] + cost[i, j]),
            )
    return float((total[n - 1, n - 1] + cost[n - 1, n - 1] + cost[0, 0]) / (2.0 * n))
