"""The elastic stage on every development collection: retrieval quality and cost
(issues "Similarity that bends" and "3-D curves that people call alike"; docs/elastic.md).

    python benchmarks/bench_3d.py [--data ../shared/data] [--depths 100,all] [--diffusion] [--constants | --timing]
                                   [--only NAMES] [--large]

Every curve of a collection is a query against the rest (the library's own search with
``exclude_self``, as ``query --exclude-self``); top-1 and bull's-eye (same class among the
2 x class-size nearest, the query counted first: 20 for psb_dev, 22 for Kimia-99). Rows:

- plain: the exact rigid distance (``query``);
- elastic M: the exact top M re-ordered by the fused distance (``query --elastic
  --elastic-depth M``; ``all`` = the collection);
- the fused distance's terms alone (elastic, statistics), ranking every curve;
- the statistics peer of the issue (sorted PCA eigenvalues + 12-bin histograms of turning
  angle, binormal dihedral angle and distance to the centroid at 128 arc-length samples,
  Euclidean), on the raw curve and low-passed to 16 harmonics: written here, not in the
  library;
- chance;
- with ``--diffusion``: diffusion on full matrices of the exact and of the fused distance:
  today's ``matrix --rerank`` (personalised PageRank) and a locally constrained diffusion
  (LCDP, written here: the measurement for the diffusion still to build).

With the seconds of the plain and the elastic search (the ratio is what holds on a busy
machine), the elastic kernel's microseconds a pair, and ``query --elastic`` against the plain
query as CLI processes on an index of each psb_dev folder and of Kimia-99 (``--timing``:
only these). ``--constants`` prints the fused
distance's constants recomputed from the pooled development pairs (the quantile tables
of nfdmatch/matching/fused.py, the block scales of statistics.py).

Collections: psb_dev cut loops and mid-sections (19 classes), Kimia-99 (9 x 11), the mesh
sections (label = mesh), the bending families (benchmarks/bending_families.py: 2-D and 3-D,
20 families of 10), and the knots check (each knotess control polygon against the smooth
knots: top-1, copies found first). Development data is not shipped.
"""

from __future__ import annotations

import argparse
import csv
import os
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)
sys.path.insert(0, os.path.dirname(HERE))

from bending_families import families  # noqa: E402

from nfdmatch import Curve, read_curves  # noqa: E402
from nfdmatch import distance as nfdmatch_distance  # noqa: E402
from nfdmatch.descriptors import descriptors_batch, resample  # noqa: E402
from nfdmatch.matching import exact_search  # noqa: E402
from nfdmatch.matching.elastic import elastic_distances, elastic_rows  # noqa: E402
from nfdmatch.matching.statistics import curve_statistics, statistics_distance  # noqa: E402
from nfdmatch.search import MemoryIndex, search_index  # noqa: E402
from nfdmatch.search.stages import ElasticStage  # noqa: E402


def _folder(folder, names=None):
    names = names or sorted(f for f in os.listdir(folder) if f.endswith(".csv") and not f.startswith("_"))
    return [read_curves(os.path.join(folder, f))[0] for f in names]


def collections(data):
    """name -> (curves, labels, bull's-eye depth or None for 2 x class size)"""
    out = {}
    for name in ("cutloop", "midsection"):
        with open(os.path.join(data, "psb_dev", name, "labels.csv")) as fh:
            rows = list(csv.DictReader(fh))
        curves = _folder(os.path.join(data, "psb_dev", name, "curves"), [r["file"] for r in rows])
        out[f"psb {name}"] = (curves, np.array([r["class"] for r in rows]), 20)
    with open(os.path.join(data, "kimia99", "_labels.csv")) as fh:
        labels = {row["csv"]: row["class_name"] for row in csv.DictReader(fh)}
    names = sorted(f for f in os.listdir(os.path.join(data, "kimia99")) if f.endswith(".csv") and f in labels)
    out["kimia99"] = (_folder(os.path.join(data, "kimia99"), names), np.array([labels[n] for n in names]), None)
    with open(os.path.join(data, "mesh_loops", "index.csv")) as fh:
        rows = [r for r in csv.DictReader(fh) if r["kind"] == "section"]
    out["mesh sections"] = (
        _folder(os.path.join(data, "mesh_loops"), [r["file"] for r in rows]),
        np.array([r["mesh"] for r in rows]),
        None,
    )
    for dimension in (2, 3):
        points, labels = families(np.random.default_rng(33 + dimension), 20, 10, dimension)
        curves = [Curve(p, id=f"bend{dimension}d-{f:02d}-{i:03d}") for i, (p, f) in enumerate(zip(points, labels))]
        out[f"bending {dimension}-D"] = (curves, labels, None)
    return out


def scores(order: np.ndarray, labels: np.ndarray, depth: int | None) -> tuple[float, float]:
    """(top-1, bull's-eye) of rankings ``order`` (N, >= N - 1) without the query itself."""
    N = len(labels)
    size = np.array([(labels == c).sum() for c in labels])
    top1 = float(np.mean(labels[order[:, 0]] == labels))
    bull = [(1 + (labels[order[i, : (depth or 2 * size[i]) - 1]] == labels[i]).sum()) / size[i] for i in range(N)]
    return top1, float(np.mean(bull))


def _order_of(results, ids) -> np.ndarray:
    position = {i: n for n, i in enumerate(ids)}
    return np.array([[position[m.id] for m in found] for found in results])


def _order_of_matrix(D: np.ndarray) -> np.ndarray:
    X = D.astype(float).copy()
    np.fill_diagonal(X, np.inf)
    return np.argsort(X, axis=1, kind="stable")[:, : len(D) - 1]


def lcdp_parts(
    D: np.ndarray, k: int = 8, scale_k: int = 10, iterations: int = 6, sparse: int | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """The diffused similarity Q of :func:`lcdp` before any scaling, and the direct affinity
    (both (N, N) float64): Q starts from the dense affinity, or (``sparse=m``) from that of
    each curve's m nearest only, symmetrised, self 1."""
    X = D.astype(float).copy()
    np.fill_diagonal(X, np.inf)
    s = np.sort(X, axis=1)[:, :scale_k].mean(axis=1)
    W = np.exp(-(D**2) / np.maximum(s[:, None] * s[None, :], 1e-300))
    np.fill_diagonal(W, 1.0)
    W = (W + W.T) / 2
    direct = W.copy()
    if sparse:
        nearest = np.argsort(X, axis=1, kind="stable")[:, :sparse]
        graph = np.zeros_like(W)
        np.put_along_axis(graph, nearest, 1.0, axis=1)
        graph = np.maximum(graph, graph.T)
        np.fill_diagonal(graph, 1.0)
        W = W * graph
    P = W / W.sum(axis=1, keepdims=True)
    keep = np.argsort(-P, axis=1)[:, :k]
    Pk = np.zeros_like(P)
    np.put_along_axis(Pk, keep, np.take_along_axis(P, keep, axis=1), axis=1)
    Pk /= Pk.sum(axis=1, keepdims=True)
    Q = P
    for _ in range(iterations):
        Q = Pk @ Q @ Pk.T
    return Q, direct


def lcdp(
    D: np.ndarray,
    k: int = 8,
    scale_k: int = 10,
    iterations: int = 6,
    sparse: int | None = None,
    mix: float = 0.0,
) -> np.ndarray:
    """The locally constrained diffusion (Yang, Koknar-Tezel & Latecki 2009) of a full
    distance matrix (a measurement for the next step, not the library's): affinity
    exp(-d^2 / (s_i s_j)), s the mean distance to the 10 nearest others; self-affinity 1;
    P row-normalised, P_k its k largest per row renormalised; Q <- P_k Q P_k^T from Q = P,
    6 times. ``sparse=None`` is the prototype of docs/elastic.md (Q starts from the dense
    affinity). ``sparse=m`` starts from the affinity of each curve's m nearest only
    (symmetrised: what a stored graph holds), scales Q to a largest entry of 1 and mixes
    ``mix`` of the direct affinity in, as ``MIX`` does for the PageRank. Returns the
    similarity (N, N)."""
    Q, direct = lcdp_parts(D, k, scale_k, iterations, sparse)
    if not sparse:
        return Q
    return (1.0 - mix) * Q / Q.max() + mix * direct


def diffusion_rows(curves, labels, depth):
    """Diffusion on full matrices of the exact and of the fused distance: today's
    ``matrix --rerank`` (personalised PageRank) and LCDP (the benchmark's)."""
    from nfdmatch.search import distance_matrix
    from nfdmatch.search.rerank import diffused_similarity

    T = distance_matrix(curves)
    F = distance_matrix(curves, elastic=True)
    ids = [c.id for c in curves]
    rows = []
    for name, D in (("exact", T), ("fused", F)):
        rows.append(
            (
                f"matrix --rerank (PPR) on {name}",
                scores(_order_of_matrix(-diffused_similarity(D, ids=ids)), labels, depth),
            )
        )
        rows.append((f"LCDP on {name} (benchmark only)", scores(_order_of_matrix(-lcdp(D)), labels, depth)))
        rows.append(
            (
                f"LCDP from the 10-NN graph, 0.2 direct, on {name}",
                scores(_order_of_matrix(-lcdp(D, sparse=10, mix=0.2)), labels, depth),
            )
        )
    return rows


def rerank_rows(curves, labels, depth):
    """``query --rerank --exclude-self`` of every curve (the library's ``rerank_index``) on an
    index with an exact graph (``--graph 10``) and on one with a fused graph (``--graph 10
    --elastic``): rows with their seconds."""
    import tempfile

    from nfdmatch import build_index, open_index, write_curves
    from nfdmatch.index.graph import GraphSpec
    from nfdmatch.search.rerank import rerank_index

    rows, N = [], len(curves)
    with tempfile.TemporaryDirectory() as tmp:
        folder = os.path.join(tmp, "curves")
        os.makedirs(folder)
        stored = []
        for i, c in enumerate(curves):
            path = os.path.join(folder, f"{i:05d}.csv")
            write_curves(path, [Curve(np.asarray(c.points), id=path)])
            stored.append(Curve(np.asarray(c.points), id=path))
        for label, graph in (("exact graph 10", 10), ("--elastic graph 10", GraphSpec(10, "fused"))):
            index = os.path.join(tmp, "i.h5")
            if os.path.exists(index):
                os.remove(index)
            build_index([folder], index, graph=graph)
            with open_index(index) as idx:
                t = time.perf_counter()
                found, _ = rerank_index(idx, stored, k=min(40, len(curves) - 1), exclude_self=True)
                seconds = time.perf_counter() - t
                position = {os.path.basename(c.id): n for n, c in enumerate(stored)}
                order = np.array([[position[os.path.basename(m.id)] for m in f] for f in found])
            rows.append((f"query --rerank, {label}", scores(order, labels, depth), seconds))
            from nfdmatch.search import distance_matrix
            from nfdmatch.search.rerank import diffused_similarity, fused_graph_lists

            fused = graph != 10
            D = distance_matrix(stored, elastic=fused)
            ids = [c.id for c in stored]
            # --elastic: the lists of the graph the index stores (fused among exact candidates)
            lists = fused_graph_lists(distance_matrix(stored), D, ids) if fused else None
            S = diffused_similarity(D, ids=ids, lists=lists)
            np.fill_diagonal(S, -np.inf)
            # the matrix's order: score, then (below the score floor, where scores are 0) the
            # distance, then id (the files' order)
            want = np.array([np.lexsort((np.arange(N), D[i], -S[i])) for i in range(N)])[:, : order.shape[1]]
            place = float(np.mean(order == want))
            shared = float(np.mean([len(set(a) & set(b)) / len(a) for a, b in zip(order, want)]))
            what = "matrix --rerank --elastic" if fused else "matrix --rerank"
            print(
                f"  ({label}: the top {order.shape[1]} of {what}: the same set at {shared:.1%}, "
                f"the same curve at {place:.1%} of the places)"
            )
    return rows


def peer(curves, low_pass: bool) -> np.ndarray:
    """The issue's statistics descriptor: sorted PCA eigenvalues + 12-bin histograms of
    turning angle, binormal dihedral angle and distance to the centroid at 128 arc-length
    samples (optionally of the curve rebuilt from 16 harmonics)."""
    rows = []
    for c in curves:
        p = resample(np.asarray(c.points if isinstance(c, Curve) else c, dtype=float), 128)
        if low_pass:
            F = np.fft.fft(p, axis=0)
            F[17:-16] = 0
            p = np.real(np.fft.ifft(F, axis=0))
        p = p - p.mean(0)
        p = p / np.sqrt((p**2).sum(1).mean())
        ev = np.sort(np.linalg.eigvalsh(np.cov(p.T)))[::-1]
        t = np.roll(p, -1, 0) - p
        t /= np.maximum(np.linalg.norm(t, axis=1, keepdims=True), 1e-12)
        turn = np.arccos(np.clip((t * np.roll(t, 1, 0)).sum(1), -1, 1))
        b = np.cross(np.roll(t, 1, 0), t)
        b /= np.maximum(np.linalg.norm(b, axis=1, keepdims=True), 1e-12)
        dihedral = np.arccos(np.clip((b * np.roll(b, 1, 0)).sum(1), -1, 1))
        radius = np.linalg.norm(p, axis=1)
        h = [
            np.histogram(v, 12, range=r)[0] / 128
            for v, r in ((turn, (0, np.pi)), (dihedral, (0, np.pi)), (radius, (0, 3)))
        ]
        rows.append(np.concatenate([ev / ev.sum()] + h))
    X = np.array(rows)
    return np.linalg.norm(X[:, None] - X[None], axis=2)


def run_collection(name, curves, labels, depth, depths, diffusion=False, rerank=True):
    ids = [c.id for c in curves]
    N = len(curves)
    memory = MemoryIndex(curves)
    t = time.perf_counter()
    plain, _ = search_index(memory, curves, k=N - 1, exclude_self=True)
    plain_s = time.perf_counter() - t
    rows = [("plain (exact rigid)", scores(_order_of(plain, ids), labels, depth), plain_s)]
    for M in depths:
        m = N - 1 if M == "all" else int(M)
        t = time.perf_counter()
        top = min(40, N - 1)
        found, _ = search_index(memory, curves, k=top, exclude_self=True, stage=ElasticStage(depth=m))
        seconds = time.perf_counter() - t
        order = _order_of(found, ids)  # the first 40: every score here reads at most 22
        rows.append((f"--elastic --elastic-depth {M}", scores(order, labels, depth), seconds))
    C = descriptors_batch(curves).coefficients
    E = np.zeros((N, N))
    for i in range(N):
        r = exact_search(C[i], C, 128)
        E[i] = elastic_distances(C[i], C, r, 128)
    S = curve_statistics(C)
    St = np.array([statistics_distance(S[i], S) for i in range(N)])
    rows.append(("elastic term alone", scores(_order_of_matrix(E), labels, depth), None))
    rows.append(("statistics term alone", scores(_order_of_matrix(St), labels, depth), None))
    rows.append(
        ("peer: statistics descriptor, raw", scores(_order_of_matrix(peer(curves, False)), labels, depth), None)
    )
    rows.append(("peer: the same low-passed (16)", scores(_order_of_matrix(peer(curves, True)), labels, depth), None))
    size = np.array([(labels == c).sum() for c in labels])
    chance_top1 = float(np.mean((size - 1) / (N - 1)))
    chance_bull = float(np.mean([(1 + ((depth or 2 * s) - 1) * (s - 1) / (N - 1)) / s for s in size]))
    rows.append(("chance", (chance_top1, chance_bull), None))
    if rerank:
        rows += rerank_rows(curves, labels, depth)
    if diffusion:
        rows += [(what, figures, None) for what, figures in diffusion_rows(curves, labels, depth)]
    print(f"\n{name} ({N} curves)")
    for what, (top1, bull), seconds in rows:
        took = "" if seconds is None else f"{seconds:8.2f} s"
        print(f"  {what:40} top-1 {top1:.3f}  bull's-eye {bull:.3f} {took}")


def knots_check(data):
    """Each knotess control polygon, and re-posed, resampled, noisy copies of each smooth
    knot (:func:`knot_copy`), against the smooth knots, plain and with --elastic: top-1 (a
    hit: the knot itself or one of the same shape, as a link's two identical circles)."""
    names = sorted(f for f in os.listdir(os.path.join(data, "knotess_smooth")) if f.endswith(".csv"))
    smooth = _folder(os.path.join(data, "knotess_smooth"), names)
    control = _folder(os.path.join(data, "knotess_control"), names)
    memory = MemoryIndex(smooth)
    smooth_id = {os.path.basename(c.id): c.id for c in smooth}
    for label, stage in (("plain", None), ("--elastic", ElasticStage())):
        found, _ = search_index(memory, control, k=1, stage=stage)
        hits = sum(_same_knot(memory, f[0].id, smooth_id[os.path.basename(q.id)]) for f, q in zip(found, control))
        print(f"  knots control -> smooth, {label:10} top-1 {hits} / {len(control)}")
    for noise in (0.005, 0.01, 0.02):
        copies = [knot_copy(np.random.default_rng(seed), c, noise) for seed, c in enumerate(smooth)]
        for label, stage in (("plain", None), ("--elastic", ElasticStage())):
            found, _ = search_index(memory, copies, k=1, stage=stage)
            hits = sum(_same_knot(memory, f[0].id, q.id) for f, q in zip(found, copies))
            print(f"  knot copies (noise {noise:.3f}) -> smooth, {label:10} top-1 {hits} / {len(copies)}")


def knot_copy(rng, knot, noise: float):
    """A copy of a curve as another program would store it: resampled at 60-400 vertices
    spaced unevenly along the arc length, noise of ``noise`` x its RMS radius, rotated,
    scaled, moved, started elsewhere and, half the time, reversed."""
    from bench_search import _rotations

    points = np.asarray(knot.points, dtype=np.float64)
    closed = np.vstack([points, points[:1]])
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(closed, axis=0), axis=1))])
    vertices = int(rng.integers(60, 401))
    steps = rng.uniform(0.5, 1.5, vertices)
    at = np.concatenate([[0.0], np.cumsum(steps)[:-1]]) / steps.sum() * arc[-1]
    copy = np.stack([np.interp(at, arc, closed[:, d]) for d in range(3)], axis=1)
    rms = np.sqrt(((copy - copy.mean(axis=0)) ** 2).sum(axis=1).mean())
    copy += rng.normal(size=copy.shape) * noise * rms
    copy = np.roll(copy, int(rng.integers(vertices)), axis=0)
    if rng.random() < 0.5:
        copy = copy[::-1]
    copy = copy @ _rotations(rng, 1)[0].T * np.exp(rng.uniform(np.log(0.1), np.log(10.0))) + rng.uniform(-100, 100, 3)
    return Curve(copy, id=knot.id)


def _same_knot(memory, found: str, wanted: str) -> bool:
    """The copy found its own knot, or one of the same shape (a link's identical components)."""
    if os.path.basename(found) == os.path.basename(wanted):
        return True
    pair = [c for c in memory.curves if c.id in (found, wanted)]
    return len(pair) == 2 and nfdmatch_distance(pair[0], pair[1]).distance < 1e-3


def kernel_timing():
    """The elastic distance a pair: one pose (the compiled kernel) and the distance as the
    stage takes it (two poses, the other direction's searched: ``elastic_distances``)."""
    rng = np.random.default_rng(0)
    points, _ = families(rng, 4, 50, 3)
    C = descriptors_batch(points).coefficients
    r = exact_search(C[0], C, 128)
    from nfdmatch.matching.kernels import set_call_threads

    figures = {}
    for threads in (1, 2):
        set_call_threads(threads)  # 1: the "a pair on one core"
        for what, run in (
            ("one pose", lambda: elastic_rows(C[0], C, r["shift"], r["reversed"], r["mirrored"], 128)),
            ("both directions", lambda: elastic_distances(C[0], C, r, 128)),
        ):
            run()
            best = np.inf
            for _ in range(5):
                t = time.perf_counter()
                run()
                best = min(best, time.perf_counter() - t)
            figures[what, threads] = best / len(C) * 1e6
    set_call_threads(4)  # the process's default again
    t = time.perf_counter()
    curve_statistics(C)
    stats_s = time.perf_counter() - t
    for threads, label in ((1, "one thread"), (2, "rows split over two threads")):
        print(f"elastic distance, {label}: {figures['both directions', threads]:.1f} us a pair "
              f"({figures['one pose', threads]:.1f} at one pose; best of 5, {len(C)} rows)")  # fmt: skip
    print(f"statistics: {stats_s / len(C) * 1e6:.1f} us a curve (once per curve)")


def cli_timing(data, runs: int = 3):
    """``query FOLDER --index --exclude-self --top 40`` as whole CLI processes, plain against
    ``--elastic`` (M = 100), in turn, on an index of each folder (format 3: statistics
    stored): the median seconds of ``runs`` each and their ratio."""
    import subprocess
    import tempfile

    exe = os.path.join(os.path.dirname(sys.executable), "nfdmatch")
    folders = {
        "psb cut loops": os.path.join(data, "psb_dev", "cutloop", "curves"),
        "psb mid-sections": os.path.join(data, "psb_dev", "midsection", "curves"),
        "kimia99": os.path.join(data, "kimia99"),
    }
    print("\nCLI processes: query FOLDER --index I --exclude-self --top 40 (every curve a query), median of", runs)
    with tempfile.TemporaryDirectory() as tmp:
        for name, folder in folders.items():
            index = os.path.join(tmp, name.replace(" ", "_") + ".h5")
            subprocess.run([exe, "-q", "index", "build", folder, "--index", index, "--glob", "[!_]*.csv"], check=True)
            base = [exe, "query", folder, "--index", index, "--exclude-self", "--top", "40", "--glob", "[!_]*.csv"]
            base += ["--format", "csv", "-o", os.path.join(tmp, "out.csv")]
            times = {"plain": [], "elastic": []}
            for _ in range(runs):
                for label, extra in (("plain", []), ("elastic", ["--elastic"])):
                    t = time.perf_counter()
                    subprocess.run(base + extra, check=True)
                    times[label].append(time.perf_counter() - t)
            plain, elastic = (float(np.median(times[k])) for k in ("plain", "elastic"))
            print(f"  {name:18} plain {plain:6.2f} s   --elastic {elastic:6.2f} s   ratio {elastic / plain:.2f}x")


def elastic_graph_timing(curves: int, work: str | None = None):
    """``index build --graph 10`` against ``--graph 10 --elastic`` on ``curves`` generated
    curves (benchmarks/bench_index.py's families of 10, 2 workers), and single ``query
    --rerank`` on each (20 queries, the median)."""
    import tempfile

    import bench_index

    from nfdmatch import open_index, read_curves
    from nfdmatch.index import build_index
    from nfdmatch.index.graph import GraphSpec
    from nfdmatch.search.rerank import rerank_index

    with tempfile.TemporaryDirectory(dir=work) as tmp:
        folder = os.path.join(tmp, f"gen{curves}")
        queries = bench_index.generate(folder, curves)
        print(f"\n{curves} generated curves (families of 10), 2 workers")
        for label, graph in (("--graph 10", 10), ("--graph 10 --elastic", GraphSpec(10, "fused"))):
            path = os.path.join(tmp, "i.h5")
            if os.path.exists(path):
                os.remove(path)
            t = time.perf_counter()
            report = build_index([folder], path, jobs=2, graph=graph)
            total = time.perf_counter() - t
            with open_index(path) as idx:
                picked = [read_curves(q)[0] if isinstance(q, str) else q for q in queries[:20]]
                rerank_index(idx, picked[:1], k=10)
                seconds = []
                for q in picked:
                    t = time.perf_counter()
                    rerank_index(idx, [q], k=10)
                    seconds.append(time.perf_counter() - t)
            print(
                f"  index build {label:22} {total:7.1f} s (graph {report.graph.seconds:6.1f} s);"
                f" one query --rerank {np.median(seconds):.3f} s (median of {len(seconds)})"
            )


def constants(cols):
    """The fused distance's constants from the pooled development pairs."""
    from nfdmatch.matching.statistics import BLOCK_SCALES, BLOCK_SIZES, BLOCKS

    T, E, S, blocks = [], [], [], {b: [] for b in BLOCKS}
    for name, (curves, _, _) in cols.items():
        if name.startswith("bending"):
            continue
        C = descriptors_batch(curves).coefficients
        st = curve_statistics(C)
        upper = np.triu_indices(len(C), 1)
        for i in range(len(C)):
            r = exact_search(C[i], C[i + 1 :], 128)
            T.append(r["distance"])
            E.append(elastic_distances(C[i], C[i + 1 :], r, 128))
        at = 0
        for b, n in zip(BLOCKS, BLOCK_SIZES):
            X = st[:, at : at + n]
            blocks[b].append(np.abs(X[:, None] - X[None]).sum(2)[upper])
            at += n
        S.append(np.concatenate([statistics_distance(st[i], st[i + 1 :]) for i in range(len(C))]))
    recomputed = tuple(round(float(np.median(np.concatenate(blocks[b]))), 4) for b in BLOCKS)
    print("BLOCK_SCALES =", recomputed, "(recomputed; statistics.py ships the frozen", BLOCK_SCALES, ")")
    levels = np.linspace(0, 1, 17)
    for name, values in (("RIGID", T), ("ELASTIC", E), ("STATISTICS", S)):
        print(f"{name}_QUANTILES =", tuple(round(float(v), 4) for v in np.quantile(np.concatenate(values), levels)))


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", default=os.path.join(os.path.dirname(HERE), "..", "shared", "data"))
    parser.add_argument("--depths", default="100,all", help="elastic depths to report, comma-separated ('all')")
    parser.add_argument("--constants", action="store_true", help="print the fused distance's constants")
    parser.add_argument("--timing", action="store_true", help="only the CLI timing (plain against --elastic)")
    parser.add_argument("--diffusion", action="store_true", help="also diffusion on full matrices (PPR, LCDP)")
    parser.add_argument("--elastic-graph", type=int, default=0, metavar="N", help="only the elastic graph's timing")
    parser.add_argument("--only", default=None, help="only these collections (comma-separated names)")
    parser.add_argument(
        "--large", action="store_true", help="also 1,400 bending 2-D curves in 70 families of 20 (the held-out shape)"
    )
    args = parser.parse_args()
    if not os.path.isdir(args.data):
        sys.exit(f"no development data at {args.data}: give --data")
    if args.elastic_graph:
        elastic_graph_timing(args.elastic_graph)
        return
    if args.timing:
        cli_timing(args.data)
        kernel_timing()
        return
    cols = collections(args.data)
    if args.large:
        points, labels = families(np.random.default_rng(7), 70, 20, 2)
        cols["bending 2-D 70x20"] = ([Curve(p, id=f"large-{i:04d}") for i, p in enumerate(points)], labels, 40)
    if args.only:
        cols = {name: c for name, c in cols.items() if name in args.only.split(",")}
    if args.constants:
        constants(cols)
        return
    depths = args.depths.split(",")
    for name, (curves, labels, depth) in cols.items():
        run_collection(name, curves, labels, depth, depths, args.diffusion)
    print()
    knots_check(args.data)
    kernel_timing()
    cli_timing(args.data)


if __name__ == "__main__":
    main()
