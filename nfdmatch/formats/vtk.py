"""VTK files: legacy ``.vtk``, XML PolyData ``.vtp``, XML UnstructuredGrid ``.vtu``.

Reading uses nfdmatch's own strict parser (:mod:`._vtk_read`), never VTK's C++
readers: those crash or hang the process on malformed files, which cannot be
caught from Python (the reasons and measurements are in :mod:`._vtk_read`).
Writing goes through pyvista, imported inside :func:`write` only, so importing
:mod:`nfdmatch.formats` stays fast.

Reading (:func:`read`): every line cell is a curve. Cells with 3 or more
points (VTK_POLY_LINE, or VTK_LINE / poly-lines in PolyData ``lines``) are
taken as given; 2-point cells are segments chained into loops like OBJ ``l a
b`` elements. PolyData uses its ``lines`` cells; UnstructuredGrid its
VTK_LINE / VTK_POLY_LINE cells. Other cells (vertices, polygons, ...) are
ignored; a file with polygons but no lines is reported as a mesh.

Writing (:func:`write`): float64 points and one closed poly-line cell per
curve, closing point index repeated; PolyData for ``.vtk`` (legacy, binary)
and ``.vtp`` (XML), UnstructuredGrid with VTK_POLY_LINE cells for ``.vtu``.
The file is written to a temporary file made exclusively beside the target
(:func:`._chain.temp_beside`, ``tempfile.mkstemp``) and renamed over it.

Test hook: ``_pyvista()`` imports pyvista as this module does (the off-screen window class
set first); tests write their reference files with it.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import os
import re
import shutil
import tempfile
import warnings
from contextlib import ExitStack

import numpy as np

from .._graph import chain_segments
from ..errors import NoCurvesError, ParseError, UnknownFormatError, WriteError
from ._chain import check_readable, ordered_curves, points_list, publish, read_bytes, temp_beside

if TYPE_CHECKING:
    import os
    from numpy.typing import NDArray
    from ..curve import CurvesLike

__all__ = ["read_points", "write", "KINDS"]

#: format name -> file extension pyvista uses to pick its reader / writer
KINDS = {"vtk": ".vtk", "vtp": ".vtp", "vtu": ".vtu"}

_VTK_POLY_LINE = 4


def _pyvista():
    os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")
    import pyvista

    return pyvista


def _kind(path: str, format: str | None) -> str:
    if format is not None:
        kind = format.lower().lstrip(".")
    else:
        kind = os.path.splitext(path)[1].lower().lstrip(".")
    if kind not in KINDS:
        raise UnknownFormatError(
            f"not a VTK format: {kind or '(no extension)'!r}; expected one of {', '.join(KINDS)}", path=path
        )
    return kind


def _first_alert(message: str) -> str:
    """The readable part of a VTK message (``ERROR: In f.cxx, line n`` / ``vtkX (0x..): what``)."""
    lines = [ln.strip() for ln in str(message).strip().splitlines() if ln.strip()]
    lines = [ln for ln in lines if not re.match(r"^[\w ]*: In .*, line \d+$", ln)]
    text = lines[0] if lines else "unknown VTK error"
    text = re.sub(r"^\w+ \(0x[0-9a-fA-F]+\):\s*", "", text)
    text = re.sub(r"\s*\(0x[0-9a-fA-F]+\)", "", text)
    return text if len(text) <= 240 else text[:237] + "..."


def _silenced(pv, stack: ExitStack):
    """Enter contexts that keep VTK from writing to the console or to logging."""
    stack.enter_context(warnings.catch_warnings())
    warnings.simplefilter("ignore")
    verbosity = getattr(pv, "vtk_verbosity", None)
    if verbosity is not None:
        stack.enter_context(verbosity("off"))
    return stack.enter_context(pv.VtkErrorCatcher(raise_errors=False, send_to_logging=False))


def read_points(path: str | os.PathLike[str], format: str | None = None) -> list[NDArray[np.float64]]:
    """The vertices of every line-cell curve of a VTK file, in cell order.

    Parameters
    ----------
    path : the file.
    format : "vtk", "vtp" or "vtu"; default from the extension.

    Returns
    -------
    list of (n_i, 3) float64 arrays, not yet cleaned.

    Raises
    ------
    ReadError : missing file, a directory, not a regular file, unreadable, too large.
    UnknownFormatError : format / extension not one of vtk, vtp, vtu.
    ParseError : empty, garbage, truncated or inconsistent file ("could not be
        read as VTK: <why>"), a line cell with one point or a point index out
        of range, a branching point among 2-point segments.
    NoCurvesError : no line cells (e.g. only triangles: a mesh), or a dataset
        that is neither PolyData nor UnstructuredGrid.
    """
    p = check_readable(path)
    kind = _kind(p, format)
    data = read_bytes(p)
    if not data.strip():
        raise ParseError("the file is empty", path=p)
    from . import _vtk_read  # xml, lzma, zlib: only when a VTK file is read

    dataset = _vtk_read.parse(data, kind, p)
    del data
    offsets, conn = dataset.line_offsets, dataset.line_connectivity
    n_cells = len(offsets) - 1
    if n_cells == 0:
        if dataset.n_other:
            raise NoCurvesError(
                f"holds {dataset.n_other} polygon/triangle cells but no line cells (polylines): "
                "it is a mesh; extract contours from it first (`nfdmatch extract`: sections or "
                "boundary loops)",
                path=p,
            )
        raise NoCurvesError("holds no line cells (polylines)", path=p)
    points = dataset.points
    n_points = len(points)
    lengths = np.diff(offsets)
    if lengths.min() < 2:
        c = int(np.flatnonzero(lengths < 2)[0])
        raise ParseError(f"line cell {c} has {int(lengths[c])} point(s); a line needs at least 2", path=p)
    outside = (conn < 0) | (conn >= n_points)
    if outside.any():
        k = int(np.flatnonzero(outside)[0])
        c = int(np.searchsorted(offsets, k, side="right")) - 1
        raise ParseError(f"line cell {c} refers to point {int(conn[k])} but the file holds {n_points} points", path=p)
    is_segment = lengths == 2
    seg_cell = np.flatnonzero(is_segment)
    segments = np.column_stack([conn[offsets[seg_cell]], conn[offsets[seg_cell] + 1]])
    polylines = [
        (c, conn[a:b])
        for c, a, b in zip(
            np.flatnonzero(~is_segment).tolist(), offsets[:-1][~is_segment].tolist(), offsets[1:][~is_segment].tolist()
        )
    ]
    seg_cell_list = seg_cell.tolist()
    loops = chain_segments(segments.reshape(-1, 2), path=p, segment_where=lambda s: f"line cell {seg_cell_list[s]}")
    loops = [(seg_cell_list[s], verts) for s, verts in loops]
    return [points[idx] for idx in ordered_curves(polylines, loops)]


def write(path: str | os.PathLike[str], curves: CurvesLike, format: str | None = None) -> None:
    """Write curves as one closed poly-line cell each, float64 points.

    Parameters
    ----------
    path : target file.
    curves : :data:`~nfdmatch.curve.CurvesLike`, one or more (cleaned before writing).
    format : "vtk" (legacy binary PolyData), "vtp" (XML PolyData) or "vtu"
        (XML UnstructuredGrid); default from the extension.

    Raises
    ------
    UnknownFormatError, ParameterError (no curves), CurveError (an invalid
    curve), WriteError (the file cannot be written).
    """
    p = str(path)
    kind = _kind(p, format)
    arrays = points_list(curves, path=p)
    folder = os.path.dirname(os.path.abspath(p))
    if os.path.isdir(p):
        raise WriteError("cannot write: is a directory", path=p)
    if not os.path.isdir(folder):
        raise WriteError("cannot write: the folder does not exist", path=p)
    pts = np.ascontiguousarray(np.concatenate(arrays), dtype=np.float64)
    cells, offset = [], 0
    for a in arrays:
        n = len(a)
        cells.append(np.concatenate([[n + 1], np.arange(offset, offset + n), [offset]]))
        offset += n
    cells = np.concatenate(cells).astype(np.int64)

    pv = _pyvista()
    if kind == "vtu":
        mesh = pv.UnstructuredGrid(cells, np.full(len(arrays), _VTK_POLY_LINE, dtype=np.uint8), pts)
    else:
        mesh = pv.PolyData(pts, lines=cells)
    if mesh.points.dtype != np.float64:  # pragma: no cover - pyvista keeps float64 input
        mesh.points = pts

    private = temp = None
    try:
        temp = temp_beside(p, KINDS[kind])
        target = temp
        if not _utf8(temp):  # VTK takes UTF-8 names only: write elsewhere, then copy
            private = tempfile.mkdtemp(prefix="nfdmatch-")
            target = os.path.join(private, "curves" + KINDS[kind])
        with ExitStack() as stack:
            catcher = _silenced(pv, stack)
            mesh.save(target, binary=True)
        if catcher.error_events:
            raise OSError(_first_alert(str(getattr(catcher.error_events[0], "alert", ""))))
        if private is not None:
            shutil.copyfile(target, temp)
        publish(temp, p)
    except Exception as exc:  # noqa: BLE001
        raise WriteError(f"cannot write the file ({exc})", path=p) from None
    finally:
        if temp is not None and os.path.lexists(temp):
            os.remove(temp)
        if private is not None:
            shutil.rmtree(private, ignore_errors=True)


def _utf8(text: str) -> bool:
    try:
        text.encode("utf-8")
    except UnicodeEncodeError:
        return False
    return True
