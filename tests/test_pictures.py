"""Reconstruction from K harmonics, the distance matrix, and matches aligned into the
query's frame (the data behind `show`), against the plain definitions."""

from __future__ import annotations

import importlib
import os

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from oracle import random_rigid_motion, random_smooth_curve, resample_polyline, reverse, start_shift, torus_knot

from nfdmatch import Curve, descriptors, distance, read_curve
from nfdmatch.descriptors import descriptors_batch, points_at, reconstruct, resample
from nfdmatch.errors import ParameterError
from nfdmatch.search import distance_matrix, rank_curves
from nfdmatch.show import matches_from_curves

#: end-to-end as a whole (subprocesses, real files, pools): left out by `make test-fast`
pytestmark = pytest.mark.slow


# --------------------------------------------------------------------------- single == batch


def test_single_descriptors_are_row_of_batch(rng):
    curves = [random_rigid_motion(random_smooth_curve(rng, n_vertices=int(n)), rng) for n in rng.integers(50, 900, 6)]
    batch = descriptors_batch(curves, samples=64, harmonics=12, scale="a1")
    for i, c in enumerate(curves):
        d = descriptors(c, samples=64, harmonics=12, scale="a1")
        np.testing.assert_allclose(d.coefficients, batch.coefficients[i], rtol=0, atol=1e-12)
        np.testing.assert_allclose(d.rotation, batch.rotation[i], atol=1e-12)
        np.testing.assert_allclose(d.centroid, batch.centroid[i], atol=1e-9)
        assert d.scale == pytest.approx(batch.scale[i], rel=1e-12)


def test_a_curve_gets_the_same_descriptors_bit_for_bit_whatever_is_batched_with_it(rng, monkeypatch):
    """A query's (and an indexed curve's) descriptors must not depend on the other curves of
    its batch: the arc length is summed per curve, not over the batch. Curves of mixed
    lengths, repeated vertices (zero-length segments), and one very long curve among short
    ones (summed curve by curve)."""
    curves = [random_rigid_motion(random_smooth_curve(rng, n_vertices=int(n)), rng) for n in rng.integers(8, 300, 7)]
    repeated = np.repeat(curves[0], rng.integers(1, 4, len(curves[0])), axis=0)  # runs of equal vertices
    long = random_smooth_curve(rng, n_vertices=40_000)
    together_first = descriptors_batch(curves + [repeated])
    for batch in (curves + [repeated], [repeated] + curves[::-1], curves[:3] + [long] + curves[3:]):
        together = descriptors_batch(batch)
        for i, c in enumerate(batch):
            alone = descriptors_batch([c])
            for key in ("coefficients", "rotation", "centroid", "scale"):
                assert np.array_equal(getattr(together, key)[i], getattr(alone, key)[0]), (i, key)
    # the samples found curve by curve (when the batch's search is far off) are the same
    # (nfdmatch.descriptors is also the name of a function: the module through importlib)
    monkeypatch.setattr(importlib.import_module("nfdmatch.descriptors"), "_MOVES", 0)
    assert np.array_equal(descriptors_batch(curves + [repeated]).coefficients, together_first.coefficients)


@pytest.mark.parametrize("tilt", [0.0, 1e-9, 1e-6, 1e-3])
def test_plane_rotation_stays_orthonormal_for_normals_near_minus_z(tilt):
    """A clockwise planar curve has its limit-plane normal at -z; a tiny tilt once made
    1 + cos(angle) cancel and the rotation lose orthonormality (1e-5): found by the matrix
    test disagreeing with `distance` by 3e-6."""
    t = np.arange(400) / 400
    pts = np.c_[3 * np.cos(-2 * np.pi * t), np.sin(-2 * np.pi * t), np.zeros(400)]
    c, s = np.cos(tilt), np.sin(tilt)
    pts = pts @ np.array([[1, 0, 0], [0, c, -s], [0, s, c]]).T
    d = descriptors(pts)
    R = d.rotation
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-13)
    assert np.linalg.det(R) == pytest.approx(1.0, abs=1e-13)
    assert np.abs(d.coefficients[:, 2]).max() < 1e-9  # the curve lies in z = 0 after rotation


def test_points_at_walks_the_polyline():
    square = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], float)
    got = points_at(square, [0.0, 0.125, 0.25, 0.5, 0.875, -0.125, 1.0])
    want = [[0, 0, 0], [0.5, 0, 0], [1, 0, 0], [1, 1, 0], [0, 0.5, 0], [0, 0.5, 0], [0, 0, 0]]
    np.testing.assert_allclose(got, want, atol=1e-15)
    np.testing.assert_allclose(resample(square, 8)[1], [0.5, 0, 0])


# --------------------------------------------------------------------------- reconstruction


def _fourier_curve(rng, harmonics: int, n: int = 3000) -> np.ndarray:
    t = np.arange(n) / n
    k = np.arange(1, harmonics + 1)
    a, b = rng.standard_normal((2, harmonics, 3)) * (k**-1.5)[None, :, None]
    return np.cos(2 * np.pi * np.outer(t, k)) @ a + np.sin(2 * np.pi * np.outer(t, k)) @ b


def test_reconstruction_at_all_harmonics_reproduces_the_samples(rng):
    """K = n/2 - 1 harmonics of a curve sampled n times give back those samples exactly
    (up to the Nyquist term), in the input's position, size and orientation."""
    pts = random_rigid_motion(random_smooth_curve(rng, n_vertices=700), rng)
    d = descriptors(pts, samples=64, harmonics=31)
    rebuilt = reconstruct(d)
    samples = resample(pts, 64)
    assert np.abs(rebuilt - samples).max() < 0.05 * np.abs(samples - samples.mean(0)).max()
    # the Nyquist term is the only difference: exact for a curve without it
    nyquist = np.fft.fft(samples, axis=0)[32] / 64
    np.testing.assert_allclose(rebuilt + nyquist.real * (-1.0) ** np.arange(64)[:, None], samples, atol=1e-9)


KNOTESS = os.path.join(
    os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "sample_curves", "library", "knotess"
)


@pytest.mark.parametrize(
    "curve", [torus_knot(2, 3, 1500), torus_knot(3, 4, 2000), torus_knot(2, 5, 1800), "3_1.csv", "4_1.csv", "5_2.csv"]
)
def test_reconstruction_distance_falls_with_k_to_zero_for_smooth_curves(curve, rng):
    if isinstance(curve, str):
        curve = read_curve(os.path.join(KNOTESS, curve)).points
    pts = random_rigid_motion(curve, rng)
    d = descriptors(pts, samples=256, harmonics=64)
    dist = [distance(pts, reconstruct(d, harmonics=k, points=512)).distance for k in (1, 2, 4, 8, 16)]
    # never rises (equal where a harmonic is absent: tk34 has no k = 2), and ends near zero
    assert all(a >= b - 1e-9 for a, b in zip(dist, dist[1:])), dist
    assert dist[-1] < 2.5e-3 and dist[0] > 100 * dist[-1], dist


def test_reconstruction_distance_falls_with_k_for_random_curves(rng):
    """Curves with uneven speed spread over more harmonics by arc length: still falling."""
    for _ in range(5):
        pts = random_rigid_motion(random_smooth_curve(rng, n_vertices=1500), rng)
        d = descriptors(pts, samples=256, harmonics=64)
        dist = [distance(pts, reconstruct(d, harmonics=k, points=512)).distance for k in (1, 4, 16, 48)]
        assert all(a > b for a, b in zip(dist, dist[1:])), dist
        assert dist[2] < 0.05 and dist[3] < 5e-3, dist


def test_reconstruction_keeps_pose_and_normalized_frame(rng):
    pts = random_rigid_motion(torus_knot(2, 3, 1500), rng)
    d = descriptors(pts, harmonics=16)
    rebuilt = reconstruct(d, points=400)
    # drawn where the input is, at its size and orientation: every vertex on the input
    size = np.abs(pts - pts.mean(0)).max()
    gaps = np.min(np.linalg.norm(rebuilt[:, None, :] - pts[None, :, :], axis=2), axis=1)
    assert gaps.max() < 0.01 * size
    np.testing.assert_allclose(rebuilt[0], resample(pts, 128)[0], atol=0.01 * size)
    normalized = reconstruct(d, points=400, normalized=True)
    assert np.abs(normalized.mean(0)).max() < 1e-9
    assert np.sqrt((normalized**2).sum(1).mean()) == pytest.approx(1.0, rel=1e-2)
    assert np.abs(normalized[:, 2]).max() < np.abs(normalized[:, :2]).max()  # limit plane ~ z = 0


def test_reconstruct_rejects_bad_parameters(rng):
    d = descriptors(random_smooth_curve(rng, n_vertices=200), harmonics=8)
    with pytest.raises(ParameterError, match="harmonics must be between 1 and 8"):
        reconstruct(d, harmonics=9)
    with pytest.raises(ParameterError, match="points"):
        reconstruct(d, points=2)


# --------------------------------------------------------------------------- the matrix


def test_matrix_is_symmetric_and_equals_distance_for_every_pair(rng):
    curves = [random_rigid_motion(random_smooth_curve(rng, n_vertices=int(n)), rng) for n in rng.integers(100, 600, 7)]
    curves.append(reverse(start_shift(curves[0], 17)))
    M = distance_matrix(curves)
    assert M.shape == (8, 8)
    np.testing.assert_array_equal(M, M.T)
    np.testing.assert_array_equal(np.diag(M), 0.0)
    for i in range(8):
        for j in range(8):
            if i != j:
                assert M[i, j] == pytest.approx(distance(curves[i], curves[j]).distance, rel=1e-9, abs=1e-12)
    assert M[0, 7] < 1e-3


def test_matrix_with_paper_method_and_progress(rng):
    curves = [random_smooth_curve(rng, n_vertices=300) for _ in range(4)]
    calls = []
    M = distance_matrix(curves, method="paper", progress=lambda done, total: calls.append((done, total)))
    np.testing.assert_array_equal(M, M.T)
    assert M[0, 2] == pytest.approx(distance(curves[0], curves[2], method="paper").distance, rel=1e-12)
    assert calls[-1] == (6, 6)
    with pytest.raises(ParameterError):
        distance_matrix(curves, method="nearest")


# --------------------------------------------------------------------------- alignment


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), shift=st.integers(0, 499), flip=st.booleans(), vertices=st.integers(300, 1200))
def test_aligned_match_lands_on_the_query(seed, shift, flip, vertices):
    """A posed, restarted, maybe reversed, resampled copy of the query is drawn on top of
    the query: its vertices lie on the query, its start marker at the query's first vertex
    and its direction marker along the query's direction of travel."""
    rng = np.random.default_rng(seed)
    base = _fourier_curve(rng, 4, n=500)
    query = Curve(random_rigid_motion(base, rng), id="q")
    copy = start_shift(base, shift)
    if flip:
        copy = reverse(copy)
    copy = resample_polyline(random_rigid_motion(copy, rng), vertices, rng)
    other = Curve(random_rigid_motion(_fourier_curve(rng, 4, n=300), rng), id="other")
    curves = [Curve(copy, id="copy"), other]
    ranked = rank_curves(query, curves, k=2)
    shown = matches_from_curves(query, ranked, curves, samples=128, harmonics=16, scale="rms")
    assert [s.id for s in shown] == ["copy", "other"]
    best = shown[0]
    size = np.abs(query.points - query.points.mean(0)).max()
    # every aligned vertex is close to the query polyline
    fine = points_at(query.points, np.arange(4000) / 4000)
    gaps = np.min(np.linalg.norm(best.points[:, None, :] - fine[None, ::4, :], axis=2), axis=1)
    assert gaps.max() < 0.03 * size
    assert np.linalg.norm(best.start - query.points[0]) < 0.02 * size
    ahead = points_at(query.points, np.array([0.04]))[0]
    assert np.linalg.norm(best.forward - ahead) < 0.03 * size
    assert best.reversed == flip
    assert best.distance == pytest.approx(ranked[0].distance)


def test_matrix_in_row_batches_equals_one_call(rng, monkeypatch):
    import nfdmatch.search.matrix as search_module

    curves = [random_smooth_curve(rng, n_vertices=int(n)) for n in rng.integers(80, 300, 9)]
    whole = distance_matrix(curves)
    monkeypatch.setattr(search_module, "BATCH_ROWS", 2)
    sizes = []
    real = search_module.exact_search
    monkeypatch.setattr(
        search_module, "exact_search", lambda A, B, *a, **k: sizes.append(len(B)) or real(A, B, *a, **k)
    )
    np.testing.assert_allclose(distance_matrix(curves), whole, rtol=1e-12, atol=1e-15)  # BLAS rounding
    assert max(sizes) == 2 and sum(sizes) == 9 * 8 // 2  # bounded calls, every pair once


def test_similarity_order_groups_clusters(rng):
    from nfdmatch.search import similarity_order

    centres = rng.normal(size=(4, 3)) * 20
    labels = rng.permutation(np.repeat(np.arange(4), 6))
    points = centres[labels] + rng.normal(size=(24, 3))
    D = np.linalg.norm(points[:, None] - points[None], axis=2)
    order = similarity_order(D)
    assert sorted(order.tolist()) == list(range(24))
    runs = np.count_nonzero(np.diff(labels[order])) + 1
    assert runs == 4  # each cluster contiguous
    np.testing.assert_array_equal(similarity_order(D), order)  # deterministic
    assert similarity_order(np.zeros((1, 1))).tolist() == [0]
    with pytest.raises(ParameterError):
        similarity_order(np.zeros((2, 3)))
