"""Brute-force reference implementations ("oracle") and test-curve generators.

Deliberately simple and independent of :mod:`nfdmatch` (plain numpy only).

Conventions (see docs/method.md):

* ``resample(points, m)``: uniform arc-length resampling of the closed polyline
  (closing edge included), sample ``j`` at arc length ``j * L / m`` from vertex 0.
* ``fd(samples) = np.fft.fft(samples, axis=0) / m``  (``A_k = 1/m sum_j a_j e^{-2 pi i jk/m}``).
* ``normalize(A, K)``: band = rows ``[1..K, m-K..m-1]`` of ``A``, i.e. signed
  frequencies ``freqs = [1, ..., K, -K, ..., -1]`` (numpy FFT order), divided by
  ``|A_1|`` ("a1") or by the RMS radius ``sqrt(sum_{k != 0} |A_k|^2)`` ("rms").
* Shift: ``B_k(s) = B_k * exp(+2 pi i s k / m)`` (k = signed frequency).  For an
  integer ``s`` this is the spectrum of ``np.roll(b, -s, axis=0)``, i.e. of the
  samples ``b_{(j+s) mod m}`` (start moved forward to vertex ``s``).
* Reversal: ``B_k -> conj(B_k)``, the spectrum of ``b_{(-j) mod m}``.  With a
  shift on top: samples ``b_{(-j-s) mod m}``.  ``b[::-1]`` is reversal + shift 1.
* Rotation: every oracle returns ``R`` with ``A_k ~= R @ B_k(s)``, i.e. ``R``
  maps B onto A.  In sample space (before scale normalisation):
  ``a_j - cent(a) ~= c * R @ (b_{(j+s) mod m} - cent(b))`` (forward) or
  ``... R @ (b_{(-j-s) mod m} - cent(b))`` (reversed).
* ``mu(A, B) = sqrt(sum_k w_k |A_k - B_k|^2)`` over the band.
"""

from __future__ import annotations

import numpy as np

__all__ = [
    # oracle
    "resample",
    "fd",
    "normalize",
    "descriptors",
    "mu",
    "shift_band",
    "reverse_band",
    "kabsch",
    "correlation_matrices",
    "oracle_integer",
    "oracle_fractional",
    "lower_bounds",
    # generators
    "random_smooth_curve",
    "random_rotation",
    "random_rigid_motion",
    "start_shift",
    "reverse",
    "resample_polyline",
    "torus_knot",
    "lissajous",
    "ellipse",
    "figure_eight_planar",
    "lemniscate_planar",
    "collinear_back_and_forth",
]

_DIRECTIONS = ("forward", "reversed")


# ---------------------------------------------------------------------------
# Descriptors
# ---------------------------------------------------------------------------


def resample(points, m, *, offset=0.0):
    """Uniform arc-length resampling of the closed polyline ``points`` (n,3).

    Sample ``j`` lies at arc length ``(offset + j/m) * L`` (mod L) measured from
    vertex 0 along ``a_0 -> a_1 -> ... -> a_{n-1} -> a_0``.  ``offset`` is a
    fraction of the perimeter (default 0: the method's convention).  Linear
    interpolation along segments; zero-length segments are harmless.
    """
    p = np.asarray(points, dtype=np.float64)
    closed = np.vstack([p, p[:1]])
    seg = np.linalg.norm(np.diff(closed, axis=0), axis=1)
    cum = np.concatenate([[0.0], np.cumsum(seg)])
    L = cum[-1]
    if not L > 0:
        raise ValueError("zero perimeter")
    out = np.empty((m, p.shape[1]))
    for j in range(m):
        t = ((offset + j / m) % 1.0) * L
        i = int(np.searchsorted(cum, t, side="right")) - 1
        i = min(max(i, 0), len(seg) - 1)
        while seg[i] == 0.0 and i > 0:  # only possible through rounding
            i -= 1
        f = (t - cum[i]) / seg[i]
        f = min(max(f, 0.0), 1.0)
        out[j] = closed[i] + f * (closed[i + 1] - closed[i])
    return out


def fd(samples):
    """Fourier descriptors ``np.fft.fft(samples, axis=0) / m`` (complex128)."""
    s = np.asarray(samples, dtype=np.float64)
    return np.fft.fft(s, axis=0) / s.shape[0]


def normalize(A, K, scale="a1"):
    """Return ``(band, freqs)``.

    ``band`` (2K,3) complex128 = rows ``1..K`` then ``m-K..m-1`` of ``A``,
    ``freqs`` = ``[1..K, -K..-1]``; divided by ``|A_1|`` (scale="a1") or by
    ``sqrt(sum_{k != 0} |A_k|^2)`` (scale="rms", the RMS radius of the samples).
    """
    A = np.asarray(A, dtype=np.complex128)
    m = A.shape[0]
    if not 2 * K < m:
        raise ValueError("need 2K < m")
    freqs = np.concatenate([np.arange(1, K + 1), np.arange(-K, 0)])
    band = A[freqs % m].copy()
    if scale == "a1":
        c = np.sqrt(np.sum(np.abs(A[1]) ** 2))
    elif scale == "rms":
        c = np.sqrt(np.sum(np.abs(A[1:]) ** 2))
    else:
        raise ValueError(scale)
    return band / c, freqs


def descriptors(points, m, K, scale="a1"):
    """``normalize(fd(resample(points, m)), K, scale)``."""
    return normalize(fd(resample(points, m)), K, scale)


def _weights(weights, nb):
    if weights is None:
        return np.ones(nb)
    w = np.asarray(weights, dtype=np.float64)
    assert w.shape == (nb,)
    return w


def mu(A, B, weights=None):
    """``sqrt(sum_k w_k |A_k - B_k|^2)`` over the band rows."""
    A = np.asarray(A)
    B = np.asarray(B)
    w = _weights(weights, A.shape[0])
    return float(np.sqrt(np.sum(w[:, None] * np.abs(A - B) ** 2)))


def shift_band(B, freqs, m, s):
    """``B_k * exp(2 pi i s k / m)`` (s may be fractional)."""
    ph = np.exp(2j * np.pi * s * np.asarray(freqs) / m)
    return np.asarray(B) * ph[:, None]


def reverse_band(B):
    """Band of the reversed traversal: ``conj(B_k)`` (samples ``b_{-j}``)."""
    return np.conj(B)


def kabsch(M, mirror=False):
    """Maximise ``trace(R @ M)``: ``M = U S V^T``, ``R = V diag(1,1,d) U^T``.

    ``d = sign(det(V U^T))`` (proper rotation) or ``d = 1`` if ``mirror``.
    Works batched over leading axes.  Returns ``(R, trace(R M))``.
    """
    U, S, Vt = np.linalg.svd(M)
    V = np.swapaxes(Vt, -1, -2)
    Ut = np.swapaxes(U, -1, -2)
    if mirror:
        d = np.ones(M.shape[:-2])
    else:
        d = np.sign(np.linalg.det(V @ Ut))
        d = np.where(d == 0, 1.0, d)
    D = np.zeros(M.shape)
    D[..., 0, 0] = 1.0
    D[..., 1, 1] = 1.0
    D[..., 2, 2] = d
    R = V @ D @ Ut
    tr = S[..., 0] + S[..., 1] + d * S[..., 2]
    return R, tr


def correlation_matrices(A, B, freqs, m, shifts, weights=None):
    """Brute force ``M(s) = Re sum_k w_k B_k(s) A_k^H`` for each s (3x3 each).

    ``trace(R M(s)) = Re sum_k w_k A_k^H R B_k(s)``.
    """
    w = _weights(weights, A.shape[0])
    shifts = np.asarray(shifts, dtype=np.float64)
    ph = np.exp(2j * np.pi * shifts[:, None] * np.asarray(freqs)[None, :] / m)
    Bs = B[None, :, :] * ph[:, :, None]  # (S, nb, 3)
    # M[s, j, i] = Re sum_k w_k Bs[s,k,j] conj(A[k,i])
    return np.real(np.einsum("k,skj,ki->sji", w, Bs, np.conj(A)))


def _check_dirs(directions):
    directions = tuple(directions)
    for d in directions:
        if d not in _DIRECTIONS:
            raise ValueError(d)
    return directions


def oracle_integer(A, B, freqs, m, *, directions=_DIRECTIONS, mirror=False, weights=None):
    """Exact min of ``mu(A, R B(s))`` over integer s in 0..m-1, directions, R.

    R in SO(3) (O(3) if ``mirror``).  Returns ``(dist, shift, R, reversed)``
    with ``A_k ~= R @ Bd_k * exp(2 pi i shift k/m)``, ``Bd = conj(B)`` if
    reversed else ``B``.  Distance is computed directly, for every shift.
    """
    A = np.asarray(A, dtype=np.complex128)
    B = np.asarray(B, dtype=np.complex128)
    best = (np.inf, None, None, None)
    shifts = np.arange(m)
    for direction in _check_dirs(directions):
        Bd = B if direction == "forward" else reverse_band(B)
        M = correlation_matrices(A, Bd, freqs, m, shifts, weights)
        R, _ = kabsch(M, mirror)
        for s in range(m):
            d = mu(A, (R[s] @ shift_band(Bd, freqs, m, s).T).T, weights)
            if d < best[0]:
                best = (d, int(s), R[s], direction == "reversed")
    return best


def oracle_fractional(A, B, freqs, m, *, upsample=32, directions=_DIRECTIONS, mirror=False, weights=None, n_direct=5):
    """As :func:`oracle_integer` over shifts ``s = j/upsample``, j in 0..upsample*m-1.

    ``M(s)`` for all grid shifts by one inverse FFT of length N = upsample*m per
    matrix entry: ``X[k mod N] = w_k B_k conj(A_k)^T``, ``M(j/upsample) =
    Re(N * ifft(X)[j])``.  Kabsch on all; trace formula ranks candidates; the
    direct ``mu`` is evaluated on the best ``n_direct`` per direction.
    Returns ``(dist, shift_float, R, reversed)`` (shift in [0, m)).
    """
    A = np.asarray(A, dtype=np.complex128)
    B = np.asarray(B, dtype=np.complex128)
    freqs = np.asarray(freqs)
    w = _weights(weights, A.shape[0])
    N = upsample * m
    nA2 = np.sum(w[:, None] * np.abs(A) ** 2)
    nB2 = np.sum(w[:, None] * np.abs(B) ** 2)
    best = (np.inf, None, None, None)
    for direction in _check_dirs(directions):
        Bd = B if direction == "forward" else reverse_band(B)
        X = np.zeros((N, 3, 3), dtype=np.complex128)
        terms = w[:, None, None] * Bd[:, :, None] * np.conj(A)[:, None, :]
        np.add.at(X, freqs % N, terms)
        M = np.real(np.fft.ifft(X, axis=0) * N)  # (N,3,3)
        R, tr = kabsch(M, mirror)
        mu2 = nA2 + nB2 - 2.0 * tr
        cand = np.argsort(mu2)[:n_direct]
        for j in cand:
            s = j / upsample
            d = mu(A, (R[j] @ shift_band(Bd, freqs, m, s).T).T, weights)
            if d < best[0]:
                best = (d, float(s), R[j], direction == "reversed")
    return best


def lower_bounds(A, B, freqs=None, weights=None):
    """Rotation/reflection/shift/reversal-invariant lower bounds on ``mu``.

    ``norm``:  sqrt(sum_k w_k (|A_k| - |B_k|)^2)
    ``sv``:    sqrt(sum_k w_k ||sigma(M_k^A) - sigma(M_k^B)||^2), M_k = [Re A_k, Im A_k] (3x2)
    ``block``: sqrt(sum_i (sigma_i(X^A) - sigma_i(X^B))^2), X = [sqrt(w_k) M_k ...] (3 x 4K)
    """
    A = np.asarray(A, dtype=np.complex128)
    B = np.asarray(B, dtype=np.complex128)
    w = _weights(weights, A.shape[0])
    nA = np.linalg.norm(A, axis=1)
    nB = np.linalg.norm(B, axis=1)
    norm = np.sqrt(np.sum(w * (nA - nB) ** 2))

    def blocks(C):
        return np.stack([C.real, C.imag], axis=2)  # (nb, 3, 2)

    sA = np.linalg.svd(blocks(A), compute_uv=False)  # (nb, 2)
    sB = np.linalg.svd(blocks(B), compute_uv=False)
    sv = np.sqrt(np.sum(w[:, None] * (sA - sB) ** 2))

    def big(C):
        Mk = blocks(C) * np.sqrt(w)[:, None, None]
        return np.concatenate(list(Mk), axis=1)  # (3, 2*nb)

    bA = np.linalg.svd(big(A), compute_uv=False)
    bB = np.linalg.svd(big(B), compute_uv=False)
    block = np.sqrt(np.sum((bA - bB) ** 2))
    return dict(norm=float(norm), sv=float(sv), block=float(block))


# ---------------------------------------------------------------------------
# Test-curve generators
# ---------------------------------------------------------------------------


def random_smooth_curve(rng, n_vertices=2000, n_harmonics=6, decay=1.5):
    """Random smooth closed 3-D curve, (n_vertices,3) float64.

    ``x(t) = sum_{k=1..H} a_k cos(2 pi k t) + b_k sin(2 pi k t)``, a_k, b_k
    random 3-vectors with std ``k**-decay``; evaluated at a monotone warp of
    uniform parameters (so vertices are not uniform in arc length).  The
    closing vertex is not repeated.
    """
    return smooth_curve_samplings(rng, [n_vertices], n_harmonics, decay)[0]


def smooth_curve_samplings(rng, counts, n_harmonics=6, decay=1.5):
    """One random smooth closed curve sampled several times: a list of (count, 3) float64,
    each at its own random monotone warp of the parameter (different vertex positions
    along the same curve, not a re-cut of a polyline)."""
    k = np.arange(1, n_harmonics + 1)
    amp = (k ** -float(decay))[:, None]
    a = rng.standard_normal((n_harmonics, 3)) * amp
    b = rng.standard_normal((n_harmonics, 3)) * amp
    out = []
    for n_vertices in counts:
        u = np.arange(n_vertices) / n_vertices
        # monotone warp: derivative 1 + sum c_l cos(...) with sum |c_l| <= 0.6
        c = rng.uniform(-1, 1, 3)
        c *= 0.6 / max(np.sum(np.abs(c)), 1e-12)
        ph = rng.uniform(0, 2 * np.pi, 3)
        t = u.copy()
        for l_, (cl, pl) in enumerate(zip(c, ph), start=1):
            t += cl * (np.sin(2 * np.pi * l_ * u + pl) - np.sin(pl)) / (2 * np.pi * l_)
        arg = 2 * np.pi * np.outer(t, k)
        out.append(np.cos(arg) @ a + np.sin(arg) @ b)
    return out


def random_rotation(rng):
    """Uniform random proper rotation (QR with sign fix, det = +1)."""
    Q, R = np.linalg.qr(rng.standard_normal((3, 3)))
    Q = Q * np.sign(np.diag(R))[None, :]
    if np.linalg.det(Q) < 0:
        Q[:, 0] = -Q[:, 0]
    return Q


def random_rigid_motion(points, rng, *, scale_range=(0.1, 10), translate=100, return_params=False):
    """``c * points @ R.T + t``: random rotation R, log-uniform scale c,
    translation t uniform in [-translate, translate]^3.

    With ``return_params`` returns ``(out, R, c, t)``.
    """
    R = random_rotation(rng)
    lo, hi = scale_range
    c = float(np.exp(rng.uniform(np.log(lo), np.log(hi))))
    t = rng.uniform(-translate, translate, 3)
    out = c * np.asarray(points, dtype=np.float64) @ R.T + t
    if return_params:
        return out, R, c, t
    return out


def start_shift(points, s):
    """Start at vertex s: ``np.roll(points, -s, axis=0)``, out[j] = points[(j+s) % n].

    With this, ``oracle(A=fd(start_shift(b, s)), B=fd(b))`` returns shift ``s``.
    """
    return np.roll(np.asarray(points), -s, axis=0)


def reverse(points):
    """Reversed traversal ``points[::-1]`` (oracle: reversed=True, shift 1)."""
    return np.asarray(points)[::-1].copy()


def resample_polyline(points, m, rng=None):
    """Same closed curve, re-discretised with m vertices at sorted uniformly
    random arc-length positions (linear interpolation along the polyline)."""
    if rng is None:
        rng = np.random.default_rng(12345)
    p = np.asarray(points, dtype=np.float64)
    closed = np.vstack([p, p[:1]])
    seg = np.linalg.norm(np.diff(closed, axis=0), axis=1)
    cum = np.concatenate([[0.0], np.cumsum(seg)])
    L = cum[-1]
    pos = np.sort(rng.uniform(0, L, m))
    out = np.empty((m, p.shape[1]))
    for d in range(p.shape[1]):
        out[:, d] = np.interp(pos, cum, closed[:, d])
    return out


def _t(n):
    return 2 * np.pi * np.arange(n) / n


def torus_knot(p, q, n, R=2.0, r=1.0):
    """(p,q) torus knot, n vertices (uniform in the parameter)."""
    t = _t(n)
    rad = R + r * np.cos(q * t)
    return np.stack([rad * np.cos(p * t), rad * np.sin(p * t), r * np.sin(q * t)], 1)


def lissajous(a, b, c, n, phase=0.5):
    """3-D Lissajous knot ``(cos(a t), cos(b t + phase), cos(c t + 2 phase))``
    (integer a, b, c), n vertices."""
    t = _t(n)
    return np.stack([np.cos(a * t), np.cos(b * t + phase), np.cos(c * t + 2 * phase)], 1)


def ellipse(rx, ry, n):
    """Planar ellipse (z = 0), n vertices."""
    t = _t(n)
    return np.stack([rx * np.cos(t), ry * np.sin(t), np.zeros(n)], 1)


def figure_eight_planar(n, r=0.3):
    """Planar closed curve (z = 0) whose first harmonic vanishes: |A_1| ~ 0.

    ``z(t) = e^{2it} + r e^{-3it}`` (x = Re z, y = Im z): a self-intersecting
    double loop with five-fold symmetry ``z(t + 2pi/5) = e^{4 pi i/5} z(t)``.
    The symmetry survives arc-length reparametrisation, so only harmonics
    k = 2 mod 5 occur and A_{+-1} vanishes up to aliasing/polyline error:
    |A_1| / rms radius ~ 3e-6 (m = 64) and ~ 3e-7 (m = 128) for n >= 1000.
    (Not a literal "8": a classic figure eight has a large A_1 with p || q;
    see ``lemniscate_planar`` for that degenerate case.)
    """
    t = _t(n)
    z = np.exp(2j * t) + r * np.exp(-3j * t)
    return np.stack([z.real, z.imag, np.zeros(n)], 1)


def lemniscate_planar(n):
    """Classic figure eight (lemniscate of Gerono) ``(sin t, sin t cos t, 0)``:
    A_1 is a real direction times a phase, so p = Re A_1 and q = -Im A_1 are
    parallel and the limit plane is undefined."""
    t = _t(n)
    return np.stack([np.sin(t), np.sin(t) * np.cos(t), np.zeros(n)], 1)


def collinear_back_and_forth(n, direction=(1.0, 0.0, 0.0)):
    """Degenerate closed polyline going along a segment and back: ``cos(t) * direction``."""
    d = np.asarray(direction, dtype=np.float64)
    return np.cos(_t(n))[:, None] * d[None, :]
