"""The object distance: two objects compared through their contours (docs/objects.md).

An object is a set of loops cut by one rule (:mod:`nfdmatch.mesh.objects`), each tagged with
its principal axis (0..2, or 3 for a boundary loop) and level (0..N-1), with size-free
measures, plus a section profile. For objects P and Q:

* loop distance ``d(p, q) = exact(p, q) + SIZE_WEIGHT |log rel. perimeter p - log rel.
  perimeter q|`` (the exact distance of :mod:`nfdmatch.matching`, computed by
  :func:`~nfdmatch.search.matrix.cross_distances`; the descriptor is scale-free, so the
  size relative to the object is given back);
* level set distance ``L(P_i, Q_j)``: the perimeter-weighted mean over P's loops of the
  nearest of Q's, averaged with the same from Q (symmetric); ``EMPTY_LEVEL`` when one side
  has no loop at that level, skipped when neither has;
* per axis and order (``j = i``, or ``j = N - 1 - i``: the axis's sign is settled by the
  better of the two, so a near-zero skew cannot flip it): the mean of ``L`` over the
  levels divided by ``SHAPE_SCALE``, plus the profile's L1 distance (each feature over its
  unit in ``PROFILE_UNITS``, mean over levels and features) divided by ``PROFILE_SCALE``;
* the distance: the mean over the three axes of the better order's value (boundary loops,
  when either object has some, a fourth term: ``L`` over ``SHAPE_SCALE``).

Symmetric (every part is, and the two orders are each other's mirror), deterministic, and
0 for an object against itself. Only loops of the same axis and of a level and its mirror
level are ever compared: ``3 x ceil(N / 2)`` small matrices instead of one of every loop.
The constants are fixed, measured on the development half of the Princeton segmentation
benchmark (docs/objects.md); no statistic of a query's answer list is used.

A query (:func:`search_objects`, :func:`nearest_objects`) visits the objects through a
cascade of proven lower bounds of this distance (:func:`object_coarse_bounds`, per-object
numbers; :func:`object_lower_bounds`, the loops' invariant bounds), then exact distances,
and stops when no object left can be nearer (docs/objects.md, "The search").

This module never imports ``index/``: it works on :class:`ObjectLoops`, which the index
reader (``Index.objects``) and :func:`object_loops` (a cut in memory) both make.

Test hooks: ``_exact`` (the exact distances of a round of :func:`nearest_objects`) and
``object_lower_bounds`` are replaced by a test and the benchmark to count the objects each
stage reached.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..mesh.objects import BOUNDARY_AXIS
from .bounds import feature_vector, row_lower_bounds_many, squared_norms
from .matrix import cross_distances
from .workers import run_tasks

__all__ = [
    "SIZE_WEIGHT",
    "EMPTY_LEVEL",
    "SHAPE_SCALE",
    "PROFILE_SCALE",
    "PROFILE_UNITS",
    "ObjectLoops",
    "ObjectDistances",
    "object_distances",
    "ObjectMatch",
    "FoundObject",
    "object_loops",
    "object_lower_bounds",
    "object_coarse_bounds",
    "nearest_objects",
    "all_nearest_objects",
    "search_objects",
]

#: weight of the size term of a loop distance (|delta log relative perimeter|)
SIZE_WEIGHT = 0.5
#: a level where one object has loops and the other none
EMPTY_LEVEL = 1.0
#: the curves' term is divided by this (its median between different objects of the
#: development half), so that curves and profile weigh alike
SHAPE_SCALE = 0.62
#: the profile term is divided by this (its median there)
PROFILE_SCALE = 1.0
#: units of the profile's features (loop count, total relative perimeter, enclosed area
#: over surface area, elongation of the longest loop): their spread on the development half
PROFILE_UNITS = np.array([1.7, 0.67, 0.05, 0.25])


@dataclass
class ObjectLoops:
    """Loops of M objects: ``coefficients`` (L, K, 3) complex (stored descriptors),
    ``axis`` (L,), ``level`` (L,), ``measures`` (L, 3) (``log relative perimeter,
    relative area, elongation``), ``owner`` (L,) int: the object of each loop (0..M-1),
    ``profile`` (M, 3 N 4), ``sections`` N, ``rows`` (L,): what a loop is called by its
    caller (index rows; None: 0..L-1)."""

    coefficients: np.ndarray
    axis: np.ndarray
    level: np.ndarray
    measures: np.ndarray
    owner: np.ndarray
    profile: np.ndarray
    sections: int
    rows: np.ndarray | None = None
    #: the loops' invariant features and their squared norms, made on first use (bounds)
    features: tuple | None = None
    #: presence and scaled profile per object, made on first use (coarse bounds)
    per_object: tuple | None = None

    @property
    def n_objects(self) -> int:
        return int(len(self.profile))

    def subset(self, chosen) -> "ObjectLoops":
        """Objects ``chosen`` (positions, in that order) alone, renumbered 0..len-1 (the loops
        of each object must be one run, in owner order, as the readers make them)."""
        chosen = np.asarray(chosen, dtype=np.int64)
        starts = np.searchsorted(self.owner, chosen)
        stops = np.searchsorted(self.owner, chosen, side="right")
        pick = np.concatenate([np.arange(a, b) for a, b in zip(starts, stops)]) if len(chosen) else np.zeros(0, int)
        return ObjectLoops(
            coefficients=self.coefficients[pick],
            axis=self.axis[pick],
            level=self.level[pick],
            measures=self.measures[pick],
            owner=np.repeat(np.arange(len(chosen)), stops - starts),
            profile=self.profile[chosen],
            sections=self.sections,
            rows=None if self.rows is None else self.rows[pick],
            features=None if self.features is None else (self.features[0][pick], self.features[1][pick]),
        )


@dataclass
class ObjectDistances:
    """(Q, M) arrays: ``distance`` (the object distance), ``curves`` and ``profile`` (the two
    terms after their scales, averaged over the axes), ``mirror`` (Q, M, 3) bool: the order
    each axis took (``j = N - 1 - i``)."""

    distance: np.ndarray
    curves: np.ndarray
    profile: np.ndarray
    mirror: np.ndarray
    blocks: list = None
    sections: int = 0

    def matched(self, q: int, m: int) -> np.ndarray:
        """The loops of object ``m`` (positions in the objects' :class:`ObjectLoops`) that are
        the nearest of some loop of query ``q`` at its matched level (the order each axis
        took), ascending: what a mesh query reports as an answer's matched curves."""
        N = self.sections
        found: set[int] = set()
        for b in self.blocks or ():
            # groups are sorted by owner, then level: the query's and the object's are runs
            g0, g1 = np.searchsorted(b.rq, q), np.searchsorted(b.rq, q, side="right")
            h0, h1 = np.searchsorted(b.co, m), np.searchsorted(b.co, m, side="right")
            levels = b.cl[h0:h1].tolist()
            for g in range(g0, g1):
                level = int(b.rl[g])
                if b.axis < 3 and self.mirror[q, m, b.axis]:
                    level = N - 1 - level
                if level not in levels:
                    continue
                h = h0 + levels.index(level)
                stop = b.rs[g + 1] if g + 1 < len(b.rs) else len(b.qsel)
                found.update(b.osel[b.nearest[b.rs[g] : stop, h]].tolist())
        return np.array(sorted(found), dtype=np.int64)


def _groups(owner: np.ndarray, level: np.ndarray):
    """Positions sorted by (owner, level), the starts of each (owner, level) run and the
    run's owner and level."""
    order = np.lexsort((level, owner))
    o, lv = owner[order], level[order]
    new = np.ones(len(order), dtype=bool)
    new[1:] = (o[1:] != o[:-1]) | (lv[1:] != lv[:-1])
    starts = np.flatnonzero(new)
    return order, starts, o[starts], lv[starts]


def _level_sets(D: np.ndarray, wr: np.ndarray, wc: np.ndarray, rs: np.ndarray, cs: np.ndarray) -> np.ndarray:
    """Symmetric weighted set distances between row groups and column groups of ``D``
    (rows and columns already sorted by group; ``rs``, ``cs`` group starts; ``wr``, ``wc``
    the loops' weights): (row groups, column groups)."""
    row_min = np.minimum.reduceat(D, cs, axis=1)  # (rows, col groups)
    wsum_r = np.add.reduceat(wr, rs)
    a = np.add.reduceat(wr[:, None] * row_min, rs, axis=0) / wsum_r[:, None]
    col_min = np.minimum.reduceat(D, rs, axis=0)  # (row groups, cols)
    wsum_c = np.add.reduceat(wc, cs)
    b = np.add.reduceat(col_min * wc[None, :], cs, axis=1) / wsum_c[None, :]
    return 0.5 * (a + b)


@dataclass
class _Block:
    """One matrix of loop distances, kept for the matched contours: query rows ``qsel`` and
    object columns ``osel`` (sorted by owner and level), the row groups (starts ``rs``,
    owner ``rq``, level ``rl``), the column groups (``co``, ``cl``) and ``nearest`` (rows,
    column groups): the column (into ``osel``) of each row's nearest loop in each group."""

    axis: int
    qsel: np.ndarray
    osel: np.ndarray
    rs: np.ndarray
    rq: np.ndarray
    rl: np.ndarray
    co: np.ndarray
    cl: np.ndarray
    nearest: np.ndarray


def _nearest_in_groups(D: np.ndarray, cs: np.ndarray) -> np.ndarray:
    """(rows, column groups): each row's first column of least distance within each group."""
    row_min = np.minimum.reduceat(D, cs, axis=1)
    counts = np.diff(np.append(cs, D.shape[1]))
    cols = np.arange(D.shape[1])[None, :]
    at = np.where(D == np.repeat(row_min, counts, axis=1), cols, D.shape[1])
    return np.minimum.reduceat(at, cs, axis=1).astype(np.int64)


def _present(loops: ObjectLoops, axes: int, N: int) -> np.ndarray:
    """(M, axes, N) bool: where the objects have loops."""
    has = np.zeros((loops.n_objects, axes, N), dtype=bool)
    has[loops.owner, loops.axis.astype(np.int64), loops.level.astype(np.int64)] = True
    return has


def _weights(loops: ObjectLoops) -> np.ndarray:
    # relative perimeter: a torso loop counts more than a finger loop of the same level
    return np.exp(loops.measures[:, 0])


def _block(q: ObjectLoops, o: ObjectLoops, qsel, osel, samples: int, processes: int, loop=(1.0, SIZE_WEIGHT)):
    """The loop distances of the selected query loops against the selected object loops;
    ``loop``: the weights of the shape (exact distance; 0: not computed) and size terms,
    and optionally ``"bound"``: the shape term is the invariant lower bound of the exact
    distance instead (:func:`~nfdmatch.search.bounds.row_lower_bounds_many`)."""
    D = np.zeros((len(qsel), len(osel)))
    if loop[0] and len(loop) > 2 and loop[2] == "bound":
        fq, _ = _features(q)
        fo, no = _features(o)
        D += loop[0] * row_lower_bounds_many(fq[qsel].astype(np.float64), fq.shape[1] - 3, fo[osel], no[osel])
    elif loop[0]:
        D += loop[0] * cross_distances(
            q.coefficients[qsel].astype(np.complex128), o.coefficients[osel].astype(np.complex128), samples,
            processes=processes,
        )  # fmt: skip
    D += loop[1] * np.abs(q.measures[qsel, 0][:, None] - o.measures[osel, 0][None, :])
    return D


def _features(loops: ObjectLoops) -> tuple[np.ndarray, np.ndarray]:
    """The loops' invariant features (float32, the layout of ``/search/features``) and their
    squared norms, computed once from the stored coefficients."""
    if loops.features is None:
        F = feature_vector(loops.coefficients.astype(np.complex128)).astype(np.float32)
        loops.features = (F, squared_norms(F, F.shape[1] - 3))
    return loops.features


def _axis_sets(q: ObjectLoops, o: ObjectLoops, a: int, samples: int, processes: int, loop, blocks) -> np.ndarray:
    """(Q, M, N, 2): the level set distances of axis ``a``, each query level i against the
    object's level i (order 0) and N - 1 - i (order 1); NaN where neither has loops,
    EMPTY_LEVEL where one has none. Each matrix's :class:`_Block` is appended to ``blocks``."""
    N = q.sections
    Q, M = q.n_objects, o.n_objects
    hq, ho = _present(q, 4, N)[:, a], _present(o, 4, N)[:, a]  # (Q, N), (M, N); axis 3: boundaries
    out = np.full((Q, M, N, 2), np.nan)
    for s in range(2):
        j = np.arange(N) if s == 0 else np.arange(N)[::-1]
        either = hq[:, None, :] | ho[None, :, j]
        out[..., s] = np.where(either, EMPTY_LEVEL, np.nan)
    for i in range((N + 1) // 2):
        pair = np.array(sorted({i, N - 1 - i}))
        qsel = np.flatnonzero((q.axis == a) & np.isin(q.level, pair))
        osel = np.flatnonzero((o.axis == a) & np.isin(o.level, pair))
        if not len(qsel) or not len(osel):
            continue
        qo, rs, rq, rl = _groups(q.owner[qsel], q.level[qsel])
        oo, cs, co, cl = _groups(o.owner[osel], o.level[osel])
        qsel, osel = qsel[qo], osel[oo]
        D = _block(q, o, qsel, osel, samples, processes, loop)
        L = _level_sets(D, _weights(q)[qsel], _weights(o)[osel], rs, cs)
        blocks.append(_Block(a, qsel, osel, rs, rq, rl, co, cl, _nearest_in_groups(D, cs)))
        qi, oi = np.meshgrid(np.arange(len(rq)), np.arange(len(co)), indexing="ij")
        qi, oi = qi.ravel(), oi.ravel()
        lq, lo = rl[qi].astype(np.int64), cl[oi].astype(np.int64)
        same = lq == lo
        out[rq[qi[same]], co[oi[same]], lq[same], 0] = L[qi[same], oi[same]]
        mirror = lq == N - 1 - lo
        out[rq[qi[mirror]], co[oi[mirror]], lq[mirror], 1] = L[qi[mirror], oi[mirror]]
    return out


def _boundary_sets(q: ObjectLoops, o: ObjectLoops, samples: int, processes: int, loop, blocks) -> np.ndarray:
    """(Q, M): the set distance of the boundary loops; NaN where neither object has any."""
    hq = np.zeros(q.n_objects, dtype=bool)
    ho = np.zeros(o.n_objects, dtype=bool)
    hq[q.owner[q.axis == BOUNDARY_AXIS]] = True
    ho[o.owner[o.axis == BOUNDARY_AXIS]] = True
    out = np.where(hq[:, None] | ho[None, :], EMPTY_LEVEL, np.nan)
    qsel, osel = np.flatnonzero(q.axis == BOUNDARY_AXIS), np.flatnonzero(o.axis == BOUNDARY_AXIS)
    if len(qsel) and len(osel):
        qo, rs, rq, rl = _groups(q.owner[qsel], q.level[qsel])
        oo, cs, co, cl = _groups(o.owner[osel], o.level[osel])
        qsel, osel = qsel[qo], osel[oo]
        D = _block(q, o, qsel, osel, samples, processes, loop)
        out[np.ix_(rq, co)] = _level_sets(D, _weights(q)[qsel], _weights(o)[osel], rs, cs)
        blocks.append(_Block(BOUNDARY_AXIS, qsel, osel, rs, rq, rl, co, cl, _nearest_in_groups(D, cs)))
    return out


def object_distances(
    queries: ObjectLoops,
    objects: ObjectLoops,
    samples: int,
    *,
    processes: int = 1,
    weights: tuple[float, float] = (1.0, 1.0),
    loop: tuple[float, float] = (1.0, SIZE_WEIGHT),
) -> ObjectDistances:
    """The object distance (module doc) of every query object against every object: (Q, M).

    ``samples``: the descriptors' sample count; ``processes``: forked workers for the loop
    distances; ``weights``: of the curves' and the profile's terms, ``loop``: of a loop
    distance's shape and size terms (the defaults are the distance; the benchmark's
    ablations set some to 0: a shape weight 0 computes no exact distance)."""
    N = objects.sections
    if queries.sections != N:
        from ..errors import ParameterError

        raise ParameterError(f"objects cut with {queries.sections} and {N} sections cannot be compared")
    Q, M = queries.n_objects, objects.n_objects
    F = queries.profile.shape[1] // (3 * N)
    pq = queries.profile.reshape(Q, 3, N, F) / PROFILE_UNITS
    po = objects.profile.reshape(M, 3, N, F) / PROFILE_UNITS
    curves = np.zeros((Q, M))
    profile = np.zeros((Q, M))
    total = np.zeros((Q, M))
    mirror = np.zeros((Q, M, 3), dtype=bool)
    blocks: list = []
    for a in range(3):
        sets = _axis_sets(queries, objects, a, samples, processes, loop, blocks)  # (Q, M, N, 2)
        counted = (~np.isnan(sets)).sum(axis=2)
        shape = np.where(counted > 0, np.nansum(sets, axis=2) / np.maximum(counted, 1), 0.0) / SHAPE_SCALE
        prof = np.empty((Q, M, 2))
        for s in range(2):
            j = np.arange(N) if s == 0 else np.arange(N)[::-1]
            prof[..., s] = np.abs(pq[:, None, a] - po[None, :, a][:, :, j]).mean(axis=(2, 3)) / PROFILE_SCALE
        fused = weights[0] * shape + weights[1] * prof  # (Q, M, 2)
        best = np.argmin(fused, axis=2)  # ties: the direct order
        pick = best[..., None]
        total += np.take_along_axis(fused, pick, axis=2)[..., 0]
        curves += np.take_along_axis(shape, pick, axis=2)[..., 0]
        profile += np.take_along_axis(prof, pick, axis=2)[..., 0]
        mirror[..., a] = best == 1
    boundary = _boundary_sets(queries, objects, samples, processes, loop, blocks) / SHAPE_SCALE
    parts = 3.0 + ~np.isnan(boundary)
    boundary = np.nan_to_num(boundary, nan=0.0)
    total = (total + weights[0] * boundary) / parts
    curves = (curves + boundary) / parts
    profile = profile / parts
    return ObjectDistances(distance=total, curves=curves, profile=profile, mirror=mirror, blocks=blocks, sections=N)


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
    obits, oprof = _per_object(objects)  # (M, 4, 2) level bitmasks, (M, 3, 2, N F) profiles
    width = oprof.shape[-1]
    total = np.zeros(objects.n_objects)
    diff = np.empty((objects.n_objects, width))
    for a in range(3):
        best = None
        for s in range(2):  # the object's levels in order, then mirrored (the query's in order)
            either = np.bitwise_count(qbits[0, a, 0] | obits[:, a, s])
            one = np.bitwise_count(qbits[0, a, 0] ^ obits[:, a, s])
            shape = EMPTY_LEVEL * one / np.maximum(either, 1) / SHAPE_SCALE
            np.subtract(oprof[:, a, s], qprof[0, a, 0], out=diff)
            prof = np.abs(diff, out=diff).sum(axis=1) / (width * PROFILE_SCALE)
            best = shape + prof if best is None else np.minimum(best, shape + prof)
        total += best
    bq, bo = qbits[0, BOUNDARY_AXIS, 0] != 0, obits[:, BOUNDARY_AXIS, 0] != 0
    total += np.where(bq ^ bo, EMPTY_LEVEL / SHAPE_SCALE, 0.0)
    return total / (3.0 + (bq | bo))


def _per_object(loops: ObjectLoops) -> tuple[np.ndarray, np.ndarray]:
    """Per object, made once per set of objects: its levels with loops as bitmasks (M, 4, 2)
    uint64 (bit i: level i; then with the levels mirrored) and its profile over the units
    (M, 3, 2, N F), the levels in order and mirrored."""
    if loops.per_object is None:
        N = loops.sections
        if N > 64:
            raise ValueError("at most 64 sections")
        has = _present(loops, 4, N)
        weights = np.left_shift(np.uint64(1), np.arange(N, dtype=np.uint64))
        bits = np.stack([(has * weights).sum(axis=2), (has[:, :, ::-1] * weights).sum(axis=2)], axis=2)
        F = loops.profile.shape[1] // (3 * N)
        prof = loops.profile.reshape(-1, 3, N, F) / PROFILE_UNITS
        both = np.stack([prof, prof[:, :, ::-1]], axis=2).reshape(-1, 3, 2, N * F)
        loops.per_object = (bits.astype(np.uint64), np.ascontiguousarray(both))
    return loops.per_object


#: objects whose exact distance is computed in the first round of :func:`nearest_objects`
#: (each next round twice as many)
_ROUND = 32


@dataclass(frozen=True)
class FoundObject:
    """One object's exact distance to a query: its ``position`` among the objects, the
    ``distance``, its ``curves`` and ``profile`` parts, and ``matched``: its loops (their
    ``rows``, or positions among the objects' loops when they have no rows) that were the
    nearest of some query loop."""

    position: int
    distance: float
    curves: float
    profile: float
    matched: tuple


def nearest_objects(
    query: ObjectLoops,
    objects: ObjectLoops,
    samples: int,
    *,
    k: int | None,
    max_distance: float | None = None,
    skip=(),
    order_rank=None,
    processes: int = 1,
    prune: bool = True,
    first_round: int = _ROUND,
) -> list[FoundObject]:
    """One query object's (``query``: one owner) nearest objects, exactly, nearest first
    (ties by ``order_rank`` (M,), default the position): the best ``k`` (None: all) within
    ``max_distance``; ``skip``: positions left out (the query's own object).

    With ``prune`` the objects are filtered by :func:`object_coarse_bounds` (the nearest of
    them by it computed first, to know a k-th distance), then visited in increasing
    :func:`object_lower_bounds` order, in rounds of exact distances (``first_round``, at
    least 2 k, then twice as many each round), until the next bound exceeds the k-th
    distance found (or ``max_distance``): every object left is provably no nearer. Without
    it every object's exact distance is computed (the reference)."""
    M = objects.n_objects
    rank = np.arange(M) if order_rank is None else np.asarray(order_rank)
    if not prune:
        return all_nearest_objects(
            query, objects, samples, k=k, max_distance=max_distance, skips={0: skip}, order_rank=rank,
            processes=processes,
        )[0]  # fmt: skip
    alive = np.ones(M, dtype=bool)
    alive[list(skip)] = False
    # a cascade, cheapest first: per-object numbers for every object, then the loops'
    # invariant bounds for the objects that pass, then exact distances in rounds
    coarse = object_coarse_bounds(query, objects)
    limit = np.inf if max_distance is None else max_distance
    alive &= coarse <= limit
    first = max(first_round, 2 * (k or 0), 1)
    order = np.flatnonzero(alive)
    order = order[np.lexsort((rank[order], coarse[order]))][:first]
    found = _exact(query, objects, order.tolist(), samples, processes)
    best = _best(found, k, max_distance, rank)
    if k is not None and len(best) == k:
        limit = min(limit, best[-1].distance)
    alive[order] = False
    alive &= coarse <= limit
    left = np.flatnonzero(alive)
    bound = np.full(M, np.inf)
    if len(left):
        bound[left] = object_lower_bounds(query, objects.subset(left))[0]
    left = left[bound[left] <= limit]
    left = left[np.lexsort((rank[left], bound[left]))].tolist()
    at, size = 0, first
    while at < len(left):
        found += _exact(query, objects, left[at : at + size], samples, processes)
        at, size = at + size, 2 * size
        best = _best(found, k, max_distance, rank)
        if k is not None and len(best) == k and at < len(left) and bound[left[at]] > best[-1].distance:
            break
    return _best(found, k, max_distance, rank)


def all_nearest_objects(
    queries: ObjectLoops,
    objects: ObjectLoops,
    samples: int,
    *,
    k: int | None,
    max_distance: float | None = None,
    skips=None,
    order_rank=None,
    processes: int = 1,
) -> list[list[FoundObject]]:
    """Every query object's nearest objects (as :func:`nearest_objects` without pruning),
    every object distance computed in one pass for all queries; ``skips``: ``{query:
    positions left out}``."""
    rank = np.arange(objects.n_objects) if order_rank is None else np.asarray(order_rank)
    d = object_distances(queries, objects, samples, processes=processes)
    out = []
    for q in range(queries.n_objects):
        skip = set((skips or {}).get(q, ()))
        order = [m for m in range(objects.n_objects) if m not in skip]
        if max_distance is not None:
            order = [m for m in order if d.distance[q, m] <= max_distance]
        order.sort(key=lambda m: (d.distance[q, m], rank[m]))
        found = []
        for m in order[:k] if k is not None else order:
            loops = d.matched(q, m)
            matched = objects.rows[loops] if objects.rows is not None else loops
            found.append(FoundObject(m, float(d.distance[q, m]), float(d.curves[q, m]), float(d.profile[q, m]),
                                     tuple(int(r) for r in matched)))  # fmt: skip
        out.append(found)
    return out


def _exact(query: ObjectLoops, objects: ObjectLoops, chosen: list, samples: int, processes: int):
    """The :class:`FoundObject` of each of the objects ``chosen``."""
    if not chosen:
        return []
    part = objects.subset(chosen)
    d = object_distances(query, part, samples, processes=processes)
    out = []
    for i, m in enumerate(chosen):
        loops = d.matched(0, i)
        if part.rows is not None:
            matched = part.rows[loops]
        else:  # positions among all the objects' loops
            matched = _positions(objects, m)[loops - np.searchsorted(part.owner, i)]
        out.append(FoundObject(m, float(d.distance[0, i]), float(d.curves[0, i]), float(d.profile[0, i]),
                               tuple(int(r) for r in matched)))  # fmt: skip
    return out


def _positions(objects: ObjectLoops, m: int) -> np.ndarray:
    """The positions of object ``m``'s loops among the objects' loops."""
    return np.arange(np.searchsorted(objects.owner, m), np.searchsorted(objects.owner, m, side="right"))


def _best(found: list, k, max_distance, rank) -> list:
    kept = [f for f in found if max_distance is None or f.distance <= max_distance]
    kept.sort(key=lambda f: (f.distance, rank[f.position]))
    return kept[:k] if k is not None else kept


@dataclass(frozen=True)
class ObjectMatch:
    """One object answer of a mesh query: ``rank`` (1-based), ``id`` (the object's mesh
    path, as the index stores it), ``distance`` (the object distance), ``curves`` (the ids
    of its contours that were the nearest of some query contour), ``terms``
    (``{"curves": ..., "profile": ...}``: the two parts of the distance)."""

    rank: int
    id: str
    distance: float
    curves: tuple = ()
    terms: dict | None = None


def object_loops(cuts, samples: int, harmonics: int, scale: str) -> ObjectLoops:
    """The :class:`ObjectLoops` of cut objects (:class:`~nfdmatch.mesh.objects.ObjectCut`),
    described as an index stores its rows (complex64), one owner per cut."""
    from ..descriptors import descriptors_batch

    cuts = list(cuts)
    loops = [c for cut in cuts for c in cut.loops]
    batch = descriptors_batch(loops, samples=samples, harmonics=harmonics, scale=scale)
    return ObjectLoops(
        coefficients=batch.coefficients.astype(np.complex64),
        axis=np.concatenate([c.axis for c in cuts]),
        level=np.concatenate([c.level for c in cuts]),
        measures=np.concatenate([c.measures for c in cuts]),
        owner=np.repeat(np.arange(len(cuts)), [len(c.loops) for c in cuts]),
        profile=np.array([c.profile for c in cuts]).reshape(len(cuts), -1),
        sections=cuts[0].rule.sections if cuts else 0,
    )


def search_objects(
    index,
    meshes,
    *,
    k: int | None = 10,
    max_distance: float | None = None,
    exclude_self: bool = False,
    processes: int | None = None,
    names=None,
    failures: list | None = None,
    prune: bool = True,
) -> list[list[ObjectMatch]]:
    """Each query mesh's nearest objects of ``index`` (an index with objects: its
    ``objects()`` and ``object_loops()``), by the object distance.

    meshes : mesh paths or ``trimesh.Trimesh`` objects, each cut by the index's recorded
        rule (:func:`~nfdmatch.mesh.objects.cut_object`).
    k : answers per query (None: every object within ``max_distance``).
    exclude_self : drop the object whose mesh is the query's file (however its path is
        spelled).
    processes : forked workers for the loop distances (None: the cores).
    names : what the queries are called in messages (default: their paths).
    failures : a list: a mesh that cannot be cut is appended as ``(position, NfdError)``
        and answered with no match, the others answered; None: its error is raised.
    prune : visit the objects by a proven lower bound of the object distance and stop when
        no other can be nearer (:func:`nearest_objects`); False: every object's distance
        (the same answer, ``query --exhaustive``).

    Returns one list per query, sorted by distance then id. Raises InputError when the
    index holds no object; what :func:`~nfdmatch.mesh.objects.cut_object` raises for a
    bad mesh (without ``failures``).
    """
    import os

    from ..errors import InputError, ParameterError
    from .selfmatch import self_rule

    if k is None and max_distance is None:
        raise ParameterError("give k or max_distance (or both)")
    if k is not None and (isinstance(k, bool) or int(k) < 1):
        raise ParameterError(f"k must be >= 1, got {k!r}")
    groups = index.objects()
    if groups is None:
        raise InputError("the index holds no mesh objects (build it from meshes to query it with a mesh)")
    processes = (os.cpu_count() or 1) if processes is None else int(processes)
    if not isinstance(meshes, (list, tuple)):
        meshes = [meshes]
    names = list(names) if names is not None else [
        str(os.fspath(m)) if isinstance(m, (str, os.PathLike)) else f"<mesh {i}>" for i, m in enumerate(meshes)
    ]  # fmt: skip
    cuts, cut_at = _cut_queries(meshes, names, groups.rule, processes, failures)
    if not cuts:
        return [[] for _ in names]
    queries = object_loops(cuts, index.samples, index.harmonics, index.scale_mode)
    objects = index.object_loops()
    ids = index.object_ids()
    rule = self_rule(index.locate) if exclude_self else None
    rank_of = np.empty(len(ids), dtype=np.int64)
    rank_of[sorted(range(len(ids)), key=ids.__getitem__)] = np.arange(len(ids))  # ties by id
    skips = {}
    for position, given in enumerate(meshes):
        if position in cut_at and rule is not None and isinstance(given, (str, os.PathLike)):
            skips[cut_at[position]] = [m for m in range(len(ids)) if rule(str(given), ids[m])]
    how = dict(k=k, max_distance=max_distance, order_rank=rank_of, processes=processes)
    if prune and k is not None and 4 * k <= objects.n_objects:
        found = [
            nearest_objects(queries.subset([q]), objects, index.samples, skip=skips.get(q, ()), **how)
            for q in range(len(cuts))
        ]
    else:  # most objects are answers anyway: every distance, all queries in one pass
        found = all_nearest_objects(queries, objects, index.samples, skips=skips, **how)
    return [_answers(index, found[cut_at[p]], ids) if p in cut_at else [] for p in range(len(meshes))]


def _cut_queries(meshes, names, rule, processes: int, failures):
    """The query meshes cut by ``rule`` over forked workers (each mesh alone: 0.1-0.5 s of
    numpy): ``(cuts, {query position: its cut's number})``; a mesh that cannot be cut goes
    to ``failures`` (``(position, NfdError)``), or its error is raised when that is None."""
    from ..errors import NfdError
    from ..mesh.objects import cut_object

    cut_of: dict = {}

    def cut(task, _threads):
        try:
            return cut_object(meshes[task], rule, name=names[task])
        except NfdError as exc:
            return exc

    run_tasks(list(range(len(meshes))), cut, cut_of.__setitem__, processes)
    cuts, cut_at = [], {}
    for q in range(len(meshes)):
        if isinstance(cut_of[q], NfdError):
            if failures is None:
                raise cut_of[q]
            failures.append((q, cut_of[q]))
            continue
        cut_at[q] = len(cuts)
        cuts.append(cut_of[q])
    return cuts, cut_at


def _answers(index, found: list, ids) -> list[ObjectMatch]:
    """The :class:`ObjectMatch` records of a query's ranked :class:`FoundObject` (the ids of
    their matched contours read in one call)."""
    rows = sorted({r for f in found for r in f.matched})
    id_of = dict(zip(rows, index.ids_at(np.asarray(rows, dtype=np.int64)))) if rows else {}
    return [
        ObjectMatch(
            rank=rank,
            id=ids[f.position],
            distance=f.distance,
            curves=tuple(id_of[r] for r in f.matched),
            terms={"curves": f.curves, "profile": f.profile},
        )
        for rank, f in enumerate(found, start=1)
    ]
