"""``nfdmatch.extract``: the mesh -> contour functions, kept under this name for existing
code; they live in :mod:`nfdmatch.mesh` (the same names)."""

from __future__ import annotations

from . import mesh
from .mesh import *  # noqa: F403  (the same public names, listed once in nfdmatch.mesh)

__all__ = list(mesh.__all__)
