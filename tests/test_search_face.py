"""One search face for curves in memory and index files (issue 37, item 2): the same
``search`` with every option named, faiss's ``(distances, rows)`` arrays, ``ids[row]``,
``MemoryIndex.save`` and ``build_index`` of curves in memory, pickling an open index, and
``k`` as the one name of the number of matches (``top=`` deprecated but working)."""

from __future__ import annotations

import inspect
import os
import pickle
import warnings

import numpy as np
import pytest
from conftest import run_cli
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import nfdmatch
from nfdmatch import Curve, MemoryIndex, build_index, open_index
from nfdmatch.errors import IndexFormatError, ParameterError
from nfdmatch.search import rank_curves, search_index


def loops(n: int, seed: int = 0, points: int = 64) -> list[np.ndarray]:
    """``n`` closed 3-D curves of random low harmonics (each one its own shape)."""
    rng = np.random.default_rng(seed)
    t = np.linspace(0.0, 2 * np.pi, points, endpoint=False)
    h = np.arange(1, 5)
    a = rng.normal(size=(n, 3, 4)) / h**1.5
    b = rng.normal(size=(n, 3, 4)) / h**1.5
    a[:, 0, 0] += 2.0  # a dominant first harmonic in the plane: no degenerate curve
    b[:, 1, 0] += 2.0
    phase = np.outer(h, t)  # (4, points)
    xyz = np.einsum("ncj,jp->npc", a, np.cos(phase)) + np.einsum("ncj,jp->npc", b, np.sin(phase))
    return list(xyz)


@pytest.fixture(scope="module")
def small(tmp_path_factory):
    curves = loops(60, seed=1)
    memory = MemoryIndex(curves, ids=[f"c{i}" for i in range(60)])
    path = str(tmp_path_factory.mktemp("face") / "small.h5")
    memory.save(path)
    return curves, memory, path


def test_memory_and_file_share_one_search_with_named_options():
    from nfdmatch.index import Index

    from nfdmatch.search.knn import search

    # one function: an index file's search and that of curves in memory take the same
    # named options (a mesh query ranks an index file's objects: tests/test_objects.py)
    assert MemoryIndex.search is search and Index.search is search
    params = inspect.signature(search).parameters
    assert not any(p.kind == p.VAR_KEYWORD for p in params.values())
    for name in ("k", "max_distance", "exclude_self", "elastic", "elastic_depth", "arrays", "method", "prune"):
        assert name in params


def test_a_mesh_query_of_curves_in_memory_is_refused_by_name(small, tmp_path):
    import trimesh

    _, memory, _ = small
    mesh = tmp_path / "ball.stl"
    trimesh.creation.icosphere(subdivisions=1).export(mesh)
    for query in (trimesh.creation.icosphere(subdivisions=1), str(mesh), [str(mesh)]):
        with pytest.raises(ParameterError, match="mesh query ranks the objects of an index file"):
            memory.search(query, k=1)


def test_arrays_are_faiss_shaped_and_padded(small):
    curves, memory, _ = small
    distances, rows = memory.search(curves[:3], k=4, arrays=True)
    assert distances.shape == rows.shape == (3, 4)
    assert distances.dtype == np.float64 and rows.dtype == np.int64
    assert rows[:, 0].tolist() == [0, 1, 2]  # each curve is its own nearest
    assert (np.diff(distances, axis=1) >= 0).all()
    # fewer matches than k: padded as faiss pads
    near, near_rows = memory.search(curves[:3], k=4, max_distance=1e-9, arrays=True)
    assert near_rows[:, 1:].tolist() == [[-1] * 3] * 3 and np.isinf(near[:, 1:]).all()
    # the records say the same as the arrays
    records = memory.search(curves[:3], k=4)
    assert [[m.row for m in found] for found in records] == rows.tolist()
    assert [[m.id for m in found] for found in records] == [memory.ids[r] for r in rows]


def test_arrays_of_the_elastic_stage_hold_the_fused_distance_they_are_sorted_by(small):
    curves, memory, _ = small
    distances, rows = memory.search(curves[:3], k=6, elastic=True, arrays=True)
    records = memory.search(curves[:3], k=6, elastic=True)
    assert [[m.row for m in found] for found in records] == rows.tolist()
    assert distances.tolist() == [[m.fused for m in found] for found in records]
    assert (np.diff(distances, axis=1) >= 0).all()


def test_exclude_self_by_id_and_the_records_carry_a_pose(small):
    curves, memory, _ = small
    queries = [Curve(curves[i], id=f"c{i}") for i in range(3)]
    _, rows = memory.search(queries, k=2, exclude_self=True, arrays=True)
    assert all(i not in rows[i] for i in range(3))
    (found,) = memory.search(queries[0], k=1)
    assert found[0].pose is not None and found[0].pose.distance == pytest.approx(0, abs=1e-9)


def test_ids_name_rows_as_a_sequence(small):
    _, memory, path = small
    with open_index(path) as index:
        for ids in (memory.ids, index.ids):
            assert len(ids) == 60
            assert ids[-1] == ids[59] and ids[1:3] == [ids[1], ids[2]]
            assert ids[np.array([2, 0])] == [ids[2], ids[0]]
            with pytest.raises(IndexError):
                ids[60]
        assert memory.ids[0] == "c0"
        assert index.ids(0, 2) == index.ids[0:2]  # the older spelling still works
        assert list(index.ids)[5] == index.ids[5]


def test_a_saved_memory_index_answers_as_in_memory_and_through_the_cli(small):
    curves, memory, path = small
    d_mem, r_mem = memory.search(curves[:5], k=3, arrays=True)
    with open_index(path) as index:
        assert len(index) == 60
        d_file, r_file = index.search(curves[:5], k=3, arrays=True)
        assert (r_file == r_mem).all()
        np.testing.assert_allclose(d_file, d_mem, atol=1e-6)  # stored in single precision
        names = index.ids[r_file[4]]
        query = index.locate(names[0])  # its curve in the file the index was built from
    code, out, err = run_cli("query", query, "--index", path, "--top", "3", "--format", "csv")
    assert code == 0, err
    rows = [line.split(",") for line in out.strip().splitlines()[1:]]
    assert [r[2] for r in rows] == names


def test_build_index_takes_curves_in_memory(tmp_path):
    curves = loops(12, seed=3)
    path = tmp_path / "mem.h5"
    report = build_index(curves, path)
    assert report.curves == 12 and os.path.exists(tmp_path / "mem.curves.obj")
    again = build_index(curves, path)  # the same curves: nothing recomputed
    assert (again.unchanged, again.added, again.updated) == (1, 0, 0)
    with pytest.raises(ParameterError):
        build_index([curves[0], str(path)], tmp_path / "mixed.h5")
    with pytest.raises(ParameterError):
        build_index([str(tmp_path / "mem.curves.obj")], tmp_path / "x.h5", curves_file=tmp_path / "c.obj")


def test_an_open_index_pickles_by_path_and_refuses_a_changed_file(tmp_path):
    path = tmp_path / "p.h5"
    build_index(loops(8, seed=4), path)
    with open_index(path) as index:
        data = pickle.dumps(index)
        expected = index.search(loops(1, seed=5), k=3, arrays=True)
    with pickle.loads(data) as copy:
        got = copy.search(loops(1, seed=5), k=3, arrays=True)
        assert (got[1] == expected[1]).all()
    build_index(loops(9, seed=4), path, allow_shrink=True)
    with pytest.raises(IndexFormatError, match="changed since it was pickled"):
        pickle.loads(data)


def test_top_is_a_deprecated_alias_of_k(small):
    curves, memory, _ = small
    q = [Curve(curves[0], id="q")]
    with pytest.warns(DeprecationWarning, match="use k="):
        old, _ = search_index(memory, q, top=2)
    new, _ = search_index(memory, q, k=2)
    assert old == new
    with pytest.warns(DeprecationWarning):
        assert rank_curves(q[0], memory.curves, top=2) == rank_curves(q[0], memory.curves, k=2)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        search_index(memory, q, k=2)


def test_the_package_ships_its_annotations():
    assert os.path.exists(os.path.join(os.path.dirname(nfdmatch.__file__), "py.typed"))


# -- the goal: 10,000 curves in memory and in a file give the same rows


@pytest.fixture(scope="module")
def large(tmp_path_factory):
    curves = loops(10_000, seed=7)
    memory = MemoryIndex(curves)
    path = str(tmp_path_factory.mktemp("large") / "large.h5")
    memory.save(path)
    index = open_index(path)
    yield curves, memory, index
    index.close()


def _same_rows_but_ties(r_a, d_a, r_b, d_b, tie=1e-6):
    """Rows equal wherever the distance is not within ``tie`` of a neighbour's (single
    against double precision may swap near-equal distances, never others)."""
    np.testing.assert_allclose(d_a, d_b, atol=tie / 2)
    for ra, da, rb in zip(r_a, d_a, r_b):
        gaps = np.diff(da)
        alone = np.ones(len(da), bool)
        alone[1:] &= gaps > tie
        alone[:-1] &= gaps > tie
        assert (ra[alone] == rb[alone]).all()


@pytest.mark.slow
@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    seeds=st.lists(st.integers(0, 9_999), min_size=1, max_size=6),
    noise=st.floats(0.0, 0.3),
    k=st.integers(1, 12),
)
def test_the_array_search_of_10000_curves_in_memory_returns_the_file_index_rows(large, seeds, noise, k):
    curves, memory, index = large
    rng = np.random.default_rng(sum(seeds))
    queries = [curves[s] + noise * rng.normal(size=curves[s].shape) * 0.05 for s in seeds]
    d_mem, r_mem = memory.search(queries, k=k, arrays=True)
    d_file, r_file = index.search(queries, k=k, arrays=True)
    _same_rows_but_ties(r_mem, d_mem, r_file, d_file)
