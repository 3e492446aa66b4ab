"""Build and a query batch on a Dask LocalCluster next to the local --jobs path, in one run.

    python benchmarks/bench_distributed.py [--curves 100000] [--queries 1000] [--workdir /tmp/nfdmatch-bench-dask]

On one machine the point is the overhead of going through Dask (scheduler, task
serialization, descriptor blocks sent back over the loopback, per-worker index reads), not
a speed-up: each row compares N Dask worker processes with the local path on N processes
(build: ``jobs=N``; query: ``threads=N``). Printed as a table: seconds, curves/s or
ms/query, and the ratio cluster / local (1.00 = no overhead).

Curves as in bench_index.py: families of a random smooth curve (members re-sampled with
60-200 vertices, re-posed, noisy) in multi-curve files of 5,000 curves, half OBJ, half VTP;
one member per family is kept apart as a query. Workers are warmed (modules imported, numba
kernels loaded) before timing; the cluster start-up is reported on its own row.
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)
from bench_index import generate  # noqa: E402

from nfdmatch import Curve  # noqa: E402


def _warm():
    """Run on each worker (and here): what a first task would otherwise pay."""
    from nfdmatch.matching import compile_kernels

    import nfdmatch.index  # noqa: F401
    try:
        import pyvista  # noqa: F401  (the VTP reader)
    except Exception:
        pass
    compile_kernels()


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--curves", type=int, default=100_000)
    ap.add_argument("--queries", type=int, default=1000)
    ap.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--workdir", default="/tmp/nfdmatch-bench-dask")
    args = ap.parse_args()

    from nfdmatch.distributed import connect
    from nfdmatch.index import build_index, open_index
    from nfdmatch.search import search_index

    work = args.workdir
    shutil.rmtree(work, ignore_errors=True)
    os.makedirs(work)
    src = os.path.join(work, "curves")
    t0 = time.perf_counter()
    queries = generate(src, args.curves)
    while len(queries) < args.queries:
        queries += queries
    qcurves = [Curve(q, id=f"q{i}") for i, q in enumerate(queries[:args.queries])]
    print(f"generated {args.curves} curves in {time.perf_counter() - t0:.1f} s", file=sys.stderr)
    _warm()
    rows = []
    local_build, local_query = {}, {}
    for n in args.workers:
        index = os.path.join(work, f"local-{n}.h5")
        t0 = time.perf_counter()
        report = build_index([src], index, jobs=n)
        local_build[n] = time.perf_counter() - t0
        rows.append((f"build {report.curves} curves, local --jobs {n}", f"{local_build[n]:.2f} s",
                     f"{report.curves / local_build[n]:,.0f} curves/s", ""))
    reference = os.path.join(work, f"local-{args.workers[0]}.h5")
    with open_index(reference) as idx:
        search_index(idx, qcurves[:20], top=10)          # page cache and kernels warm
        for n in args.workers:
            t0 = time.perf_counter()
            local_results, stats = search_index(idx, qcurves, top=10, threads=n)
            local_query[n] = time.perf_counter() - t0
            rows.append((f"query {len(qcurves)} x {stats.rows} curves, top 10, local {n} threads",
                         f"{local_query[n]:.2f} s", f"{local_query[n] / len(qcurves) * 1e3:.2f} ms/query", ""))
    for n in args.workers:
        t0 = time.perf_counter()
        with connect(f"local:{n}", timeout=60) as cluster:
            cluster.client.run(_warm)
            rows.append((f"start a LocalCluster of {n} workers and warm them", f"{time.perf_counter() - t0:.2f} s",
                         "", ""))
            index = os.path.join(work, f"dask-{n}.h5")
            t0 = time.perf_counter()
            report = cluster.build_index([src], index)
            dt = time.perf_counter() - t0
            rows.append((f"build {report.curves} curves, Dask {n} workers", f"{dt:.2f} s",
                         f"{report.curves / dt:,.0f} curves/s", f"{dt / local_build[n]:.2f}"))
            cluster.search_index(reference, qcurves[:20], top=10)     # each worker opens the index once
            t0 = time.perf_counter()
            results, stats = cluster.search_index(reference, qcurves, top=10)
            dt = time.perf_counter() - t0
            same = all([r["match"] for r in a] == [r["match"] for r in b] for a, b in zip(results, local_results))
            rows.append((f"query {len(qcurves)} x {stats.rows} curves, top 10, Dask {n} workers",
                         f"{dt:.2f} s", f"{dt / len(qcurves) * 1e3:.2f} ms/query",
                         f"{dt / local_query[n]:.2f}" + ("" if same else " (RESULTS DIFFER)")))
    width = max(len(r[0]) for r in rows)
    print(f"| {'measure'.ljust(width)} | time | rate | Dask / local |\n|{'-' * (width + 2)}|---:|---:|---:|")
    for r in rows:
        print(f"| {r[0].ljust(width)} | {r[1]} | {r[2]} | {r[3]} |")


if __name__ == "__main__":
    main()
