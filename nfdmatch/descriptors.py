"""Curve -> normalized Fourier descriptors (pure numpy).

Conventions (``docs/method.md`` of the design, restated in README):

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

from dataclasses import dataclass

import numpy as np

from .curve import Curve, as_points
from .errors import ParameterError

__all__ = ["Descriptors", "descriptors", "resample", "SCALES", "DEFAULT_SAMPLES",
           "DEFAULT_HARMONICS", "DEFAULT_SCALE", "validate_parameters"]

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
        return (np.concatenate([k, -k]),
                np.concatenate([self.coefficients, np.conj(self.coefficients)]))


def validate_parameters(samples: int, harmonics: int, scale: str) -> None:
    """Raise :class:`ParameterError` unless ``samples > 2 * harmonics >= 2`` and scale is known."""
    if not isinstance(samples, (int, np.integer)) or isinstance(samples, bool) or samples < 3:
        raise ParameterError(f"samples must be an integer >= 3, got {samples!r}")
    if not isinstance(harmonics, (int, np.integer)) or isinstance(harmonics, bool) or harmonics < 1:
        raise ParameterError(f"harmonics must be an integer >= 1, got {harmonics!r}")
    if 2 * harmonics >= samples:
        raise ParameterError(f"harmonics ({harmonics}) must be below samples/2 ({samples}/2): "
                             f"raise samples or lower harmonics")
    if scale not in SCALES:
        raise ParameterError(f"scale must be one of {', '.join(SCALES)}, got {scale!r}")


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
    closed = np.vstack([points, points[:1]])
    seg = np.linalg.norm(np.diff(closed, axis=0), axis=1)
    cum = np.concatenate([[0.0], np.cumsum(seg)])
    targets = np.arange(samples) * (cum[-1] / samples)
    # searchsorted over the cumulative length; zero-length segments were removed by cleaning
    idx = np.clip(np.searchsorted(cum, targets, side="right") - 1, 0, len(seg) - 1)
    t = (targets - cum[idx]) / np.where(seg[idx] > 0, seg[idx], 1.0)
    return closed[idx] + t[:, None] * (closed[idx + 1] - closed[idx])


def _plane_rotation(a1: np.ndarray) -> tuple[np.ndarray, bool]:
    """Rotation taking the limit-plane normal of ``a1`` ((3,) complex) onto +z.

    Returns ``((3, 3) float64, degenerate)``; identity when the plane is undefined.
    """
    p, q = a1.real, -a1.imag
    sv = np.linalg.svd(np.column_stack([p, q]), compute_uv=False)
    if sv[0] == 0 or sv[1] / sv[0] < PLANE_DEGENERACY:
        return np.eye(3), True
    normal = np.cross(p, q)
    normal /= np.linalg.norm(normal)
    z = np.array([0.0, 0.0, 1.0])
    c = float(normal @ z)
    if c < -1 + 1e-12:  # antiparallel: half-turn about x
        return np.diag([1.0, -1.0, -1.0]), False
    v = np.cross(normal, z)
    vx = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + vx + vx @ vx / (1 + c), False


def descriptors(curve, *, samples: int = DEFAULT_SAMPLES, harmonics: int = DEFAULT_HARMONICS,
                scale: str = DEFAULT_SCALE) -> Descriptors:
    """Normalized Fourier descriptors of one closed curve.

    Parameters
    ----------
    curve : :class:`~nfdmatch.curve.Curve` or array-like (n, 3) / (n, 2) of float.
    samples : int, arc-length samples (default 128; a power of two is fastest).
    harmonics : int K, frequencies +-1..+-K are kept (default 16); ``2K < samples``.
    scale : ``"rms"`` (default, RMS radius of the samples) or ``"a1"`` (``|A_1|``, the paper).

    Returns
    -------
    :class:`Descriptors` with ``coefficients`` (K, 3) complex128.
    """
    validate_parameters(samples, harmonics, scale)
    points = as_points(curve)
    curve_id = curve.id if isinstance(curve, Curve) else "<array>"
    # Work on a centred, rescaled copy so that huge or tiny coordinates stay in range.
    offset = points.mean(axis=0)
    extent = float(np.abs(points - offset).max())
    unit = (points - offset) / extent
    pts = resample(unit, samples)
    fd = np.fft.fft(pts, axis=0) / samples
    rms = float(np.sqrt(np.sum(np.abs(fd[1:]) ** 2)))
    a1 = float(np.linalg.norm(fd[1]))
    divisor = rms if scale == "rms" else max(a1, rms * 1e-15)
    coeffs = fd[1:harmonics + 1] / divisor
    rotation, degenerate = _plane_rotation(fd[1])
    if a1 < rms * PLANE_DEGENERACY:
        rotation, degenerate = np.eye(3), True
    return Descriptors(
        coefficients=coeffs @ rotation.T,
        rotation=rotation,
        centroid=offset + fd[0].real * extent,
        scale=divisor * extent,
        plane_degenerate=degenerate,
        samples=int(samples),
        harmonics=int(harmonics),
        scale_mode=scale,
        id=curve_id,
    )
