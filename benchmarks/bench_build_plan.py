"""Build planning and writing: what stored paths, recorded sources and space reservation cost.

    python benchmarks/bench_build_plan.py [--files 5000] [--curves-per-file 1] [--workdir /tmp/nfdmatch-bench-plan]

Prints seconds (best of 3 for the rebuild that changes nothing, else one run) for, on F
one-curve CSV files:
- the first build (-j 1, every file read and described, the index written);
- a rebuild that changes nothing, sources spelled as at first (planning only: walk, stat, compare);
- the same from another working directory with the absolute spelling (the same rows: before
  stored paths, every file was removed and added again here);
- a rebuild with no SOURCE (the recorded sources re-scanned);
- a rebuild after touching one file in ten (hash, copy rows, write the index).
Run it with PYTHONPATH pointing at another checkout to compare (the no-SOURCE line is then
skipped if that version does not record sources).
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, "..", "tests"))
import oracle  # noqa: E402

from nfdmatch import write_curves  # noqa: E402
from nfdmatch.index import build_index  # noqa: E402


def timed(fn, repeat=1):
    best, result = float("inf"), None
    for _ in range(repeat):
        t0 = time.perf_counter()
        result = fn()
        best = min(best, time.perf_counter() - t0)
    return best, result


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--files", type=int, default=5000)
    ap.add_argument("--curves-per-file", type=int, default=1)
    ap.add_argument("--workdir", default="/tmp/nfdmatch-bench-plan")
    args = ap.parse_args()
    shutil.rmtree(args.workdir, ignore_errors=True)
    lib = os.path.join(args.workdir, "lib")
    rng = np.random.default_rng(7)
    for i in range(args.files):
        sub = os.path.join(lib, f"d{i // 500:02d}")
        os.makedirs(sub, exist_ok=True)
        curves = [oracle.random_smooth_curve(rng, 48, 3) for _ in range(args.curves_per_file)]
        write_curves(
            os.path.join(sub, f"c{i:05d}.csv" if args.curves_per_file == 1 else f"c{i:05d}.obj"),
            curves[0] if args.curves_per_file == 1 else curves,
        )
    index = os.path.join(args.workdir, "idx.h5")
    os.chdir(args.workdir)
    import nfdmatch

    print(f"nfdmatch from {os.path.dirname(nfdmatch.__file__)}; {args.files} files x {args.curves_per_file} curves")
    rows = []
    t, r = timed(lambda: build_index(["lib"], "idx.h5", jobs=1))
    rows.append(("first build (-j 1)", t, f"{r.added} added, {r.curves} curves"))
    t, r = timed(lambda: build_index(["lib"], "idx.h5", jobs=1), 3)
    rows.append(("rebuild, nothing changed", t, f"{r.unchanged} unchanged, written={r.written}"))
    os.chdir("/")
    t, r = timed(lambda: build_index([os.path.abspath(lib)], index, jobs=1))  # once: it may rewrite
    rows.append(
        (
            "same, absolute spelling, cwd /",
            t,
            f"{r.unchanged} unchanged, {r.added} added, {r.removed} removed, written={r.written}",
        )
    )
    try:
        t, r = timed(lambda: build_index([], index, jobs=1))
        rows.append(
            ("no SOURCE (recorded ones)", t, f"{r.unchanged} unchanged, {r.removed} removed, written={r.written}")
        )
    except Exception as exc:  # an older version: no recorded sources
        rows.append(("no SOURCE (recorded ones)", float("nan"), f"{type(exc).__name__}"))
    os.chdir(args.workdir)
    if "allow_shrink" in build_index.__code__.co_varnames:
        build_index(["lib"], "idx.h5", jobs=1, allow_shrink=True)
    else:
        build_index(["lib"], "idx.h5", jobs=1)
    for _k, (root, _, names) in enumerate(os.walk(lib)):
        for j, name in enumerate(sorted(names)):
            if j % 10 == 0:
                p = os.path.join(root, name)
                st = os.stat(p)
                os.utime(p, ns=(st.st_atime_ns, st.st_mtime_ns + 1_000_000_000))
    t, r = timed(lambda: build_index(["lib"], "idx.h5", jobs=1))
    rows.append(("one file in ten touched", t, f"{r.unchanged} unchanged, written={r.written}"))
    width = max(len(name) for name, _, _ in rows)
    for name, t, what in rows:
        print(f"{name:<{width}}  {t:8.3f} s   {what}")
    shutil.rmtree(args.workdir, ignore_errors=True)


if __name__ == "__main__":
    main()
