"""The paper's step (Zhang & Fiume): limit planes aligned with the xy-plane, then for each
integer shift a rotation about z by the angle between bisectors. Kept to reproduce the paper."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from .common import INVARIANT
from .common import search_inputs

if TYPE_CHECKING:
    from numpy.typing import ArrayLike


# --------------------------------------------------------------------------- paper

_PAPER_VARIANTS = {
    # (transform in the aligned frame, conjugate?, reversed, mirrored). Reversal or a
    # reflection flips the limit-plane normal; the paper's alignment would flip it back
    # to +z, which is what the transform does.
    "forward": (np.eye(3), False, False, False),
    "reversed": (np.diag([1.0, -1.0, -1.0]), True, True, False),
    "mirrored": (np.diag([1.0, -1.0, 1.0]), False, False, True),
    "mirrored_reversed": (np.diag([1.0, 1.0, -1.0]), True, True, True),
}


def _bisector_angle(c1: np.ndarray) -> np.ndarray:
    """Angle in the xy-plane of the bisector of p = Re c1, q = -Im c1; c1 (..., 3) complex."""
    p, q = c1.real[..., :2], -c1.imag[..., :2]
    tiny = np.finfo(float).tiny
    h = p / np.maximum(np.linalg.norm(p, axis=-1, keepdims=True), tiny) + q / np.maximum(
        np.linalg.norm(q, axis=-1, keepdims=True), tiny
    )
    return np.arctan2(h[..., 1], h[..., 0])


def paper_search(
    A: np.ndarray,
    B: np.ndarray,
    samples: int,
    *,
    weights: ArrayLike | None = None,
    direction: str = INVARIANT,
    mirror: bool = False,
) -> dict[str, np.ndarray]:
    """The paper's matching step (Zhang & Fiume 2002, section 4.2.3), one query against many rows.

    Both ``A`` (K, 3) and ``B`` (N, K, 3) must be limit-plane aligned (as returned by
    :func:`~nfdmatch.descriptors.descriptors`). For each integer shift, b is rotated about
    z so that the bisectors of its (p, q) and a's coincide; the smallest distance wins.
    Not optimal, kept to reproduce the paper. Direction and mirror handling are ours:
    the reversed / reflected b is re-aligned to +z as the paper would, then searched the same way.

    Returns the same dict as :func:`exact_search`.
    """
    A, B, w, n = search_inputs(A, B, samples, weights, direction)
    N, K, _ = B.shape
    names = ["forward"] + (["reversed"] if direction == INVARIANT else [])
    if mirror:
        names += ["mirrored"] + (["mirrored_reversed"] if direction == INVARIANT else [])
    k = np.arange(1, K + 1)
    shifts = np.arange(n)
    phase = np.exp(2j * np.pi * np.outer(shifts, k) / n)  # (n, K)
    theta_a = _bisector_angle(A[0])
    best = {
        "distance": np.full(N, np.inf),
        "shift": np.zeros(N),
        "rotation": np.tile(np.eye(3), (N, 1, 1)),
        "reversed": np.zeros(N, bool),
        "mirrored": np.zeros(N, bool),
    }
    for name in names:
        T, conj, rev, mir = _PAPER_VARIANTS[name]
        Bv = (np.conj(B) if conj else B) @ T.T  # (N, K, 3)
        Bs = Bv[:, None, :, :] * phase[None, :, :, None]  # (N, n, K, 3)
        theta = theta_a - _bisector_angle(Bs[:, :, 0, :])  # (N, n)
        c, s = np.cos(theta), np.sin(theta)
        x = c[..., None] * Bs[..., 0] - s[..., None] * Bs[..., 1]
        y = s[..., None] * Bs[..., 0] + c[..., None] * Bs[..., 1]
        d2 = 2.0 * np.einsum(
            "k,nsk->ns", w, np.abs(A[:, 0] - x) ** 2 + np.abs(A[:, 1] - y) ** 2 + np.abs(A[:, 2] - Bs[..., 2]) ** 2
        )
        j = np.argmin(d2, axis=1)
        dist = np.sqrt(d2[np.arange(N), j])
        better = dist < best["distance"]
        th = theta[np.arange(N), j]
        Rz = np.zeros((N, 3, 3))
        Rz[:, 0, 0], Rz[:, 0, 1], Rz[:, 1, 0], Rz[:, 1, 1], Rz[:, 2, 2] = (
            np.cos(th),
            -np.sin(th),
            np.sin(th),
            np.cos(th),
            1.0,
        )
        best["distance"] = np.where(better, dist, best["distance"])
        best["shift"] = np.where(better, j.astype(float), best["shift"])
        best["rotation"] = np.where(better[:, None, None], Rz @ T, best["rotation"])
        best["reversed"] = np.where(better, rev, best["reversed"])
        best["mirrored"] = np.where(better, mir, best["mirrored"])
    return best
