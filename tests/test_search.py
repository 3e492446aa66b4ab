"""k-NN search with lower-bound pruning equals the exhaustive exact ranking."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from oracle import random_rigid_motion, smooth_curve_samplings, start_shift

from nfdmatch import Curve, distance
from nfdmatch.search import MemoryIndex, rank_curves, search_index


def _family_curves(rng, families, members, noise):
    """Clusters of the same curve re-sampled, re-posed and perturbed: what retrieval sees."""
    curves = []
    for f in range(families):
        versions = smooth_curve_samplings(rng, [int(rng.integers(60, 200)) for _ in range(members)],
                                          n_harmonics=int(rng.integers(2, 7)))
        for m, pts in enumerate(versions):
            pts = pts + rng.normal(scale=noise, size=pts.shape)
            curves.append(Curve(random_rigid_motion(start_shift(pts, int(rng.integers(len(pts)))), rng),
                                id=f"f{f:03d}-m{m:02d}"))
    return curves


@settings(max_examples=12, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), top=st.integers(1, 12), families=st.integers(1, 12),
       members=st.integers(1, 6), noise=st.sampled_from([0.0, 0.01, 0.1]), mirror=st.booleans(),
       chunk=st.sampled_from([7, 64, 100000]))
def test_pruned_search_equals_exhaustive_ranking(seed, top, families, members, noise, mirror, chunk):
    rng = np.random.default_rng(seed)
    curves = _family_curves(rng, families, members, noise)
    queries = _family_curves(rng, 2, 1, noise) + [curves[int(rng.integers(len(curves)))]]
    index = MemoryIndex(curves)
    pruned, stats = search_index(index, queries, top=top, mirror=mirror, chunk_rows=chunk)
    full, full_stats = search_index(index, queries, top=top, mirror=mirror, prune=False, chunk_rows=chunk)
    assert full_stats.exact == len(queries) * len(curves)
    assert stats.exact <= full_stats.exact
    for p, f in zip(pruned, full):
        assert [r["match"] for r in p] == [r["match"] for r in f]
        assert np.allclose([r["distance"] for r in p], [r["distance"] for r in f], rtol=1e-12, atol=1e-12)
        assert [r["rank"] for r in p] == list(range(1, len(p) + 1))


def test_pruning_skips_most_rows_on_clustered_data(rng):
    curves = _family_curves(rng, 40, 5, 0.01)
    index = MemoryIndex(curves)
    results, stats = search_index(index, curves[::10], top=5)
    assert stats.exact_fraction < 0.5
    for q, res in zip(curves[::10], results):
        assert res[0]["match"] == q.id and res[0]["distance"] < 1e-9


def test_matches_pairwise_distance_and_max_distance(rng):
    curves = _family_curves(rng, 6, 3, 0.02)
    query = curves[4]
    ranked = rank_curves(query, curves, top=None, max_distance=0.2)
    expected = sorted((distance(query, c).distance, c.id) for c in curves)
    expected = [(d, i) for d, i in expected if d <= 0.2]
    assert [r["match"] for r in ranked] == [i for _, i in expected]
    assert np.allclose([r["distance"] for r in ranked], [d for d, _ in expected], rtol=1e-9, atol=1e-12)


def test_ties_are_ordered_by_id():
    t = np.linspace(0, 2 * np.pi, 200, endpoint=False)
    circle = np.c_[np.cos(t), np.sin(t), 0 * t]
    curves = [Curve(circle * s, id=name) for s, name in ((1, "c"), (2, "a"), (3, "b"))]
    ranked = rank_curves(curves[0], curves, top=3)
    assert [r["match"] for r in ranked] == ["a", "b", "c"]


def test_weights_disable_pruning_but_still_rank(rng):
    curves = _family_curves(rng, 4, 2, 0.01)
    w = np.linspace(1, 0, 16)
    ranked = rank_curves(curves[0], curves, top=3, weights=w)
    assert ranked[0]["match"] == curves[0].id


def test_bad_arguments(rng):
    index = MemoryIndex(_family_curves(rng, 1, 2, 0.0))
    from nfdmatch.errors import ParameterError
    for kwargs in ({"top": 0}, {"top": None}, {"method": "fast"}):
        with pytest.raises(ParameterError):
            search_index(index, [Curve(np.eye(3))], **kwargs)
