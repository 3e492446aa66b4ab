"""The whole collection against itself (issue 22): the neighbour graph, pairs and groups,
and all-against-all, each next to the issue's starting commit where it exists.

    .venv/bin/python benchmarks/bench_selfjoin.py                 # 100,000 family curves
    .venv/bin/python benchmarks/bench_selfjoin.py --curves 20000  # a quicker run
    .venv/bin/python benchmarks/bench_selfjoin.py --skip-base     # this tree only
    .venv/bin/python benchmarks/bench_selfjoin.py --elastic       # --graph 10 against --graph 10 --elastic

Prints a markdown table:

* ``index build --graph 10`` on an index of N generated family curves (bench_search.py's
  ``generate_families``: families of 50, 32 vertices, 1% noise, re-posed, rescaled,
  start-shifted, half reversed), wall time and peak memory, for this tree and for the
  starting commit (a ``git worktree`` of it, run with this environment); whether the two
  graphs are identical (neighbours; distances to 1e-9), and a sample of rows checked
  against the exhaustive search (``query --exhaustive``'s library call);
* ``pairs`` and ``groups`` at ``--max-distance`` on the same index (new commands: no
  figure for the starting commit), with the number of pairs and the agreement of the
  groups with the generated families (curves whose group is exactly their family, and the
  adjusted Rand index);
* all-against-all at ~1,400 curves (28 families of 50): ``query DIR --top 40`` of every
  indexed curve (the same command in both trees: the batch path is not routed through
  the join yet), ``matrix`` of the same curves to a CSV file (and whether the two trees'
  files are identical), and the self-join's 40 nearest others (``nearest_others``) in
  this tree. ``--curves 0`` gives these rows alone.

``--elastic`` gives instead the issue "Similarity that bends"'s rows: ``index build --graph K``
and ``index build --graph K --elastic`` (docs/elastic.md) added in turn to copies of the same
built index of N family curves, this tree only: wall time, the graph's seconds (the build's
JSON summary) and its share, peak memory, and the elastic build's ratio to the exact one.

Timings are wall-clock on whatever else the machine runs: the two trees run one after the
other in the same invocation.
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
sys.path.insert(0, HERE)

from bench_search import _sample, _smooth_coefficients, _write_obj  # noqa: E402

BASE = "1a903b8"
MEMBERS = 50


def generate(folder: str, families: int, files: int = 100, vertices: int = 32, seed: int = 11) -> dict:
    """bench_search.generate_families' curves (the same seed gives the same files), and each
    curve's family: ``{(file name, index in file): family}``."""
    rng = np.random.default_rng(seed)
    a, b = _smooth_coefficients(rng, families, rng.integers(3, 7, families))
    owner = rng.permutation(np.repeat(np.arange(families), MEMBERS))
    os.makedirs(folder, exist_ok=True)
    labels = {}
    for i, part in enumerate(np.array_split(owner, files)):
        name = f"part-{i:03d}.obj"
        path = os.path.join(folder, name)
        if not os.path.exists(path):
            _write_obj(path, _sample(a[part], b[part], vertices, np.random.default_rng([seed, i]), 0.01))
        for j, f in enumerate(part):
            labels[(name, j)] = int(f)
    return labels


def timed(cmd, env) -> tuple[float, float, subprocess.CompletedProcess]:
    """(seconds, peak MB, process) of a command run under /usr/bin/time, in the working
    folder (not a source tree: ``python -m`` puts the working folder first on sys.path)."""
    t0 = time.perf_counter()
    proc = subprocess.run(["/usr/bin/time", "-f", "MAXRSS %M"] + cmd, capture_output=True, text=True, env=env)
    seconds = time.perf_counter() - t0
    if proc.returncode != 0:
        sys.exit(f"failed ({proc.returncode}): {' '.join(cmd)}\n{proc.stderr}")
    rss = [line for line in proc.stderr.splitlines() if line.startswith("MAXRSS ")]
    return seconds, int(rss[-1].split()[1]) / 1024 if rss else float("nan"), proc


def tree_env(tree: str) -> dict:
    env = dict(os.environ)
    env["PYTHONPATH"] = tree  # ahead of the editable install of this tree
    return env


def base_tree(work: str) -> str:
    """A worktree of the starting commit, with this tree's compiled kernels when their
    source is the same (else it compiles its own with numba on first use)."""
    path = os.path.join(work, "base")
    if not os.path.exists(path):
        subprocess.run(["git", "worktree", "add", "--detach", path, BASE], cwd=ROOT, check=True, capture_output=True)
    same = subprocess.run(
        ["git", "diff", "--quiet", BASE, "--", "nfdmatch/matching/_kernels.py", "nfdmatch/matching/aot.py"], cwd=ROOT
    )
    if same.returncode == 0:
        folder = os.path.join(ROOT, "nfdmatch", "matching")
        for name in os.listdir(folder):
            if name.startswith("_kernels_aot"):
                shutil.copy2(os.path.join(folder, name), os.path.join(path, "nfdmatch", "matching", name))
    return path


def graph_of(path):
    import h5py

    with h5py.File(path, "r") as f:
        return f["graph/neighbour"][...], f["graph/distance"][...]


def exhaustive_sample(index_path: str, rows: np.ndarray, k: int) -> bool:
    """The graph's lists of ``rows`` equal the exhaustive search's top k + 1 less the row."""
    from nfdmatch.index import open_index
    from nfdmatch.search.engine import BestRows, Cascade
    from nfdmatch.search.index_search import _exhaustive, ranked_rows

    nb, _ = graph_of(index_path)
    with open_index(index_path) as idx:
        q = np.asarray(idx.coefficients_at(rows), dtype=np.complex128)
        tops = [BestRows(k + 1, None) for _ in rows]
        _exhaustive(idx, q, tops, Cascade(idx.samples), weights=None, progress=None)
        found = ranked_rows(idx, tops, k + 1)
    return all([m.row for m in res if m.row != r][:k] == nb[r].tolist() for r, res in zip(rows, found))


def adjusted_rand(a: np.ndarray, b: np.ndarray) -> float:
    _, ai = np.unique(a, return_inverse=True)
    _, bi = np.unique(b, return_inverse=True)
    table = np.zeros((ai.max() + 1, bi.max() + 1), dtype=np.int64)
    np.add.at(table, (ai, bi), 1)
    comb = lambda x: (x * (x - 1) / 2.0).sum()  # noqa: E731
    index, rows, cols, total = comb(table), comb(table.sum(1)), comb(table.sum(0)), comb(np.array([len(a)]))
    expected = rows * cols / total
    top = (rows + cols) / 2
    return float((index - expected) / (top - expected)) if top != expected else 1.0


def elastic_graph_rows(work: str, py: list, curves: int, k: int) -> None:
    """``index build --graph k`` and ``--graph k --elastic`` added in turn to copies of one
    built index of ``curves`` family curves; prints their table."""
    import json

    folder = os.path.join(work, f"families-{curves}")
    generate(folder, curves // MEMBERS)
    plain = os.path.join(work, f"plain-{curves}.h5")
    if not os.path.exists(plain):
        seconds, mb, _ = timed(py + ["index", "build", folder, "--index", plain, "-q"], tree_env(ROOT))
        print(f"index build of {curves:,} family curves (no graph): {seconds:.1f} s, {mb:.0f} MB", flush=True)
    rows, walls = [], {}
    for label, extra in ((f"--graph {k}", []), (f"--graph {k} --elastic", ["--elastic"])):
        target = os.path.join(work, f"graph-{curves}{'-elastic' if extra else ''}.h5")
        shutil.copy(plain, target)
        cmd = ["index", "build", folder, "--index", target, "--graph", str(k)] + extra + ["--format", "json", "-q"]
        seconds, mb, proc = timed(py + cmd, tree_env(ROOT))
        graph = json.loads(proc.stdout.splitlines()[-1])["graph"]
        walls[label] = seconds
        rows.append(
            (
                f"`index build --graph {k}{' --elastic' if extra else ''}`, {curves:,} family curves",
                f"{seconds:.1f} s",
                f"the graph {graph['seconds']:.1f} s ({graph['seconds'] / seconds:.0%}) on {graph['processes']} "
                f"processes, {mb:.0f} MB peak",
            )
        )
        print(" | ".join(rows[-1]), flush=True)
    ratio = walls[f"--graph {k} --elastic"] / walls[f"--graph {k}"]
    rows.append(("`--elastic` against the exact graph, the same run", f"{ratio:.2f}x", ""))
    print("| measure | wall | note |\n|---|---:|---|")
    for r in rows:
        print("| " + " | ".join(r) + " |")


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument(
        "--curves", type=int, default=100_000, help="family curves of the graph, pairs and groups (0: none)"
    )
    ap.add_argument("--small", type=int, default=1400, help="curves of the all-against-all row")
    ap.add_argument("--graph", type=int, default=10, help="K of index build --graph")
    ap.add_argument("--max-distance", type=float, default=0.05, help="D of pairs and groups")
    ap.add_argument("--skip-base", action="store_true", help="this tree only")
    ap.add_argument(
        "--elastic", action="store_true", help="only index build --graph K against --graph K --elastic (this tree)"
    )
    ap.add_argument("--work", default=None, help="folder for the data (default: a temporary one, removed)")
    args = ap.parse_args()
    work = os.path.abspath(args.work or tempfile.mkdtemp(prefix="bench-selfjoin-"))
    os.makedirs(work, exist_ok=True)
    os.chdir(work)  # the commands run here: not in a source tree
    py = [sys.executable, "-m", "nfdmatch"]
    if args.elastic:
        try:
            elastic_graph_rows(work, py, args.curves, args.graph)
        finally:
            if args.work is None:
                shutil.rmtree(work, ignore_errors=True)
        return
    trees = [("this tree", ROOT)] + ([] if args.skip_base else [(BASE, base_tree(work))])
    rows = []
    try:
        if args.curves:  # 0: the 1,400-curve rows only
            # ---------------------------------------------------------------- the graph
            folder = os.path.join(work, f"families-{args.curves}")
            labels = generate(folder, args.curves // MEMBERS)
            plain = os.path.join(work, f"plain-{args.curves}.h5")
            if not os.path.exists(plain):
                timed(py + ["index", "build", folder, "--index", plain, "-q"], tree_env(ROOT))
            graphs = {}
            for name, tree in trees:
                target = os.path.join(work, f"graph-{args.curves}-{name.replace(' ', '-')}.h5")
                shutil.copy(plain, target)
                seconds, mb, _ = timed(
                    py + ["index", "build", folder, "--index", target, "--graph", str(args.graph), "-q"], tree_env(tree)
                )
                graphs[name] = target
                rows.append(
                    (
                        f"`index build --graph {args.graph}`, {args.curves:,} family curves",
                        name,
                        f"{seconds:.1f} s",
                        f"{mb:.0f} MB",
                    )
                )
            nb, dist = graph_of(graphs["this tree"])
            if BASE in graphs:
                nb0, dist0 = graph_of(graphs[BASE])
                same = np.array_equal(nb, nb0)
                diff = float(np.abs(dist - dist0).max())
                rows.append(
                    ("graphs identical (neighbours; max distance difference)", "both", f"{same}", f"{diff:.1e}")
                )
            sample = np.random.default_rng(0).choice(len(nb), 20, replace=False)
            ok = exhaustive_sample(graphs["this tree"], sample, args.graph)
            rows.append(("20 rows' lists = the exhaustive search's", "this tree", f"{ok}", ""))

            # ---------------------------------------------------------------- pairs and groups
            index = graphs["this tree"]
            D = str(args.max_distance)
            seconds, mb, proc = timed(
                py + ["pairs", "--index", index, "--max-distance", D, "--format", "csv"], tree_env(ROOT)
            )
            count = len(proc.stdout.splitlines()) - 1
            rows.append(
                (
                    f"`pairs --max-distance {D}`, {args.curves:,} curves",
                    "this tree",
                    f"{seconds:.1f} s",
                    f"{mb:.0f} MB, {count:,} pairs",
                )
            )
            within = sum(MEMBERS * (MEMBERS - 1) // 2 for _ in range(args.curves // MEMBERS))
            rows.append(("pairs inside a family (all of them)", "generated", f"{within:,}", ""))
            seconds, mb, proc = timed(
                py + ["groups", "--index", index, "--max-distance", D, "--format", "csv"], tree_env(ROOT)
            )
            got, fam = [], []
            for line in proc.stdout.splitlines()[1:]:
                curve, group = line.split(",")[:2]
                path, j = curve.rsplit("#", 1)
                got.append(int(group))
                fam.append(labels[(os.path.basename(path), int(j))])
            got, fam = np.array(got), np.array(fam)
            exact = 0
            for g in np.unique(got):
                members = fam[got == g]
                exact += len(members) * (len(np.unique(members)) == 1 and len(members) == (fam == members[0]).sum())
            rows.append(
                (
                    f"`groups --max-distance {D}`",
                    "this tree",
                    f"{seconds:.1f} s",
                    f"{mb:.0f} MB, {len(np.unique(got)):,} groups; {exact / len(got):.1%} of curves grouped exactly "
                    f"as their family; adjusted Rand {adjusted_rand(got, fam):.4f}",
                )
            )

        # ---------------------------------------------------------------- all against all
        small = os.path.join(work, f"families-{args.small}")
        generate(small, max(1, args.small // MEMBERS), files=10, seed=12)
        small_index = os.path.join(work, f"small-{args.small}.h5")
        if not os.path.exists(small_index):
            timed(py + ["index", "build", small, "--index", small_index, "-q"], tree_env(ROOT))
        for name, tree in trees:
            seconds, mb, _ = timed(
                py + ["query", small, "--index", small_index, "--top", "40", "--format", "csv", "-q"], tree_env(tree)
            )
            rows.append(
                (
                    f"all against all, {args.small:,} curves: `query DIR --top 40`",
                    name,
                    f"{seconds:.1f} s",
                    f"{mb:.0f} MB",
                )
            )
        matrices = {}
        for name, tree in trees:
            matrices[name] = os.path.join(work, f"matrix-{name.replace(' ', '-')}.csv")
            if os.path.exists(matrices[name]):
                os.remove(matrices[name])  # written afresh (an unchanged file is not rewritten)
            seconds, mb, _ = timed(py + ["matrix", small, "-o", matrices[name], "-q"], tree_env(tree))
            rows.append((f"`matrix` of the same {args.small:,} curves (CSV)", name, f"{seconds:.1f} s", f"{mb:.0f} MB"))
        if len(matrices) == 2:
            with open(matrices["this tree"], "rb") as a, open(matrices[BASE], "rb") as b:
                same = a.read() == b.read()
            rows.append(("the two matrices' files identical", "both", f"{same}", ""))
        code = (
            "import sys, time; t0 = time.perf_counter(); from nfdmatch.index import open_index; "
            "from nfdmatch.search.engine import Cascade; from nfdmatch.search.join import nearest_others; "
            "idx = open_index(sys.argv[1]); nearest_others(idx.search_table(), idx.coefficients_at, 40, "
            "Cascade(idx.samples)); print(time.perf_counter() - t0)"
        )
        seconds, mb, proc = timed([sys.executable, "-c", code, small_index], tree_env(ROOT))
        rows.append(
            (
                f"all against all, {args.small:,} curves: the self-join, 40 nearest others",
                "this tree",
                f"{seconds:.1f} s",
                f"{mb:.0f} MB (process; join {float(proc.stdout):.1f} s)",
            )
        )
    finally:
        if not args.skip_base and os.path.exists(os.path.join(work, "base")):
            subprocess.run(["git", "worktree", "remove", "--force", os.path.join(work, "base")], cwd=ROOT)
        if args.work is None:
            shutil.rmtree(work, ignore_errors=True)
    print("| measure | tree | figure | note |\n|---|---|---:|---|")
    for r in rows:
        print("| " + " | ".join(r) + " |")


if __name__ == "__main__":
    main()
