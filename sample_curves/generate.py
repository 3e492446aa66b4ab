"""Regenerate the sample curves (deterministic): python sample_curves/generate.py [--data ../shared/data]

Generated families (torus knots, Lissajous curves, ellipses, noisy and re-posed variants)
in every supported format, plus a few curves copied from the development data
(knotess, MIT; trimesh model sections, MIT), credited in README.md.
"""

from __future__ import annotations

import argparse
import os
import shutil

import numpy as np

from nfdmatch import write_curves

HERE = os.path.dirname(os.path.abspath(__file__))
LIB = os.path.join(HERE, "library")
QUERIES = os.path.join(HERE, "queries")


def torus_knot(p, q, n, R=2.0, r=1.0, phase=0.0):
    t = np.linspace(0, 2 * np.pi, n, endpoint=False) + phase
    rr = R + r * np.cos(q * t)
    return np.c_[rr * np.cos(p * t), rr * np.sin(p * t), r * np.sin(q * t)]


def lissajous(a, b, c, n, phase=(0.3, 0.7)):
    t = np.linspace(0, 2 * np.pi, n, endpoint=False)
    return np.c_[np.sin(a * t + phase[0]), np.sin(b * t + phase[1]), np.sin(c * t)]


def ellipse(rx, ry, n):
    t = np.linspace(0, 2 * np.pi, n, endpoint=False)
    return np.c_[rx * np.cos(t), ry * np.sin(t)]


def superellipse(rx, ry, e, n):
    t = np.linspace(0, 2 * np.pi, n, endpoint=False)
    c, s = np.cos(t), np.sin(t)
    return np.c_[rx * np.sign(c) * np.abs(c) ** e, ry * np.sign(s) * np.abs(s) ** e]


def rotation(rng):
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] = -q[:, 0]
    return q


def repose(points, rng, *, vertices=None, reverse=False):
    """Rotate, scale, translate, re-sample at random arc-length positions, shift the start."""
    pts = np.c_[points, np.zeros(len(points))] if points.shape[1] == 2 else points
    if vertices is not None:
        closed = np.vstack([pts, pts[:1]])
        cum = np.concatenate([[0], np.cumsum(np.linalg.norm(np.diff(closed, axis=0), axis=1))])
        at = np.sort(rng.uniform(0, cum[-1], vertices))
        pts = np.column_stack([np.interp(at, cum, closed[:, i]) for i in range(3)])
    pts = np.roll(pts, int(rng.integers(len(pts))), axis=0)
    if reverse:
        pts = pts[::-1]
    return rng.uniform(0.2, 5.0) * pts @ rotation(rng).T + rng.uniform(-50, 50, 3)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--data", default=os.path.join(HERE, "..", "..", "shared", "data"))
    args = ap.parse_args()
    rng = np.random.default_rng(2002)
    for d in (LIB, QUERIES):
        shutil.rmtree(d, ignore_errors=True)
        os.makedirs(d)
    w = lambda name, curves: write_curves(os.path.join(LIB, name), curves)  # noqa: E731

    trefoil = torus_knot(2, 3, 400)
    w("trefoil.csv", trefoil)
    w("trefoil-noisy.csv", trefoil + rng.normal(scale=0.03, size=trefoil.shape))
    w("trefoil-coarse.vtk", torus_knot(2, 3, 24, phase=0.1))
    w("cinquefoil.vtp", torus_knot(2, 5, 500))
    w("torus-knot-3-4.obj", torus_knot(3, 4, 600))
    w("torus-knot-3-5.vtu", torus_knot(3, 5, 700))
    w("torus-knot-2-7.csv", torus_knot(2, 7, 700))
    w("lissajous-family.obj", [lissajous(1, 2, 3, 500), lissajous(3, 2, 1, 500), lissajous(2, 3, 5, 600)])
    w("ellipse-2to1.csv", ellipse(2, 1, 200))
    w("ellipse-4to1.csv", ellipse(4, 1, 200))
    w("circle.tsv", ellipse(1, 1, 90))
    w("superellipses.vtp", [superellipse(1, 1, 0.3, 300), superellipse(2, 1, 0.3, 300)])
    w("trefoil-mirror.csv", trefoil * np.array([1.0, 1.0, -1.0]))

    data = os.path.normpath(args.data)
    knotess = os.path.join(LIB, "knotess")
    os.makedirs(knotess)
    for name in ("3_1", "4_1", "5_1", "5_2", "6_1"):
        shutil.copy(os.path.join(data, "knotess_smooth", f"{name}.csv"), knotess)
    meshes = os.path.join(LIB, "mesh-loops")
    os.makedirs(meshes)
    for rel in ("sections/bunny-03.csv", "boundary/fuze-b01.csv", "boundary/teapot-b01.csv"):
        shutil.copy(os.path.join(data, "mesh_loops", rel), os.path.join(meshes, os.path.basename(rel)))

    q = lambda name, curves: write_curves(os.path.join(QUERIES, name), curves)  # noqa: E731
    q("trefoil-posed.obj", repose(trefoil, rng, vertices=777, reverse=True))
    q("ellipse-posed.csv", repose(ellipse(2, 1, 200), rng, vertices=150))
    shutil.copy(os.path.join(data, "knotess_control", "4_1.csv"), os.path.join(QUERIES, "4_1-control.csv"))


if __name__ == "__main__":
    main()
