"""The :class:`Curve` record and the one place where raw vertices are cleaned and validated."""

from __future__ import annotations

from typing import TYPE_CHECKING, TypeAlias

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from .errors import CurveError

if TYPE_CHECKING:
    from numpy.typing import ArrayLike

__all__ = ["Curve", "CurvesLike", "clean_points", "as_points", "STDIN_ID"]

#: the id of a curve read from stdin (``-`` on the command line): it names no file
STDIN_ID = "<stdin>"


@dataclass(frozen=True)
class Curve:
    """A closed polyline.

    Attributes
    ----------
    points : (n, 3) float64, n >= 3. Vertices in order; the closing edge
        ``points[-1] -> points[0]`` is implicit (never repeated), no two
        consecutive vertices are equal.
    id : str. ``path`` for a single-curve file, ``path#i`` (0-based) for curve
        ``i`` of a multi-curve file, or any label for in-memory curves.
    source : str or None. The file the curve came from.
    index : int or None. Position of the curve within ``source``.
    """

    points: np.ndarray = field(repr=False)
    id: str = "<array>"
    source: str | None = None
    index: int | None = None

    def __post_init__(self):
        object.__setattr__(self, "points", clean_points(self.points, path=self.source or self.id, curve=self.index))
        self.points.setflags(write=False)

    @classmethod
    def trusted(cls, points: np.ndarray, id: str, source: str | None = None, index: int | None = None) -> "Curve":
        """A Curve from vertices already cleaned by :func:`clean_points` / :func:`clean_many`
        (no second validation pass: readers of large multi-curve files use this)."""
        obj = object.__new__(cls)
        points = np.asarray(points, dtype=np.float64)
        points.setflags(write=False)
        for name, value in (("points", points), ("id", id), ("source", source), ("index", index)):
            object.__setattr__(obj, name, value)
        return obj

    @property
    def n_vertices(self) -> int:
        return int(self.points.shape[0])

    @property
    def in_xy_plane(self) -> bool:
        """True when all vertices have z == 0 (2-D silhouettes read as z = 0); see
        :func:`nfdmatch.render.is_coplanar` for "in some plane, within a tolerance"."""
        return bool(np.all(self.points[:, 2] == 0.0))


#: the curves a writer takes (``write_curves`` and every format's ``write``): a sequence of
#: :class:`Curve` or (n, 3) / (n, 2) float arrays; a bare Curve or 2-D array is one curve.
#: Their vertices are cleaned (:func:`clean_points`) before anything is written.
CurvesLike: TypeAlias = Curve | NDArray[np.floating] | Sequence[Curve | NDArray[np.floating]]


def clean_points(points: ArrayLike, *, path: str | None = None, curve: int | None = None) -> NDArray[np.float64]:
    """Validate and clean the vertices of one closed polyline.

    Parameters
    ----------
    points : array-like (n, 3) or (n, 2) of real numbers; (n, 2) means z = 0.
    path, curve : where the curve came from, used in error messages only.

    Returns
    -------
    (m, 3) float64, a new array: consecutive duplicate vertices removed, a
    repeated closing vertex removed.

    Raises
    ------
    CurveError : wrong shape, NaN/Inf, fewer than 3 distinct points, zero perimeter.
    """
    try:
        pts = np.array(points, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise CurveError(f"vertices are not numbers ({exc})", path=path, curve=curve) from None
    if pts.ndim != 2 or pts.shape[1] not in (2, 3):
        raise CurveError(
            f"expected an (n, 3) or (n, 2) array of vertices, got shape {pts.shape}", path=path, curve=curve
        )
    if pts.shape[1] == 2:
        pts = np.column_stack([pts, np.zeros(len(pts))])
    bad = ~np.isfinite(pts).all(axis=1)
    if bad.any():
        first = int(np.flatnonzero(bad)[0])
        raise CurveError(f"vertex {first} is not finite (NaN or Inf): {pts[first].tolist()}", path=path, curve=curve)
    if len(pts):
        keep = np.ones(len(pts), dtype=bool)
        keep[1:] = np.any(pts[1:] != pts[:-1], axis=1)
        pts = pts[keep]
        while len(pts) > 1 and np.array_equal(pts[-1], pts[0]):
            pts = pts[:-1]
    distinct = _distinct_up_to_three(pts)
    if distinct < 3:
        raise CurveError(f"a closed curve needs at least 3 distinct points, got {distinct}", path=path, curve=curve)
    # measured on a rescaled copy so that huge coordinates (1e200) do not overflow
    extent = np.abs(pts).max()
    perimeter = np.linalg.norm(np.diff(pts / extent, axis=0, append=pts[:1] / extent), axis=1).sum()
    if not perimeter > 0 or not np.isfinite(perimeter):
        raise CurveError(f"the curve has no usable length (perimeter {perimeter})", path=path, curve=curve)
    return pts


def clean_many(arrays: Sequence[NDArray[np.float64]], *, path: str | None = None) -> list[NDArray[np.float64]]:
    """:func:`clean_points` for many curves at once, vectorized over their vertices.

    Parameters
    ----------
    arrays : sequence of (n_i, 3) float64 arrays (curve i of file ``path``).

    Returns
    -------
    list of cleaned (m_i, 3) float64 arrays (views into one new array).

    Raises
    ------
    CurveError : naming ``path#i`` for the first invalid curve (the message
        :func:`clean_points` gives for it).
    """
    if len(arrays) < 8 or any(np.ndim(a) != 2 or np.shape(a)[1] != 3 for a in arrays):
        return [clean_points(a, path=path, curve=i if len(arrays) > 1 else None) for i, a in enumerate(arrays)]
    counts = np.array([len(a) for a in arrays])
    pts = np.concatenate(arrays).astype(np.float64, copy=False)
    curve_of = np.repeat(np.arange(len(arrays)), counts)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    magnitude = np.abs(pts).max(axis=1) if len(pts) else np.zeros(0)
    suspicious = ~np.isfinite(magnitude) | (magnitude > 1e150) | ((magnitude < 1e-150) & (magnitude > 0))
    if (counts < 3).any() or suspicious.any():
        bad = np.unique(np.concatenate([np.flatnonzero(counts < 3), curve_of[suspicious]]))
        for i in bad:  # the careful path raises with the exact message, or passes
            clean_points(arrays[i], path=path, curve=int(i))
    keep = np.ones(len(pts), dtype=bool)
    keep[1:] = np.any(pts[1:] != pts[:-1], axis=1)
    keep[starts] = True
    last_kept = np.maximum.reduceat(np.where(keep, np.arange(len(pts)), -1), starts)
    closing = np.all(pts[last_kept] == pts[starts], axis=1) & (last_kept != starts)
    keep[last_kept[closing]] = False
    new_counts = np.add.reduceat(keep, starts)
    pts, curve_of = pts[keep], curve_of[keep]
    new_starts = np.concatenate([[0], np.cumsum(new_counts)[:-1]])
    second = np.minimum(new_starts + 1, len(pts) - 1)
    third = np.any(pts != pts[new_starts][curve_of], axis=1) & np.any(pts != pts[second][curve_of], axis=1)
    distinct3 = np.logical_or.reduceat(third, new_starts) & (new_counts >= 3)
    for i in np.flatnonzero(~distinct3):
        clean_points(arrays[i], path=path, curve=int(i))  # raises the precise error
    return np.split(pts, np.cumsum(new_counts)[:-1])


def _distinct_up_to_three(pts: np.ndarray) -> int:
    """Number of distinct rows of (n, 3) pts, counted up to 3 (O(n), no sorting)."""
    if len(pts) == 0:
        return 0
    differs_from_first = np.any(pts != pts[0], axis=1)
    if not differs_from_first.any():
        return 1
    second = pts[np.argmax(differs_from_first)]
    third = differs_from_first & np.any(pts != second, axis=1)
    return 3 if third.any() else 2


def as_points(curve: Curve | ArrayLike) -> NDArray[np.float64]:
    """(n, 3) float64 vertices of a :class:`Curve` or an array-like, cleaned and validated."""
    if isinstance(curve, Curve):
        return curve.points
    return clean_points(curve)
