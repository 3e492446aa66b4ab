"""Curve -> normalized Fourier descriptors (pure numpy).

Conventions (the project's ``docs/method.md``):

* A curve is resampled uniformly by arc length to ``samples`` points, starting
  at its first vertex (:func:`resample`).
* ``A_k = fft(samples)[k] / n``; the band that carries the shape is the
  frequencies ``+-1 .. +-harmonics``. Because the samples are real,
  ``A_{-k} = conj(A_k)``, so only ``k = 1 .. K`` is stored; every sum over the
  band is twice the sum over the stored half.
* Normalization: translation (``A_0 = 0``), scale (``"rms"``: RMS radius of the
  samples, or ``"a1"``: ``|A_1|`` as in the paper), orientation (rotate the
  limit-plane normal ``Re A_1 x (-Im A_1)`` onto +z). The exact matcher does not
  depend on the orientation step; the paper's matcher does.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from .curve import Curve, as_points
from .errors import CurveError, ParameterError

if TYPE_CHECKING:
    from numpy.typing import ArrayLike

__all__ = [
    "Descriptors",
    "descriptors",
    "resample",
    "SCALES",
    "DEFAULT_SAMPLES",
    "DEFAULT_HARMONICS",
    "DEFAULT_SCALE",
    "validate_parameters",
    "descriptors_batch",
    "DescriptorBatch",
    "points_at",
    "reconstruct",
]

SCALES = ("rms", "a1")
DEFAULT_SAMPLES = 128
DEFAULT_HARMONICS = 16
DEFAULT_SCALE = "rms"
# Below this ratio sigma2/sigma1 of [p q] (or |A_1| / RMS radius) the limit plane is too
# ill-conditioned to trust (noise of 0.1% would turn it arbitrarily).
PLANE_DEGENERACY = 1e-3


@dataclass(frozen=True)
class Descriptors:
    """Normalized Fourier descriptors of one curve.

    Attributes
    ----------
    coefficients : (K, 3) complex128. Normalized ``A_1 .. A_K`` (A_{-k} = conj(A_k)),
        centred, scaled and rotated into the limit-plane frame.
    rotation : (3, 3) float64. The plane-alignment rotation applied:
        ``coefficients = rotation @ raw_scaled_coefficients``.
    centroid : (3,) float64. Centroid of the resampled points (``A_0``), in input units.
    scale : float. The divisor applied (RMS radius or ``|A_1|``), in input units.
    plane_degenerate : bool. True when the limit plane is undefined (``p`` and ``q``
        nearly parallel or ``|A_1|`` nearly zero); the rotation is then the identity.
    samples, harmonics : int. The parameters used.
    scale_mode : str. ``"rms"`` or ``"a1"``.
    id : str. The curve id.
    """

    coefficients: np.ndarray
    rotation: np.ndarray
    centroid: np.ndarray
    scale: float
    plane_degenerate: bool
    samples: int
    harmonics: int
    scale_mode: str
    id: str = "<array>"

    def band(self) -> tuple[np.ndarray, np.ndarray]:
        """The full band: ``(frequencies (2K,) int64, coefficients (2K, 3) complex128)``,
        frequencies ordered ``1..K, -1..-K``."""
        k = np.arange(1, self.harmonics + 1)
        return (np.concatenate([k, -k]), np.concatenate([self.coefficients, np.conj(self.coefficients)]))


def validate_parameters(samples: int, harmonics: int, scale: str) -> None:
    """Raise :class:`ParameterError` unless ``samples > 2 * harmonics >= 2`` and scale is known."""
    if not isinstance(samples, (int, np.integer)) or isinstance(samples, bool) or samples < 3:
        raise ParameterError(f"samples must be an integer >= 3, got {samples!r}")
    if not isinstance(harmonics, (int, np.integer)) or isinstance(harmonics, bool) or harmonics < 1:
        raise ParameterError(f"harmonics must be an integer >= 1, got {harmonics!r}")
    if 2 * harmonics >= samples:
        raise ParameterError(
            f"harmonics ({harmonics}) must be below samples/2 ({samples}/2): raise samples or lower harmonics"
        )
    if scale not in SCALES:
        raise ParameterError(f"scale must be one of {', '.join(SCALES)}, got {scale!r}")


#: the direction of travel at a curve's start is drawn towards the point this fraction of
#: its length further on (the query's own arrow in a picture, and where nfdmatch.show places
#: each match's, from the match's alignment)
START_STEP = 0.04


def points_at(points: np.ndarray, fractions: ArrayLike) -> np.ndarray:
    """Points of a closed polyline at given fractions of its length.

    Parameters
    ----------
    points : (n, 3) float64, a cleaned closed polyline (closing edge implicit).
    fractions : (m,) float, arc length from ``points[0]`` over the total length; taken
        modulo 1, so negative values walk backwards from the start.

    Returns
    -------
    (m, 3) float64.
    """
    # scaled by a power of two (exact): lengths of a curve near 1e308 would overflow
    magnitude = float(np.abs(points).max()) if len(points) else 0.0
    pre = float(np.exp2(np.floor(np.log2(magnitude)))) if magnitude > 0 else 1.0
    closed = np.vstack([points, points[:1]]) / pre
    seg = np.linalg.norm(np.diff(closed, axis=0), axis=1)
    cum = np.concatenate([[0.0], np.cumsum(seg)])
    targets = np.mod(np.asarray(fractions, dtype=np.float64), 1.0) * cum[-1]
    # searchsorted over the cumulative length; zero-length segments were removed by cleaning
    idx = np.clip(np.searchsorted(cum, targets, side="right") - 1, 0, len(seg) - 1)
    t = (targets - cum[idx]) / np.where(seg[idx] > 0, seg[idx], 1.0)
    return (closed[idx] + t[:, None] * (closed[idx + 1] - closed[idx])) * pre


def resample(points: np.ndarray, samples: int) -> np.ndarray:
    """Uniform arc-length resampling of a closed polyline.

    Parameters
    ----------
    points : (n, 3) float64, a cleaned closed polyline (closing edge implicit).
    samples : int, number of output points.

    Returns
    -------
    (samples, 3) float64: sample ``j`` lies at arc length ``j * L / samples`` from
    ``points[0]`` along ``points[0] -> points[1] -> ... -> points[0]``.
    """
    return points_at(points, np.arange(samples) / samples)


def descriptors(
    curve: Curve | ArrayLike,
    *,
    samples: int = DEFAULT_SAMPLES,
    harmonics: int = DEFAULT_HARMONICS,
    scale: str = DEFAULT_SCALE,
) -> Descriptors:
    """Normalized Fourier descriptors of one closed curve.

    Parameters
    ----------
    curve : :class:`~nfdmatch.curve.Curve` or array-like (n, 3) / (n, 2) of float.
    samples : int, arc-length samples (default 128; a power of two is fastest).
    harmonics : int K, frequencies +-1..+-K are kept (default 16); ``2K < samples``.
    scale : ``"rms"`` (default, RMS radius of the samples) or ``"a1"`` (``|A_1|``, the paper).

    Returns
    -------
    :class:`Descriptors` with ``coefficients`` (K, 3) complex128: row 0 of
    :func:`descriptors_batch` of this one curve (one implementation of the normalization).
    """
    return descriptors_batch([curve], samples=samples, harmonics=harmonics, scale=scale).row(
        0, curve.id if isinstance(curve, Curve) else "<array>"
    )


def reconstruct(
    d: "Descriptors", *, harmonics: int | None = None, points: int | None = None, normalized: bool = False
) -> np.ndarray:
    """The curve rebuilt from its first harmonics: what the descriptor sees.

    ``x(t) = A_0 + 2 Re sum_{k=1..K} A_k exp(2 pi i k t)`` at ``t = j / points``, with the
    raw coefficients ``A_k = scale * rotation^T @ coefficients_k`` (input units and
    orientation) and ``A_0 = centroid``; ``normalized=True`` gives the normalized curve
    instead (centred, unit scale, limit plane on z = 0).

    Parameters
    ----------
    d : :class:`Descriptors`.
    harmonics : K, at most ``d.harmonics`` (default: all of them).
    points : vertices of the output (default ``d.samples``); sample ``j`` sits at the
        parameter of the descriptor's sample ``j * d.samples / points``.
    normalized : output in the normalized frame.

    Returns
    -------
    (points, 3) float64, a closed polyline (closing edge implicit).
    """
    K = d.harmonics if harmonics is None else int(harmonics)
    if not 1 <= K <= d.harmonics:
        raise ParameterError(f"harmonics must be between 1 and {d.harmonics} (the descriptor's), got {harmonics!r}")
    m = d.samples if points is None else int(points)
    if m < 3:
        raise ParameterError(f"points must be at least 3, got {points!r}")
    coeffs = d.coefficients[:K]  # (K, 3)
    if not normalized:
        coeffs = coeffs @ d.rotation  # rotation^T applied to each row
    phase = np.exp(2j * np.pi * np.outer(np.arange(m) / m, np.arange(1, K + 1)))  # (m, K)
    curve = 2.0 * (phase @ coeffs).real
    if normalized:
        return curve
    # scaled last: the sum over harmonics in input units would overflow for a curve near 1e308
    with np.errstate(over="ignore", invalid="ignore"):
        out = curve * d.scale + d.centroid
    if not np.isfinite(out).all():
        raise CurveError(
            "the rebuilt curve lies beyond float64 (coordinates near 1.8e308); "
            "use normalized=True or scale the input down"
        )
    return out


@dataclass(frozen=True)
class DescriptorBatch:
    """Normalized descriptors of many curves, as arrays (row i = curve i).

    Attributes
    ----------
    coefficients : (N, K, 3) complex128, as :attr:`Descriptors.coefficients`.
    rotation : (N, 3, 3) float64.
    centroid : (N, 3) float64.
    scale : (N,) float64.
    plane_degenerate : (N,) bool.
    samples, harmonics : int; scale_mode : str.
    """

    coefficients: np.ndarray
    rotation: np.ndarray
    centroid: np.ndarray
    scale: np.ndarray
    plane_degenerate: np.ndarray
    samples: int
    harmonics: int
    scale_mode: str

    def __len__(self) -> int:
        return int(self.coefficients.shape[0])

    def row(self, i: int, id: str = "<array>") -> Descriptors:
        """Row ``i`` as a :class:`Descriptors` (arrays copied)."""
        return Descriptors(
            coefficients=self.coefficients[i].copy(),
            rotation=self.rotation[i].copy(),
            centroid=self.centroid[i].copy(),
            scale=float(self.scale[i]),
            plane_degenerate=bool(self.plane_degenerate[i]),
            samples=self.samples,
            harmonics=self.harmonics,
            scale_mode=self.scale_mode,
            id=id,
        )


def _plane_rotations(a1: np.ndarray, rms: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotations taking each limit-plane normal ``Re a1 x (-Im a1)`` onto +z.

    a1 (N, 3) complex, rms (N,) -> ((N, 3, 3) float64, (N,) bool degenerate); the identity
    where the plane is undefined (``p``, ``q`` nearly parallel or ``|a1|`` nearly zero)."""
    p, q = a1.real, -a1.imag
    sv = np.linalg.svd(np.stack([p, q], axis=-1), compute_uv=False)  # (N, 2)
    degenerate = (
        (sv[:, 0] == 0)
        | (sv[:, 1] < PLANE_DEGENERACY * sv[:, 0])
        | (np.linalg.norm(a1, axis=1) < rms * PLANE_DEGENERACY)
    )
    normal = np.cross(p, q)
    length = np.linalg.norm(normal, axis=1, keepdims=True)
    normal = normal / np.where(length > 0, length, 1.0)
    c = normal[:, 2]
    v = np.stack([normal[:, 1], -normal[:, 0], np.zeros(len(c))], axis=1)  # normal x z
    vx = np.zeros((len(c), 3, 3))
    vx[:, 0, 1], vx[:, 0, 2], vx[:, 1, 0] = -v[:, 2], v[:, 1], v[:, 2]
    vx[:, 1, 2], vx[:, 2, 0], vx[:, 2, 1] = -v[:, 0], -v[:, 1], v[:, 0]
    # 1 + c cancels for normals near -z; for a unit normal 1 + c = (nx^2 + ny^2) / (1 - c)
    # exactly, which keeps the rotation orthonormal to rounding however close to -z
    off_axis = normal[:, 0] ** 2 + normal[:, 1] ** 2
    antiparallel = (c < 0) & (off_axis < 1e-300)
    one_plus_c = np.where(c >= 0, 1.0 + c, off_axis / (1.0 - np.minimum(c, 0.0)))
    factor = 1.0 / np.where(antiparallel, 1.0, one_plus_c)
    R = np.eye(3) + vx + (vx @ vx) * factor[:, None, None]
    R[antiparallel] = np.diag([1.0, -1.0, -1.0])
    R[degenerate] = np.eye(3)
    return R, degenerate


def _arc_lengths(seg: np.ndarray, starts: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """(len(seg) + 1,) float64: at curve i's vertex ``starts[i] + j`` (j = 0..counts[i]), the
    running sum of its first j segments, from 0 at its first vertex; each curve's sum is the
    one ``np.cumsum`` gives for that curve alone (a sum is sequential: padding after a
    curve's segments changes none of its values). Positions between curves are unused."""
    local = np.zeros(len(seg) + 1)
    N, longest, total = len(counts), int(counts.max()), int(counts.sum())
    if N * longest <= 4 * total + 4096:  # curves of similar lengths: one padded 2-D sum
        curve = np.repeat(np.arange(N), counts)
        within = np.arange(total) - np.repeat(np.cumsum(counts) - counts, counts)
        source = np.repeat(starts, counts) + within
        padded = np.zeros((N, longest))
        padded[curve, within] = seg[source]
        local[source + 1] = np.cumsum(padded, axis=1)[curve, within]
    else:  # one very long curve among short ones: curve by curve
        for a, c in zip(starts.tolist(), counts.tolist()):
            local[a + 1 : a + c + 1] = np.cumsum(seg[a : a + c])
    return local


#: vectorized one-vertex moves of :func:`_segments_at` before it searches curve by curve
_MOVES = 8


def _segments_at(local, seg, starts, targets, first_vertex, last) -> np.ndarray:
    """For each target arc length (of the curve whose vertices run from ``first_vertex`` to
    ``last + 1``), the last vertex at or before it within the curve, clipped to its segments:
    found on the batch's running arc length (monotone, one search), then moved to agree with
    each curve's own arc lengths ``local`` (the two differ by rounding only)."""
    running = np.concatenate([[0.0], np.cumsum(seg)])
    idx = np.searchsorted(running, running[first_vertex] + targets, side="right") - 1
    idx = np.clip(idx, first_vertex, last)
    for _ in range(_MOVES):
        up = (idx < last) & (local[np.minimum(idx + 1, len(local) - 1)] <= targets)
        down = (idx > first_vertex) & (local[idx] > targets)
        if not (up.any() or down.any()):
            return idx
        idx = idx + up - down
    # rounding moved a search by many vertices (runs of near-zero segments): exactly, per curve
    samples = len(targets) // len(starts)
    for i, a in enumerate(starts.tolist()):
        lo, hi = i * samples, (i + 1) * samples
        found = np.searchsorted(local[a : last[lo] + 2], targets[lo:hi], side="right") - 1 + a
        idx[lo:hi] = np.clip(found, a, last[lo])
    return idx


def descriptors_batch(
    curves: Sequence[Curve | np.ndarray],
    *,
    samples: int = DEFAULT_SAMPLES,
    harmonics: int = DEFAULT_HARMONICS,
    scale: str = DEFAULT_SCALE,
) -> DescriptorBatch:
    """:func:`descriptors` of many curves at once, vectorized (no Python loop over vertices).

    Parameters
    ----------
    curves : sequence of :class:`~nfdmatch.curve.Curve` or cleaned (n_i, 3) float64 arrays.
    samples, harmonics, scale : as in :func:`descriptors`.

    Returns
    -------
    :class:`DescriptorBatch`; row i equals ``descriptors(curves[i])`` to rounding.
    """
    validate_parameters(samples, harmonics, scale)
    pts_list = [as_points(c) for c in curves]
    N = len(pts_list)
    if N == 0:
        return DescriptorBatch(
            np.zeros((0, harmonics, 3), complex),
            np.zeros((0, 3, 3)),
            np.zeros((0, 3)),
            np.zeros(0),
            np.zeros(0, bool),
            samples,
            harmonics,
            scale,
        )
    counts = np.array([len(p) for p in pts_list])
    unit, offset, extent, pre = _unit_curves(pts_list, counts)
    sampled = _arc_length_samples(unit, counts, samples)
    # real samples: rfft gives A_0 .. A_{n//2}, all that is used (A_{-k} = conj A_k)
    fd = np.fft.rfft(sampled, axis=-1).transpose(1, 2, 0) / samples  # (N, n//2 + 1, 3)
    # sum over k = 1 .. n-1 of |A_k|^2: twice each k < n/2, once the Nyquist term
    twice = np.where(2 * np.arange(fd.shape[1]) < samples, 2.0, 1.0)
    twice[0] = 0.0
    rms = np.sqrt(np.einsum("k,nk->n", twice, np.sum(np.abs(fd) ** 2, axis=2)))
    a1 = np.linalg.norm(fd[:, 1], axis=1)
    divisor = rms if scale == "rms" else np.maximum(a1, rms * 1e-15)
    coeffs = fd[:, 1 : harmonics + 1] / divisor[:, None, None]
    R, degenerate = _plane_rotations(fd[:, 1], rms)
    centroid = (offset + fd[:, 0].real * extent[:, None]) * pre[:, None]
    size = divisor * extent * pre
    _check_finite(size, centroid, curves)
    return DescriptorBatch(
        coefficients=np.einsum("nij,nkj->nki", R, coeffs),
        rotation=R,
        centroid=centroid,
        scale=size,
        plane_degenerate=degenerate,
        samples=int(samples),
        harmonics=int(harmonics),
        scale_mode=scale,
    )


def _unit_curves(pts_list, counts):
    """Every curve closed explicitly (first vertex repeated), all concatenated, each scaled
    into the unit box about its vertex mean: ``(unit points, vertex means, extents, power-of-
    two prescales)``; a curve's point ``p`` is ``(unit * extent + mean) * prescale``."""
    N = len(pts_list)
    # each curve closed explicitly (first vertex repeated), all concatenated: one insert
    flat = np.concatenate(pts_list) if N > 1 else pts_list[0]
    ends = np.cumsum(counts)
    closed = np.insert(flat, ends, flat[ends - counts], axis=0)
    curve_of = np.repeat(np.arange(N), counts + 1)
    first = np.concatenate([[0], np.cumsum(counts + 1)[:-1]])
    # scaled first by a power of two per curve (exact, so ordinary curves give the same bits):
    # a sum or difference of coordinates near 1e308 would overflow
    magnitude = np.maximum.reduceat(np.abs(closed).max(axis=1), first)
    pre = np.exp2(np.floor(np.log2(np.where(magnitude > 0, magnitude, 1.0))))
    closed = closed / pre[curve_of, None]
    offset = np.add.reduceat(closed, first, axis=0)
    offset = (offset - closed[first]) / counts[:, None]  # vertex mean
    centred = closed - offset[curve_of]
    extent = np.maximum.reduceat(np.abs(centred).max(axis=1), first)
    unit = centred / extent[curve_of, None]
    return unit, offset, extent, pre


def _arc_length_samples(unit, counts, samples: int) -> np.ndarray:
    """``samples`` points per closed curve of ``unit`` (:func:`_unit_curves`), equally
    spaced in arc length from its first vertex: (3, N, samples), coordinate-major."""
    N = len(counts)
    step = np.diff(unit, axis=0)
    seg = np.linalg.norm(step, axis=1)
    starts = np.concatenate([[0], np.cumsum(counts + 1)[:-1]])  # index of each curve's first vertex
    seg[starts[1:] - 1] = 0.0  # no segment between curves
    # each curve's arc length from its own first vertex: a curve's samples must not depend
    # on the curves batched with it (a running sum over the batch would round differently)
    local = _arc_lengths(seg, starts, counts)
    lengths = local[starts + counts]
    targets = (np.arange(samples)[None, :] * (lengths / samples)[:, None]).ravel()  # (N * samples,)
    first_vertex = starts.repeat(samples)
    last = (starts + counts - 1).repeat(samples)  # last segment of each curve
    idx = _segments_at(local, seg, starts, targets, first_vertex, last)
    seglen = local[idx + 1] - local[idx]
    t = (targets - local[idx]) / np.where(seglen > 0, seglen, 1.0)
    # coordinate-major (3, N * samples): contiguous gathers, and FFTs along the last axis
    return (unit.T[:, idx] + t * step.T[:, idx]).reshape(3, N, samples)


def _check_finite(size, centroid, curves) -> None:
    """A CurveError for the first curve whose size or position overflowed float64."""
    bad = ~(np.isfinite(size) & np.isfinite(centroid).all(axis=1))
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        c = curves[i]
        raise CurveError(
            "the curve's size or position is beyond float64 (coordinates near 1.8e308): scale the input down",
            path=c.id if isinstance(c, Curve) else None,
        )
