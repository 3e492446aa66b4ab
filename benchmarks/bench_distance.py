"""Per-pair time and accuracy: exact vs the paper's step vs brute-force oracles.

    python benchmarks/bench_distance.py [--pairs 200] [--batch 2000]

All methods run on the same random smooth 3-D pairs (2,000-2,500 vertices, n = 128,
K = 16, scale a1, direction-invariant), in the same process, so the ratios hold on a
noisy machine. Oracles (tests/oracle.py): (1) every integer shift x Kabsch (SVD) with
the distance computed directly per shift; (1v) the same fully vectorized (batched SVD
over all shifts, no Python loop), a stronger baseline; (2) a 1/32-sample shift grid.

The exact rows are the numpy path (NFDMATCH_KERNELS=numpy); the compiled kernels
(nfdmatch/_kernels.py, numba) are timed separately when numba is installed: one call per
pair and batched, on one thread and with the rows split over threads (what a call from the
main thread does), with their agreement with the numpy path.
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np

os.environ["NFDMATCH_KERNELS"] = "numpy"  # the exact rows below: numpy path; numba: see numba_rows()
sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "tests"))
import oracle  # noqa: E402

from nfdmatch.matching import exact_search, paper_search  # noqa: E402

N, K = 128, 16


def brute_force_vectorized(A, B, freqs, m):
    """Integer shifts x Kabsch for both directions in one batched SVD (no Python loop)."""
    best = np.inf
    for Bd in (B, np.conj(B)):
        M = oracle.correlation_matrices(A, Bd, freqs, m, np.arange(m))
        R, _ = oracle.kabsch(M)
        ph = np.exp(2j * np.pi * np.outer(np.arange(m), freqs) / m)
        Bs = Bd[None] * ph[:, :, None]
        d = np.sqrt(np.sum(np.abs(A[None] - np.einsum("sij,skj->ski", R, Bs)) ** 2, axis=(1, 2)))
        best = min(best, d.min())
    return best


def timed(fn, repeat=1):
    t0 = time.perf_counter()
    for _ in range(repeat):
        out = fn()
    return out, (time.perf_counter() - t0) / repeat


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--pairs", type=int, default=200)
    ap.add_argument("--batch", type=int, default=2000, help="rows for the batched per-pair timing")
    args = ap.parse_args()
    rng = np.random.default_rng(7)
    pairs = []
    for _ in range(args.pairs):
        a = oracle.random_smooth_curve(rng, n_vertices=2000)
        b = oracle.random_smooth_curve(rng, n_vertices=2500)
        A, freqs = oracle.descriptors(a, N, K, "a1")
        B, _ = oracle.descriptors(b, N, K, "a1")
        pairs.append((A, B))
    freqs = np.concatenate([np.arange(1, K + 1), -np.arange(K, 0, -1)])
    half = lambda X: X[:K]  # noqa: E731  (stored half band: frequencies 1..K)

    t = {k: 0.0 for k in ("exact", "exact_int", "paper", "o1", "o1v", "o2")}
    res = {k: [] for k in t}
    for A, B in pairs:
        r, dt = timed(lambda: exact_search(half(A), half(B)[None], N)["distance"][0])
        t["exact"] += dt
        res["exact"].append(r)
        r, dt = timed(lambda: exact_search(half(A), half(B)[None], N, refine=False)["distance"][0])
        t["exact_int"] += dt
        res["exact_int"].append(r)
        # the paper's step needs plane-aligned descriptors: rotate both (distance is rotation-invariant otherwise)
        r, dt = timed(lambda: paper_search(_aligned(half(A)), _aligned(half(B))[None], N)["distance"][0])
        t["paper"] += dt
        res["paper"].append(r)
        r, dt = timed(lambda: oracle.oracle_integer(A, B, freqs, N)[0])
        t["o1"] += dt
        res["o1"].append(r)
        r, dt = timed(lambda: brute_force_vectorized(A, B, freqs, N))
        t["o1v"] += dt
        res["o1v"].append(r)
        r, dt = timed(lambda: oracle.oracle_fractional(A, B, freqs, N)[0])
        t["o2"] += dt
        res["o2"].append(r)
    res = {k: np.array(v) for k, v in res.items()}
    per = {k: v / len(pairs) * 1e3 for k, v in t.items()}

    # batched: one query against many rows, as a search does
    rows = np.stack([half(B) for _, B in pairs] * (args.batch // len(pairs) + 1))[: args.batch]
    q = half(pairs[0][0])
    _, dt_batch = timed(lambda: exact_search(q, rows, N))
    _, dt_batch_int = timed(lambda: exact_search(q, rows, N, refine=False))
    _, dt_batch_paper = timed(lambda: paper_search(_aligned(q), np.stack([_aligned(r) for r in rows]), N))

    print(f"# {len(pairs)} random smooth pairs, n={N}, K={K}, scale a1, direction-invariant\n")
    print("| method | ms per pair (one call per pair) | vs oracle (1) | vs vectorized brute force (1v) |")
    print("|---|---:|---:|---:|")
    for key, name in [
        ("exact", "exact (shift x SO(3), sub-sample)"),
        ("exact_int", "exact, integer shifts only"),
        ("paper", "paper's step"),
        ("o1", "oracle (1): all shifts x Kabsch"),
        ("o1v", "(1v) vectorized brute force"),
        ("o2", "oracle (2): 1/32-shift grid"),
    ]:
        print(f"| {name} | {per[key]:.3f} | {per['o1'] / per[key]:.1f}x faster | {per['o1v'] / per[key]:.1f}x faster |")
    print(
        f"\nbatched, one query vs {args.batch} rows: exact {dt_batch / args.batch * 1e6:.1f} us/pair "
        f"(integer shifts only {dt_batch_int / args.batch * 1e6:.1f} us/pair), paper {dt_batch_paper / args.batch * 1e6:.1f} us/pair; "
        f"oracle (1) is {per['o1'] * 1e3 / (dt_batch / args.batch * 1e6):.0f}x slower per pair than batched exact\n"
    )

    def stats(ratio):
        return (
            f"median {np.median(ratio):.6f}, p99 {np.quantile(ratio, 0.99):.6f}, max {ratio.max():.6f}, "
            f"> 1.001: {np.mean(ratio > 1.001) * 100:.1f}%, > 1.01: {np.mean(ratio > 1.01) * 100:.1f}%"
        )

    print("accuracy (distance ratios; < 1 means below the oracle):")
    print(f"- exact / oracle (2):          {stats(res['exact'] / res['o2'])}")
    print(f"- exact / oracle (1):          {stats(res['exact'] / res['o1'])}")
    print(f"- exact integer / oracle (1):  {stats(res['exact_int'] / res['o1'])}")
    print(f"- paper / oracle (1):          {stats(res['paper'] / res['o1'])}")
    print(f"- paper / oracle (2):          {stats(res['paper'] / res['o2'])}")
    within = np.mean(res["exact"] <= res["o2"] * 1.001) * 100
    print(
        f"\nexact within 0.1% of oracle (2) on {within:.1f}% of pairs; "
        f"above oracle (1) beyond 1e-9 relative on {np.sum(res['exact'] > res['o1'] * (1 + 1e-9))} pairs"
    )
    numba_rows(pairs, rows, q, per, res["exact"])


def numba_rows(pairs, rows, q, per, exact_numpy, repeat=5):
    """The same exact search through the numba kernels, next to the numpy figures above."""
    from nfdmatch import matching

    import importlib.util

    if importlib.util.find_spec("numba") is None:
        print("\nnumba kernels: numba is not installed (pip install numba)")
        return
    fresh = "numba" not in sys.modules
    t0 = time.perf_counter()
    chosen = matching.use_kernels("numba")
    load = time.perf_counter() - t0
    if chosen.name != "numba":
        print(f"\nnumba kernels unavailable: {chosen.reason}")
        return
    import numba

    half = lambda X: X[:K]  # noqa: E731
    got, dt = [], 0.0
    for A, B in pairs:
        r, t = timed(lambda: exact_search(half(A), half(B)[None], N)["distance"][0])
        got.append(r)
        dt += t
    per_numba = dt / len(pairs) * 1e3
    workers = min(os.cpu_count() or 1, matching.kernels._MAX_THREADS)
    saved = matching.kernels._THREAD_ROWS

    def run(mode, threshold=saved, **kw):
        matching.use_kernels({"0": "numpy", "1": "numba"}[mode])
        matching.kernels._THREAD_ROWS = threshold
        dt = timed(lambda: exact_search(q, rows, N, **kw))[1]
        if mode == "0":
            time.sleep(0.3)  # OpenBLAS worker threads spin for a while after a GEMM
        return dt

    # numpy and numba interleaved, medians of `repeat` runs each (the machine may be shared)
    labels = {"numpy": ("0", saved), "numba, 1 thread": ("1", 10**12), f"numba, {workers} threads": ("1", saved)}
    figures = {label: ([], []) for label in labels}
    for mode, threshold in labels.values():
        run(mode, threshold)  # warm
    for _ in range(repeat):
        for label, (mode, threshold) in labels.items():
            figures[label][0].append(run(mode, threshold))
            figures[label][1].append(run(mode, threshold, refine=False))
    figures = {label: (float(np.median(a)), float(np.median(b))) for label, (a, b) in figures.items()}
    matching.kernels._THREAD_ROWS = saved
    matching.use_kernels("numba")
    batch = exact_search(q, rows, N)
    matching.use_kernels("numpy")
    reference = exact_search(q, rows, N)
    got = np.array(got)
    agree = max(
        np.max(np.abs(got - exact_numpy) / exact_numpy),
        np.max(np.abs(batch["distance"] - reference["distance"]) / reference["distance"]),
    )
    same_shift = np.mean(np.abs((batch["shift"] - reference["shift"] + N / 2) % N - N / 2) < 1e-7) * 100
    n = len(rows)
    t_np, t_np_int = figures.pop("numpy")
    print(
        f"\nnumba kernels (numba {numba.__version__}; {'import numba + ' if fresh else ''}load of the kernels "
        f"{load:.2f} s in this process); batched: medians of {repeat} interleaved runs"
    )
    print("| exact search | numpy | numba | speed-up |")
    print("|---|---:|---:|---:|")
    print(
        f"| one call per pair, ms per pair | {per['exact']:.3f} | {per_numba:.3f} | {per['exact'] / per_numba:.1f}x |"
    )
    for label, (t_all, t_int) in figures.items():
        print(
            f"| batched ({n} rows), {label}, us per pair | {t_np / n * 1e6:.1f} | {t_all / n * 1e6:.1f} | "
            f"{t_np / t_all:.1f}x |"
        )
        print(
            f"| batched, integer shifts only, {label}, us per pair | {t_np_int / n * 1e6:.1f} | "
            f"{t_int / n * 1e6:.1f} | {t_np_int / t_int:.1f}x |"
        )
    print(
        f"\nnumba vs numpy: max relative distance difference {agree:.1e}; same shift on {same_shift:.1f}% of "
        f"the batched rows"
    )


def _aligned(C):
    """Rotate a half band (K, 3) so its limit-plane normal is +z (as descriptors() does)."""
    from nfdmatch.descriptors import _plane_rotations

    R, _ = _plane_rotations(C[:1], np.array([np.linalg.norm(C)]))
    return C @ R[0].T


if __name__ == "__main__":
    main()
