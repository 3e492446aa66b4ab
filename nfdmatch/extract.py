"""``nfdmatch.extract``: the mesh -> contour functions, kept under this name for existing
code; they live in :mod:`nfdmatch.mesh`."""

from __future__ import annotations

from .mesh import (
    AXES,
    DEFAULT_SECTIONS,
    MANIFEST,
    Contour,
    ExtractResult,
    PruneResult,
    extract_contours,
    find_mesh_files,
    load_mesh,
    mesh_extensions,
    mesh_stem,
    prune_contours,
    read_manifest,
    section_levels,
    write_contours,
)

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
    "prune_contours",
    "read_manifest",
    "mesh_stem",
]
