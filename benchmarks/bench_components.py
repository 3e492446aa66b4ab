"""The connected components of `groups` (nfdmatch.search.groups._components) against the
Python union-find it replaced (issue 37, item 3).

    python benchmarks/bench_components.py [--rows 1000000]

Graphs of --rows rows: as many random pairs as rows, a tenth as many, and one chain
through every row in a shuffled order (the worst case of hooking to the smallest label).
Prints each one's seconds for both and whether they give the same labels.
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))

from nfdmatch.search.groups import _components  # noqa: E402


def union_find(N: int, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The loop `groups` ran before: path compression, the smaller root kept."""
    parent = np.arange(N, dtype=np.int64)

    def find(x):
        root = x
        while parent[root] != root:
            root = parent[root]
        while parent[x] != root:
            parent[x], x = root, parent[x]
        return root

    for x, y in zip(a.tolist(), b.tolist()):
        rx, ry = find(x), find(y)
        if rx != ry:
            parent[max(rx, ry)] = min(rx, ry)
    return np.array([find(x) for x in range(N)], dtype=np.int64)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rows", type=int, default=1_000_000)
    N = ap.parse_args().rows
    rng = np.random.default_rng(0)
    chain = rng.permutation(N)
    graphs = {
        f"{N} rows, {N} random pairs": (rng.integers(0, N, N), rng.integers(0, N, N)),
        f"{N} rows, {N // 10} random pairs": (rng.integers(0, N, N // 10), rng.integers(0, N, N // 10)),
        f"{N} rows in one shuffled chain": (chain[:-1], chain[1:]),
    }
    for name, (a, b) in graphs.items():
        t = time.perf_counter()
        loop = union_find(N, a, b)
        t_loop = time.perf_counter() - t
        t = time.perf_counter()
        arrays = _components(N, a, b)
        t_arrays = time.perf_counter() - t
        same = bool((loop == arrays).all())
        print(f"{name}: Python union-find {t_loop:.2f} s, whole arrays {t_arrays:.2f} s, same labels: {same}")


if __name__ == "__main__":
    main()
