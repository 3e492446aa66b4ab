"""Development data that bends: families of curves whose members differ by articulation and
deformation, not only by pose and sampling (issue "Similarity that bends", item 4).

The collection has one template: a body (an ellipse in 2-D, a smooth closed space curve in
3-D) with four or five limbs (bumps along the body's outward direction); each family's base
is the template with its limbs moved, resized and lifted a little, so that families are
cousins and what tells them apart is of the size of what bends. A member is the base
with every limb bent at its root by its own angle (a rotation of the limb's points about
the root, in the body's plane, or about a random axis in 3-D), a local stretch (a warp of
the parameter), one swelling (a wide bump of the radius), a small sharp bump at a random
place, vertex noise, and then a random pose, scale, start vertex, direction and resampling.

``families(rng, count, members, dimension)`` returns ``(curves, labels)``; deterministic for
a seeded ``rng``. Used by ``bench_3d.py`` and ``bench_rerank.py``.
"""

from __future__ import annotations

import numpy as np

__all__ = ["families", "BEND_DEGREES"]

#: the standard deviation of a limb's bend at its root, in degrees
BEND_DEGREES = 35.0


def _rotation(rng) -> np.ndarray:
    q = rng.standard_normal(4)
    q /= np.linalg.norm(q)
    w, x, y, z = q
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def _turn(axis: np.ndarray, angle: float) -> np.ndarray:
    axis = axis / np.linalg.norm(axis)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k


def _base(rng, dimension: int, template: dict) -> dict:
    """A family's base: the collection's template with its limbs moved, resized and lifted a
    little (families are cousins: what tells them apart is of the size of what bends)."""
    limbs = len(template["centres"])
    return {
        "aspect": template["aspect"] * rng.uniform(0.85, 1.15),
        "wobble": template["wobble"] + rng.normal(0, 0.06, (3, 2)),
        "lift": template["lift"] + rng.normal(0, 0.05 if dimension == 3 else 0.0, 3),
        "centres": np.sort(template["centres"] + rng.normal(0, 0.25, limbs)),
        "lengths": template["lengths"] * rng.uniform(0.6, 1.4, limbs),
        "widths": template["widths"] * rng.uniform(0.8, 1.25, limbs),
        "bend": BEND_DEGREES,
    }


def _template(rng, dimension: int) -> dict:
    limbs = int(rng.integers(4, 6))
    return {
        "aspect": rng.uniform(0.5, 1.0),
        "wobble": rng.normal(0, 0.15, (3, 2)),
        "lift": rng.normal(0, 0.35 if dimension == 3 else 0.0, 3),
        "centres": np.sort(rng.uniform(0, 2 * np.pi, limbs)),
        "lengths": rng.uniform(0.5, 1.1, limbs),
        "widths": rng.uniform(0.08, 0.16, limbs),
    }


def _member(rng, base: dict, dimension: int, vertices: int) -> np.ndarray:
    n = 1200
    u = np.arange(n) / n * 2 * np.pi
    t = u + 0.25 * rng.uniform(-1, 1) * np.sin(u + rng.uniform(0, 2 * np.pi))  # local stretch
    r = 1.0 + sum(
        base["wobble"][m, 0] * np.cos((m + 2) * t) + base["wobble"][m, 1] * np.sin((m + 2) * t) for m in range(3)
    )
    swell = rng.uniform(0, 2 * np.pi)
    r = r + 0.15 * rng.uniform(0.3, 1.0) * np.exp(-(((t - swell + np.pi) % (2 * np.pi) - np.pi) ** 2) / 0.3)
    bump = rng.uniform(0, 2 * np.pi)
    r = r + 0.05 * np.exp(-(((t - bump + np.pi) % (2 * np.pi) - np.pi) ** 2) / 0.002)
    limb_of = np.full(n, -1)
    for i, (c, length, width) in enumerate(zip(base["centres"], base["lengths"], base["widths"])):
        gap = (t - c + np.pi) % (2 * np.pi) - np.pi
        shape = np.exp(-(gap**2) / (2 * (width / 2.5) ** 2))
        r = r + length * shape
        limb_of[np.abs(gap) < width] = i
    z = sum(base["lift"][m] * np.sin((m + 1) * t + m) for m in range(3)) * 0.5
    points = np.stack([r * np.cos(t), base["aspect"] * r * np.sin(t), z], axis=1)
    for i in range(len(base["centres"])):
        mine = np.flatnonzero(limb_of == i)
        if len(mine) < 3:
            continue
        root = 0.5 * (points[mine[0]] + points[mine[-1]])
        axis = np.array([0.0, 0.0, 1.0]) if dimension == 2 else rng.standard_normal(3)
        points[mine] = (points[mine] - root) @ _turn(axis, np.radians(rng.normal(0, base["bend"]))).T + root
    size = np.sqrt(((points - points.mean(0)) ** 2).sum(1).mean())
    points = points + rng.normal(0, 0.004 * size, points.shape) * np.array([1, 1, 1 if dimension == 3 else 0])
    keep = np.sort(rng.choice(n, size=vertices, replace=False))
    points = np.roll(points[keep], int(rng.integers(0, vertices)), axis=0)
    if rng.random() < 0.5:
        points = points[::-1]
    if dimension == 3:
        points = points @ _rotation(rng).T
    else:
        a = rng.uniform(0, 2 * np.pi)
        points = points @ np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]]).T
    return points * np.exp(rng.uniform(np.log(0.2), np.log(5))) + rng.uniform(-50, 50, 3)


def families(rng, count: int = 20, members: int = 10, dimension: int = 2, vertices=(150, 500)):
    """``(curves, labels)``: ``count`` families of ``members`` curves, (m, 3) float64 arrays
    (z = 0 for ``dimension`` 2), and the family of each (int64)."""
    curves, labels = [], []
    template = _template(rng, dimension)
    for f in range(count):
        base = _base(rng, dimension, template)
        for _ in range(members):
            curves.append(_member(rng, base, dimension, int(rng.integers(*vertices))))
            labels.append(f)
    return curves, np.array(labels, dtype=np.int64)
