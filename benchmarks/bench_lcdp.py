"""The locally constrained diffusion (LCDP) of one query, computed locally on the stored
graph, against the full-matrix version, and what it costs next to ``query --rerank``
(docs/elastic.md, "Not done yet": "Development evidence for the rigid graph's goal").

    python benchmarks/bench_lcdp.py [--data ../shared/data] [--only bending,psb,foreign,large]
                                     [--tolerances 1e-4,1e-3,1e-2] [--large-families 500]

A prototype, here only (no library change). The matrix version is
``bench_3d.lcdp(D, sparse=10, mix=0.2)``: s_i the mean distance to i's 10 nearest, W_ij =
exp(-D_ij^2 / (s_i s_j)) on the symmetrised 10-NN graph (self 1), P row-normalised, Pk its
8 largest per row (self included) renormalised, Q = Pk^6 P (Pk^6)^T, score = 0.8 Q / max Q
+ 0.2 exp(-D^2 / (s_i s_j)) (unrestricted). Ranked by score; a score below
:data:`FLOOR` counts 0 and those rows follow by exact distance (then row).

The local version of a stored curve q (left out of its answers) reads only the index's
stored graph (``index build --graph 10``: each row's 10 nearest and their distances, and
the lists turned round, through :class:`nfdmatch.search.diffusion.GraphWalk`'s readers):
``Q[q, :] = ((e_q Pk^6) P) (Pk^T)^6``, a sparse vector walked 6 steps forward along Pk, one
along P, 6 backward (``u'[j] = sum_b Pk[j, b] u[b]``: the j with b among their 8 heaviest,
all in b's symmetrised neighbourhood), after each step the entries below ``tolerance`` x the
vector's largest dropped. Q's largest entry is an index-wide constant: here the largest
diagonal entry ``Q[q, q] = a P a^T``, ``a = e_q Pk^6`` (the forward walk alone) of every
stored row, at the same tolerance (what a build would compute: N forward walks, timed),
checked against the matrix's Q.max() and the largest entry of the queries' local rows. The direct affinity needs the
exact distance of the rows ranked: candidates are the ``3 top`` rows of largest Q plus the
query's exact ``3 top`` nearest (the library's search), each given its exact distance from
the stored coefficients (``nfdmatch.matching.exact_search``). Other candidate rules, for
what they save: the Q rows plus the query's exact ``top`` nearest (the plain query's
answer), plus its graph row only, plus its graph row's rows (2 hops): no search.

Collections: (1) 1,400 bending 2-D curves, ``families(default_rng(7), 70, 20, 2)``
(bull's-eye over 40); (2) the psb_dev cut loops (over 20); (3) ``--only large``: 10,000
such curves (``--large-families 500``), every 10th a query (``--large-every``). The matrix
version's Q is computed row block by row block on the graph (exact, no pruning: the same
arithmetic, checked against ``bench_3d.lcdp`` on the first two), its direct affinity from
every exact distance of the queries' rows. ``--only foreign``: Q.max() of the matrix
version when the 1,400 share the index with foreign curves or with 12 copies of one curve.

Prints per collection and tolerance: the top-40 set agreement with the matrix (share of
entries, every stored curve a query) and the same place; top-1 and bull's-eye of both; the
support (nodes in the walk's vectors: the largest vector and all the nodes visited; the
graph rows one cold query reads); milliseconds per query of the local LCDP (warm batch: the
rows of P and Pk computed once per process; and cold single queries) against the library's
``rerank_index`` (``query --rerank --exclude-self --top 40``) and ``search_index`` of the
same queries as one batch.
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
sys.path.insert(0, HERE)
sys.path.insert(0, os.path.dirname(HERE))

from bench_3d import lcdp, lcdp_parts  # noqa: E402
from bending_families import families  # noqa: E402

from nfdmatch import Curve, build_index, open_index, read_curves, write_curves  # noqa: E402
from nfdmatch.matching import exact_search  # noqa: E402
from nfdmatch.search import search_index  # noqa: E402
from nfdmatch.search.diffusion import GraphWalk  # noqa: E402
from nfdmatch.search.rerank import rerank_index  # noqa: E402

#: the stored graph's neighbours (s_i: their mean distance; the symmetrised graph)
GRAPH_K = 10
#: Pk: each row's heaviest entries kept
KEEP = 8
#: steps forward (and backward) along Pk
STEPS = 6
#: weight of the direct affinity
MIX = 0.2
#: scores below count 0: those rows follow by exact distance
FLOOR = 1e-3
#: answers per query
TOP = 40
#: candidates per query: ``WIDE x TOP`` of largest Q, and as many exact nearest
WIDE = 3


# -- the graph, locally


class LocalLCDP:
    """The rows of P, Pk and Pk's in-edges, computed as a query's walk reaches them (each
    once per process: a batch reuses them), from the stored graph alone.

    Row u needs u's list, the lists naming u (the in-edges; their distance to u is in their
    own list) and the scale of each of those (their lists): its symmetrised neighbourhood.
    Pk's in-edges at b (the j with b among j's 8 heaviest) need the Pk rows of b's
    neighbourhood."""

    def __init__(self, index):
        self.N = index.n_curves
        self.walk = GraphWalk(index.graph_reader(), self.N, GRAPH_K, 0.8, index.graph_reverse_reader())
        N = self.N
        self.scale = np.full(N, np.nan)
        self.width = 32  # the padded rows' width (grown when a neighbourhood is wider)
        self.p_t = np.full((N, self.width), -1, np.int64)
        self.p_w = np.zeros((N, self.width))
        self.p_known = np.zeros(N, bool)
        self.k_t = np.full((N, KEEP), -1, np.int64)
        self.k_w = np.zeros((N, KEEP))
        self.r_t = np.full((N, self.width), -1, np.int64)
        self.r_w = np.zeros((N, self.width))
        self.r_known = np.zeros(N, bool)

    def _grow(self, width: int) -> None:
        if width <= self.width:
            return
        extra = width - self.width
        for name, fill in (("p_t", -1), ("p_w", 0.0), ("r_t", -1), ("r_w", 0.0)):
            a = getattr(self, name)
            setattr(self, name, np.pad(a, ((0, 0), (0, extra)), constant_values=fill))
        self.width = width

    def scales(self, nodes: np.ndarray) -> np.ndarray:
        new = nodes[np.isnan(self.scale[nodes])]
        if len(new):
            self.walk.ensure(new)
            d = self.walk._d[new]  # the stored lists' distances (inf pads)
            finite = np.isfinite(d)
            self.scale[new] = np.where(finite, d, 0).sum(1) / np.maximum(finite.sum(1), 1)
        return self.scale[nodes]

    def rows(self, nodes: np.ndarray) -> None:
        """P's and Pk's rows of ``nodes``."""
        U = np.unique(nodes[~self.p_known[nodes]])
        if not len(U):
            return
        walk = self.walk
        walk.ensure(U)
        nb, d = walk._nb[U], walk._d[U]
        real = nb >= 0
        counts, src = walk.in_edges(U)
        owner = np.repeat(U, counts)
        walk.ensure(src)
        hit = walk._nb[src] == owner[:, None]
        d_in = walk._d[src][np.arange(len(src)), hit.argmax(1)]
        u = np.concatenate([np.repeat(U, GRAPH_K)[real.ravel()], owner, U])
        v = np.concatenate([nb[real], src, U])
        dd = np.concatenate([d[real], d_in, np.zeros(len(U))])
        s = self.scales(np.unique(v))  # (v holds U)
        s_u, s_v = self.scale[u], self.scale[v]
        del s
        w = np.exp(-(dd**2) / np.maximum(s_u * s_v, 1e-300))
        w[u == v] = 1.0
        # a mutual pair twice (each list's distance): their mean, as the matrix's (W + W^T) / 2
        key = u * self.N + v
        order = np.argsort(key, kind="stable")
        key, w = key[order], w[order]
        first = np.ones(len(key), bool)
        first[1:] = key[1:] != key[:-1]
        starts = np.flatnonzero(first)
        w = np.add.reduceat(w, starts) / np.diff(np.append(starts, len(key)))
        u, v = np.divmod(key[starts], self.N)
        # u ascending (keys sorted), within it v ascending
        row_start = np.searchsorted(u, U)
        size = np.diff(np.append(row_start, len(u)))
        self._grow(int(size.max()))
        total = np.add.reduceat(w, row_start)
        p = w / np.repeat(total, size)
        col = np.arange(len(u)) - np.repeat(row_start, size)
        self.p_t[U] = -1
        self.p_w[U] = 0.0
        at = np.repeat(U, size)
        self.p_t[at, col], self.p_w[at, col] = v, p
        # Pk: the KEEP largest of each row (ties: the lower column, i.e. row), renormalised
        pw = np.where(self.p_t[U] >= 0, self.p_w[U], -1.0)
        keep = np.argsort(-pw, axis=1, kind="stable")[:, :KEEP]
        kt, kw = np.take_along_axis(self.p_t[U], keep, 1), np.take_along_axis(pw, keep, 1)
        kw = np.where(kt >= 0, kw, 0.0)
        self.k_t[U], self.k_w[U] = kt, kw / kw.sum(1, keepdims=True)
        self.p_known[U] = True

    def reverse(self, nodes: np.ndarray) -> None:
        """Pk's in-edges at ``nodes``: (j, Pk[j, b]) for the j with b among j's KEEP."""
        B = np.unique(nodes[~self.r_known[nodes]])
        if not len(B):
            return
        self.rows(B)
        self.rows(self.p_t[B][self.p_t[B] >= 0])
        nbr = self.p_t[B]  # b's neighbourhood (b included)
        safe = np.where(nbr >= 0, nbr, 0)
        w = (self.k_w[safe] * (self.k_t[safe] == B[:, None, None])).sum(2)  # Pk[j, b]
        w = np.where(nbr >= 0, w, 0.0)
        self.r_t[B] = np.where(w > 0, nbr, -1)
        self.r_w[B] = w
        self.r_known[B] = True

    def _step(self, nodes, values, targets, weights, tolerance, seen):
        t, w = targets[nodes], weights[nodes] * values[:, None]
        real = t >= 0
        t, w = t[real], w[real]
        dense = np.bincount(t, weights=w, minlength=self.N)
        out = np.flatnonzero(dense)
        vals = dense[out]
        keep = vals >= tolerance * vals.max()
        seen.append(out)
        return out[keep], vals[keep]

    def query(self, q: int, tolerance: float) -> tuple[np.ndarray, np.ndarray, int, int]:
        """Q[q, :] as (nodes ascending, values), the largest vector's size and the nodes
        visited (in any of the vectors)."""
        nodes, values, seen = np.array([q]), np.ones(1), [np.array([q])]
        for _ in range(STEPS):
            self.rows(nodes)
            nodes, values = self._step(nodes, values, self.k_t, self.k_w, tolerance, seen)
        self.rows(nodes)
        nodes, values = self._step(nodes, values, self.p_t, self.p_w, tolerance, seen)
        for _ in range(STEPS):
            self.reverse(nodes)
            nodes, values = self._step(nodes, values, self.r_t, self.r_w, tolerance, seen)
        largest = max(len(s) for s in seen)
        visited = len(np.unique(np.concatenate(seen)))
        return nodes, values, largest, visited


# -- the matrix version


def _sparse(targets: np.ndarray, weights: np.ndarray):
    """The sparse (N, N) matrix of rows ``targets`` / ``weights`` (padded -1), by column."""
    src, col = np.nonzero(targets >= 0)
    dst, w = targets[src, col], weights[src, col]
    order = np.argsort(dst, kind="stable")
    src, dst, w = src[order], dst[order], w[order]
    starts = np.flatnonzero(np.r_[True, dst[1:] != dst[:-1]])
    return src, dst[starts], starts, w


def _spread(X: np.ndarray, matrix) -> np.ndarray:
    """X (b, N) times a :func:`_sparse` matrix."""
    src, cols, starts, w = matrix
    out = np.zeros(X.shape)
    out[:, cols] = np.add.reduceat(X[:, src] * w, starts, axis=1)
    return out


def _q_block(matrices, N: int, rows: np.ndarray) -> np.ndarray:
    """Q's rows ``rows``, exactly; ``matrices``: Pk, P and Pk^T as :func:`_sparse` gives them."""
    pk, p, back = matrices
    X = np.zeros((len(rows), N))
    X[np.arange(len(rows)), rows] = 1.0
    for _ in range(STEPS):
        X = _spread(X, pk)
    X = _spread(X, p)
    for _ in range(STEPS):
        X = _spread(X, back)
    return X


def exact_rows(C: np.ndarray, samples: int, rows: np.ndarray) -> np.ndarray:
    return np.array([exact_search(C[i], C, samples)["distance"] for i in rows])


def ranked(score: np.ndarray, dist: np.ndarray, cols: np.ndarray, top: int) -> np.ndarray:
    """The first ``top`` of ``cols`` by floored score, then exact distance, then row."""
    s = np.where(score >= FLOOR, score, 0.0)
    return cols[np.lexsort((cols, dist, -s))[:top]]


def reference(local: LocalLCDP, queries: np.ndarray, s: np.ndarray, top: int, D: np.ndarray, block: int = 50):
    """The matrix version's top ``top`` of each of ``queries`` (every other row ranked; ``D``
    their rows of exact distances), Q computed row block by row block on the graph (exact:
    no pruning); and Q's largest entry and largest diagonal entry over every row."""
    N = local.N
    every = np.arange(N)
    local.rows(every)
    local.reverse(every)
    matrices = [_sparse(t, w) for t, w in ((local.k_t, local.k_w), (local.p_t, local.p_w), (local.r_t, local.r_w))]
    q_max, diag_max, kept = 0.0, 0.0, {}
    wanted = set(queries.tolist())
    for a in range(0, N, block):
        rows = every[a : a + block]
        X = _q_block(matrices, N, rows)
        q_max = max(q_max, float(X.max()))
        diag_max = max(diag_max, float(X[np.arange(len(rows)), rows].max()))
        for n, i in enumerate(rows.tolist()):
            if i in wanted:
                kept[i] = X[n]
    want = np.empty((len(queries), top), np.int64)
    for n, i in enumerate(queries.tolist()):
        S = (1 - MIX) * kept[i] / q_max + MIX * np.exp(-(D[n] ** 2) / np.maximum(s[i] * s, 1e-300))
        cols = np.delete(every, i)
        want[n] = ranked(S[cols], D[n][cols], cols, top)
    return want, q_max, diag_max


def diagonal(local: LocalLCDP, q: int, tolerance: float) -> float:
    """Q[q, q] = a P a^T, a = e_q Pk^6: the forward walk alone (what a build would compute
    for every row to find Q's largest entry, when it is on the diagonal)."""
    nodes, values, seen = np.array([q]), np.ones(1), []
    for _ in range(STEPS):
        local.rows(nodes)
        nodes, values = local._step(nodes, values, local.k_t, local.k_w, tolerance, seen)
    local.rows(nodes)
    a = np.zeros(local.N)
    a[nodes] = values
    t, w = local.p_t[nodes], local.p_w[nodes]
    return float((values[:, None] * np.where(t >= 0, w * a[np.maximum(t, 0)], 0.0)).sum())


# -- the collections


def bending(count: int):
    points, labels = families(np.random.default_rng(7), count, 20, 2)
    return [Curve(p, id=f"large-{i:04d}") for i, p in enumerate(points)], np.asarray(labels)


def psb_cutloops(data: str):
    folder = os.path.join(data, "psb_dev", "cutloop")
    with open(os.path.join(folder, "labels.csv")) as fh:
        rows = list(csv.DictReader(fh))
    curves = [read_curves(os.path.join(folder, "curves", r["file"]))[0] for r in rows]
    curves = [Curve(np.asarray(c.points), id=f"psb-{i:04d}") for i, c in enumerate(curves)]
    return curves, np.array([r["class"] for r in rows])


def indexed(curves, work: str):
    """One CSV a curve (named by its id), an index with ``--graph 10``; returns the index's
    path, the stored curves as queries (in the index's row order) and each row's position in
    ``curves``."""
    folder = os.path.join(work, "curves")
    os.makedirs(folder)
    for c in curves:
        write_curves(os.path.join(folder, c.id + ".csv"), [c])
    path = os.path.join(work, "i.h5")
    build_index([folder], path, graph=GRAPH_K, jobs=2)
    position = {c.id: n for n, c in enumerate(curves)}
    with open_index(path) as idx:
        ids = idx.ids_at(np.arange(idx.n_curves))
    names = [os.path.splitext(os.path.basename(i.split("#")[0]))[0] for i in ids]
    queries = [read_curves(os.path.join(folder, n + ".csv"))[0] for n in names]
    return path, queries, np.array([position[n] for n in names])


def figures(order: np.ndarray, labels: np.ndarray, depth: int, queries: np.ndarray) -> tuple[float, float]:
    """(top-1, bull's-eye) of the rankings ``order`` of ``queries`` (bench_3d.scores' rule)."""
    size = {c: int((labels == c).sum()) for c in set(labels.tolist())}
    mine = labels[queries]
    top1 = float(np.mean(labels[order[:, 0]] == mine))
    bull = [(1 + (labels[o[: depth - 1]] == c).sum()) / size[c] for o, c in zip(order, mine.tolist())]
    return top1, float(np.mean(bull))


def _time(fn):
    t = time.perf_counter()
    out = fn()
    return time.perf_counter() - t, out


def _agree(got: np.ndarray, want: np.ndarray, top: int) -> str:
    share = np.mean([len(set(a) & set(b)) / top for a, b in zip(got, want)])
    full = float(np.mean([len(set(a) & set(b)) == top for a, b in zip(got, want)]))
    return f"top-{top} set {share:.2%} (every entry in {full:.1%} of queries; same place {np.mean(got == want):.1%})"


def run(name: str, curves, labels, depth: int, tolerances, work: str, every: int = 1):
    N = len(curves)
    t = time.perf_counter()
    path, stored, pos = indexed(curves, work)
    labels = labels[pos]  # in the index's row order from here on
    qs = np.arange(0, N, every)
    queries = [stored[q] for q in qs]
    top = min(TOP, N - 1)
    print(f"\n## {name}: {N} curves, {len(qs)} of them queries, bull's-eye over {depth}, top {top}", flush=True)
    print(f"index build --graph {GRAPH_K}: {time.perf_counter() - t:.1f} s", flush=True)
    with open_index(path) as idx:
        samples = idx.samples
        C = idx.coefficients_at(np.arange(N))
        # -- the matrix version
        t = time.perf_counter()
        ref_local = LocalLCDP(idx)
        s = ref_local.scales(np.arange(N))
        nb = ref_local.walk._nb[:N].copy()
        D = exact_rows(C, samples, qs)
        D[np.arange(len(qs)), qs] = 0.0
        want, q_max, diag_max = reference(ref_local, qs, s, top, D)
        if len(qs) == N and N <= 3000:
            # the graph is the matrix's 10-NN (ties aside) and the arithmetic bench_3d's
            X = D.copy()
            np.fill_diagonal(X, np.inf)
            order = np.argsort(X, 1, kind="stable")
            same_lists = float(np.mean(np.sort(order[:, :GRAPH_K], 1) == np.sort(nb, 1)))
            S3 = lcdp(D, sparse=GRAPH_K, mix=MIX)
            check = np.empty_like(want)
            for n, i in enumerate(qs):
                cols = np.delete(np.arange(N), i)
                check[n] = ranked(S3[i, cols], D[i, cols], cols, top)
            print(
                f"matrix: the graph's lists are D's 10 nearest at {same_lists:.2%} of entries; the graph-computed "
                f"matrix ranks as bench_3d.lcdp(D, sparse=10, mix=0.2) at {np.mean(check == want):.2%} of places",
                flush=True,
            )
            del S3, X
        del D
        on_diag = "yes" if np.isclose(diag_max, q_max) else f"no (diagonal's largest {diag_max:.4g})"
        print(f"matrix: Q.max() {q_max:.4g}, on the diagonal: {on_diag} ({time.perf_counter() - t:.1f} s)")
        del ref_local
        ref = figures(want, labels, depth, qs)
        print(f"matrix LCDP                           top-1 {ref[0]:.3f}  bull's-eye {ref[1]:.3f}")

        # -- the library: plain and --rerank, the same queries as one batch (best of 2)
        lib = {}
        for label, fn in (
            ("plain", lambda: search_index(idx, queries, k=top, exclude_self=True)),
            ("nearest", lambda: search_index(idx, queries, k=WIDE * top, exclude_self=True)),
            ("rerank", lambda: rerank_index(idx, queries, k=top, exclude_self=True)),
        ):
            runs = [_time(fn) for _ in range(2)]
            lib[label] = (min(r[0] for r in runs) / len(qs) * 1e3, runs[-1][1][0])
        for label in ("plain", "rerank"):
            order = np.array([[m.row for m in f] for f in lib[label][1]])
            sc = figures(order, labels, depth, qs)
            what = "query --rerank" if label == "rerank" else "query (plain)"
            print(
                f"library {what:29} top-1 {sc[0]:.3f}  bull's-eye {sc[1]:.3f}  {lib[label][0]:7.2f} ms a query "
                f"(batch of {len(qs)}; its top-40 set as the matrix LCDP's: "
                f"{np.mean([len(set(a) & set(b)) / top for a, b in zip(order, want)]):.1%})"
            )
        nearest = [np.array([m.row for m in f]) for f in lib["nearest"][1]]
        plain = [np.array([m.row for m in f]) for f in lib["plain"][1]]

        # -- the local version
        for tol in tolerances:
            local = LocalLCDP(idx)
            t = time.perf_counter()
            diag = [diagonal(local, q, tol) for q in range(N)]
            diag_s = time.perf_counter() - t
            local_max = max(diag)
            t = time.perf_counter()
            walked = [local.query(int(q), tol) for q in qs]
            walk_ms = (time.perf_counter() - t) / len(qs) * 1e3
            full_max = max(float(v.max()) for _, v, _, _ in walked)
            variants = {
                "+ exact 3 x top nearest": [],
                "+ exact top nearest": [],
                "walk + graph row": [],
                "walk + 2-hop graph rows": [],
            }
            spent = dict.fromkeys(variants, 0.0)
            for n, (q, (node, value, _, _)) in enumerate(zip(qs.tolist(), walked)):
                other = node != q
                node, value = node[other], value[other]
                by_q = node[np.lexsort((node, -value))[: WIDE * top]]
                row = local.p_t[q][local.p_t[q] >= 0]  # the symmetrised neighbourhood
                two = local.p_t[row][local.p_t[row] >= 0] if local.p_known[row].all() else row
                for label, extra in zip(variants, (nearest[n], plain[n], nb[q][nb[q] >= 0], two)):
                    t = time.perf_counter()
                    cand = np.unique(np.concatenate([by_q, extra]))
                    cand = cand[cand != q]
                    d = exact_search(C[q], C[cand], samples)["distance"]
                    qv = np.zeros(len(cand))
                    at = np.minimum(np.searchsorted(node, cand), max(len(node) - 1, 0))
                    hit = node[at] == cand if len(node) else np.zeros(len(cand), bool)
                    qv[hit] = value[at[hit]]
                    direct = np.exp(-(d**2) / np.maximum(s[q] * s[cand], 1e-300))
                    variants[label].append(ranked((1 - MIX) * qv / local_max + MIX * direct, d, cand, top))
                    spent[label] += time.perf_counter() - t
            largest = np.array([w[2] for w in walked])
            visited = np.array([w[3] for w in walked])
            print(
                f"\ntolerance {tol:.0e} (entries below it x the vector's largest dropped after each step)\n"
                f"  Q.max(): the largest of the {N} diagonal entries by forward walks {local_max:.6g}, of the local "
                f"rows {full_max:.6g}, the matrix's {q_max:.6g}; the {N} forward walks {diag_s:.1f} s; the diagonal's "
                f"median / 1% / 99% {np.median(diag) / local_max:.2f} / {np.quantile(diag, 0.01) / local_max:.2f} / "
                f"{np.quantile(diag, 0.99) / local_max:.2f} of its largest\n"
                f"  support: largest vector mean {largest.mean():.0f} / max {largest.max()}, nodes visited mean "
                f"{visited.mean():.0f} / max {visited.max()}"
            )
            for label, rows in variants.items():
                got = np.array([np.pad(r, (0, top - len(r)), constant_values=-1) for r in rows])
                sc = figures(got, labels, depth, qs)
                extra = {"+ exact 3": lib["nearest"][0], "+ exact t": lib["plain"][0]}.get(label[:9], 0.0)
                ms = walk_ms + spent[label] / len(qs) * 1e3 + extra
                print(
                    f"  local, {label:24} {_agree(got, want, top)}  top-1 {sc[0]:.3f}  bull's-eye {sc[1]:.3f}  "
                    f"{ms:6.2f} ms a query (walk {walk_ms:.2f} + distances {spent[label] / len(qs) * 1e3:.2f}"
                    + (f" + the library's search {extra:.2f})" if extra else ")")
                )
            cold = []
            for q in qs[np.linspace(0, len(qs) - 1, 20).astype(int)]:
                fresh = LocalLCDP(idx)
                t = time.perf_counter()
                fresh.query(int(q), tol)
                cold.append((time.perf_counter() - t, fresh.walk.rows_read))
            print(
                f"  cold single query (a fresh walk, 20 queries): walk {np.median([c[0] for c in cold]) * 1e3:.1f} ms "
                f"median, graph rows read {np.median([c[1] for c in cold]):.0f} median / {max(c[1] for c in cold)} max"
            )
        print(
            f"library, batch of {len(qs)}: query --rerank {lib['rerank'][0]:.2f} ms a query, plain {lib['plain'][0]:.2f}"
        )
        picked = [queries[n] for n in np.linspace(0, len(qs) - 1, 20).astype(int)]
        single = [_time(lambda: rerank_index(idx, [q], k=top, exclude_self=True))[0] for q in picked]
        plain1 = [_time(lambda: search_index(idx, [q], k=top, exclude_self=True))[0] for q in picked]
        print(
            f"library, single queries: --rerank {np.median(single) * 1e3:.1f} ms, plain {np.median(plain1) * 1e3:.1f} "
            "ms (medians of 20)"
        )


def dense_q(D: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``bench_3d.lcdp(D, sparse=10)``'s Q (before its scaling) and the direct affinity."""
    return lcdp_parts(D, KEEP, GRAPH_K, STEPS, sparse=GRAPH_K)


def foreign(data: str):
    """Q.max() against what an index may hold besides the 1,400 (matrix version): foreign
    curves (a circle, an ellipse, a five-lobed star, the first psb cut loops) and 12 copies
    of one curve (1e-8 apart, as a mesh's duplicate sections): Q.max() and where it is,
    and the 1,400's rankings (among themselves) against those without."""
    from bench_3d import scores

    from nfdmatch.descriptors import descriptors_batch

    curves, labels = bending(70)
    t = np.linspace(0, 2 * np.pi, 200, endpoint=False)
    lobes = 1 + 0.3 * np.cos(5 * t)
    extra = [Curve(np.c_[np.cos(t), np.sin(t)]), Curve(np.c_[np.cos(t), 0.3 * np.sin(t)])]
    extra.append(Curve(np.c_[np.cos(t) * lobes, np.sin(t) * lobes]))
    folder = os.path.join(data, "psb_dev", "cutloop", "curves")
    extra += [read_curves(os.path.join(folder, f))[0] for f in sorted(os.listdir(folder))[:3]]
    C = descriptors_batch(curves + extra).coefficients
    N = len(curves)
    print("\n## Q.max() and the scale of the mix: the 1,400 with other curves (matrix version)", flush=True)
    D0 = exact_rows(C, 128, np.arange(len(C)))
    D0 = (D0 + D0.T) / 2
    np.fill_diagonal(D0, 0.0)
    rng = np.random.default_rng(1)
    base = None
    for what, m, copies in (("alone", 0, 0), ("+ 3 foreign", 3, 0), ("+ 6 foreign", 6, 0), ("+ 12 copies", 0, 12)):
        M = N + m + copies
        D = np.zeros((M, M))
        D[: N + m, : N + m] = D0[: N + m, : N + m]
        if copies:  # copies of row 0, 1e-8 apart from it and each other
            D[N:, :N] = D0[0, :N]
            D[:N, N:] = D0[:N, 0][:, None]
            e = rng.uniform(0.5, 1.5, (copies + 1, copies + 1)) * 1e-8
            near = np.r_[0, np.arange(N, M)]
            D[np.ix_(near, near)] = (e + e.T) / 2
            np.fill_diagonal(D, 0.0)
        Q, direct = dense_q(D)
        S = (1 - MIX) * Q / Q.max() + MIX * direct
        order = np.empty((N, TOP), np.int64)
        for i in range(N):
            cols = np.delete(np.arange(N), i)
            order[i] = ranked(S[i, cols], D[i, cols], cols, TOP)
        base = order if base is None else base
        sc = scores(order, labels, 40)
        diag = np.diag(Q)[:N]
        print(
            f"  {what:12} Q.max() {Q.max():.4f} at row {Q.argmax() // M} (on the diagonal: "
            f"{'yes' if np.isclose(np.diag(Q).max(), Q.max()) else 'no'}); the 1,400's diagonal median "
            f"{np.median(diag) / Q.max():.2f} of it; their top-1 {sc[0]:.3f} bull's-eye {sc[1]:.3f}, top-40 sets "
            f"as alone {np.mean([len(set(a) & set(b)) / TOP for a, b in zip(order, base)]):.2%}",
            flush=True,
        )


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", default=os.path.join(os.path.dirname(HERE), "..", "shared", "data"))
    parser.add_argument("--only", default="bending,psb", help="bending, psb, foreign, large (comma-separated)")
    parser.add_argument("--tolerances", default="1e-4,1e-3,1e-2")
    parser.add_argument("--large-every", type=int, default=10, help="in 'large', every n-th curve a query")
    parser.add_argument("--large-families", type=int, default=500, help="families of 20 in 'large'")
    args = parser.parse_args()
    tolerances = [float(t) for t in args.tolerances.split(",")]
    only = args.only.split(",")
    work = tempfile.mkdtemp(prefix="bench-lcdp-")
    try:
        if "bending" in only:
            curves, labels = bending(70)
            run("bending 2-D, 70 x 20", curves, labels, 40, tolerances, os.path.join(work, "bending"))
        if "psb" in only:
            curves, labels = psb_cutloops(os.path.join(args.data))
            run("psb_dev cut loops", curves, labels, 20, tolerances, os.path.join(work, "psb"))
        if "foreign" in only:
            foreign(args.data)
        if "large" in only:
            curves, labels = bending(args.large_families)
            name = f"bending 2-D, {args.large_families} x 20"
            run(name, curves, labels, 40, tolerances, os.path.join(work, "large"), every=args.large_every)
    finally:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
