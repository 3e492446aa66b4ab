"""Objects by their curves: every mesh of a labelled folder a query against the others.

    python benchmarks/bench_objects.py [--data ../shared/data/psb_dev/meshes] [--jobs 2]
                                       [--no-table] [--no-baselines] [--no-terms] [--scale 100000]
                                       [--file-scale 100000 [--keep DIR]]

For the folder's meshes (``labels.csv``: ``file,class``), as a user runs it:

1. ``nfdmatch index build MESHES --index TMP.h5 --jobs J`` (timed);
2. ``nfdmatch query MESHES --index TMP.h5 --exclude-self --top M-1 --format csv`` (timed);

then top-1 and bull's-eye (same class among the 20 nearest, the query counted first, as the
Princeton benchmark counts it: ``(hits among the 19 nearest others + 1) / class size``).
Beside it, the issue's baselines, computed here and not in the library:

* ``xyz-pooled``: each mesh cut by ``extract --sections 5`` along x, y and z, every loop of
  every mesh in one exact distance matrix, the set distance mean over A's loops of the
  nearest of B's, averaged with the same from B;
* ``D2`` (Osada et al. 2001): 4,096 seeded surface samples, 200,000 random pairs, distances
  over their mean, a 64-bin histogram on [0, 3], L1.

and each term's share (``--no-terms`` skips it): retrieval by the shape, size and profile
terms alone (library ablations of :func:`nfdmatch.search.objects.object_distances`), and the
mean share of the curves' and the profile's parts in the object distance.

``--scale M`` (0: skipped) times the pruned object search (:func:`nfdmatch.search.objects.
nearest_objects`, k = 10) on M generated objects in memory: copies of the folder's cut
objects with each loop's relative size moved by N(0, 0.2) in log and each profile number by
a factor in [0.7, 1.3], their invariant features given (as an index stores them); a few
meshes of the folder are the queries. It reports seconds per query after the first (which
makes the per-object tables once) and how many objects needed the loops' bounds and the
exact distance.

``--file-scale M`` (0: skipped) does the same through an index file, as a user's query
reads it: ``index build`` (:func:`nfdmatch.index.build_index`, the real writer: ``/curves``,
``/files``, ``/objects``, ``/search``) of M small stand-in files ``generated/gNNN/oNNNNNN.ply``
whose results are given by a ``runner`` (build_index's hook for computing files elsewhere):
the folder's objects as the build's workers cut them, copied with the same perturbations
(cutting 100,000 real meshes would take hours). Then ``nfdmatch query MESH --index FILE
--top 10`` of a few folder meshes, each in a new process, cold (the file evicted from the
page cache first, ``posix_fadvise``) and warm, and in one process the open of the index
apart from each query (``Index.search_objects``, the median). ``--keep DIR`` builds the index
there (kept, and reused when it is there) instead of a temporary folder.

The Princeton segmentation meshes are research data, not shipped: the benchmark says so
and stops when the folder is absent.
"""

from __future__ import annotations

import argparse
import csv
import io
import os
import subprocess
import sys
import tempfile
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
DEFAULT_DATA = os.path.normpath(os.path.join(HERE, "..", "..", "shared", "data", "psb_dev", "meshes"))
NFDMATCH = [sys.executable, "-m", "nfdmatch"]


def labels_of(folder: str) -> dict:
    with open(os.path.join(folder, "labels.csv"), newline="") as f:
        return {row["file"]: row["class"] for row in csv.DictReader(f)}


def scores(names: list, classes: dict, ranked: dict) -> tuple[float, float]:
    """Top-1 and bull's-eye from each query's ranked other names."""
    top1, bulls = [], []
    for n in names:
        answers = ranked[n]
        size = sum(1 for m in names if classes[m] == classes[n])
        top1.append(bool(answers) and classes[answers[0]] == classes[n])
        bulls.append((sum(classes[m] == classes[n] for m in answers[:19]) + 1) / size)
    return float(np.mean(top1)), float(np.mean(bulls))


def ranked_from_matrix(names: list, D: np.ndarray) -> dict:
    """Each name's others by increasing distance (ties by name)."""
    out = {}
    for i, n in enumerate(names):
        order = sorted((j for j in range(len(names)) if j != i), key=lambda j: (D[i, j], names[j]))
        out[n] = [names[j] for j in order]
    return out


def tool(folder: str, names: list, jobs: int) -> tuple[dict, float, float]:
    """The CLI's build and query: ``(ranked, build seconds, query seconds)``."""
    paths = [os.path.join(folder, n) for n in names]
    with tempfile.TemporaryDirectory() as tmp:
        index = os.path.join(tmp, "objects.h5")
        t0 = time.perf_counter()
        subprocess.run(NFDMATCH + ["-q", "index", "build", *paths, "--index", index, "--jobs", str(jobs)], check=True)
        t1 = time.perf_counter()
        out = subprocess.run(
            NFDMATCH + ["-q", "query", *paths, "--index", index, "--exclude-self", "--top", str(len(names) - 1)]
            + ["--format", "csv"],
            check=True, capture_output=True, text=True,
        ).stdout  # fmt: skip
        t2 = time.perf_counter()
    ranked: dict = {n: [] for n in names}
    for row in csv.DictReader(io.StringIO(out)):
        ranked[os.path.basename(row["query"])].append(os.path.basename(row["match"]))
    return ranked, t1 - t0, t2 - t1


def xyz_pooled(folder: str, names: list, jobs: int) -> np.ndarray:
    """The issue's first baseline: sections along x, y, z pooled, mean-of-nearest set distance."""
    from nfdmatch.mesh import extract_contours
    from nfdmatch.search.matrix import distance_matrix

    loops, owner = [], []
    for k, n in enumerate(names):
        for axis in "xyz":
            for c in extract_contours(os.path.join(folder, n), sections=5, axis=axis).contours:
                loops.append(c.points)
                owner.append(k)
    owner = np.asarray(owner)
    D = distance_matrix(loops, processes=jobs)
    starts = np.flatnonzero(np.r_[True, owner[1:] != owner[:-1]])
    row_min = np.minimum.reduceat(D, starts, axis=1)  # (loops, meshes)
    counts = np.diff(np.r_[starts, len(owner)])
    mean_nearest = np.add.reduceat(row_min, starts, axis=0) / counts[:, None]  # (meshes, meshes)
    return 0.5 * (mean_nearest + mean_nearest.T)


def d2(folder: str, names: list, seed: int = 0) -> np.ndarray:
    """Osada et al. 2001's D2 shape distribution, L1 between histograms."""
    import trimesh

    hists = []
    for k, n in enumerate(names):
        mesh = trimesh.load(os.path.join(folder, n), process=False)
        rng = np.random.default_rng(seed + k)
        points, _ = trimesh.sample.sample_surface(mesh, 4096, seed=int(rng.integers(1 << 31)))
        i, j = rng.integers(0, len(points), (2, 200_000))
        d = np.linalg.norm(points[i] - points[j], axis=1)
        h, _ = np.histogram(d / d.mean(), bins=64, range=(0.0, 3.0))
        hists.append(h / h.sum())
    H = np.array(hists)
    return np.abs(H[:, None, :] - H[None, :, :]).sum(axis=2)


def terms(folder: str, names: list, jobs: int) -> list:
    """Retrieval by each term alone and the curves' and profile's shares: library ablations."""
    from nfdmatch.mesh.objects import cut_object
    from nfdmatch.search.object_distance import SIZE_WEIGHT, object_distances, object_loops

    loops = object_loops([cut_object(os.path.join(folder, n)) for n in names], 128, 16, "rms")
    runs = {
        "shape alone (exact distance, levels, perimeter weights)": dict(weights=(1, 0), loop=(1, 0)),
        "size alone (delta log relative perimeter)": dict(weights=(1, 0), loop=(0, SIZE_WEIGHT)),
        "profile alone": dict(weights=(0, 1), loop=(0, SIZE_WEIGHT)),
        "shape + size (no profile)": dict(weights=(1, 0)),
        "object distance (shape + size + profile)": dict(),
    }
    out = []
    for name, kw in runs.items():
        found = object_distances(loops, loops, 128, processes=jobs, **kw)
        share = None
        if not kw:
            off = ~np.eye(len(names), dtype=bool)
            share = float(np.mean(found.curves[off] / np.maximum(found.distance[off], 1e-300)))
        out.append((name, found.distance, share))
    return out


def scale(folder: str, names: list, objects_wanted: int, jobs: int) -> None:
    """The pruned object search on ``objects_wanted`` generated objects (module doc)."""
    from nfdmatch.mesh.objects import cut_object
    from nfdmatch.search import objects as module
    from nfdmatch.search.bounds import feature_vector, squared_norms

    t0 = time.perf_counter()
    base = module.object_loops([cut_object(os.path.join(folder, n)) for n in names], 128, 16, "rms")
    rep = -(-objects_wanted // base.n_objects)
    rng = np.random.default_rng(0)
    L, M = len(base.owner), base.n_objects
    big = module.ObjectLoops(
        coefficients=np.tile(base.coefficients, (rep, 1, 1)),
        axis=np.tile(base.axis, rep),
        level=np.tile(base.level, rep),
        measures=np.tile(base.measures, (rep, 1)) + rng.normal(scale=0.2, size=(L * rep, 3)) * [1, 0, 0],
        owner=np.concatenate([base.owner + r * M for r in range(rep)]),
        profile=np.tile(base.profile, (rep, 1)) * rng.uniform(0.7, 1.3, size=(M * rep, base.profile.shape[1])),
        sections=base.sections,
    )
    F = np.tile(feature_vector(base.coefficients.astype(np.complex128)).astype(np.float32), (rep, 1))
    big.features = (F, squared_norms(F, F.shape[1] - 3))
    print(f"\n## the pruned object search: {big.n_objects:,} generated objects, {len(big.owner):,} contours")
    print(f"(made in {time.perf_counter() - t0:.0f} s)\n")
    print("| query | seconds | objects bounded by their loops | exact object distances | nearest |")
    print("|---|---|---|---|---|")
    counts: dict = {}
    exact, bounds = module._exact, module.object_lower_bounds

    def counted_exact(query, objs, chosen, samples, processes):
        counts["exact"] = counts.get("exact", 0) + len(chosen)
        return exact(query, objs, chosen, samples, processes)

    def counted_bounds(query, objs):
        counts["bounded"] = objs.n_objects
        return bounds(query, objs)

    module._exact, module.object_lower_bounds = counted_exact, counted_bounds
    try:
        for i, q in enumerate([0, 0, 57, 101, 150, 189]):
            counts.clear()
            t = time.perf_counter()
            found = module.nearest_objects(base.subset([q]), big, 128, k=10, processes=jobs)
            seconds = time.perf_counter() - t
            label = f"{names[q]}{' (first: makes the per-object tables)' if i == 0 else ''}"
            print(f"| {label} | {seconds:.2f} | {counts.get('bounded', 0)} | {counts.get('exact', 0)} | "
                  f"{found[0].distance:.3g} |")  # fmt: skip
    finally:
        module._exact, module.object_lower_bounds = exact, bounds


def _base_results(folder: str, names: list, jobs: int) -> list:
    """Each mesh's result as a build's worker computes it (cut, described, its object record)."""
    from nfdmatch.index.pool import run_tasks
    from nfdmatch.mesh.objects import ObjectRule

    rule = ObjectRule().as_tuple()
    tasks = [(os.path.join(folder, n), None, 128, 16, "rms", None, rule) for n in names]
    got = dict(run_tasks(tasks, jobs, None))
    return [got[i] for i in range(len(names))]


def generated_index(folder: str, names: list, objects_wanted: int, where: str, jobs: int) -> str:
    """An index file of ``objects_wanted`` generated objects in ``where`` (module doc)."""
    import hashlib

    from nfdmatch.index import build_index

    index = os.path.join(where, "objects.h5")
    if os.path.exists(index):
        return index
    t0 = time.perf_counter()
    base = _base_results(folder, names, jobs)
    stand_ins = os.path.join(where, "generated")
    for i in range(objects_wanted):
        sub = os.path.join(stand_ins, f"g{i // 1000:03d}")
        if i % 1000 == 0:
            os.makedirs(sub, exist_ok=True)
        with open(os.path.join(sub, f"o{i:06d}.ply"), "w") as f:
            f.write(f"nfdmatch benchmark: generated object {i}, a copy of {names[i % len(names)]}\n")
    t1 = time.perf_counter()

    def runner(tasks, _jobs, _lock_fd):
        for number, task in enumerate(tasks):
            path = task[0]
            i = int(os.path.basename(path)[1:7])
            b, rng = base[i % len(base)], np.random.default_rng(i)
            with open(path, "rb") as f:
                sha = hashlib.sha256(f.read()).hexdigest()
            st = os.stat(path)
            record = dict(b["object"])
            n = len(record["measures"])
            record["measures"] = record["measures"] + np.c_[rng.normal(scale=0.2, size=n), np.zeros((n, 2))]
            record["profile"] = record["profile"] * rng.uniform(0.7, 1.3, size=record["profile"].shape)
            yield number, {"path": path, "size": st.st_size, "mtime_ns": st.st_mtime_ns, "sha256": sha,
                           "status": "ok", "error": "", "ids": list(b["ids"]), "arrays": b["arrays"],
                           "object": record}  # fmt: skip

    report = build_index([stand_ins], index, jobs=jobs, runner=runner)
    t2 = time.perf_counter()
    print(f"\n## an index file of {report.added:,} generated objects, {report.curves:,} contours\n")
    print(f"built in {t2 - t0:.0f} s ({t1 - t0:.0f} s the folder's cuts and the stand-in files, {t2 - t1:.0f} s "
          f"index build); {os.path.getsize(index) / 1e9:.2f} GB: {index}")  # fmt: skip
    return index


def _evicted(path: str) -> None:
    """The file dropped from the page cache (its next read comes from the disk)."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
        os.posix_fadvise(fd, 0, 0, os.POSIX_FADV_DONTNEED)
    finally:
        os.close(fd)


def file_scale(folder: str, names: list, objects_wanted: int, jobs: int, keep: str | None) -> None:
    """Mesh queries against an index file of ``objects_wanted`` generated objects (module doc)."""
    with tempfile.TemporaryDirectory() as tmp:
        where = keep or tmp
        os.makedirs(where, exist_ok=True)
        index = generated_index(folder, names, objects_wanted, where, jobs)
        queries = [os.path.join(folder, names[q]) for q in (0, 57, 101, 150, 189)]
        print("\n| query (a new process each: `nfdmatch query MESH --index FILE --top 10`) | cold s | warm s |")
        print("|---|---|---|")
        cold, warm = [], []
        for q in queries:
            run = NFDMATCH + ["-q", "query", q, "--index", index, "--top", "10", "--format", "csv"]
            times = []
            for evict in (True, False):
                if evict:
                    _evicted(index)
                t = time.perf_counter()
                subprocess.run(run, check=True, capture_output=True)
                times.append(time.perf_counter() - t)
            cold.append(times[0])
            warm.append(times[1])
            print(f"| {os.path.basename(q)} | {times[0]:.2f} | {times[1]:.2f} |", flush=True)
        print(f"| median | {np.median(cold):.2f} | {np.median(warm):.2f} |")
        _in_process(index, queries, jobs)


def _in_process(index: str, queries: list, jobs: int) -> None:
    """The open of the index (cold) apart from each query in the same process (the median)."""
    from nfdmatch.index import open_index

    _evicted(index)
    t = time.perf_counter()
    idx = open_index(index)
    idx.object_loops()  # what every mesh query reads first: /objects, the objects' rows
    opened = time.perf_counter() - t
    seconds = []
    with idx:
        for q in queries:
            t = time.perf_counter()
            idx.search_objects([q], k=10, processes=jobs)
            seconds.append(time.perf_counter() - t)
    print(f"\nin one process: open and /objects read (cold) {opened:.2f} s; then a query (its mesh cut "
          f"included) median {np.median(seconds):.2f} s (min {min(seconds):.2f}, max {max(seconds):.2f})")  # fmt: skip


def retrieval(args, names: list, classes: dict) -> None:
    """The retrieval table: the tool, the baselines, each term (module doc)."""
    print(f"# objects by their curves: {len(names)} meshes of {len(set(classes.values()))} classes, {args.data}")
    print(f"every mesh a query against the other {len(names) - 1}; bull's-eye: same class among the 20 nearest\n")
    print("| method | top-1 | bull's-eye | seconds |")
    print("|---|---|---|---|")
    ranked, build_s, query_s = tool(args.data, names, args.jobs)
    t1, be = scores(names, classes, ranked)
    print(
        f"| nfdmatch index build + query (objects) | {t1:.3f} | {be:.3f} | build {build_s:.1f} + query {query_s:.1f} "
        f"= {build_s + query_s:.1f} |",
        flush=True,
    )
    if not args.no_baselines:
        t0 = time.perf_counter()
        D = xyz_pooled(args.data, names, args.jobs)
        t1, be = scores(names, classes, ranked_from_matrix(names, D))
        print(
            f"| x/y/z sections (5 each) pooled, mean of nearest | {t1:.3f} | {be:.3f} | {time.perf_counter() - t0:.1f} |"
        )
        t0 = time.perf_counter()
        D = d2(args.data, names)
        t1, be = scores(names, classes, ranked_from_matrix(names, D))
        print(
            f"| D2 shape distribution (Osada 2001) | {t1:.3f} | {be:.3f} | {time.perf_counter() - t0:.1f} |", flush=True
        )
    if not args.no_terms:
        print("\n## each term (library, the same cuts; shares of the object distance between different meshes)\n")
        print("| terms | top-1 | bull's-eye |")
        print("|---|---|---|")
        for name, D, share in terms(args.data, names, args.jobs):
            t1, be = scores(names, classes, ranked_from_matrix(names, D))
            print(f"| {name} | {t1:.3f} | {be:.3f} |")
            if share is not None:
                print(
                    f"\nmean share of the object distance: curves (shape + size) {share:.3f}, profile {1 - share:.3f}"
                )


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", default=DEFAULT_DATA, help="a folder of meshes with labels.csv")
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--no-table", action="store_true", help="skip the retrieval table (tool, baselines, terms)")
    ap.add_argument("--no-baselines", action="store_true")
    ap.add_argument("--no-terms", action="store_true")
    ap.add_argument("--scale", type=int, default=0, metavar="M", help="generated objects of the pruned search")
    ap.add_argument("--file-scale", type=int, default=0, metavar="M", help="generated objects of an index file")
    ap.add_argument("--keep", default=None, metavar="DIR", help="where --file-scale builds (and keeps) its index")
    args = ap.parse_args()
    if not os.path.isfile(os.path.join(args.data, "labels.csv")):
        print(
            f"skipped: no labelled meshes at {args.data} (the Princeton segmentation meshes are research "
            "data, not shipped with nfdmatch; pass --data)",
            file=sys.stderr,
        )
        return 0
    classes = labels_of(args.data)
    names = sorted(classes)
    if not args.no_table:
        retrieval(args, names, classes)
    if args.scale:
        scale(args.data, names, args.scale, args.jobs)
    if args.file_scale:
        file_scale(args.data, names, args.file_scale, args.jobs, args.keep)
    return 0


if __name__ == "__main__":
    sys.exit(main())
