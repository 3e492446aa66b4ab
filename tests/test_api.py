"""The library's face: build and query an index from Python, as the README shows."""

from __future__ import annotations

import dataclasses
import os
import re
import shutil
import subprocess
import sys

import numpy as np
import pytest
from conftest import ROOT

import nfdmatch
from nfdmatch import Curve, build_index, open_index, read_curves
from nfdmatch.search import search_index


def _readme_block(marker: str) -> str:
    with open(os.path.join(ROOT, "README.md"), encoding="utf-8") as f:
        blocks = re.findall(r"```python\n(.*?)```", f.read(), re.S)
    (block,) = [b for b in blocks if marker in b]
    return block


@pytest.fixture
def library(tmp_path):
    shutil.copytree(os.path.join(ROOT, "sample_curves"), tmp_path / "sample_curves")
    return tmp_path


def test_the_readme_python_example_runs_as_written(library):
    code = _readme_block("build_index")
    out = subprocess.run(
        [sys.executable, "-c", code], cwd=library, capture_output=True, text=True, env=dict(os.environ)
    )
    assert out.returncode == 0, out.stderr
    lines = out.stdout.splitlines()
    assert lines[0] == "24 curves, 0 files failed"
    assert lines[1].startswith("24 curves: ['sample_curves/library/")
    assert [line.split()[:2] for line in lines[2:5]] == [
        ["1", "sample_curves/library/trefoil.csv"],
        ["2", "sample_curves/library/trefoil-coarse.vtk"],
        ["3", "sample_curves/library/trefoil-noisy.csv"],
    ]


def test_index_search_is_the_exact_search_with_every_kind_of_query(library, monkeypatch):
    monkeypatch.chdir(library)
    report = build_index(["sample_curves/library"], "lib.h5")
    assert report.curves == 24
    query_file = "sample_curves/queries/trefoil-posed.obj"
    (query,) = read_curves(query_file)
    with open_index("lib.h5") as index:
        assert len(index) == 24 and index.ids() == index.ids(0, 24)
        (expected,), _ = search_index(index, [query], k=4, prune=False)
        for given in (query_file, query, query.points, [query.points]):
            (got,) = index.search(given, k=4)
            assert [(m.id, m.rank) for m in got] == [(m.id, m.rank) for m in expected]
            np.testing.assert_allclose([m.distance for m in got], [m.distance for m in expected], rtol=1e-12)
        within = index.search(query, k=None, max_distance=expected[2].distance)[0]
        assert [m.id for m in within] == [m.id for m in expected[:3]]
        # k None without max_distance: the default k, as scikit-learn's n_neighbors=None
        assert len(index.search(query, k=None)[0]) == len(index.search(query)[0]) == 10
        with pytest.raises(nfdmatch.NfdError):
            index.search(query, k=0)


def test_a_match_pose_maps_the_stored_curve_onto_the_query(library, monkeypatch):
    monkeypatch.chdir(library)
    build_index(["sample_curves/library"], "lib.h5")
    (query,) = read_curves("sample_curves/queries/trefoil-posed.obj")
    with open_index("lib.h5") as index:
        ((best, *_),) = index.search(query, k=3)
        ((unposed, *_),) = index.search(query, k=3, pose=False)
    assert best.id == "sample_curves/library/trefoil.csv" and unposed.pose is None
    (stored,) = read_curves(best.id)
    moved = best.pose.apply(stored.points)
    # every vertex of the posed query lies near the moved curve (both trace the same knot)
    gaps = np.min(np.linalg.norm(query.points[:, None] - moved[None], axis=2), axis=1)
    assert gaps.max() < 0.05 * np.ptp(query.points, axis=0).max()
    assert best.pose.distance == pytest.approx(best.distance, rel=1e-9)


def test_exclude_self_drops_a_query_stored_in_the_index_however_its_path_is_spelled(library, monkeypatch):
    monkeypatch.chdir(library)
    build_index(["sample_curves/library"], "lib.h5")
    with open_index("lib.h5") as index:
        ids = index.ids()
        plain = index.search(ids, k=2, pose=False)
        without = index.search([os.path.abspath(i) for i in ids], k=2, exclude_self=True, pose=False)
    for i, mine, other in zip(ids, plain, without):
        assert mine[0].id == i and mine[0].distance < 1e-6  # a stored curve finds itself (complex64)
        assert i not in [m.id for m in other] and [m.rank for m in other] == [1, 2]
        assert other[0].id == mine[1].id


def test_importing_nfdmatch_does_not_load_the_index_side():
    code = "import sys, nfdmatch; print('h5py' in sys.modules); nfdmatch.open_index; print('h5py' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.split() == ["False", "True"]


def test_curves_in_memory_take_exclude_self_too(rng):
    from nfdmatch.search import rank_curves

    t = np.linspace(0, 2 * np.pi, 80, endpoint=False)[:, None]
    curves = [Curve(np.hstack([np.cos(t), np.sin(k * t), 0.1 * k * np.sin(2 * t)]), id=f"c{k}") for k in range(1, 6)]
    ranked = rank_curves(curves[2], curves, k=2, exclude_self=True)
    assert [m.rank for m in ranked] == [1, 2] and "c3" not in [m.id for m in ranked]


def test_match_parameters_are_the_keywords_distance_rank_curves_and_distance_matrix_take():
    from nfdmatch.matching import MatchParameters
    from nfdmatch.search import distance_matrix, rank_curves

    p = MatchParameters()
    assert (p.samples, p.harmonics, p.scale) == (128, 16, "rms")
    assert (p.method, p.direction, p.mirror, p.weights) == ("exact", "invariant", False, None)
    p = MatchParameters(samples=64, harmonics=6, scale="a1", method="paper", direction="strict", mirror=True)
    assert p.descriptor == {"samples": 64, "harmonics": 6, "scale": "a1"}
    assert p.matching == {"method": "paper", "direction": "strict", "mirror": True, "weights": None}
    with pytest.raises(dataclasses.FrozenInstanceError):
        p.samples = 32
    t = np.linspace(0, 2 * np.pi, 60, endpoint=False)[:, None]
    curves = [Curve(np.hstack([np.cos(t), np.sin(k * t), 0.2 * np.sin(3 * t)]), id=f"c{k}") for k in (1, 2, 3)]
    given = dict(samples=64, harmonics=6, scale="a1", direction="strict", mirror=True)
    d = nfdmatch.distance(curves[0], curves[1], **given).distance
    assert distance_matrix(curves, **given)[0, 1] == pytest.approx(d, rel=1e-9)
    assert rank_curves(curves[0], curves[1:2], **given)[0].distance == pytest.approx(d, rel=1e-9)
    for call in (
        lambda: nfdmatch.distance(curves[0], curves[1], sample=64),
        lambda: rank_curves(curves[0], curves, sample=64),
        lambda: distance_matrix(curves, sample=64),
    ):
        with pytest.raises(TypeError, match="sample"):
            call()
