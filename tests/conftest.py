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


#: test modules that are end-to-end runs as a whole (subprocesses, signals, worker pools,
#: fuzzing, pictures, Dask clusters): marked ``slow``, so that ``make test-fast`` (``-m "not
#: slow"``) runs the unit tests in under a minute; ``make test`` runs everything
SLOW_MODULES = {
    "test_fuzz_formats",
    "test_pool",
    "test_distributed",
    "test_render",
    "test_cli_pictures",
    "test_pictures",
    "test_walkthrough",
    "test_read_limits",
    "test_rerank",
    "test_integrity",
    "test_extract",
    "test_vtk_reader",
}
#: single slow tests in otherwise fast modules (each several seconds: real processes, big inputs)
SLOW_TESTS = {
    "test_readers_and_a_second_build_while_a_build_runs",
    "test_kill_9_during_a_build_leaves_the_previous_index",
    "test_exact_matches_the_brute_force_oracles_on_100_random_pairs",
    "test_search_work_does_not_grow_with_the_index_for_a_near_duplicate",
    "test_progress_bars_only_on_a_terminal_and_not_with_quiet",
    "test_the_readme_makefile_runs_and_a_second_run_rebuilds_nothing",
    "test_numba_without_a_cache_directory_falls_back_to_numpy",
    "test_pruned_equals_exhaustive_on_an_index_file_with_cells",
}


def pytest_collection_modifyitems(config, items):
    for item in items:
        module = item.module.__name__.rsplit(".", 1)[-1] if item.module is not None else ""
        if module in SLOW_MODULES or item.originalname in SLOW_TESTS:
            item.add_marker(pytest.mark.slow)


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
