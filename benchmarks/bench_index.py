"""Index build throughput, query latency, batch queries, all-vs-all, dev-data retrieval.

    python benchmarks/bench_index.py [--curves 100000] [--workdir /tmp/nfdmatch-bench] [--skip-devdata]

Measured side by side in one run on this machine, printed as tables:
- build throughput on N generated curves in multi-curve OBJ and VTP files (CLI, new process);
- single query end to end (`nfdmatch query q.csv --index big.h5 --top 10`, a new process)
  on 10k and N curves, next to the bare `nfdmatch --help` start-up;
- batch queries on N curves (one process, index loaded once): ms per query and the
  fraction of rows that needed an exact distance;
- all-vs-all top-40 on Kimia-99 and on 1,400 generated curves;
- retrieval on the development data through the CLI (knotess control -> smooth top-1,
  Kimia-99 same-class hits at ranks 1..10).

Generated curves come in families (a random smooth curve, then members re-sampled with
60-200 vertices, re-posed, start-shifted, some reversed, with noise), as in real collections
where a query has near neighbours; one family member of each family is also kept apart as
a query.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import shutil
import statistics
import subprocess
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, "..", "tests"))
import oracle  # noqa: E402

from nfdmatch import Curve, write_curves  # noqa: E402

DATA = os.path.normpath(os.path.join(HERE, "..", "..", "shared", "data"))
NFDMATCH = [sys.executable, "-m", "nfdmatch"]


def family_members(rng, members, noise=0.01):
    counts = [int(rng.integers(60, 201)) for _ in range(members)]
    out = []
    for pts in oracle.smooth_curve_samplings(rng, counts, n_harmonics=int(rng.integers(3, 8))):
        pts = pts + rng.normal(scale=noise, size=pts.shape)
        pts = oracle.start_shift(pts, int(rng.integers(len(pts))))
        if rng.random() < 0.5:
            pts = pts[::-1]
        out.append(oracle.random_rigid_motion(pts, rng))
    return out


def generate(folder, n_curves, per_file=5000, members=10, seed=1):
    """n_curves curves in multi-curve files, half OBJ, half VTP; returns query curves."""
    rng = np.random.default_rng(seed)
    os.makedirs(folder, exist_ok=True)
    queries, buffer, files = [], [], 0
    while files * per_file < n_curves:
        fam = family_members(rng, members + 1)
        queries.append(fam.pop())
        buffer.extend(fam)
        if len(buffer) >= per_file:
            ext = "obj" if files % 2 == 0 else "vtp"
            write_curves(os.path.join(folder, f"part-{files:03d}.{ext}"), buffer[:per_file])
            buffer = buffer[per_file:]
            files += 1
    return queries


def run(cmd, **kw):
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True, **kw)
    return time.perf_counter() - t0, proc


def median_time(cmd, repeat=5):
    times = []
    for _ in range(repeat):
        dt, proc = run(cmd)
        if proc.returncode != 0:
            raise SystemExit(f"{' '.join(cmd)} failed: {proc.stderr}")
        times.append(dt)
    return statistics.median(times)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--curves", type=int, default=100_000)
    ap.add_argument("--workdir", default="/tmp/nfdmatch-bench")
    ap.add_argument("--skip-devdata", action="store_true")
    args = ap.parse_args()
    work = args.workdir
    shutil.rmtree(work, ignore_errors=True)
    os.makedirs(work)
    rows = []

    # ---- build throughput
    big_dir, small_dir = os.path.join(work, "big"), os.path.join(work, "small")
    t0 = time.perf_counter()
    queries = generate(big_dir, args.curves)
    generate(small_dir, 10_000, per_file=2500, seed=2)
    print(f"generated {args.curves} + 10000 curves in {time.perf_counter() - t0:.1f} s", file=sys.stderr)
    big, small = os.path.join(work, "big.h5"), os.path.join(work, "small.h5")
    for label, folder, index, glob in (
        ("OBJ+VTP", big_dir, big, None),
        ("VTP only", big_dir, big + ".vtp.h5", "*.vtp"),
        ("OBJ only", big_dir, big + ".obj.h5", "*.obj"),
        ("10k", small_dir, small, None),
    ):
        cmd = NFDMATCH + ["index", "build", folder, "--index", index, "--format", "json"]
        if glob:
            cmd += ["--glob", glob]
        dt, proc = run(cmd)
        report = json.loads(proc.stdout)
        rows.append(
            (f"build {label}: {report['curves']} curves", f"{dt:.2f} s", f"{report['curves'] / dt:,.0f} curves/s")
        )
        dt, proc = run(cmd)
        rows.append(
            (
                f"rebuild {label}, nothing changed",
                f"{dt:.2f} s",
                f"unchanged {json.loads(proc.stdout)['unchanged']} files",
            )
        )

    # ---- single query, new process
    qfile = os.path.join(work, "q.csv")
    write_curves(qfile, queries[0])
    help_t = median_time(NFDMATCH + ["--help"])
    rows.append(("`nfdmatch --help` start-up", f"{help_t * 1e3:.0f} ms", ""))
    for label, index in (("10k", small), (f"{args.curves // 1000}k", big)):
        t = median_time(NFDMATCH + ["query", qfile, "--index", index, "--top", "10"])
        rows.append(
            (
                f"single query end to end, {label} curves",
                f"{t * 1e3:.0f} ms",
                f"{(t - help_t) * 1e3:.0f} ms above start-up",
            )
        )

    # ---- batch queries in one process
    from nfdmatch.index import open_index
    from nfdmatch.search import search_index

    qcurves = [Curve(q, id=f"q{i}") for i, q in enumerate(queries[:500])]
    with open_index(big) as idx:
        for label in ("first run in the process, incl. loading the numba kernel", "again, warm"):
            t0 = time.perf_counter()
            results, stats = search_index(idx, qcurves, top=10)
            dt = time.perf_counter() - t0
            rows.append(
                (
                    f"batch: {len(qcurves)} queries on {stats.rows} curves, top 10, {label}",
                    f"{dt / len(qcurves) * 1e3:.2f} ms/query",
                    f"exact distances for {stats.exact_fraction:.3%} of rows",
                )
            )

    # ---- all-vs-all
    from nfdmatch.search import MemoryIndex

    rng = np.random.default_rng(5)
    gen = [Curve(p, id=f"g{i:04d}") for i, p in enumerate(x for _ in range(70) for x in family_members(rng, 20))]
    for label, curves in (("1,400 generated curves", gen),) + (
        (("Kimia-99", _kimia()),) if os.path.isdir(DATA) else ()
    ):
        t0 = time.perf_counter()
        memory = MemoryIndex(curves)
        _, stats = search_index(memory, curves, top=40)
        dt = time.perf_counter() - t0
        rows.append((f"all-vs-all top-40, {label}", f"{dt:.2f} s", f"exact for {stats.exact_fraction:.1%} of pairs"))

    # ---- dev data through the CLI
    if os.path.isdir(DATA) and not args.skip_devdata:
        rows.extend(_devdata(work))

    width = max(len(r[0]) for r in rows)
    print(f"| {'measure'.ljust(width)} | figure | note |\n|{'-' * (width + 2)}|---:|---|")
    for r in rows:
        print(f"| {r[0].ljust(width)} | {r[1]} | {r[2]} |")


def _kimia():
    from nfdmatch import read_curve

    folder = os.path.join(DATA, "kimia99")
    return [read_curve(os.path.join(folder, f)) for f in sorted(os.listdir(folder)) if not f.startswith("_")]


def _devdata(work):
    rows = []
    index = os.path.join(work, "knots.h5")
    run(NFDMATCH + ["index", "build", os.path.join(DATA, "knotess_smooth"), "--index", index])
    _, proc = run(
        NFDMATCH + ["query", os.path.join(DATA, "knotess_control"), "--index", index, "--top", "1", "--format", "csv"]
    )
    hits = [
        os.path.basename(r["query"]) == os.path.basename(r["match"]) for r in csv.DictReader(proc.stdout.splitlines())
    ]
    rows.append(("knotess control -> smooth, top-1 (CLI)", f"{sum(hits)}/{len(hits)}", ""))
    kimia = os.path.join(DATA, "kimia99")
    index = os.path.join(work, "kimia.h5")
    run(NFDMATCH + ["index", "build", kimia, "--index", index])
    _, proc = run(NFDMATCH + ["query", kimia, "--index", index, "--top", "11", "--format", "csv"])
    counts = np.zeros(10, int)
    by_query = {}
    for r in csv.DictReader(proc.stdout.splitlines()):
        by_query.setdefault(r["query"], []).append(r["match"])
    cls = lambda p: os.path.basename(p).rsplit("-", 1)[0]  # noqa: E731
    for q, matches in by_query.items():
        matches = [m for m in matches if m != q][:10]
        counts[: len(matches)] += [cls(m) == cls(q) for m in matches]
    rows.append(("Kimia-99 same-class hits at ranks 1..10 (CLI)", " ".join(map(str, counts)), f"sum {counts.sum()}"))
    return rows


if __name__ == "__main__":
    main()
