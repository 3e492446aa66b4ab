"""The self-join (nfdmatch.search.join) equals the brute force: every pair's exact distance."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from oracle import random_rigid_motion, smooth_curve_samplings, start_shift

from nfdmatch import Curve
from nfdmatch.errors import ParameterError
from nfdmatch.matching import exact_search
from nfdmatch.search import MemoryIndex
from nfdmatch.search.bounds import (
    cell_pair_lower_bounds,
    feature_vector,
    query_radius,
    row_lower_bounds,
    row_lower_bounds_many,
)
from nfdmatch.search.engine import Cascade
from nfdmatch.search.join import nearest_others, pairs_within

#: distances this close to a threshold may fall either side of it (a pair's distance is
#: computed from one of its curves: the two orders agree to ~1e-15)
SLACK = 1e-9


def family_curves(rng, families, members, noise):
    """Families of one smooth curve each, every member re-sampled, start-shifted, sometimes
    reversed, scaled and moved rigidly, with noise."""
    curves = []
    for f in range(families):
        versions = smooth_curve_samplings(
            rng, [int(rng.integers(40, 120)) for _ in range(members)], n_harmonics=int(rng.integers(2, 6))
        )
        for m, pts in enumerate(versions):
            pts = pts + rng.normal(scale=noise, size=pts.shape)
            pts = start_shift(pts, int(rng.integers(len(pts))))
            if rng.random() < 0.3:
                pts = pts[::-1]
            pts = pts * float(rng.uniform(0.5, 3.0))
            curves.append(Curve(random_rigid_motion(pts, rng), id=f"f{f:02d}-m{m:02d}"))
    return curves


def brute_force(index, cascade):
    """(N, N) every exact distance, row i as the query (diagonal inf)."""
    N = index.n_curves
    C = index.coefficients_at(np.arange(N))
    D = np.array(
        [
            exact_search(
                np.asarray(C[i], np.complex128), C, index.samples, direction=cascade.direction, mirror=cascade.mirror
            )["distance"]
            for i in range(N)
        ]
    )
    np.fill_diagonal(D, np.inf)
    return D


@settings(max_examples=12, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    families=st.integers(1, 8),
    members=st.integers(1, 6),
    noise=st.sampled_from([0.0, 0.01, 0.1]),
    k=st.integers(1, 8),
    cells=st.sampled_from([None, 1, 3, 8]),
    mirror=st.booleans(),
    strict=st.booleans(),
    truncate=st.booleans(),
    restrict=st.booleans(),
)
def test_nearest_others_equal_the_brute_force(
    seed, families, members, noise, k, cells, mirror, strict, truncate, restrict
):
    rng = np.random.default_rng(seed)
    curves = family_curves(rng, families, members, noise)
    index = MemoryIndex(curves, rows_per_cell=cells)
    cascade = Cascade(index.samples, direction="strict" if strict else "invariant", mirror=mirror, truncate=truncate)
    N = len(curves)
    rows = np.sort(rng.choice(N, int(rng.integers(0, N + 1)), replace=False)) if restrict else None
    nb, dist, stats = nearest_others(index.search_table(), index.coefficients_at, k, cascade, rows=rows)
    D = brute_force(index, cascade)
    assert nb.shape == dist.shape == (N, k)
    assert stats.exact <= N * (N - 1) // 2
    wanted = np.arange(N) if rows is None else rows
    for i in range(N):
        if i not in set(wanted.tolist()):
            assert (nb[i] == -1).all() and np.isinf(dist[i]).all()
            continue
        others = min(k, N - 1)
        expected = np.sort(D[i])[:others]
        np.testing.assert_allclose(dist[i, :others], expected, rtol=1e-9, atol=1e-12)
        assert (nb[i, others:] == -1).all() and np.isinf(dist[i, others:]).all()
        assert len(set(nb[i, :others].tolist())) == others and i not in nb[i]
        if others:
            kth = expected[-1]
            # every row clearly nearer than the k-th is listed; every listed row is within it
            assert set(np.flatnonzero(D[i] < kth - SLACK).tolist()) <= set(nb[i, :others].tolist())
            assert (np.minimum(D[i, nb[i, :others]], D[nb[i, :others], i]) <= kth + SLACK).all()
            assert np.all(np.diff(dist[i, :others]) >= -1e-12)


@settings(max_examples=12, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    families=st.integers(1, 8),
    members=st.integers(1, 6),
    noise=st.sampled_from([0.0, 0.01, 0.1]),
    quantile=st.sampled_from([0.0, 0.05, 0.3, 1.0]),
    cells=st.sampled_from([None, 1, 3, 8]),
    mirror=st.booleans(),
    truncate=st.booleans(),
    restrict=st.booleans(),
)
def test_pairs_within_equal_the_brute_force(
    seed, families, members, noise, quantile, cells, mirror, truncate, restrict
):
    rng = np.random.default_rng(seed)
    curves = family_curves(rng, families, members, noise)
    index = MemoryIndex(curves, rows_per_cell=cells)
    cascade = Cascade(index.samples, mirror=mirror, truncate=truncate)
    N = len(curves)
    D = brute_force(index, cascade)
    off = D[np.isfinite(D)]
    limit = float(np.quantile(off, quantile)) if len(off) else 0.1
    rows = np.sort(rng.choice(N, int(rng.integers(0, N + 1)), replace=False)) if restrict else None
    a, b, d, stats = pairs_within(index.search_table(), index.coefficients_at, limit, cascade, rows=rows)
    assert (a < b).all() and len(set(zip(a.tolist(), b.tolist()))) == len(a)
    assert list(zip(a.tolist(), b.tolist())) == sorted(zip(a.tolist(), b.tolist()))
    assert (d <= limit).all()
    in_rows = np.ones(N, bool) if rows is None else np.isin(np.arange(N), rows)
    both = np.minimum(D, D.T)
    sure = {(i, j) for i in range(N) for j in range(i + 1, N) if D[i, j] <= limit - SLACK and D[j, i] <= limit - SLACK}
    sure = {(i, j) for i, j in sure if in_rows[i] or in_rows[j]}
    got = set(zip(a.tolist(), b.tolist()))
    assert sure <= got
    assert all(both[i, j] <= limit + SLACK and (in_rows[i] or in_rows[j]) for i, j in got)
    np.testing.assert_allclose(d, both[a, b], rtol=1e-9, atol=1e-12)


def test_the_pair_bounds_never_exceed_the_row_bounds(rng):
    """cell_pair_lower_bounds <= the features' distance of every pair of rows of the two
    cells; row_lower_bounds_many is row_lower_bounds query by query (to float32 rounding)."""
    curves = family_curves(rng, 12, 5, 0.05)
    index = MemoryIndex(curves, rows_per_cell=6)
    table = index.search_table()
    split = table.split
    for c in range(table.n_cells):
        rows, F, sq, coef = table.cell_rows(np.array([c]))
        fq = feature_vector(np.asarray(coef, np.complex128))
        reach = query_radius(fq, split, table.centre[c])
        cb = cell_pair_lower_bounds(table.centre[c], reach, split, table.centre, table.radius)
        for e in range(table.n_cells):
            _, Fe, sqe, _ = table.cell_rows(np.array([e]))
            many = row_lower_bounds_many(fq, split, Fe, sqe)
            for i in range(len(fq)):
                np.testing.assert_allclose(many[i], row_lower_bounds(fq[i], split, Fe, sqe), atol=1e-5)
                diff = fq[i][None, :] - Fe.astype(np.float64)
                true = np.maximum(np.linalg.norm(diff[:, :split], axis=1), np.linalg.norm(diff[:, split:], axis=1))
                assert (cb[e] <= true + 1e-12).all()
                assert (many[i] <= true + 1e-12).all()


def test_every_pair_is_computed_at_most_once_and_tight_families_are_cheap(rng):
    curves = family_curves(rng, 30, 8, 0.002)
    index = MemoryIndex(curves, rows_per_cell=16)
    N = len(curves)
    _, _, stats = nearest_others(index.search_table(), index.coefficients_at, 4, Cascade(index.samples))
    # seeds and the join share each pair: far fewer than one search per row (~k + a few)
    assert stats.exact < 12 * N
    assert stats.cell_pairs < stats.cells * stats.cells / 2


def test_an_empty_or_single_row_table_and_bad_arguments(rng):
    one = MemoryIndex(family_curves(rng, 1, 1, 0.0))
    nb, dist, _ = nearest_others(one.search_table(), one.coefficients_at, 3, Cascade(one.samples))
    assert (nb == -1).all() and np.isinf(dist).all()
    a, b, d, _ = pairs_within(one.search_table(), one.coefficients_at, 1.0, Cascade(one.samples))
    assert len(a) == len(b) == len(d) == 0
    with pytest.raises(ParameterError):
        nearest_others(one.search_table(), one.coefficients_at, 0, Cascade(one.samples))
    with pytest.raises(ParameterError):
        pairs_within(one.search_table(), one.coefficients_at, -1.0, Cascade(one.samples))
    with pytest.raises(ParameterError):
        pairs_within(one.search_table(), one.coefficients_at, 1.0, Cascade(one.samples), rows=[5])


def test_the_graph_of_a_build_equals_the_per_row_search_and_the_join(tmp_path, rng):
    """`index build --graph K` stores the lists a search of every row gives
    (engine.search_block for k + 1, the row itself dropped, ties by id), and the self-join's
    nearest_others gives the same lists: families of 6 with K = 8, so every list ends outside
    its family, over several cells."""
    import h5py

    from nfdmatch import write_curves
    from nfdmatch.index import build_index, open_index
    from nfdmatch.search.engine import BestRows, search_block
    from nfdmatch.search.graph import _ordered

    curves = family_curves(rng, 40, 6, 0.02)
    (tmp_path / "c").mkdir()
    for i, part in enumerate(np.array_split(np.arange(len(curves)), 3)):
        write_curves(tmp_path / "c" / f"part-{i}.obj", [curves[j] for j in part])
    index = tmp_path / "i.h5"
    report = build_index([tmp_path / "c"], index, jobs=1, graph=8)
    assert report.graph.searched == len(curves)
    with h5py.File(index, "r") as f:
        nb, dist, ids = f["graph/neighbour"][...], f["graph/distance"][...], f["curves/id"].asstr()[...]
    with open_index(index) as idx:
        table = idx.search_table()
        assert table.n_cells > 1
        N = idx.n_curves
        q = np.asarray(idx.coefficients_at(np.arange(N)), np.complex128)
        tops = [BestRows(9, None) for _ in range(N)]
        search_block(table, q, feature_vector(q), tops, Cascade(idx.samples), threads=1)
    expected_nb, expected_d = np.full((N, 8), -1), np.full((N, 8), np.inf)
    ids = np.asarray(ids, dtype=object)
    for i, top in enumerate(tops):
        expected_nb[i], expected_d[i] = _ordered(i, top.rows, top.dist, ids, 8)
    np.testing.assert_array_equal(nb, expected_nb)
    np.testing.assert_allclose(dist, expected_d, rtol=1e-9, atol=1e-12)
    order = np.argsort(ids, kind="stable")
    tie_key = np.empty(N, dtype=np.int64)
    tie_key[order] = np.arange(N)
    with open_index(index) as idx:
        joined_nb, joined_d, _ = nearest_others(
            idx.search_table(), idx.coefficients_at, 8, Cascade(idx.samples), tie_key=tie_key, threads=1
        )
    np.testing.assert_array_equal(joined_nb, expected_nb)
    np.testing.assert_allclose(joined_d, expected_d, rtol=1e-9, atol=1e-12)


def test_pairs_of_curves_in_memory_and_new_without_a_record(rng):
    from nfdmatch.search.groups import index_groups, index_pairs

    index = MemoryIndex(family_curves(rng, 3, 3, 0.0))
    found, stats = index_pairs(index, 0.05)
    assert stats.rows == 9 and all(p.a < p.b and p.distance <= 0.05 for p in found)
    members, _ = index_groups(index, 0.05, min_size=2)
    assert {m.id for m in members} == {p.a for p in found} | {p.b for p in found}
    with pytest.raises(ParameterError, match="does not record"):
        index_pairs(index, 0.05, new=True)
    with pytest.raises(ParameterError):
        index_groups(index, 0.05, min_size=0)
    with pytest.raises(ParameterError):
        index_pairs(index, 0.05, method="nope")


@settings(max_examples=80, deadline=None)
@given(
    n=st.integers(1, 300),
    edges=st.lists(st.tuples(st.integers(0, 299), st.integers(0, 299)), max_size=400),
)
def test_the_components_of_groups_are_those_of_a_union_find(n, edges):
    from nfdmatch.search.groups import _components

    pairs = [(x % n, y % n) for x, y in edges]
    parent = list(range(n))

    def find(x):
        while parent[x] != x:
            x = parent[x]
        return x

    for x, y in pairs:
        rx, ry = find(x), find(y)
        if rx != ry:
            parent[max(rx, ry)] = min(rx, ry)
    a = np.array([p[0] for p in pairs], dtype=np.int64)
    b = np.array([p[1] for p in pairs], dtype=np.int64)
    assert _components(n, a, b).tolist() == [find(x) for x in range(n)]


@pytest.mark.parametrize("stop", [KeyboardInterrupt, RuntimeError])
def test_a_join_stopped_early_does_not_finish_the_steps_running(stop, monkeypatch):
    """Ctrl-C (or a fault) while the join's steps run on threads: the steps running stop at
    their next batch of exact distances instead of finishing (their pairs are thrown away;
    `pairs` went on ~11 s after Ctrl-C, its CLI killed by the watchdog meanwhile)."""
    from nfdmatch.search.join import _Join

    rng = np.random.default_rng(3)
    index = MemoryIndex(family_curves(rng, 8, 30, 0.3), rows_per_cell=10)
    cascade = Cascade(index.samples, truncate=False)
    stopped, calls, after = [], [], []
    exact = _Join._exact

    def counted(self, a, bs, thr):
        calls.append(len(bs))
        if stopped:
            after.append(len(bs))
        return exact(self, a, bs, thr)

    def progress(done, total):
        if done >= 1:
            stopped.append(done)
            raise stop("stop")

    monkeypatch.setattr(_Join, "_exact", counted)
    with pytest.raises(stop):
        pairs_within(index.search_table(), index.coefficients_at, 10.0, cascade, threads=2, progress=progress)
    assert len(after) <= 2, after  # at most one batch per thread began after the stop
    began = len(calls)
    stopped.clear()
    calls.clear()
    pairs_within(index.search_table(), index.coefficients_at, 10.0, cascade, threads=2)
    assert began < len(calls) / 2, (began, len(calls))  # the join did not run to its end
