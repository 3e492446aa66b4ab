"""The k nearest curves of an index for each query, as a Python user asks for them
(:meth:`nfdmatch.index.Index.search`). The rule that drops a query's own curve from its
matches (``exclude_self``) is ``selfmatch.py``'s, re-exported here.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

from ..curve import Curve
from ..errors import ParameterError
from ..matching import DEFAULT_DIRECTION, DEFAULT_METHOD
from ..records import RankedMatch
from .limits import check_limits
from .selfmatch import drop_self, is_self, self_rule

if TYPE_CHECKING:
    from ..descriptors import Descriptors

__all__ = [
    "as_queries", "is_mesh_query", "self_rule", "is_self", "drop_self", "search", "SearchFace", "as_arrays",
    "stored_descriptors", "DEFAULT_K",
]  # fmt: skip


def as_queries(queries: Any) -> list[Curve]:
    """Query curves from what a user holds: one or a sequence of :class:`~nfdmatch.Curve`,
    (n, 3) or (n, 2) float arrays (ids ``<array i>``) and paths (str or PathLike: every curve
    of the file; ``"file#i"`` for one)."""
    from ..formats import read_curve, read_curves, split_selector

    if isinstance(queries, (Curve, str, os.PathLike)) or (isinstance(queries, np.ndarray) and queries.ndim == 2):
        queries = [queries]
    out: list[Curve] = []
    for i, q in enumerate(queries):
        if isinstance(q, Curve):
            out.append(q)
        elif isinstance(q, (str, os.PathLike)):
            _, selected = split_selector(str(q))
            out.extend([read_curve(q)] if selected is not None else read_curves(q))
        else:
            out.append(Curve(np.asarray(q, dtype=np.float64), id=f"<array {i}>"))
    return out


def is_mesh_query(queries: Any) -> bool:
    """Whether ``queries`` are meshes (a ``trimesh.Trimesh``, a mesh file path, or a list of
    them) rather than curves."""
    from ..mesh.objects import is_mesh_file

    items = queries if isinstance(queries, (list, tuple)) else [queries]
    if not items:
        return False
    first = items[0]
    if type(first).__module__.startswith("trimesh"):
        return True
    return isinstance(first, (str, os.PathLike)) and "#" not in str(first) and is_mesh_file(str(first))


def search(
    index: Any,
    queries: Any,
    k: int | None = None,
    *,
    max_distance: float | None = None,
    exclude_self: bool = False,
    method: str = DEFAULT_METHOD,
    direction: str = DEFAULT_DIRECTION,
    mirror: bool = False,
    prune: bool = True,
    threads: int | None = None,
    pose: bool = True,
    elastic: bool = False,
    elastic_depth: int | None = None,
    arrays: bool = False,
) -> list[list[RankedMatch]] | tuple[np.ndarray, np.ndarray]:
    """Each query's k nearest curves of ``index`` (an open :class:`~nfdmatch.index.Index` or
    a :class:`~nfdmatch.MemoryIndex`: their ``search`` is this function, :class:`SearchFace`).
    A mesh query (:func:`is_mesh_query`: a mesh file path, a ``trimesh.Trimesh``, or a list
    of them) ranks the objects of an index file instead (``index.search_objects``: ``k``,
    ``max_distance``, ``exclude_self``, ``prune``; one list of
    :class:`~nfdmatch.search.objects.ObjectMatch` per mesh).

    queries : a :class:`~nfdmatch.Curve`, an (n, 3) array, a path, or a sequence of them
        (:func:`as_queries`).
    k : matches per query (None: every match within ``max_distance``; with neither,
        :data:`DEFAULT_K`).
    max_distance : only matches at most this far.
    exclude_self : drop each query's own curve (:func:`is_self`: same id, or the same curve
        of the same file however the path is spelled).
    method, direction, mirror : as in :func:`nfdmatch.distance`.
    prune : False computes every exact distance (the reference the pruned search equals).
    threads : queries answered in parallel (default: the cores, at most 4).
    pose : give each match its alignment onto the query (``RankedMatch.pose``: a
        :class:`~nfdmatch.Match` with rotation, scale, translation, start shift and
        direction), from the descriptors and pose the index stores.
    elastic : re-order each query's exact top ``elastic_depth`` (default 100) by the fused
        distance of the elastic stage (:class:`~nfdmatch.search.stages.ElasticStage`;
        matches gain ``elastic`` and ``fused``; docs/elastic.md).
    arrays : return ``(distances, rows)`` instead of records, as faiss does: float64 and
        int64 arrays of shape (number of queries, k), each query's row sorted as the records
        are, padded with ``inf`` and ``-1`` where a query has fewer matches (``k`` None: as
        wide as the longest answer). ``index.ids[rows[i, j]]`` names a match. No pose. The
        distances are those the rows are sorted by: exact, or fused with ``elastic``.

    Returns one list of :class:`~nfdmatch.records.RankedMatch` per query curve, sorted by
    distance then id (by the fused distance with ``elastic``), or the arrays.
    """
    from .index_search import search_index

    if k is None and max_distance is None:
        k = DEFAULT_K
    check_limits(k, max_distance, top_name="k")
    if elastic_depth is not None and not elastic:
        raise ParameterError("elastic_depth needs elastic=True")
    if is_mesh_query(queries):
        if not hasattr(index, "search_objects"):
            raise ParameterError(
                "a mesh query ranks the objects of an index file (built from meshes): curves in memory have none"
            )
        return index.search_objects(queries, k=k, max_distance=max_distance, exclude_self=exclude_self, prune=prune)
    stage = None
    if elastic:
        from ..defaults import DEFAULT_ELASTIC_DEPTH
        from .stages import ElasticStage

        stage = ElasticStage(DEFAULT_ELASTIC_DEPTH if elastic_depth is None else elastic_depth)
    curves = as_queries(queries)
    how = {"method": method, "direction": direction, "mirror": mirror}
    results, _ = search_index(
        index, curves, k=k, max_distance=max_distance, exclude_self=exclude_self, prune=prune, threads=threads,
        stage=stage, **how,
    )  # fmt: skip
    if arrays:
        return as_arrays(results, k)
    if pose:
        results = [_posed(index, q, found, how) for q, found in zip(curves, results)]
    return results


#: matches per query when a search is given neither k nor max_distance
DEFAULT_K = 10


class SearchFace:
    """What an index file (:class:`~nfdmatch.index.Index`) and curves in memory
    (:class:`~nfdmatch.MemoryIndex`) share: :meth:`search` (:func:`search`, the one search of
    both), ``len()``, and ``scale``, the deprecated alias of ``scale_mode``. A subclass sets
    ``n_curves`` and ``scale_mode``."""

    n_curves: int
    scale_mode: str

    #: :func:`search` of this index
    search = search

    def __len__(self) -> int:
        """The curves (rows) of the index."""
        return self.n_curves

    @property
    def scale(self) -> str:
        """Deprecated alias of :attr:`scale_mode`."""
        return self.scale_mode


def as_arrays(results: Sequence[Sequence[RankedMatch]], k: int | None) -> tuple[np.ndarray, np.ndarray]:
    """``(distances, rows)`` of a search's records: (Q, width) float64 and int64, padded with
    ``inf`` and ``-1`` (faiss's padding); width ``k``, or the longest answer's length. A
    distance is what the records are sorted by: the fused one after the elastic stage (an
    exact distance beside it would not be in order), else the exact one."""
    width = k if k is not None else max((len(found) for found in results), default=0)
    distances = np.full((len(results), width), np.inf)
    rows = np.full((len(results), width), -1, dtype=np.int64)
    for i, found in enumerate(results):
        n = min(width, len(found))
        distances[i, :n] = [m.distance if m.fused is None else m.fused for m in found[:n]]
        rows[i, :n] = [m.row for m in found[:n]]
    return distances, rows


def _posed(index: Any, query: Curve, found: Sequence[RankedMatch], how: dict) -> list[RankedMatch]:
    """``found`` with each match's alignment onto ``query`` (its stored descriptors)."""
    from ..descriptors import descriptors
    from ..matching import match_descriptors

    if not found:
        return list(found)
    dq = descriptors(query, samples=index.samples, harmonics=index.harmonics, scale=index.scale_mode)
    return [m.replace(pose=match_descriptors(dq, stored_descriptors(index, m.row, m.id), **how)) for m in found]


def stored_descriptors(index: Any, row: int, curve_id: str) -> Descriptors:
    """The :class:`~nfdmatch.descriptors.Descriptors` an index keeps for one row (true size
    and pose included: its rotation, centroid and scale)."""
    from ..descriptors import DescriptorBatch

    r = index.read_rows(row, row + 1, ["coefficients", "rotation", "centroid", "scale", "plane_degenerate"])
    return DescriptorBatch(
        r["coefficients"],
        r["rotation"],
        r["centroid"],
        r["scale"],
        r["plane_degenerate"],
        index.samples,
        index.harmonics,
        index.scale_mode,
    ).row(0, curve_id)
