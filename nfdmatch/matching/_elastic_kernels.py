"""Compiled (numba) kernel of the elastic distance (:mod:`.elastic`): the same arithmetic as
its numpy reference, :func:`.elastic.elastic_reference`, operation for operation but for
the order of a few sums and ``e^{i k theta}`` as a grid table times a phase turn (agreement to
~1e-12; tests/test_elastic.py).

One call computes a query's distance to many posed rows: per row, the signatures of both
curves at their half-shifted phases (:func:`signature`) and the banded dynamic programme
over their correspondence (:func:`banded_dtw`). ``cache=True`` and ``nogil=True`` as the
exact kernels (:mod:`._kernels`); compiled ahead of time with them (:mod:`.aot`).

The arrays are laid out so that the long loops run over samples, contiguous, with the index a
loop counter (a slice's, not ``i + shift``, which numba checks for negative wrap-around):
the compiler then vectorises them. Each number is still summed in the same order as one
sample at a time, so the digits are those of the sample-by-sample loops they replaced (equal
to the bit on 12,690 pairs: bending 2-D and 3-D families, figure eights, lines, random
polygons; one pose 2.1x faster, docs/elastic.md "Cost").
"""

from __future__ import annotations

import numpy as np
from numba import njit

__all__ = ["signature", "grid_basis", "banded_dtw", "elastic_rows"]

_jit = {"cache": True, "nogil": True, "error_model": "numpy"}


@njit(**_jit)
def signature(C, phase, offsets, oriented_area, basis_re, basis_im, points, tangents, frame, out):
    """The local signature of the curve of half-band ``C`` ((K, 3) complex128) sampled at
    ``t_j = j / N + phase`` (N = ``out.shape[1]``) into ``out`` ((4 len(offsets) + 1, N)
    float64: a feature per row); ``basis_re``, ``basis_im``: (K, N) float64, the real and
    imaginary parts of ``e^{2 pi i (k + 1) j / N}`` (:func:`grid_basis`); ``points``,
    ``tangents``: (3, N) float64, ``frame``: (6, N) float64 work arrays."""
    n = out.shape[1]
    K = C.shape[0]
    points[:, :] = 0.0
    tangents[:, :] = 0.0
    for k in range(K):
        theta = 2.0 * np.pi * (k + 1) * phase
        rotation = complex(np.cos(theta), np.sin(theta))
        w = 2.0 * np.pi * (k + 1)
        for d in range(3):
            c = C[k, d] * rotation
            cr, ci = c.real, c.imag
            p = points[d]
            q = tangents[d]
            er = basis_re[k]
            ei = basis_im[k]
            for j in range(n):
                p[j] += cr * er[j] - ci * ei[j]
                q[j] -= w * (cr * ei[j] + ci * er[j])
    for d in range(3):
        for j in range(n):
            points[d, j] = 2.0 * points[d, j]
            tangents[d, j] = 2.0 * tangents[d, j]
    square = 0.0
    a0, a1, a2 = 0.0, 0.0, 0.0
    for j in range(n):
        p0, p1, p2 = points[0, j], points[1, j], points[2, j]
        t0, t1, t2 = tangents[0, j], tangents[1, j], tangents[2, j]
        square += p0 * p0 + p1 * p1 + p2 * p2
        a0 += p1 * t2 - p2 * t1
        a1 += p2 * t0 - p0 * t2
        a2 += p0 * t1 - p1 * t0
    rms = np.sqrt(square / n)
    length = np.sqrt(a0 * a0 + a1 * a1 + a2 * a2)
    oriented = rms > 0.0 and 0.5 * length / n > oriented_area * rms * rms
    if oriented:
        a0, a1, a2 = a0 / length, a1 / length, a2 / length
    # the frame of each sample: unit tangent (rows 0-2), in-plane normal l = a x t (rows 3-5)
    for i in range(n):
        t0, t1, t2 = tangents[0, i], tangents[1, i], tangents[2, i]
        speed = np.sqrt(t0 * t0 + t1 * t1 + t2 * t2)
        if speed > 0.0:
            t0, t1, t2 = t0 / speed, t1 / speed, t2 / speed
        else:
            t0, t1, t2 = 0.0, 0.0, 0.0
        frame[0, i], frame[1, i], frame[2, i] = t0, t1, t2
        frame[3, i], frame[4, i], frame[5, i] = a1 * t2 - a2 * t1, a2 * t0 - a0 * t2, a0 * t1 - a1 * t0
    m = offsets.shape[0]
    for g in range(m):
        for side in range(2):
            # the partner of sample i is i + step (mod n): offsets[g] ahead, or behind
            ahead = offsets[g] % n
            step = ahead if side == 0 else (n - ahead) % n
            along_row = out[4 * g + 2 * side]
            across_row = out[4 * g + 2 * side + 1]
            # the samples whose partner does not wrap round, then those whose does
            for part in range(2):
                lo = 0 if part == 0 else n - step
                hi = n - step if part == 0 else n
                there = lo + step if part == 0 else lo + step - n
                count = hi - lo
                x0, y0, z0 = points[0, lo:hi], points[1, lo:hi], points[2, lo:hi]
                end = there + count
                x1, y1, z1 = points[0, there:end], points[1, there:end], points[2, there:end]
                along_part = along_row[lo:hi]
                across_part = across_row[lo:hi]
                # the chord along l (oriented) or, without a plane, its part off the tangent
                first = 3 if oriented else 0
                fx, fy, fz = frame[first, lo:hi], frame[first + 1, lo:hi], frame[first + 2, lo:hi]
                for i in range(count):
                    x = x1[i] - x0[i]
                    y = y1[i] - y0[i]
                    z = z1[i] - z0[i]
                    chord = np.sqrt(x * x + y * y + z * z)
                    inverse = 1.0 / chord if chord > 0.0 else 0.0
                    dot = x * fx[i] + y * fy[i] + z * fz[i]
                    if oriented:
                        along_part[i] = dot * inverse
                        across_part[i] = (x * a0 + y * a1 + z * a2) * inverse
                    else:
                        rest = chord * chord - dot * dot
                        along_part[i] = np.sqrt(rest if rest > 0.0 else 0.0) * inverse
                        across_part[i] = 0.0
    for i in range(n):
        radius = np.sqrt(points[0, i] ** 2 + points[1, i] ** 2 + points[2, i] ** 2)
        out[4 * m, i] = radius / rms if rms > 0.0 else 0.0


@njit(**_jit)
def grid_basis(n, K):
    """``e^{2 pi i (k + 1) j / n}`` as its real and imaginary parts, each (K, n) float64;
    once per call of :func:`elastic_rows`."""
    re = np.empty((K, n))
    im = np.empty((K, n))
    for j in range(n):
        for k in range(K):
            theta = 2.0 * np.pi * ((k + 1) * j % n) / n
            re[k, j] = np.cos(theta)
            im[k, j] = np.sin(theta)
    return re, im


@njit(**_jit)
def banded_dtw(a, b, band, cost, total):
    """Closed symmetric dynamic time warping of signatures ``a``, ``b`` ((F, N) float64, a
    feature per row): a cyclic path through (0, 0) within ``|i - j| <= band``. A step between
    cells u and v costs ``(c_u + c_v) / 2`` times its weight, 2 for a diagonal step, 1
    otherwise (c the L1 difference of the two points), so the cost does not depend on the
    direction the path is walked; it leaves (0, 0) by the diagonal step to (1, 1) and closes
    by the diagonal step from (N-1, N-1), so a path walked backwards is a path too. The total
    over 2N. ``cost``: (2 band + 1, N) float64, the cost of cell (i, i + o - band) at
    ``[o, i]``; ``total``: (N, 2 band + 1) float64; work arrays."""
    F, n = a.shape
    width = 2 * band + 1
    for o in range(width):
        shift = o - band
        lo = max(0, -shift)
        hi = min(n, n - shift)
        row = cost[o]
        row[:] = np.inf
        part = row[lo:hi]
        part[:] = 0.0
        for f in range(F):
            here = a[f, lo:hi]
            there = b[f, lo + shift : hi + shift]
            for i in range(hi - lo):
                part[i] += abs(here[i] - there[i])
    for i in range(n):
        for o in range(width):
            j = i + o - band
            if j < 0 or j >= n or (i == 0) != (j == 0):
                total[i, o] = np.inf
                continue
            if i == 0:
                total[i, o] = 0.0
                continue
            c = cost[o, i]
            best = np.inf
            if i > 0 and j > 0:
                best = total[i - 1, o] + (cost[o, i - 1] + c)
            if i > 0 and o + 1 < width:
                v = total[i - 1, o + 1] + 0.5 * (cost[o + 1, i - 1] + c)
                if v < best:
                    best = v
            if o > 0:
                v = total[i, o - 1] + 0.5 * (cost[o - 1, i] + c)
                if v < best:
                    best = v
            total[i, o] = best
    return (total[n - 1, band] + cost[band, n - 1] + cost[band, 0]) / (2.0 * n)


@njit(**_jit)
def elastic_rows(A, B, fractions, offsets, samples, band, oriented_area, out):
    """``out[r]``: the elastic distance of the query ``A`` ((K, 3) complex128) to row ``r``
    of ``B`` ((M, K, 3) complex128, posed: reversed and mirrored as the rigid optimum says),
    the query sampled at ``-fractions[r] / 2``, the row at ``+fractions[r] / 2`` (fractions of
    the perimeter: the rigid optimum's start shift, in [-1/2, 1/2))."""
    F = 4 * offsets.shape[0] + 1
    sa = np.empty((F, samples))
    sb = np.empty((F, samples))
    points = np.empty((3, samples))
    tangents = np.empty((3, samples))
    frame = np.empty((6, samples))
    cost = np.empty((2 * band + 1, samples))
    total = np.empty((samples, 2 * band + 1))
    basis_re, basis_im = grid_basis(samples, A.shape[0])
    for r in range(B.shape[0]):
        signature(A, -0.5 * fractions[r], offsets, oriented_area, basis_re, basis_im, points, tangents, frame, sa)
        signature(B[r], 0.5 * fractions[r], offsets, oriented_area, basis_re, basis_im, points, tangents, frame, sb)
        out[r] = banded_dtw(sa, sb, band, cost, total)
