"""Invariant features and the lower bound of the distance they give (docs/method.md,
"Lower bounds")."""

from __future__ import annotations

from typing import TYPE_CHECKING


import numpy as np

from .common import _weights

if TYPE_CHECKING:
    from numpy.typing import ArrayLike


# --------------------------------------------------------------------------- bounds


def invariants(coefficients: np.ndarray, weights: ArrayLike | None = None) -> dict[str, np.ndarray]:
    """Shift-, rotation-, reflection- and reversal-invariant features of descriptors.

    Parameters
    ----------
    coefficients : (..., K, 3) complex, normalized half-bands.
    weights : (K,) or None.

    Returns
    -------
    ``{"norm": (..., K), "sv": (..., 2K), "block": (..., 3)}`` float64 (``block``: the three
    singular values of all blocks side by side, (3, 2K); with K = 1 the third is 0), scaled so that
    the Euclidean distance between two curves' features is a lower bound of mu
    (docs/method.md, "Lower bounds": norms, Mirsky on each [Re A_k, Im A_k], and on all blocks).
    """
    C = np.asarray(coefficients, dtype=np.complex128)
    K = C.shape[-2]
    w = _weights(weights, K)
    root = np.sqrt(2.0 * w)
    blocks = np.stack([C.real, C.imag], axis=-1)  # (..., K, 3, 2)
    norm = np.linalg.norm(C, axis=-1) * root
    sv = _singular_values_3x2(C.real, C.imag) * root[:, None]  # (..., K, 2)
    wide = (blocks * np.sqrt(w)[:, None, None]).swapaxes(-3, -2).reshape(*C.shape[:-2], 3, 2 * K)
    block = np.linalg.svd(wide, compute_uv=False) * np.sqrt(2.0)
    if block.shape[-1] < 3:  # K = 1: a 3x2 matrix has two singular values, the third is 0
        block = np.concatenate([block, np.zeros((*block.shape[:-1], 3 - block.shape[-1]))], axis=-1)
    return {"norm": norm, "sv": sv.reshape(*C.shape[:-2], 2 * K), "block": block}


def _singular_values_3x2(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Singular values, descending, of the 3x2 matrices ``[a b]`` (a, b: (..., 3)) -> (..., 2),
    as ``np.linalg.svd(..., compute_uv=False)`` gives them (to rounding), in closed form: the
    larger from the 2x2 Gram matrix's larger eigenvalue (no cancellation), the smaller as
    ``|a x b| / s1`` (the product of the two is the parallelogram's area), accurate even
    when it is tiny. Each matrix is first scaled by its largest entry, so that no square
    under- or overflows."""
    t = np.maximum(np.abs(a).max(axis=-1), np.abs(b).max(axis=-1))  # scaled to 1: no
    t = np.where(t > 0, t, 1.0)  # under- or overflow
    a, b = a / t[..., None], b / t[..., None]
    aa = np.einsum("...i,...i->...", a, a)
    bb = np.einsum("...i,...i->...", b, b)
    ab = np.einsum("...i,...i->...", a, b)
    s1 = np.sqrt(0.5 * (aa + bb) + np.hypot(0.5 * (aa - bb), ab))
    area = np.linalg.norm(np.cross(a, b), axis=-1)
    with np.errstate(divide="ignore", invalid="ignore"):
        s2 = np.where(s1 > 0, area / np.where(s1 > 0, s1, 1.0), 0.0)
    return np.stack([s1, np.minimum(s2, s1)], axis=-1) * t[..., None]


def lower_bound(A: np.ndarray, B: np.ndarray, weights: ArrayLike | None = None) -> np.ndarray:
    """max of the three invariant lower bounds of mu(A, B): A (K, 3), B (..., K, 3) -> (...,)."""
    ia, ib = invariants(A, weights), invariants(B, weights)
    return np.max([np.linalg.norm(ib[key] - ia[key], axis=-1) for key in ia], axis=0)
