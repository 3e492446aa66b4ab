"""Closed contours from triangle meshes: planar cross-sections and boundary loops.

The library behind ``nfdmatch extract``: it never prints and never exits.

Modules: :mod:`.load` (finding and loading meshes), :mod:`.sections` (sections and
boundary loops), :mod:`.contours` (the records), :mod:`.naming` (file names, writing),
:mod:`.manifest` (what extract wrote, ``--prune``).
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

from .contours import AXES, DEFAULT_SECTIONS, Contour, ExtractResult, mesh_stem
from .load import find_mesh_files, load_mesh, mesh_extensions
from .manifest import MANIFEST, PruneResult, prune_contours, read_manifest
from .naming import refused_targets, write_contours
from .sections import extract_contours, section_levels

__all__ = [
    "AXES",
    "DEFAULT_SECTIONS",
    "Contour",
    "ExtractResult",
    "PruneResult",
    "MANIFEST",
    "mesh_extensions",
    "find_mesh_files",
    "load_mesh",
    "section_levels",
    "extract_contours",
    "write_contours",
    "refused_targets",
    "prune_contours",
    "read_manifest",
    "mesh_stem",
]
