"""Helpers shared by the format modules.

* :func:`chain_segments` turns 2-point line segments (OBJ ``l a b``, VTK_LINE
  cells) into closed loops.
* :func:`ordered_curves` merges polylines and chained loops in file order.
* :func:`read_bytes` / :func:`read_text` / :func:`check_readable` open a file
  and turn every I/O problem into a :class:`~nfdmatch.errors.ReadError`.
* :func:`make_curves` / :func:`points_list` convert between raw vertex arrays
  and :class:`~nfdmatch.curve.Curve` records with the library's id rules.

Nothing here imports pyvista or trimesh.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence

import numpy as np

from ..curve import Curve, clean_many, clean_points
from ..errors import ParameterError, ParseError, ReadError, WriteError

__all__ = ["chain_segments", "ordered_curves", "read_bytes", "read_text", "check_readable",
           "write_text", "curve_id", "make_curve", "make_curves", "points_list"]


# ---------------------------------------------------------------------------
# segment chaining
# ---------------------------------------------------------------------------

def chain_segments(segments, *, path: str | None = None,
                   vertex_label: Callable[[int], str] | None = None,
                   segment_where: Callable[[int], str] | None = None,
                   ) -> list[tuple[int, np.ndarray]]:
    """Chain undirected 2-point segments into loops (or open paths).

    Parameters
    ----------
    segments : array-like (m, 2) of int, vertex indices (any non-negative base).
        Self-segments ``(a, a)`` and repeated segments (``a b`` twice, in
        either direction) are dropped silently.
    path : file name used in error messages.
    vertex_label : maps a vertex index to how the format names it in messages
        (e.g. 1-based for OBJ). Default: ``str(v)``.
    segment_where : maps a segment's position in ``segments`` to a location
        text for messages (e.g. ``"line 12"``). Optional.

    Returns
    -------
    list of ``(first, vertices)`` in order of ``first``, where ``first`` is the
    position in ``segments`` of the component's earliest segment and
    ``vertices`` is an (k,) int64 array of vertex indices in walking order,
    never repeating the start. Each connected component whose vertices all have
    degree 2 is a closed loop, walked from the earliest segment in that
    segment's direction; a simple path (two degree-1 ends) is returned the same
    way, its closing edge being implicit.

    Raises
    ------
    ParseError : a vertex used by more than two segments (a branching point).
    """
    label = vertex_label or str
    seg = np.asarray(segments, dtype=np.int64).reshape(-1, 2)
    if len(seg) == 0:
        return []
    order = np.arange(len(seg))
    keep = seg[:, 0] != seg[:, 1]
    seg, order = seg[keep], order[keep]
    if len(seg) == 0:
        return []
    # drop repeated undirected segments, keeping the first occurrence
    key = np.sort(seg, axis=1)
    _, first_idx = np.unique(key, axis=0, return_index=True)
    first_idx.sort()
    seg, order = seg[first_idx], order[first_idx]

    verts, inv = np.unique(seg.ravel(), return_inverse=True)
    local = inv.reshape(-1, 2)
    nv = len(verts)
    degree = np.bincount(local.ravel(), minlength=nv)
    if degree.max() > 2:
        v = int(np.flatnonzero(degree > 2)[0])
        users = np.flatnonzero((local == v).any(axis=1))
        where = ""
        if segment_where is not None:
            shown = ", ".join(segment_where(int(order[u])) for u in users[:5])
            more = ", ..." if len(users) > 5 else ""
            where = f" ({shown}{more})"
        raise ParseError(
            f"vertex {label(int(verts[v]))} is shared by {int(degree[v])} line segments{where}: "
            "it is a branching point, but each curve must be a simple loop",
            path=path)

    # adjacency: up to two neighbours per vertex (degree is 1 or 2 here)
    ends = np.concatenate([local[:, 0], local[:, 1]])
    others = np.concatenate([local[:, 1], local[:, 0]])
    by_vertex = np.argsort(ends, kind="stable")
    start = np.searchsorted(ends[by_vertex], np.arange(nv))
    nbr = np.full((nv, 2), -1, dtype=np.int64)
    nbr[:, 0] = others[by_vertex[start]]
    two = degree == 2
    nbr[two, 1] = others[by_vertex[start[two] + 1]]
    nbr_l = nbr.tolist()
    visited = bytearray(nv)
    result: list[tuple[int, np.ndarray]] = []

    def walk(start: int, nxt: int) -> tuple[list[int], bool]:
        """Vertices from ``start`` via ``nxt`` until a dead end or back at ``start``."""
        out = [start]
        visited[start] = 1
        prev, cur = start, nxt
        while cur != -1 and cur != start:
            out.append(cur)
            visited[cur] = 1
            n0, n1 = nbr_l[cur]
            prev, cur = cur, (n1 if n0 == prev else n0)
        return out, cur == start

    # segments are in file order (first_idx sorted): the earliest segment of a
    # component not yet visited starts that component, in its own direction
    for s, (a, b) in enumerate(local.tolist()):
        if visited[a]:
            continue
        forward, closed = walk(a, b)
        if not closed:
            n0, n1 = nbr_l[a]
            other = n1 if n0 == b else n0
            if other != -1:
                backward, _ = walk(a, other)
                forward = backward[:0:-1] + forward
        result.append((int(order[s]), verts[np.array(forward, dtype=np.int64)]))
    return result


def ordered_curves(polylines: Sequence[tuple[int, np.ndarray]],
                   loops: Sequence[tuple[int, np.ndarray]]) -> list[np.ndarray]:
    """Merge ``(position, vertex_indices)`` lists of polylines and chained loops in file order."""
    items = sorted([*polylines, *loops], key=lambda item: item[0])
    return [v for _, v in items]


# ---------------------------------------------------------------------------
# file access
# ---------------------------------------------------------------------------

def check_readable(path) -> str:
    """Return ``str(path)`` if it is a readable regular file, else raise :class:`ReadError`."""
    p = str(path)
    try:
        if os.path.isdir(p):
            raise ReadError("is a directory, not a file", path=p)
        with open(p, "rb") as fh:
            fh.read(1)
    except ReadError:
        raise
    except FileNotFoundError:
        raise ReadError("no such file", path=p) from None
    except PermissionError:
        raise ReadError("permission denied", path=p) from None
    except OSError as exc:
        raise ReadError(f"cannot read the file ({exc.strerror or exc})", path=p) from None
    return p


def read_bytes(path) -> bytes:
    """All bytes of a file; any I/O problem becomes a :class:`ReadError`."""
    p = check_readable(path)
    try:
        with open(p, "rb") as fh:
            return fh.read()
    except OSError as exc:
        raise ReadError(f"cannot read the file ({exc.strerror or exc})", path=p) from None


def read_text(path) -> str:
    """The file decoded as UTF-8 (a leading BOM is dropped), line ends made ``\\n``.

    Raises
    ------
    ReadError : missing, a directory, unreadable.
    ParseError : empty (0 bytes or only whitespace), NUL bytes or invalid UTF-8
        ("not a text file").
    """
    p = str(path)
    data = read_bytes(p)
    if b"\x00" in data:
        raise ParseError("not a text file (it contains NUL bytes); is it a binary file?", path=p)
    try:
        text = data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise ParseError(f"not a text file (invalid UTF-8 at byte {exc.start})", path=p) from None
    if not text.strip():
        raise ParseError("the file is empty", path=p)
    if "\r" in text:  # Windows (CRLF) and old Mac (CR) line ends
        text = text.replace("\r\n", "\n").replace("\r", "\n")
    return text


# ---------------------------------------------------------------------------
# Curve construction
# ---------------------------------------------------------------------------

def curve_id(path: str, index: int, count: int) -> str:
    """``path`` for a single-curve file, else ``path#index``."""
    return path if count == 1 else f"{path}#{index}"


def make_curve(path, points: np.ndarray, index: int, count: int) -> Curve:
    """One :class:`Curve` of a file holding ``count`` curves.

    ``index`` is None for a single-curve file, so that messages and ids agree
    (``path`` rather than ``path#0``).
    """
    p = str(path)
    return Curve(points, id=curve_id(p, index, count), source=p,
                 index=None if count == 1 else index)


def make_curves(path, point_arrays: Sequence[np.ndarray]) -> list[Curve]:
    """Curves with ids ``path`` (one curve) or ``path#i`` (several); see :func:`make_curve`.

    Many curves are cleaned in one vectorized pass (:func:`~nfdmatch.curve.clean_many`)."""
    n = len(point_arrays)
    if n < 8:
        return [make_curve(path, pts, i, n) for i, pts in enumerate(point_arrays)]
    p = str(path)
    cleaned = clean_many(point_arrays, path=p)
    return [Curve.trusted(pts, curve_id(p, i, n), p, i) for i, pts in enumerate(cleaned)]


def points_list(curves, *, path=None) -> list[np.ndarray]:
    """Normalise what the writers accept into a list of cleaned (n, 3) float64 arrays.

    ``curves`` is a sequence of :class:`Curve` or (n, 3)/(n, 2) array-likes; a
    single :class:`Curve` or a single 2-D array is taken as one curve.

    Raises
    ------
    ParameterError : no curves.
    CurveError : a curve that is not a valid closed polyline.
    """
    if isinstance(curves, Curve):
        curves = [curves]
    elif isinstance(curves, np.ndarray) and curves.ndim == 2:
        curves = [curves]
    p = None if path is None else str(path)
    out = []
    for c in curves:
        if isinstance(c, Curve):
            out.append(c.points)
        else:
            out.append(clean_points(c, path=p, curve=len(out)))
    if not out:
        raise ParameterError("no curves to write", path=p)
    return out


def write_if_changed(path: str, produce) -> bool:
    """Write a file whole: ``produce(temp)`` writes it to a hidden temporary file beside
    ``path`` (same extension, so writers that go by it work), which then replaces ``path``
    unless the bytes are the same; the existing file and its mtime are then kept, so
    make-style pipelines see no change. Returns True when ``path`` was (re)written.
    Errors of ``produce`` and OSError propagate; the temporary file never stays."""
    import filecmp

    folder, name = os.path.split(os.path.abspath(path))
    temp = os.path.join(folder, f".{name}.{os.getpid()}.tmp{os.path.splitext(name)[1]}")
    try:
        produce(temp)
        if os.path.isfile(path) and filecmp.cmp(temp, path, shallow=False):
            return False
        os.replace(temp, path)
        return True
    finally:
        if os.path.exists(temp):
            os.remove(temp)


def write_text(path, text: str) -> None:
    """Write ``text`` as UTF-8 with ``\\n`` line ends; I/O problems become :class:`ReadError`.

    (errors.py has no dedicated write error; ReadError is the I/O error class,
    an ``OSError``.)
    """
    p = str(path)
    try:
        with open(p, "w", encoding="utf-8", newline="\n") as fh:
            fh.write(text)
    except IsADirectoryError:
        raise WriteError("cannot write: is a directory", path=p) from None
    except FileNotFoundError:
        raise WriteError("cannot write: the folder does not exist", path=p) from None
    except PermissionError:
        raise WriteError("cannot write: permission denied", path=p) from None
    except OSError as exc:
        raise WriteError(f"cannot write the file ({exc.strerror or exc})", path=p) from None
