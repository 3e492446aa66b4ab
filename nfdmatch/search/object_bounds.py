"""Proven lower bounds of the object distance (:mod:`.object_distance`), cheapest first: per-object
numbers (:func:`object_coarse_bounds`) and the loops' invariant bounds
(:func:`object_lower_bounds`); the search (:mod:`.objects`) visits the objects in their
order (docs/objects.md, "The search")."""

from __future__ import annotations

import numpy as np

from ..mesh.objects import BOUNDARY_AXIS
from .object_distance import (
    EMPTY_LEVEL,
    PROFILE_SCALE,
    PROFILE_UNITS,
    SHAPE_SCALE,
    SIZE_WEIGHT,
    ObjectLoops,
    object_distances,
    present_levels,
)

__all__ = ["object_lower_bounds", "object_coarse_bounds"]


def object_lower_bounds(queries: ObjectLoops, objects: ObjectLoops) -> np.ndarray:
    """(Q, M) lower bounds of the object distance, without one exact loop distance.

    The object distance is built from its loop distances by operations that never decrease
    when an entry grows (a minimum over loops, weighted means with fixed weights, a sum with
    the profile, a minimum over the two orders, a mean over the axes). Each loop's exact
    distance is replaced by its invariant lower bound (the Euclidean distance between the
    stored invariant features, rounding slack subtracted: ``search/bounds.py``), the size
    and profile terms kept exact: every entry is then at most the true one, so the result
    is at most the object distance."""
    return object_distances(queries, objects, 0, loop=(1.0, SIZE_WEIGHT, "bound")).distance


def object_coarse_bounds(query: ObjectLoops, objects: ObjectLoops) -> np.ndarray:
    """(M,) lower bounds of one query object's distance to every object from per-object
    numbers only (no loop is read): the profile term exactly, and of the curves' term only
    its levels where one object has loops and the other none (``EMPTY_LEVEL`` each; every
    other level counts 0, its least). Every part is at most its part of the object
    distance, and the parts are combined as there (a minimum over the two orders of their
    sum, a mean over the axes), so the result is at most the object distance."""
    qbits, qprof = _per_object(query)
    obits, oprof = _per_object(objects)  # (M, 4, 2) level bitmasks, (M, 3, N F) profiles
    N, M, width = objects.sections, objects.n_objects, oprof.shape[-1]
    # the object's levels mirrored against the query's in order sum as the query's mirrored
    # against the object's in order: only the one query is mirrored
    mirrored = qprof[0].reshape(3, N, -1)[:, ::-1].reshape(3, width)
    unit = np.tile(1.0 / PROFILE_UNITS, N) / (width * PROFILE_SCALE)  # each feature over its unit, the mean
    total = np.zeros(M)
    diff = np.empty((M, width))
    for a in range(3):
        best = None
        for s, q in ((0, qprof[0, a]), (1, mirrored[a])):
            either = np.bitwise_count(qbits[0, a, s] | obits[:, a, 0])
            one = np.bitwise_count(qbits[0, a, s] ^ obits[:, a, 0])
            shape = EMPTY_LEVEL * one / np.maximum(either, 1) / SHAPE_SCALE
            np.subtract(oprof[:, a], q, out=diff)
            prof = np.abs(diff, out=diff) @ unit
            best = shape + prof if best is None else np.minimum(best, shape + prof)
        total += best
    bq, bo = qbits[0, BOUNDARY_AXIS, 0] != 0, obits[:, BOUNDARY_AXIS, 0] != 0
    total += np.where(bq ^ bo, EMPTY_LEVEL / SHAPE_SCALE, 0.0)
    return total / (3.0 + (bq | bo))


def _per_object(loops: ObjectLoops) -> tuple[np.ndarray, np.ndarray]:
    """Per object, made once per set of objects: its levels with loops as bitmasks (M, 4, 2)
    uint64 (bit i: level i; then with the levels mirrored) and its profile as given, (M, 3,
    N F) (a view: nothing copied for an index's 100,000 objects)."""
    if loops.per_object is None:
        N = loops.sections
        if N > 64:
            raise ValueError("at most 64 sections")
        has = present_levels(loops, 4, N)
        weights = np.left_shift(np.uint64(1), np.arange(N, dtype=np.uint64))
        bits = np.stack([(has * weights).sum(axis=2), (has[:, :, ::-1] * weights).sum(axis=2)], axis=2)
        profile = np.asarray(loops.profile, dtype=np.float64)
        loops.per_object = (bits.astype(np.uint64), profile.reshape(len(profile), 3, -1))
    return loops.per_object
