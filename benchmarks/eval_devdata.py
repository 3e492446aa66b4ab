"""Retrieval on the development data (../shared/data): knotess control -> smooth top-1,
Kimia-99 same-class counts at ranks 1..10, for both methods and both scale modes.

    python benchmarks/eval_devdata.py [--data ../shared/data]

Prints tables; run from the repository root. Development data is not shipped.
"""

from __future__ import annotations

import argparse
import csv
import os
import sys
import time

import numpy as np

from nfdmatch import descriptors, read_curves
from nfdmatch.matching import exact_search, paper_search

HERE = os.path.dirname(os.path.abspath(__file__))
DEFAULT_DATA = os.path.normpath(os.path.join(HERE, "..", "..", "shared", "data"))


def load_folder(folder):
    names = sorted(f for f in os.listdir(folder) if f.endswith(".csv") and not f.startswith("_"))
    return names, [read_curves(os.path.join(folder, f))[0] for f in names]


def distance_matrix(queries, rows, method, scale, samples=128, harmonics=16):
    dq = [descriptors(c, samples=samples, harmonics=harmonics, scale=scale).coefficients for c in queries]
    dr = np.stack([descriptors(c, samples=samples, harmonics=harmonics, scale=scale).coefficients for c in rows])
    search = exact_search if method == "exact" else paper_search
    return np.array([search(q, dr, samples)["distance"] for q in dq])


def knots(data):
    names_c, control = load_folder(os.path.join(data, "knotess_control"))
    names_s, smooth = load_folder(os.path.join(data, "knotess_smooth"))
    assert names_c == names_s
    print(f"\n## knotess: each of {len(control)} control polygons against {len(smooth)} smooth curves, top-1")
    print(f"{'method':8} {'scale':6} {'top-1':>8} {'seconds':>8}  misses (query -> found, distance)")
    for method in ("exact", "paper"):
        for scale in ("rms", "a1"):
            t0 = time.perf_counter()
            D = distance_matrix(control, smooth, method, scale)
            dt = time.perf_counter() - t0
            order = np.lexsort((np.tile(np.arange(len(smooth)), (len(control), 1)), D), axis=1)
            best = order[:, 0]
            hits = best == np.arange(len(control))
            misses = ", ".join(
                f"{names_c[i][:-4]} -> {names_s[best[i]][:-4]} ({D[i, best[i]]:.3g}; true {D[i, i]:.3g})"
                for i in np.flatnonzero(~hits)
            )
            print(f"{method:8} {scale:6} {hits.sum():>4}/{len(control)} {dt:8.2f}  {misses}")


def kimia(data):
    folder = os.path.join(data, "kimia99")
    with open(os.path.join(folder, "_labels.csv")) as fh:
        labels = {row["csv"]: row["class_name"] for row in csv.DictReader(fh)}
    names, curves = load_folder(folder)
    cls = np.array([labels[n] for n in names])
    print(
        f"\n## Kimia-99: same-class matches at ranks 1..10 over {len(curves)} queries (max 99 each), "
        "query itself excluded"
    )
    print(f"{'method':8} {'scale':6} " + " ".join(f"{r:>3}" for r in range(1, 11)) + "   sum")
    for method in ("exact", "paper"):
        for scale in ("rms", "a1"):
            D = distance_matrix(curves, curves, method, scale)
            np.fill_diagonal(D, np.inf)
            order = np.argsort(D, axis=1, kind="stable")[:, :10]
            same = cls[order] == cls[:, None]
            counts = same.sum(axis=0)
            print(f"{method:8} {scale:6} " + " ".join(f"{c:>3}" for c in counts) + f"  {counts.sum():>4}")


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=DEFAULT_DATA)
    args = ap.parse_args()
    if not os.path.isdir(args.data):
        sys.exit(f"development data not found at {args.data}")
    knots(args.data)
    kimia(args.data)


if __name__ == "__main__":
    main()
