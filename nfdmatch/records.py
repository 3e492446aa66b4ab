"""The match record: what a search returns (:class:`RankedMatch`) and the same match aligned
onto its query for drawing (:class:`ShownMatch`).

One record all the way: :func:`~nfdmatch.search.search_index`, :func:`~nfdmatch.search.rank_curves`
and :func:`~nfdmatch.search.rerank_index` return :class:`RankedMatch` es; :mod:`nfdmatch.show`
extends each with its vertices in the query's frame (:class:`ShownMatch`);
:func:`~nfdmatch.render.render_matches` draws :class:`ShownMatch` es; the CLI formats rows
from them. (:class:`nfdmatch.matching.Match` is the alignment of two curves: rotation, scale,
translation; it is not a ranking.)

This module sits at the base of the layers (docs/architecture.md): it imports numpy only.
"""

from __future__ import annotations

from typing import Any, TYPE_CHECKING

import dataclasses
from dataclasses import dataclass

import numpy as np

if TYPE_CHECKING:
    from collections.abc import Callable

__all__ = ["RankedMatch", "ShownMatch", "RowIds", "SOURCES", "INDEX_NOTE"]

#: where a shown match's vertices come from: its curve file, or the harmonics stored in the index
SOURCES = ("file", "index")
#: the remark drawn under a match drawn from the index's harmonics
INDEX_NOTE = "drawn from index harmonics"


@dataclass(frozen=True)
class RankedMatch:
    """One match of a query, as a search ranks it.

    Attributes
    ----------
    rank : int, 1-based.
    id : str, the match's curve id (an index's ids are relative to its folder).
    distance : float, the exact distance to the query.
    shift : float, the start shift in samples (as in :class:`~nfdmatch.matching.Match`).
    reversed, mirrored : bool, as in :class:`~nfdmatch.matching.Match`.
    row : int, the match's row in the index (its position in the curves ranked), or None.
    score : float, the diffused score of a re-ranked search (higher is closer), else None.
    elastic : float, the elastic distance after the elastic stage (``--elastic``), else None.
    fused : float, the fused distance the elastic stage ranks by, else None.
    pose : the alignment onto the query (:class:`nfdmatch.matching.Match`: rotation, scale,
        translation that map the match onto the query), when the search was asked for it
        (``Index.search``), else None.
    """

    rank: int
    id: str
    distance: float
    shift: float = 0.0
    reversed: bool = False
    mirrored: bool = False
    row: int | None = None
    score: float | None = None
    pose: object | None = None
    elastic: float | None = None
    fused: float | None = None

    def replace(self, **changes: Any) -> RankedMatch:
        """A copy with some fields changed (e.g. ``rank`` after dropping rows)."""
        return dataclasses.replace(self, **changes)


def _of_match(name: str) -> property:
    """A read-only property of :class:`ShownMatch`: its match's field ``name``."""
    return property(lambda shown: getattr(shown.match, name), doc=f"The match's ``{name}``.")


@dataclass(frozen=True)
class ShownMatch:
    """A :class:`RankedMatch` aligned onto its query, ready to draw.

    Attributes
    ----------
    match : the :class:`RankedMatch`; its ``shift``, ``reversed`` and ``mirrored`` are the
        alignment's (the search's, except between equally good alignments of a symmetric curve).
    points : (m, 3) float64, the match's vertices in the query's coordinates (closed; the
        closing edge is implicit).
    start : (3,) float64, the point of the match that corresponds to the query's first vertex.
    forward : (3,) float64, the point that corresponds to the query a little further on
        (:data:`~nfdmatch.descriptors.START_STEP` of its length): with ``start``, the
        direction of travel.
    source : ``"file"`` (drawn from the curve file) or ``"index"`` (from stored harmonics).

    ``rank``, ``id``, ``distance``, ``reversed``, ``mirrored`` read the match's; ``note`` is
    the remark drawn with it (:data:`INDEX_NOTE` for ``source="index"``, else None).
    """

    match: RankedMatch
    points: np.ndarray
    start: np.ndarray
    forward: np.ndarray
    source: str = "file"

    rank = _of_match("rank")
    id = _of_match("id")
    distance = _of_match("distance")
    reversed = _of_match("reversed")
    mirrored = _of_match("mirrored")

    @property
    def note(self) -> str | None:
        return INDEX_NOTE if self.source == "index" else None


class RowIds:
    """The ids of an index's rows as a read-only sequence (``index.ids[row]``, a slice, an
    array of rows, ``len``, iteration), read on demand: an index file of a million rows is
    not read whole to name the five a search returned. Calling it, ``index.ids(start,
    stop)``, is the older spelling of ``index.ids[start:stop]`` (a list)."""

    def __init__(
        self, count: int, at: Callable[[np.ndarray], list[str]], span: Callable[[int, int], list[str]]
    ) -> None:
        self._count = count
        self._at = at  # rows -> list[str]
        self._span = span  # (start, stop) -> list[str]

    def __len__(self) -> int:
        return self._count

    def __getitem__(self, key):
        if isinstance(key, slice):
            start, stop, step = key.indices(self._count)
            if step != 1:
                return self._at(np.arange(start, stop, step))
            return self._span(start, max(start, stop))
        if isinstance(key, (int, np.integer)):
            row = int(key)
            if row < 0:
                row += self._count
            if not 0 <= row < self._count:
                raise IndexError(f"row {int(key)} out of range 0..{self._count - 1}")
            return self._at([row])[0]
        rows = np.asarray(key, dtype=np.int64)
        return self._at(np.where(rows < 0, rows + self._count, rows))

    def __iter__(self):
        step = 65536
        for start in range(0, self._count, step):
            yield from self._span(start, min(self._count, start + step))

    def __call__(self, start: int = 0, stop: int | None = None) -> list[str]:
        return self[slice(start, stop)]

    def __repr__(self) -> str:
        return f"<{self._count} ids>"
