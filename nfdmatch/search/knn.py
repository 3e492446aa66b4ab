"""The k nearest curves of an index for each query, as a Python user asks for them
(:meth:`nfdmatch.index.Index.search`). The rule that drops a query's own curve from its
matches (``exclude_self``) is ``selfmatch.py``'s, re-exported here.
"""

from __future__ import annotations

import os
from collections.abc import Sequence

import numpy as np

from ..curve import Curve
from ..errors import ParameterError
from ..records import RankedMatch
from .limits import check_limits
from .selfmatch import drop_self, is_self, self_rule

__all__ = ["as_queries", "self_rule", "is_self", "drop_self", "search", "stored_descriptors"]


def as_queries(queries) -> list[Curve]:
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


def search(
    index,
    queries,
    *,
    k: int | None = 10,
    max_distance: float | None = None,
    exclude_self: bool = False,
    pose: bool = True,
    elastic: bool = False,
    elastic_depth: int | None = None,
    **options,
) -> list[list[RankedMatch]]:
    """Each query's k nearest curves of ``index`` (an open :class:`~nfdmatch.index.Index`).

    queries : a :class:`~nfdmatch.Curve`, an (n, 3) array, a path, or a sequence of them
        (:func:`as_queries`).
    k : matches per query (None: every match within ``max_distance``).
    max_distance : only matches at most this far.
    exclude_self : drop each query's own curve (:func:`is_self`: same id, or the same curve
        of the same file however the path is spelled).
    pose : give each match its alignment onto the query (``RankedMatch.pose``: a
        :class:`~nfdmatch.Match` with rotation, scale, translation, start shift and
        direction), from the descriptors and pose the index stores.
    elastic : re-order each query's exact top ``elastic_depth`` (default 100) by the fused
        distance of the elastic stage (:class:`~nfdmatch.search.stages.ElasticStage`;
        matches gain ``elastic`` and ``fused``; docs/elastic.md).
    options : ``method``, ``direction``, ``mirror``, ``prune``, ``threads`` as
        :func:`~nfdmatch.search.search_index`.

    Returns one list per query curve, sorted by distance then id.
    """
    from .index_search import search_index

    if k is None and max_distance is None:
        raise ParameterError("give k or max_distance (or both)")
    check_limits(k, max_distance, top_name="k")
    if elastic_depth is not None and not elastic:
        raise ParameterError("elastic_depth needs elastic=True")
    if elastic:
        from ..defaults import DEFAULT_ELASTIC_DEPTH
        from .stages import ElasticStage

        options["stage"] = ElasticStage(DEFAULT_ELASTIC_DEPTH if elastic_depth is None else elastic_depth)
    curves = as_queries(queries)
    results, _ = search_index(index, curves, top=k, max_distance=max_distance, exclude_self=exclude_self, **options)
    if pose:
        results = [_posed(index, q, found, options) for q, found in zip(curves, results)]
    return results


def _posed(index, query: Curve, found: Sequence[RankedMatch], options: dict) -> list[RankedMatch]:
    """``found`` with each match's alignment onto ``query`` (its stored descriptors)."""
    from ..descriptors import descriptors
    from ..matching import match_descriptors

    if not found:
        return list(found)
    dq = descriptors(query, samples=index.samples, harmonics=index.harmonics, scale=index.scale_mode)
    how = {key: options[key] for key in ("method", "direction", "mirror") if key in options}
    return [m.replace(pose=match_descriptors(dq, stored_descriptors(index, m.row, m.id), **how)) for m in found]


def stored_descriptors(index, row: int, curve_id: str):
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
