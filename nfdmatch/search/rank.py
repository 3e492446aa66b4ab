"""Ranking curves held in memory against one query."""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

from ..matching import EXACT, INVARIANT
from ..descriptors import DEFAULT_HARMONICS, DEFAULT_SAMPLES, DEFAULT_SCALE, descriptors
from ..errors import ParameterError
from ..records import RankedMatch
from .index_search import search_index
from .memory import MemoryIndex

if TYPE_CHECKING:
    from numpy.typing import ArrayLike

    from ..curve import Curve


def rank_curves(
    query: Curve | ArrayLike,
    curves: Sequence[Curve],
    *,
    top: int | None = None,
    max_distance: float | None = None,
    samples: int = DEFAULT_SAMPLES,
    harmonics: int = DEFAULT_HARMONICS,
    scale: str = DEFAULT_SCALE,
    method: str = EXACT,
    direction: str = INVARIANT,
    mirror: bool = False,
    weights: ArrayLike | None = None,
    exclude_self: bool = False,
) -> list[RankedMatch]:
    """Rank ``curves`` by distance to ``query``.

    Parameters
    ----------
    query : :class:`~nfdmatch.curve.Curve` (or (n, 3) array).
    curves : sequence of :class:`~nfdmatch.curve.Curve`.
    top : keep the best ``top`` (all when None).
    max_distance : drop matches farther than this.
    exclude_self : drop the query's own curve (as :func:`~nfdmatch.search.search_index`).
    Other parameters as in :func:`nfdmatch.distance`.

    Returns
    -------
    list of :class:`~nfdmatch.records.RankedMatch` sorted by distance, ties broken by id so
    the order is deterministic; ``rank`` is 1-based, ``row`` the match's position in ``curves``.
    """
    from ..curve import Curve

    if not isinstance(query, Curve):
        query = Curve(query, id="<query>")
    if not curves:
        if top is not None and top < 1:
            raise ParameterError(f"top must be at least 1, got {top}")
        descriptors(query, samples=samples, harmonics=harmonics, scale=scale)  # validates
        return []
    memory = MemoryIndex(curves, samples=samples, harmonics=harmonics, scale=scale)
    results, _ = search_index(
        memory,
        [query],
        top=top if top is not None or max_distance is not None else len(curves),
        max_distance=max_distance,
        method=method,
        direction=direction,
        mirror=mirror,
        weights=weights,
        prune=weights is None,
        exclude_self=exclude_self,
    )
    return results[0]
