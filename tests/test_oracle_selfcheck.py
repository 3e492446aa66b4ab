"""Self-checks of the brute-force oracle in tests/oracle.py (no nfdmatch)."""

from __future__ import annotations

import numpy as np
import pytest

from oracle import (
    collinear_back_and_forth,
    ellipse,
    fd,
    figure_eight_planar,
    kabsch,
    lemniscate_planar,
    lissajous,
    lower_bounds,
    mu,
    normalize,
    oracle_fractional,
    oracle_integer,
    random_rigid_motion,
    random_rotation,
    random_smooth_curve,
    resample,
    resample_polyline,
    reverse,
    reverse_band,
    shift_band,
    start_shift,
    torus_knot,
)

M, K = 64, 8


def band(samples, K=K, scale="a1"):
    return normalize(fd(samples), K, scale)


def circ_dist(a, b, m):
    d = (a - b) % m
    return min(d, m - d)


# --------------------------------------------------------------------------- basics


def test_resample_convention():
    sq = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], float)
    r = resample(sq, 8)
    exp = np.array([[0, 0], [0.5, 0], [1, 0], [1, 0.5], [1, 1], [0.5, 1], [0, 1], [0, 0.5]])
    np.testing.assert_allclose(r[:, :2], exp, atol=1e-15)
    # zero-length segments and repeated vertices are harmless
    sq2 = np.array([[0, 0, 0], [1, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], float)
    np.testing.assert_allclose(resample(sq2, 8), r, atol=1e-15)
    # 3 x 1 rectangle with irregular extra vertices on its edges: samples are
    # at exact arc-length positions j * 8 / m along the boundary
    rg = np.random.default_rng(0)
    corners = np.array([[0, 0], [3, 0], [3, 1], [0, 1]], float)
    verts = []
    for i in range(4):
        a, b = corners[i], corners[(i + 1) % 4]
        for f in np.concatenate([[0.0], np.sort(rg.uniform(0, 1, 7))]):
            verts.append(a + f * (b - a))
    verts = np.hstack([np.array(verts), np.zeros((len(verts), 1))])
    m = 40
    r = resample(verts, m)
    for j in range(m):
        t = 8.0 * j / m
        if t < 3:
            e = (t, 0)
        elif t < 4:
            e = (3, t - 3)
        elif t < 7:
            e = (7 - t, 1)
        else:
            e = (0, 8 - t)
        np.testing.assert_allclose(r[j, :2], e, atol=1e-12)
    # offset: start half a sample later
    np.testing.assert_allclose(resample(verts, m, offset=0.5 / m)[0, :2], (0.1, 0), atol=1e-12)


def test_fd_and_normalize_conventions(rng):
    a = rng.standard_normal((M, 3))
    A = fd(a)
    j = np.arange(M)
    for k in (0, 1, 5, M - 1):
        ref = (a * np.exp(-2j * np.pi * j * k / M)[:, None]).sum(0) / M
        np.testing.assert_allclose(A[k], ref, atol=1e-13)
    B, freqs = normalize(A, K, "a1")
    assert list(freqs) == list(range(1, K + 1)) + list(range(-K, 0))
    np.testing.assert_allclose(np.linalg.norm(B[0]), 1.0)
    Br, _ = normalize(A, K, "rms")
    rms = np.sqrt(np.mean(np.sum((a - a.mean(0)) ** 2, axis=1)))
    np.testing.assert_allclose(Br * rms, A[freqs % M], atol=1e-13)


def test_shift_and_reverse_sign_conventions(rng):
    a = rng.standard_normal((M, 3))
    A = fd(a)
    freqs = np.concatenate([np.arange(1, K + 1), np.arange(-K, 0)])
    s = 5
    np.testing.assert_allclose(fd(start_shift(a, s))[freqs % M], shift_band(A[freqs % M], freqs, M, s), atol=1e-13)
    np.testing.assert_allclose(fd(np.roll(a[::-1], 1, axis=0))[freqs % M], reverse_band(A[freqs % M]), atol=1e-13)
    # a[::-1] == reversal followed by shift 1
    np.testing.assert_allclose(
        fd(reverse(a))[freqs % M], shift_band(reverse_band(A[freqs % M]), freqs, M, 1), atol=1e-13
    )


def test_generators(rng):
    for R in (random_rotation(rng) for _ in range(20)):
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
        assert np.linalg.det(R) == pytest.approx(1.0)
    c = random_smooth_curve(rng, 500)
    assert c.shape == (500, 3) and not np.allclose(c[0], c[-1])
    d = np.linalg.norm(np.diff(c, axis=0), axis=1)
    assert d.std() / d.mean() > 0.05  # not uniform in arc length
    for f in (
        torus_knot(2, 3, 300),
        lissajous(3, 2, 5, 300),
        ellipse(2, 1, 100),
        figure_eight_planar(1000),
        lemniscate_planar(400),
        collinear_back_and_forth(100),
        resample_polyline(c, 77, rng),
    ):
        assert f.ndim == 2 and f.shape[1] == 3 and np.isfinite(f).all()
    A = fd(resample(figure_eight_planar(1000), 128))
    assert np.linalg.norm(A[1]) < 1e-5 * np.sqrt(np.sum(np.abs(A[1:]) ** 2))
    A = fd(resample(lemniscate_planar(1000), 128))
    sv = np.linalg.svd(np.stack([A[1].real, -A[1].imag], 1), compute_uv=False)
    assert sv[1] < 1e-10 * sv[0]
    out, R, s, t = random_rigid_motion(c, rng, return_params=True)
    np.testing.assert_allclose(out, s * c @ R.T + t)


# --------------------------------------------------------------------------- (a)


@pytest.mark.parametrize("trial", range(5))
def test_a_rigid_copy_recovered(rng, trial):
    p = resample(random_smooth_curve(rng), M)
    s0 = int(rng.integers(M))
    moved, R0, _, _ = random_rigid_motion(start_shift(p, s0), rng, return_params=True)
    A, freqs = band(moved)
    B, _ = band(p)
    for scale in ("a1", "rms"):
        A, _ = band(moved, scale=scale)
        B, _ = band(p, scale=scale)
        d, s, R, rev = oracle_integer(A, B, freqs, M)
        assert d < 1e-9
        assert s == s0 and not rev
        np.testing.assert_allclose(R, R0, atol=1e-9)
        np.testing.assert_allclose(A, (R @ shift_band(B, freqs, M, s).T).T, atol=1e-9)


# --------------------------------------------------------------------------- (b)


def test_b_reversed_copy(rng):
    p = resample(random_smooth_curve(rng), M)
    s0 = int(rng.integers(M))
    q = random_rigid_motion(start_shift(reverse(p), s0), rng)
    A, freqs = band(q)
    B, _ = band(p)
    d, s, R, rev = oracle_integer(A, B, freqs, M)
    assert d < 1e-9 and rev
    # q_j = p_{m-1-(j+s0)} = p_{(-j-(s0+1)) mod m}
    assert s == (s0 + 1) % M
    d_fwd, *_ = oracle_integer(A, B, freqs, M, directions=("forward",))
    assert d_fwd > 1e-2
    d_rev, *_ = oracle_integer(A, B, freqs, M, directions=("reversed",))
    assert d_rev < 1e-9


# --------------------------------------------------------------------------- (c)


def test_c_mirrored_copy(rng):
    p = resample(random_smooth_curve(rng), M)
    q = p * np.array([-1.0, 1.0, 1.0])
    q = random_rigid_motion(start_shift(q, 7), rng)
    A, freqs = band(q)
    B, _ = band(p)
    d_m, s, R, _ = oracle_integer(A, B, freqs, M, mirror=True)
    assert d_m < 1e-9 and s == 7
    assert np.linalg.det(R) == pytest.approx(-1.0)
    d, *_ = oracle_integer(A, B, freqs, M)
    assert d > 1e-2


def test_c_planar_mirror_is_a_rotation():
    # a planar mirror image equals a rotation (by pi about an in-plane axis)
    p = resample(lissajous(1, 2, 3, 500) * np.array([1, 1, 0]) + [0.3, 0, 0], M)
    A, freqs = band(p * np.array([-1.0, 1.0, 1.0]))
    B, _ = band(p)
    d, *_ = oracle_integer(A, B, freqs, M)
    assert d < 1e-9


# --------------------------------------------------------------------------- (d)


def test_d_fractional_never_worse(rng):
    for _ in range(8):
        A, freqs = band(resample(random_smooth_curve(rng), M))
        B, _ = band(resample(random_smooth_curve(rng), M))
        mirror = bool(rng.integers(2))
        di, si, *_ = oracle_integer(A, B, freqs, M, mirror=mirror)
        df, sf, *_ = oracle_fractional(A, B, freqs, M, upsample=16, mirror=mirror)
        assert df <= di + 1e-12
        if sf == int(sf):
            assert df == pytest.approx(di, abs=1e-12)


def test_d_fractional_equals_integer_on_integer_shift(rng):
    p = resample(random_smooth_curve(rng), M)
    A, freqs = band(random_rigid_motion(start_shift(p, 11), rng))
    B, _ = band(p)
    di, si, Ri, ri = oracle_integer(A, B, freqs, M)
    df, sf, Rf, rf = oracle_fractional(A, B, freqs, M)
    assert sf == 11.0 and si == 11 and ri == rf
    assert df < 1e-9 and abs(df - di) < 1e-9
    np.testing.assert_allclose(Rf, Ri, atol=1e-9)


def test_d_fft_matrices_match_direct(rng):
    from oracle import correlation_matrices

    A, freqs = band(rng.standard_normal((M, 3)))
    B, _ = band(rng.standard_normal((M, 3)))
    U = 4
    N = U * M
    X = np.zeros((N, 3, 3), complex)
    X[freqs % N] = B[:, :, None] * np.conj(A)[:, None, :]
    Mf = np.real(np.fft.ifft(X, axis=0) * N)
    js = np.array([0, 1, 3, 17, N - 1])
    Md = correlation_matrices(A, B, freqs, M, js / U)
    np.testing.assert_allclose(Mf[js], Md, atol=1e-12)


# --------------------------------------------------------------------------- (e)


@pytest.mark.parametrize("trial", range(3))
def test_e_fractional_start_offset(rng, trial):
    dense = random_smooth_curve(rng, 4000, decay=2.0)
    a = resample(dense, M)
    b = resample(dense, M, offset=0.5 / M)  # b_j = a at j + 1/2 samples
    b = random_rigid_motion(b, rng)
    A, freqs = band(a)
    B, _ = band(b)
    di, *_ = oracle_integer(A, B, freqs, M)
    df, sf, *_ = oracle_fractional(A, B, freqs, M)
    # a_j ~ b_{j - 1/2}: shift -1/2 == M - 1/2
    assert sf == pytest.approx(M - 0.5, abs=1.5 / 32)
    assert df < 0.05 * di
    assert df < 5e-3


# --------------------------------------------------------------------------- (f)


def _pairs(rng, n):
    gens = [
        lambda: random_smooth_curve(rng, 600),
        lambda: random_smooth_curve(rng, 600, n_harmonics=3, decay=0.5),
        lambda: torus_knot(int(rng.integers(1, 4)), int(rng.integers(2, 6)), 500),
        lambda: lissajous(*rng.integers(1, 6, 3), 500, rng.uniform(0, 3)),
        lambda: ellipse(rng.uniform(0.5, 2), rng.uniform(0.5, 2), 200),
    ]
    for _ in range(n):
        yield gens[rng.integers(len(gens))](), gens[rng.integers(len(gens))]()


def test_f_lower_bounds(rng):
    m, k = 32, 6
    for pa, pb in _pairs(rng, 50):
        Fa, Fb = fd(resample(pa, m)), fd(resample(pb, m))
        degenerate = min(np.linalg.norm(F[1]) / np.linalg.norm(F[1:]) for F in (Fa, Fb)) < 1e-3
        scale = "rms" if degenerate or rng.integers(2) else "a1"  # symmetric knots: A_1 ~ 0
        A, freqs = normalize(Fa, k, scale)
        B, _ = normalize(Fb, k, scale)
        lb = lower_bounds(A, B, freqs)
        w = rng.uniform(0.2, 2.0, 2 * k)
        lbw = lower_bounds(A, B, freqs, weights=w)
        for mirror in (False, True):
            d, *_ = oracle_integer(A, B, freqs, m, mirror=mirror)
            dw, *_ = oracle_integer(A, B, freqs, m, mirror=mirror, weights=w)
            for key in ("norm", "sv", "block"):
                assert lb[key] <= d + 1e-12 * (1 + d), (key, lb, d)
                assert lbw[key] <= dw + 1e-12 * (1 + dw), (key, lbw, dw)
            assert lb["sv"] >= lb["norm"] - 1e-12  # sv bound is tighter


# --------------------------------------------------------------------------- (g)


def test_g_trace_formula_matches_direct(rng):
    for _ in range(20):
        A, freqs = band(rng.standard_normal((M, 3)))
        B, _ = band(rng.standard_normal((M, 3)))
        s = rng.uniform(0, M)
        mirror = bool(rng.integers(2))
        Bs = shift_band(B, freqs, M, s)
        Mm = np.real(Bs.T @ np.conj(A))  # sum_k B_k(s) A_k^H
        R, tr = kabsch(Mm, mirror)
        direct2 = mu(A, (R @ Bs.T).T) ** 2
        formula = np.sum(np.abs(A) ** 2) + np.sum(np.abs(B) ** 2) - 2 * tr
        assert direct2 == pytest.approx(formula, rel=1e-10, abs=1e-12)
        assert np.trace(R @ Mm) == pytest.approx(tr, rel=1e-12)
        # Kabsch is optimal: no random rotation does better
        for _ in range(20):
            Q = random_rotation(rng)
            if mirror and rng.integers(2):
                Q = Q @ np.diag([1.0, 1.0, -1.0])
            assert mu(A, (Q @ Bs.T).T) >= np.sqrt(max(direct2, 0)) - 1e-12


# --------------------------------------------------------------------------- (h)


def test_h_symmetry(rng):
    for _ in range(6):
        A, freqs = band(resample(random_smooth_curve(rng, 500), M))
        B, _ = band(resample(random_smooth_curve(rng, 500), M))
        mirror = bool(rng.integers(2))
        dab, sab, Rab, rab = oracle_integer(A, B, freqs, M, mirror=mirror)
        dba, sba, Rba, rba = oracle_integer(B, A, freqs, M, mirror=mirror)
        assert dab == pytest.approx(dba, rel=1e-10)
        assert rab == rba
        if not rab:  # generic: unique optimum, inverse transform
            assert sba == (-sab) % M
            np.testing.assert_allclose(Rba, Rab.T, atol=1e-8)
        fab = oracle_fractional(A, B, freqs, M, upsample=8, mirror=mirror)[0]
        fba = oracle_fractional(B, A, freqs, M, upsample=8, mirror=mirror)[0]
        assert fab == pytest.approx(fba, rel=1e-10)


def test_resample_polyline_same_curve(rng):
    dense = random_smooth_curve(rng, 3000, decay=2.0)
    other = resample_polyline(dense, 5000, rng)
    A, freqs = band(resample(dense, M))
    B, _ = band(resample(other, M))
    df, *_ = oracle_fractional(A, B, freqs, M)
    di, *_ = oracle_integer(A, B, freqs, M)
    assert df < 1e-2 and df <= di + 1e-12
