"""k-NN search with lower-bound pruning equals the exhaustive exact ranking."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from oracle import random_rigid_motion, resample_polyline, smooth_curve_samplings, start_shift

from nfdmatch import Curve, distance
from nfdmatch.search import MemoryIndex, rank_curves, search_index


def _family_curves(rng, families, members, noise):
    """Clusters of the same curve re-sampled, re-posed and perturbed: what retrieval sees."""
    curves = []
    for f in range(families):
        versions = smooth_curve_samplings(
            rng, [int(rng.integers(60, 200)) for _ in range(members)], n_harmonics=int(rng.integers(2, 7))
        )
        for m, pts in enumerate(versions):
            pts = pts + rng.normal(scale=noise, size=pts.shape)
            curves.append(
                Curve(random_rigid_motion(start_shift(pts, int(rng.integers(len(pts)))), rng), id=f"f{f:03d}-m{m:02d}")
            )
    return curves


def _variants(rng, curves, count):
    """Fresh queries: stored curves re-sampled, re-posed, start-shifted, some reversed or
    mirrored, with a little noise."""
    out = []
    for i in rng.choice(len(curves), min(count, len(curves)), replace=False):
        pts = resample_polyline(curves[int(i)].points, int(rng.integers(40, 160)), rng)
        pts = start_shift(pts, int(rng.integers(len(pts))))
        if rng.random() < 0.5:
            pts = pts[::-1]
        if rng.random() < 0.25:
            pts = pts * np.array([1.0, 1.0, -1.0])
        pts = pts + rng.normal(scale=0.005 * np.ptp(pts), size=pts.shape)
        out.append(Curve(random_rigid_motion(pts, rng), id=f"q{len(out)}"))
    return out


def _same(pruned, full):
    for p, f in zip(pruned, full):
        assert [r.id for r in p] == [r.id for r in f]
        assert np.allclose([r.distance for r in p], [r.distance for r in f], rtol=1e-12, atol=1e-12)
        assert [r.rank for r in p] == list(range(1, len(p) + 1))


@settings(max_examples=14, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    top=st.integers(1, 12),
    families=st.integers(1, 12),
    members=st.integers(1, 6),
    noise=st.sampled_from([0.0, 0.01, 0.1]),
    mirror=st.booleans(),
    strict=st.booleans(),
    cells=st.sampled_from([None, 1, 3, 16]),
    truncate=st.booleans(),
)
def test_pruned_search_equals_exhaustive_ranking(seed, top, families, members, noise, mirror, strict, cells, truncate):
    rng = np.random.default_rng(seed)
    curves = _family_curves(rng, families, members, noise)
    queries = _family_curves(rng, 2, 1, noise) + _variants(rng, curves, 2) + [curves[int(rng.integers(len(curves)))]]
    index = MemoryIndex(curves, rows_per_cell=cells)
    options = dict(k=top, mirror=mirror, direction="strict" if strict else "invariant")
    pruned, stats = search_index(index, queries, truncate=truncate, **options)
    full, full_stats = search_index(index, queries, prune=False, **options)
    assert full_stats.exact == len(queries) * len(curves)
    assert stats.exact <= full_stats.exact
    _same(pruned, full)


@pytest.mark.slow
@settings(max_examples=6, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(seed=st.integers(0, 2**32 - 1), top=st.integers(1, 15), max_distance=st.sampled_from([None, 0.05, 0.3]))
def test_pruned_equals_exhaustive_on_an_index_file_with_cells(seed, top, max_distance, tmp_path_factory, monkeypatch):
    """The stored /search cells (many small ones), read cell by cell, give the exhaustive answer."""
    from nfdmatch import write_curves
    from nfdmatch.index import build_index, open_index
    from nfdmatch.search import cells as cells_module

    monkeypatch.setattr(cells_module, "ROWS_PER_CELL", 4)
    rng = np.random.default_rng(seed)
    folder = tmp_path_factory.mktemp("lib")
    curves = _family_curves(rng, 10, 4, 0.01)
    for a in range(0, len(curves), 8):
        write_curves(str(folder / f"part{a:03d}.obj"), [c.points for c in curves[a : a + 8]])
    index_path = str(folder / "idx.h5")
    build_index([str(folder)], index_path, jobs=1)
    queries = _variants(rng, curves, 3) + _family_curves(rng, 1, 1, 0.0)
    with open_index(index_path) as idx:
        assert idx.format_version >= 2 and idx.search_table().n_cells >= 8
        pruned, stats = search_index(idx, queries, k=top, max_distance=max_distance)
        full, _ = search_index(idx, queries, k=top, max_distance=max_distance, prune=False)
    _same(pruned, full)
    assert stats.cells <= stats.cell_count * len(queries)


@pytest.mark.slow
def test_search_work_does_not_grow_with_the_index_for_a_near_duplicate(rng):
    """One best-first order over all rows: adding unrelated rows (here, in front of the
    query's family) changes neither the answer nor the number of exact distances much."""
    families = _family_curves(rng, 30, 6, 0.01)
    unrelated = [Curve(c.points, id="u" + c.id) for c in _family_curves(rng, 500, 6, 0.01)]
    pts = start_shift(families[3].points, 17)[::-1]
    query = [Curve(random_rigid_motion(pts + rng.normal(scale=1e-3, size=pts.shape), rng), id="q")]
    small = MemoryIndex(families, rows_per_cell=16)
    big = MemoryIndex(unrelated + families, rows_per_cell=16)
    (r_small,), s_small = search_index(small, query, k=5)
    (r_big,), s_big = search_index(big, query, k=5)
    assert r_small[0].id == families[3].id
    assert [r.id for r in r_small] == [r.id for r in r_big]
    assert s_big.exact <= s_small.exact + 10
    assert s_big.scanned < big.n_curves / 2  # the cells kept most rows unread


def test_pruning_skips_most_rows_on_clustered_data(rng):
    curves = _family_curves(rng, 40, 5, 0.01)
    index = MemoryIndex(curves)
    results, stats = search_index(index, curves[::10], k=5)
    assert stats.exact_fraction < 0.5
    for q, res in zip(curves[::10], results):
        assert res[0].id == q.id and res[0].distance < 1e-9


def test_matches_pairwise_distance_and_max_distance(rng):
    curves = _family_curves(rng, 6, 3, 0.02)
    query = curves[4]
    ranked = rank_curves(query, curves, k=None, max_distance=0.2)
    expected = sorted((distance(query, c).distance, c.id) for c in curves)
    expected = [(d, i) for d, i in expected if d <= 0.2]
    assert [r.id for r in ranked] == [i for _, i in expected]
    assert np.allclose([r.distance for r in ranked], [d for d, _ in expected], rtol=1e-9, atol=1e-12)


def test_ties_are_ordered_by_id():
    t = np.linspace(0, 2 * np.pi, 200, endpoint=False)
    circle = np.c_[np.cos(t), np.sin(t), 0 * t]
    curves = [Curve(circle * s, id=name) for s, name in ((1, "c"), (2, "a"), (3, "b"))]
    ranked = rank_curves(curves[0], curves, k=3)
    assert [r.id for r in ranked] == ["a", "b", "c"]


class _IdsOnly:
    """An index as rank_rows sees it: ids by row, and which rows it was asked for."""

    def __init__(self, ids):
        self.ids, self.asked = ids, []

    def ids_at(self, rows):
        self.asked.extend(int(r) for r in rows)
        return [self.ids[int(r)] for r in rows]


@settings(max_examples=60, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    m=st.integers(0, 60),
    levels=st.integers(1, 8),
    top=st.one_of(st.none(), st.integers(1, 70)),
)
def test_rows_are_ranked_by_distance_then_id_and_ids_are_read_only_for_ties(seed, m, levels, top):
    """rank_rows orders a query's rows as the reported matches are ordered (distance, distances
    within TIE by id), ``top`` cut inside a tie included, reading ids only for a query with a tie."""
    from nfdmatch.search.engine import TIE, BestRows
    from nfdmatch.search.index_search import rank_rows

    rng = np.random.default_rng(seed)
    n_rows = 100
    ids = [f"f{rng.integers(0, 10**6)}#{i}" for i in range(n_rows)]
    index = _IdsOnly(ids)
    tops = []
    for _ in range(3):
        tk = BestRows(None, None)
        tk.rows = rng.permutation(n_rows)[:m].astype(np.int64)
        # few distinct distances (ties), some moved by less than TIE (ties too)
        tk.dist = rng.integers(0, levels, m) * 0.25 + rng.choice([0.0, 0.3 * TIE], m)
        tk.extra = {"shift": tk.rows * 0.5, "position": -tk.rows}
        tops.append(tk)
    want = []
    for tk in tops:
        order = sorted(range(m), key=lambda i: (round(float(tk.dist[i]) / TIE), ids[tk.rows[i]]))[:top]
        want.append((tk.rows[order], tk.dist[order]))
    tied = {int(r) for tk in tops for r in tk.rows if len(np.unique(np.round(tk.dist / TIE))) < len(tk.rows)}
    rank_rows(index, tops, top)
    for tk, (rows, dist) in zip(tops, want):
        assert tk.rows.tolist() == rows.tolist()
        assert tk.dist.tolist() == dist.tolist()
        assert tk.extra["shift"].tolist() == (rows * 0.5).tolist()
        assert tk.extra["position"].tolist() == (-rows).tolist()
    assert set(index.asked) <= tied


def test_weights_disable_pruning_but_still_rank(rng):
    curves = _family_curves(rng, 4, 2, 0.01)
    w = np.linspace(1, 0, 16)
    ranked = rank_curves(curves[0], curves, k=3, weights=w)
    assert ranked[0].id == curves[0].id


def test_bad_arguments(rng):
    index = MemoryIndex(_family_curves(rng, 1, 2, 0.0))
    from nfdmatch.errors import ParameterError

    for kwargs in ({"k": 0}, {"k": None}, {"method": "fast"}):
        with pytest.raises(ParameterError):
            search_index(index, [Curve(np.eye(3))], **kwargs)


def test_a_batch_on_ahead_of_time_kernels_releasing_the_gil_runs_on_threads_without_numba(monkeypatch, rng):
    """The kernels ``make install`` builds release the GIL: a batch answers its queries on
    threads at once, never importing numba's just-in-time kernels, and the answer is the
    exhaustive one."""
    from concurrent.futures import ThreadPoolExecutor

    from nfdmatch.matching import kernels

    monkeypatch.setattr(kernels, "_chosen", kernels.choose("auto"))
    assert kernels.current().name == "aot" and kernels.current().threads, "make install builds them"
    pools = []

    class CountingPool(ThreadPoolExecutor):
        def __init__(self, *args, **kwargs):
            super().__init__(*args, **kwargs)
            pools.append(self)

    monkeypatch.setattr("concurrent.futures.ThreadPoolExecutor", CountingPool)
    curves = _family_curves(rng, 20, 4, 0.01)
    queries = _variants(rng, curves, 6)
    index = MemoryIndex(curves, rows_per_cell=8)
    pruned, _ = search_index(index, queries, k=5, threads=2)
    assert pools and kernels.current().name == "aot"
    full, _ = search_index(index, queries, k=5, prune=False)
    _same(pruned, full)


def test_a_table_reads_only_the_first_harmonics_for_the_first_bound_and_all_of_them_once(monkeypatch):
    """``head_harmonics``: a request for the first H harmonics, from a search expecting
    many such rows, reads only those; a request for more reads every harmonic; a cell held
    with every harmonic serves a later request for the first ones without reading; a
    search expecting few rows reads their cells whole at once."""
    from nfdmatch.search import table as table_module
    from nfdmatch.search.table import SearchTable

    rng = np.random.default_rng(3)
    N, K, H = 100, 6, 4
    coefficients = (rng.standard_normal((N, K, 3)) + 1j * rng.standard_normal((N, K, 3))).astype(np.complex64)
    features = rng.random((N, 2 * K + 3)).astype(np.float32)
    start = np.arange(0, N + 1, 10)
    calls = []

    def read_descriptors(a, b, harmonics=None):
        calls.append((a, b, harmonics))
        return coefficients[a:b, : harmonics or K]

    table = SearchTable(
        K,
        start,
        np.zeros((N // 10, 2 * K + 3)),
        np.full((N // 10, 2), np.inf),
        lambda a, b: (np.arange(a, b), features[a:b], None, None),
        lambda rows: coefficients[rows],
        read_descriptors,
        head_harmonics=H,
    )
    positions = np.array([12, 3, 15])
    table.open_cells(np.array([0, 1]))
    monkeypatch.setattr(table_module, "_HEAD_FROM_ROWS", 5)  # "many" for a table of 100 rows
    many = 5
    assert np.array_equal(table.coefficients_at_positions(positions, H, expect=many), coefficients[positions, :H])
    assert {h for *_, h in calls} == {H}
    calls.clear()
    assert np.array_equal(table.coefficients_at_positions(positions), coefficients[positions])
    assert calls and {h for *_, h in calls} == {None}
    table.open_cells(np.array([2]))
    calls.clear()
    assert np.array_equal(table.coefficients_at_positions(np.array([21, 22]), 2 * K), coefficients[[21, 22]])
    assert np.array_equal(
        table.coefficients_at_positions(np.array([29, 20]), H, expect=many), coefficients[[29, 20], :H]
    )
    assert [h for *_, h in calls] == [None]  # cell 2 held whole: its first harmonics need no read
    table.open_cells(np.array([3]))
    calls.clear()  # few rows expected: their cells are read whole at once
    assert np.array_equal(table.coefficients_at_positions(np.array([33]), H, expect=2), coefficients[[33], :H])
    assert [h for *_, h in calls] == [None]


def test_an_index_file_stores_the_first_harmonics_apart_and_its_search_reads_them_alone(tmp_path, monkeypatch):
    """Unrelated curves (loose invariant bounds: the first truncated bound runs on many
    rows): it reads /search/coefficients' first chunk of harmonics only, and answers as the
    exhaustive search does."""
    from nfdmatch import write_curves
    from nfdmatch.index import build_index, open_index
    from nfdmatch.search import cells as cells_module
    from nfdmatch.search import table as table_module
    from nfdmatch.search.bounds import TRUNCATED_HARMONICS

    monkeypatch.setattr(cells_module, "ROWS_PER_CELL", 8)
    monkeypatch.setattr(table_module, "_HEAD_FROM_ROWS", 16)  # a small index: "many rows" scaled down
    rng = np.random.default_rng(11)
    curves = [random_rigid_motion(smooth_curve_samplings(rng, [80], n_harmonics=6)[0], rng) for _ in range(600)]
    write_curves(str(tmp_path / "lib.obj"), curves)
    build_index([str(tmp_path / "lib.obj")], str(tmp_path / "idx.h5"), jobs=1)
    widths = []
    read_runs = table_module.SearchTable._read_cell_descriptors
    load_all = table_module.SearchTable._load_all_descriptors
    monkeypatch.setattr(
        table_module.SearchTable,
        "_read_cell_descriptors",
        lambda self, tier, cells: (widths.append(tier.harmonics), read_runs(self, tier, cells))[1],
    )
    monkeypatch.setattr(
        table_module.SearchTable,
        "_load_all_descriptors",
        lambda self, tier: (widths.append(tier.harmonics), load_all(self, tier))[1],
    )
    queries = _variants(rng, [Curve(c, id=str(i)) for i, c in enumerate(curves)], 3)
    with open_index(str(tmp_path / "idx.h5")) as idx:
        stored = idx._h5["search/coefficients"]
        assert stored.chunks[1] == TRUNCATED_HARMONICS < stored.shape[1]
        pruned, stats = search_index(idx, queries, k=5)
        assert TRUNCATED_HARMONICS in widths and stats.truncated > 0
        full, _ = search_index(idx, queries, k=5, prune=False)
    _same(pruned, full)


def test_a_batch_answered_on_one_thread_does_not_import_numpy_ma():
    """Deciding when to switch kernels takes the median pace of the queries: np.median
    imports numpy.ma on first use (25 ms of a command's start-up)."""
    import os
    import subprocess
    import sys

    code = (
        "import sys, numpy as np\n"
        "from nfdmatch import Curve\n"
        "from nfdmatch.search import MemoryIndex, search_index\n"
        "t = np.linspace(0, 2 * np.pi, 64, endpoint=False)[:, None]\n"
        "curves = [Curve(np.hstack([np.cos(t), np.sin(k * t), np.sin(3 * t) / k]), id=str(k)) for k in range(1, 9)]\n"
        "search_index(MemoryIndex(curves), curves, k=2, threads=2)\n"
        "print('numpy.ma' in sys.modules)\n"
    )
    env = {k: v for k, v in os.environ.items() if k != "NFDMATCH_KERNELS"}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, check=True)
    assert out.stdout.strip() == "False"


def test_a_table_told_of_more_queries_reads_whole_what_they_would_read_most_of():
    """``expect_more``: the first query's reads, times the queries left, decide: a width of
    descriptors it read a tenth of is read whole for 9 more queries, not for 1."""
    from nfdmatch.search.table import SearchTable

    rng = np.random.default_rng(5)
    N, K = 100, 6
    coefficients = (rng.standard_normal((N, K, 3)) + 1j * rng.standard_normal((N, K, 3))).astype(np.complex64)
    features = rng.random((N, 2 * K + 3)).astype(np.float32)
    calls = []

    def table():
        def read_descriptors(a, b, harmonics=None):
            calls.append((a, b))
            return coefficients[a:b, : harmonics or K]

        return SearchTable(
            K,
            np.arange(0, N + 1, 10),
            np.zeros((10, 2 * K + 3)),
            np.full((10, 2), np.inf),
            lambda a, b: (np.arange(a, b), features[a:b], None, None),
            lambda rows: coefficients[rows],
            read_descriptors,
        )

    for more, whole in ((1, False), (9, True)):
        t = table()
        t.open_cells(np.array([3]))
        t.coefficients_at_positions(np.array([31, 35]))
        calls.clear()
        t.expect_more(more)
        assert (calls == [(0, N)]) is whole
        assert np.array_equal(t.coefficients_at_positions(np.array([95, 2])), coefficients[[95, 2]])


def test_a_search_skipping_cells_answers_for_the_other_cells_exactly(rng):
    """``skip_cells`` (the cluster's second round, which leaves out the cells of the first):
    the answer is the exhaustive one over the rows of the cells not skipped."""
    from nfdmatch.descriptors import descriptors_batch
    from nfdmatch.matching import exact_search
    from nfdmatch.search.bounds import feature_vector
    from nfdmatch.search.engine import Cascade, BestRows, search_block

    curves = _family_curves(rng, 8, 4, 0.01)
    index = MemoryIndex(curves, rows_per_cell=4)
    table = index.search_table()
    skip = np.sort(rng.choice(table.n_cells, table.n_cells // 2, replace=False))
    skipped_rows = np.concatenate([table.cell_rows(np.array([c]))[0] for c in skip])
    kept = np.setdiff1d(np.arange(len(curves)), skipped_rows)
    for query in _variants(rng, curves, 3):
        A = descriptors_batch(
            [query], samples=index.samples, harmonics=index.harmonics, scale=index.scale_mode
        ).coefficients[0]
        A = np.asarray(A, dtype=np.complex128)
        top = BestRows(5, None)
        search_block(table, A[None], feature_vector(A[None]), [top], Cascade(index.samples), skip_cells=[skip])
        everything = exact_search(A, index.coefficients_at(kept), index.samples)["distance"]
        best = kept[np.argsort(everything, kind="stable")[:5]]
        assert set(top.rows.tolist()) == set(best.tolist())
        assert np.allclose(np.sort(top.dist)[:5], np.sort(everything)[:5], rtol=1e-9, atol=1e-12)


@pytest.fixture(params=["numpy", "numba", "aot"])
def each_kernels(request):
    """The process's kernels set to each kind in turn (restored after)."""
    from nfdmatch.matching import kernels

    before = kernels.current()
    got = kernels.use_kernels(request.param)
    if got.name != request.param:
        kernels.use_kernels(before)
        pytest.fail(f"{request.param} kernels cannot be loaded: {got.reason}")
    yield got
    kernels.use_kernels(before)


def test_a_row_computed_by_the_kernels_has_the_same_digits_whatever_rows_come_with_it(rng, each_kernels):
    """Bit for bit, on each kind of kernels: a row's distance, shift and rotation do not
    depend on the other rows of the call, their number or the threads (the search reports
    these digits)."""
    from nfdmatch.matching import exact_search

    curves = _family_curves(rng, 4, 20, 0.02)
    B = np.concatenate(
        [MemoryIndex(curves).coefficients_at(np.arange(len(curves)))] * 8
    )  # 640 rows: split over threads
    for query in (0, 7, 33):
        whole = exact_search(B[query], B, 128, kernels=each_kernels)
        for N in (1, 2, 5, 300):
            for first in (0, 3, 41):
                part = exact_search(B[query], B[first : first + N], 128, kernels=each_kernels)
                for key in ("distance", "shift", "rotation", "reversed", "mirrored"):
                    assert np.array_equal(part[key], whole[key][first : first + N]), (key, N, first)


def test_a_match_reports_the_same_digits_whatever_top_asks_for(rng, each_kernels):
    """A row's digits must not depend on how many rows come with it nor on the threshold
    the search met it at (``--top 1`` and ``--top 8`` print the same distance for the best
    match), on each kind of kernels."""
    curves = _family_curves(rng, 6, 5, 0.02)
    queries = _variants(rng, curves, 4)
    index = MemoryIndex(curves, rows_per_cell=8)
    wide, _ = search_index(index, queries, k=8)
    for top in (1, 2, 3, 5):
        narrow, _ = search_index(index, queries, k=top)
        for n, w in zip(narrow, wide):
            assert [(r.id, r.distance, r.shift) for r in n] == [(r.id, r.distance, r.shift) for r in w[:top]]
    within, _ = search_index(index, queries, k=None, max_distance=wide[0][4].distance)
    assert [(r.id, r.distance) for r in within[0]] == [(r.id, r.distance) for r in wide[0][:5]]


def test_a_batch_reports_each_query_as_a_search_of_its_own_would(rng, each_kernels):
    """The digits of a query in a batch are those of the query searched alone, on each
    kind of kernels."""
    curves = _family_curves(rng, 6, 5, 0.02)
    queries = _variants(rng, curves, 5)
    index = MemoryIndex(curves, rows_per_cell=8)
    together, _ = search_index(index, queries, k=4)
    for q, expect in zip(queries, together):
        alone, _ = search_index(index, [q], k=4)
        assert [(r.id, r.distance, r.shift, r.reversed) for r in alone[0]] == [
            (r.id, r.distance, r.shift, r.reversed) for r in expect
        ]


def test_the_recomputation_in_small_passes_gives_the_same_answers(rng, monkeypatch):
    """The reported rows are recomputed in passes of at most EXHAUSTIVE_ROWS rows, queries
    packed together and split across passes: the size of the passes changes no digit."""
    from nfdmatch.search import index_search

    curves = _family_curves(rng, 6, 5, 0.02)
    queries = _variants(rng, curves, 5)
    index = MemoryIndex(curves, rows_per_cell=8)
    whole, _ = search_index(index, queries, k=7)
    monkeypatch.setattr(index_search, "EXHAUSTIVE_ROWS", 3)
    small, _ = search_index(index, queries, k=7)
    assert [[(r.id, r.distance, r.shift) for r in q] for q in small] == [
        [(r.id, r.distance, r.shift) for r in q] for q in whole
    ]


def test_a_memory_index_of_no_curves_answers_nothing(rng):
    """MemoryIndex([]) raised numpy's "cannot reshape array of size 0 into shape (0,newaxis)";
    it answers every query with nothing, as an index file of no curves does."""
    query = _family_curves(rng, 1, 1, 0.0)[0]
    empty = MemoryIndex([])
    assert len(empty) == 0
    assert empty.search(query, k=3) == [[]]
    assert empty.search(query, k=3, elastic=True) == [[]]
    assert empty.search(query, k=None, max_distance=1.0) == [[]]
    distances, rows = empty.search(query, k=2, arrays=True)
    assert np.array_equal(distances, [[np.inf, np.inf]]) and np.array_equal(rows, [[-1, -1]])
