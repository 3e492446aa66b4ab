"""What the exact search and the paper's step share: the method and direction names, weights,
the closed-form Kabsch trace of 3x3 matrices, and the DFT bases over start shifts."""

from __future__ import annotations

from typing import Any, TYPE_CHECKING

from functools import lru_cache

import numpy as np

from ..errors import ParameterError

if TYPE_CHECKING:
    from numpy.typing import ArrayLike, NDArray


METHODS = ("exact", "paper")
DIRECTIONS = ("invariant", "strict")
#: the method and direction of every matching function and command unless told otherwise
#: the names, one constant each (a parameter spells them through these)
EXACT, PAPER = METHODS
INVARIANT, STRICT = DIRECTIONS
DEFAULT_METHOD, DEFAULT_DIRECTION = EXACT, INVARIANT
#: the direction that does not match a curve traversed backwards (``--strict-direction``)
STRICT_DIRECTION = DIRECTIONS[1]
REFINE_CANDIDATES = 3  # integer local maxima refined per row


# --------------------------------------------------------------------------- helpers


def _weights(weights, harmonics: int) -> np.ndarray:
    """(K,) float64 weights w_1..w_K, validated (uniform when None)."""
    if weights is None:
        return np.ones(harmonics)
    w = np.asarray(weights, dtype=np.float64).reshape(-1)
    if w.shape != (harmonics,) or not np.all(np.isfinite(w)) or np.any(w < 0):
        raise ParameterError(
            f"weights must be {harmonics} finite non-negative numbers "
            f"(one per harmonic 1..{harmonics}), got shape {w.shape}"
        )
    return w


def check_direction(direction: str) -> None:
    if direction not in DIRECTIONS:
        raise ParameterError(f"direction must be one of {', '.join(DIRECTIONS)}, got {direction!r}")


def search_inputs(
    A: ArrayLike, B: ArrayLike, samples: int, weights: ArrayLike | None, direction: str
) -> tuple[NDArray[np.complex128], NDArray[np.complex128], NDArray[np.float64], int]:
    """A search's arguments checked once: ``(A (K, 3) complex128, B (N, K, 3) complex128,
    w (K,) float64, n int)``; a single row ``B`` (K, 3) becomes (1, K, 3)."""
    A = np.asarray(A, dtype=np.complex128)
    B = np.asarray(B, dtype=np.complex128)
    if B.ndim == 2:
        B = B[None]
    check_direction(direction)
    return A, B, _weights(weights, B.shape[1]), int(samples)


_TINY = np.finfo(np.float64).tiny


def _lmax_soa(s00, s11, s22, s01, s02, s12):
    """Largest eigenvalue of symmetric PSD 3x3 matrices given entry-wise (trigonometric formula)."""
    q = (s00 + s11 + s22) * (1.0 / 3.0)
    d0, d1, d2 = s00 - q, s11 - q, s22 - q
    p = np.sqrt((d0 * d0 + d1 * d1 + d2 * d2 + 2.0 * (s01 * s01 + s02 * s02 + s12 * s12)) * (1.0 / 6.0))
    det = d0 * (d1 * d2 - s12 * s12) - s01 * (s01 * d2 - s12 * s02) + s02 * (s01 * s12 - d1 * s02)
    # p == 0 means three equal eigenvalues; then det == 0 and any r gives q
    r = np.minimum(np.maximum(det / np.maximum(2.0 * p * p * p, _TINY), -1.0), 1.0)
    return np.maximum(q + 2.0 * p * np.cos(np.arccos(r) * (1.0 / 3.0)), 0.0)


def gram_entries(a: Any, b: Any, c: Any, d: Any, e: Any, f: Any, g: Any, h: Any, i: Any) -> tuple[Any, ...]:
    """The entries 00, 11, 22, 01, 02, 12 of X^T X for X = [[a, b, c], [d, e, f], [g, h, i]]
    given entry-wise, as a tuple: of arrays here (:func:`_lmax_gram_soa`), of floats in the
    compiled kernels, which compile this same function (:mod:`._kernels`)."""
    return (
        a * a + d * d + g * g,
        b * b + e * e + h * h,
        c * c + f * f + i * i,
        a * b + d * e + g * h,
        a * c + d * f + g * i,
        b * c + e * f + h * i,
    )


def _lmax_gram_soa(a, b, c, d, e, f, g, h, i):
    """Largest eigenvalue of X^T X for matrices X = [[a, b, c], [d, e, f], [g, h, i]] given
    entry-wise."""
    return _lmax_soa(*gram_entries(a, b, c, d, e, f, g, h, i))


def trace_soa(m: np.ndarray, mirror: bool) -> np.ndarray:
    """max_R tr(R M) for matrices given as m = (9, ...) row-major entries (structure of arrays).

    sigma1 from the largest eigenvalue of M^T M, sigma1*sigma2 from the largest of C^T C
    (C the cofactor matrix, singular values s2 s3, s1 s3, s1 s2), sigma3 = |det M| / (s1 s2).
    Only largest eigenvalues are taken: the sqrt of a small one would lose half the
    digits exactly when the curves are near-planar or near-linear.
    """
    a, b, c, d, e, f, g, h, i = m
    l1 = _lmax_gram_soa(a, b, c, d, e, f, g, h, i)
    c00, c01, c02 = e * i - f * h, f * g - d * i, d * h - e * g
    c10, c11, c12 = c * h - b * i, a * i - c * g, b * g - a * h
    c20, c21, c22 = b * f - c * e, c * d - a * f, a * e - b * d
    det = a * c00 + b * c01 + c * c02
    l12 = _lmax_gram_soa(c00, c01, c02, c10, c11, c12, c20, c21, c22)
    s1 = np.sqrt(l1)
    s12 = np.sqrt(l12)
    s2 = s12 / np.maximum(s1, _TINY)
    third = np.minimum(np.maximum(det / np.maximum(s12, _TINY), -s2), s2)
    if mirror:
        third = np.abs(third)
    return s1 + s2 + third


def kabsch_trace(M: np.ndarray, mirror: bool = False) -> np.ndarray:
    """max over rotations R of tr(R M), in closed form, for a stack of 3x3 matrices.

    Parameters
    ----------
    M : (..., 3, 3) float64.
    mirror : allow improper R (reflections): returns sigma1 + sigma2 + sigma3.

    Returns
    -------
    (...,) float64: ``sigma1 + sigma2 + sign(det M) sigma3`` (SO(3)), accurate to a few
    ulps of sigma1 even for rank-deficient M.
    """
    M = np.asarray(M, dtype=np.float64)
    return trace_soa(np.moveaxis(M.reshape(*M.shape[:-2], 9), -1, 0), mirror)


def kabsch_rotation(M: np.ndarray, mirror: bool) -> np.ndarray:
    """(..., 3, 3) the R maximizing tr(R M) (SO(3), or O(3) when mirror)."""
    U, _, Vh = np.linalg.svd(M)
    V = np.swapaxes(Vh, -1, -2)
    Ut = np.swapaxes(U, -1, -2)
    if not mirror:
        d = np.sign(np.linalg.det(V @ Ut))
        d = np.where(d == 0, 1.0, d)
        V = V.copy()
        V[..., :, 2] *= d[..., None]
    return V @ Ut


def direction_variants(B: np.ndarray, direction: str) -> list[tuple[np.ndarray, bool]]:
    check_direction(direction)
    variants = [(B, False)]
    if direction == "invariant":
        variants.append((np.conj(B), True))
    return variants


@lru_cache(maxsize=32)
def integer_shift_basis(K: int, n: int) -> np.ndarray:
    """(2K, n) basis for the integer shifts 0..n-1 (cached: the same for every query)."""
    basis = shift_basis(np.arange(n, dtype=np.float64), K, n)
    basis.setflags(write=False)
    return basis


def shift_basis(shifts: np.ndarray, K: int, n: int) -> np.ndarray:
    """(..., 2K, m) real basis: [2 cos(2 pi k s / n); -2 sin(2 pi k s / n)] for shifts (..., m).

    With P = [Re P_k, Im P_k] (2K columns), ``P @ basis`` is ``M(s) = 2 Re sum_k P_k e^{2 pi i k s/n}``.
    """
    theta = (2.0 * np.pi / n) * np.arange(1, K + 1)[:, None] * shifts[..., None, :]
    return np.concatenate([2.0 * np.cos(theta), -2.0 * np.sin(theta)], axis=-2)
