"""Generate the meshes of the README's mesh -> contours -> index -> query walk-through.

    python sample_curves/make_meshes.py OUT_DIR

writes into OUT_DIR:

* ``column.stl``: a closed "column" 4 units tall whose horizontal cross-section morphs
  from a rounded triangle (bottom) through a circle to a rounded square (top), with a
  twist, so that every level has its own shape;
* ``column-posed.ply``: the same column spun about its axis, laid along x, scaled by 2.5
  and moved, re-triangulated with other ring counts (its sections are sampled differently);
* ``cup.stl``: an open cup (no lid): its rim is a boundary loop (``--boundaries``).

Deterministic (no random numbers); needs numpy and trimesh.
"""

from __future__ import annotations

import os
import sys

import numpy as np


def column_rings(levels: int = 81, around: int = 96, height: float = 4.0) -> np.ndarray:
    """(levels, around, 3) float64: the rings of the column's side, bottom to top."""
    z = np.linspace(0.0, height, levels)
    theta = np.linspace(0.0, 2 * np.pi, around, endpoint=False)
    u = z / height                                             # 0 at the bottom, 1 at the top
    tri = 0.25 * (1 - u) ** 1.5                                # three lobes fade out going up
    square = 0.18 * u ** 1.5                                   # four lobes grow
    twist = 0.6 * u
    t = theta[None, :] - twist[:, None]
    r = 1.0 + tri[:, None] * np.cos(3 * t) + square[:, None] * np.cos(4 * t) + 0.1 * np.sin(np.pi * u)[:, None]
    return np.stack([r * np.cos(theta)[None, :], r * np.sin(theta)[None, :],
                     np.broadcast_to(z[:, None], r.shape)], axis=-1)


def tube_mesh(rings: np.ndarray, *, bottom: bool = True, top: bool = True):
    """A triangle mesh of the surface through ``rings`` ((L, M, 3) float64), with optional
    flat caps (a fan around each ring's centroid)."""
    import trimesh

    L, M, _ = rings.shape
    vertices = [rings.reshape(-1, 3)]
    idx = np.arange(L * M).reshape(L, M)
    a, b = idx[:-1], np.roll(idx[:-1], -1, axis=1)
    c, d = idx[1:], np.roll(idx[1:], -1, axis=1)
    faces = [np.stack([a, b, d], -1).reshape(-1, 3), np.stack([a, d, c], -1).reshape(-1, 3)]
    for ring, flip, use in ((0, True, bottom), (L - 1, False, top)):
        if not use:
            continue
        centre = len(np.concatenate(vertices))
        vertices.append(rings[ring].mean(axis=0)[None])
        ring_idx = idx[ring]
        fan = np.stack([np.full(M, centre), ring_idx, np.roll(ring_idx, -1)], -1)
        faces.append(fan[:, [0, 2, 1]] if flip else fan)
    return trimesh.Trimesh(np.concatenate(vertices), np.concatenate(faces), process=True)


def main(out_dir: str) -> None:
    os.makedirs(out_dir, exist_ok=True)
    column = tube_mesh(column_rings())
    column.export(os.path.join(out_dir, "column.stl"))
    posed = tube_mesh(column_rings(levels=67, around=71))
    # spun 35 degrees about its own axis, then laid down along x (sections stay perpendicular
    # to the column's axis, which the longest side of the bounding box still finds)
    angle = np.radians(35.0)
    c, s = np.cos(angle), np.sin(angle)
    rotation = np.array([[0, 0, 1], [0, 1, 0], [-1, 0, 0]]) @ np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    transform = np.eye(4)
    transform[:3, :3] = 2.5 * rotation
    transform[:3, 3] = [10.0, -4.0, 3.0]
    posed.apply_transform(transform)
    posed.export(os.path.join(out_dir, "column-posed.ply"))
    theta = np.linspace(0.0, 2 * np.pi, 64, endpoint=False)
    z = np.linspace(0.0, 1.2, 13)
    r = 0.6 + 0.35 * (z / 1.2) ** 0.7
    cup = np.stack([r[:, None] * np.cos(theta)[None, :] * (1 + 0.15 * np.cos(2 * theta))[None, :],
                    r[:, None] * np.sin(theta)[None, :], np.broadcast_to(z[:, None], (13, 64))], -1)
    tube_mesh(cup, top=False).export(os.path.join(out_dir, "cup.stl"))


if __name__ == "__main__":
    if len(sys.argv) != 2:
        sys.exit(__doc__)
    main(sys.argv[1])
