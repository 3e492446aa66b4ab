"""The records of an extraction: a :class:`Contour` (one closed loop of a mesh, with
where it came from) and an :class:`ExtractResult` (one mesh's contours and notes)."""

from __future__ import annotations

from typing import TYPE_CHECKING

import os
import re
from dataclasses import dataclass, field

import numpy as np

if TYPE_CHECKING:
    import os


#: the axes a section can be perpendicular to
AXES = ("x", "y", "z")
#: default number of section levels
DEFAULT_SECTIONS = 10

_KINDS = ("section", "boundary")
UNSAFE = re.compile(r"[^A-Za-z0-9._-]+")
# trimesh formats that are not triangle meshes (point clouds) or not extensions
NOT_MESH_FORMATS = {"xyz", "stl_ascii"}


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
        level = f"{self.level + 0.0:.6g}"  # + 0.0: no "-0"
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


def mesh_stem(path: str | os.PathLike[str]) -> str:
    """The mesh file name without extension, made filesystem- and selector-safe.

    Runs of characters other than ``A-Z a-z 0-9 . _ -`` become ``_``; a name
    left empty or starting with ``.`` gets the prefix ``mesh``.
    """
    base = os.path.splitext(os.path.basename(str(os.fspath(path))))[0]
    stem = UNSAFE.sub("_", base)
    if not stem or stem.startswith("."):
        stem = "mesh" + stem
    return stem
