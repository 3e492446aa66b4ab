"""Curves held in memory as the sources of a build (:func:`nfdmatch.index.build_index` of
curves, :meth:`nfdmatch.MemoryIndex.save`): written first, in order, into one OBJ file that
the index then records as its source, so that row i is curve i and the file is there for
``show``, ``report`` and later builds."""

from __future__ import annotations

import os
from typing import Any

import numpy as np

from ..curve import Curve
from ..errors import InputError, ParameterError
from ..formats.obj import write as write_obj

__all__ = ["memory_sources"]


def memory_sources(sources: Any, index_path: str, curves_file: str | os.PathLike[str] | None) -> Any:
    """``sources``, or for curves in memory the file they were written to."""
    if _in_memory(sources):
        return [_write_curves(sources, index_path, curves_file)]
    if curves_file is not None:
        raise ParameterError("curves_file is where curves in memory are written: give curves")
    return sources


def _in_memory(sources: Any) -> bool:
    """Whether ``sources`` are curves (a Curve, an array, or a sequence of them), not paths."""
    if isinstance(sources, (Curve, np.ndarray)):
        return True
    if isinstance(sources, (str, bytes, os.PathLike)) or sources is None:
        return False
    items = list(sources)
    kinds = {isinstance(s, (Curve, np.ndarray, list, tuple)) for s in items}
    if kinds == {True, False}:
        raise ParameterError("sources are either paths or curves in memory, not both")
    return kinds == {True}


def _write_curves(curves: Any, index_path: str, curves_file: str | os.PathLike[str] | None) -> str:
    """The file holding curves given in memory (written whole, atomically; identical bytes
    leave it as it was, so that a second build of the same curves recomputes nothing)."""
    if curves_file is None:
        curves_file = os.path.splitext(index_path)[0] + ".curves.obj"
    path = os.fspath(curves_file)
    if isinstance(curves, (Curve, np.ndarray)):
        curves = [curves]
    points = [c.points if isinstance(c, Curve) else np.asarray(c, dtype=np.float64) for c in curves]
    if not points:
        raise InputError("no curves to index")
    write_obj(path, points)
    return str(path)
