"""Compiled (numba) kernel of the elastic distance (:mod:`.elastic`): the same arithmetic as
its numpy reference, :func:`.elastic.elastic_reference`, operation for operation but for
the order of a few sums and ``e^{i k theta}`` as a grid table times a phase turn (agreement to
~1e-12; tests/test_elastic.py).

One call computes a query's distance to many posed rows: per row, the signatures of both
curves at their half-shifted phases (:func:`signature`) and the banded dynamic programme
over their correspondence (:func:`banded_dtw`). ``cache=True`` and ``nogil=True`` as the
exact kernels (:mod:`._kernels`); compiled ahead of time with them (:mod:`.aot`).
"""

from __future__ import annotations

import numpy as np
from numba import njit

__all__ = ["signature", "grid_basis", "banded_dtw", "elastic_rows"]

_jit = {"cache": True, "nogil": True, "error_model": "numpy"}


@njit(**_jit)
def signature(C, phase, offsets, oriented_area, basis, points, tangents, out):
    """The local signature of the curve of half-band ``C`` ((K, 3) complex128) sampled at
    ``t_j = j / N + phase`` (N = ``out.shape[0]``) into ``out`` ((N, 4 len(offsets) + 1)
    float64); ``basis``: (N, K) complex128, ``e^{2 pi i (k + 1) j / N}`` (:func:`grid_basis`);
    ``points``, ``tangents``: (N, 3) float64 work arrays."""
    n = out.shape[0]
    K = C.shape[0]
    # the phase turns each coefficient once, so the sum over the grid has no chain of
    # products from one harmonic to the next (the samples' sums are independent)
    turned = np.empty((K, 3), dtype=np.complex128)
    for k in range(K):
        theta = 2.0 * np.pi * (k + 1) * phase
        rotation = complex(np.cos(theta), np.sin(theta))
        for d in range(3):
            turned[k, d] = C[k, d] * rotation
    for j in range(n):
        p0, p1, p2 = 0.0, 0.0, 0.0
        q0, q1, q2 = 0.0, 0.0, 0.0
        for k in range(K):
            er, ei = basis[j, k].real, basis[j, k].imag
            w = 2.0 * np.pi * (k + 1)
            c = turned[k, 0]
            p0 += c.real * er - c.imag * ei
            q0 -= w * (c.real * ei + c.imag * er)
            c = turned[k, 1]
            p1 += c.real * er - c.imag * ei
            q1 -= w * (c.real * ei + c.imag * er)
            c = turned[k, 2]
            p2 += c.real * er - c.imag * ei
            q2 -= w * (c.real * ei + c.imag * er)
        points[j, 0], points[j, 1], points[j, 2] = 2.0 * p0, 2.0 * p1, 2.0 * p2
        tangents[j, 0], tangents[j, 1], tangents[j, 2] = 2.0 * q0, 2.0 * q1, 2.0 * q2
    square = 0.0
    a0, a1, a2 = 0.0, 0.0, 0.0
    for j in range(n):
        p0, p1, p2 = points[j, 0], points[j, 1], points[j, 2]
        t0, t1, t2 = tangents[j, 0], tangents[j, 1], tangents[j, 2]
        square += p0 * p0 + p1 * p1 + p2 * p2
        a0 += p1 * t2 - p2 * t1
        a1 += p2 * t0 - p0 * t2
        a2 += p0 * t1 - p1 * t0
    rms = np.sqrt(square / n)
    length = np.sqrt(a0 * a0 + a1 * a1 + a2 * a2)
    oriented = rms > 0.0 and 0.5 * length / n > oriented_area * rms * rms
    if oriented:
        a0, a1, a2 = a0 / length, a1 / length, a2 / length
    m = offsets.shape[0]
    for i in range(n):
        t0, t1, t2 = tangents[i, 0], tangents[i, 1], tangents[i, 2]
        speed = np.sqrt(t0 * t0 + t1 * t1 + t2 * t2)
        if speed > 0.0:
            t0, t1, t2 = t0 / speed, t1 / speed, t2 / speed
        else:
            t0, t1, t2 = 0.0, 0.0, 0.0
        l0, l1, l2 = a1 * t2 - a2 * t1, a2 * t0 - a0 * t2, a0 * t1 - a1 * t0
        for g in range(m):
            for side in range(2):
                other = (i + offsets[g]) % n if side == 0 else (i - offsets[g]) % n
                x = points[other, 0] - points[i, 0]
                y = points[other, 1] - points[i, 1]
                z = points[other, 2] - points[i, 2]
                chord = np.sqrt(x * x + y * y + z * z)
                along, across = 0.0, 0.0
                if chord > 0.0:
                    inverse = 1.0 / chord
                    if oriented:
                        along = (x * l0 + y * l1 + z * l2) * inverse
                        across = (x * a0 + y * a1 + z * a2) * inverse
                    else:
                        projected = x * t0 + y * t1 + z * t2
                        rest = chord * chord - projected * projected
                        along = np.sqrt(rest if rest > 0.0 else 0.0) * inverse
                out[i, 4 * g + 2 * side] = along
                out[i, 4 * g + 2 * side + 1] = across
        radius = np.sqrt(points[i, 0] ** 2 + points[i, 1] ** 2 + points[i, 2] ** 2)
        out[i, 4 * m] = radius / rms if rms > 0.0 else 0.0


@njit(**_jit)
def grid_basis(n, K):
    """``e^{2 pi i (k + 1) j / n}``: (n, K) complex128, once per call of :func:`elastic_rows`."""
    basis = np.empty((n, K), dtype=np.complex128)
    for j in range(n):
        for k in range(K):
            theta = 2.0 * np.pi * ((k + 1) * j % n) / n
            basis[j, k] = complex(np.cos(theta), np.sin(theta))
    return basis


@njit(**_jit)
def banded_dtw(a, b, band, cost, total):
    """Closed symmetric dynamic time warping of signatures ``a``, ``b`` ((N, F) float64):
    a cyclic path through (0, 0) within ``|i - j| <= band``. A step between cells u and v
    costs ``(c_u + c_v) / 2`` times its weight, 2 for a diagonal step, 1 otherwise (c the
    L1 difference of the two points), so the cost does not depend on the direction the path
    is walked; it leaves (0, 0) by the diagonal step to (1, 1) and closes by the diagonal
    step from (N-1, N-1), so a path walked backwards is a path too. The total over 2N.
    ``cost``, ``total``: (N, 2 band + 1) float64 work arrays."""
    n, F = a.shape
    width = 2 * band + 1
    for i in range(n):
        for o in range(width):
            j = i + o - band
            if j < 0 or j >= n:
                cost[i, o] = np.inf
                continue
            c = 0.0
            for f in range(F):
                c += abs(a[i, f] - b[j, f])
            cost[i, o] = c
    for i in range(n):
        for o in range(width):
            j = i + o - band
            if j < 0 or j >= n or (i == 0) != (j == 0):
                total[i, o] = np.inf
                continue
            if i == 0:
                total[i, o] = 0.0
                continue
            c = cost[i, o]
            best = np.inf
            if i > 0 and j > 0:
                best = total[i - 1, o] + (cost[i - 1, o] + c)
            if i > 0 and o + 1 < width:
                v = total[i - 1, o + 1] + 0.5 * (cost[i - 1, o + 1] + c)
                if v < best:
                    best = v
            if o > 0:
                v = total[i, o - 1] + 0.5 * (cost[i, o - 1] + c)
                if v < best:
                    best = v
            total[i, o] = best
    return (total[n - 1, band] + cost[n - 1, band] + cost[0, band]) / (2.0 * n)


@njit(**_jit)
def elastic_rows(A, B, fractions, offsets, samples, band, oriented_area, out):
    """``out[r]``: the elastic distance of the query ``A`` ((K, 3) complex128) to row ``r``
    of ``B`` ((M, K, 3) complex128, posed: reversed and mirrored as the rigid optimum says),
    the query sampled at ``-fractions[r] / 2``, the row at ``+fractions[r] / 2`` (fractions of
    the perimeter: the rigid optimum's start shift, in [-1/2, 1/2))."""
    F = 4 * offsets.shape[0] + 1
    sa = np.empty((samples, F))
    sb = np.empty((samples, F))
    points = np.empty((samples, 3))
    tangents = np.empty((samples, 3))
    cost = np.empty((samples, 2 * band + 1))
    total = np.empty((samples, 2 * band + 1))
    basis = grid_basis(samples, A.shape[0])
    for r in range(B.shape[0]):
        signature(A, -0.5 * fractions[r], offsets, oriented_area, basis, points, tangents, sa)
        signature(B[r], 0.5 * fractions[r], offsets, oriented_area, basis, points, tangents, sb)
        out[r] = banded_dtw(sa, sb, band, cost, total)
