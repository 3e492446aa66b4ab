"""The exact matcher against brute-force oracles, invariances, the paper's step, bounds."""

from __future__ import annotations

import os

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import oracle
from oracle import random_rigid_motion, random_smooth_curve, reverse, start_shift

from nfdmatch import descriptors, distance
from nfdmatch.errors import NfdError, ParameterError
from nfdmatch.matching import exact_search, kabsch_trace, lower_bound, paper_search

N, K = 128, 16


def _pair_figures(a, b, scale="a1"):
    """Exact, paper, both oracles and the bound for one pair, all on the same descriptors."""
    A, freqs = oracle.descriptors(a, N, K, scale)
    B, _ = oracle.descriptors(b, N, K, scale)
    o1 = oracle.oracle_integer(A, B, freqs, N)[0]
    o2 = oracle.oracle_fractional(A, B, freqs, N)[0]
    bounds = oracle.lower_bounds(A, B, freqs)
    exact = distance(a, b, samples=N, harmonics=K, scale=scale).distance
    paper = distance(a, b, samples=N, harmonics=K, scale=scale, method="paper").distance
    return exact, paper, o1, o2, max(bounds.values())


@pytest.mark.slow
def test_exact_matches_the_brute_force_oracles_on_100_random_pairs():
    rng = np.random.default_rng(20021)
    rows = []
    for _ in range(100):
        a = random_smooth_curve(rng, n_vertices=2000)
        b = random_smooth_curve(rng, n_vertices=2500)
        rows.append(_pair_figures(a, b))
    exact, paper, o1, o2, bound = np.array(rows).T
    within = exact <= o2 * 1.001
    assert within.mean() >= 0.99, f"only {within.sum()} of 100 within 0.1% of the 1/32-shift oracle"
    assert np.all(exact <= o1 * (1 + 1e-9) + 1e-12), "exact above the integer-shift brute force"
    assert np.all(exact >= bound * (1 - 1e-9) - 1e-12), "exact below the invariant lower bound"
    assert np.all(paper >= exact * (1 - 1e-9)), "the paper's step cannot beat the global optimum"
    # The paper's step is not optimal: on random pairs it is usually well above.
    assert np.median(paper / o1) > 1.01


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 2**32 - 1), mirror=st.booleans(), strict=st.booleans(), scale=st.sampled_from(["a1", "rms"]))
def test_exact_never_worse_than_integer_oracle_nor_below_bound(seed, mirror, strict, scale):
    rng = np.random.default_rng(seed)
    a = random_smooth_curve(rng, n_vertices=600, n_harmonics=int(rng.integers(2, 9)))
    b = random_smooth_curve(rng, n_vertices=800, n_harmonics=int(rng.integers(2, 9)))
    A, freqs = oracle.descriptors(a, N, K, scale)
    B, _ = oracle.descriptors(b, N, K, scale)
    dirs = ("forward",) if strict else ("forward", "reversed")
    o1 = oracle.oracle_integer(A, B, freqs, N, directions=dirs, mirror=mirror)[0]
    m = distance(a, b, scale=scale, mirror=mirror, direction="strict" if strict else "invariant")
    assert m.distance <= o1 * (1 + 1e-9) + 1e-12
    assert m.distance >= max(oracle.lower_bounds(A, B, freqs).values()) * (1 - 1e-9) - 1e-12
    assert m.mirrored is False or mirror
    assert m.reversed is False or not strict


@settings(max_examples=30, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    reversed_=st.booleans(),
    shift=st.integers(0, 10_000),
    vertices=st.integers(600, 1500),
)
def test_invariant_under_motion_scale_start_reversal_and_resampling(seed, reversed_, shift, vertices):
    rng = np.random.default_rng(seed)
    a, b = oracle.smooth_curve_samplings(rng, [1000, vertices])  # the same curve, sampled twice
    b = start_shift(b, shift % vertices)
    if reversed_:
        b = reverse(b)
    b = random_rigid_motion(b, rng)
    m = distance(a, b)
    assert m.distance <= 0.01
    if m.distance < 1e-3:  # for a clear match the alignment must be the true one
        assert m.reversed == reversed_ or np.allclose(a, a[::-1])


def test_alignment_maps_b_onto_a_in_input_coordinates(rng):
    a = random_smooth_curve(rng, n_vertices=1024)
    b, R, c, t = random_rigid_motion(start_shift(a, 300), rng, return_params=True)
    m = distance(a, b)
    # a different start vertex changes where the samples fall: close to, not exactly, zero
    assert m.distance < 2e-3
    assert np.allclose(m.rotation, R.T, atol=2e-3)
    assert m.scale == pytest.approx(1 / c, rel=2e-3)
    mapped = m.scale * b @ m.rotation.T + m.translation
    assert np.allclose(mapped, start_shift(a, 300), atol=5e-3 * np.abs(a).max())
    same = distance(a, random_rigid_motion(a, rng))  # same vertices, same start
    assert same.distance < 1e-8


def test_same_curve_sampled_twice_scores_about_zero(rng):
    a, b = oracle.smooth_curve_samplings(rng, [3000, 2000])
    integer_only = exact_search(descriptors(a).coefficients, descriptors(b).coefficients, N, refine=False)
    refined = distance(a, b).distance
    assert refined < 1e-3
    assert refined <= integer_only["distance"][0]


def test_identical_curve_is_exactly_zero_and_symmetric(rng):
    a = random_smooth_curve(rng)
    b = random_smooth_curve(rng)
    assert distance(a, a).distance < 1e-9
    ab, ba = distance(a, b).distance, distance(b, a).distance
    assert ab == pytest.approx(ba, rel=1e-9)


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**32 - 1))
def test_symmetric_to_1e9_relative(seed):
    rng = np.random.default_rng(seed)
    a = random_smooth_curve(rng, n_vertices=700)
    b = random_smooth_curve(rng, n_vertices=900)
    assert distance(a, b).distance == pytest.approx(distance(b, a).distance, rel=1e-9)


def test_mirror_and_direction_options(rng):
    a = random_smooth_curve(rng, n_vertices=1500)
    mirrored = a * np.array([-1.0, 1.0, 1.0])
    assert distance(a, mirrored).distance > 0.05
    m = distance(a, mirrored, mirror=True)
    assert m.distance < 1e-6 and m.mirrored and np.linalg.det(m.rotation) < 0
    backwards = reverse(a)
    assert distance(a, backwards).distance < 1e-3 and distance(a, backwards).reversed
    assert distance(a, backwards, direction="strict").distance > 0.05


def test_paper_method_reproduces_zero_for_a_rigid_copy(rng):
    a = random_smooth_curve(rng, n_vertices=1024)
    b = random_rigid_motion(a, rng)
    m = distance(a, b, method="paper", scale="a1")
    assert m.distance < 1e-6 and m.method == "paper"


def test_paper_step_is_the_bisector_rotation_per_shift(rng):
    """Independent re-implementation of section 4.2.3 on plane-aligned descriptors."""
    a, b = random_smooth_curve(rng), random_smooth_curve(rng)
    da, db = descriptors(a, scale="a1"), descriptors(b, scale="a1")
    A, B = da.coefficients, db.coefficients

    def bisector(c):
        p, q = c.real[:2], -c.imag[:2]
        h = p / np.linalg.norm(p) + q / np.linalg.norm(q)
        return np.arctan2(h[1], h[0])

    best = np.inf
    for j in range(N):
        Bj = B * np.exp(2j * np.pi * j * np.arange(1, K + 1) / N)[:, None]
        th = bisector(A[0]) - bisector(Bj[0])
        Rz = np.array([[np.cos(th), -np.sin(th), 0], [np.sin(th), np.cos(th), 0], [0, 0, 1]])
        best = min(best, np.sqrt(2 * np.sum(np.abs(A - Bj @ Rz.T) ** 2)))
    got = paper_search(A, B, N, direction="strict")["distance"][0]
    assert got == pytest.approx(best, rel=1e-12)


def test_kabsch_trace_closed_form_matches_svd(rng):
    M = rng.normal(size=(500, 3, 3)) * rng.uniform(1e-6, 1e3, size=(500, 1, 1))
    M[:50, 2] = M[:50, 1] * 0.5  # rank-deficient
    s = np.linalg.svd(M, compute_uv=False)
    d = np.sign(np.linalg.det(M))
    expect = s[:, 0] + s[:, 1] + d * s[:, 2]
    scale = s[:, 0]
    assert np.allclose(kabsch_trace(M) / scale, expect / scale, atol=1e-12)
    assert np.allclose(kabsch_trace(M, mirror=True) / scale, s.sum(axis=1) / scale, atol=1e-12)


def test_lower_bound_holds_for_batches(rng):
    A = descriptors(random_smooth_curve(rng)).coefficients
    B = np.stack([descriptors(random_smooth_curve(rng)).coefficients for _ in range(30)])
    lb = lower_bound(A, B)
    exact = exact_search(A, B, N, mirror=True)["distance"]
    assert np.all(lb <= exact * (1 + 1e-9))
    assert np.median(lb / exact) > 0.2  # a bound that prunes, not just zero


def test_batch_equals_pairwise(rng):
    A = descriptors(random_smooth_curve(rng)).coefficients
    Bs = [descriptors(random_smooth_curve(rng)).coefficients for _ in range(12)]
    batch = exact_search(A, np.stack(Bs), N)["distance"]
    single = [exact_search(A, B, N)["distance"][0] for B in Bs]
    assert np.allclose(batch, single, rtol=1e-12)


def test_degenerate_first_harmonic_is_safe():
    """(2,9)-like torus curve: |A_1| ~ 0. The rms scale stays sane, the exact method works."""
    t = np.linspace(0, 2 * np.pi, 900, endpoint=False)
    r = 2 + np.cos(9 * t / 1)
    knot = np.c_[r * np.cos(2 * t), r * np.sin(2 * t), np.sin(9 * t)]
    d = descriptors(knot)
    assert d.plane_degenerate
    assert np.all(np.isfinite(d.coefficients))
    turned = knot @ oracle.random_rotation(np.random.default_rng(1)).T
    assert distance(knot, np.roll(turned, 77, axis=0)).distance < 1e-3
    assert np.isfinite(distance(knot, turned, scale="a1").distance)


@pytest.mark.parametrize(
    "points",
    [
        oracle.collinear_back_and_forth(50),
        np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], float) * 1e12,
        np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], float) * 1e-12,
        np.array([[0, 0], [2, 0], [1, 1e-9]], float),
    ],
)
def test_degenerate_but_valid_curves_give_finite_results(points, rng):
    other = random_smooth_curve(rng, n_vertices=300)
    for method in ("exact", "paper"):
        for scale in ("rms", "a1"):
            m = distance(points, other, method=method, scale=scale)
            assert np.isfinite(m.distance) and np.all(np.isfinite(m.rotation))
            assert distance(points, points, method=method, scale=scale).distance < 1e-6


@pytest.mark.parametrize(
    "kwargs",
    [
        {"samples": 16, "harmonics": 8},
        {"harmonics": 0},
        {"samples": 2},
        {"scale": "max"},
        {"method": "best"},
        {"direction": "both"},
        {"weights": np.ones(3)},
    ],
)
def test_bad_parameters_are_nfd_errors(kwargs, rng):
    a = random_smooth_curve(rng, n_vertices=100)
    with pytest.raises(ParameterError) as info:
        distance(a, a, **kwargs)
    assert isinstance(info.value, NfdError) and isinstance(info.value, ValueError)


def test_weights_change_the_distance(rng):
    a, b = random_smooth_curve(rng), random_smooth_curve(rng)
    w = np.zeros(K)
    w[0] = 1.0
    only_first = distance(a, b, weights=w).distance
    assert only_first < distance(a, b).distance
    A, freqs = oracle.descriptors(a, N, K, "rms")
    B, _ = oracle.descriptors(b, N, K, "rms")
    o = oracle.oracle_fractional(A, B, freqs, N, weights=np.concatenate([w, w[::-1]]))[0]
    assert only_first <= o * (1 + 1e-3) + 1e-12


@pytest.mark.parametrize("ext", ["obj", "vtk", "vtp", "vtu"])
def test_same_vertices_in_every_format_give_the_same_distance(tmp_path, rng, ext):
    from nfdmatch import read_curve, write_curves

    a = random_smooth_curve(rng, n_vertices=700)
    other = random_smooth_curve(rng, n_vertices=500)
    write_curves(tmp_path / "a.csv", a)
    write_curves(tmp_path / f"a.{ext}", a)
    from_csv, from_other = read_curve(tmp_path / "a.csv"), read_curve(tmp_path / f"a.{ext}")
    assert distance(from_csv, from_other).distance <= 1e-6
    assert distance(from_csv, other).distance == pytest.approx(distance(from_other, other).distance, abs=1e-6)


# --------------------------------------------------------------------------- compiled kernels
# nfdmatch/_kernels.py (numba, optional) must give what the numpy path gives.


def _exact_with(kernels, *args, **kwargs):
    """exact_search on the given :class:`~nfdmatch.matching.Kernels` (a setting of the rule,
    or a Kernels); returns (result, kernels)."""
    from nfdmatch.matching import kernels as kernels_module

    if isinstance(kernels, str):
        kernels = kernels_module.choose(kernels)
    return exact_search(*args, kernels=kernels, **kwargs), kernels


def _kernel_rows(rng, samples, harmonics):
    """(rows, generic): 10 random 3-D curves, then degenerate rows: collinear (twice),
    |A_1| ~ 0 (torus knot, planar five-fold figure), planar ellipse, all-zero, a copy of row 0."""
    generic = [random_smooth_curve(rng, n_vertices=400, n_harmonics=int(rng.integers(2, 9))) for _ in range(10)]
    degenerate = [
        oracle.collinear_back_and_forth(50),
        oracle.collinear_back_and_forth(80, (1.0, 2.0, -0.5)),
        oracle.torus_knot(2, 9, 900),
        oracle.figure_eight_planar(1000),
        oracle.ellipse(2.0, 1.0, 300),
    ]
    rows = [descriptors(c, samples=samples, harmonics=harmonics).coefficients for c in generic + degenerate]
    rows += [np.zeros((harmonics, 3), complex), rows[0].copy()]
    return np.stack(rows), len(generic)


@pytest.mark.parametrize("samples, harmonics", [(128, 16), (64, 8), (30, 7), (127, 16), (12, 3)])
@pytest.mark.parametrize(
    "options",
    [
        {},
        {"mirror": True},
        {"direction": "strict"},
        {"refine": False},
        {"refine_below": 0.5},
        {"weights": "random"},
        {"mirror": True, "direction": "strict"},
    ],
)
def test_numba_path_equals_numpy_path(monkeypatch, rng, samples, harmonics, options):
    pytest.importorskip("numba")
    rows, generic = _kernel_rows(rng, samples, harmonics)
    if options.get("weights") == "random":
        options = {"weights": rng.uniform(0.0, 2.0, harmonics)}
    for query in (0, 3, generic, generic + 2):  # random curves, collinear, |A_1| ~ 0
        ref, ref_kernels = _exact_with("numpy", rows[query], rows, samples, **options)
        got, kernels = _exact_with("numba", rows[query], rows, samples, **options)
        assert ref_kernels.module is None and kernels.name == "numba", kernels.reason
        assert np.all(np.isfinite(got["distance"])) and np.all(np.isfinite(got["rotation"]))
        np.testing.assert_allclose(got["distance"], ref["distance"], rtol=1e-12, atol=1e-13)
        assert np.allclose(got["rotation"] @ np.swapaxes(got["rotation"], 1, 2), np.eye(3), atol=1e-12)
        assert np.array_equal(np.linalg.det(got["rotation"]) < 0, got["mirrored"])
        assert not got["mirrored"].any() or options.get("mirror")
        assert not got["reversed"].any() or options.get("direction") != "strict"
        if query < generic:
            # generic pairs have one optimum; degenerate ones (symmetric, collinear, planar
            # with mirror) have several equivalent ones, either path may pick any
            g = slice(0, generic)
            delta = (got["shift"][g] - ref["shift"][g] + samples / 2) % samples - samples / 2
            assert np.all(np.abs(delta) < 1e-7), (got["shift"][g], ref["shift"][g])
            assert np.array_equal(got["reversed"][g], ref["reversed"][g])
            assert np.array_equal(got["mirrored"][g], ref["mirrored"][g])
            np.testing.assert_allclose(got["rotation"][g], ref["rotation"][g], atol=1e-8)


@pytest.mark.parametrize("options", [{}, {"mirror": True}, {"direction": "strict"}])
def test_the_reference_path_gives_a_row_the_same_digits_whatever_rows_come_with_it(rng, options):
    """Bit for bit: a row's distance, shift and rotation on the numpy reference path do not
    depend on the batch it is computed in (a search recomputes its reported rows together)."""
    from nfdmatch.matching import NUMPY

    rows, _ = _kernel_rows(rng, 128, 16)
    B = np.concatenate([rows, rows[::-1] * np.exp(0.3j)])
    for query in (0, 4, 11):
        whole = exact_search(rows[query], B, 128, kernels=NUMPY, **options)
        for N in (1, 2, 3, 4, 7):
            for first in (0, 5):
                part = exact_search(rows[query], B[first : first + N], 128, kernels=NUMPY, **options)
                for key in ("distance", "shift", "rotation", "reversed", "mirrored"):
                    assert np.array_equal(part[key], whole[key][first : first + N]), (key, N, first)


def _aot_kernels():
    """The ahead-of-time kernels (their module), which ``make install`` builds (a missing
    build is a failure: the README's set-up promises them)."""
    from nfdmatch.matching import aot

    kernels = aot.load()
    assert kernels is not None, "the ahead-of-time kernels are not built: run make install"
    return kernels


def _aot():
    """The rule's choice for ``aot``: the ahead-of-time kernels as a Kernels."""
    from nfdmatch.matching.kernels import choose

    kernels = choose("aot")
    assert kernels.name == "aot", kernels.reason
    return kernels


@pytest.mark.parametrize("samples, harmonics", [(128, 16), (30, 7), (127, 16), (12, 3)])
@pytest.mark.parametrize(
    "options",
    [{}, {"mirror": True}, {"direction": "strict"}, {"refine": False}, {"refine_below": 0.5}, {"weights": "random"}],
)
def test_ahead_of_time_kernels_equal_the_numpy_path(rng, samples, harmonics, options):
    kernels = _aot()
    rows, generic = _kernel_rows(rng, samples, harmonics)
    if options.get("weights") == "random":
        options = {"weights": rng.uniform(0.0, 2.0, harmonics)}
    for query in (0, 3, generic):
        ref, _ = _exact_with("numpy", rows[query], rows, samples, **options)
        got, _ = _exact_with(kernels, rows[query], rows, samples, **options)
        np.testing.assert_allclose(got["distance"], ref["distance"], rtol=1e-12, atol=1e-13)
        assert np.allclose(got["rotation"] @ np.swapaxes(got["rotation"], 1, 2), np.eye(3), atol=1e-12)
        assert np.array_equal(np.linalg.det(got["rotation"]) < 0, got["mirrored"])
        g = slice(0, generic) if query < generic else slice(0, 0)
        delta = (got["shift"][g] - ref["shift"][g] + samples / 2) % samples - samples / 2
        assert np.all(np.abs(delta) < 1e-7)
        assert np.array_equal(got["reversed"][g], ref["reversed"][g])


def test_ahead_of_time_grid_bound_equals_the_numpy_path(rng):
    from nfdmatch import matching

    kernels = _aot()
    rows, _ = _kernel_rows(rng, 128, 16)
    for harmonics, grid, direction, mirror in (
        (4, 24, "invariant", False),
        (8, 48, "strict", True),
        (5, 15, "invariant", True),
    ):
        A, B = rows[1, :harmonics], rows[:, :harmonics]
        slack = np.full(len(B), 1e-3)
        for need_of in (lambda v: np.full(len(v), -np.inf), lambda v: 0.99 * v):
            need = need_of(matching.grid_maximum(A, B, grid, direction=direction, mirror=mirror))
            options = dict(direction=direction, mirror=mirror)
            ref = matching.grid_bound(A, B, grid, 9 * slack, slack, need, kernels=matching.NUMPY, **options)
            got = matching.grid_bound(A, B, grid, 9 * slack, slack, need, kernels=kernels, **options)
            np.testing.assert_allclose(got, ref, rtol=1e-12, atol=1e-12)


def test_a_stale_ahead_of_time_build_is_not_used(monkeypatch, tmp_path):
    from nfdmatch.matching import aot

    stamp = tmp_path / "stamp"
    module = aot.module_digest(aot._module_path(aot._HERE))
    stamp.write_text("0" * 64 + f"\nnogil\n{module}\n")  # built from another kernel source
    monkeypatch.setattr(aot, "_STAMP", str(stamp))
    assert aot.load() is None and aot.unused_reason() is None  # stale: make install's business
    stamp.write_text(aot.source_digest() + f"\nnogil\n{module}\n")
    assert aot.load().threads
    stamp.write_text(aot.source_digest() + f"\ngil\n{module}\n")  # built holding the GIL
    assert aot.load() is not None and not aot.load().threads
    stamp.write_text(aot.source_digest() + "\nnogil\n")  # a stamp from before the module's digest
    assert aot.load() is None and "no recorded digest" in aot.unused_reason()


def _aot_copy(tmp_path):
    """A copy of the built module and its stamp in ``tmp_path``: (module path, stamp path)."""
    import shutil

    from nfdmatch.matching import aot

    _aot_kernels()
    src = aot._module_path(aot._HERE)
    dst = tmp_path / os.path.basename(src)
    shutil.copyfile(src, dst)
    shutil.copyfile(aot._STAMP, tmp_path / "stamp")
    return dst, tmp_path / "stamp"


@pytest.mark.parametrize("damage", ["truncated to 1,000 bytes", "truncated to half", "20 bytes flipped", "replaced"])
def test_a_damaged_compiled_module_is_never_loaded(tmp_path, damage):
    """Issue 24, item 4: a truncated or flipped module crashed the process that loaded it
    (SIGBUS, SIGSEGV, SIGILL); it is now checked against the digest its build recorded."""
    from nfdmatch.matching import aot

    module, stamp = _aot_copy(tmp_path)
    kernels, reason = aot.load_checked(str(tmp_path), str(stamp))  # the intact copy loads
    assert kernels is not None and reason is None
    data = bytearray(module.read_bytes())
    if damage == "truncated to 1,000 bytes":
        data = data[:1000]
    elif damage == "truncated to half":
        data = data[: len(data) // 2]
    elif damage == "replaced":
        data = b"\x7fELF" + bytes(len(data) - 4)
    else:
        rng = np.random.default_rng(4)
        for at in rng.choice(len(data), 20, replace=False):
            data[at] ^= 0x5A
    module.unlink()  # a new file: the intact copy stays mapped in this process as it was
    module.write_bytes(bytes(data))
    kernels, reason = aot.load_checked(str(tmp_path), str(stamp))
    assert kernels is None
    assert reason == (
        f"compiled kernels not used: {module} does not match its build stamp (damaged or replaced "
        "since it was built); using the other kernels (`make install` rebuilds it)"
    )


@pytest.mark.slow  # processes of their own
def test_a_damaged_compiled_module_means_one_line_on_stderr_and_the_same_answer(tmp_path):
    """End to end, in a process of its own: a copy of the package whose compiled module is
    truncated answers as the intact one (the other kernels) and says why once."""
    import shutil
    import subprocess
    import sys

    import nfdmatch
    from nfdmatch import Curve, write_curves

    pkg = os.path.dirname(nfdmatch.__file__)
    shutil.copytree(pkg, tmp_path / "nfdmatch", ignore=shutil.ignore_patterns("__pycache__"))
    rng = np.random.default_rng(5)
    write_curves(tmp_path / "lib.obj", [Curve(random_smooth_curve(rng, 60, 4), id=f"c{i}") for i in range(30)])
    write_curves(tmp_path / "q.csv", random_smooth_curve(rng, 60, 4))
    env = dict(os.environ, PYTHONPATH=str(tmp_path), NFDMATCH_NUMBA="aot")

    def run(*args):
        return subprocess.run(
            [sys.executable, "-m", "nfdmatch", *args], cwd=tmp_path, env=env, capture_output=True, text=True
        )

    built = run("index", "build", "lib.obj", "--index", "lib.h5")
    assert built.returncode == 0, built.stderr
    intact = run("query", "q.csv", "--index", "lib.h5", "--top", "5")
    assert intact.returncode == 0 and "Warning" not in intact.stderr, intact.stderr
    from nfdmatch.matching import aot

    so = tmp_path / "nfdmatch" / "matching" / os.path.basename(aot._module_path(aot._HERE))
    so.write_bytes(so.read_bytes()[:1000])
    for args in (("query", "q.csv", "--index", "lib.h5", "--top", "5"), ("rank", "q.csv", "lib.obj")):
        got = run(*args)
        assert got.returncode == 0, (got.returncode, got.stderr)
        lines = [line for line in got.stderr.splitlines() if line.startswith("Warning:")]
        assert len(lines) == 1 and "does not match its build stamp" in lines[0], got.stderr
    assert run("query", "q.csv", "--index", "lib.h5", "--top", "5").stdout == intact.stdout


def _big_bound_call(rows: int = 200_000):
    """Arguments of a grid-bound call on ``rows`` random rows (~0.3 s on one core)."""
    from nfdmatch.matching.common import integer_shift_basis

    rng = np.random.default_rng(3)
    A = rng.standard_normal((4, 3)) + 1j * rng.standard_normal((4, 3))
    B = rng.standard_normal((rows, 4, 3)) + 1j * rng.standard_normal((rows, 4, 3))
    slack = np.full(rows, 1e-3)
    return np.conj(A), B, 2, np.array(integer_shift_basis(4, 24)), 3, False, 9 * slack, slack, np.zeros(rows)


def test_the_ahead_of_time_kernels_release_the_gil():
    """While one thread is inside a kernel, Python runs on another (the build's flag works)."""
    import threading

    kernels = _aot_kernels()
    assert kernels.threads
    args = _big_bound_call()
    finished = threading.Event()
    worker = threading.Thread(target=lambda: (kernels.grid_bound_rows(*args), finished.set()))
    turns = 0
    worker.start()
    while not finished.is_set():  # holding the GIL, the kernel would leave no turn to take
        turns += 1
    worker.join()
    assert turns > 1000


def test_the_ahead_of_time_kernels_split_over_threads_give_the_same_rows():
    kernels = _aot_kernels()
    args = _big_bound_call(5000)
    assert np.array_equal(kernels.grid_bound_rows(*args, workers=1), kernels.grid_bound_rows(*args, workers=2))
    rng = np.random.default_rng(4)
    rows, _ = _kernel_rows(rng, 128, 16)
    B = np.concatenate([rows] * 40)
    from nfdmatch.matching.kernels import folded_basis

    basis, quarter = folded_basis(16, 128)
    A = rows[2]
    call = (A, np.conj(A), np.ones(16), B, 2, basis, quarter, 128, False, 4, True, np.inf)
    one, two = kernels.exact_rows(*call, workers=1), kernels.exact_rows(*call, workers=2)
    for a, b in zip(one, two):
        assert np.array_equal(a, b)


def test_a_process_does_not_import_numba_when_the_ahead_of_time_kernels_serve():
    import subprocess
    import sys

    _aot_kernels()
    code = (
        "import sys, numpy as np\n"
        "from nfdmatch import matching\n"
        "B = np.random.default_rng(0).normal(size=(3000, 16, 3)) * (1 + 1j)\n"
        "d = matching.exact_search(B[0], B, 128)['distance']\n"
        "print(sys.modules.get('numba') is not None, d[0] < 1e-9)\n"
    )
    env = {k: v for k, v in os.environ.items() if k != "NFDMATCH_KERNELS"}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, check=True)
    assert out.stdout.split() == ["False", "True"]


def test_the_ahead_of_time_exports_forward_to_the_kernels_with_their_own_parameters():
    """What numba.pycc compiles for each export: a plain function with the kernel's parameters,
    in order, that calls the kernel with them."""
    pytest.importorskip("numba")
    import inspect

    from nfdmatch.matching import _kernels, aot

    for kernel in (_kernels._exact_rows, _kernels.grid_bound_kernel(4), _kernels.grid_bound_kernel(0)):
        forward = aot._forwarding(kernel)
        assert inspect.signature(forward).parameters.keys() == inspect.signature(kernel.py_func).parameters.keys()
    kernel = _kernels.grid_bound_kernel(4)
    args = _big_bound_call(300)
    got, want = np.full(300, np.nan), np.full(300, np.nan)
    aot._forwarding(kernel)(*args, got, 0, 300)
    kernel(*args, want, 0, 300)
    assert np.array_equal(got, want) and np.all(np.isfinite(got))


def _posed_rows(rng, rows, copies: int, noise: float):
    """``copies`` rotated, start-shifted, noisy copies of each of ``rows`` (N, K, 3): near
    matches, whose weaker candidates the kernels skip refining."""
    N, K, _ = rows.shape
    out = []
    for _ in range(copies):
        q, _r = np.linalg.qr(rng.standard_normal((3, 3)))
        phase = np.exp(2j * np.pi * np.outer(rng.uniform(0, 1, N), np.arange(1, K + 1)))
        wobble = noise * (rng.standard_normal(rows.shape) + 1j * rng.standard_normal(rows.shape))
        out.append((rows @ q.T) * phase[:, :, None] + wobble * np.abs(rows).mean())
    return np.concatenate(out)


@settings(max_examples=12, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    seed=st.integers(0, 2**32 - 1),
    samples=st.sampled_from([128, 64, 50, 7]),
    direction=st.sampled_from([1, 2]),
    mirror=st.booleans(),
    weighted=st.booleans(),
    limited=st.booleans(),
)
def test_skipping_hopeless_refinements_changes_no_bit(seed, samples, direction, mirror, weighted, limited):
    """The compiled kernels refine only the candidates that can still overtake a row's best
    integer local maximum (``prune``); every output is the same bits as refining all."""
    pytest.importorskip("numba")
    from nfdmatch.matching import _kernels
    from nfdmatch.matching.kernels import folded_basis

    rng = np.random.default_rng(seed)
    harmonics = min(16, (samples - 1) // 2)
    rows, _ = _kernel_rows(rng, samples, harmonics)
    rows = np.ascontiguousarray(np.concatenate([rows, _posed_rows(rng, rows, 3, rng.choice([0.0, 1e-3, 0.05]))]))
    w = rng.uniform(0.2, 2.0, harmonics) if weighted else np.ones(harmonics)
    basis, quarter = folded_basis(harmonics, samples)
    kinds = [_kernels, _aot_kernels()] if samples == 128 else [_kernels]
    for a in (0, 3, 10):
        A = np.ascontiguousarray(rows[a])
        Aw = np.ascontiguousarray(np.conj(A) * w[:, None])
        limit = 0.3 if limited else np.inf
        call = (A, Aw, w, rows, direction, basis, quarter, samples, mirror, min(3, direction * samples), True, limit)
        for kernels in kinds:
            every = kernels.exact_rows(*call, prune=False)
            skipping = kernels.exact_rows(*call, prune=True)
            for x, y in zip(every, skipping):
                assert np.array_equal(x, y, equal_nan=True)


def test_numba_kernel_split_over_threads_gives_the_same_bits(rng):
    pytest.importorskip("numba")
    from nfdmatch.matching import _kernels
    from nfdmatch.matching.kernels import folded_basis

    rows, _ = _kernel_rows(rng, 128, 16)
    rows = np.ascontiguousarray(np.concatenate([rows] * 4))
    A = np.ascontiguousarray(rows[1])
    basis, quarter = folded_basis(16, 128)
    for limit in (np.inf, 0.3):
        one = _kernels.exact_rows(A, np.conj(A), np.ones(16), rows, 2, basis, quarter, 128, False, 3, True, limit)
        three = _kernels.exact_rows(
            A, np.conj(A), np.ones(16), rows, 2, basis, quarter, 128, False, 3, True, limit, workers=3
        )
        assert all(np.array_equal(a, b) for a, b in zip(one, three))


def test_numba_cos_third_arccos_is_within_a_few_ulps(rng):
    numba = pytest.importorskip("numba")
    from nfdmatch.matching._kernels import cos_third_acos

    @numba.njit
    def evaluate(r, out):
        for i in range(r.shape[0]):
            out[i] = cos_third_acos(r[i])

    r = np.concatenate(
        [
            rng.uniform(-1, 1, 200_000),
            -1 + rng.uniform(0, 1e-5, 20_000) ** 2,
            1 - rng.uniform(0, 1e-5, 20_000) ** 2,
            0.5 + rng.uniform(-1e-6, 1e-6, 20_000),
            -0.5 + rng.uniform(-1e-6, 1e-6, 20_000),
            [-1.0, 1.0, 0.0, 0.5, -0.5, -0.0],
        ]
    )
    out = np.empty_like(r)
    evaluate(r, out)
    expect = np.cos(np.arccos(r) / 3)
    assert np.max(np.abs(out - expect) / np.spacing(expect)) <= 4
    evaluate(np.array([np.nan]), out[:1])
    assert np.isnan(out[0])


def test_the_rule_falls_back_to_numpy_when_numba_cannot_be_imported(monkeypatch, rng):
    import sys

    from nfdmatch import matching
    from nfdmatch.matching.kernels import choose

    rows, _ = _kernel_rows(rng, 128, 16)
    ref, _ = _exact_with("numpy", rows[0], rows, 128)
    monkeypatch.setitem(sys.modules, "numba", None)  # import numba -> ImportError
    monkeypatch.delitem(sys.modules, "nfdmatch.matching._kernels", raising=False)
    monkeypatch.delattr(matching, "_kernels", raising=False)
    kernels = choose("numba")
    assert kernels.name == "numpy" and "numba unavailable (ModuleNotFoundError" in kernels.reason
    got, _ = _exact_with(kernels, rows[0], rows, 128)
    assert np.array_equal(got["distance"], ref["distance"]) and np.array_equal(got["shift"], ref["shift"])


def test_the_rule_takes_aot_then_numba_then_numpy(monkeypatch):
    """auto: the ahead-of-time build when it is there for this source, else numba; the choice
    is made once per process and kept (no switch later), or made explicitly."""
    from nfdmatch.matching import aot, kernels

    assert kernels.choose("auto").name == "aot"
    assert kernels.choose("numpy").name == "numpy"
    monkeypatch.setattr(aot, "load", lambda: None)
    got = kernels.choose("auto")
    assert got.name == "numba" and "no ahead-of-time build" in got.reason
    assert kernels.choose("aot").name == "numpy"
    with pytest.raises(matching_errors().ParameterError, match="NFDMATCH_KERNELS"):
        kernels.choose("fast")
    monkeypatch.setattr(kernels, "_chosen", None)
    monkeypatch.setenv("NFDMATCH_KERNELS", "numpy")
    first = kernels.current()
    monkeypatch.setenv("NFDMATCH_KERNELS", "numba")
    assert kernels.current() is first and first.name == "numpy"  # decided once
    assert kernels.use_kernels("numba").name == "numba" and kernels.current().name == "numba"


def matching_errors():
    from nfdmatch import errors

    return errors


def test_importing_and_a_small_distance_do_not_import_numba():
    import subprocess
    import sys

    code = (
        "import sys, numpy as np\n"
        "import nfdmatch, nfdmatch.cli, nfdmatch.search\n"
        "from nfdmatch import distance\n"
        "t = np.linspace(0, 2 * np.pi, 200, endpoint=False)\n"
        "a = np.c_[np.cos(t), np.sin(2 * t), np.sin(3 * t)]\n"
        "distance(a, a[::-1] * 2)\n"
        "print(sys.modules.get('numba') is not None)\n"
    )
    env = {k: v for k, v in os.environ.items() if k != "NFDMATCH_KERNELS"}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, check=True)
    assert out.stdout.strip() == "False"


@pytest.mark.slow
def test_numba_without_a_cache_directory_falls_back_to_numpy(rng):
    """numba raises when no cache directory is usable (read-only install, no writable home):
    exact_search must not fail, it stays on numpy."""
    pytest.importorskip("numba")
    import subprocess
    import sys

    code = (
        "import numba.core.caching as caching, numpy as np, sys\n"
        "caching.CacheImpl._locator_classes = []\n"
        "from nfdmatch import matching\n"
        "B = np.random.default_rng(0).normal(size=(5, 16, 3)) * (1 + 1j)\n"
        "d = matching.exact_search(B[0], B, 128)['distance']\n"
        "print(matching.kernels.current().name, d[0] < 1e-9)\n"
        "print(matching.kernels.current().reason)\n"
    )
    env = dict(os.environ, NFDMATCH_KERNELS="numba")  # (the ahead-of-time kernels would serve)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env)
    assert out.returncode == 0, out.stderr
    first, reason = out.stdout.splitlines()
    assert first.split() == ["numpy", "True"] and "numba unavailable (RuntimeError" in reason, out.stdout


def test_gram_entries_are_the_upper_triangle_of_x_transpose_x(rng):
    from nfdmatch.matching.common import gram_entries

    X = rng.standard_normal((20, 3, 3))
    entries = np.array(gram_entries(*X.reshape(20, 9).T))  # (6, 20)
    G = np.einsum("nji,njk->nik", X, X)
    rows, cols = [0, 1, 2, 0, 0, 1], [0, 1, 2, 1, 2, 2]
    np.testing.assert_allclose(entries.T, G[:, rows, cols], rtol=1e-13, atol=1e-13)
    assert gram_entries(*X[0].ravel().tolist()) == tuple(entries[:, 0])  # floats: the compiled kernels' case
