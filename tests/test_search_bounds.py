"""The search's lower bounds and cells: each bound never exceeds what it bounds."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from oracle import random_rigid_motion, random_smooth_curve, resample_polyline, start_shift

from nfdmatch import Curve
from nfdmatch.descriptors import descriptors_batch
from nfdmatch.matching import exact_search, grid_maximum, invariants
from nfdmatch.search.bounds import (
    cell_lower_bounds,
    feature_split,
    feature_vector,
    row_lower_bounds,
    squared_norms,
    truncated_lower_bounds,
)
from nfdmatch.search.cells import build_cells

N, K = 128, 16


def _coefficients(curves):
    return descriptors_batch([Curve(c) for c in curves], samples=N, harmonics=K, scale="rms").coefficients


def _pairs(rng, count):
    """A query and rows: unrelated curves, and re-posed, re-sampled, noisy copies of the
    query (the hard case for a bound: distances near 0)."""
    a = random_smooth_curve(rng, n_vertices=300, n_harmonics=int(rng.integers(2, 8)))
    rows = []
    for i in range(count):
        if i % 3 == 0:
            b = resample_polyline(a, int(rng.integers(50, 400)), rng)
            b = start_shift(b, int(rng.integers(len(b))))
            if rng.random() < 0.5:
                b = b[::-1]
            b = b + rng.normal(scale=10.0 ** rng.uniform(-6, -1), size=b.shape)
        else:
            b = random_smooth_curve(rng, n_vertices=200, n_harmonics=int(rng.integers(2, 8)))
        rows.append(random_rigid_motion(b, rng))
    A = _coefficients([a])[0]
    # rows as an index stores them: complex64
    B = _coefficients(rows).astype(np.complex64).astype(np.complex128)
    return A, B


@settings(max_examples=25, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    mirror=st.booleans(),
    strict=st.booleans(),
    harmonics=st.integers(1, 8),
    grid=st.sampled_from([8, 12, 24, 32, 48]),
    limit_quantile=st.sampled_from([None, 0.0, 0.1, 0.5, 0.9]),
)
def test_truncated_bound_never_exceeds_the_exact_distance(seed, mirror, strict, harmonics, grid, limit_quantile):
    """With or without a limit (a search's k-th distance: coarse to fine, grids divisible by
    3), at any limit."""
    rng = np.random.default_rng(seed)
    A, B = _pairs(rng, 24)
    direction = "strict" if strict else "invariant"
    exact = exact_search(A, B, N, direction=direction, mirror=mirror)["distance"]
    limit = None if limit_quantile is None else float(np.quantile(exact, limit_quantile))
    bound = truncated_lower_bounds(
        A, B, direction=direction, mirror=mirror, harmonics=harmonics, grid=grid, limit=limit
    )
    assert np.all(bound <= exact * (1 + 1e-9) + 1e-12), np.max(bound - exact)
    # and it is the truncated distance up to the stated slack: never above it either
    truncated = exact_search(A[:harmonics], B[:, :harmonics], N, direction=direction, mirror=mirror)["distance"]
    assert np.all(bound <= truncated * (1 + 1e-9) + 1e-12)


def test_a_limit_spends_the_fine_grid_only_where_it_decides():
    """Rows far above the limit keep a (looser) coarse bound, still above the limit; rows
    below it get the fine grid's bound or better."""
    rng = np.random.default_rng(11)
    A, B = _pairs(rng, 90)
    full = truncated_lower_bounds(A, B)
    limit = float(np.quantile(full, 0.3))
    limited = truncated_lower_bounds(A, B, limit=limit)
    assert np.all(limited[full > limit * 1.5] > limit)
    assert np.all(limited[full <= limit] >= full[full <= limit] - 1e-12)
    assert np.any(limited < full - 1e-6)  # coarse bounds somewhere: the work was skipped


def test_truncated_bound_is_tight_on_unrelated_curves():
    rng = np.random.default_rng(7)
    A, B = _pairs(rng, 60)
    exact = exact_search(A, B, N)["distance"]
    bound = truncated_lower_bounds(A, B)
    far = exact > 0.2
    assert np.median(bound[far] / exact[far]) > 0.8


def test_truncated_stages_each_keep_more_harmonics_than_the_last():
    from nfdmatch.search.bounds import TRUNCATED_STAGES, truncated_stages

    assert truncated_stages(16, 16) == list(TRUNCATED_STAGES)
    assert truncated_stages(16, 4) == [TRUNCATED_STAGES[0]]  # a format-1 table: head harmonics only
    assert truncated_stages(6, 6) == [(4, 24)]  # K' = K is the exact distance's job
    assert truncated_stages(3, 3) == [(3, 24)]
    for K in range(1, 20):
        stages = truncated_stages(K, K)
        assert all(a[0] < b[0] for a, b in zip(stages, stages[1:]))
        assert all(g > 2 * k for k, g in stages)


def test_the_finer_stage_is_tighter_on_unrelated_curves():
    rng = np.random.default_rng(8)
    A, B = _pairs(rng, 60)
    exact = exact_search(A, B, N)["distance"]
    coarse, fine = (truncated_lower_bounds(A, B, harmonics=k, grid=g) for k, g in ((4, 24), (8, 48)))
    far = exact > 0.2
    assert np.all(fine <= exact * (1 + 1e-9) + 1e-12)
    assert np.median(fine[far] / exact[far]) > np.median(coarse[far] / exact[far])


@pytest.mark.parametrize("harmonics", [3, 4, 8])  # the general kernel and the specialised ones
def test_grid_bound_compiled_equals_numpy(harmonics):
    rng = np.random.default_rng(3)
    A, B = _pairs(rng, 70)  # more than a block of rows
    from nfdmatch.matching import NUMPY, _kernels, grid_bound
    from nfdmatch.matching.common import integer_shift_basis

    m = len(B)
    slack = rng.uniform(0, 0.05, m)
    for mirror in (False, True):
        for direction, D in (("invariant", 2), ("strict", 1)):
            values = grid_maximum(A[:harmonics], B[:, :harmonics], 48, direction=direction, mirror=mirror)
            for ratio, need in ((1, np.full(m, -np.inf)), (3, np.full(m, np.inf)), (3, values * 0.97), (3, values)):
                reference = grid_bound(
                    A[:harmonics],
                    B[:, :harmonics],
                    48,
                    9 * slack,
                    slack,
                    need,
                    ratio=ratio,
                    direction=direction,
                    mirror=mirror,
                    kernels=NUMPY,
                )
                compiled = _kernels.grid_bound_rows(
                    np.conj(A[:harmonics]),
                    np.ascontiguousarray(B[:, :harmonics]),
                    D,
                    np.array(integer_shift_basis(harmonics, 48)),
                    ratio,
                    mirror,
                    9 * slack,
                    slack,
                    need,
                )
                assert np.allclose(compiled, reference, rtol=1e-12, atol=1e-12)


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), spread=st.sampled_from([1e-7, 1e-4, 1e-2, 1.0]))
def test_row_bound_in_float32_never_exceeds_the_feature_distance(seed, spread):
    """The float32 pass subtracts its own rounding: even for nearly equal features (where
    |x|^2 + |q|^2 - 2 x.q cancels) the bound stays below the float64 distance."""
    rng = np.random.default_rng(seed)
    D, split = 35, 32
    q = np.abs(rng.normal(size=D)) * rng.uniform(0.1, 3)
    X = (q[None, :] + rng.normal(scale=spread, size=(200, D))).astype(np.float32)
    bound = row_lower_bounds(q, split, X, squared_norms(X, split))
    X64 = X.astype(np.float64)
    true = np.maximum(
        np.linalg.norm(X64[:, :split] - q[:split], axis=1), np.linalg.norm(X64[:, split:] - q[split:], axis=1)
    )
    assert np.all(bound <= true)
    assert np.all(bound >= true - 2e-3 * (1 + np.linalg.norm(q)))


def test_invariant_bound_never_exceeds_the_exact_distance():
    rng = np.random.default_rng(11)
    A, B = _pairs(rng, 60)
    qf = feature_vector(A[None])[0]
    F = feature_vector(B).astype(np.float32)
    split = feature_split(K)
    bound = row_lower_bounds(qf, split, F, squared_norms(F, split))
    exact = exact_search(A, B, N, mirror=True)["distance"]
    assert np.all(bound <= exact * (1 + 1e-5) + 1e-6)


@settings(max_examples=10, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), rows=st.integers(1, 400), per_cell=st.sampled_from([1, 3, 16, 256]))
def test_cells_partition_the_rows_and_their_radii_hold(seed, rows, per_cell):
    rng = np.random.default_rng(seed)
    split = 6
    centres = rng.normal(size=(5, 9))
    F = (centres[rng.integers(0, 5, rows)] + rng.normal(scale=0.1, size=(rows, 9))).astype(np.float32)
    cells = build_cells(F, split, rows_per_cell=per_cell)
    assert sorted(cells.row.tolist()) == list(range(rows))
    assert cells.start[0] == 0 and cells.start[-1] == rows and np.all(np.diff(cells.start) > 0)
    # a random query, and one at a centre: the centres' norms (the search table's path)
    # cancel in |c|^2 + |q|^2 - 2 c.q there, and their slack must cover it
    for q in (rng.normal(size=9), cells.centre[int(rng.integers(cells.count))] * (1 + 1e-9)):
        cb = cell_lower_bounds(q, split, cells.centre, cells.radius)
        by_norms = cell_lower_bounds(q, split, cells.centre, cells.radius, squared_norms(cells.centre, split))
        assert np.all(by_norms <= cb + 1e-12) and np.all(by_norms >= cb - 1e-6)
        for c in range(cells.count):
            members = cells.row[cells.start[c] : cells.start[c + 1]]
            assert np.all(np.diff(members) > 0)  # ascending within a cell
            X = F[members].astype(np.float64)
            assert np.all(np.linalg.norm(X[:, :split] - cells.centre[c, :split], axis=1) <= cells.radius[c, 0])
            assert np.all(np.linalg.norm(X[:, split:] - cells.centre[c, split:], axis=1) <= cells.radius[c, 1])
            true = np.maximum(
                np.linalg.norm(X[:, :split] - q[:split], axis=1), np.linalg.norm(X[:, split:] - q[split:], axis=1)
            )
            assert np.all(cb[c] <= true) and np.all(by_norms[c] <= true)
    again = build_cells(F, split, rows_per_cell=per_cell)
    assert np.array_equal(again.row, cells.row) and np.array_equal(again.centre, cells.centre)


@pytest.mark.parametrize("rows, per_cell", [(70_000, 128), (20_000, 64)])
def test_cells_trained_on_samples_still_hold_every_row(rows, per_cell):
    """Past ``_COARSE_SAMPLE`` rows, and past ``_FINE_SAMPLE_PER_CELL`` rows per cell, the
    k-means is trained on a sample: every row must still be in exactly one cell, within the
    stored radius of its centre in both feature parts (what keeps the search exact)."""
    from nfdmatch.search import cells as cells_module

    assert rows > cells_module._COARSE_SAMPLE or per_cell > cells_module._FINE_SAMPLE_PER_CELL
    rng = np.random.default_rng(rows)
    split = 6
    centres = rng.normal(size=(40, 9)) * rng.uniform(0.1, 3, size=(40, 1))
    F = (
        centres[rng.integers(0, 40, rows)]
        + rng.normal(scale=0.05, size=(rows, 9)) * rng.uniform(0.1, 10, size=(rows, 1))
    ).astype(np.float32)
    F[:50] *= 1e3  # a few far outliers
    cells = build_cells(F, split, rows_per_cell=per_cell)
    assert np.array_equal(np.sort(cells.row), np.arange(rows))
    assert cells.start[0] == 0 and cells.start[-1] == rows and np.all(np.diff(cells.start) > 0)
    cell_of = np.repeat(np.arange(cells.count), np.diff(cells.start))
    X = F[cells.row].astype(np.float64)
    c = cells.centre[cell_of]
    assert np.all(np.linalg.norm(X[:, :split] - c[:, :split], axis=1) <= cells.radius[cell_of, 0])
    assert np.all(np.linalg.norm(X[:, split:] - c[:, split:], axis=1) <= cells.radius[cell_of, 1])
    members_ascending = np.diff(cells.row) > 0
    assert np.all(members_ascending | (np.diff(cell_of) > 0))


@settings(max_examples=200, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), kind=st.sampled_from(["random", "planar", "flat", "rank1", "zero", "tiny"]))
def test_invariant_singular_values_equal_the_svd(seed, kind):
    """The 3x2 blocks' singular values of ``invariants`` come in closed form (cheaper than
    ``np.linalg.svd``); they agree with the SVD to rounding (relative to the larger value),
    planar, rank-deficient and zero blocks included."""
    rng = np.random.default_rng(seed)
    K = int(rng.integers(1, 20))
    C = (rng.normal(size=(7, K, 3)) + 1j * rng.normal(size=(7, K, 3))) * 10.0 ** rng.uniform(-3, 3, size=(7, K, 1))
    if kind == "planar":
        C[..., 2] = 0
    elif kind == "flat":
        C[..., 2] *= 1e-9
    elif kind == "rank1":
        C = C.real * (1 + 2j) * rng.normal()
    elif kind == "zero":
        C[:, ::2] = 0
    elif kind == "tiny":
        C *= 1e-200
    got = invariants(C)["sv"].reshape(7, K, 2)
    blocks = np.stack([C.real, C.imag], axis=-1)
    w = np.sqrt(2.0 * np.ones(K))  # the default weights are uniform
    ref = np.linalg.svd(blocks, compute_uv=False) * w[:, None]
    scale = np.maximum(ref[..., :1], np.finfo(float).tiny)
    assert np.all(np.abs(got - ref) <= 1e-12 * scale)
    assert np.all(got[..., 0] >= got[..., 1]) and np.all(got >= 0)
