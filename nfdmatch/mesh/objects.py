"""A mesh as an object: its contours cut by a recorded rule, with the per-loop measures and
the section profile that the object distance needs (docs/objects.md).

The rule (:class:`ObjectRule`, recorded in the index's ``/objects`` group):

* **Frame.** The area-weighted second moments of the triangles about the area centroid
  (exact for each triangle, so the frame depends on the surface, not on how it is
  triangulated); axes by decreasing variance; each axis's sign from the exact third moment
  of area along it (positive skew), the last axis flipped if needed to keep a rotation.
* **Levels.** ``sections`` planes per axis at the exact area quantiles ``(i + 0.5) / N`` of
  the surface along the axis, so that the levels do not depend on the triangulation or on
  outlying vertices; a quantile on a face flat across the axis (a box's cap) is moved 0.1%
  of the extent into the solid, so that the plane cuts the walls, not the face.
* **Loops.** Every closed loop of every section with at least ``min_vertices`` vertices
  (shorter ones are triangulation noise at a tangent plane), plus the boundary loops of an
  open mesh (axis :data:`BOUNDARY_AXIS`, level 0). Loops are stored in the mesh's own
  coordinates; the descriptor forgets the frame anyway.
* **Measures** of each loop, all free of the object's size: log relative perimeter
  ``log(perimeter / sqrt(surface area))``, enclosed area over surface area, and elongation
  ``sqrt(l2 / l1)`` of the loop's length-weighted 2-D second moments in its plane.
* **Profile** per axis and level: loop count, total relative perimeter, enclosed area over
  surface area, elongation of the longest loop (``3 x N x 4`` numbers).

trimesh is imported inside the functions (through :func:`~.load.load_mesh`).
"""

from __future__ import annotations

from typing import Any, TYPE_CHECKING

import os
from dataclasses import dataclass, field

import numpy as np

from ..errors import MeshError, ParameterError
from ..sources import MESH_EXTENSIONS
from .contours import Contour, ExtractResult
from .load import load_mesh, unit_power
from .sections import boundary_loops, section_loops

if TYPE_CHECKING:
    import os
    import trimesh
    from .contours import ExtractResult

__all__ = [
    "ObjectRule",
    "ObjectCut",
    "DEFAULT_OBJECT_SECTIONS",
    "BOUNDARY_AXIS",
    "MESH_EXTENSIONS",
    "PROFILE_FEATURES",
    "MEASURES",
    "is_mesh_file",
    "principal_frame",
    "area_quantile_levels",
    "cut_object",
]

#: planes per principal axis (the prototype measured 5, 7 and 9 as ties; 7 kept)
DEFAULT_OBJECT_SECTIONS = 7
#: loops with fewer vertices are dropped (a plane grazing a few triangles)
DEFAULT_MIN_VERTICES = 8
#: the axis number of boundary loops (principal axes are 0, 1, 2)
BOUNDARY_AXIS = 3
#: the name of the cutting rule (recorded; a reader refuses a rule it does not know)
RULE_NAME = "principal-area-quantile"
#: columns of a loop's measures
MEASURES = ("log_relative_perimeter", "relative_area", "elongation")
#: features of the profile per axis and level
PROFILE_FEATURES = ("loops", "relative_perimeter", "relative_area", "elongation")


@dataclass(frozen=True)
class ObjectRule:
    """How an object's contours are cut (see the module doc): ``sections`` planes per
    principal axis, loops of at least ``min_vertices`` vertices, boundary loops of open
    meshes when ``boundaries``."""

    sections: int = DEFAULT_OBJECT_SECTIONS
    min_vertices: int = DEFAULT_MIN_VERTICES
    boundaries: bool = True
    name: str = RULE_NAME

    def __post_init__(self):
        for what in ("sections", "min_vertices"):
            value = getattr(self, what)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
                raise ParameterError(f"{what} must be an integer >= 1, got {value!r}")
        if self.min_vertices < 3:
            raise ParameterError(f"min_vertices must be >= 3, got {self.min_vertices}")
        if self.name != RULE_NAME:
            raise ParameterError(f"unknown object rule {self.name!r} (this nfdmatch knows {RULE_NAME!r})")

    def as_tuple(self) -> tuple:
        """A picklable, comparable form (what a build's worker task carries)."""
        return (int(self.sections), int(self.min_vertices), bool(self.boundaries))

    @classmethod
    def from_tuple(cls, t: tuple[Any, ...]) -> ObjectRule:
        return cls(sections=int(t[0]), min_vertices=int(t[1]), boundaries=bool(t[2]))


@dataclass
class ObjectCut:
    """One object's contours and measures.

    ``loops``: closed (m_i, 3) float64 polylines in the mesh's coordinates, by axis, level,
    then decreasing perimeter; ``axis`` (L,) int8 (0..2 principal, 3 boundary), ``level``
    (L,) int16; ``measures`` (L, 3) float64 (:data:`MEASURES`); ``profile`` (3 N 4,)
    float64 (axis-major, then level, then :data:`PROFILE_FEATURES`); ``area`` the surface
    area; ``frame`` (4, 3): the area centroid then the three principal axes (rows);
    ``levels`` (3, N) the plane offsets along each axis from the centroid; ``notes``."""

    mesh: str
    rule: ObjectRule
    loops: list = field(default_factory=list)
    axis: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int8))
    level: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int16))
    measures: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    profile: np.ndarray = field(default_factory=lambda: np.zeros(0))
    area: float = 0.0
    frame: np.ndarray = field(default_factory=lambda: np.zeros((4, 3)))
    levels: np.ndarray = field(default_factory=lambda: np.zeros((3, 0)))
    notes: list = field(default_factory=list)


def is_mesh_file(path: str) -> bool:
    """Whether ``path`` is read as a mesh rather than as a curve file: an extension of
    :data:`MESH_EXTENSIONS`, or an OBJ file with a face (``f``) element (an OBJ of ``l``
    polylines stays a curve file). Reads at most the OBJ file's lines, no trimesh."""
    ext = os.path.splitext(str(path))[1].lower()
    if ext in MESH_EXTENSIONS:
        return True
    if ext != ".obj":
        return False
    try:
        with open(path, "rb") as fh:
            return any(line.lstrip().startswith(b"f ") for line in fh)
    except OSError:
        return False


#: an object whose extent is outside this range is cut scaled by a power of two (exact): the
#: frame's moments are the 4th and 5th powers of the coordinates and overflow (or vanish)
#: beyond ~1e61 (below ~1e-61)
_CUT_RANGE = (2.0**-100, 2.0**100)


def _triangles(mesh) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """The vertices (scaled), faces, the triangles' areas (scaled) and the power of two
    the vertices were scaled by (1.0 unless the extent is outside :data:`_CUT_RANGE`)."""
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    faces = np.asarray(mesh.faces, dtype=np.int64)
    tri = vertices[faces]
    scale = 1.0
    if tri.size:
        extent = float((tri.max(axis=(0, 1)) - tri.min(axis=(0, 1))).max())
        if extent > 0 and not _CUT_RANGE[0] <= extent <= _CUT_RANGE[1]:
            scale = unit_power(extent)  # extent in [0.5, 1)
            vertices, tri = vertices * scale, tri * scale
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    return vertices, faces, area, scale


def principal_frame(tri: np.ndarray, area: np.ndarray) -> np.ndarray:
    """(4, 3): the area centroid, then the principal axes (rows, a rotation) of the
    triangles ``tri`` (f, 3, 3) with areas ``area`` (f,)."""
    total = float(area.sum())
    if not total > 0:
        raise MeshError("not a usable surface: its area is zero")
    centroid = (area[:, None] * tri.mean(axis=1)).sum(axis=0) / total
    rel = tri - centroid
    s = rel.sum(axis=1)  # (f, 3)
    # exact second moment of a uniform triangle: (sum v v^T + s s^T) / 12 per unit area
    second = np.einsum("f,fvi,fvj->ij", area, rel, rel) + np.einsum("f,fi,fj->ij", area, s, s)
    values, vectors = np.linalg.eigh(second / (12.0 * total))
    axes = vectors[:, ::-1].T.copy()  # rows, decreasing variance
    for a in range(3):
        h = rel @ axes[a]  # (f, 3) heights of the corners
        # exact third moment of a uniform triangle: the complete symmetric cubic over 10
        h0, h1, h2 = h[:, 0], h[:, 1], h[:, 2]
        cubic = (
            h0**3 + h1**3 + h2**3 + h0 * h0 * (h1 + h2) + h1 * h1 * (h0 + h2) + h2 * h2 * (h0 + h1) + h0 * h1 * h2
        ) / 10.0
        if float((area * cubic).sum()) < 0:
            axes[a] = -axes[a]
    if np.linalg.det(axes) < 0:
        axes[2] = -axes[2]
    return np.vstack([centroid, axes])


#: heights within this fraction of the extent are one height (a face flat across the axis)
_FLAT = 1e-9
#: a level on a flat face is moved this fraction of the extent into the solid: a plane on
#: the face itself cuts nothing well defined, one just inside cuts the walls next to it
_OFF_FACE = 1e-3
#: bisection steps of a quantile (2^-60 of the bracket: below float64's resolution)
_STEPS = 60


def _area_below(t: float, h: np.ndarray, area: np.ndarray, flat: np.ndarray) -> float:
    """The exact area of the triangles (sorted corner heights ``h`` (f, 3), areas ``area``)
    below height ``t``: the area density of a triangle along an axis is a tent, rising
    from its lowest corner to its middle one, falling to its highest."""
    h0, h1, h2 = h[:, 0], h[:, 1], h[:, 2]
    w = np.where(flat, 1.0, h2 - h0)
    frac = (t >= h2).astype(np.float64)
    rising = (t > h0) & (t <= h1) & ~flat
    frac[rising] = (t - h0[rising]) ** 2 / (w[rising] * (h1[rising] - h0[rising]))
    falling = (t > h1) & (t < h2) & ~flat
    frac[falling] = 1.0 - (h2[falling] - t) ** 2 / (w[falling] * (h2[falling] - h1[falling]))
    return float((area * frac).sum())


def area_quantile_levels(heights: np.ndarray, area: np.ndarray, sections: int) -> np.ndarray:
    """(sections,) levels along one axis at the exact area quantiles ``(i + 0.5) / N`` of the
    triangles with corner ``heights`` (f, 3) and areas ``area`` (f,): the same surface
    gives the same levels however it is triangulated. A quantile that falls on a face
    flat across the axis (a jump of the area below) is moved just inside the solid."""
    h = np.sort(heights, axis=1)
    lo, hi = float(h[:, 0].min()), float(h[:, 2].max())
    extent = hi - lo
    if not extent > 0:
        return np.full(sections, lo)
    flat = (h[:, 2] - h[:, 0]) <= _FLAT * extent
    total = float(area.sum())
    levels = np.empty(sections)
    for i in range(sections):
        target = (i + 0.5) / sections * total
        a, b = lo, hi
        hs, areas, flats, below = h, area, flat, 0.0
        for step in range(_STEPS):
            if step % 8 == 7:  # only the triangles across the bracket still matter
                done = hs[:, 2] <= a
                below += float(areas[done].sum())
                keep = ~done & (hs[:, 0] < b)
                hs, areas, flats = hs[keep], areas[keep], flats[keep]
            mid = 0.5 * (a + b)
            if below + _area_below(mid, hs, areas, flats) < target:
                a = mid
            else:
                b = mid
        t = 0.5 * (a + b)
        on_face = flat & (np.abs(h[:, 0] - t) <= 1e-6 * extent)
        if on_face.any():  # inward: towards the centre of the extent
            centre = 0.5 * (lo + hi)
            t = t + _OFF_FACE * extent * (1.0 if t < centre else -1.0)
        levels[i] = t
    return levels


def _loop_measures(loop: np.ndarray, a: int | None, area: float) -> tuple[float, float, float, float]:
    """``(perimeter, relative enclosed area, elongation, log relative perimeter)`` of a
    loop in the frame (``a``: the axis its plane is perpendicular to; None: a boundary
    loop, measured in its own best plane)."""
    nxt = np.roll(loop, -1, axis=0)
    seg = np.linalg.norm(nxt - loop, axis=1)
    perimeter = float(seg.sum())
    mid = 0.5 * (loop + nxt)
    w = seg / max(perimeter, 1e-300)
    centre = (w[:, None] * mid).sum(axis=0)
    rel = mid - centre
    if a is None:
        cov3 = np.einsum("i,ij,ik->jk", w, rel, rel)
        _, vec = np.linalg.eigh(cov3)
        uv = (loop - centre) @ vec[:, 1:]
        rel2 = rel @ vec[:, 1:]
    else:
        keep = [k for k in range(3) if k != a]
        uv = loop[:, keep]
        rel2 = rel[:, keep]
    cov = np.einsum("i,ij,ik->jk", w, rel2, rel2)
    ev = np.clip(np.linalg.eigvalsh(cov), 0.0, None)  # a collinear loop: -1e-17, not NaN
    elongation = float(np.sqrt(ev[0] / ev[1])) if ev[1] > 0 else 0.0
    x, y = uv[:, 0], uv[:, 1]
    enclosed = 0.5 * abs(float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1))))
    root = np.sqrt(area)
    return perimeter, enclosed / area, elongation, float(np.log(max(perimeter / root, 1e-12)))


def cut_object(
    mesh: str | os.PathLike[str] | trimesh.Trimesh, rule: ObjectRule | None = None, *, name: str | None = None
) -> ObjectCut:
    """The contours and measures of one object (see the module doc).

    ``mesh``: a mesh file path (read with :func:`~.load.load_mesh`) or a ``trimesh.Trimesh``;
    ``rule``: an :class:`ObjectRule` (None: the default); ``name``: what the notes call it.
    Raises ReadError, UnknownFormatError, MeshError (:func:`~.load.load_mesh`; a surface
    of zero area)."""
    rule = ObjectRule() if rule is None else rule
    if isinstance(mesh, (str, bytes, os.PathLike)):
        where = str(os.fspath(mesh)) if name is None else name
        mesh = load_mesh(mesh)
    else:
        where = name or "<mesh>"
    vertices, faces, tri_area, scale = _triangles(mesh)  # computed scaled; results unscaled
    try:
        frame = principal_frame(vertices[faces], tri_area)
    except MeshError as exc:
        raise MeshError(exc.message, path=where) from None
    total = float(tri_area.sum())
    area = total / scale / scale  # scale**2 itself may be out of range
    if not (np.isfinite(area) and area > 0):
        raise MeshError(
            f"its surface area ({'above' if area > 0 else 'below'} float64's range) cannot be stored: "
            f"coordinates too {'large' if area > 0 else 'small'}",
            path=where,
        )
    centroid, axes = frame[0], frame[1:]
    local = (vertices - centroid) @ axes.T  # the frame's coordinates
    edges = np.asarray(mesh.edges_unique, dtype=np.int64)
    face_edges = np.asarray(mesh.faces_unique_edges, dtype=np.int64)
    N = rule.sections
    cut = ObjectCut(
        mesh=where, rule=rule, area=area, frame=np.vstack([centroid / scale, axes]), levels=np.zeros((3, N))
    )
    loops, axis_of, level_of, measures = [], [], [], []
    profile = np.zeros((3, N, len(PROFILE_FEATURES)))
    notes: list[str] = []
    for a in range(3):
        height = local[:, a]
        face_h = height[faces]
        levels = area_quantile_levels(face_h, tri_area, N)
        cut.levels[a] = levels / scale
        face_lo, face_hi = face_h.min(axis=1), face_h.max(axis=1)
        for i, t in enumerate(levels.tolist()):
            found = section_loops(local, faces, edges, face_edges, face_lo, face_hi, a, t, where, notes)
            kept = [c for c in found if len(c) >= rule.min_vertices]
            for k, c in enumerate(kept):
                perimeter, rel_area, elongation, log_rel = _loop_measures(c, a, total)
                loops.append((c @ axes + centroid) / scale)
                axis_of.append(a)
                level_of.append(i)
                measures.append((log_rel, rel_area, elongation))
                profile[a, i, 0] += 1
                profile[a, i, 1] += perimeter / np.sqrt(total)
                profile[a, i, 2] += rel_area
                if k == 0:  # loops come by decreasing perimeter
                    profile[a, i, 3] = elongation
    if rule.boundaries:
        for c in boundary_loops(mesh, f"{where}: boundary", notes):
            if len(c) < rule.min_vertices:
                continue
            _, rel_area, elongation, log_rel = _loop_measures((c * scale - centroid) @ axes.T, None, total)
            loops.append(np.array(c))
            axis_of.append(BOUNDARY_AXIS)
            level_of.append(0)
            measures.append((log_rel, rel_area, elongation))
    cut.loops = loops
    cut.axis = np.asarray(axis_of, dtype=np.int8)
    cut.level = np.asarray(level_of, dtype=np.int16)
    cut.measures = np.asarray(measures, dtype=np.float64).reshape(-1, len(MEASURES))
    cut.profile = profile.reshape(-1)
    cut.notes = notes
    if not loops:
        raise MeshError(
            f"no closed contour of {rule.min_vertices} or more vertices in any section: not an object", path=where
        )
    return cut


#: the names of the principal axes in contour names and listings (decreasing variance)
PRINCIPAL_AXES = ("pa", "pb", "pc")


def principal_contours(path: str | os.PathLike[str], *, sections: int, boundaries: bool) -> ExtractResult:
    """``extract --axis principal``: the contours of the mesh at ``path`` cut by the object
    rule (:func:`cut_object` with ``sections`` >= 1 planes per principal axis; ``boundaries``:
    the boundary loops of an open mesh too), as an
    :class:`~.contours.ExtractResult` whose contours name their axis ``pa``, ``pb``, ``pc``
    and their level as the plane's offset from the area centroid along it."""
    p = str(os.fspath(path))
    mesh = load_mesh(p)
    cut = cut_object(mesh, ObjectRule(sections=sections, boundaries=boundaries), name=p)
    result = ExtractResult(
        mesh=p, axis="principal", levels=cut.levels[0].copy(), vertices=len(mesh.vertices), faces=len(mesh.faces)
    )
    result.notes.extend(cut.notes)
    keys = list(zip(cut.axis.tolist(), cut.level.tolist()))
    for i, (pts, key) in enumerate(zip(cut.loops, keys)):
        a, level = key
        same = [j for j, k in enumerate(keys) if k == key]
        loop, count = same.index(i), len(same)
        if a == BOUNDARY_AXIS:
            result.contours.append(Contour(points=pts, mesh=p, kind="boundary", loop=loop, loop_count=count))
            continue
        result.contours.append(
            Contour(
                points=pts,
                mesh=p,
                kind="section",
                axis=PRINCIPAL_AXES[a],
                level=float(cut.levels[a, level]),
                level_index=level,
                loop=loop,
                level_count=sections,
                loop_count=count,
            )  # fmt: skip
        )
    return result
