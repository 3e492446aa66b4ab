"""Ranking curves held in memory against one query."""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

from ..matching import MatchParameters
from ..descriptors import descriptors
from ..records import RankedMatch
from .index_search import search_index
from .limits import check_limits
from .memory import MemoryIndex

if TYPE_CHECKING:
    from numpy.typing import ArrayLike

    from ..curve import Curve
    from .stages import Stage


def rank_curves(
    query: Curve | ArrayLike,
    curves: Sequence[Curve],
    *,
    top: int | None = None,
    max_distance: float | None = None,
    exclude_self: bool = False,
    stage: Stage | None = None,
    **parameters,
) -> list[RankedMatch]:
    """Rank ``curves`` by distance to ``query``.

    Parameters
    ----------
    query : :class:`~nfdmatch.curve.Curve` (or (n, 3) array).
    curves : sequence of :class:`~nfdmatch.curve.Curve`.
    top : keep the best ``top`` (all when None).
    max_distance : drop matches farther than this.
    exclude_self : drop the query's own curve (as :func:`~nfdmatch.search.search_index`).
    stage : a re-ordering stage (:class:`~nfdmatch.search.stages.ElasticStage`), as
        :func:`~nfdmatch.search.search_index` takes it.
    samples, harmonics, scale, method, direction, mirror, weights : by keyword, as in
        :func:`nfdmatch.distance` (the fields of :class:`~nfdmatch.matching.MatchParameters`).

    Returns
    -------
    list of :class:`~nfdmatch.records.RankedMatch` sorted by distance, ties broken by id so
    the order is deterministic; ``rank`` is 1-based, ``row`` the match's position in ``curves``.
    """
    from ..curve import Curve

    p = MatchParameters(**parameters)
    if not isinstance(query, Curve):
        query = Curve(query, id="<query>")
    if not curves:
        check_limits(top)
        descriptors(query, **p.descriptor)  # validates
        return []
    memory = MemoryIndex(curves, **p.descriptor)
    results, _ = search_index(
        memory,
        [query],
        top=top if top is not None or max_distance is not None else len(curves),
        max_distance=max_distance,
        **p.matching,
        prune=p.weights is None,
        exclude_self=exclude_self,
        stage=stage,
    )
    return results[0]
