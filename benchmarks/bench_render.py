"""Time and look of the pictures of `nfdmatch show` and `nfdmatch matrix`, per renderer.

    python benchmarks/bench_render.py [--repeat 3] [--out /tmp/nfdmatch-bench-render]

Pictures (1600x900, a query and its 5 best matches from sample_curves/library, each
aligned onto the query the way `show` does it):

* 2-D: the re-posed ellipse (sample_curves/queries/ellipse-posed.csv, planar but not in
  z = 0) against the planar library curves;
* 3-D: the re-posed trefoil (queries/trefoil-posed.obj, 777 vertices) against the whole
  library (its matches have 24 to 400 vertices);
* 3-D dense: the same with every curve subdivided to 2,000 vertices;
* matrix: the all-pairs matrix of 100 curves (the library and re-posed, resampled,
  noisy copies of it), matplotlib only.

Columns: "first" is the first picture of a fresh process, import of nfdmatch.render and
of the renderer included (run in a child process; Python's own start-up not included);
"then" is the median of --repeat more pictures in this process. The pictures are saved
in --out to be looked at.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
sys.path.insert(0, ROOT)

from nfdmatch.descriptors import DEFAULT_HARMONICS, DEFAULT_SCALE, points_at  # noqa: E402
from nfdmatch.formats import read_curve  # noqa: E402
from nfdmatch.search import distance_matrix, rank_curves  # noqa: E402
from nfdmatch.show import matches_from_curves  # noqa: E402
from nfdmatch.sources import find_curve_files, read_all  # noqa: E402

LIB = os.path.join(ROOT, "sample_curves", "library")
QUERIES = os.path.join(ROOT, "sample_curves", "queries")
SAMPLES = 128
SIZE = (1600, 900)


def library_curves():
    curves, errors = read_all(find_curve_files([LIB]))
    assert not errors, errors
    return curves


def subdivide(points, n):
    """The same closed polyline with about n vertices (original vertices kept)."""
    closed = np.vstack([points, points[:1]])
    seg = np.linalg.norm(np.diff(closed, axis=0), axis=1)
    k = np.maximum(1, np.round(seg / seg.sum() * n).astype(int))
    frac = np.concatenate([np.arange(j) / j for j in k])
    return np.repeat(closed[:-1], k, axis=0) + frac[:, None] * np.repeat(np.diff(closed, axis=0), k, axis=0)


def scene(query_path, candidates, top=5):
    """The data `nfdmatch show --against` draws: the query and its top matches, aligned."""
    query = read_curve(query_path)
    rows = rank_curves(query, candidates, top=top, samples=SAMPLES)
    shown = matches_from_curves(
        query, rows, candidates, samples=SAMPLES, harmonics=DEFAULT_HARMONICS, scale=DEFAULT_SCALE
    )
    panels = [
        dict(
            id=m.id,
            distance=m.distance,
            points=m.points,
            start=m.start,
            forward=m.forward,
            reversed=m.reversed,
            mirrored=m.mirrored,
        )
        for m in shown
    ]  # plain data, saved with np.savez
    return dict(query=query.points, query_id=query.id, panels=panels)


def rel(path):
    return os.path.relpath(path, ROOT)


def scenes():
    lib = library_curves()
    planar = [
        c
        for c in lib
        if abs(np.linalg.svd(c.points - c.points.mean(0), compute_uv=False)[2]) <= 1e-9 * np.ptp(c.points, axis=0).max()
    ]
    two = scene(os.path.join(QUERIES, "ellipse-posed.csv"), planar)
    three = scene(os.path.join(QUERIES, "trefoil-posed.obj"), lib)
    dense = dict(
        query=subdivide(three["query"], 2000),
        query_id=three["query_id"],
        panels=[dict(p, points=subdivide(p["points"], 2000)) for p in three["panels"]],
    )
    for s in (two, three, dense):
        s["query_id"] = rel(s["query_id"])
        for p in s["panels"]:
            p["id"] = rel(p["id"])
    return {"2d": two, "3d": three, "3d-2000": dense}


def matrix_data(n=100, seed=3):
    rng = np.random.default_rng(seed)
    lib = library_curves()
    curves, ids = [c.points for c in lib], [rel(c.id) for c in lib]
    while len(curves) < n:
        c = lib[len(curves) % len(lib)]
        q, _ = np.linalg.qr(rng.standard_normal((3, 3)))
        m = rng.integers(60, 900)
        p = points_at(c.points, np.sort(rng.random(m)))
        p = p @ q.T * rng.uniform(0.5, 2.0) + rng.standard_normal(3)
        p = p + rng.standard_normal(p.shape) * 0.01 * np.ptp(p, axis=0).max()
        curves.append(p)
        ids.append(f"variants/{os.path.splitext(os.path.basename(c.id.split('#')[0]))[0]}-{len(curves):03d}.csv")
    return distance_matrix(curves, samples=SAMPLES), ids


def shown_match(rank, p):
    """The :class:`~nfdmatch.records.ShownMatch` of one saved panel."""
    from nfdmatch.records import RankedMatch, ShownMatch

    return ShownMatch(
        RankedMatch(rank, p["id"], p["distance"], reversed=p["reversed"], mirrored=p["mirrored"]),
        p["points"],
        p["start"],
        p["forward"],
    )


def panels_of(s):
    return [shown_match(rank, p) for rank, p in enumerate(s["panels"], 1)]


CHILD = r"""
import json, sys, time, numpy as np
t0 = time.perf_counter()
from nfdmatch.records import RankedMatch, ShownMatch
from nfdmatch.render import render_matches
data = np.load(sys.argv[1], allow_pickle=True)["scene"].item()
panels = [ShownMatch(RankedMatch(rank, p["id"], p["distance"], reversed=p["reversed"], mirrored=p["mirrored"]),
                     p["points"], p["start"], p["forward"]) for rank, p in enumerate(data["panels"], 1)]
r = render_matches(data["query"], data["query_id"], panels, sys.argv[2], renderer=sys.argv[3])
print(json.dumps({"seconds": time.perf_counter() - t0, "renderer": r.renderer, "note": r.note}))
"""


def first_picture(scene_data, out_png, renderer, workdir):
    npz = os.path.join(workdir, "scene.npz")
    np.savez(npz, scene=np.array(scene_data, dtype=object))
    proc = subprocess.run(
        [sys.executable, "-c", CHILD, npz, out_png, renderer], capture_output=True, text=True, cwd=ROOT
    )
    if proc.returncode != 0:
        return None, (proc.stderr.strip().splitlines() or ["failed"])[-1]
    r = json.loads(proc.stdout)
    return r["seconds"], r["note"]


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=3, help="pictures timed after the first (median)")
    ap.add_argument("--out", default="/tmp/nfdmatch-bench-render", help="folder for the pictures")
    ap.add_argument("--renderers", default="matplotlib,pyvista")
    args = ap.parse_args()
    os.makedirs(args.out, exist_ok=True)
    from nfdmatch.render import render_matches, render_matrix

    data = scenes()
    print(f"pictures {SIZE[0]}x{SIZE[1]}, a query and 5 matches; vertices per curve:")
    for name, s in data.items():
        counts = [len(s["query"])] + [len(p["points"]) for p in s["panels"]]
        print(f"  {name:8s} query {counts[0]}, matches {', '.join(map(str, counts[1:]))}")
    print()
    print(f"{'renderer':11s} {'picture':8s} {'first (s)':>10s} {'then (s)':>9s}  file")
    for renderer in args.renderers.split(","):
        for name, s in data.items():
            png = os.path.join(args.out, f"show-{name}-{renderer}.png")
            first, note = first_picture(s, png, renderer, args.out)
            times = []
            try:  # warm-up: imports and the pyvista probe are in "first"
                render_matches(s["query"], s["query_id"], panels_of(s), png, size=SIZE, renderer=renderer)
            except Exception as exc:  # noqa: BLE001  (reported below)
                note = f"{type(exc).__name__}: {exc}"
            for _ in range(max(args.repeat, 1)):
                t0 = time.perf_counter()
                try:
                    render_matches(s["query"], s["query_id"], panels_of(s), png, size=SIZE, renderer=renderer)
                except Exception as exc:  # noqa: BLE001  (report and go on)
                    note = f"{type(exc).__name__}: {exc}"
                    break
                times.append(time.perf_counter() - t0)
            then = f"{statistics.median(times):9.3f}" if times else f"{'-':>9s}"
            first_s = f"{first:10.3f}" if first is not None else f"{'-':>10s}"
            print(
                f"{renderer:11s} {name:8s} {first_s} {then}  {rel(png) if png.startswith(ROOT) else png}"
                + (f"  ({note})" if note else "")
            )
    m, ids = matrix_data()
    png = os.path.join(args.out, f"matrix-{len(ids)}.png")
    times = []
    for _ in range(max(args.repeat, 1) + 1):
        r = render_matrix(m, ids, png, title=f"exact distance, {len(ids)} curves")
        times.append(r.seconds)
    times = times[1:]
    small = os.path.join(args.out, "matrix-library.png")
    k = len(library_curves())
    render_matrix(m[:k, :k], ids[:k], small, title=f"exact distance, {k} curves")
    print(
        f"{'matplotlib':11s} {'matrix':8s} {'':>10s} {statistics.median(times):9.3f}  {png} "
        f"({len(ids)} curves); {small} ({k} curves)"
    )


if __name__ == "__main__":
    main()
