"""The :class:`Curve` record and the one place where raw vertices are cleaned and validated."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .errors import CurveError

__all__ = ["Curve", "clean_points", "as_points"]


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
        object.__setattr__(self, "points", clean_points(self.points, path=self.source or self.id,
                                                        curve=self.index))
        self.points.setflags(write=False)

    @property
    def n_vertices(self) -> int:
        return int(self.points.shape[0])

    @property
    def is_planar(self) -> bool:
        """True when all vertices have z == 0 (2-D silhouettes read as z = 0)."""
        return bool(np.all(self.points[:, 2] == 0.0))


def clean_points(points, *, path: str | None = None, curve: int | None = None) -> np.ndarray:
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
        raise CurveError(f"expected an (n, 3) or (n, 2) array of vertices, got shape {pts.shape}",
                         path=path, curve=curve)
    if pts.shape[1] == 2:
        pts = np.column_stack([pts, np.zeros(len(pts))])
    bad = ~np.isfinite(pts).all(axis=1)
    if bad.any():
        first = int(np.flatnonzero(bad)[0])
        raise CurveError(f"vertex {first} is not finite (NaN or Inf): {pts[first].tolist()}",
                         path=path, curve=curve)
    if len(pts):
        keep = np.ones(len(pts), dtype=bool)
        keep[1:] = np.any(pts[1:] != pts[:-1], axis=1)
        pts = pts[keep]
        while len(pts) > 1 and np.array_equal(pts[-1], pts[0]):
            pts = pts[:-1]
    distinct = _distinct_up_to_three(pts)
    if distinct < 3:
        raise CurveError(f"a closed curve needs at least 3 distinct points, got {distinct}",
                         path=path, curve=curve)
    # measured on a rescaled copy so that huge coordinates (1e200) do not overflow
    extent = np.abs(pts).max()
    perimeter = np.linalg.norm(np.diff(pts / extent, axis=0, append=pts[:1] / extent), axis=1).sum()
    if not perimeter > 0 or not np.isfinite(perimeter):
        raise CurveError(f"the curve has no usable length (perimeter {perimeter})",
                         path=path, curve=curve)
    return pts


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


def as_points(curve) -> np.ndarray:
    """(n, 3) float64 vertices of a :class:`Curve` or an array-like, cleaned and validated."""
    if isinstance(curve, Curve):
        return curve.points
    return clean_points(curve)
