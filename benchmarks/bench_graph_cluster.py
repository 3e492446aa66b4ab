"""The neighbour graph of ``index build --graph 10``: local ``--jobs N`` next to ``--scheduler``
on a Dask LocalCluster of N workers (issue 22 item 6), in one run.

    .venv/bin/python benchmarks/bench_graph_cluster.py [--curves 20000] [--workers 2] [--pairs 2]
                                                       [--workdir /tmp/nfdmatch-bench-graph]
                                                       [--pairs-only]   (only the builds in turn)

Curves: bench_selfjoin.py's ``generate`` (families of 50, 32 vertices, 1% noise). An index
without a graph is built once; each row copies it and adds the graph with the CLI
(``index build --index I --graph 10``: every file unchanged, every row searched), in a
subprocess (a local build forks its ``--jobs`` workers, which this process could not do
with a Dask client's threads running). Rows:

* local ``--jobs N``, no cluster running;
* ``--scheduler local:N``: the command starts its own cluster (its start-up included);
* with a LocalCluster of N workers started here and alive for both (as in
  bench_distributed.py: an idle cluster slows a local build on the same cores), a local
  build and a ``--scheduler ADDRESS`` build in turn, ``--pairs`` times; medians.

Each row gives the command's wall time and the graph's own seconds (the JSON summary's
``graph.seconds``); every graph is compared byte for byte with the first.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import time

import h5py

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)
from bench_selfjoin import MEMBERS, generate  # noqa: E402


def _build(work: str, base: str, name: str, *options) -> tuple[float, dict, bytes]:
    """(wall seconds, the JSON summary's graph, the graph's bytes) of adding a graph of 10
    to a copy of ``base`` with ``options``."""
    index = os.path.join(work, name)
    shutil.copy(base, index)
    cmd = [sys.executable, "-m", "nfdmatch", "index", "build", "--index", index, "--graph", "10", "--format", "json"]
    t0 = time.perf_counter()
    proc = subprocess.run(cmd + list(options), capture_output=True, text=True, cwd=work)
    seconds = time.perf_counter() - t0
    if proc.returncode != 0:
        sys.exit(f"failed ({proc.returncode}): {' '.join(cmd + list(options))}\n{proc.stderr}")
    with h5py.File(index, "r") as h5:
        stored = h5["graph/neighbour"][...].tobytes() + h5["graph/distance"][...].tobytes()
    return seconds, json.loads(proc.stdout)["graph"], stored


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--curves", type=int, default=20000)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--pairs", type=int, default=2)
    parser.add_argument("--workdir", default="/tmp/nfdmatch-bench-graph")
    parser.add_argument("--pairs-only", action="store_true", help="only the builds in turn with a running cluster")
    args = parser.parse_args()
    work = os.path.abspath(args.workdir)
    src = os.path.join(work, "curves")
    n = args.workers
    generate(src, args.curves // MEMBERS)
    base = os.path.join(work, "base.h5")
    if not os.path.exists(base):
        subprocess.run(
            [sys.executable, "-m", "nfdmatch", "-q", "index", "build", src, "--index", base, "--jobs", str(n)],
            check=True,
            cwd=work,
        )
    rows = []
    load = f"{os.getloadavg()[0]:.1f}"  # the machine is shared: say how busy it was
    reference = None  # the first local graph: every other is compared with it
    if not args.pairs_only:
        t, g, reference = _build(work, base, "local.h5", "--jobs", str(n))
        rows.append((f"local --jobs {n}, no cluster running", t, g["seconds"], "yes"))
        t, g, stored = _build(work, base, "started.h5", "--scheduler", f"local:{n}")
        rows.append(
            (f"--scheduler local:{n} (the command starts the cluster)", t, g["seconds"], _same(stored, reference))
        )

    from nfdmatch.distributed import connect

    with connect(f"local:{n}", timeout=60) as cluster:
        address = cluster.client.scheduler.address
        local, remote = [], []
        for _ in range(args.pairs):
            t, g, stored = _build(work, base, "local.h5", "--jobs", str(n))
            reference = stored if reference is None else reference
            local.append((t, g["seconds"], _same(stored, reference)))
            t, g, stored = _build(work, base, "remote.h5", "--scheduler", address)
            remote.append((t, g["seconds"], _same(stored, reference)))
        ratios = [r[1] / loc[1] for loc, r in zip(local, remote)]
        for label, got in (
            (f"local --jobs {n}, in turn with the cluster's (median of {args.pairs})", local),
            (
                f"--scheduler to {n} workers already running (median of {args.pairs}; the graph's "
                f"seconds / the local build's, pair by pair: {', '.join(f'{r:.2f}' for r in ratios)})",
                remote,
            ),
        ):
            same = "yes" if all(s == "yes" for _, _, s in got) else "NO"
            rows.append((label, statistics.median(w for w, _, _ in got), statistics.median(s for _, s, _ in got), same))
    print(
        f"{args.curves} curves, `index build --graph 10` added to an index without a graph "
        f"(load average before and after: {load}, {os.getloadavg()[0]:.1f})\n"
    )
    print("| run | command | the graph | graph identical |\n|---|---:|---:|---|")
    for label, wall, graph_s, same in rows:
        print(f"| {label} | {wall:.1f} s | {graph_s:.1f} s | {same} |")


def _same(a: bytes, b: bytes) -> str:
    return "yes" if a == b else "NO"


if __name__ == "__main__":
    main()
