"""Finding and loading triangle meshes (trimesh, imported inside the functions)."""

from __future__ import annotations

from typing import TYPE_CHECKING

import json
import logging
import os
from collections.abc import Iterable
from contextlib import contextmanager

import numpy as np

from ..errors import MeshError, NfdError, ReadError, UnknownFormatError
from ..formats import FORMATS
from ..formats._chain import check_readable
from .contours import NOT_MESH_FORMATS

if TYPE_CHECKING:
    import os
    import trimesh


def mesh_extensions() -> list[str]:
    """Extensions of the triangle-mesh formats the installed trimesh reads, e.g. ``['.glb', ..., '.stl']``.

    Point-cloud formats (``.xyz``) are not included. Imports trimesh.
    """
    from trimesh.exchange.load import mesh_formats

    return sorted("." + f for f in mesh_formats() if f not in NOT_MESH_FORMATS)


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
    from ..sources import UniquePaths, walk_folder

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


def load_mesh(path: str | os.PathLike[str]) -> trimesh.Trimesh:
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

    ext = _mesh_extension(p)
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
    except FileNotFoundError as exc:  # trimesh's resolver: no errno, the name it looked for
        if isinstance(exc.__context__, json.JSONDecodeError):  # a .gltf that is not JSON
            raise MeshError(f"not a readable triangle mesh: not JSON ({exc.__context__})", path=p) from None
        missing = exc.filename or (exc.args[-1] if exc.args else "?")
        raise MeshError(f"not a readable triangle mesh: a file it refers to is missing: {missing}", path=p) from None
    except Exception as exc:  # trimesh raises ValueError, KeyError, IndexError, struct.error, ...
        said = str(exc).strip() or type(exc).__name__
        raise MeshError(f"not a readable triangle mesh: {said}", path=p) from None
    if isinstance(parts, str):
        extra = f" ({'; '.join(log[:2])})" if log else ""
        if ext == ".obj" and _has_obj_lines(p):
            extra += " (an OBJ of 'l' polylines is a curve file: index or query it directly)"
        raise MeshError(f"not a triangle mesh: {parts}{extra}", path=p)

    return _merged_mesh(parts, p)


def _mesh_extension(p: str) -> str:
    """The file's extension, lower case, if trimesh reads it as a mesh; else
    UnknownFormatError (with a hint for a curve file's extension)."""
    ext = os.path.splitext(p)[1].lower()
    known = mesh_extensions()
    if ext not in known:
        what = f"unknown mesh file extension {ext!r}" if ext else "no file extension"
        hint = ""
        if ext in {e for exts in FORMATS.values() for e in exts}:
            hint = " (it looks like a curve file: index or query it directly)"
        raise UnknownFormatError(f"{what}{hint}; mesh formats: {', '.join(known)}", path=p)
    return ext


def _merged_mesh(parts, p: str):
    """One ``trimesh.Trimesh`` of the ``(vertices, faces)`` parts: coincident vertices
    merged, faces with a non-finite or repeated vertex dropped; MeshError if none is left."""
    import trimesh

    vertices = np.concatenate([v for v, _ in parts]) if parts else np.zeros((0, 3))
    offsets = np.cumsum([0] + [len(v) for v, _ in parts[:-1]])
    faces = np.concatenate([f + o for (_, f), o in zip(parts, offsets)]) if parts else np.zeros((0, 3), dtype=np.int64)
    if len(faces) == 0:
        raise MeshError("not a triangle mesh: it has no faces", path=p)
    finite = np.isfinite(vertices).all(axis=1)
    usable = finite[faces].all(axis=1)
    faces = faces[usable]
    scale = _merge_scale(vertices[faces])
    try:
        with np.errstate(all="ignore"):
            mesh = trimesh.Trimesh(vertices=vertices * scale, faces=faces, process=True, validate=False)
            if scale != 1.0:  # a power of two: exact both ways
                mesh.vertices = np.asarray(mesh.vertices) / scale
    except Exception as exc:
        raise MeshError(f"not a usable triangle mesh: {exc}", path=p) from None
    f = np.asarray(mesh.faces, dtype=np.int64)
    keep = (f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2])
    if not keep.all():
        mesh.update_faces(keep)
    if len(mesh.faces) == 0:
        raise MeshError(
            "not a usable triangle mesh: every face is degenerate (repeated or non-finite vertices)", path=p
        )
    return mesh


#: trimesh merges coincident vertices rounded to 1e-8 as int64: absolute, and overflowing
#: beyond ~9e10. A mesh whose largest coordinate is outside this range is merged scaled by a
#: power of two (exact): the large ones to just inside it, the small ones to [1, 2).
_MERGE_RANGE = (2.0**-10, 2.0**36)


def unit_power(largest: float) -> float:
    """The power of two that brings ``largest`` (> 0) into [0.5, 1); 1.0 for 0. Scaling
    coordinates by it is exact, so what is computed after it (lengths, areas, moments) is
    the true value scaled, without overflow or underflow."""
    return float(np.ldexp(1.0, -int(np.frexp(largest)[1]))) if largest > 0 else 1.0


def _merge_scale(corners: np.ndarray) -> float:
    """The power of two the vertices (the faces' ``corners``) are merged scaled by: 1.0
    when their largest coordinate is within :data:`_MERGE_RANGE`."""
    largest = float(np.abs(corners).max()) if corners.size else 0.0
    lo, hi = _MERGE_RANGE
    if largest == 0.0 or lo <= largest <= hi:
        return 1.0
    return unit_power(largest) * (2.0**36 if largest > hi else 2.0)


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
            parts.append(
                (
                    np.asarray(g.vertices, dtype=np.float64).reshape(-1, 3),
                    np.asarray(g.faces, dtype=np.int64).reshape(-1, 3),
                )
            )
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
