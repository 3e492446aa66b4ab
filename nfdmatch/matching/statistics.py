"""Pose-free shape statistics of a curve, and their distance (docs/elastic.md).

What a curve is like regardless of where its parts sit: the spectrum of its radius
function, the spectrum of its covariance, the share of each harmonic's power, the
distribution of distances between its points (D2), of its curvature at three low-pass
levels, and its length and total curvature. All are computed from the stored descriptor
(the curve low-passed to K harmonics, scale-normalised), never from the vertices: invariant
to translation, scale, rotation, start, direction and mirror image, and blind to the
vertex count and the tessellation.

Blocks (:data:`BLOCKS`, in this order in a statistics vector) and the numbers each holds:

- ``radius`` (8): ``|FFT|`` 1..8 of the distance to the centroid at 128 samples, over its mean;
- ``covariance`` (3): eigenvalues of the points' covariance, decreasing, over their sum;
- ``power`` (16): the square root of each harmonic's share of the power (k = 1..16);
- ``d2`` (12): histogram of the distances between 64 points over their mean, on [0, 3];
- ``curvature`` (24): 8-bin histograms of log(curvature x mean speed) at 16, 8 and 4
  harmonics, weighted by arc length;
- ``size`` (2): log of the length over the RMS radius and log of the total curvature.

The distance of two vectors is the sum over blocks of each block's L1 difference over a
fixed constant (:data:`BLOCK_SCALES`: the median of that block's differences over the
pooled development collections, so each block weighs about the same).
"""

from __future__ import annotations

import numpy as np

__all__ = ["BLOCKS", "BLOCK_SIZES", "BLOCK_SCALES", "LENGTH", "curve_statistics", "statistics_distance"]

BLOCKS = ("radius", "covariance", "power", "d2", "curvature", "size")
BLOCK_SIZES = (8, 3, 16, 12, 24, 2)
#: numbers in a statistics vector
LENGTH = sum(BLOCK_SIZES)
#: each block's typical L1 difference (pooled development data: Kimia-99, the mesh sections,
#: psb_dev cut loops and mid-sections), frozen as an earlier draft of these blocks measured
#: them: the fused distance is stamped (``fused.FUSED_VERSION``) and its statistics quantile
#: table was made with these. ``benchmarks/bench_3d.py --constants`` prints them recomputed
#: on today's blocks (0.243, 0.295, 0.211, 0.296, 1.833, 0.373): with those, and the table
#: recomputed, every development figure stays within one query (docs/elastic.md)
BLOCK_SCALES = (0.2807, 0.3128, 0.2593, 0.3194, 2.1033, 0.5619)

_CURVE_SAMPLES = 128
_CURVATURE_LEVELS = (16, 8, 4)
_CURVATURE_RANGE = (np.log(0.5), np.log(200.0))
_TINY = 1e-12


def _curve(C: np.ndarray, harmonics: int, samples: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Points, first and second derivatives ((M, samples, 3) float64 each) of the curves
    of half-bands ``C`` ((M, K, 3) complex) low-passed to ``harmonics``."""
    K = min(harmonics, C.shape[1])
    t = np.arange(samples) / samples
    k = np.arange(1, K + 1)
    e = np.exp(2j * np.pi * np.outer(t, k))
    low = C[:, :K, :]
    points = 2.0 * np.matmul(e, low).real
    first = 2.0 * np.matmul(e * (2j * np.pi * k), low).real
    second = 2.0 * np.matmul(e * (2j * np.pi * k) ** 2, low).real
    return points, first, second


def _histograms(values: np.ndarray, bins: int, low: float, high: float, weights: np.ndarray) -> np.ndarray:
    """Row-wise histograms: values, weights (M, m) -> (M, bins); values outside are dropped."""
    M = values.shape[0]
    position = np.floor((values - low) / (high - low) * bins).astype(np.int64)
    inside = (position >= 0) & (position < bins)
    flat = (np.arange(M)[:, None] * bins + np.clip(position, 0, bins - 1))[inside]
    return np.bincount(flat, weights=weights[inside], minlength=M * bins).reshape(M, bins)


def curve_statistics(C: np.ndarray) -> np.ndarray:
    """The statistics vectors of curves.

    C : (M, K, 3) complex (or (K, 3) for one curve), normalized half-bands.
    Returns (M, LENGTH) float64 (or (LENGTH,)), finite for any input (a curve of no extent
    gets zeros where a ratio has no value)."""
    C = np.asarray(C, dtype=np.complex128)
    single = C.ndim == 2
    if single:
        C = C[None]
    M = C.shape[0]
    points, first, second = _curve(C, C.shape[1], _CURVE_SAMPLES)
    rms = np.sqrt((points**2).sum(axis=2).mean(axis=1))
    scale = np.where(rms > _TINY, rms, 1.0)[:, None, None]
    points, first, second = points / scale, first / scale, second / scale

    radius = np.linalg.norm(points, axis=2)
    mean_radius = radius.mean(axis=1)
    spectrum = np.abs(np.fft.rfft(radius, axis=1))[:, 1:9]
    radius_block = spectrum / (_CURVE_SAMPLES * np.where(mean_radius > _TINY, mean_radius, 1.0))[:, None]

    covariance = np.matmul(points.transpose(0, 2, 1), points) / _CURVE_SAMPLES
    eigen = np.clip(np.linalg.eigvalsh(covariance)[:, ::-1], 0.0, None)
    total = eigen.sum(axis=1, keepdims=True)
    covariance_block = eigen / np.where(total > _TINY, total, 1.0)

    power = (np.abs(C) ** 2).sum(axis=2)[:, :16]
    power = np.pad(power, ((0, 0), (0, 16 - power.shape[1])))
    share = power.sum(axis=1, keepdims=True)
    power_block = np.sqrt(power / np.where(share > _TINY, share, 1.0))

    half = points[:, ::2]
    upper = np.triu_indices(half.shape[1], 1)
    gaps = np.linalg.norm(half[:, upper[0]] - half[:, upper[1]], axis=2)
    mean_gap = gaps.mean(axis=1, keepdims=True)
    gaps = gaps / np.where(mean_gap > _TINY, mean_gap, 1.0)
    d2_block = _histograms(gaps, 12, 0.0, 3.0, np.full(gaps.shape, 1.0 / gaps.shape[1]))

    curvature_blocks = []
    for level in _CURVATURE_LEVELS:
        _, d1, d2 = _curve(C, level, _CURVE_SAMPLES)
        d1, d2 = d1 / scale, d2 / scale
        speed = np.linalg.norm(d1, axis=2)
        mean_speed = speed.mean(axis=1, keepdims=True)
        bend = np.linalg.norm(np.cross(d1, d2), axis=2) / np.maximum(speed, _TINY) ** 3 * mean_speed
        weight = speed / np.where(mean_speed > _TINY, mean_speed * _CURVE_SAMPLES, 1.0)
        curvature_blocks.append(_histograms(np.log(np.maximum(bend, 1e-3)), 8, *_CURVATURE_RANGE, weight))
    curvature_block = np.concatenate(curvature_blocks, axis=1)

    speed = np.linalg.norm(first, axis=2)
    bend = np.linalg.norm(np.cross(first, second), axis=2) / np.maximum(speed, _TINY) ** 3
    length = speed.mean(axis=1)
    turning = (bend * speed).mean(axis=1)
    size_block = np.stack([np.log(np.maximum(length, _TINY)), np.log(np.maximum(turning, _TINY))], axis=1)

    out = np.concatenate([radius_block, covariance_block, power_block, d2_block, curvature_block, size_block], axis=1)
    out = np.where(np.isfinite(out), out, 0.0)
    return out[0] if single else out.reshape(M, LENGTH)


def statistics_distance(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Distances between statistics vectors: ``a`` (LENGTH,) or (M, LENGTH), ``b`` (M,
    LENGTH) -> (M,) float64: per block the L1 difference over its :data:`BLOCK_SCALES`,
    summed."""
    gaps = np.abs(np.asarray(a, dtype=np.float64) - np.asarray(b, dtype=np.float64))
    gaps = np.atleast_2d(gaps)
    total = np.zeros(gaps.shape[0])
    start = 0
    for size, scale in zip(BLOCK_SIZES, BLOCK_SCALES):
        total += gaps[:, start : start + size].sum(axis=1) / scale
        start += size
    return total
