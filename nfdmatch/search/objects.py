"""Objects by their curves: a mesh query's nearest objects (docs/objects.md).

A query (:func:`search_objects`, :func:`nearest_objects`) visits the objects through a
cascade of proven lower bounds of the object distance (:mod:`.object_bounds`:
:func:`object_coarse_bounds`, per-object numbers; :func:`object_lower_bounds`, the loops'
invariant bounds), then exact distances (:mod:`.object_distance`), and stops when no object
left can be nearer (docs/objects.md, "The search"). The names of those two modules are
also reached from here.

Test hooks: ``_exact`` (the exact distances of a round of :func:`nearest_objects`) and
``object_lower_bounds`` are replaced in this module by a test and the benchmark to count
the objects each stage reached.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from .object_bounds import object_coarse_bounds, object_lower_bounds
from .object_distance import (
    ObjectLoops,
    object_distances,
    object_loops,
)
from .workers import run_tasks

if TYPE_CHECKING:
    from collections.abc import Iterable, Sequence

    from numpy.typing import ArrayLike

    from ..errors import NfdError
    from ..index import Index
    from ..mesh.objects import ObjectCut, ObjectRule
    from .object_distance import ObjectDistances

__all__ = ["ObjectMatch", "FoundObject", "nearest_objects", "all_nearest_objects", "search_objects"]


#: objects whose exact distance is computed in the first round of :func:`nearest_objects`
#: (each next round twice as many)
_ROUND = 32


@dataclass(frozen=True)
class FoundObject:
    """One object's exact distance to a query: its ``position`` among the objects, the
    ``distance``, its ``curves`` and ``profile`` parts, and ``matched``: its loops (their
    ``rows``, or positions among the objects' loops when they have no rows) that were the
    nearest of some query loop; ``mirror``: per principal axis, whether the better order was
    the mirrored one (the object's axis taken the other way round)."""

    position: int
    distance: float
    curves: float
    profile: float
    matched: tuple
    mirror: tuple = (False, False, False)


def nearest_objects(
    query: ObjectLoops,
    objects: ObjectLoops,
    samples: int,
    *,
    k: int | None,
    max_distance: float | None = None,
    skip: Sequence[int] = (),
    order_rank: ArrayLike | None = None,
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
    skips: dict[int, Sequence[int]] | None = None,
    order_rank: ArrayLike | None = None,
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
                                     tuple(int(r) for r in matched), _mirror(d, q, m)))  # fmt: skip
        out.append(found)
    return out


def _exact(
    query: ObjectLoops, objects: ObjectLoops, chosen: list[int], samples: int, processes: int
) -> list[FoundObject]:
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
                               tuple(int(r) for r in matched), _mirror(d, 0, i)))  # fmt: skip
    return out


def _mirror(d: ObjectDistances, q: int, m: int) -> tuple:
    return tuple(bool(v) for v in d.mirror[q, m])


def _positions(objects: ObjectLoops, m: int) -> np.ndarray:
    """The positions of object ``m``'s loops among the objects' loops."""
    return np.arange(np.searchsorted(objects.owner, m), np.searchsorted(objects.owner, m, side="right"))


def _best(found: list[FoundObject], k: int | None, max_distance: float | None, rank: np.ndarray) -> list[FoundObject]:
    kept = [f for f in found if max_distance is None or f.distance <= max_distance]
    kept.sort(key=lambda f: (f.distance, rank[f.position]))
    return kept[:k] if k is not None else kept


@dataclass(frozen=True)
class ObjectMatch:
    """One object answer of a mesh query: ``rank`` (1-based), ``id`` (the object's mesh
    path, as the index stores it), ``distance`` (the object distance), ``curves`` (the ids
    of its contours that were the nearest of some query contour), ``terms``
    (``{"curves": ..., "profile": ...}``: the two parts of the distance), ``mirror``: per
    principal axis, whether the object's axis was taken the other way round (the better of
    the two orders; what ``show`` flips to draw it beside the query)."""

    rank: int
    id: str
    distance: float
    curves: tuple = ()
    terms: dict | None = None
    mirror: tuple = (False, False, False)


def search_objects(
    index: Index,
    meshes: Any,
    *,
    k: int | None = 10,
    max_distance: float | None = None,
    exclude_self: bool = False,
    processes: int | None = None,
    names: Iterable[str] | None = None,
    failures: list | None = None,
    prune: bool = True,
    cuts: list | None = None,
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
    cuts : a list: receives each query's :class:`~nfdmatch.mesh.objects.ObjectCut` (None for
        a mesh that could not be cut), in query order: what ``show`` draws.

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
    made, cut_at = _cut_queries(meshes, names, groups.rule, processes, failures)
    if cuts is not None:
        cuts.extend(made[cut_at[p]] if p in cut_at else None for p in range(len(meshes)))
    if not made:
        return [[] for _ in names]
    queries = object_loops(made, index.samples, index.harmonics, index.scale_mode)
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
            for q in range(len(made))
        ]
    else:  # most objects are answers anyway: every distance, all queries in one pass
        found = all_nearest_objects(queries, objects, index.samples, skips=skips, **how)
    return [_answers(index, found[cut_at[p]], ids) if p in cut_at else [] for p in range(len(meshes))]


def _cut_queries(
    meshes: Sequence[Any], names: list[str], rule: ObjectRule, processes: int, failures: list | None
) -> tuple[list[ObjectCut], dict[int, int]]:
    """The query meshes cut by ``rule`` over forked workers (each mesh alone: 0.1-0.5 s of
    numpy): ``(cuts, {query position: its cut's number})``; a mesh that cannot be cut goes
    to ``failures`` (``(position, NfdError)``), or its error is raised when that is None.
    An error that is not nfdmatch's (a fault of the cutting itself) is that mesh's
    MeshError "unexpected error", as a build reports it: one mesh does not end the query."""
    from ..errors import MeshError, NfdError
    from ..mesh.objects import cut_object

    cut_of: dict = {}

    def cut(task: int, _threads: int) -> ObjectCut | NfdError:
        try:
            return cut_object(meshes[task], rule, name=names[task])
        except NfdError as exc:
            return exc
        except Exception as exc:
            return MeshError(f"unexpected error: {type(exc).__name__}: {exc}", path=names[task])

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


def _answers(index: Index, found: list[FoundObject], ids: Sequence[str]) -> list[ObjectMatch]:
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
            mirror=f.mirror,
        )
        for rank, f in enumerate(found, start=1)
    ]
