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

The proven lower bounds of this distance are in :mod:`.object_bounds`, the search that
uses them in :mod:`.objects`. This module never imports ``index/``: it works on
:class:`ObjectLoops`, which the index reader (``Index.object_loops``) and
:func:`object_loops` (a cut in memory) both make.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..mesh.objects import BOUNDARY_AXIS
from .bounds import feature_vector, row_lower_bounds_many, squared_norms
from .matrix import cross_distances

__all__ = [
    "SIZE_WEIGHT",
    "EMPTY_LEVEL",
    "SHAPE_SCALE",
    "PROFILE_SCALE",
    "PROFILE_UNITS",
    "ObjectLoops",
    "ObjectDistances",
    "object_distances",
    "object_loops",
    "present_levels",
    "StoredRows",
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


class StoredRows:
    """A per-loop array left where it is stored (an index file): ``read(rows)`` reads the
    given rows (any order) and gives them back in that order. :meth:`take` narrows it to some
    loops without reading; :meth:`load` reads them. What :class:`ObjectLoops` of an index
    hold for the descriptors and the invariant features, so that a query reads the rows of
    the objects its bounds reach, not those of every object."""

    def __init__(self, rows: np.ndarray, read: Callable[[np.ndarray], np.ndarray]) -> None:
        self.rows = np.asarray(rows, dtype=np.int64)
        self.read = read

    def __len__(self) -> int:
        return len(self.rows)

    def take(self, pick: Any) -> StoredRows:
        return StoredRows(self.rows[pick], self.read)

    def load(self) -> np.ndarray:
        return self.read(self.rows)


def _take(values, pick):
    """``values`` (an array, a tuple of arrays, :class:`StoredRows` or None) at the loops ``pick``."""
    if values is None:
        return None
    if isinstance(values, StoredRows):
        return values.take(pick)
    if isinstance(values, tuple):
        return tuple(v[pick] for v in values)
    return values[pick]


@dataclass
class ObjectLoops:
    """Loops of M objects: ``coefficients`` (L, K, 3) complex (stored descriptors, or
    :class:`StoredRows` of them, read on first use), ``axis`` (L,), ``level`` (L,),
    ``measures`` (L, 3) (``log relative perimeter, relative area, elongation``), ``owner``
    (L,) int: the object of each loop (0..M-1), ``profile`` (M, 3 N 4), ``sections`` N,
    ``rows`` (L,): what a loop is called by its caller (index rows; None: 0..L-1)."""

    coefficients: np.ndarray | StoredRows
    axis: np.ndarray
    level: np.ndarray
    measures: np.ndarray
    owner: np.ndarray
    profile: np.ndarray
    sections: int
    rows: np.ndarray | None = None
    #: the loops' invariant features and their squared norms (bounds): given, or
    #: :class:`StoredRows` of the features (read on first use), or None (made from the
    #: descriptors on first use)
    features: tuple | StoredRows | None = None
    #: presence and scaled profile per object, made on first use (coarse bounds)
    per_object: tuple | None = None

    @property
    def n_objects(self) -> int:
        return int(len(self.profile))

    def subset(self, chosen: Any) -> ObjectLoops:
        """Objects ``chosen`` (positions, in that order) alone, renumbered 0..len-1 (the loops
        of each object must be one run, in owner order, as the readers make them); stored
        rows stay unread."""
        chosen = np.asarray(chosen, dtype=np.int64)
        starts = np.searchsorted(self.owner, chosen)
        stops = np.searchsorted(self.owner, chosen, side="right")
        pick = np.concatenate([np.arange(a, b) for a, b in zip(starts, stops)]) if len(chosen) else np.zeros(0, int)
        return ObjectLoops(
            coefficients=_take(self.coefficients, pick),
            axis=self.axis[pick],
            level=self.level[pick],
            measures=self.measures[pick],
            owner=np.repeat(np.arange(len(chosen)), stops - starts),
            profile=self.profile[chosen],
            sections=self.sections,
            rows=None if self.rows is None else self.rows[pick],
            features=_take(self.features, pick),
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


def present_levels(loops: ObjectLoops, axes: int, N: int) -> np.ndarray:
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
            _coefficients(q)[qsel].astype(np.complex128), _coefficients(o)[osel].astype(np.complex128), samples,
            processes=processes,
        )  # fmt: skip
    D += loop[1] * np.abs(q.measures[qsel, 0][:, None] - o.measures[osel, 0][None, :])
    return D


def _coefficients(loops: ObjectLoops) -> np.ndarray:
    """The loops' descriptors, read once when they are stored rows."""
    if isinstance(loops.coefficients, StoredRows):
        loops.coefficients = np.asarray(loops.coefficients.load())
    return loops.coefficients


def _features(loops: ObjectLoops) -> tuple[np.ndarray, np.ndarray]:
    """The loops' invariant features (float32, the layout of ``/search/features``) and their
    squared norms: read once when they are stored rows, else computed once from the
    descriptors."""
    if isinstance(loops.features, StoredRows):
        F = np.asarray(loops.features.load(), dtype=np.float32)
        loops.features = (F, squared_norms(F, F.shape[1] - 3))
    elif loops.features is None:
        F = feature_vector(_coefficients(loops).astype(np.complex128)).astype(np.float32)
        loops.features = (F, squared_norms(F, F.shape[1] - 3))
    return loops.features


def _axis_sets(q: ObjectLoops, o: ObjectLoops, a: int, samples: int, processes: int, loop, blocks) -> np.ndarray:
    """(Q, M, N, 2): the level set distances of axis ``a``, each query level i against the
    object's level i (order 0) and N - 1 - i (order 1); NaN where neither has loops,
    EMPTY_LEVEL where one has none. Each matrix's :class:`_Block` is appended to ``blocks``."""
    N = q.sections
    Q, M = q.n_objects, o.n_objects
    hq, ho = present_levels(q, 4, N)[:, a], present_levels(o, 4, N)[:, a]  # (Q, N), (M, N); axis 3: boundaries
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


def object_loops(cuts: Any, samples: int, harmonics: int, scale: str) -> ObjectLoops:
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
