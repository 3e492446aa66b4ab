"""The k nearest curves of an index for each query, as a Python user asks for them
(:meth:`nfdmatch.index.Index.search`), and the rule that drops a query's own curve from its
matches (``exclude_self``, shared by every search that offers it).
"""

from __future__ import annotations

import functools
import os
from collections.abc import Sequence

import numpy as np

from ..curve import STDIN_ID, Curve
from ..errors import ParameterError
from ..records import RankedMatch

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


def _curve_key(curve_id: str) -> tuple | None:
    """The file (its device and inode: however the path is spelled, symbolic links
    followed) and curve an id names; None when it names no file here. One stat: a batch
    checks every match of every query."""
    from ..formats import split_selector

    path, selected = split_selector(curve_id)
    try:
        st = os.stat(path)
    except (OSError, ValueError):
        return None
    return st.st_dev, st.st_ino, selected


def self_rule(locate=None):
    """``rule(query_id, match_id) -> bool``: whether a match names the query's curve: the
    same id, or the same curve of the same file however the path is spelled (never for
    stdin). ``locate``: id -> a path that opens it here (an index's ids are relative to its
    folder: ``Index.locate``). Each id is resolved once per rule (a batch asks about the
    same ids query after query)."""
    from ..names import decode_name

    where = locate or decode_name  # an id is a file's name encoded (nfdmatch.names)
    stored_key = functools.lru_cache(maxsize=None)(lambda i: _curve_key(where(i)))
    query_key = functools.lru_cache(maxsize=None)(lambda i: _curve_key(decode_name(i)))

    def rule(query_id: str, match_id: str) -> bool:
        if query_id == STDIN_ID:
            return False
        if match_id == query_id:
            return True
        mine = query_key(query_id)
        return mine is not None and stored_key(match_id) == mine

    return rule


def is_self(query_id: str, match_id: str, locate=None) -> bool:
    """One question of :func:`self_rule`."""
    return self_rule(locate)(query_id, match_id)


def drop_self(query_id: str, matches: list[RankedMatch], k: int | None, locate=None, rule=None) -> list[RankedMatch]:
    """``matches`` (ranked) without those naming the query's curve (:func:`self_rule`;
    ``rule`` one made already, for a batch), ranks renumbered, at most ``k``. The search
    asked for one match more."""
    rule = rule or self_rule(locate)
    kept = [m for m in matches if not rule(query_id, m.id)]
    return [m.replace(rank=rank) for rank, m in enumerate(kept[:k] if k is not None else kept, start=1)]


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
