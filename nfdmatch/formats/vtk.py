"""VTK files through pyvista: legacy ``.vtk``, XML PolyData ``.vtp``, XML UnstructuredGrid ``.vtu``.

pyvista (and so VTK) is imported inside the functions only, so importing
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
The file is written next to the target under a temporary name and renamed.
"""

from __future__ import annotations

import os
import re
import warnings
from contextlib import ExitStack

import numpy as np

from ..curve import Curve
from ..errors import NfdError, NoCurvesError, ParseError, ReadError, UnknownFormatError, WriteError
from ._chain import chain_segments, check_readable, make_curves, ordered_curves, points_list

__all__ = ["read", "read_points", "write", "KINDS"]

#: format name -> file extension pyvista uses to pick its reader / writer
KINDS = {"vtk": ".vtk", "vtp": ".vtp", "vtu": ".vtu"}

_VTK_VERTEX, _VTK_POLY_VERTEX, _VTK_LINE, _VTK_POLY_LINE = 1, 2, 3, 4


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
        raise UnknownFormatError(f"not a VTK format: {kind or '(no extension)'!r}; expected one "
                                 f"of {', '.join(KINDS)}", path=path)
    return kind


# pipeline follow-up errors that say nothing about what is wrong with the file
_BOILERPLATE = ("No update piece number", "did not create output for port",
                "returned failure for request", "Error parsing input file")


_FAILURE = re.compile(r"error|premature|unexpected|unrecognized|cannot|can't|could not|"
                      r"failed|invalid|truncat|unsupported", re.IGNORECASE)


# metadata that VTK fails to parse without affecting the data: the XML writer
# stores an L2-norm range of "inf" for points whose norm overflows (|p| > 1e308)
_HARMLESS = re.compile(r"InformationKey")


def _first_alert(message: str) -> str:
    """The readable part of a VTK message (``ERROR: In f.cxx, line n`` / ``vtkX (0x..): what``)."""
    lines = [ln.strip() for ln in str(message).strip().splitlines() if ln.strip()]
    lines = [ln for ln in lines if not re.match(r"^[\w ]*: In .*, line \d+$", ln)]
    text = lines[0] if lines else "unknown VTK error"
    text = re.sub(r"^\w+ \(0x[0-9a-fA-F]+\):\s*", "", text)
    text = re.sub(r"\s*\(0x[0-9a-fA-F]+\)", "", text)
    return text if len(text) <= 240 else text[:237] + "..."


class _Quiet:
    """Collect VTK error events of the given objects instead of printing them."""

    def __init__(self):
        self.messages: list[str] = []

    def __call__(self, _obj, _event, message=None):
        self.messages.append(str(message))

    CallDataType = "string0"

    def watch(self, obj) -> None:
        if obj is None:
            return
        obj.AddObserver("ErrorEvent", self)
        obj.AddObserver("WarningEvent", self)


def _silenced(pv, stack: ExitStack):
    """Enter contexts that keep VTK from writing to the console or to logging."""
    stack.enter_context(warnings.catch_warnings())
    warnings.simplefilter("ignore")
    verbosity = getattr(pv, "vtk_verbosity", None)
    if verbosity is not None:
        stack.enter_context(verbosity("off"))
    return stack.enter_context(pv.VtkErrorCatcher(raise_errors=False, send_to_logging=False))


def _load(path: str, kind: str):
    pv = _pyvista()
    quiet = _Quiet()
    catcher = None
    mesh = None
    failure = None
    try:
        with ExitStack() as stack:
            catcher = _silenced(pv, stack)
            reader = pv.get_reader(path, force_ext=KINDS[kind])
            alg = getattr(reader, "reader", None)
            if alg is not None:
                quiet.watch(alg)
                quiet.watch(alg.GetExecutive() if hasattr(alg, "GetExecutive") else None)
            mesh = reader.read()
    except NfdError:
        raise
    except Exception as exc:  # noqa: BLE001 - anything VTK/pyvista raises is a parse failure
        failure = f"{type(exc).__name__}: {exc}"
    events = [*catcher.error_events, *catcher.warning_events] if catcher else []
    errors = [str(getattr(e, "alert", e)) for e in events] + quiet.messages
    # warnings are failures only when they report a read error (a truncated
    # legacy file gives just the warning "Error reading binary data!")
    errors = [e for e in errors if _FAILURE.search(e) and not _HARMLESS.search(e)]
    if errors:
        useful = [e for e in errors if not any(b in e for b in _BOILERPLATE)] or errors
        raise ParseError(f"could not be read as VTK: {_first_alert(useful[0])}", path=path)
    if failure is not None:
        raise ParseError(f"could not be read as VTK: {_first_alert(failure)}", path=path)
    if mesh is None:
        raise ParseError("could not be read as VTK: the reader returned nothing", path=path)
    return pv, mesh


def _line_cells(pv, mesh, path: str) -> tuple[list[np.ndarray], int]:
    """Point-index arrays of the line cells, and the number of polygon-like cells."""
    if isinstance(mesh, pv.PolyData):
        n_other = int(mesh.GetNumberOfPolys()) + int(mesh.GetNumberOfStrips())
        if mesh.n_lines == 0:
            return [], n_other
        if hasattr(mesh, "line_offsets"):
            offsets = np.asarray(mesh.line_offsets, dtype=np.int64)
            conn = np.asarray(mesh.line_connectivity, dtype=np.int64)
            cells = [conn[a:b] for a, b in zip(offsets[:-1].tolist(), offsets[1:].tolist())]
        else:  # older pyvista: flat [n, i0, ..., n, ...]
            flat = np.asarray(mesh.lines, dtype=np.int64)
            cells, k = [], 0
            while k < len(flat):
                n = int(flat[k])
                cells.append(flat[k + 1:k + 1 + n])
                k += 1 + n
        return cells, n_other
    if isinstance(mesh, pv.UnstructuredGrid):
        types = np.asarray(mesh.celltypes)
        offsets = np.asarray(mesh.cell_offsets if hasattr(mesh, "cell_offsets") else mesh.offset,
                             dtype=np.int64)
        conn = np.asarray(mesh.cell_connectivity, dtype=np.int64)
        is_line = (types == _VTK_LINE) | (types == _VTK_POLY_LINE)
        n_other = int(np.count_nonzero(~is_line & (types != _VTK_VERTEX)
                                       & (types != _VTK_POLY_VERTEX) & (types != 0)))
        cells = [conn[offsets[c]:offsets[c + 1]] for c in np.flatnonzero(is_line).tolist()]
        return cells, n_other
    raise NoCurvesError(f"holds a dataset of type {type(mesh).__name__}; curves are read from "
                        "the line cells of PolyData or UnstructuredGrid only", path=path)


def read_points(path, format: str | None = None) -> list[np.ndarray]:
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
    ReadError : missing file, a directory, unreadable.
    UnknownFormatError : format / extension not one of vtk, vtp, vtu.
    ParseError : empty, garbage or truncated file ("could not be read as VTK"),
        a line cell with one point or a point index out of range, a branching
        point among 2-point segments.
    NoCurvesError : no line cells (e.g. only triangles: a mesh).
    """
    p = check_readable(path)
    kind = _kind(p, format)
    if os.path.getsize(p) == 0:
        raise ParseError("the file is empty", path=p)
    pv, mesh = _load(p, kind)
    cells, n_other = _line_cells(pv, mesh, p)
    if not cells:
        if n_other:
            raise NoCurvesError(
                f"holds {n_other} polygon/triangle cells but no line cells (polylines): it is a "
                "mesh; extract contours from it first (`nfdmatch extract`: sections or boundary loops)", path=p)
        raise NoCurvesError("holds no line cells (polylines)", path=p)
    points = np.asarray(mesh.points, dtype=np.float64).reshape(-1, 3)
    n_points = len(points)
    polylines, segments, seg_cell = [], [], []
    for c, ids in enumerate(cells):
        if len(ids) < 2:
            raise ParseError(f"line cell {c} has {len(ids)} point(s); a line needs at least 2",
                             path=p)
        if ids.min() < 0 or ids.max() >= n_points:
            raise ParseError(f"line cell {c} refers to point {int(ids.max())} but the file "
                             f"holds {n_points} points", path=p)
        if len(ids) == 2:
            segments.append(ids)
            seg_cell.append(c)
        else:
            polylines.append((c, ids))
    loops = chain_segments(np.array(segments, dtype=np.int64).reshape(-1, 2), path=p,
                           segment_where=lambda s: f"line cell {seg_cell[s]}")
    loops = [(seg_cell[s], verts) for s, verts in loops]
    return [points[idx] for idx in ordered_curves(polylines, loops)]


def read(path, format: str | None = None) -> list[Curve]:
    """Every curve of a VTK file as :class:`Curve` records.

    Ids: ``str(path)`` for a single-curve file, else ``f"{path}#{i}"`` (0-based,
    cell order); ``source=str(path)``, ``index`` = i (None for one curve).
    See :func:`read_points` for the parameters and errors.
    """
    return make_curves(path, read_points(path, format))


def write(path, curves, format: str | None = None) -> None:
    """Write curves as one closed poly-line cell each, float64 points.

    Parameters
    ----------
    path : target file.
    curves : list of :class:`Curve` or (n, 3) / (n, 2) arrays (a bare Curve or
        2-D array is one curve). Vertices are cleaned before writing.
    format : "vtk" (legacy binary PolyData), "vtp" (XML PolyData) or "vtu"
        (XML UnstructuredGrid); default from the extension.

    Raises
    ------
    UnknownFormatError, ParameterError (no curves), CurveError (an invalid
    curve), ReadError (the file cannot be written).
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
        mesh = pv.UnstructuredGrid(cells, np.full(len(arrays), _VTK_POLY_LINE, dtype=np.uint8),
                                   pts)
    else:
        mesh = pv.PolyData(pts, lines=cells)
    if mesh.points.dtype != np.float64:  # pragma: no cover - pyvista keeps float64 input
        mesh.points = pts

    tmp = os.path.join(folder, f".{os.path.basename(p)}.{os.getpid()}.tmp{KINDS[kind]}")
    try:
        with ExitStack() as stack:
            catcher = _silenced(pv, stack)
            mesh.save(tmp, binary=True)
        if catcher.error_events:
            raise OSError(_first_alert(str(getattr(catcher.error_events[0], "alert", ""))))
        os.replace(tmp, p)
    except Exception as exc:  # noqa: BLE001
        try:
            os.remove(tmp)
        except OSError:
            pass
        raise WriteError(f"cannot write the file ({exc})", path=p) from None
