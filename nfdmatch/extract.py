"""Closed contours from triangle meshes: planar cross-sections and boundary loops.

The library behind ``nfdmatch extract``: it never prints and never exits.
trimesh is imported inside the functions that need it, so importing this module
(or the CLI) does not pay for it.

What is extracted
-----------------
* **Sections**: the mesh is cut by ``N`` planes perpendicular to one axis
  (``"x"``, ``"y"``, ``"z"``, or ``"auto"``: the longest extent of the
  axis-aligned bounding box, ties going to the earlier axis). With the extent
  ``[lo, hi]`` along that axis the levels are the midpoints of ``N`` equal
  slabs, ``level_i = lo + (i + 0.5) * (hi - lo) / N`` for ``i = 0 .. N-1``, so
  no plane lies on a flat cap of the mesh and ``N = 1`` cuts through the middle.
  Every closed loop of every section is one contour; open pieces (where the
  plane crosses a hole of an open mesh) are skipped with a note.
* **Boundaries** (``boundaries=True``): the edges used by exactly one face,
  chained into loops; a closed (watertight) mesh has none (a note says so).

How a section is computed
-------------------------
Each vertex gets the signed height ``d = coordinate - level``; a vertex exactly
on the plane counts as above it (``d >= 0``), as if the plane were moved down by
an infinitesimal amount. A unique mesh edge whose ends lie on different sides
crosses the plane at one point, and a face with a crossing has exactly two
crossing edges, giving one segment between two *edge ids*. Chaining segments by
edge id (not by rounded coordinates) gives the exact topology: on a manifold
mesh every crossing edge has two faces, so every section of a closed mesh is a
set of closed loops. The points get the level as their coordinate along the
axis exactly. Consecutive coincident points (a plane through a vertex) are
removed by :func:`~nfdmatch.curve.clean_points`.

Section loops run counter-clockwise seen from the positive end of the axis
(right-handed about ``+axis``). Boundary loops follow the winding of the faces
along them where the boundary is a simple loop. Within one section (or the
boundary set) loops are numbered by decreasing perimeter, so ``loop0`` is the
longest (the outer loop of a section with holes).

Branching points (a section or boundary vertex used by more than two segments:
non-manifold edges, two loops touching at a vertex) do not stop the extraction:
dangling branches are removed as open pieces, the rest is split into simple
loops at the branching vertices (a note tells how many branching points).

File names
----------
One curve per file, ``<stem>_section-<axis><ii>_at<level>_loop<k>`` or
``<stem>_boundary_loop<k>`` plus the curve format's extension, for example
``torus_section-z03_at-0.125_loop0.obj`` or ``cup_boundary_loop1.obj``:

* ``<stem>``: the mesh file name without its extension, every run of
  characters other than ``A-Z a-z 0-9 . _ -`` replaced by ``_`` (so no ``#``,
  which would read as a curve selector, and no spaces). When several meshes of
  one :func:`write_contours` call share a stem (``part.stl`` and ``part.ply``,
  or ``a/part.stl`` and ``b/part.stl``) the extension is appended
  (``part-stl``), then ``-2``, ``-3`` ... in input order.
* ``<ii>``: the 0-based level index, zero-padded to the width of ``N - 1``
  (at least 2 digits) so that files sort in level order.
* ``<level>``: the plane's coordinate along the axis, ``%.6g`` (``-0.125``,
  ``3``, ``1.5e+06``); for reading only, the index makes names unique.
* ``<k>``: the loop number, zero-padded to the width of the loop count - 1.
"""

from __future__ import annotations

import logging
import os
import re
from collections.abc import Iterable, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field

import numpy as np

from .curve import Curve, clean_points
from .errors import (CurveError, MeshError, NfdError, ParameterError, ReadError,
                     UnknownFormatError, WriteError)
from .formats import FORMATS, format_of, write_curves
from .formats._chain import chain_segments, check_readable, write_if_changed

__all__ = ["AXES", "DEFAULT_SECTIONS", "Contour", "ExtractResult", "PruneResult", "MANIFEST", "mesh_extensions",
           "find_mesh_files", "load_mesh", "section_levels", "extract_contours",
           "write_contours", "prune_contours", "read_manifest", "mesh_stem"]

#: the axes a section can be perpendicular to
AXES = ("x", "y", "z")
#: default number of section levels
DEFAULT_SECTIONS = 10

_KINDS = ("section", "boundary")
_UNSAFE = re.compile(r"[^A-Za-z0-9._-]+")
# trimesh formats that are not triangle meshes (point clouds) or not extensions
_NOT_MESH_FORMATS = {"xyz", "stl_ascii"}


# ---------------------------------------------------------------------------
# records
# ---------------------------------------------------------------------------

@dataclass(frozen=True)
class Contour:
    """One closed contour extracted from a mesh.

    Attributes
    ----------
    points : (m, 3) float64, read-only, m >= 3. A closed polyline, cleaned by
        :func:`~nfdmatch.curve.clean_points`: the closing edge is implicit (the
        last vertex is not repeated), no two consecutive vertices are equal.
        Section points have the level as their coordinate along ``axis``.
    mesh : the mesh file it comes from (as given).
    kind : ``"section"`` or ``"boundary"``.
    axis : ``"x"``, ``"y"`` or ``"z"`` for a section, None for a boundary loop.
    level : the plane's coordinate along ``axis`` (section), else None.
    level_index : 0-based index of the level (section), else None.
    loop : 0-based loop number within its section (or within the boundary
        loops), by decreasing perimeter.
    level_count : number of levels N of the extraction (zero-padding of the
        level index in :attr:`name`), None for a boundary loop.
    loop_count : number of loops of its section / boundary set (zero-padding
        of the loop number).
    """

    points: np.ndarray = field(repr=False)
    mesh: str
    kind: str
    axis: str | None = None
    level: float | None = None
    level_index: int | None = None
    loop: int = 0
    level_count: int | None = None
    loop_count: int | None = None

    @property
    def n_vertices(self) -> int:
        return int(self.points.shape[0])

    @property
    def name(self) -> str:
        """File stem, e.g. ``torus_section-z03_at-0.125_loop0`` or ``box_boundary_loop0``."""
        return self.name_for(mesh_stem(self.mesh))

    def name_for(self, stem: str) -> str:
        """The file stem with ``stem`` in place of the mesh's own (see the module doc)."""
        loop_width = len(str(max((self.loop_count or 1) - 1, 0)))
        loop = f"loop{self.loop:0{loop_width}d}"
        if self.kind == "boundary":
            return f"{stem}_boundary_{loop}"
        width = max(2, len(str(max((self.level_count or 1) - 1, 0))))
        level = f"{self.level + 0.0:.6g}"          # + 0.0: no "-0"
        return f"{stem}_section-{self.axis}{self.level_index:0{width}d}_at{level}_{loop}"


@dataclass
class ExtractResult:
    """What :func:`extract_contours` found in one mesh.

    Attributes
    ----------
    mesh : the mesh file (as given).
    axis : the section axis used (``"auto"`` resolved), None when ``sections == 0``.
    levels : (N,) float64, the section levels along ``axis`` (empty when N is 0).
    contours : sections in level order (loops by decreasing perimeter), then
        boundary loops.
    notes : human-readable remarks, each starting with the mesh path: open
        pieces skipped, degenerate loops skipped, branching points split, no
        boundary, nothing extracted.
    vertices, faces : size of the mesh after merging coincident vertices.
    """

    mesh: str
    axis: str | None
    levels: np.ndarray
    contours: list[Contour] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    vertices: int = 0
    faces: int = 0


# ---------------------------------------------------------------------------
# finding and loading meshes
# ---------------------------------------------------------------------------

def mesh_extensions() -> list[str]:
    """Extensions of the triangle-mesh formats the installed trimesh reads, e.g. ``['.glb', ..., '.stl']``.

    Point-cloud formats (``.xyz``) are not included. Imports trimesh.
    """
    from trimesh.exchange.load import mesh_formats

    return sorted("." + f for f in mesh_formats() if f not in _NOT_MESH_FORMATS)


def find_mesh_files(sources: Iterable, *, exclude: Iterable = ()) -> list[str]:
    """Mesh files named by ``sources``, in a deterministic order.

    Parameters
    ----------
    sources : paths. A path that is not a folder is taken as given, whatever
        its extension and even if it does not exist, so that
        :func:`extract_contours` reports it (a missing file is then one failed
        input among others, not the end of the run). A folder is walked
        recursively, keeping files with an extension of :func:`mesh_extensions`
        (case-insensitive) and skipping hidden files and folders.
    exclude : folders not to walk into (e.g. the output folder, which may hold
        ``.obj`` contours written by an earlier run).

    Returns
    -------
    list of str paths, sorted within each folder, without duplicates.
    """
    from .sources import UniquePaths, walk_folder

    extensions = set(mesh_extensions())
    found = UniquePaths()
    for source in sources:
        source = str(os.fspath(source))
        if not os.path.isdir(source):
            found.add(source)
            continue
        for path in walk_folder(source, extensions, exclude=exclude):
            found.add(path)
    return found.paths


@contextmanager
def _captured_trimesh_log(messages: list[str]):
    """Collect trimesh's log records instead of letting Python print them on stderr."""

    class _Collect(logging.Handler):
        def emit(self, record):
            try:
                messages.append(record.getMessage())
            except Exception:  # pragma: no cover - a malformed log call
                pass

    logger = logging.getLogger("trimesh")
    handler = _Collect(level=logging.WARNING)
    logger.addHandler(handler)
    try:
        yield
    finally:
        logger.removeHandler(handler)


def load_mesh(path):
    """Read a triangle mesh with trimesh; every geometry of a scene, concatenated.

    Parameters
    ----------
    path : str or PathLike, a file in a format of :func:`mesh_extensions`
        (chosen by its extension).

    Returns
    -------
    ``trimesh.Trimesh`` built from the geometry only (vertices (n, 3) float64,
    faces (f, 3) int64): scene transforms applied, coincident vertices merged
    (so that UV/normal seams and STL's unshared vertices do not look like
    holes), faces with a repeated vertex and faces with a non-finite vertex
    dropped.

    Raises
    ------
    ReadError : missing, a folder, unreadable.
    UnknownFormatError : an extension trimesh does not read as a mesh (a curve
        CSV, ``.xyz``, ...).
    MeshError : an empty file, contents trimesh cannot parse, a file holding no
        triangle geometry (a point cloud, lines) or no usable face.
    """
    p = check_readable(str(os.fspath(path)))
    import trimesh

    ext = os.path.splitext(p)[1].lower()
    known = mesh_extensions()
    if ext not in known:
        what = f"unknown mesh file extension {ext!r}" if ext else "no file extension"
        hint = ""
        if ext in {e for exts in FORMATS.values() for e in exts}:
            hint = " (it looks like a curve file: index or query it directly)"
        raise UnknownFormatError(f"{what}{hint}; mesh formats: {', '.join(known)}", path=p)
    try:
        if os.path.getsize(p) == 0:
            raise MeshError("not a triangle mesh: the file is empty", path=p)
    except OSError as exc:  # pragma: no cover - vanished between the checks
        raise ReadError(f"cannot read the file ({exc.strerror or exc})", path=p) from None

    log: list[str] = []
    try:
        with _captured_trimesh_log(log), np.errstate(all="ignore"):
            loaded = trimesh.load(p, file_type=ext[1:], process=False)
            parts = _triangle_parts(loaded)
    except NfdError:
        raise
    except MemoryError:
        raise MeshError("not a triangle mesh: out of memory while reading it", path=p) from None
    except Exception as exc:  # trimesh raises ValueError, KeyError, IndexError, struct.error, ...
        said = str(exc).strip() or type(exc).__name__
        raise MeshError(f"not a readable triangle mesh: {said}", path=p) from None
    if isinstance(parts, str):
        extra = f" ({'; '.join(log[:2])})" if log else ""
        if ext == ".obj" and _has_obj_lines(p):
            extra += " (an OBJ of 'l' polylines is a curve file: index or query it directly)"
        raise MeshError(f"not a triangle mesh: {parts}{extra}", path=p)

    vertices = np.concatenate([v for v, _ in parts]) if parts else np.zeros((0, 3))
    offsets = np.cumsum([0] + [len(v) for v, _ in parts[:-1]])
    faces = (np.concatenate([f + o for (_, f), o in zip(parts, offsets)]) if parts
             else np.zeros((0, 3), dtype=np.int64))
    if len(faces) == 0:
        raise MeshError("not a triangle mesh: it has no faces", path=p)
    finite = np.isfinite(vertices).all(axis=1)
    usable = finite[faces].all(axis=1)
    faces = faces[usable]
    try:
        with np.errstate(all="ignore"):
            mesh = trimesh.Trimesh(vertices=vertices, faces=faces, process=True, validate=False)
    except Exception as exc:
        raise MeshError(f"not a usable triangle mesh: {exc}", path=p) from None
    f = np.asarray(mesh.faces, dtype=np.int64)
    keep = (f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2])
    if not keep.all():
        mesh.update_faces(keep)
    if len(mesh.faces) == 0:
        raise MeshError("not a usable triangle mesh: every face is degenerate "
                        "(repeated or non-finite vertices)", path=p)
    return mesh


def _has_obj_lines(path: str) -> bool:
    """True when the (failed) OBJ file has ``l`` polyline elements (a curve file)."""
    try:
        with open(path, "rb") as fh:
            return any(line.lstrip().startswith(b"l ") for line in fh)
    except OSError:  # pragma: no cover
        return False


def _triangle_parts(loaded) -> list[tuple[np.ndarray, np.ndarray]] | str:
    """``[(vertices (n, 3) float64, faces (f, 3) int64), ...]`` of a loaded geometry,
    or a text saying why there is no triangle geometry."""
    import trimesh

    if isinstance(loaded, trimesh.Scene):
        if not loaded.geometry:
            return "trimesh found no geometry in it (garbage, or another format?)"
        geometries = loaded.dump(concatenate=False)  # scene-graph transforms applied
    else:
        geometries = [loaded]
    parts, others = [], []
    for g in geometries:
        if isinstance(g, trimesh.Trimesh) and len(g.faces):
            parts.append((np.asarray(g.vertices, dtype=np.float64).reshape(-1, 3),
                          np.asarray(g.faces, dtype=np.int64).reshape(-1, 3)))
        else:
            others.append(g)
    if parts:
        return parts
    kinds = sorted({_geometry_kind(g) for g in others}) or ["nothing"]
    return f"it holds {' and '.join(kinds)} but no faces"


def _geometry_kind(g) -> str:
    import trimesh

    if isinstance(g, trimesh.PointCloud):
        return "a point cloud"
    if isinstance(g, trimesh.Trimesh):
        return "vertices"
    if isinstance(g, trimesh.path.path.Path):
        return "lines"
    return type(g).__name__


# ---------------------------------------------------------------------------
# levels
# ---------------------------------------------------------------------------

def section_levels(bounds, sections: int, axis: str = "auto") -> tuple[str, np.ndarray]:
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

def extract_contours(path, *, sections: int = DEFAULT_SECTIONS, axis: str = "auto",
                     boundaries: bool = False) -> ExtractResult:
    """Closed section loops (and boundary loops) of the triangle mesh in ``path``.

    Parameters
    ----------
    path : a mesh file (see :func:`load_mesh`).
    sections : number N >= 0 of section levels (see :func:`section_levels`);
        0 with ``boundaries=True`` extracts only the boundary loops.
    axis : ``"x"``, ``"y"``, ``"z"`` or ``"auto"`` (the longest extent of the
        bounding box).
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
    result = ExtractResult(mesh=p, axis=None, levels=np.zeros(0), vertices=len(vertices),
                           faces=len(faces))
    notes = result.notes

    if sections:
        axis_name, levels = section_levels(mesh.bounds, sections, axis)
        result.axis, result.levels = axis_name, levels
        a = AXES.index(axis_name)
        bounds = np.asarray(mesh.bounds, dtype=np.float64)   # of the vertices used by faces
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
                loops = _section_loops(vertices, faces, edges, face_edges, face_lo, face_hi,
                                       a, level, where, notes)
                loops = _orient_ccw(loops, a)
                result.contours.extend(
                    Contour(points=pts, mesh=p, kind="section", axis=axis_name, level=float(level),
                            level_index=i, loop=k, level_count=sections, loop_count=len(loops))
                    for k, pts in enumerate(loops))

    if boundaries:
        loops = _boundary_loops(mesh, f"{p}: boundary", notes)
        if not loops and not any(n.startswith(f"{p}: boundary") for n in notes):
            notes.append(f"{p}: no boundary loops (the mesh is closed)")
        result.contours.extend(
            Contour(points=pts, mesh=p, kind="boundary", loop=k, loop_count=len(loops))
            for k, pts in enumerate(loops))

    if not result.contours:
        asked = " or ".join(w for w, on in (("section loops", sections), ("boundary loops", boundaries))
                            if on)
        notes.append(f"{p}: nothing extracted (no closed {asked})")
    return result


def _section_loops(vertices, faces, edges, face_edges, face_lo, face_hi, a: int, level: float,
                   where: str, notes: list[str]) -> list[np.ndarray]:
    """Closed loops of the plane ``coordinate a == level``, as cleaned (m, 3) float64 arrays.

    vertices (n, 3) float64, faces (f, 3) int64, edges (e, 2) int64 unique
    sorted edges, face_edges (f, 3) int64 into ``edges``, face_lo/face_hi (f,)
    float64 the faces' extent along ``a``. A vertex on the plane counts as above it.
    """
    hit = (face_lo < level) & (face_hi >= level)
    if not hit.any():
        return []
    fe = face_edges[hit]                                    # (h, 3) edge ids
    used = np.unique(fe)
    ends = edges[used]                                      # (u, 2)
    d = vertices[ends, a] - level                           # (u, 2) signed heights
    crossing = (d[:, 0] >= 0) != (d[:, 1] >= 0)
    cross_of = np.zeros(len(edges), dtype=bool)
    cross_of[used[crossing]] = True
    fc = cross_of[fe]                                       # (h, 3): two True per row
    rows, cols = np.nonzero(fc)
    segments = fe[rows, cols].reshape(-1, 2)                # (h, 2) pairs of edge ids

    # crossing points, one per crossing edge (computed once per edge, so both faces
    # of an edge share it exactly); segments renumbered into them
    ids = used[crossing]                                    # sorted edge ids
    d0, d1 = d[crossing, 0], d[crossing, 1]
    t = d0 / (d0 - d1)
    p0, p1 = vertices[edges[ids, 0]], vertices[edges[ids, 1]]
    # (1 - t) p0 + t p1 gives the vertex itself exactly where the plane passes through one
    # (t = 0 or 1), so the two edges meeting there give the same point and cleaning drops it
    points = (1.0 - t)[:, None] * p0 + t[:, None] * p1      # (c, 3)
    points[:, a] = level
    return _loops_to_points(np.searchsorted(ids, segments), points, where, notes)


def _boundary_loops(mesh, where: str, notes: list[str]) -> list[np.ndarray]:
    """Boundary loops (edges used by exactly one face) as cleaned (m, 3) float64 arrays,
    by decreasing perimeter."""
    from trimesh.grouping import group_rows

    single = group_rows(np.asarray(mesh.edges_sorted), require_count=1)
    if len(single) == 0:
        return []
    segments = np.asarray(mesh.edges, dtype=np.int64)[np.asarray(single, dtype=np.int64)]
    order = np.argsort(single, kind="stable")               # face order: walking follows winding
    return _loops_to_points(segments[order], np.asarray(mesh.vertices, dtype=np.float64),
                            where, notes)


def _loops_to_points(segments: np.ndarray, points: np.ndarray, where: str,
                     notes: list[str]) -> list[np.ndarray]:
    """Chain segments (m, 2) int64 of ids into ``points`` (k, 3) into closed loops.

    Returns cleaned (n_i, 3) float64 loops by decreasing perimeter; open pieces,
    branching points and degenerate loops are counted in ``notes`` (prefixed by ``where``).
    """
    loops, open_pieces, branching = _chain_loops(segments)
    if branching:
        notes.append(f"{where}: {branching} branching point{'s' if branching != 1 else ''} "
                     "(non-manifold), loops split there")
    if open_pieces:
        notes.append(f"{where}: {open_pieces} open piece{'s' if open_pieces != 1 else ''} "
                     "skipped (not closed)")
    out, degenerate = [], 0
    for ids in loops:
        try:
            out.append(clean_points(points[ids]))
        except CurveError:
            degenerate += 1
    if degenerate:
        notes.append(f"{where}: {degenerate} degenerate loop{'s' if degenerate != 1 else ''} "
                     "skipped (fewer than 3 distinct points)")
    lengths = [float(np.linalg.norm(np.diff(c, axis=0, append=c[:1]), axis=1).sum()) for c in out]
    order = sorted(range(len(out)), key=lambda k: (-lengths[k], tuple(out[k].min(axis=0))))
    result = [out[k] for k in order]
    for c in result:
        c.setflags(write=False)
    return result


def _chain_loops(segments) -> tuple[list[np.ndarray], int, int]:
    """Closed loops of an undirected segment graph.

    Parameters
    ----------
    segments : (m, 2) int array of vertex ids; self-segments and repeated
        segments are ignored.

    Returns
    -------
    ``(loops, open_pieces, branching)``: loops as (k,) int64 id arrays in walking
    order (closing edge implicit); the number of open pieces dropped; the number
    of ids used by more than two segments. Without branching this is
    :func:`~nfdmatch.formats._chain.chain_segments` keeping its closed
    components; with branching see :func:`_split_branching`.
    """
    seg = np.asarray(segments, dtype=np.int64).reshape(-1, 2)
    seg = seg[seg[:, 0] != seg[:, 1]]
    if len(seg) == 0:
        return [], 0, 0
    key = np.sort(seg, axis=1)
    _, first = np.unique(key, axis=0, return_index=True)
    seg = seg[np.sort(first)]
    degree = np.bincount(seg.ravel())
    branching = int((degree > 2).sum())
    if branching:
        loops, open_pieces = _split_branching(seg)
        return loops, open_pieces, branching
    components = chain_segments(seg)          # degree <= 2 here: it cannot find a branch
    loops, open_pieces = [], 0
    for _, ids in components:
        if (degree[ids] == 2).all():
            loops.append(ids)
        else:
            open_pieces += 1
    return loops, open_pieces, 0


def _split_branching(seg: np.ndarray) -> tuple[list[np.ndarray], int]:
    """Simple loops of a segment graph with branching vertices, and the number of open pieces.

    ``seg`` (m, 2) int64, no self or repeated segments. Dangling branches are
    pruned first (each connected group of pruned segments is one open piece);
    the rest is walked edge by edge, cutting off a simple loop whenever the walk
    comes back to a vertex already on it; a walk that gets stuck (possible with
    odd degrees, e.g. a theta shape) leaves its unclosed part as an open piece.
    """
    m = len(seg)
    adjacency: dict[int, list[tuple[int, int]]] = {}
    for e, (u, v) in enumerate(seg.tolist()):
        adjacency.setdefault(u, []).append((v, e))
        adjacency.setdefault(v, []).append((u, e))
    alive = [True] * m
    degree = {v: len(n) for v, n in adjacency.items()}

    # prune dangling branches
    pruned: list[int] = []
    stack = [v for v, k in degree.items() if k == 1]
    while stack:
        v = stack.pop()
        if degree[v] != 1:
            continue
        for w, e in adjacency[v]:
            if alive[e]:
                alive[e] = False
                pruned.append(e)
                degree[v] -= 1
                degree[w] -= 1
                if degree[w] == 1:
                    stack.append(w)
                break
    open_pieces = _count_components(seg[pruned]) if pruned else 0

    loops: list[np.ndarray] = []
    used = [not a for a in alive]
    cursor = {v: 0 for v in adjacency}

    def next_edge(v: int):
        nbrs = adjacency[v]
        i = cursor[v]
        while i < len(nbrs) and used[nbrs[i][1]]:
            i += 1
        cursor[v] = i
        return nbrs[i] if i < len(nbrs) else None

    for e0 in range(m):
        if used[e0]:
            continue
        used[e0] = True
        u, v = int(seg[e0, 0]), int(seg[e0, 1])
        path, position = [u, v], {u: 0, v: 1}
        while True:
            step = next_edge(path[-1])
            if step is None:
                if len(path) > 1:
                    open_pieces += 1
                break
            w, e = step
            used[e] = True
            if w in position:
                i = position[w]
                loops.append(np.array(path[i:], dtype=np.int64))
                for x in path[i + 1:]:
                    del position[x]
                del path[i + 1:]
                if len(path) == 1 and next_edge(w) is None:
                    break
            else:
                position[w] = len(path)
                path.append(w)
    return loops, open_pieces


def _count_components(seg: np.ndarray) -> int:
    """Number of connected components of the graph with edges ``seg`` (m, 2) int64."""
    parent: dict[int, int] = {}

    def find(x: int) -> int:
        parent.setdefault(x, x)
        while parent[x] != x:
            parent[x] = parent[parent[x]]
            x = parent[x]
        return x

    for u, v in seg.tolist():
        ru, rv = find(u), find(v)
        if ru != rv:
            parent[ru] = rv
    return len({find(x) for x in parent})


def _orient_ccw(loops: list[np.ndarray], a: int) -> list[np.ndarray]:
    """Reverse the loops that run clockwise seen from the positive end of axis ``a``."""
    i, j = (a + 1) % 3, (a + 2) % 3                        # right-handed in-plane coordinates
    out = []
    for c in loops:
        x, y = c[:, i], c[:, j]
        area2 = float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))
        if area2 < 0:
            c = c[::-1].copy()
            c.setflags(write=False)
        out.append(c)
    return out


# ---------------------------------------------------------------------------
# writing
# ---------------------------------------------------------------------------

def mesh_stem(path) -> str:
    """The mesh file name without extension, made filesystem- and selector-safe.

    Runs of characters other than ``A-Z a-z 0-9 . _ -`` become ``_``; a name
    left empty or starting with ``.`` gets the prefix ``mesh``.
    """
    base = os.path.splitext(os.path.basename(str(os.fspath(path))))[0]
    stem = _UNSAFE.sub("_", base)
    if not stem or stem.startswith("."):
        stem = "mesh" + stem
    return stem


def _unique_stems(meshes: Sequence[str]) -> dict[str, str]:
    """Mesh path -> file-name stem, unique across ``meshes`` (see the module doc)."""
    ordered = list(dict.fromkeys(meshes))
    base = {m: mesh_stem(m) for m in ordered}
    count: dict[str, int] = {}
    for m in ordered:
        count[base[m]] = count.get(base[m], 0) + 1
    stems: dict[str, str] = {}
    taken: set[str] = set()
    for m in ordered:
        stem = base[m]
        if count[stem] > 1:
            ext = os.path.splitext(m)[1].lstrip(".").lower()
            stem = f"{stem}-{_UNSAFE.sub('_', ext)}" if ext else stem
        candidate, k = stem, 1
        while candidate in taken:
            k += 1
            candidate = f"{stem}-{k}"
        taken.add(candidate)
        stems[m] = candidate
    return stems


def write_contours(contours: Sequence[Contour], out_dir, *, format: str = "obj") -> list[str]:
    """Write each contour to its own curve file in ``out_dir`` (created if needed).

    Parameters
    ----------
    contours : the contours of one or several meshes (e.g. of several
        :func:`extract_contours` results).
    out_dir : the folder; existing files of the same name are replaced when their
        content changes and left untouched (mtime kept) when it would not, so that
        make-style pipelines downstream rebuild only what changed; other files are left
        alone. Each file is written whole to a hidden temporary file, then renamed. The
        folder's manifest (:data:`MANIFEST`) records every file written, for
        :func:`prune_contours`.
    format : a curve format of :data:`nfdmatch.formats.FORMATS` (``"obj"``,
        ``"csv"``, ``"vtp"``, ...); the file extension is its first one.

    Returns
    -------
    list of the written paths (``os.path.join(out_dir, name + ext)``), in the
    order of ``contours``. Names as :attr:`Contour.name`, made unique across
    meshes sharing a stem (module doc). Each file holds one curve, whose id when
    read back is its path.

    Raises
    ------
    UnknownFormatError : an unknown format.
    WriteError : the folder cannot be created, or a file cannot be written.
    """
    fmt = format_of("contour", format)
    ext = FORMATS[fmt][0]
    d = str(os.fspath(out_dir))
    try:
        os.makedirs(d, exist_ok=True)
    except FileExistsError:
        raise WriteError("cannot create the output folder: a file is in the way", path=d) from None
    except PermissionError:
        raise WriteError("cannot create the output folder: permission denied", path=d) from None
    except OSError as exc:
        raise WriteError(f"cannot create the output folder ({exc.strerror or exc})", path=d) from None
    stems = _unique_stems([c.mesh for c in contours])
    written = []
    produced: dict[str, str] = {}
    for c in contours:
        name = c.name_for(stems[c.mesh])
        target = os.path.join(d, name + ext)
        try:
            curve = Curve.trusted(c.points, name, c.mesh)
            write_if_changed(target, lambda temp: write_curves(temp, [curve], format=fmt))
        except WriteError:
            raise
        except NfdError as exc:
            raise WriteError(f"cannot write the contour: {exc}", path=target) from None
        except OSError as exc:
            raise WriteError(f"cannot write the file ({exc.strerror or exc})", path=target) from None
        except Exception as exc:  # a writer backend (VTK) failing its own way
            raise WriteError(f"cannot write the file ({type(exc).__name__}: {exc})",
                             path=target) from None
        written.append(target)
        produced[os.path.basename(target)] = c.mesh
    _record(d, produced)
    return written


# ---------------------------------------------------------------------------
# the manifest: which files of the folder extract wrote (docs/extract.md)
# ---------------------------------------------------------------------------

#: the manifest's file name in an output folder (hidden: no curve reader or walk sees it)
MANIFEST = ".nfdmatch-extract.json"
_MANIFEST_FORMAT = "nfdmatch-extract-manifest"


@dataclass
class PruneResult:
    """What :func:`prune_contours` did: ``removed`` (paths deleted), ``kept`` (``(path,
    reason)`` of files the manifest lists that were left alone: changed since extract wrote
    them, or their mesh failed this run) and ``notes`` (a manifest that could not be read)."""

    removed: list = field(default_factory=list)
    kept: list = field(default_factory=list)
    notes: list = field(default_factory=list)


def _sha256_file(path: str) -> str | None:
    import hashlib

    try:
        with open(path, "rb") as fh:
            return hashlib.sha256(fh.read()).hexdigest()
    except OSError:
        return None


def read_manifest(out_dir) -> tuple[dict, str | None]:
    """The manifest of ``out_dir``: ``({file name: {"mesh": real path, "sha256": hex}}, problem)``;
    ``problem`` is None, or why an existing manifest could not be used (it is then empty)."""
    import json

    path = os.path.join(str(os.fspath(out_dir)), MANIFEST)
    try:
        with open(path, encoding="utf-8") as fh:
            data = json.load(fh)
    except FileNotFoundError:
        return {}, None
    except (OSError, ValueError) as exc:
        return {}, f"{path}: cannot read the manifest ({type(exc).__name__}); nothing pruned by it"
    files = data.get("files") if isinstance(data, dict) and data.get("format") == _MANIFEST_FORMAT else None
    if not isinstance(files, dict):
        return {}, f"{path}: not an nfdmatch extract manifest; nothing pruned by it"
    entries = {}
    for name, entry in files.items():
        # only plain names of this folder: a manifest never points elsewhere
        if (isinstance(name, str) and isinstance(entry, dict) and name == os.path.basename(name)
                and name not in ("", ".", "..", MANIFEST) and isinstance(entry.get("sha256"), str)):
            entries[name] = {"mesh": str(entry.get("mesh", "")), "sha256": entry["sha256"]}
    return entries, None


def _write_manifest(d: str, entries: dict) -> None:
    import json

    text = json.dumps({"format": _MANIFEST_FORMAT, "version": 1,
                       "files": {name: entries[name] for name in sorted(entries)}}, indent=1, sort_keys=True) + "\n"
    target = os.path.join(d, MANIFEST)

    def produce(temp):
        with open(temp, "w", encoding="utf-8", newline="\n") as fh:
            fh.write(text)
    try:
        write_if_changed(target, produce)           # whole, atomically; untouched when the same
    except OSError as exc:
        raise WriteError(f"cannot write the manifest ({exc.strerror or exc})", path=target) from None


def _record(d: str, produced: dict) -> None:
    """Add this run's files (name -> mesh) to the manifest; entries of files gone are dropped."""
    entries, _ = read_manifest(d)
    entries = {name: e for name, e in entries.items() if os.path.lexists(os.path.join(d, name))}
    for name, mesh in produced.items():
        sha = _sha256_file(os.path.join(d, name))
        if sha is not None:
            entries[name] = {"mesh": os.path.realpath(mesh), "sha256": sha}
    _write_manifest(d, entries)


def prune_contours(out_dir, written, *, keep_meshes=()) -> PruneResult:
    """Remove the contour files of ``out_dir`` that extract wrote in an earlier run and this
    run (``written``, the paths :func:`write_contours` returned) no longer produces: a mesh
    whose levels moved, a deleted mesh. Only files the folder's manifest lists are candidates,
    and only while their content is what extract wrote (same SHA-256): files extract did not
    write, or that were changed since, are never touched. Contours of ``keep_meshes`` (meshes
    that failed to read this run) are kept.

    Raises WriteError when the manifest cannot be rewritten.
    """
    d = str(os.fspath(out_dir))
    entries, problem = read_manifest(d)
    result = PruneResult(notes=[problem] if problem else [])
    produced = {os.path.basename(str(p)) for p in written}
    keep = {os.path.realpath(str(m)) for m in keep_meshes}
    for name in sorted(entries):
        if name in produced:
            continue
        path = os.path.join(d, name)
        entry = entries[name]
        if entry["mesh"] in keep:
            result.kept.append((path, "its mesh could not be read this run"))
            continue
        if not os.path.lexists(path):
            del entries[name]
            continue
        if os.path.islink(path) or _sha256_file(path) != entry["sha256"]:
            result.kept.append((path, "changed since extract wrote it; left alone"))
            del entries[name]                          # no longer extract's file
            continue
        try:
            os.remove(path)
        except OSError as exc:
            result.kept.append((path, f"cannot remove it ({exc.strerror or exc})"))
            continue
        del entries[name]
        result.removed.append(path)
    _write_manifest(d, entries)
    return result
