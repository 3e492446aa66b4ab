"""The elastic stage: the elastic distance's kernels against the numpy reference, its
invariances, what it is for (a bent part), degenerate curves, and the stage in the search,
the Python API and the CLI (docs/elastic.md)."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import oracle as o
from nfdmatch import Curve, build_index, open_index
from nfdmatch.descriptors import descriptors_batch
from nfdmatch.matching import NUMPY, exact_search
from nfdmatch.matching.elastic import elastic_distances, elastic_reference, elastic_rows, posed_rows
from nfdmatch.matching.fused import ELASTIC_QUANTILES, RIGID_QUANTILES, fuse, fused_distance, fused_rows
from nfdmatch.matching.kernels import choose
from nfdmatch.matching.statistics import LENGTH, curve_statistics, statistics_distance
from nfdmatch.search import rank_curves
from nfdmatch.search.stages import ElasticStage


def _compiled():
    """The compiled kernels this install has (ahead of time and numba), each by name."""
    out = []
    for name in ("aot", "numba"):
        kernels = choose(name)
        if kernels.name == name:
            out.append(kernels)
    return out


COMPILED = _compiled()


def _coefficients(curves):
    return descriptors_batch(curves).coefficients


def _random_coefficients(seed, count, planar):
    """The descriptors of ``count`` random smooth curves (in the plane z = 0 when ``planar``)."""
    rng = np.random.default_rng(seed)
    curves = [o.random_smooth_curve(rng, 300, n_harmonics=int(rng.integers(2, 9))) for _ in range(count)]
    if planar:
        for c in curves:
            c[:, 2] = 0.0
    return _coefficients(curves)


def _copy(points, rng, *, reverse=False):
    """A re-posed, re-scaled, resampled, start-shifted (and maybe reversed) copy."""
    q = o.resample_polyline(points, int(rng.integers(150, 700)), rng)
    q = o.start_shift(q, int(rng.integers(0, len(q))))
    if reverse:
        q = o.reverse(q)
    return o.random_rigid_motion(q, rng)


@pytest.mark.skipif(not COMPILED, reason="no compiled kernels: the numpy reference is the only path")
@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 2**32 - 1), mirror=st.booleans(), planar=st.booleans())
def test_compiled_kernel_equals_the_numpy_reference(seed, mirror, planar):
    C = _random_coefficients(seed, 4, planar)
    rigid = exact_search(C[0], C, 128, mirror=mirror)
    reference = np.array(
        [
            elastic_reference(
                C[0],
                posed_rows(C[r : r + 1], rigid["reversed"][r : r + 1], rigid["mirrored"][r : r + 1])[0],
                (rigid["shift"][r] / 128 + 0.5) % 1.0 - 0.5,
            )
            for r in range(len(C))
        ]
    )  # fmt: skip
    assert np.allclose(
        elastic_rows(C[0], C, rigid["shift"], rigid["reversed"], rigid["mirrored"], 128, kernels=NUMPY), reference
    )
    for kernels in COMPILED:
        got = elastic_rows(C[0], C, rigid["shift"], rigid["reversed"], rigid["mirrored"], 128, kernels=kernels)
        assert np.allclose(got, reference, rtol=1e-9, atol=1e-9), kernels.name


@settings(max_examples=20, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 2**32 - 1), reverse=st.booleans())
def test_a_reposed_resampled_restarted_copy_is_at_about_zero(seed, reverse):
    rng = np.random.default_rng(seed)
    p = o.random_smooth_curve(rng, 800, n_harmonics=5)
    other = o.random_smooth_curve(rng, 800, n_harmonics=5)
    _, same = fused_distance(p, _copy(p, rng, reverse=reverse))
    _, different = fused_distance(p, other)
    assert same.elastic[0] < 0.25 * different.elastic[0]
    assert same.fused[0] < 0.1
    assert same.fused[0] < 0.25 * different.fused[0]


@settings(max_examples=15, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 2**32 - 1), planar=st.booleans(), mirror=st.booleans())
def test_the_elastic_distance_is_the_lesser_of_both_directions_best_poses(seed, planar, mirror):
    """At the rigid optimum and at the other direction's best pose (searched as the rigid
    one): the lesser, symmetric in the pair; a search strict in direction keeps one pose."""
    C = _random_coefficients(seed, 5, planar)
    rigid = exact_search(C[0], C, 128, mirror=mirror)
    at_rigid = elastic_rows(C[0], C, rigid["shift"], rigid["reversed"], rigid["mirrored"], 128)
    got = elastic_distances(C[0], C, rigid, 128, mirror=mirror)
    other_way = np.where(rigid["reversed"][:, None, None], C, np.conj(C))
    other = exact_search(C[0], other_way, 128, direction="strict", mirror=mirror)
    at_other = elastic_rows(C[0], other_way, other["shift"], np.zeros(len(C), bool), other["mirrored"], 128)
    assert np.array_equal(got, np.minimum(at_rigid, at_other))
    for r in range(1, len(C)):
        back = exact_search(C[r], C[:1], 128, mirror=mirror)
        assert elastic_distances(C[r], C[:1], back, 128, mirror=mirror)[0] == pytest.approx(got[r], rel=1e-6, abs=1e-9)
    strict = exact_search(C[0], C, 128, direction="strict", mirror=mirror)
    assert np.array_equal(
        elastic_distances(C[0], C, strict, 128, direction="strict", mirror=mirror),
        elastic_rows(C[0], C, strict["shift"], strict["reversed"], strict["mirrored"], 128),
    )


def test_the_distance_is_symmetric_and_zero_for_the_same_curve(rng):
    a, b = o.random_smooth_curve(rng, 400), o.random_smooth_curve(rng, 400)
    m_ab, ab = fused_distance(a, b)
    m_ba, ba = fused_distance(b, a)
    assert ab.elastic[0] == pytest.approx(ba.elastic[0], rel=1e-6)
    assert ab.fused[0] == pytest.approx(ba.fused[0], rel=1e-6)
    _, aa = fused_distance(a, a)
    assert aa.elastic[0] == pytest.approx(0.0, abs=1e-9)
    assert aa.fused[0] == pytest.approx(0.0, abs=1e-6)


def _hand(bend_degrees: float = 0.0, n: int = 400) -> np.ndarray:
    """A palm (an ellipse) with four fingers: long thin bumps of the polar radius; with
    ``bend_degrees`` the points of the second finger turned about its base."""
    t = np.linspace(0, 2 * np.pi, n, endpoint=False)
    r = 1.0 + sum(1.1 * np.exp(-(((t - c + np.pi) % (2 * np.pi) - np.pi) ** 2) / 0.004) for c in (0.5, 1.1, 1.7, 2.3))
    points = np.stack([1.2 * r * np.cos(t), r * np.sin(t), np.zeros(n)], axis=1)
    if bend_degrees:
        finger = np.abs(((t - 1.1 + np.pi) % (2 * np.pi)) - np.pi) < 0.22
        base = points[finger][[0, -1]].mean(axis=0)
        a = np.radians(bend_degrees)
        turn = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
        points[finger] = (points[finger] - base) @ turn.T + base
    return points


def test_a_bent_finger_is_nearer_under_the_elastic_distance_than_under_the_rigid_one():
    """Each distance on its own scale (its quantile among the development pairs, the scale
    the fused distance sums): the bent copy ranks nearer by the elastic distance."""
    match, terms = fused_distance(_hand(), _hand(bend_degrees=35.0))
    rigid_rank = np.interp(match.distance, RIGID_QUANTILES, np.linspace(0, 1, 17))
    elastic_rank = np.interp(terms.elastic[0], ELASTIC_QUANTILES, np.linspace(0, 1, 17))
    assert elastic_rank < rigid_rank


@pytest.mark.parametrize(
    "points",
    [
        o.collinear_back_and_forth(50),
        o.figure_eight_planar(100),
        np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]]),
        np.repeat(o.ellipse(2, 1, 20), 3, axis=0),
    ],
    ids=["collinear", "figure-eight", "three-vertices", "repeated-points"],
)
def test_degenerate_curves_get_finite_terms(points):
    _, terms = fused_distance(points, o.ellipse(2, 1, 50))
    for key in ("elastic", "statistics", "fused"):
        value = getattr(terms, key)[0]
        assert np.isfinite(value) and value >= 0, key
    assert np.all(np.isfinite(curve_statistics(_coefficients([points])[0])))


def test_mirror_images_are_apart_unless_mirror_is_asked_for():
    knot = o.torus_knot(2, 3, 300)
    mirrored = knot * np.array([1.0, 1.0, -1.0])
    _, strict = fused_distance(knot, mirrored)
    _, allowed = fused_distance(knot, mirrored, mirror=True)
    assert allowed.fused[0] < 0.05 < strict.fused[0]


def test_statistics_are_pose_free_and_blind_to_sampling(rng):
    p = o.random_smooth_curve(rng, 600)
    a = curve_statistics(_coefficients([p])[0])
    b = curve_statistics(_coefficients([_copy(p, rng, reverse=True) * np.array([1, 1, -1])])[0])
    assert a.shape == (LENGTH,)
    assert statistics_distance(a, b[None])[0] < 0.5


def test_fuse_maps_each_term_through_its_quantiles():
    assert fuse(0.0, 0.0, 0.0) == 0.0
    assert fuse(1e9, 1e9, 1e9) == 3.0
    assert 0 < fuse(0.2, 2.5, 5.0) < 3


def _families(rng, count=6, members=5):
    """Curves in families: a smooth shape each, members re-posed, resampled copies."""
    curves = []
    for f in range(count):
        base = o.random_smooth_curve(rng, 500, n_harmonics=4)
        for m in range(members):
            curves.append(Curve(_copy(base, rng, reverse=bool(m % 2)), id=f"f{f}-{m}"))
    return curves


def _family_folder(tmp_path, rng, count=4, members=6):
    from nfdmatch.formats import write_curves

    curves = _families(rng, count=count, members=members)
    folder = tmp_path / "lib"
    folder.mkdir()
    for c in curves:
        write_curves(str(folder / f"{c.id}.csv"), [c])
    return folder, curves


def test_the_stage_reorders_the_exact_top_m_and_equals_the_fused_distance(tmp_path, rng):
    curves = _families(rng)
    query = curves[0]
    ranked = rank_curves(query, curves[1:], k=5, stage=ElasticStage(depth=12))
    assert [m.rank for m in ranked] == [1, 2, 3, 4, 5]
    fused = [m.fused for m in ranked]
    assert fused == sorted(fused)
    plain = rank_curves(query, curves[1:], k=12)
    assert {m.id for m in ranked} <= {m.id for m in plain}
    for m in ranked:
        _, terms = fused_distance(query, curves[1:][m.row])
        assert m.fused == pytest.approx(terms.fused[0], abs=1e-5)
        assert m.distance == pytest.approx(next(p.distance for p in plain if p.id == m.id))
    # the family members come first, by either order
    assert all(m.id.startswith("f0-") for m in ranked[:4])


def test_index_search_elastic_matches_rank_curves_and_checks_its_options(tmp_path, rng):
    from nfdmatch.errors import ParameterError

    folder, _ = _family_folder(tmp_path, rng, count=4, members=4)
    build_index([str(folder)], str(tmp_path / "x.h5"))
    with open_index(str(tmp_path / "x.h5")) as idx:
        found = idx.search(str(folder / "f1-0.csv"), k=3, elastic=True, elastic_depth=8, exclude_self=True)[0]
        assert len(found) == 3 and all("f1-" in m.id for m in found)
        assert all(m.elastic is not None and m.fused is not None and m.pose is not None for m in found)
        with pytest.raises(ParameterError):
            idx.search(str(folder / "f1-0.csv"), k=3, elastic_depth=8)


def test_an_elastic_depth_that_is_not_a_positive_integer_is_refused(tmp_path, rng):
    """Index.search(elastic_depth=2.5) searched to depth 2 (int() of the value); "10" and
    True were taken as 10 and 1; NaN or a list raised a bare ValueError/TypeError."""
    from nfdmatch.errors import ParameterError

    folder, _ = _family_folder(tmp_path, rng, count=2, members=3)
    build_index([str(folder)], str(tmp_path / "x.h5"))
    with open_index(str(tmp_path / "x.h5")) as idx:
        for depth in (2.5, 10.0, "10", True, float("nan"), [3], 0, -1):
            with pytest.raises(ParameterError, match="elastic depth must be an integer of at least 1"):
                idx.search(str(folder / "f1-0.csv"), k=3, elastic=True, elastic_depth=depth)
            with pytest.raises(ParameterError, match="elastic depth must be an integer of at least 1"):
                ElasticStage(depth=depth)
        assert len(idx.search(str(folder / "f1-0.csv"), k=3, elastic=True, elastic_depth=np.int64(4))[0]) == 3
    assert ElasticStage(depth=np.int64(7)).candidates(3) == 7


def test_query_elastic_cli(tmp_path, rng):
    from conftest import run_cli

    folder, _ = _family_folder(tmp_path, rng, count=3, members=4)
    index = str(tmp_path / "x.h5")
    assert run_cli("index", "build", str(folder), "--index", index)[0] == 0
    query = str(folder / "f2-0.csv")
    code, out, err = run_cli(
        "query", query, "--index", index, "--elastic", "--elastic-depth", "6", "--top", "3", "--format", "json",
        "--exclude-self",
    )  # fmt: skip
    assert code == 0, err
    rows = json.loads(out)
    assert [row["rank"] for row in rows] == [1, 2, 3]
    assert list(rows[0]) == ["query", "rank", "match", "distance", "elastic", "fused"]
    assert [row["fused"] for row in rows] == sorted(row["fused"] for row in rows)
    assert all("f2-" in row["match"] for row in rows)
    code, out, err = run_cli("query", query, "--index", index, "--elastic-depth", "6")
    assert code == 2 and "--elastic-depth needs --elastic" in err and not out
    code, out, err = run_cli("query", query, "--index", index, "--elastic", "--rerank")
    assert code == 2 and "--elastic" in err and not out
    code, out, err = run_cli("distance", query, str(folder / "f2-1.csv"), "--elastic", "--format", "json")
    assert code == 0, err
    assert {"distance", "elastic", "statistics", "fused"} <= set(json.loads(out))
    code, out, err = run_cli("matrix", str(folder), "--elastic", "--format", "json")
    assert code == 0, err
    values = np.array(json.loads(out)["distances"])
    assert values.shape == (12, 12) and np.allclose(values, values.T) and np.all(np.diag(values) == 0)
    assert np.all((values >= 0) & (values <= 3))
    code, out, err = run_cli("rank", query, str(folder), "--elastic", "--top", "2", "--format", "csv")
    assert code == 0, err
    assert out.splitlines()[0] == "query,rank,match,distance,elastic,fused"


def test_show_elastic_draws_the_stage_order_and_prints_its_columns(tmp_path, rng):
    from conftest import run_cli

    folder, _ = _family_folder(tmp_path, rng, count=2, members=3)
    query = str(folder / "f0-0.csv")
    picture = tmp_path / "m.png"
    code, out, err = run_cli(
        "show", query, str(folder), "--against", "--elastic", "--top", "3", "-o", str(picture), "--format", "csv"
    )
    assert code == 0, err
    lines = out.splitlines()
    assert lines[0] == "query,rank,match,distance,elastic,fused,source"
    fused = [float(line.split(",")[5]) for line in lines[1:]]
    assert len(fused) == 3 and fused == sorted(fused)
    assert picture.stat().st_size > 0


def test_the_stage_needs_the_exact_method(tmp_path, rng):
    from nfdmatch.errors import ParameterError
    from nfdmatch.formats import write_curves

    from conftest import run_cli

    curves = _families(rng, count=2, members=2)
    with pytest.raises(ParameterError, match="exact"):
        rank_curves(curves[0], curves[1:], k=2, stage=ElasticStage(), method="paper")
    for c in curves:
        write_curves(str(tmp_path / f"{c.id}.csv"), [c])
    code, out, err = run_cli("rank", tmp_path / "f0-0.csv", tmp_path, "--elastic", "--method", "paper")
    assert code != 0 and "method must be exact" in err and not out


def test_an_elastic_graph_is_built_verified_and_diffused_over(tmp_path, rng):
    """index build --graph K --elastic stores fused distances; query --rerank then gives its
    candidates their fused distances (the exact one stays the distance column) and ranks
    like matrix --rerank --elastic; a rebuild without --elastic says the graph changes."""
    from conftest import run_cli
    from nfdmatch.search import distance_matrix
    from nfdmatch.search.rerank import diffused_similarity, fused_graph_lists

    folder, curves = _family_folder(tmp_path, rng)
    index = str(tmp_path / "x.h5")
    code, out, err = run_cli("index", "build", str(folder), "--index", index, "--graph", "8", "--elastic")
    assert code == 0, err
    assert "fused distances" in err
    code, out, err = run_cli("index", "info", "--index", index, "--format", "json")
    assert json.loads(out)["graph_distance"] == "fused"
    code, out, err = run_cli("index", "verify", "--index", index)
    assert code == 0, out + err
    with open_index(index) as idx:
        assert idx.graph_distance() == "fused"
        neighbour, distance = idx.graph_reader()(np.arange(len(curves)))
        ids = idx.ids()
        # each stored distance is the pair's fused distance
        for i in (0, 7):
            _, terms = fused_distance(curves[[c.id for c in curves].index(ids[i].split("/")[-1][:-4])],
                                      curves[[c.id for c in curves].index(ids[neighbour[i, 0]].split("/")[-1][:-4])])  # fmt: skip
            assert distance[i, 0] == pytest.approx(terms.fused[0], abs=1e-4)
    files = sorted(str(p) for p in folder.iterdir())
    code, out, err = run_cli(
        "query", *files, "--index", index, "--rerank", "--elastic", "--exclude-self", "--top", "5", "--format", "json"
    )
    assert code == 0, err
    rows = json.loads(out)
    assert list(rows[0]) == ["query", "rank", "match", "distance", "score", "elastic", "fused"]
    # the same order as matrix --rerank --elastic: the diffusion of the fused matrix over the
    # graph the index stores (its curves in the index's order; ties by exact distance)
    from nfdmatch import read_curves

    code, out, err = run_cli("matrix", *files, "--rerank", "--elastic", "--format", "json")
    assert code == 0, err
    S = np.array(json.loads(out)["scores"])
    stored = [read_curves(f)[0] for f in files]
    assert np.allclose(S, diffused_similarity(distance_matrix(stored, elastic=True), ids=files, lists=fused_graph_lists(distance_matrix(stored), distance_matrix(stored, elastic=True), files)))  # fmt: skip
    exact = distance_matrix(stored)
    agree = total = 0
    for qi, f in enumerate(files):
        mine = [os.path.basename(r["match"]) for r in rows if r["query"] == f]
        others = [j for j in np.lexsort((exact[qi], -S[qi])) if j != qi][:5]
        agree += sum(a == os.path.basename(files[j]) for a, j in zip(mine, others))
        total += len(mine)
    assert agree >= 0.99 * total
    code, out, err = run_cli("index", "build", "--index", index, "--graph", "8")
    assert code == 0 and "changes from fused to exact" in err
    with open_index(index) as idx:
        assert idx.graph_distance() == "exact"
    code, out, err = run_cli("query", files[0], "--index", index, "--rerank", "--elastic")
    assert code == 2 and "needs a graph of fused distances" in err and not out
    code, out, err = run_cli("index", "build", "--index", index, "--elastic")
    assert code == 2 and "--elastic needs --graph" in err


def test_a_graph_of_an_older_fused_distance_is_named_and_computed_afresh(tmp_path, rng):
    """A graph stamped with another fused distance's version (one written before the elastic
    term took two poses carries none: version 1) is named by query --rerank on stderr, and a
    plain `index build` rerun computes it afresh, once."""
    import h5py
    from conftest import run_cli
    from nfdmatch.matching.fused import FUSED_VERSION

    folder, curves = _family_folder(tmp_path, rng, count=3, members=5)
    index = str(tmp_path / "x.h5")
    assert run_cli("index", "build", str(folder), "--index", index, "--graph", "8", "--elastic")[0] == 0
    code, out, err = run_cli("index", "info", "--index", index, "--format", "json")
    assert json.loads(out)["graph_fused_version"] == FUSED_VERSION
    with open_index(index) as idx:
        lists = idx.graph_reader()(np.arange(len(curves)))
    with h5py.File(index, "r+") as h5:
        del h5["graph"].attrs["fused_version"]
    with open_index(index) as idx:
        assert idx.graph_fused_version() == 1
    files = sorted(str(p) for p in folder.iterdir())
    code, out, err = run_cli("query", files[0], "--index", index, "--rerank", "--top", "3")
    assert code == 0 and out
    assert "older definition (version 1" in err and "index build --index" in err
    code, out, err = run_cli("index", "build", "--index", index)
    assert code == 0 and "computed afresh" in err, err
    with open_index(index) as idx:
        assert idx.graph_fused_version() == FUSED_VERSION
        again = idx.graph_reader()(np.arange(len(curves)))
    assert np.array_equal(again[0], lists[0]) and np.allclose(again[1], lists[1])
    inode = os.stat(index).st_ino
    code, out, err = run_cli("index", "build", "--index", index)
    assert code == 0 and "computed afresh" not in err and os.stat(index).st_ino == inode
    code, out, err = run_cli("query", files[0], "--index", index, "--rerank", "--top", "3")
    assert code == 0 and "older definition" not in err


def test_fused_graph_lists_are_the_same_in_any_blocks_and_over_worker_processes(rng):
    """The fused lists of a build (blocks in the search table's order, over its --jobs
    processes) are those of the straightforward loop: each row alone, in row order, here."""
    from nfdmatch.search.engine import TIE
    from nfdmatch.search.graph import fused_lists

    curves = _families(rng, count=5, members=8)
    C = np.asarray(_coefficients(curves), dtype=np.complex128)
    S = curve_statistics(C)
    N, m, k = len(C), 9, 4
    ids = [f"c{int(i):03d}" for i in rng.permutation(N)]
    candidates = np.array([rng.choice(np.delete(np.arange(N), i), m, replace=False) for i in range(N)])
    candidates[3, 5:] = -1  # a short list, padded
    candidates[11, :] = -1  # no candidates at all
    expected_nb, expected_d = np.full((N, k), -1), np.full((N, k), np.inf)
    for i in range(N):
        found = candidates[i][candidates[i] >= 0]
        if not len(found):
            continue
        rigid = exact_search(C[i], C[found], 128)
        fused = fused_rows(C[i], C[found], rigid, 128, query_statistics=S[i], row_statistics=S[found]).fused
        order = sorted(range(len(found)), key=lambda j: (np.round(fused[j] / TIE), ids[found[j]]))[:k]
        expected_nb[i, : len(order)], expected_d[i, : len(order)] = found[order], fused[order]
    blocks = np.array_split(rng.permutation(N), 6)
    for how in ({}, {"blocks": blocks}, {"blocks": blocks, "processes": 2}):
        nb, d = fused_lists(lambda r: C[r], lambda r: S[r], ids, candidates, k, 128, **how)
        assert np.array_equal(nb, expected_nb) and np.array_equal(d, expected_d), how


def test_a_fused_graphs_batch_over_threads_answers_as_each_query_alone(tmp_path, rng, monkeypatch):
    """query --rerank on a fused graph spreads its queries' fused distances over threads (as
    on 4 cores here), a batch's PageRank push beside them, a single query's after them: the
    batch gives every query the answer it gets alone and on one thread, to the digit, with
    and without exclude_self."""
    from nfdmatch.index.graph import GraphSpec
    from nfdmatch.matching import _threads
    from nfdmatch.matching import kernels as kernels_module
    from nfdmatch.search.rerank import rerank_index

    folder, curves = _family_folder(tmp_path, rng)
    build_index([str(folder)], str(tmp_path / "f.h5"), graph=GraphSpec(8, "fused"))
    spread = []
    run_spread = _threads.run_spread
    monkeypatch.setattr(
        _threads, "run_spread", lambda calls, threads: spread.append(threads) or run_spread(calls, threads)
    )
    monkeypatch.setattr(kernels_module, "cpu_count", lambda: 4)
    queries = curves  # the batch's fused distances: ~23 a source pushed, so the push runs beside them
    limit = kernels_module._call_threads
    with open_index(str(tmp_path / "f.h5")) as idx:
        for exclude_self in (False, True):
            batch, _ = rerank_index(idx, queries, k=10, exclude_self=exclude_self)
            assert max(spread) > 1
            alone = [rerank_index(idx, [q], k=10, exclude_self=exclude_self)[0][0] for q in queries]
            try:
                kernels_module.set_call_threads(1)
                spread.clear()
                one_thread, _ = rerank_index(idx, queries, k=10, exclude_self=exclude_self)
                assert max(spread) == 1
            finally:
                kernels_module.set_call_threads(limit)
            assert batch == alone == one_thread
            assert all(m.fused is not None for r in batch for m in r)


def test_a_fused_graph_of_too_few_neighbours_is_rebuilt_fused(tmp_path, rng):
    """The advice for a graph of fewer than 8 neighbours keeps --elastic when the graph holds
    fused distances (the rebuild it gave, without it, would have made an exact graph)."""
    from conftest import run_cli

    folder, _ = _family_folder(tmp_path, rng, count=2, members=3)
    query = str(folder / "f0-0.csv")
    for extra, advice in (([], "--graph 8"), (["--elastic"], "--graph 8 --elastic")):
        index = str(tmp_path / f"x{len(extra)}.h5")
        assert run_cli("index", "build", str(folder), "--index", index, "--graph", "4", *extra)[0] == 0
        code, out, err = run_cli("query", query, "--index", index, "--rerank", *extra)
        assert (code, out) == (2, "")
        assert err == (
            f"Error: {index}: the index's graph holds 4 neighbours per curve; --rerank needs at least 8: "
            f"rebuild it with `nfdmatch index build ... --index {index} {advice}` or more\n"
        )
