"""Re-ranking by diffusion: which method, and what it costs (docs/rerank.md).

    python benchmarks/bench_rerank.py [--data ../shared/data] [--curves 10000] [--skip-timing | --skip-tables]
                                      [--skip-methods]
    python benchmarks/bench_rerank.py --index I.h5 [--queries FILE --batch 100]
    python benchmarks/bench_rerank.py --self-batch 1400
    python benchmarks/bench_rerank.py --graph-batch [--compare ../other-checkout] [--work DIR] [--pairs 3] [--families 500]

Prints, from the repository root:

1. the method comparison on full distance matrices (every curve of a collection a query,
   itself left out): plain exact distance, personalised PageRank (PPR) kNN diffusion as
   A A^T, the shipped PPR (cosine of the PageRank rows + 0.2 direct affinity),
   tensor-product graph diffusion, offline diffusion + online linear combination,
   k-reciprocal re-ranking, contextual dissimilarity;
2. the shipped path (`query --rerank`: each query's exact top 100 joined to the graph
   stored by `index build --graph`), on the same collections;
3. graph build time next to the plain build, and query --rerank time next to the plain
   query, on ``--curves`` generated curves (families of 10, benchmarks/bench_index.py);
   with ``--index`` the query timing only, on that index; with ``--queries FILE`` too, the
   first ``--batch`` curves of FILE as one batch, --top 10: plain, ``--rerank`` with exact
   and with walk candidates, each with the seconds of its PageRank push (issue 23);
4. with ``--self-batch N``: the held-out benchmark's shape (issue 23's "time for 1,400
   queries"): N generated curves in families of 20, every one a query in one batch,
   ``--top 40``, plain against ``--rerank``, as CLI processes in turn and in the library;
5. with ``--graph-batch``: the library's batch on both kinds of graph (issue 23's goal for
   the fused graph: ``rerank_index`` at most 4x the plain ``search_index``): 1,400 bending
   curves (70 families of 20, benchmarks/bending_families.py), indexed with ``--graph 10``
   and with ``--graph 10 --elastic``; 200 of them as one batch, ``--top 40``: plain, the
   exact graph's ``--rerank``, the fused graph's, in turn, each round's ratios to its own
   plain. With ``--compare TREE`` the same in processes of that checkout (its
   ``.venv/bin/python``), the two in turn, and whether both give the same answers (every
   id, distance and score to the digit).

Collections: Kimia-99 (9 classes x 11; same-class hits at ranks 1..10 and bull's-eye, the
same-class hits in the top 22, query included, as a fraction of 11); knotess control ->
smooth top-1 (each control polygon against the 148 smooth curves; one miss is a pair of
identical circles); mesh_loops sections (227, label = mesh; precision at 10, bull's-eye
in the top 2 x mesh size); generated families (40 families x 12, bench_search's
generator at noise 0.15 and 0.30 of the RMS radius; precision at 10). Development data is
not shipped.
"""

from __future__ import annotations

import argparse
import csv
import os
import shutil
import sys
import tempfile
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
#: the checkout whose nfdmatch is measured: this one, or (``--graph-batch --compare``'s
#: processes) the one the variable names
TREE = os.environ.get("NFDMATCH_BENCH_TREE") or os.path.dirname(HERE)
sys.path.insert(0, HERE)
sys.path.insert(0, TREE)

from nfdmatch import Curve, read_curves, write_curves  # noqa: E402
from nfdmatch.descriptors import descriptors_batch  # noqa: E402
from nfdmatch.matching import exact_search  # noqa: E402
from nfdmatch.search import distance_matrix  # noqa: E402
from nfdmatch.search.rerank import (  # noqa: E402
    ALPHA,
    MATRIX_TOLERANCE,
    MIX,
    SCALE_NEIGHBOURS,
    diffused_similarity,
)

DEFAULT_DATA = os.path.normpath(os.path.join(HERE, "..", "..", "shared", "data"))
K, A = SCALE_NEIGHBOURS, ALPHA


# --------------------------------------------------------------------------- methods on a full matrix
# (research versions for the comparison; the shipped one lives in nfdmatch/search/rerank.py)


def _knn_affinity(D, k=K):
    N = len(D)
    off = D.copy()
    np.fill_diagonal(off, np.inf)
    order = np.argsort(off, axis=1, kind="stable")
    s = np.maximum(off[np.arange(N), order[:, min(k, N - 1) - 1]], 1e-12)
    W = np.exp(-(D**2) / (s[:, None] * s[None, :]))
    mask = np.zeros_like(W, dtype=bool)
    mask[np.arange(N)[:, None], order[:, :k]] = True
    np.fill_diagonal(mask, True)
    return W * mask, W, order


def _ppr_rows(D, k=K, alpha=A):
    Wk, _, _ = _knn_affinity(D, k)
    P = Wk / Wk.sum(axis=1, keepdims=True)
    return (1 - alpha) * np.linalg.inv(np.eye(len(D)) - alpha * P)


def ppr_product(D):
    """PPR rows A, similarity A A^T (the issue's prototype)."""
    F = _ppr_rows(D)
    return F @ F.T


def tensor_product(D, k=K, alpha=A, iterations=30):
    """Tensor-product graph diffusion (Yang, Prasad, Latecki 2012): Q <- alpha P Q P^T + I."""
    Wk, _, _ = _knn_affinity(D, k)
    P = Wk / Wk.sum(axis=1, keepdims=True)
    Q = np.eye(len(D))
    for _ in range(iterations):
        Q = alpha * P @ Q @ P.T + np.eye(len(D))
    return Q


def offline_online(D, k=K):
    """Offline PPR A A^T of the collection; a query's row is the affinity-weighted mean of
    its k neighbours' rows (the query is left out of its own neighbours)."""
    F = ppr_product(D)
    N = len(D)
    off = D.copy()
    np.fill_diagonal(off, np.inf)
    order = np.argsort(off, axis=1, kind="stable")[:, :k]
    s = np.maximum(off[np.arange(N), order[:, -1]], 1e-12)
    S = np.empty_like(F)
    for i in range(N):
        w = np.exp(-(off[i, order[i]] ** 2) / (s[i] * s[order[i]])) + 1e-300
        S[i] = w @ F[order[i]] / w.sum()
    return S


def k_reciprocal(D, k1=10, k2=4, lam=0.3):
    """k-reciprocal encoding with expansion and local query expansion, Jaccard distance
    mixed with the original (Zhong et al. 2017), as a similarity."""
    N = len(D)
    order = np.argsort(D, axis=1, kind="stable")

    def reciprocal(i, k):
        return {int(j) for j in order[i, : k + 1] if i in order[j, : k + 1]}

    R = []
    for i in range(N):
        base = reciprocal(i, k1)
        grown = set(base)
        for j in base:
            Rj = reciprocal(j, max(k1 // 2, 1))
            if len(Rj & base) > 2 / 3 * len(Rj):
                grown |= Rj
        R.append(grown)
    V = np.zeros((N, N))
    for i in range(N):
        idx = np.array(sorted(R[i]))
        scale = max(float(np.median(D[i, order[i, 1 : k1 + 1]])), 1e-12)
        V[i, idx] = np.exp(-D[i, idx] / scale)
        V[i] /= V[i].sum()
    if k2 > 1:
        V = np.stack([V[order[i, :k2]].mean(axis=0) for i in range(N)])
    J = 1 - np.minimum(V[:, None, :], V[None, :, :]).sum(2) / np.maximum(V[:, None, :], V[None, :, :]).sum(2)
    return -((1 - lam) * J + lam * D / np.median(D[D > 0]))


def contextual(D, k=K):
    """Contextual dissimilarity (Jegou et al. 2007): d_ij / sqrt(r_i r_j), r = mean k-NN distance."""
    off = D.copy()
    np.fill_diagonal(off, np.inf)
    r = np.sort(off, axis=1)[:, :k].mean(axis=1)
    return -D / np.sqrt(r[:, None] * r[None, :])


METHODS = {
    "plain exact distance": lambda D: -D,
    "PPR kNN, A A^T": ppr_product,
    f"PPR kNN, cosine + {MIX} affinity (shipped)": diffused_similarity,
    "tensor-product graph": tensor_product,
    "offline PPR + online combination": offline_online,
    "k-reciprocal (k1 10, k2 4, lambda 0.3)": k_reciprocal,
    "contextual dissimilarity": contextual,
}


# --------------------------------------------------------------------------- collections


def _folder(folder, names=None):
    names = names or sorted(f for f in os.listdir(folder) if f.endswith(".csv") and not f.startswith("_"))
    return names, [read_curves(os.path.join(folder, f))[0] for f in names]


def collections(data):
    """name -> dict(curves, labels (or None), D)"""
    out = {}
    with open(os.path.join(data, "kimia99", "_labels.csv")) as fh:
        labels = {row["csv"]: row["class_name"] for row in csv.DictReader(fh)}
    names, curves = _folder(os.path.join(data, "kimia99"))
    out["kimia99"] = dict(curves=curves, labels=np.array([labels[n] for n in names]))
    with open(os.path.join(data, "mesh_loops", "index.csv")) as fh:
        rows = [r for r in csv.DictReader(fh) if r["kind"] == "section"]
    _, curves = _folder(os.path.join(data, "mesh_loops"), [r["file"] for r in rows])
    out["mesh sections"] = dict(curves=curves, labels=np.array([r["mesh"] for r in rows]))
    from bench_search import _sample, _smooth_coefficients

    rng = np.random.default_rng(5)
    F, M = 40, 12
    a, b = _smooth_coefficients(rng, F, rng.integers(3, 7, F))
    owner = np.repeat(np.arange(F), M)
    for noise in (0.15, 0.3):
        pts = _sample(a[owner], b[owner], 48, np.random.default_rng(int(noise * 100)), noise)
        out[f"families noise {noise:.2f}"] = dict(
            curves=[Curve(p, id=f"f{o:02d}-{i:03d}") for i, (p, o) in enumerate(zip(pts, owner))], labels=owner
        )
    for c in out.values():
        c["D"] = distance_matrix(c["curves"])
    return out


def knots(data):
    names_c, control = _folder(os.path.join(data, "knotess_control"))
    names_s, smooth = _folder(os.path.join(data, "knotess_smooth"))
    assert names_c == names_s
    Ds = distance_matrix(smooth)
    bs = descriptors_batch(smooth).coefficients
    Q = np.array([exact_search(q, bs, 128)["distance"] for q in descriptors_batch(control).coefficients])
    return control, smooth, Ds, Q


def scores_table(S, labels):
    """(same-class counts at ranks 1..10 with the query left out, precision at 10, bull's-eye)."""
    S = np.array(S, dtype=float)
    N = len(S)
    excl = S.copy()
    np.fill_diagonal(excl, -np.inf)
    order = np.argsort(-excl, axis=1, kind="stable")[:, :10]
    same = labels[order] == labels[:, None]
    incl = S.copy()
    np.fill_diagonal(incl, np.inf)  # the query itself first, as bull's-eye counts it
    size = np.array([(labels == c).sum() for c in labels])
    order2 = np.argsort(-incl, axis=1, kind="stable")
    bull = np.mean([(labels[order2[i, : 2 * size[i]]] == labels[i]).sum() / size[i] for i in range(N)])
    return same.sum(axis=0), same.mean(), bull


def knots_top1(method, Ds, Q):
    N = len(Ds)
    hits = 0
    for i in range(N):
        Aug = np.zeros((N + 1, N + 1))
        Aug[1:, 1:] = Ds
        Aug[0, 1:] = Aug[1:, 0] = Q[i]
        s = np.asarray(method(Aug), dtype=float)[0, 1:]
        hits += int(np.lexsort((Q[i], -s))[0] == i)
    return hits


# --------------------------------------------------------------------------- the shipped path


def _against_the_matrix(results, position, S):
    """query --rerank --exclude-self of every stored curve against ``matrix --rerank``'s
    similarity S (rows in ``position``'s order): the largest gap between a reported score and
    the matrix's, and how many queries' orders invert two matrix scores by more than twice
    MATRIX_TOLERANCE (issue 23: the same order up to the documented tolerance)."""
    gap, otherwise = 0.0, 0
    for i, r in enumerate(results):
        if not r:
            continue
        want = S[i, [position[m.id] for m in r]]
        gap = max(gap, float(np.max(np.abs(np.array([m.score for m in r]) - want))))
        later_best = np.maximum.accumulate(want[::-1])[::-1]
        otherwise += bool(np.any(later_best[1:] - want[:-1] > 2 * MATRIX_TOLERANCE))
    return gap, otherwise


def shipped(cols, knot_data, work, candidates="walk"):
    """query --rerank (library) through an index with a graph: Kimia, mesh, families, knots."""
    from nfdmatch.index import build_index, open_index
    from nfdmatch.search import search_index
    from nfdmatch.search.rerank import rerank_index

    print(
        "\n## The shipped path: each query's exact top 100 re-ordered by the diffusion over the stored graph "
        "(index build --graph 10, query --rerank --exclude-self); time: every curve a query, one batch; "
        f"candidates: {candidates}"
    )
    print(
        f"{'collection':24} {'plain P@10':>10} {'rerank P@10':>11} {'plain BE':>9} {'rerank BE':>9}"
        f" {'plain s':>8} {'rerank s':>8}  {'rerank ranks 1..10 (same class)':s}"
    )
    for name, c in cols.items():
        folder = os.path.join(work, name.replace(" ", "_"))
        os.makedirs(folder)
        write_curves(os.path.join(folder, "curves.obj"), c["curves"])
        build_index([folder], os.path.join(work, name.replace(" ", "_") + ".h5"), jobs=2, graph=10)
        stored = read_curves(os.path.join(folder, "curves.obj"))
        with open_index(os.path.join(work, name.replace(" ", "_") + ".h5")) as idx:
            t = time.perf_counter()
            search_index(idx, stored, top=min(40, len(stored) - 1), exclude_self=True)
            t_plain = time.perf_counter() - t
            t = time.perf_counter()
            res, _ = rerank_index(
                idx,
                stored,
                top=100 if len(stored) > 100 else len(stored) - 1,
                depth=100,
                exclude_self=True,
                candidates=candidates,
            )
            t_rerank = time.perf_counter() - t
        pos = {os.path.relpath(s.id, work): i for i, s in enumerate(stored)}  # ids relative to the index
        N = len(stored)
        S = np.full((N, N), -np.inf)
        for i, r in enumerate(res):
            for m in r:
                S[i, pos[m.id]] = m.score
        np.fill_diagonal(S, np.inf)
        counts, p10, bull = scores_table(S, c["labels"])
        pc, pp, pb = scores_table(-c["D"], c["labels"])
        gap, otherwise = _against_the_matrix(res, pos, diffused_similarity(c["D"], ids=list(pos)))
        print(
            f"{name:24} {pp:10.3f} {p10:11.3f} {pb:9.3f} {bull:9.3f} {t_plain:8.1f} {t_rerank:8.1f}"
            f"  {' '.join(str(x) for x in counts)} = {counts.sum()} (plain {pc.sum()}); against matrix --rerank: "
            f"largest score gap {gap:.1e}, queries ordered otherwise beyond 2 x {MATRIX_TOLERANCE:g}: {otherwise}",
            flush=True,
        )
    control, smooth, _, _ = knot_data
    folder = os.path.join(work, "knots")
    os.makedirs(folder)
    write_curves(os.path.join(folder, "smooth.obj"), smooth)
    build_index([folder], os.path.join(work, "knots.h5"), jobs=2, graph=10)
    with open_index(os.path.join(work, "knots.h5")) as idx:
        res, _ = rerank_index(idx, control, top=1, candidates=candidates)
        ids = idx.ids()
    hits = sum(r[0].id == ids[i] for i, r in enumerate(res))
    print(f"{'knotess control->smooth':24} top-1 with --rerank: {hits}/{len(control)}")


def timing(curves, work):
    import bench_index
    from nfdmatch.index import build_index

    folder = os.path.join(work, f"gen{curves}")
    queries_all = bench_index.generate(folder, curves)
    t = time.perf_counter()
    plain = build_index([folder], os.path.join(work, "plain.h5"), jobs=2)
    t_plain = time.perf_counter() - t
    t = time.perf_counter()
    graph8 = build_index([folder], os.path.join(work, "graph8.h5"), jobs=2, graph=8)
    t_graph8 = time.perf_counter() - t
    t = time.perf_counter()
    graph = build_index([folder], os.path.join(work, "graph.h5"), jobs=2, graph=10)
    t_graph = time.perf_counter() - t
    # incremental: one more file of 1% new curves
    extra = bench_index.family_members(np.random.default_rng(99), max(curves // 100, 2))
    write_curves(os.path.join(folder, "zz-extra.obj"), extra)
    inc = build_index([folder], os.path.join(work, "graph.h5"), jobs=2)
    print(f"\n## Build, {plain.curves} generated curves (families of 10), 2 workers")
    print(
        f"plain build {t_plain:.1f} s; with --graph 10 {t_graph:.1f} s, of which the graph "
        f"{graph.graph.seconds:.1f} s ({graph.graph.searched} rows searched, "
        f"{1e3 * graph.graph.seconds / max(graph.graph.searched, 1):.2f} ms per row)"
    )
    print(
        f"with --graph 8 {t_graph8:.1f} s, of which the graph {graph8.graph.seconds:.1f} s "
        f"({1e3 * graph8.graph.seconds / max(graph8.graph.searched, 1):.2f} ms per row: the 9 nearest other "
        f"rows of a row are its family, the 10th is not)"
    )
    print(
        f"incremental, +{len(extra)} curves: {inc.seconds:.1f} s, graph {inc.graph.seconds:.1f} s "
        f"({inc.graph.searched} searched, {inc.graph.updated} updated, {inc.graph.kept} kept)"
    )
    query_timing(os.path.join(work, "graph.h5"), queries_all)


def query_timing(index, queries, batch=200, single=20):
    """Plain query against query --rerank: a batch of ``batch`` queries (--top 40, depth 100)
    and ``single`` queries one at a time (--top 10), each the best of 3 runs."""
    from nfdmatch.index import open_index
    from nfdmatch.search import search_index
    from nfdmatch.search.rerank import rerank_index

    with open_index(index) as idx:
        many, few = queries[:batch], queries[:single]
        for label, fn in (
            (f"plain query --top 40, batch of {len(many)}", lambda: search_index(idx, many, top=40)),
            (f"query --rerank --top 40, batch of {len(many)}", lambda: rerank_index(idx, many, top=40)),
            ("plain query --top 10, one query at a time", lambda: [search_index(idx, [q], top=10) for q in few]),
            ("query --rerank --top 10, one query at a time", lambda: [rerank_index(idx, [q], top=10) for q in few]),
        ):
            fn()
            best = min(_time(fn) for _ in range(3))
            n = len(many) if "batch" in label else len(few)
            print(f"{label:46} {best:7.2f} s, {1e3 * best / n:7.1f} ms per query", flush=True)


def batch_timing(index, queries, runs=3):
    """One batch of ``queries`` (--top 10): the plain query, ``--rerank`` with the exact top
    100 as candidates and with the walk's; each the best of ``runs`` after a first run (the
    same process: the index's pages warm), with the seconds of the PageRank push
    (``GraphWalk.pagerank``) in that run."""
    from nfdmatch.index import open_index
    from nfdmatch.matching.kernels import current
    from nfdmatch.search import search_index
    from nfdmatch.search.diffusion import GraphWalk
    from nfdmatch.search.rerank import rerank_index

    pushed = [0.0]
    real = GraphWalk.pagerank

    def timed(self, *args, **kwargs):
        t = time.perf_counter()
        try:
            return real(self, *args, **kwargs)
        finally:
            pushed[0] += time.perf_counter() - t

    GraphWalk.pagerank = timed
    try:
        with open_index(index) as idx:
            print(f"{idx.n_curves} curves, a batch of {len(queries)} queries, kernels: {current().describe()}")
            for label, fn in (
                ("plain query --top 10", lambda: search_index(idx, queries, top=10)),
                (
                    "query --rerank --top 10 (exact top 100)",
                    lambda: rerank_index(idx, queries, top=10, candidates="exact"),
                ),
                ("query --rerank --top 10 (walk)", lambda: rerank_index(idx, queries, top=10, candidates="walk")),
            ):
                fn()
                best = None
                for _ in range(runs):
                    pushed[0] = 0.0
                    took = _time(fn)
                    if best is None or took < best[0]:
                        best = (took, pushed[0])
                push = f", push {best[1]:5.2f} s" if "rerank" in label else ""
                print(f"{label:42} {best[0]:6.2f} s{push}", flush=True)
    finally:
        GraphWalk.pagerank = real


def self_batch_timing(curves=1400, members=20, runs=5):
    """The held-out benchmark's shape (issue 23): ``curves`` generated curves in families of
    ``members`` (1,400 in 70 of 20), indexed with ``--graph 10``; every curve a query, one
    batch, ``--top 40``. Plain ``query`` against ``query --rerank`` as whole processes of the
    CLI, run in turn ``runs`` times each (medians, and the median of the in-turn ratios), and
    in the library (the same process, the best of 3). The answers are the same run to run
    (checked)."""
    import statistics
    import subprocess

    import bench_index
    from nfdmatch.index import build_index, open_index
    from nfdmatch.search import search_index
    from nfdmatch.search.rerank import rerank_index

    work = tempfile.mkdtemp(prefix="bench-rerank-self-")
    try:
        folder = os.path.join(work, "curves")
        bench_index.generate(folder, curves, per_file=max(curves // 10, 1), members=members)
        index = os.path.join(work, "i.h5")
        build_index([folder], index, jobs=2, graph=10)
        with open_index(index) as idx:
            n = idx.n_curves
        print(f"\n## Every curve a query, one batch, --top 40: {n} generated curves in families of {members}")
        base = [sys.executable, "-m", "nfdmatch", "query", folder, "--index", index, "--top", "40", "--format", "csv"]
        commands = {"plain": base, "rerank": base + ["--rerank"]}
        seconds, outputs = {k: [] for k in commands}, {k: set() for k in commands}
        for _ in range(runs):
            for key, cmd in commands.items():
                t = time.perf_counter()
                out = subprocess.run(cmd, capture_output=True, check=True, cwd=work).stdout
                seconds[key].append(time.perf_counter() - t)
                outputs[key].add(out)
        ratios = [r / p for p, r in zip(seconds["plain"], seconds["rerank"])]
        same = all(len(v) == 1 for v in outputs.values())
        print(
            f"CLI, {runs} runs in turn: plain {statistics.median(seconds['plain']):.2f} s, --rerank "
            f"{statistics.median(seconds['rerank']):.2f} s (medians); --rerank / plain {statistics.median(ratios):.2f} "
            f"(median of the in-turn ratios; range {min(ratios):.2f}-{max(ratios):.2f}); answers the same run to "
            f"run: {'yes' if same else 'NO'}"
        )
        stored = []
        for name in sorted(os.listdir(folder)):
            stored += read_curves(os.path.join(folder, name))
        with open_index(index) as idx:
            lib = {
                "plain": lambda: search_index(idx, stored, top=40),
                "rerank": lambda: rerank_index(idx, stored, top=40),
            }
            best = {}
            for key, fn in lib.items():
                fn()
                best[key] = min(_time(fn) for _ in range(3))
        print(
            f"library, the best of 3: plain {best['plain']:.2f} s, --rerank {best['rerank']:.2f} s, "
            f"ratio {best['rerank'] / best['plain']:.2f}"
        )
    finally:
        shutil.rmtree(work, ignore_errors=True)


GRAPH_BATCH = {"curves": (70, 20, 2), "queries": 200, "top": 40}


def graph_batch_timing(work=None, compare=None, pairs=3, rounds=3, families_count=None):
    """Item 5 of the module's docstring: this checkout's processes and ``compare``'s in turn,
    ``pairs`` times, each process ``rounds`` rounds of plain, exact-graph ``--rerank`` and
    fused-graph ``--rerank`` (:func:`graph_batch_child`); the medians of the seconds and of
    each round's ratios to its plain. ``work``: where the curves and the two indexes are
    (made there when missing, by this checkout); ``families_count``: that many families of 20
    instead of 70 (500: the 10,000 bending curves whose walks spread, docs/rerank.md)."""
    import json
    import statistics
    import subprocess

    from bending_families import families
    from nfdmatch import Curve, build_index, write_curves
    from nfdmatch.index.graph import GraphSpec

    work = work or tempfile.mkdtemp(prefix="bench-rerank-graphs-")
    folder = os.path.join(work, "curves")
    if not os.path.exists(os.path.join(work, "fused.h5")):
        os.makedirs(folder, exist_ok=True)
        count, members, dimension = GRAPH_BATCH["curves"]
        points, _ = families(np.random.default_rng(7), families_count or count, members, dimension)
        for part in range(7):
            batch = [Curve(p, id=f"c{part}-{i}") for i, p in enumerate(points[part::7])]
            write_curves(os.path.join(folder, f"p{part}.obj"), batch)
        build_index([folder], os.path.join(work, "exact.h5"), graph=10)
        build_index([folder], os.path.join(work, "fused.h5"), graph=GraphSpec(10, "fused"))
    trees = {"this": os.path.dirname(HERE)} | ({"compare": os.path.abspath(compare)} if compare else {})
    runs = {name: [] for name in trees}
    for pair in range(pairs):
        for name in trees if pair % 2 == 0 else list(trees)[::-1]:
            tree = trees[name]
            python = os.path.join(tree, ".venv", "bin", "python")
            command = [python if os.path.exists(python) else sys.executable, os.path.abspath(__file__)]
            command += ["--graph-batch-child", work, "--rounds", str(rounds)]
            env = dict(os.environ, NFDMATCH_BENCH_TREE=tree)
            out = subprocess.run(command, capture_output=True, text=True, check=True, env=env).stdout
            runs[name].append(json.loads(out.splitlines()[-1]))
    q, stored = GRAPH_BATCH["queries"], sum(len(read_curves(os.path.join(folder, f))) for f in os.listdir(folder))
    print(f"\n## {q} of {stored} bending curves as one batch, --top {GRAPH_BATCH['top']}, the library")
    print(f"({pairs} processes per checkout in turn, {rounds} rounds each; medians; ratios per round to its plain)")
    for name, tree in trees.items():
        rows = [r for run in runs[name] for r in run["rounds"]]
        median = {key: statistics.median(r[key] for r in rows) for key in rows[0]}
        ratio = {key: statistics.median(r[key] / r["plain"] for r in rows) for key in ("exact", "fused")}
        print(
            f"{name:8} {tree}: plain {median['plain']:.2f} s, --rerank exact graph {median['exact']:.2f} s "
            f"({ratio['exact']:.2f}x), fused graph {median['fused']:.2f} s ({ratio['fused']:.2f}x)"
        )
    if compare:
        same = {run["answers"] for name in trees for run in runs[name]}
        print(
            f"the same answers (ids, distances, scores to the digit) in both checkouts: {'yes' if len(same) == 1 else 'NO'}"
        )


def graph_batch_child(work, rounds):
    """One process of :func:`graph_batch_timing`: prints one JSON line, ``{"rounds": [{plain,
    exact, fused seconds}], "answers": sha256 of the three answers (every id and figure)}``."""
    import hashlib
    import json

    from nfdmatch.index import open_index
    from nfdmatch.search import search_index
    from nfdmatch.search.rerank import rerank_index

    queries = read_curves(os.path.join(work, "curves", "p2.obj"))[: GRAPH_BATCH["queries"]]
    top = GRAPH_BATCH["top"]
    with open_index(os.path.join(work, "exact.h5")) as exact, open_index(os.path.join(work, "fused.h5")) as fused:
        runs = {
            "plain": lambda: search_index(exact, queries, k=top)[0],
            "exact": lambda: rerank_index(exact, queries, k=top)[0],
            "fused": lambda: rerank_index(fused, queries, k=top)[0],
        }
        answers = {key: run() for key, run in runs.items()}  # the first call of each: not timed
        timed = [{key: _time(run) for key, run in runs.items()} for _ in range(rounds)]
    # a RankedMatch's repr holds every field, each float to the digit (repr: the shortest exact)
    digest = hashlib.sha256(repr(answers).encode()).hexdigest()
    print(json.dumps({"rounds": timed, "answers": digest}))


def _time(fn):
    t = time.perf_counter()
    fn()
    return time.perf_counter() - t


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=DEFAULT_DATA)
    ap.add_argument("--curves", type=int, default=10000, help="generated curves for the timing (default 10000)")
    ap.add_argument("--skip-timing", action="store_true")
    ap.add_argument("--skip-tables", action="store_true", help="only the build and query timing")
    ap.add_argument("--skip-methods", action="store_true", help="tables: the shipped path only")
    ap.add_argument(
        "--candidates",
        choices=("walk", "exact"),
        default="walk",
        help="the shipped path's candidates (rerank_index(candidates=...)): from the walk (the default) "
        "or the exact top 100",
    )
    ap.add_argument("--index", help="timing: only the queries, on this index (built with --graph) of generated curves")
    ap.add_argument("--queries", help="with --index: a curve file whose first --batch curves are the batch")
    ap.add_argument("--batch", type=int, default=100, help="with --queries: the batch's size (default 100)")
    ap.add_argument(
        "--self-batch",
        type=int,
        metavar="N",
        help="only the held-out benchmark's shape: N generated curves in families of 20, every one a query, "
        "--top 40, plain against --rerank (the CLI and the library)",
    )
    ap.add_argument(
        "--graph-batch",
        action="store_true",
        help="only the library's batch of 200 on an exact and a fused graph of 1,400 bending curves, ratios to plain",
    )
    ap.add_argument(
        "--compare", metavar="TREE", help="with --graph-batch: also this checkout, in turn, the same answers?"
    )
    ap.add_argument("--work", help="with --graph-batch: the curves and indexes here (made when missing)")
    ap.add_argument("--pairs", type=int, default=3, help="with --graph-batch: processes per checkout (default 3)")
    ap.add_argument("--rounds", type=int, default=3, help="with --graph-batch: rounds per process (default 3)")
    ap.add_argument(
        "--families",
        type=int,
        help="with --graph-batch: families of 20 to make (default 70; 500: a graph whose walks spread)",
    )
    ap.add_argument("--graph-batch-child", metavar="WORK", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.graph_batch_child:
        graph_batch_child(args.graph_batch_child, args.rounds)
        return
    if args.graph_batch:
        graph_batch_timing(args.work, args.compare, args.pairs, args.rounds, args.families)
        return
    if args.self_batch:
        self_batch_timing(args.self_batch)
        return
    if args.index and args.queries:
        batch_timing(args.index, read_curves(args.queries)[: args.batch])
        return
    if not os.path.isdir(args.data):
        sys.exit(f"development data not found at {args.data}")
    if args.index:  # the queries of bench_index.generate(..., len(index)) (same seed: same queries)
        import bench_index
        from nfdmatch.index import open_index

        with open_index(args.index) as idx:
            n = idx.n_curves
        folder = tempfile.mkdtemp(prefix="bench-rerank-queries-")
        try:
            query_timing(args.index, bench_index.generate(folder, n))
        finally:
            shutil.rmtree(folder, ignore_errors=True)
        return
    work = tempfile.mkdtemp(prefix="bench-rerank-")
    try:
        if not args.skip_tables:
            tables(args.data, work, methods=not args.skip_methods, candidates=args.candidates)
        if not args.skip_timing:
            timing(args.curves, work)
    finally:
        shutil.rmtree(work, ignore_errors=True)


def tables(data, work, methods=True, candidates="walk"):
    t0 = time.perf_counter()
    cols = collections(data)
    knot_data = knots(data)
    print(f"(distance matrices: {time.perf_counter() - t0:.1f} s)")
    if not methods:
        shipped(cols, knot_data, work, candidates)
        return
    print(
        f"\n## Methods on full distance matrices (k = {K} neighbours, alpha = {A}); P@10 = precision at 10, "
        f"BE = bull's-eye; knots = control->smooth top-1 of 148"
    )
    header = f"{'method':44} {'kimia ranks 1..10 = sum':>36} {'kimia BE':>8} {'mesh P@10':>9} {'mesh BE':>8}"
    header += "".join(f" {'fam ' + n.split()[-1] + ' P@10':>14}" for n in cols if n.startswith("families"))
    print(header + f" {'knots':>6}")
    for name, method in METHODS.items():
        kc, _, kb = scores_table(method(cols["kimia99"]["D"]), cols["kimia99"]["labels"])
        _, mp, mb = scores_table(method(cols["mesh sections"]["D"]), cols["mesh sections"]["labels"])
        line = f"{name:44} {' '.join(f'{x:2d}' for x in kc) + f' = {kc.sum()}':>36} {kb:8.3f} {mp:9.3f} {mb:8.3f}"
        for n, c in cols.items():
            if n.startswith("families"):
                line += f" {scores_table(method(c['D']), c['labels'])[1]:14.3f}"
        line += f" {knots_top1(method, knot_data[2], knot_data[3]):6d}"
        print(line, flush=True)
    shipped(cols, knot_data, work, candidates)


if __name__ == "__main__":
    main()
