"""Shared test fixtures; curve generators re-exported from ``oracle``.

Tests can use ``from oracle import random_smooth_curve, oracle_integer, ...``
(or ``from conftest import ...``): tests/ is on sys.path. ``run_cli`` runs the CLI the
way every CLI test does; ``ROOT`` is the repository folder.
"""

from __future__ import annotations

import os
import sys
import zlib

import numpy as np
import pytest
from hypothesis import settings

_HERE = os.path.dirname(os.path.abspath(__file__))
#: the repository's root folder (sample_curves/, README.md, ...)
ROOT = os.path.dirname(_HERE)
if _HERE not in sys.path:
    sys.path.insert(0, _HERE)

from oracle import (  # noqa: E402,F401  (re-exports)
    collinear_back_and_forth,
    ellipse,
    figure_eight_planar,
    lemniscate_planar,
    lissajous,
    random_rigid_motion,
    random_rotation,
    random_smooth_curve,
    resample_polyline,
    reverse,
    start_shift,
    torus_knot,
)


# CI must be reproducible: hypothesis draws the same examples on every run unless
# NFDMATCH_HYPOTHESIS=explore asks for fresh ones.
settings.register_profile("reproducible", derandomize=True, print_blob=True)
settings.register_profile("explore", derandomize=False, print_blob=True)
settings.load_profile("explore" if os.environ.get("NFDMATCH_HYPOTHESIS") == "explore" else "reproducible")


@pytest.fixture
def rng(request):
    """``np.random.default_rng`` seeded deterministically from the test id."""
    seed = zlib.crc32(request.node.nodeid.encode("utf-8"))
    return np.random.default_rng(seed)


def run_cli(*args, env=None, input=None):
    """Run ``nfdmatch ARGS...`` through click's CliRunner (arguments as str): returns
    ``(exit_code, stdout, stderr)``, separately, as a user's shell would see them."""
    from click.testing import CliRunner

    from nfdmatch.cli import main

    result = CliRunner(env=env).invoke(main, [str(a) for a in args], catch_exceptions=False, input=input)
    return result.exit_code, result.stdout, result.stderr


@pytest.fixture
def reads(monkeypatch):
    """Paths read by in-process (jobs=1) builds: the index's reader of curve files, counted."""
    from nfdmatch.index import pool

    seen = []
    real = pool.read_curves

    def counting(path, format=None):
        seen.append(str(path))
        return real(path, format=format)

    real_fast = pool._fast_points

    def counting_fast(path, data, input_format):
        # the bulk path of small CSV files parses the bytes read for the hash: a read too
        # (when it declines, read_curves reads the file and is counted there)
        arr = real_fast(path, data, input_format)
        if arr is not None:
            seen.append(str(path))
        return arr

    monkeypatch.setattr(pool, "read_curves", counting)
    monkeypatch.setattr(pool, "_fast_points", counting_fast)
    return seen


@pytest.fixture(scope="module")
def client():
    """A Dask LocalCluster of 2 worker processes (1 thread each) and its client, once per
    test module that asks for it (the distributed tests)."""
    from distributed import Client, LocalCluster

    with (
        LocalCluster(
            n_workers=2, threads_per_worker=1, processes=True, dashboard_address=":0", silence_logs=50
        ) as cluster,
        Client(cluster, set_as_default=False) as c,
    ):
        c.wait_for_workers(2, timeout=60)
        yield c


@pytest.fixture
def cluster(client):
    """nfdmatch's cluster on the module's client, its 2 workers up (a test may have killed
    them: their nannies restart them)."""
    from nfdmatch.distributed import connect

    client.wait_for_workers(2, timeout=60)
    with connect(client) as c:
        yield c
