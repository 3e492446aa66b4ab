"""Helpers shared by the format modules.

* :func:`is_number`, the text readers' test for a numeric field (segments are chained
  into loops by :func:`nfdmatch._graph.chain_segments`).
* :func:`ordered_curves` merges polylines and chained loops in file order.
* :func:`read_bytes` / :func:`read_text` / :func:`check_readable` open a file
  and turn every I/O problem into a :class:`~nfdmatch.errors.ReadError`; they
  read regular files only (never a FIFO, device or socket) of at most
  :data:`MAX_FILE_BYTES` (1 GiB; environment variable ``NFDMATCH_MAX_FILE_BYTES``).
* :func:`make_curves` / :func:`points_list` convert between raw vertex arrays
  and :class:`~nfdmatch.curve.Curve` records with the library's id rules.

Nothing here imports pyvista or trimesh.

An internal module: tests import its helpers directly; ``_os_open`` is a test hook (a
module-level name, so tests can make opening a file fail).
"""

from __future__ import annotations

import os
import stat
from collections.abc import Sequence

import numpy as np

from .._io import publish, temp_beside, write_file  # noqa: F401  (re-exported)
from ..curve import Curve, CurvesLike, clean_many, clean_points
from ..errors import ParameterError, ParseError, ReadError, WriteError, excerpt, os_error_message

__all__ = [
    "is_number",
    "ordered_curves",
    "read_bytes",
    "read_text",
    "check_readable",
    "write_text",
    "curve_id",
    "make_curve",
    "make_curves",
    "points_list",
]


# ---------------------------------------------------------------------------
# fields and segments
# ---------------------------------------------------------------------------


def is_number(token: str) -> bool:
    """True when ``float(token)`` parses (the text readers' test for a numeric field)."""
    try:
        float(token)
    except ValueError:
        return False
    return True


def ordered_curves(
    polylines: Sequence[tuple[int, np.ndarray]], loops: Sequence[tuple[int, np.ndarray]]
) -> list[np.ndarray]:
    """Merge ``(position, vertex_indices)`` lists of polylines and chained loops in file order."""
    items = sorted([*polylines, *loops], key=lambda item: item[0])
    return [v for _, v in items]


# ---------------------------------------------------------------------------
# file access
# ---------------------------------------------------------------------------

#: Largest file the readers read, in bytes (1 GiB). Set this module attribute, or the
#: environment variable ``NFDMATCH_MAX_FILE_BYTES`` (read at each call, so it reaches
#: the CLI and worker processes), to allow more.
MAX_FILE_BYTES = 1 << 30


def max_file_bytes() -> int:
    """The read size cap in force: ``NFDMATCH_MAX_FILE_BYTES`` if set, else :data:`MAX_FILE_BYTES`."""
    value = os.environ.get("NFDMATCH_MAX_FILE_BYTES", "").strip()
    if value:
        try:
            limit = int(value)
        except ValueError:
            raise ParameterError(f"NFDMATCH_MAX_FILE_BYTES must be a number of bytes, not {excerpt(value)!r}") from None
        if limit > 0:
            return limit
    return MAX_FILE_BYTES


_os_open = os.open  # a module name, so tests can make opening fail


def file_kind(mode: int) -> str:
    """What a file of ``mode`` (not a regular file) is, for messages: "a FIFO (named pipe)"."""
    for test, name in (
        (stat.S_ISFIFO, "a FIFO (named pipe)"),
        (stat.S_ISSOCK, "a socket"),
        (stat.S_ISCHR, "a character device"),
        (stat.S_ISBLK, "a block device"),
        (stat.S_ISDIR, "a directory"),
    ):
        if test(mode):
            return name
    return "not a regular file"


def _refuse_irregular(p: str, mode: int) -> None:
    if stat.S_ISDIR(mode):
        raise ReadError("is a directory, not a file", path=p)
    if not stat.S_ISREG(mode):
        raise ReadError(f"is {file_kind(mode)}, not a regular file; only regular files are read", path=p)


def _io_error(p: str, exc: OSError) -> ReadError:
    known = {FileNotFoundError: "no such file", PermissionError: "permission denied"}
    return ReadError(os_error_message(exc, known, "cannot read the file"), path=p)


def _open_regular(p: str) -> tuple[int, int]:
    """Open a regular file for reading: ``(fd, size)``. FIFOs, devices, sockets and
    directories are refused from ``stat`` before any ``open`` (opening a FIFO blocks,
    reading ``/dev/zero`` never ends) and again from ``fstat`` of what was opened (the
    name may have been replaced in between; ``O_NONBLOCK`` keeps that open from blocking)."""
    try:
        _refuse_irregular(p, os.stat(p).st_mode)
        fd = _os_open(p, os.O_RDONLY | os.O_NONBLOCK | os.O_NOCTTY | getattr(os, "O_CLOEXEC", 0))
    except ReadError:
        raise
    except OSError as exc:
        raise _io_error(p, exc) from None
    try:
        info = os.fstat(fd)
        _refuse_irregular(p, info.st_mode)
        limit = max_file_bytes()
        if info.st_size > limit:
            raise ReadError(
                f"is {info.st_size} bytes, more than the limit of {limit} bytes "
                "(set the environment variable NFDMATCH_MAX_FILE_BYTES to allow more)",
                path=p,
            )
    except BaseException:
        os.close(fd)
        raise
    return fd, info.st_size


def check_readable(path) -> str:
    """Return ``str(path)`` if it is a readable regular file within the size cap, else raise
    :class:`ReadError` (missing, a directory, a FIFO / device / socket, no permission, too
    large). Nothing is read."""
    p = str(path)
    fd, _ = _open_regular(p)
    os.close(fd)
    return p


def read_bytes(path) -> bytes:
    """All bytes of a regular file of at most :func:`max_file_bytes` bytes; any I/O problem
    becomes a :class:`ReadError` (see :func:`check_readable`)."""
    p = str(path)
    fd, size = _open_regular(p)
    limit = max_file_bytes()
    try:
        with os.fdopen(fd, "rb") as fh:
            # read(n) allocates n bytes up front: ask for the size fstat gave, then the rest
            # in small pieces should the file have grown since
            data = fh.read(size + 1)
            if len(data) > size:
                pieces, total = [data], len(data)
                while piece := fh.read(1 << 20):
                    total += len(piece)
                    if total > limit:
                        raise ReadError(
                            f"is more than the limit of {limit} bytes (set the "
                            "environment variable NFDMATCH_MAX_FILE_BYTES to allow "
                            "more)",
                            path=p,
                        )
                    pieces.append(piece)
                data = b"".join(pieces)
    except OSError as exc:
        if isinstance(exc, ReadError):
            raise
        raise _io_error(p, exc) from None
    return data


def read_text_bytes(path) -> bytes:
    """The file's bytes, checked to be UTF-8 text: a leading BOM dropped; line ends left as
    they are.

    Raises
    ------
    ReadError : see :func:`read_bytes`.
    ParseError : empty (0 bytes or only whitespace), NUL bytes or invalid UTF-8
        ("not a text file").
    """
    p = str(path)
    data = read_bytes(p)
    if b"\x00" in data:
        raise ParseError("not a text file (it contains NUL bytes); is it a binary file?", path=p)
    if data.startswith(b"\xef\xbb\xbf"):
        data = data[3:]
    if not data.isascii():
        try:
            data.decode("utf-8")
        except UnicodeDecodeError as exc:
            raise ParseError(f"not a text file (invalid UTF-8 at byte {exc.start})", path=p) from None
    if not data.strip():
        raise ParseError("the file is empty", path=p)
    return data


def read_text(path) -> str:
    """The file decoded as UTF-8 (a leading BOM is dropped), line ends made ``\\n``.

    Raises
    ------
    ReadError : see :func:`read_bytes`.
    ParseError : empty (0 bytes or only whitespace), NUL bytes or invalid UTF-8
        ("not a text file").
    """
    text = read_text_bytes(path).decode("utf-8")
    if not text.strip():
        raise ParseError("the file is empty", path=str(path))
    if "\r" in text:  # Windows (CRLF) and old Mac (CR) line ends
        text = text.replace("\r\n", "\n").replace("\r", "\n")
    return text


# ---------------------------------------------------------------------------
# Curve construction
# ---------------------------------------------------------------------------


def curve_id(path: str, index: int, count: int) -> str:
    """``path`` for a single-curve file, else ``path#index``; the name as an id
    (:func:`nfdmatch.names.encode_name`: one-to-one, undecodable bytes as ``\\xNN``, a
    backslash doubled)."""
    from ..names import encode_name

    name = encode_name(path)
    return name if count == 1 else f"{name}#{index}"


def make_curve(path, points: np.ndarray, index: int, count: int) -> Curve:
    """One :class:`Curve` of a file holding ``count`` curves.

    ``index`` is None for a single-curve file, so that messages and ids agree
    (``path`` rather than ``path#0``).
    """
    p = str(path)
    return Curve(points, id=curve_id(p, index, count), source=p, index=None if count == 1 else index)


def make_curves(path, point_arrays: Sequence[np.ndarray]) -> list[Curve]:
    """Curves with ids ``path`` (one curve) or ``path#i`` (several); see :func:`make_curve`.

    Many curves are cleaned in one vectorized pass (:func:`~nfdmatch.curve.clean_many`)."""
    n = len(point_arrays)
    if n < 8:
        return [make_curve(path, pts, i, n) for i, pts in enumerate(point_arrays)]
    p = str(path)
    cleaned = clean_many(point_arrays, path=p)
    return [Curve.trusted(pts, curve_id(p, i, n), p, i) for i, pts in enumerate(cleaned)]


def points_list(curves: CurvesLike, *, path=None) -> list[np.ndarray]:
    """Normalise what the writers accept into a list of cleaned (n, 3) float64 arrays.

    ``curves``: :data:`~nfdmatch.curve.CurvesLike` (a single :class:`Curve` or 2-D array is
    one curve).

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


# one atomic writer for every file the tool writes (nfdmatch/_io.py); the old names stay
# importable from here: ``write_if_changed`` is :func:`nfdmatch._io.write_file` (an identical
# file is kept, with a fresh mtime)
write_if_changed = write_file


def write_text(path, text: str) -> None:
    """Write ``text`` as UTF-8 with ``\\n`` line ends; I/O problems become
    :class:`~nfdmatch.errors.WriteError` (an ``OSError``) naming the file."""
    p = str(path)
    try:
        with open(p, "w", encoding="utf-8", newline="\n") as fh:
            fh.write(text)
    except OSError as exc:
        known = {
            IsADirectoryError: "cannot write: is a directory",
            FileNotFoundError: "cannot write: the folder does not exist",
            PermissionError: "cannot write: permission denied",
        }
        raise WriteError(os_error_message(exc, known, "cannot write the file"), path=p) from None
