"""Compiled (numba) kernels for :func:`nfdmatch.matching.exact_search`.

Optional: :mod:`nfdmatch.matching` imports this module lazily, only once a process has
enough exact work to amortize importing numba (~0.2-0.3 s), and falls back to its numpy
path (the reference) when numba is missing or fails. Nothing else imports it.

Numerics: the formulas of ``matching.trace_soa`` / ``_lmax_soa`` / ``_refine_shifts``
operation for operation (largest eigenvalues of M^T M and of the cofactor Gram by the
trigonometric formula, sigma3 = det / (sigma1 sigma2), the same clipping, the same three
parabolic steps), no fastmath, numpy's NaN behaviour for maximum / minimum. What differs,
at the rounding level only:

* ``cos(arccos(r) / 3)`` is evaluated without library calls (fdlibm's arccos rational
  approximation, Taylor cosine; within 3 ulps of numpy) so that the loops over shifts
  vectorize -- numba has no vector libm here;
* M(s) = P @ basis sums in another order than BLAS, and uses the symmetries of the DFT
  basis (s <-> n - s, and for n divisible by 4 s <-> n/2 -+ s with even/odd frequencies),
  with an exactly reduced basis argument (2 pi ((k s) mod n) / n); the numpy basis rounds
  2 pi k s / n, ~1e-14 at k s ~ 2000;
* the refinement builds e^{i k theta} by complex multiplication from e^{i theta};
* the final rotation comes from a one-sided Jacobi SVD instead of LAPACK's; where the
  optimal rotation is not unique (rank(M) < 2, or a planar pair with mirror) either may be
  returned, with the same distance;
* among equal values the lower index wins (argpartition's order is unspecified); a row
  with fewer than C local maxima gets its lowest-index non-maxima as the remaining
  candidates (numpy: arbitrary ones). Both paths refine those too, which can change the
  result only when n is so coarse (n < ~10) that the refinement's premises do not hold.

F agrees with the numpy path to ~1e-14 relative; the distances (recomputed from the
residual at the chosen alignment) to ~1e-15, and the same shifts where the optimum is
unique (tests/test_matching.py).

Kernels
-------
``exact_rows`` (entry point, one compiled function ``_exact_rows`` per block of rows):
``_integer_rows`` -- per row and direction, P (9 x 2K) from the half-bands, M(s) at the n
integer shifts, F(s) = max_R tr(R M(s)), the best C local maxima over both directions with
their neighbours, without the (9, D, N, n) temporaries of the numpy path; the refine_below
test; ``_refine_rows`` -- ``_refine_shifts``, vectorized across candidates; the pick;
``_finish_rows`` -- the rotation and the residual distance at the chosen shift. One call
per exact_search keeps the Python overhead (held under the GIL) at ~40 us per call.

``grid_bound_rows`` (matching.grid_bound, the truncated-harmonic bound): per block of 32
rows, F on the coarse grid for every row and direction at once, then only the intervals
whose coarse value could reach the caller's limit on the fine grid. Here the loops run over
the block's rows (x directions), not over shifts: loops over the 8-24 shifts of one row are
too short to vectorize (AVX-512 takes 8 doubles and unrolls by 2-4), which left most
evaluations scalar (~35 ns each against ~13 ns). Compiled once per K' of the truncated
stages (4, 8) so that the sums over harmonics unroll, and once for any K'.

One formula is shared with the numpy path as plain Python: the Gram entries of
``_lmax_gram`` are ``common.gram_entries``, compiled here. Numba's cache below checks this
file only: after an edit to ``gram_entries``, clear it (``__pycache__/_kernels*.nbi``,
``*.nbc``) or touch this file; the ahead-of-time build checks both (:mod:`.aot`).

``cache=True``: the machine code is cached in ``__pycache__`` next to this file (or numba's
user-wide cache directory when that is not writable; with neither, numba raises on import
and matching falls back to numpy). ``nogil=True``: callers may run them from several
threads, and ``exact_rows`` can split the rows over a small thread pool (``workers``).
No ``parallel=True``: prange took ~45 s more to compile on first use for what plain threads
over row blocks give as well, and numba's workqueue threading layer aborts when parallel
kernels are entered from two threads at once (search_index runs queries on threads).
Numba-level inlining only for the trace helpers, ``_products`` and ``_shift_matrices`` (the
loops over shifts vectorize only then) and the grid bound's parts (``_bound_*``: its sums over
2K' unroll only with the kernel's K' as a constant); the rest are plain calls, which keeps
the first compile at ~10-15 s instead of ~20 s (+45 s with prange).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from . import _threads
from .common import gram_entries

_TINY = float(np.finfo(np.float64).tiny)
_THIRD = 1.0 / 3.0
_SIXTH = 1.0 / 6.0
_NINF = -np.inf
# offsets and step of the refinement (as matching._REFINE_MID_OFFSETS / _REFINE_FINE_STEP)
_MID0, _MID1, _MID2, _MID3, _MID4 = -2.0 / 16.0, -1.0 / 16.0, 0.0, 1.0 / 16.0, 2.0 / 16.0
_FINE = 1e-3
_REFINE_BLOCK = 64  # candidates refined together (vectorized across them)

_jit = dict(error_model="numpy")  # float division by zero gives inf / nan, as numpy
_inline = dict(inline="always", **_jit)


# ----------------------------------------------------------------------------- scalar helpers
# NaN handling as numpy's maximum / minimum: a NaN argument stays NaN.


@njit(**_inline)
def _atleast(x, lo):
    return lo if x < lo else x


@njit(**_inline)
def _atmost(x, hi):
    return hi if x > hi else x


# cos(arccos(r) / 3) without library calls. arccos as fdlibm's e_acos.c: rational
# approximation R(z) of (asin(x) - x) / x^3 on |x| <= 0.5, the three ranges as selects,
# without fdlibm's extra-precision split of s (~1 ulp); the cosine on [0, pi/3] by its
# Taylor series to x^18 (remainder < 2e-18).
_PIO2_HI = 1.57079632679489655800e00
_PIO2_LO = 6.12323399573676603587e-17
_PI = 3.14159265358979311600e00
_PS0, _PS1, _PS2 = 1.66666666666666657415e-01, -3.25565818622400915405e-01, 2.01212532134862925881e-01
_PS3, _PS4, _PS5 = -4.00555345006794114027e-02, 7.91534994289814532176e-04, 3.47933107596021167570e-05
_QS1, _QS2 = -2.40339491173441421878e00, 2.02094576023350569471e00
_QS3, _QS4 = -6.88283971605453293030e-01, 7.70381505559019352791e-02
_C1, _C2, _C3 = -1.0 / 2.0, 1.0 / 24.0, -1.0 / 720.0
_C4, _C5, _C6 = 1.0 / 40320.0, -1.0 / 3628800.0, 1.0 / 479001600.0
_C7, _C8, _C9 = -1.0 / 87178291200.0, 1.0 / 20922789888000.0, -1.0 / 6402373705728000.0


@njit(**_inline)
def cos_third_acos(r):
    """cos(arccos(r) / 3) for r in [-1, 1] (NaN stays NaN); within 3 ulps of numpy's."""
    ax = abs(r)
    small = ax < 0.5
    z = r * r if small else (1.0 - ax) * 0.5
    p = z * (_PS0 + z * (_PS1 + z * (_PS2 + z * (_PS3 + z * (_PS4 + z * _PS5)))))
    q = 1.0 + z * (_QS1 + z * (_QS2 + z * (_QS3 + z * _QS4)))
    rz = p / q
    s = math.sqrt(z)
    if small:
        theta = _PIO2_HI - (r - (_PIO2_LO - r * rz))
    elif r > 0.0:
        theta = 2.0 * (s + s * rz)
    else:
        theta = _PI - 2.0 * (s + (rz * s - _PIO2_LO))
    x = theta * _THIRD
    y = x * x
    return 1.0 + y * (_C1 + y * (_C2 + y * (_C3 + y * (_C4 + y * (_C5 + y * (_C6 + y * (_C7 + y * (_C8 + y * _C9))))))))


@njit(**_inline)
def _lmax(s00, s11, s22, s01, s02, s12):
    """matching._lmax_soa for one matrix."""
    q = (s00 + s11 + s22) * _THIRD
    d0 = s00 - q
    d1 = s11 - q
    d2 = s22 - q
    p = math.sqrt((d0 * d0 + d1 * d1 + d2 * d2 + 2.0 * (s01 * s01 + s02 * s02 + s12 * s12)) * _SIXTH)
    det = d0 * (d1 * d2 - s12 * s12) - s01 * (s01 * d2 - s12 * s02) + s02 * (s01 * s12 - d1 * s02)
    r = _atmost(_atleast(det / _atleast(2.0 * p * p * p, _TINY), -1.0), 1.0)
    return _atleast(q + 2.0 * p * cos_third_acos(r), 0.0)


_gram_entries = njit(**_inline)(gram_entries)


@njit(**_inline)
def _lmax_gram(a, b, c, d, e, f, g, h, i):
    """matching._lmax_gram_soa for one matrix: the largest eigenvalue of X^T X."""
    s00, s11, s22, s01, s02, s12 = _gram_entries(a, b, c, d, e, f, g, h, i)
    return _lmax(s00, s11, s22, s01, s02, s12)


@njit(**_inline)
def trace1(a, b, c, d, e, f, g, h, i, mirror):
    """max_R tr(R M), M = [[a, b, c], [d, e, f], [g, h, i]]: matching.trace_soa for one matrix."""
    l1 = _lmax_gram(a, b, c, d, e, f, g, h, i)
    c00 = e * i - f * h
    c01 = f * g - d * i
    c02 = d * h - e * g
    c10 = c * h - b * i
    c11 = a * i - c * g
    c12 = b * g - a * h
    c20 = b * f - c * e
    c21 = c * d - a * f
    c22 = a * e - b * d
    det = a * c00 + b * c01 + c * c02
    l12 = _lmax_gram(c00, c01, c02, c10, c11, c12, c20, c21, c22)
    s1 = math.sqrt(l1)
    s12 = math.sqrt(l12)
    s2 = s12 / _atleast(s1, _TINY)
    third = _atmost(_atleast(det / _atleast(s12, _TINY), -s2), s2)
    if mirror:
        third = abs(third)
    return s1 + s2 + third


@njit(**_inline)
def _products(Aw, B, row, conj, P, c):
    """P[:, :, c] (2K, 9) = [Re; Im] of B_k[j] conj(A_k[i]) w_k (index 3 j + i) for one row, B
    conjugated for the reversed direction: M(s) = P^T @ basis(s), as exact_search's einsum."""
    K = Aw.shape[0]
    for k in range(K):
        for j in range(3):
            bk = B[row, k, j]
            if conj:
                bk = bk.conjugate()
            for i in range(3):
                z = bk * Aw[k, i]
                P[k, 3 * j + i, c] = z.real
                P[K + k, 3 * j + i, c] = z.imag


@njit(**_jit)
def _argmax_first(v0, v1, v2, v3, v4):
    """np.argmax of five values: the first maximum, or the first NaN."""
    best = 0
    top = v0
    if v0 != v0:
        return 0
    for t, v in enumerate((v1, v2, v3, v4)):
        if v != v:
            return t + 1
        if v > top:
            best = t + 1
            top = v
    return best


# ----------------------------------------------------------------------------- integer stage


@njit(**_inline)
def _add_terms(P, basis, jj, first, step, target, W):
    """W[target, s] += P[k, jj] basis[k, s] and W[target + 2, s] += P[K + k, jj] basis[K + k, s]
    for k = first, first + step, ... < K, in ascending k: the same sums in the same order as
    one term at a time, four terms per pass over s. One pass per term spent more on entering
    the loop (its alias checks) than on its five vector iterations (n = 128)."""
    K = P.shape[0] // 2
    width = basis.shape[1]
    k = first
    while k + 3 * step < K:
        k1 = k + step
        k2 = k + 2 * step
        k3 = k + 3 * step
        r0, r1, r2, r3 = P[k, jj, 0], P[k1, jj, 0], P[k2, jj, 0], P[k3, jj, 0]
        i0, i1, i2, i3 = P[K + k, jj, 0], P[K + k1, jj, 0], P[K + k2, jj, 0], P[K + k3, jj, 0]
        for s in range(width):
            w = W[target, s] + r0 * basis[k, s]
            w = w + r1 * basis[k1, s]
            w = w + r2 * basis[k2, s]
            W[target, s] = w + r3 * basis[k3, s]
            v = W[target + 2, s] + i0 * basis[K + k, s]
            v = v + i1 * basis[K + k1, s]
            v = v + i2 * basis[K + k2, s]
            W[target + 2, s] = v + i3 * basis[K + k3, s]
        k += 4 * step
    while k < K:
        r0 = P[k, jj, 0]
        i0 = P[K + k, jj, 0]
        for s in range(width):
            W[target, s] += r0 * basis[k, s]
            W[target + 2, s] += i0 * basis[K + k, s]
        k += step


@njit(**_inline)
def _shift_matrices(P, basis, quarter, W, M):
    """M (9, n) = the products P (2K, 9, 1) times the integer-shift basis, through the folded
    basis (2K, width): columns s = 0..n/4 (``quarter``, n divisible by 4) or 0..n/2 of
    [2 cos(2 pi k s / n); -2 sin(2 pi k s / n)], zero-padded.

    Half fold: the cosine (W0) and sine (W2) sums at s give M(s) = W0 + W2 and
    M(n - s) = W0 - W2. Quarter fold: also split even (W0, W2) and odd (W1, W3) frequencies;
    with n = 4q, e^{i pi k} = (-1)^k gives M(s), M(n - s), M(2q - s), M(2q + s).
    """
    n = M.shape[1]
    width = basis.shape[1]
    for jj in range(9):
        for s in range(width):
            W[0, s] = 0.0
            W[1, s] = 0.0
            W[2, s] = 0.0
            W[3, s] = 0.0
        if quarter:
            _add_terms(P, basis, jj, 0, 2, 1, W)  # k = 0, 2, ..: frequencies 1, 3, .. (odd)
            _add_terms(P, basis, jj, 1, 2, 0, W)
            q = n // 4
            h = 2 * q
            for s in range(q + 1):
                M[jj, s] = (W[0, s] + W[1, s]) + (W[2, s] + W[3, s])
            for s in range(1, q + 1):
                M[jj, n - s] = (W[0, s] + W[1, s]) - (W[2, s] + W[3, s])
            for s in range(q):
                M[jj, h - s] = (W[0, s] - W[1, s]) - (W[2, s] - W[3, s])
            for s in range(1, q):
                M[jj, h + s] = (W[0, s] - W[1, s]) + (W[2, s] - W[3, s])
        else:
            _add_terms(P, basis, jj, 0, 1, 0, W)
            for s in range(n // 2 + 1):
                M[jj, s] = W[0, s] + W[2, s]
            for s in range(1, (n + 1) // 2):
                M[jj, n - s] = W[0, s] - W[2, s]


@njit(**_jit)
def _integer_rows(Aw, B, D, basis, quarter, n, mirror, C, cand, val, fminus, fplus, reach, fmax, lo, hi):
    """Rows lo..hi of B: their C best local maxima of F over shifts and directions, written
    at index row - lo of cand (d * n + s), val (F there, -inf if not a local maximum),
    fminus / fplus (F at s -+ 1), reach (the largest F at s - 2..s + 2; inf if one is NaN)
    and fmax (the largest local maximum)."""
    K = Aw.shape[0]
    P = np.empty((2 * K, 9, 1))
    W = np.empty((4, basis.shape[1]))
    M = np.empty((9, n))
    F = np.empty(D * n)
    FM = np.empty(D * n)
    top_idx = np.zeros(C, dtype=np.int64)
    top_val = np.empty(C)
    for row in range(lo, hi):
        for dd in range(D):
            _products(Aw, B, row, dd == 1, P, 0)
            _shift_matrices(P, basis, quarter, W, M)
            base = dd * n
            for s in range(n):  # no calls: vectorizes over s
                F[base + s] = trace1(
                    M[0, s], M[1, s], M[2, s], M[3, s], M[4, s], M[5, s], M[6, s], M[7, s], M[8, s], mirror
                )
        # the C largest local maxima (periodic in s per direction): as argpartition on
        # Fm = where(local max, F, -inf), ties to the lower index
        for dd in range(D):
            base = dd * n
            last = base + n - 1
            for s in range(1, n - 1):  # vectorizes
                fv = F[base + s]
                FM[base + s] = fv if (fv >= F[base + s - 1] and fv >= F[base + s + 1]) else _NINF
            fv = F[base]
            FM[base] = fv if (fv >= F[last] and fv >= F[base + 1 if n > 1 else base]) else _NINF
            fv = F[last]
            FM[last] = fv if (fv >= F[last - 1 if n > 1 else last] and fv >= F[base]) else _NINF
        filled = 0
        best = _NINF
        for idx in range(D * n):
            v = FM[idx]
            if v > best:
                best = v
            if filled < C:
                pos = filled
                filled += 1
            elif v > top_val[C - 1]:
                pos = C - 1
            else:
                continue
            while pos > 0 and v > top_val[pos - 1]:
                top_val[pos] = top_val[pos - 1]
                top_idx[pos] = top_idx[pos - 1]
                pos -= 1
            top_val[pos] = v
            top_idx[pos] = idx
        r = row - lo
        fmax[r] = best
        for c in range(C):
            idx = top_idx[c]
            dd = idx // n
            s = idx - dd * n
            cand[r, c] = idx
            val[r, c] = top_val[c]
            fminus[r, c] = F[dd * n + (s - 1) % n]
            fplus[r, c] = F[dd * n + (s + 1) % n]
            most = F[idx]
            for j in range(-2, 3):
                v = F[dd * n + (s + j) % n]
                if v != v:
                    most = np.inf
                    break
                if v > most:
                    most = v
            reach[r, c] = most


# ----------------------------------------------------------------------------- refinement


@njit(**_jit)
def _evaluate(P, x, m, n, mirror, CR, CI, ZR, ZI, MA, out):
    """out[c] = F at shift x[c] for the candidates c < m with products P (2K, 9, block):
    matching.shift_basis + trace_soa, vectorized across candidates."""
    K = P.shape[0] // 2
    w0 = 2.0 * math.pi / n
    for c in range(m):
        theta = w0 * x[c]
        ZR[c] = math.cos(theta)
        ZI[c] = math.sin(theta)
        CR[c] = ZR[c]
        CI[c] = ZI[c]
    for jj in range(9):
        for c in range(m):
            MA[jj, c] = 0.0
    for k in range(K):
        if k > 0:  # e^{i (k+1) theta} = e^{i k theta} e^{i theta}
            for c in range(m):
                cr = CR[c] * ZR[c] - CI[c] * ZI[c]
                CI[c] = CR[c] * ZI[c] + CI[c] * ZR[c]
                CR[c] = cr
        for jj in range(9):
            for c in range(m):
                MA[jj, c] += P[k, jj, c] * (2.0 * CR[c]) + P[K + k, jj, c] * (-2.0 * CI[c])
    for c in range(m):
        out[c] = trace1(
            MA[0, c], MA[1, c], MA[2, c], MA[3, c], MA[4, c], MA[5, c], MA[6, c], MA[7, c], MA[8, c], mirror
        )


@njit(**_jit)
def _parabola(x, h, f_minus, f_0, f_plus):
    """matching._parabola for scalars: (location, value, concave)."""
    curvature = f_plus - 2.0 * f_0 + f_minus
    slope = 0.5 * (f_plus - f_minus)
    concave = curvature < 0
    if concave:
        t = _atmost(_atleast(-slope / curvature, -1.0), 1.0)
        value = f_0 + t * slope + 0.5 * t * t * curvature
    else:
        t = 0.0
        value = f_0 + t * slope + 0.5 * t * t * 0.0
    return x + t * h, value, concave


@njit(**_jit)
def _refine_rows(Aw, B, rows, dirs, s0, f_minus, f_0, f_plus, n, mirror, shift, value, lo, hi):
    K = Aw.shape[0]
    bs = _REFINE_BLOCK
    P = np.empty((2 * K, 9, bs))
    X = np.empty((8, bs))  # the 5 mid points, then the 3 fine ones
    FX = np.empty((8, bs))
    X2 = np.empty(bs)
    CR = np.empty(bs)
    CI = np.empty(bs)
    ZR = np.empty(bs)
    ZI = np.empty(bs)
    MA = np.empty((9, bs))
    for b0 in range(lo, hi, bs):
        m = min(bs, hi - b0)
        for c in range(m):
            g = b0 + c
            _products(Aw, B, rows[g], dirs[g] == 1, P, c)
            x1, _v, _c = _parabola(s0[g], 1.0, f_minus[g], f_0[g], f_plus[g])
            X[0, c] = x1 + _MID0
            X[1, c] = x1 + _MID1
            X[2, c] = x1 + _MID2
            X[3, c] = x1 + _MID3
            X[4, c] = x1 + _MID4
        for t in range(5):
            _evaluate(P, X[t], m, n, mirror, CR, CI, ZR, ZI, MA, FX[t])
        for c in range(m):
            j = _argmax_first(FX[0, c], FX[1, c], FX[2, c], FX[3, c], FX[4, c])
            j = 1 if j < 1 else (3 if j > 3 else j)
            x2, _v, _c = _parabola(X[j, c], _MID1 - _MID0, FX[j - 1, c], FX[j, c], FX[j + 1, c])
            X2[c] = x2
            X[5, c] = x2 + (-_FINE)
            X[6, c] = x2 + 0.0
            X[7, c] = x2 + _FINE
        for t in range(5, 8):
            _evaluate(P, X[t], m, n, mirror, CR, CI, ZR, ZI, MA, FX[t])
        for c in range(m):
            g = b0 + c
            x3, f3, concave = _parabola(X2[c], _FINE, FX[5, c], FX[6, c], FX[7, c])
            # as np.argmax over [s0, mid (5), fine (3), x3]: first maximum, or first NaN
            bx = s0[g]
            bv = f_0[g]
            if bv == bv:
                for t in range(8):
                    v = FX[t, c]
                    if v != v:
                        bx = X[t, c]
                        bv = v
                        break
                    if v > bv:
                        bx = X[t, c]
                        bv = v
                if bv == bv:
                    v = f3 if concave else _NINF
                    if v != v or v > bv:
                        bx = x3
                        bv = v
            shift[g] = bx
            value[g] = bv


# ----------------------------------------------------------------------------- final alignment

_JACOBI_SWEEPS = 40


@njit(**_jit)
def _jacobi(M, X, V):
    """One-sided Jacobi for _kabsch: X = M V (V proper), with mutually orthogonal columns."""
    for a in range(3):
        for b in range(3):
            X[a, b] = M[a, b]
            V[a, b] = 1.0 if a == b else 0.0
    for _sweep in range(_JACOBI_SWEEPS):
        rotated = False
        for pair in range(3):
            p = 0 if pair < 2 else 1
            q = 1 if pair == 0 else 2
            alpha = X[0, p] * X[0, p] + X[1, p] * X[1, p] + X[2, p] * X[2, p]
            beta = X[0, q] * X[0, q] + X[1, q] * X[1, q] + X[2, q] * X[2, q]
            gamma = X[0, p] * X[0, q] + X[1, p] * X[1, q] + X[2, p] * X[2, q]
            if not abs(gamma) > 1e-16 * math.sqrt(alpha * beta):
                continue
            zeta = (beta - alpha) / (2.0 * gamma)
            t = 1.0 / (abs(zeta) + math.sqrt(1.0 + zeta * zeta))
            if zeta < 0.0:
                t = -t
            c = 1.0 / math.sqrt(1.0 + t * t)
            s = c * t
            for r in range(3):
                xp = X[r, p]
                xq = X[r, q]
                X[r, p] = c * xp - s * xq
                X[r, q] = s * xp + c * xq
                vp = V[r, p]
                vq = V[r, q]
                V[r, p] = c * vp - s * vq
                V[r, q] = s * vp + c * vq
            rotated = True
        if not rotated:
            break


@njit(**_jit)
def _by_norm(X):
    """The columns of X sorted by norm, descending (insertion sort on 3): (o0, o1, o2, the
    largest norm, the sign that keeps V proper: -1 after an odd permutation)."""
    nrm0 = math.sqrt(X[0, 0] * X[0, 0] + X[1, 0] * X[1, 0] + X[2, 0] * X[2, 0])
    nrm1 = math.sqrt(X[0, 1] * X[0, 1] + X[1, 1] * X[1, 1] + X[2, 1] * X[2, 1])
    nrm2 = math.sqrt(X[0, 2] * X[0, 2] + X[1, 2] * X[1, 2] + X[2, 2] * X[2, 2])
    o0, o1, o2 = 0, 1, 2
    if nrm1 > nrm0:
        o0, o1 = o1, o0
        nrm0, nrm1 = nrm1, nrm0
    if nrm2 > nrm1:
        o1, o2 = o2, o1
        nrm1, nrm2 = nrm2, nrm1
        if nrm1 > nrm0:
            o0, o1 = o1, o0
            nrm0, nrm1 = nrm1, nrm0
    odd = (o0 == 1 and o1 == 0) or (o0 == 2 and o1 == 1) or (o0 == 0 and o1 == 2)  # one swap
    sgn = -1.0 if odd else 1.0
    return o0, o1, o2, nrm0, sgn


@njit(**_jit)
def _kabsch(M, mirror, X, V, R):
    """R (3, 3) maximizing tr(R M) over SO(3) (O(3) when mirror); returns True when R is a
    reflection. matching.kabsch_rotation without LAPACK: one-sided Jacobi on the columns
    of X = M V (V proper), sorted by norm; U = [x1 / |x1|, x2 orthogonalized, u1 x u2], so
    U^T M V = diag(s1, s2, s3') with s3' signed like det M; R = V U^T, with u3 flipped when
    mirror and s3' < 0. Where the optimum is not unique (rank < 2, or s3' = 0 with mirror)
    the choice may differ from LAPACK's, the trace not."""
    _jacobi(M, X, V)
    o0, o1, o2, nrm0, sgn = _by_norm(X)
    x1 = (X[0, o0], X[1, o0], X[2, o0])
    x2 = (X[0, o1], X[1, o1], X[2, o1])
    x3 = (sgn * X[0, o2], sgn * X[1, o2], sgn * X[2, o2])
    v1 = (V[0, o0], V[1, o0], V[2, o0])
    v2 = (V[0, o1], V[1, o1], V[2, o1])
    v3 = (sgn * V[0, o2], sgn * V[1, o2], sgn * V[2, o2])
    if nrm0 > 0.0:
        u1 = (x1[0] / nrm0, x1[1] / nrm0, x1[2] / nrm0)
    else:  # M = 0: R = I, as LAPACK's U = V = I
        u1 = v1
    d = u1[0] * x2[0] + u1[1] * x2[1] + u1[2] * x2[2]
    y = (x2[0] - d * u1[0], x2[1] - d * u1[1], x2[2] - d * u1[2])
    ny = math.sqrt(y[0] * y[0] + y[1] * y[1] + y[2] * y[2])
    if not ny > 1e-300 or (nrm0 == 0.0):
        # rank <= 1: any unit vector orthogonal to u1 (v2 when M = 0)
        if nrm0 == 0.0:
            y = v2
        else:
            ax, ay, az = abs(u1[0]), abs(u1[1]), abs(u1[2])
            if ax <= ay and ax <= az:
                e = (1.0, 0.0, 0.0)
            elif ay <= az:
                e = (0.0, 1.0, 0.0)
            else:
                e = (0.0, 0.0, 1.0)
            d = u1[0] * e[0] + u1[1] * e[1] + u1[2] * e[2]
            y = (e[0] - d * u1[0], e[1] - d * u1[1], e[2] - d * u1[2])
        ny = math.sqrt(y[0] * y[0] + y[1] * y[1] + y[2] * y[2])
    u2 = (y[0] / ny, y[1] / ny, y[2] / ny)
    u3 = (u1[1] * u2[2] - u1[2] * u2[1], u1[2] * u2[0] - u1[0] * u2[2], u1[0] * u2[1] - u1[1] * u2[0])
    s3 = u3[0] * x3[0] + u3[1] * x3[1] + u3[2] * x3[2]
    reflect = mirror and s3 < 0.0
    if reflect:
        u3 = (-u3[0], -u3[1], -u3[2])
    for a in range(3):
        for b in range(3):
            R[a, b] = v1[a] * u1[b] + v2[a] * u2[b] + v3[a] * u3[b]
    return reflect


@njit(**_jit)
def _finish_rows(A, Aw, w, B, dirs, shift, n, mirror, dist, rot, mirrored, lo, hi):
    """Rows lo..hi of B at direction dirs[row - lo] and start shift[row - lo]: the optimal
    rotation rot[row] (mirrored[row]: a reflection) and the residual distance dist[row]."""
    K = A.shape[0]
    w0 = 2.0 * math.pi / n
    Bs = np.empty((K, 3), dtype=np.complex128)
    M = np.empty((3, 3))
    X = np.empty((3, 3))
    V = np.empty((3, 3))
    R = np.empty((3, 3))
    for row in range(lo, hi):
        conj = dirs[row - lo] == 1
        for k in range(K):
            theta = w0 * (shift[row - lo] * (k + 1))
            ph = complex(math.cos(theta), math.sin(theta))
            for j in range(3):
                b = B[row, k, j]
                if conj:
                    b = b.conjugate()
                Bs[k, j] = b * ph
        for j in range(3):
            for i in range(3):
                acc = 0.0
                for k in range(K):
                    acc += (Bs[k, j] * Aw[k, i]).real
                M[j, i] = 2.0 * acc
        mirrored[row] = _kabsch(M, mirror, X, V, R)
        total = 0.0
        for k in range(K):
            part = 0.0
            for i in range(3):
                z = A[k, i] - (R[i, 0] * Bs[k, 0] + R[i, 1] * Bs[k, 1] + R[i, 2] * Bs[k, 2])
                part += z.real * z.real + z.imag * z.imag
            total += w[k] * part
        dist[row] = math.sqrt(2.0 * total)
        for a in range(3):
            for b in range(3):
                rot[row, a, b] = R[a, b]


# ----------------------------------------------------------------------------- the driver


@njit(**_jit)
def _argmax_row(values, r, C):
    """np.argmax(values[r, :C]): the first maximum, or the first NaN."""
    best = 0
    for c in range(C):
        v = values[r, c]
        if v != v:
            return c
        if v > values[r, best]:
            best = c
    return best


@njit(**_inline)
def _harmonic_norm(X, k):
    """|X_k|: the norm of harmonic k of a half-band X (K, 3) complex."""
    t = 0.0
    for j in range(3):
        t += X[k, j].real * X[k, j].real + X[k, j].imag * X[k, j].imag
    return math.sqrt(t)


@njit(**_jit)
def _refine_todo(A, w, B, n, fmax, refine_limit, lo, todo):
    """todo[r] = False where row lo + r cannot reach refine_limit (distance^2) by refining."""
    m = todo.shape[0]
    K = A.shape[0]
    # as exact_search: refining gains at most C2 / 8 on F, C2 bounding |F''|
    norm_a = np.empty(K)
    sq_a = 0.0
    for k in range(K):
        norm_a[k] = _harmonic_norm(A, k)
        sq_a += w[k] * norm_a[k] ** 2
    for r in range(m):
        curvature = 0.0
        sq_b = 0.0
        row = B[lo + r]
        for k in range(K):
            norm_b = _harmonic_norm(row, k)
            curvature += 2.0 * w[k] * (2.0 * math.pi * (k + 1) / n) ** 2 * norm_a[k] * norm_b
            sq_b += w[k] * norm_b**2
        lower2 = (2.0 * sq_a + 2.0 * sq_b) - 2.0 * (fmax[r] + curvature / 8.0)
        todo[r] = lower2 <= refine_limit


@njit(**_jit)
def _prune_candidates(A, w, B, n, val, reach, fmax, lo, todo):
    """todo[r, c] = False for the candidates whose refinement cannot overtake the row's best
    integer local maximum, so that it would never be picked: the same pick, shift and
    distance as refining all of them, for a third of the refinements.

    Why it is safe: the refinement evaluates F only within s0 -+ 1.2 (a first parabola
    within s0 -+ 1, five points -+ 1/8 around it, a second parabola -+ 1/16, fine points
    -+ 1e-3), and returns the best value it saw, or the last parabola's vertex. With
    C2 = sum_k 2 w_k (2 pi k / n)^2 |A_k| |B_k| bounding |f''| of every tr(R M(s)), F + C2 s^2 / 2
    is convex, so between two integer shifts F exceeds the larger end by at most C2 / 8:
    over s0 -+ 2, F <= reach + C2 / 8. The vertex exceeds its three points (1e-3 apart) by
    at most 1e-3 C1, C1 = sum_k 2 w_k (2 pi k / n) |A_k| |B_k| bounding |F'|. The best
    candidate's refined value is at least its integer value (the refinement starts there).
    A relative slack of 1e-9 covers the rounding of the F values compared."""
    m, C = todo.shape
    K = A.shape[0]
    norm_a = np.empty(K)
    for k in range(K):
        norm_a[k] = _harmonic_norm(A, k)
    for r in range(m):
        if not (fmax[r] > _NINF and fmax[r] < np.inf):
            continue  # no finite local maximum: every candidate as before
        best = _argmax_row(val, r, C)
        top = val[r, best]
        scale = 0.0
        first = 0.0
        second = 0.0
        row = B[lo + r]
        for k in range(K):
            product = 2.0 * w[k] * norm_a[k] * _harmonic_norm(row, k)
            frequency = 2.0 * math.pi * (k + 1) / n
            scale += product
            first += product * frequency
            second += product * frequency * frequency
        margin = second / 8.0 + _FINE * first + 1e-9 * (scale + abs(top))
        for c in range(C):
            if c != best and todo[r, c] and reach[r, c] + margin < top:
                todo[r, c] = False


@njit(**_jit)
def _refine_candidates(Aw, B, n, mirror, cand, shifts, val, fminus, fplus, todo, lo):
    """The candidates c of the rows lo + r with todo[r, c], refined: shifts and val updated."""
    m, C = cand.shape
    count = 0
    for r in range(m):
        for c in range(C):
            if todo[r, c]:
                count += 1
    rows = np.empty(count, dtype=np.int64)
    dirs = np.empty(count, dtype=np.int64)
    s0 = np.empty(count)
    f_m = np.empty(count)
    f_0 = np.empty(count)
    f_p = np.empty(count)
    t = 0
    for r in range(m):
        for c in range(C):
            if todo[r, c]:
                rows[t] = lo + r
                dirs[t] = cand[r, c] // n
                s0[t] = shifts[r, c]
                f_m[t] = fminus[r, c]
                f_0[t] = val[r, c]
                f_p[t] = fplus[r, c]
                t += 1
    new_shift = np.empty(count)
    new_value = np.empty(count)
    _refine_rows(Aw, B, rows, dirs, s0, f_m, f_0, f_p, n, mirror, new_shift, new_value, 0, count)
    t = 0
    for r in range(m):
        for c in range(C):
            if todo[r, c]:
                shifts[r, c] = new_shift[t]
                val[r, c] = new_value[t]
                t += 1


@njit(cache=True, nogil=True, **_jit)
def _exact_rows(
    A,
    Aw,
    w,
    B,
    D,
    basis,
    quarter,
    n,
    mirror,
    C,
    refine,
    refine_limit,
    prune,
    dist,
    shift,
    rot,
    reversed_,
    mirrored,
    lo,
    hi,
):
    """exact_search for rows lo..hi of B, all stages: integer candidates, the refine_below
    test, refinement (of the candidates that can still win, with ``prune``: the same result
    as refining all), the pick, the final alignment (as matching.exact_search's numpy path)."""
    m = hi - lo
    cand = np.empty((m, C), dtype=np.int64)
    val = np.empty((m, C))
    fminus = np.empty((m, C))
    fplus = np.empty((m, C))
    reach = np.empty((m, C))
    fmax = np.empty(m)
    _integer_rows(Aw, B, D, basis, quarter, n, mirror, C, cand, val, fminus, fplus, reach, fmax, lo, hi)
    shifts = np.empty((m, C))
    for r in range(m):
        for c in range(C):
            shifts[r, c] = float(cand[r, c] % n)
    if refine:
        rows_todo = np.ones(m, dtype=np.bool_)
        if refine_limit < np.inf:
            _refine_todo(A, w, B, n, fmax, refine_limit, lo, rows_todo)
        todo = np.empty((m, C), dtype=np.bool_)
        for r in range(m):
            for c in range(C):
                todo[r, c] = rows_todo[r]
        if prune:
            _prune_candidates(A, w, B, n, val, reach, fmax, lo, todo)
        _refine_candidates(Aw, B, n, mirror, cand, shifts, val, fminus, fplus, todo, lo)
    best_dir = np.empty(m, dtype=np.int64)
    best_shift = np.empty(m)
    for r in range(m):
        if not (fmax[r] > _NINF and fmax[r] < np.inf):  # no finite local maximum
            for c in range(C):
                val[r, c] = _NINF
        c = _argmax_row(val, r, C)
        best_dir[r] = cand[r, c] // n
        best_shift[r] = shifts[r, c]
    _finish_rows(A, Aw, w, B, best_dir, best_shift, n, mirror, dist, rot, mirrored, lo, hi)
    for r in range(m):
        x = best_shift[r] % n
        near = math.floor(x + 0.5)
        if abs(x - near) < 1e-9:  # 127.99999.. -> 0
            x = near
        shift[lo + r] = x % n
        reversed_[lo + r] = best_dir[r] == 1


def exact_rows(A, Aw, w, B, D, basis, quarter, n, mirror, C, refine, refine_limit, workers=1, prune=True):
    """matching.exact_search's compiled path for all rows of B (see ``_threads.exact_rows``)."""
    return _threads.exact_rows(
        _exact_rows, A, Aw, w, B, D, basis, quarter, n, mirror, C, refine, refine_limit, workers, prune
    )


# ----------------------------------------------------------------------------- grid bound

#: rows per block of the grid bound (its products and shift matrices stay in cache); the
#: loops over a block's rows (times directions) are the ones that vectorize
_BOUND_ROWS = 32


@njit(**_inline)
def _bound_products(Aw, B, b0, m, D, K, P):
    """P (9, 2K, m D): the products of rows b0..b0+m of B (as _products), column d m + r."""
    for d in range(D):
        for kk in range(K):
            for j in range(3):
                for i in range(3):
                    a = Aw[kk, i]
                    for r in range(m):
                        bk = B[b0 + r, kk, j]
                        if d == 1:
                            bk = bk.conjugate()
                        z = bk * a
                        P[3 * j + i, kk, d * m + r] = z.real
                        P[3 * j + i, K + kk, d * m + r] = z.imag


@njit(**_inline)
def _bound_coarse(P, Bc, W, K2, mirror, Mc, Fc):
    """Fc[c, rd] = F at coarse shift c for the W columns of P, through Mc (9, nc, W)."""
    for c in range(Bc.shape[1]):
        for jj in range(9):
            for rd in range(W):  # vectorizes: the sum over kk unrolls
                acc = 0.0
                for kk in range(K2):
                    acc += P[jj, kk, rd] * Bc[kk, c]
                Mc[jj, c, rd] = acc
        for rd in range(W):  # no calls: vectorizes over the block
            Fc[c, rd] = trace1(
                Mc[0, c, rd],
                Mc[1, c, rd],
                Mc[2, c, rd],
                Mc[3, c, rd],
                Mc[4, c, rd],
                Mc[5, c, rd],
                Mc[6, c, rd],
                Mc[7, c, rd],
                Mc[8, c, rd],
                mirror,
            )


@njit(**_inline)
def _bound_select(P, BT, Fc, b0, m, D, K2, ratio, slack_coarse, slack_fine, need, Mf, owner, U):
    """Per row r of the block: U[r] = the largest F + slack_coarse[b0 + r] over the coarse
    points not refined; the fine points of the refined ones (all but the centre, which is
    a coarse point) get their matrices in Mf and their row in owner. Returns their count."""
    n = BT.shape[0]
    nc = Fc.shape[0]
    half = ratio // 2
    nf = 0
    for r in range(m):
        row = b0 + r
        sc = slack_coarse[row]
        sf = slack_fine[row]
        u = _NINF
        for d in range(D):
            rd = d * m + r
            for c in range(nc):
                f = Fc[c, rd]
                if f + sc >= need[row] or f != f:
                    v = f + sf  # the coarse point is one of its fine points
                    for t in range(1, half + 1):  # the pair c -+ t at once
                        s1 = (c * ratio - t) % n
                        s2 = (c * ratio + t) % n
                        for jj in range(9):
                            a1 = 0.0
                            a2 = 0.0
                            for kk in range(K2):
                                p = P[jj, kk, rd]
                                a1 += p * BT[s1, kk]
                                a2 += p * BT[s2, kk]
                            Mf[jj, nf] = a1
                            Mf[jj, nf + 1] = a2
                        owner[nf] = r
                        owner[nf + 1] = r
                        nf += 2
                else:
                    v = f + sc
                if u == u and (v > u or v != v):
                    u = v
        U[r] = u
    return nf


@njit(**_inline)
def _bound_fine(Mf, nf, owner, slack_fine, b0, mirror, Ff, U):
    """U[r] = max(U[r], F + slack_fine) over the nf fine points of the block (NaN wins)."""
    for e in range(nf):  # vectorizes
        Ff[e] = trace1(Mf[0, e], Mf[1, e], Mf[2, e], Mf[3, e], Mf[4, e], Mf[5, e], Mf[6, e], Mf[7, e], Mf[8, e], mirror)
    for e in range(nf):
        r = owner[e]
        v = Ff[e] + slack_fine[b0 + r]
        u = U[r]
        if u == u and (v > u or v != v):
            U[r] = v


def _grid_bound_kernel(harmonics):
    """The compiled grid bound with K' = ``harmonics`` fixed at compile time (the sums over
    the 2K' basis rows unroll, which lets the loops over rows vectorize), or any K' for 0."""

    @njit(cache=True, nogil=True, **_jit)
    def grid_bound_rows(Aw, B, D, basis, ratio, mirror, slack_coarse, slack_fine, need, out, lo, hi):
        """Rows lo..hi of B: out[row] = max over the coarse shifts c ratio (c = 0..n/ratio-1)
        of F + slack_coarse[row], except that a coarse point whose value reaches need[row]
        (or is NaN) is replaced by its interval's fine points (c ratio - ratio // 2 .. c ratio +
        ratio // 2, mod n), each F + slack_fine[row]; F(s) = max_R tr(R M(s)) over both
        directions (D = 2) as in _integer_rows, M(s) = P^T basis[:, s]. NaN propagates."""
        K = harmonics if harmonics else Aw.shape[0]
        K2 = 2 * K
        n = basis.shape[1]
        nc = n // ratio
        R = _BOUND_ROWS
        Bc = np.empty((K2, nc))
        BT = np.empty((n, K2))
        for kk in range(K2):
            for c in range(nc):
                Bc[kk, c] = basis[kk, c * ratio]
            for s in range(n):
                BT[s, kk] = basis[kk, s]
        P = np.empty((9, K2, R * D))  # products, column d m + r
        Mc = np.empty((9, nc, R * D))
        Fc = np.empty((nc, R * D))
        fine = R * D * nc * (ratio - 1)
        Mf = np.empty((9, fine))
        Ff = np.empty(fine)
        owner = np.empty(fine, dtype=np.int64)
        U = np.empty(R)
        for b0 in range(lo, hi, R):
            m = min(R, hi - b0)
            _bound_products(Aw, B, b0, m, D, K, P)
            _bound_coarse(P, Bc, m * D, K2, mirror, Mc, Fc)
            nf = _bound_select(P, BT, Fc, b0, m, D, K2, ratio, slack_coarse, slack_fine, need, Mf, owner, U)
            _bound_fine(Mf, nf, owner, slack_fine, b0, mirror, Ff, U)
            for r in range(m):
                out[b0 + r] = U[r]

    return grid_bound_rows


_grid_bound_rows_any = _grid_bound_kernel(0)
_grid_bound_rows_4 = _grid_bound_kernel(4)
_grid_bound_rows_8 = _grid_bound_kernel(8)


def grid_bound_kernel(harmonics):
    """The compiled grid bound for K' harmonics (a specialised one for the stages' K')."""
    return {4: _grid_bound_rows_4, 8: _grid_bound_rows_8}.get(harmonics, _grid_bound_rows_any)


def grid_bound_rows(Aw, B, D, basis, ratio, mirror, slack_coarse, slack_fine, need, workers=1):
    """matching.grid_bound's compiled path: (N,) bound per row of B (see ``_threads.grid_bound_rows``)."""
    kernel = grid_bound_kernel(Aw.shape[0])
    return _threads.grid_bound_rows(kernel, Aw, B, D, basis, ratio, mirror, slack_coarse, slack_fine, need, workers)
