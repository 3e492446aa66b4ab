"""`pairs` and `groups` on a Dask cluster (--scheduler): split by ranges of search cells,
the same rows as a local run. A LocalCluster of 2 worker processes, once for the module."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("distributed")

from conftest import run_cli as run  # noqa: E402
from oracle import random_rigid_motion, smooth_curve_samplings, start_shift  # noqa: E402

from nfdmatch import Curve, write_curves  # noqa: E402
from nfdmatch.distributed import connect  # noqa: E402
from nfdmatch.index import build_index, open_index  # noqa: E402
from nfdmatch.search.engine import Cascade  # noqa: E402
from nfdmatch.search.join import pairs_within  # noqa: E402

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def index(tmp_path_factory):
    """300 curves in families of 6, over several search cells."""
    rng = np.random.default_rng(22)
    folder = tmp_path_factory.mktemp("families")
    curves = []
    for f in range(50):
        versions = smooth_curve_samplings(rng, [int(rng.integers(60, 120)) for _ in range(6)], n_harmonics=4)
        for m, pts in enumerate(versions):
            pts = start_shift(pts + rng.normal(scale=0.01, size=pts.shape), int(rng.integers(len(pts))))
            curves.append(Curve(random_rigid_motion(pts, rng), id=f"f{f:02d}-{m}"))
    for i, part in enumerate(np.array_split(np.arange(len(curves)), 4)):
        write_curves(folder / f"part-{i}.obj", [curves[j] for j in part])
    path = folder / "i.h5"
    build_index([folder], path, jobs=1)
    with open_index(path) as idx:
        assert idx.search_table().n_cells > 1
    return path


def test_cluster_pairs_equal_the_local_pairs_for_every_split(client, index):
    with open_index(index) as idx, connect(client) as cluster:
        cascade = Cascade(idx.samples)
        local = pairs_within(idx.search_table(), idx.coefficients_at, 0.3, cascade)
        assert len(local[0]) > 100
        for parts in (1, 3, 50):
            got = cluster.pairs_within(idx, 0.3, cascade, parts=parts)
            np.testing.assert_array_equal(got[0], local[0])
            np.testing.assert_array_equal(got[1], local[1])
            np.testing.assert_allclose(got[2], local[2], rtol=1e-12, atol=0)
            assert got[3].exact == local[3].exact
        rows = np.arange(0, idx.n_curves, 7)
        restricted = pairs_within(idx.search_table(), idx.coefficients_at, 0.3, cascade, rows=rows)
        got = cluster.pairs_within(idx, 0.3, cascade, rows=rows, parts=4)
        np.testing.assert_array_equal(got[0], restricted[0])
        np.testing.assert_array_equal(got[1], restricted[1])


def test_cli_pairs_and_groups_on_the_scheduler_print_what_a_local_run_prints(client, index):
    address = client.scheduler.address
    for command in (["pairs"], ["groups", "--min-size", "2"]):
        local = run(*command, "--index", index, "--max-distance", "0.3", "--format", "csv")
        remote = run(*command, "--index", index, "--max-distance", "0.3", "--format", "csv", "--scheduler", address)
        assert local[0] == remote[0] == 0
        assert remote[1] == local[1] and len(local[1].splitlines()) > 10
        assert remote[2] == ""
