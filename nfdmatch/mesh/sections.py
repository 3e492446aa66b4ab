"""Planar sections and boundary loops of a triangle mesh, as closed contours (see the
package docstring: how a section is computed, orientation, branching points)."""

from __future__ import annotations

from typing import TYPE_CHECKING

import os

import numpy as np

from .._graph import closed_loops
from ..curve import clean_points
from ..errors import CurveError, ParameterError
from .contours import AXES, Contour, DEFAULT_SECTIONS, ExtractResult
from .load import load_mesh, unit_power

if TYPE_CHECKING:
    import os
    import trimesh
    from numpy.typing import ArrayLike, NDArray


def section_levels(bounds: ArrayLike, sections: int, axis: str = "auto") -> tuple[str, NDArray[np.float64]]:
    """The axis and levels of ``sections`` evenly spaced planes.

    Parameters
    ----------
    bounds : (2, 3) float, ``[[xmin, ymin, zmin], [xmax, ymax, zmax]]``.
    sections : N >= 0.
    axis : ``"x"``, ``"y"``, ``"z"`` or ``"auto"`` (longest extent; ties to the
        earlier axis).

    Returns
    -------
    ``(axis, levels)``: the axis name and (N,) float64
    ``lo + (i + 0.5) * (hi - lo) / N``, i = 0 .. N-1 (all equal to ``lo`` when
    the extent is 0).
    """
    b = np.asarray(bounds, dtype=np.float64).reshape(2, 3)
    if axis == "auto":
        a = int(np.argmax(b[1] - b[0]))
    elif axis in AXES:
        a = AXES.index(axis)
    else:
        raise ParameterError(f"unknown axis {axis!r}; choose one of x, y, z, auto")
    lo, hi = b[0, a], b[1, a]
    levels = lo + (np.arange(sections, dtype=np.float64) + 0.5) * ((hi - lo) / max(sections, 1))
    return AXES[a], levels


# ---------------------------------------------------------------------------
# extraction
# ---------------------------------------------------------------------------


def extract_contours(
    path: str | os.PathLike[str], *, sections: int = DEFAULT_SECTIONS, axis: str = "auto", boundaries: bool = False
) -> ExtractResult:
    """Closed section loops (and boundary loops) of the triangle mesh in ``path``.

    Parameters
    ----------
    path : a mesh file (see :func:`load_mesh`).
    sections : number N >= 0 of section levels (see :func:`section_levels`);
        0 with ``boundaries=True`` extracts only the boundary loops.
    axis : ``"x"``, ``"y"``, ``"z"`` or ``"auto"`` (the longest extent of the
        bounding box). The principal axes of an object's rule are
        :func:`~.objects.principal_contours` (``extract --axis principal``).
    boundaries : also extract the boundary loops (edges used by one face).

    Returns
    -------
    :class:`ExtractResult`. A mesh with nothing to extract is not an error: the
    result has no contours and a note says why.

    Raises
    ------
    ParameterError : sections < 0, an unknown axis, or nothing asked for
        (``sections == 0`` without ``boundaries``).
    ReadError, UnknownFormatError, MeshError : see :func:`load_mesh`.
    """
    if isinstance(sections, bool) or not isinstance(sections, (int, np.integer)) or sections < 0:
        raise ParameterError(f"sections must be an integer >= 0, got {sections!r}")
    sections = int(sections)
    if axis != "auto" and axis not in AXES:
        raise ParameterError(f"unknown axis {axis!r}; choose one of x, y, z, auto")
    if sections == 0 and not boundaries:
        raise ParameterError("nothing to extract: sections is 0 and boundaries are off")
    p = str(os.fspath(path))
    mesh = load_mesh(p)
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    faces = np.asarray(mesh.faces, dtype=np.int64)
    result = ExtractResult(mesh=p, axis=None, levels=np.zeros(0), vertices=len(vertices), faces=len(faces))
    notes = result.notes

    if sections:
        _add_sections(result, mesh, vertices, faces, sections, axis)

    if boundaries:
        loops = boundary_loops(mesh, f"{p}: boundary", notes)
        if not loops and not any(n.startswith(f"{p}: boundary") for n in notes):
            notes.append(f"{p}: no boundary loops (the mesh is closed)")
        result.contours.extend(
            Contour(points=pts, mesh=p, kind="boundary", loop=k, loop_count=len(loops)) for k, pts in enumerate(loops)
        )

    if not result.contours:
        asked = " or ".join(w for w, on in (("section loops", sections), ("boundary loops", boundaries)) if on)
        notes.append(f"{p}: nothing extracted (no closed {asked})")
    return result


def _add_sections(result: ExtractResult, mesh, vertices, faces, sections: int, axis: str) -> None:
    """Add to ``result`` the closed loops of the ``sections`` planes across ``axis`` (its
    axis and levels too; a note for a mesh flat along it)."""
    p, notes = result.mesh, result.notes
    axis_name, levels = section_levels(mesh.bounds, sections, axis)
    result.axis, result.levels = axis_name, levels
    a = AXES.index(axis_name)
    bounds = np.asarray(mesh.bounds, dtype=np.float64)  # of the vertices used by faces
    if not bounds[1, a] - bounds[0, a] > 0:
        notes.append(f"{p}: the mesh is flat along {axis_name} (zero extent): no sections")
    else:
        edges = np.asarray(mesh.edges_unique, dtype=np.int64)
        face_edges = np.asarray(mesh.faces_unique_edges, dtype=np.int64)
        height = vertices[:, a]
        face_h = height[faces]
        face_lo, face_hi = face_h.min(axis=1), face_h.max(axis=1)
        width = max(2, len(str(sections - 1)))
        for i, level in enumerate(levels.tolist()):
            where = f"{p}: section {axis_name}{i:0{width}d} at {level + 0.0:.6g}"
            loops = section_loops(vertices, faces, edges, face_edges, face_lo, face_hi, a, level, where, notes)
            loops = _orient_ccw(loops, a)
            result.contours.extend(
                Contour(
                    points=pts,
                    mesh=p,
                    kind="section",
                    axis=axis_name,
                    level=float(level),
                    level_index=i,
                    loop=k,
                    level_count=sections,
                    loop_count=len(loops),
                )
                for k, pts in enumerate(loops)
            )


def section_loops(
    vertices: NDArray[np.float64],
    faces: NDArray[np.int64],
    edges: NDArray[np.int64],
    face_edges: NDArray[np.int64],
    face_lo: NDArray[np.float64],
    face_hi: NDArray[np.float64],
    a: int,
    level: float,
    where: str,
    notes: list[str],
) -> list[NDArray[np.float64]]:
    """Closed loops of the plane ``coordinate a == level``, as cleaned (m, 3) float64 arrays.

    vertices (n, 3) float64, faces (f, 3) int64, edges (e, 2) int64 unique
    sorted edges, face_edges (f, 3) int64 into ``edges``, face_lo/face_hi (f,)
    float64 the faces' extent along ``a``. A vertex on the plane counts as above it.
    """
    hit = (face_lo < level) & (face_hi >= level)
    if not hit.any():
        return []
    fe = face_edges[hit]  # (h, 3) edge ids
    used = np.unique(fe)
    ends = edges[used]  # (u, 2)
    d = vertices[ends, a] - level  # (u, 2) signed heights
    crossing = (d[:, 0] >= 0) != (d[:, 1] >= 0)
    cross_of = np.zeros(len(edges), dtype=bool)
    cross_of[used[crossing]] = True
    fc = cross_of[fe]  # (h, 3): two True per row
    rows, cols = np.nonzero(fc)
    segments = fe[rows, cols].reshape(-1, 2)  # (h, 2) pairs of edge ids

    # crossing points, one per crossing edge (computed once per edge, so both faces
    # of an edge share it exactly); segments renumbered into them
    ids = used[crossing]  # sorted edge ids
    d0, d1 = d[crossing, 0], d[crossing, 1]
    t = d0 / (d0 - d1)
    p0, p1 = vertices[edges[ids, 0]], vertices[edges[ids, 1]]
    # (1 - t) p0 + t p1 gives the vertex itself exactly where the plane passes through one
    # (t = 0 or 1), so the two edges meeting there give the same point and cleaning drops it
    points = (1.0 - t)[:, None] * p0 + t[:, None] * p1  # (c, 3)
    points[:, a] = level
    return _loops_to_points(np.searchsorted(ids, segments), points, where, notes)


def boundary_loops(mesh: trimesh.Trimesh, where: str, notes: list[str]) -> list[NDArray[np.float64]]:
    """Boundary loops (edges used by exactly one face) as cleaned (m, 3) float64 arrays,
    by decreasing perimeter."""
    from trimesh.grouping import group_rows

    single = group_rows(np.asarray(mesh.edges_sorted), require_count=1)
    if len(single) == 0:
        return []
    segments = np.asarray(mesh.edges, dtype=np.int64)[np.asarray(single, dtype=np.int64)]
    order = np.argsort(single, kind="stable")  # face order: walking follows winding
    return _loops_to_points(segments[order], np.asarray(mesh.vertices, dtype=np.float64), where, notes)


def _loops_to_points(segments: np.ndarray, points: np.ndarray, where: str, notes: list[str]) -> list[np.ndarray]:
    """Chain segments (m, 2) int64 of ids into ``points`` (k, 3) into closed loops.

    Returns cleaned (n_i, 3) float64 loops by decreasing perimeter; open pieces,
    branching points and degenerate loops are counted in ``notes`` (prefixed by ``where``).
    """
    loops, open_pieces, branching = closed_loops(segments)
    if branching:
        notes.append(
            f"{where}: {branching} branching point{'s' if branching != 1 else ''} (non-manifold), loops split there"
        )
    if open_pieces:
        notes.append(f"{where}: {open_pieces} open piece{'s' if open_pieces != 1 else ''} skipped (not closed)")
    out, degenerate = [], 0
    for ids in loops:
        try:
            out.append(clean_points(points[ids]))
        except CurveError:
            degenerate += 1
    if degenerate:
        notes.append(
            f"{where}: {degenerate} degenerate loop{'s' if degenerate != 1 else ''} "
            "skipped (fewer than 3 distinct points)"
        )
    unit = _unit_scale(points)  # exact: beyond ~1e154 the squares would overflow
    lengths = [float(np.linalg.norm(np.diff(c * unit, axis=0, append=c[:1] * unit), axis=1).sum()) for c in out]
    order = sorted(range(len(out)), key=lambda k: (-lengths[k], tuple(out[k].min(axis=0))))
    result = [out[k] for k in order]
    for c in result:
        c.setflags(write=False)
    return result


def _unit_scale(points: np.ndarray) -> float:
    """The power of two that brings the largest finite coordinate of ``points`` into [0.5, 1)
    (1.0 for none): scaling by it is exact, so lengths and areas compared after it compare
    as the true ones do, without overflow."""
    finite = np.abs(points[np.isfinite(points)])
    return unit_power(float(finite.max()) if finite.size else 0.0)


def _orient_ccw(loops: list[np.ndarray], a: int) -> list[np.ndarray]:
    """Reverse the loops that run clockwise seen from the positive end of axis ``a``."""
    i, j = (a + 1) % 3, (a + 2) % 3  # right-handed in-plane coordinates
    out = []
    for c in loops:
        unit = _unit_scale(c)  # exact: beyond ~1e154 the products would overflow
        x, y = c[:, i] * unit, c[:, j] * unit
        area2 = float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))
        if area2 < 0:
            c = c[::-1].copy()
            c.setflags(write=False)
        out.append(c)
    return out


# ---------------------------------------------------------------------------
# writing
# ---------------------------------------------------------------------------
