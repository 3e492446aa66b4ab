"""Matches put into the query's frame, for pictures: the data behind ``nfdmatch show``.

Each match is re-matched against the query (one search per match, with the search's
method; only the top few) to get the rotation, scale, translation, start shift and
direction that the search found, and its vertices are mapped into the query's coordinates
with them. A match is drawn from its source file when that file still holds the indexed
curve, otherwise from the harmonics stored in the index (true size and pose: the index
keeps each curve's centroid, scale and rotation).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any, TYPE_CHECKING

import numpy as np

from .matching import EXACT, INVARIANT
from .curve import Curve
from .descriptors import START_STEP, Descriptors, descriptors, points_at, reconstruct
from .errors import CurveError, NfdError
from .matching import Match, match_descriptors
from .records import RankedMatch, ShownMatch
from .search.knn import stored_descriptors

if TYPE_CHECKING:
    from collections.abc import Iterable

__all__ = [
    "ShownMatch",
    "align_match",
    "match_panels",
    "matches_from_curves",
    "matches_from_index",
    "show_ranked",
    "show_searched",
]

#: a file whose re-matched distance differs from the indexed one by more than this (relative
#: to 1 + distance) no longer holds the indexed curve: draw from the index instead
_CHANGED = 1e-3
#: largest coordinate of a query that can be drawn: the pictures square lengths (moments,
#: extents), which overflows float64 past ~1.3e154
MAX_DRAWN_COORDINATE = 1e150


def _drawable(query: Curve) -> None:
    """Raise CurveError for a query too large to draw (the matches are drawn at its size)."""
    largest = float(np.abs(query.points).max())
    if largest > MAX_DRAWN_COORDINATE:
        raise CurveError(
            f"coordinates up to {largest:.3g} are too large to draw (at most "
            f"{MAX_DRAWN_COORDINATE:g}): scale the curve down (distance, query and reconstruct "
            f"take it as it is)",
            path=query.id,
        )


def align_match(
    dq: Descriptors,
    db: Descriptors,
    points_b: np.ndarray,
    ranked: RankedMatch,
    *,
    source: str,
    alignment: Match | None = None,
    **matching: Any,
) -> ShownMatch:
    """The ranked match ``ranked`` with ``points_b`` ((m, 3) float64, the curve behind
    ``db``) mapped into the frame of the query behind ``dq`` by the alignment of their match
    (``alignment``; when None, computed by :func:`~nfdmatch.matching.match_descriptors` with
    the keywords ``matching``: method, direction, mirror); the shift and direction become
    the alignment's."""
    m = alignment if alignment is not None else match_descriptors(dq, db, **matching)
    fractions = m.partner_fractions(np.array([0.0, START_STEP]), dq.samples)
    marks = m.apply(points_at(points_b, fractions))
    aligned = ranked.replace(
        id=db.id, distance=float(ranked.distance), shift=m.shift, reversed=m.reversed, mirrored=m.mirrored
    )
    return ShownMatch(match=aligned, points=m.apply(points_b), start=marks[0], forward=marks[1], source=source)


def matches_from_curves(
    query: Curve,
    results: list[RankedMatch],
    curves: Sequence[Curve],
    *,
    samples: int,
    harmonics: int,
    scale: str,
    method: str = EXACT,
    direction: str = INVARIANT,
    mirror: bool = False,
) -> list[ShownMatch]:
    """Matches of a ranking over curves held in memory.

    results : the matches :func:`~nfdmatch.search.rank_curves` found in ``curves`` (``row``:
        the match's position in ``curves``).
    curves : the sequence of :class:`~nfdmatch.curve.Curve` that was ranked.
    """
    dq = descriptors(query, samples=samples, harmonics=harmonics, scale=scale)
    shown = []
    for ranked in results:
        curve = curves[ranked.row]
        db = descriptors(curve, samples=samples, harmonics=harmonics, scale=scale)
        shown.append(
            align_match(dq, db, curve.points, ranked, source="file", method=method, direction=direction, mirror=mirror)
        )
    return shown


def matches_from_index(
    query: Curve,
    results: list[RankedMatch],
    index: Any,
    *,
    method: str = EXACT,
    direction: str = INVARIANT,
    mirror: bool = False,
    read_curve: Callable[[str], Curve] | None = None,
    points: int = 256,
) -> tuple[list[ShownMatch], list[str]]:
    """Matches of an index search, drawn from their files when those still hold the curve.

    results : one query's matches from :func:`~nfdmatch.search.search_index`.
    index : the open :class:`~nfdmatch.index.Index` searched.
    read_curve : ``spec -> Curve`` (default :func:`nfdmatch.formats.read_curve`).
    points : vertices of a curve drawn from its stored harmonics.

    Returns ``(matches, notes)``; a note says which match was drawn from the index and why.
    """
    if read_curve is None:
        from .formats import read_curve
    samples, harmonics, scale = index.samples, index.harmonics, index.scale_mode
    dq = descriptors(query, samples=samples, harmonics=harmonics, scale=scale)
    shown, notes = [], []
    for ranked in results:
        curve_id = ranked.id
        try:
            # an index's ids are relative to its folder: found from any working directory
            located = index.locate(curve_id) if hasattr(index, "locate") else curve_id
            curve = read_curve(located)  # type: ignore[misc]
            if located != curve_id:  # shown under the id the index reports
                curve = Curve.trusted(curve.points, curve_id, curve.source, curve.index)
        except NfdError as exc:
            reason = f"cannot read it ({exc})"
        else:
            db = descriptors(curve, samples=samples, harmonics=harmonics, scale=scale)
            m = match_descriptors(dq, db, method=method, direction=direction, mirror=mirror)
            if abs(m.distance - ranked.distance) <= _CHANGED * (1.0 + ranked.distance):
                shown.append(align_match(dq, db, curve.points, ranked, source="file", alignment=m))
                continue
            reason = f"the file changed since it was indexed (distance now {m.distance:.4g})"
        db = stored_descriptors(index, ranked.row, curve_id)
        shown.append(
            align_match(
                dq,
                db,
                reconstruct(db, points=points),
                ranked,
                source="index",
                method=method,
                direction=direction,
                mirror=mirror,
            )
        )
        notes.append(f"{curve_id}: drawn from its {harmonics} indexed harmonics: {reason}")
    return shown, notes


def _k(k: int | None, top: int | None, where: str) -> int | None:
    """``k``, or the deprecated ``top`` a caller still passes."""
    if top is not None:
        import warnings

        warnings.warn(f"{where}(top=) is deprecated: use k=", DeprecationWarning, stacklevel=3)
        k = top
    return k


def show_ranked(
    query: Curve,
    curves: Sequence[Curve],
    *,
    k: int | None = None,
    samples: int | None = None,
    harmonics: int | None = None,
    scale: str | None = None,
    method: str = EXACT,
    direction: str = INVARIANT,
    mirror: bool = False,
    max_distance: float | None = None,
    exclude_self: bool = False,
    stage: Any = None,
    top: int | None = None,
) -> list[ShownMatch]:
    """The best ``k`` matches (``top``: its deprecated older name) of ``query`` among
    ``curves`` (Curves), aligned onto it. ``samples, harmonics, scale`` None take the
    library defaults; ``max_distance``, ``exclude_self`` and ``stage`` (a re-ordering
    stage, :class:`~nfdmatch.search.stages.ElasticStage`) as ``rank_curves`` takes them."""
    from .descriptors import DEFAULT_HARMONICS, DEFAULT_SAMPLES, DEFAULT_SCALE
    from .search import rank_curves

    params = dict(
        samples=samples or DEFAULT_SAMPLES,
        harmonics=harmonics or DEFAULT_HARMONICS,
        scale=scale or DEFAULT_SCALE,
        method=method,
        direction=direction,
        mirror=mirror,
    )
    _drawable(query)
    ranked = rank_curves(
        query, curves, k=_k(k, top, "show_ranked"), max_distance=max_distance, exclude_self=exclude_self,
        stage=stage, **params,
    )  # fmt: skip
    return matches_from_curves(query, ranked, curves, **params)


def show_searched(
    query: Curve,
    index: Any,
    *,
    k: int | None = None,
    method: str = EXACT,
    direction: str = INVARIANT,
    mirror: bool = False,
    read_curve: Callable[[str], Curve] | None = None,
    max_distance: float | None = None,
    exclude_self: bool = False,
    stage: Any = None,
    top: int | None = None,
) -> tuple[list[ShownMatch], list[str]]:
    """The best ``k`` matches (``top``: its deprecated older name) of ``query`` in the open
    ``index``, aligned onto it, and the notes of :func:`matches_from_index`;
    ``max_distance``, ``exclude_self`` and ``stage`` as
    :func:`~nfdmatch.search.search_index` takes them."""
    from .search import search_index

    _drawable(query)
    results, _ = search_index(
        index, [query], k=_k(k, top, "show_searched"), method=method, direction=direction, mirror=mirror,
        max_distance=max_distance, exclude_self=exclude_self, stage=stage,
    )  # fmt: skip
    return matches_from_index(
        query, results[0], index, method=method, direction=direction, mirror=mirror, read_curve=read_curve
    )


def match_panels(shown: Iterable[ShownMatch]) -> list[ShownMatch]:
    """Deprecated: :func:`~nfdmatch.render.render_matches` draws :class:`ShownMatch` es as
    they are; this returns them as a list."""
    return list(shown)
