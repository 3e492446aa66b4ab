"""Invariant features and the lower bound of the distance they give (docs/method.md,
"Lower bounds")."""

from __future__ import annotations


import numpy as np

from .common import _weights


# --------------------------------------------------------------------------- bounds

def invariants(coefficients: np.ndarray, weights=None) -> dict[str, np.ndarray]:
    """Shift-, rotation-, reflection- and reversal-invariant features of descriptors.

    Parameters
    ----------
    coefficients : (..., K, 3) complex, normalized half-bands.
    weights : (K,) or None.

    Returns
    -------
    ``{"norm": (..., K), "sv": (..., 2K), "block": (..., 3)}`` float64, scaled so that
    the Euclidean distance between two curves' features is a lower bound of mu
    (docs/method.md, "Lower bounds": norms, Mirsky on each [Re A_k, Im A_k], and on all blocks).
    """
    C = np.asarray(coefficients, dtype=np.complex128)
    K = C.shape[-2]
    w = _weights(weights, K)
    root = np.sqrt(2.0 * w)
    blocks = np.stack([C.real, C.imag], axis=-1)                          # (..., K, 3, 2)
    norm = np.linalg.norm(C, axis=-1) * root
    sv = np.linalg.svd(blocks, compute_uv=False) * root[:, None]          # (..., K, 2)
    wide = (blocks * np.sqrt(w)[:, None, None]).swapaxes(-3, -2).reshape(*C.shape[:-2], 3, 2 * K)
    block = np.linalg.svd(wide, compute_uv=False) * np.sqrt(2.0)
    return {"norm": norm, "sv": sv.reshape(*C.shape[:-2], 2 * K), "block": block}


def lower_bound(A: np.ndarray, B: np.ndarray, weights=None) -> np.ndarray:
    """max of the three invariant lower bounds of mu(A, B): A (K, 3), B (..., K, 3) -> (...,)."""
    ia, ib = invariants(A, weights), invariants(B, weights)
    return np.max([np.linalg.norm(ib[key] - ia[key], axis=-1) for key in ia], axis=0)
