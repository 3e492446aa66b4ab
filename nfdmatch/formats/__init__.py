"""Reading and writing closed curves: one module per file format, one registry.

Formats (name: extensions)

* ``csv``: ``.csv .tsv .txt .xyz`` -- one curve per file (:mod:`.csv`)
* ``obj``: ``.obj`` -- Wavefront ``l`` polylines, any number (:mod:`.obj`)
* ``vtk``: ``.vtk`` -- legacy VTK, line cells (:mod:`.vtk`)
* ``vtp``: ``.vtp`` -- XML PolyData, line cells
* ``vtu``: ``.vtu`` -- XML UnstructuredGrid, line cells

Every format module has ``read_points(path) -> list[ndarray]`` and ``write(path, curves)
-> None``, registered once here with its extensions (:func:`register`). The format is
chosen from the file extension (case-insensitive) unless ``format=`` names one.

Curve ids: ``str(path)`` for a file holding exactly one curve (then
``index`` is None), ``f"{path}#{i}"`` with ``index=i`` (0-based, file order)
otherwise; ``source`` is always ``str(path)``. A file name that is not valid
UTF-8 (its undecodable bytes are lone surrogates in Python's ``str``, the
``surrogateescape`` rule of ``os.fsdecode``) is written in the id with those
bytes as ``\\xNN`` (byte 0xff -> ``\\xff``), so that ids are valid UTF-8 and
can be printed and stored in HDF5; ``source`` keeps the name that opens the file
(:func:`nfdmatch.errors.escape_name`).

Reading: regular files only (a FIFO, device or socket is refused without being
opened) of at most 1 GiB (``nfdmatch.formats._chain.MAX_FILE_BYTES``, or the
environment variable ``NFDMATCH_MAX_FILE_BYTES``), a CSV line of at most 1 MiB
(``nfdmatch.formats.csv.MAX_LINE_BYTES``; both caps are checked while stdin is read,
:mod:`._stream`); compressed VTK XML data may
inflate to at most ``max(256 MiB, 16 x the file size)``
(``nfdmatch.formats._vtk_read.MAX_INFLATED_BYTES`` / ``MAX_INFLATION_RATIO``).

Importing this package does not import pyvista, VTK or trimesh.
"""

from __future__ import annotations

import os
import re
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from functools import partial

import numpy as np

from ..curve import Curve, CurvesLike
from ..errors import CurveSelectionError, NoCurvesError, UnknownFormatError
from . import csv as _csv
from . import obj as _obj
from . import vtk as _vtk
from ._chain import check_readable, make_curve, make_curves

__all__ = [
    "FORMATS",
    "Format",
    "register",
    "supported_extensions",
    "format_of",
    "split_selector",
    "read_curves",
    "read_curve",
    "write_curves",
]


@dataclass(frozen=True)
class Format:
    """A registered curve format: its ``name``, file ``extensions`` (lower case, with the
    dot), ``read(path) -> list of (n, 3) float64 vertex arrays`` and ``write(path, curves)``."""

    name: str
    extensions: tuple[str, ...]
    read: Callable[[str], list[np.ndarray]]
    write: Callable[..., None]


_REGISTRY: dict[str, Format] = {}
_BY_EXTENSION: dict[str, str] = {}
#: format name -> file extensions (lower case, with the dot), in registration order
FORMATS: dict[str, tuple[str, ...]] = {}


def register(
    name: str, extensions: Iterable[str], read: Callable[[str], list[np.ndarray]], write: Callable[..., None]
) -> Format:
    """Register a curve format; an extension belongs to one format only."""
    exts = tuple(e.lower() for e in extensions)
    taken = [e for e in exts if _BY_EXTENSION.get(e, name) != name]
    if taken:
        raise ValueError(f"extensions already registered: {', '.join(taken)}")
    fmt = Format(name, exts, read, write)
    _REGISTRY[name] = fmt
    FORMATS[name] = exts
    _BY_EXTENSION.update({e: name for e in exts})
    return fmt


register("csv", (".csv", ".tsv", ".txt", ".xyz"), _csv.read_points, _csv.write)
register("obj", (".obj",), _obj.read_points, _obj.write)
for _name in ("vtk", "vtp", "vtu"):
    register(_name, ("." + _name,), partial(_vtk.read_points, format=_name), partial(_vtk.write, format=_name))


_SELECTOR = re.compile(r"-?[0-9]+")


def supported_extensions() -> list[str]:
    """All extensions a format is registered for, e.g. ``['.csv', '.tsv', ..., '.vtu']``."""
    return list(_BY_EXTENSION)


def format_of(path: str | os.PathLike[str], format: str | None = None) -> str:
    """The format name used for ``path``: ``format`` if given, else from the extension.

    ``format`` may be a format name (``"vtp"``) or an extension (``"tsv"``,
    ``".TSV"``), case-insensitive.

    Raises
    ------
    UnknownFormatError : an unknown ``format`` or extension.
    """
    p = os.fspath(path) if not isinstance(path, str) else path
    p = str(p)
    if format is not None:
        name = str(format).strip().lower()
        if name in FORMATS:
            return name
        ext = name if name.startswith(".") else "." + name
        if ext in _BY_EXTENSION:
            return _BY_EXTENSION[ext]
        raise UnknownFormatError(f"unknown format {format!r}; choose one of {', '.join(FORMATS)}", path=p)
    ext = os.path.splitext(p)[1].lower()
    if ext in _BY_EXTENSION:
        return _BY_EXTENSION[ext]
    if ext in _MESH_EXTENSIONS:
        raise UnknownFormatError(
            f"{ext!r} is a triangle mesh, not a curve file: extract its contours first "
            f"(`nfdmatch extract`: planar sections or boundary loops)",
            path=p,
        )
    what = f"unknown file extension {ext!r}" if ext else "no file extension"
    raise UnknownFormatError(
        f"{what}; supported extensions: {', '.join(supported_extensions())}; "
        f"name the format instead (--input-format / --output-format, format= in Python): "
        f"one of {', '.join(FORMATS)}",
        path=p,
    )


#: mesh formats that people hand to the curve readers by mistake
_MESH_EXTENSIONS = {".stl", ".ply", ".off", ".glb", ".gltf", ".3mf", ".dae"}


def split_selector(spec: str | os.PathLike[str]) -> tuple[str, int | None]:
    """Split ``"file.obj#2"`` into ``("file.obj", 2)``; no selector gives ``(spec, None)``.

    Only the part after the last ``#`` can be a selector, and only when it is an
    integer (possibly negative, which :func:`read_curve` rejects) and either the
    path before it exists or the whole ``spec`` does not (so a file really named
    ``a#1`` is still found).
    """
    s = str(os.fspath(spec))
    head, sep, tail = s.rpartition("#")
    if sep and head and _SELECTOR.fullmatch(tail) and (os.path.exists(head) or not os.path.exists(s)):
        return head, int(tail)
    return s, None


def _read_arrays(path: str, format: str | None) -> list[np.ndarray]:
    check_readable(path)
    # only NfdError is a bad file; anything else a reader raises is a bug, and stays one
    arrays = _REGISTRY[format_of(path, format)].read(path)
    if not arrays:  # the readers raise first; kept as a guard
        raise NoCurvesError("no curves in the file", path=path)
    return arrays


def read_curves(path: str | os.PathLike[str], format: str | None = None) -> list[Curve]:
    """All curves of one file.

    Parameters
    ----------
    path : str or PathLike (no ``#`` selector; see :func:`read_curve`).
    format : format name or extension overriding the file's extension.

    Returns
    -------
    list of :class:`Curve`, file order; each ``points`` (n, 3) float64. Ids
    ``str(path)`` (one curve, ``index`` None) or ``f"{path}#{i}"`` (``index`` i).

    Raises
    ------
    ReadError : missing, a directory, unreadable.
    UnknownFormatError : unknown extension / format name.
    ParseError, CurveError, NoCurvesError : bad contents (see the format modules).
    """
    p = str(os.fspath(path))
    return make_curves(p, _read_arrays(p, format))


def read_curve(spec: str | os.PathLike[str], format: str | None = None) -> Curve:
    """One curve: ``spec`` is a file holding one curve, or ``"file#i"`` to pick curve ``i``.

    A single-curve file also accepts ``#0``. The returned curve's id is
    ``str(path)`` for a single-curve file, else ``f"{path}#{i}"``.

    Raises
    ------
    CurveSelectionError : a multi-curve file without selector (the message
        gives the count and how to pick one), or a selector out of range.
    and everything :func:`read_curves` raises.
    """
    path, sel = split_selector(spec)
    arrays = _read_arrays(path, format)
    n = len(arrays)
    if sel is None:
        if n != 1:
            raise CurveSelectionError(
                f"holds {n} curves; pick one by appending #0 ... #{n - 1} to the file name (e.g. {path}#0)", path=path
            )
        return make_curve(path, arrays[0], 0, 1)
    if not 0 <= sel < n:
        valid = "#0" if n == 1 else f"#0 ... #{n - 1}"
        raise CurveSelectionError(
            f"no curve #{sel}: the file holds {n} curve{'s' if n != 1 else ''} ({valid})", path=path
        )
    return make_curve(path, arrays[sel], sel, n)


def write_curves(path: str | os.PathLike[str], curves: CurvesLike, format: str | None = None) -> None:
    """Write curves to one file.

    Parameters
    ----------
    path : target file (overwritten).
    curves : :data:`~nfdmatch.curve.CurvesLike`: one or more curves (cleaned first).
    format : format name or extension overriding the file's extension.

    CSV holds exactly one curve (header ``x,y,z``, ``repr`` precision); OBJ
    writes ``v`` lines then ``l 1 2 ... n 1`` per curve; VTK/VTP/VTU write
    float64 points and one closed poly-line cell per curve. Reading a written
    file back gives the same vertices exactly.

    Raises
    ------
    UnknownFormatError, ParameterError (no curves, or several for CSV),
    CurveError (an invalid curve), WriteError (cannot write).
    """
    p = str(os.fspath(path))
    _REGISTRY[format_of(p, format)].write(p, curves)
