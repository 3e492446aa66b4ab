"""Delimited text: one closed curve per file, one vertex per row.

Layout accepted by :func:`read`:

* an optional header line (the first non-blank, non-comment line if any of
  its tokens is not a number);
* 3 columns ``x, y, z`` or 2 columns ``x, y`` (then z = 0); with a header
  naming ``x``, ``y`` (and ``z``) case-insensitively, those columns are used
  among any number of others (which may hold text);
* delimiter comma, semicolon, tab or runs of whitespace, detected from the
  first data row; whitespace around delimiters is allowed;
* ``#`` starts a comment (whole line or trailing); blank lines are ignored;
  UTF-8, a leading byte-order mark is dropped;
* a line holds at most :data:`MAX_LINE_BYTES` (1 MiB) bytes.

:func:`write` writes a header ``x,y,z`` and every coordinate with ``repr``
(shortest string that round-trips exactly), comma separated (tab for ``.tsv``,
space for ``.txt`` / ``.xyz``).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import io
import os
import re
import warnings

import numpy as np

from ..errors import CurveError, ParameterError, ParseError, excerpt
from ._chain import is_number, points_list, read_text_bytes, write_text
from ._stream import MAX_LINE_BYTES, check_line_lengths

if TYPE_CHECKING:
    import os
    from numpy.typing import NDArray
    from ..curve import CurvesLike

__all__ = ["read_points", "write"]

_ANY_DELIMITER = re.compile(r"\s*[,;\t]\s*|\s+")

# MAX_LINE_BYTES (_stream.py, where stdin's copy checks it too): the longest line read


def _unquote(token: str) -> str:
    return token.strip().strip("\"'").strip()


def _read_bulk(data: bytes, path: str) -> np.ndarray | None:
    """The common case parsed in bulk by ``numpy.loadtxt`` straight from the bytes (so peak
    memory stays a small multiple of the file, where the careful parser below holds every
    row as Python strings: 21x the file). ASCII, no quotes, no CR line ends; the header,
    delimiter and columns are decided from the first lines exactly as the careful parser
    does. Returns None whenever anything is off (a bad row, NaN, ...): the careful parser
    then reads the file and reports the problem with its line number."""
    if not data.isascii() or b"\r" in data or b'"' in data or b"'" in data:
        return None
    first_rows: list[str] = []
    pos = 0
    body_start = None
    while len(first_rows) < 2 and pos < len(data):
        end = data.find(b"\n", pos)
        end = len(data) if end < 0 else end
        line = data[pos:end].decode("ascii").split("#", 1)[0].strip()
        if line:
            first_rows.append(line)
            if len(first_rows) == 1:
                body_start = pos
        pos = end + 1
    if len(first_rows) < 2:
        return None
    first, sample = first_rows
    has_header = not all(is_number(t) for t in _ANY_DELIMITER.split(first) if t)
    delim = _delimiter(sample if has_header else first)
    ncol = (
        len(sample.split(delim) if delim else sample.split())
        if has_header
        else len(first.split(delim) if delim else first.split())
    )
    cols = _columns(first, delim, ncol) if has_header else list(range(ncol))
    if cols != list(range(ncol)) or ncol not in (2, 3):
        return None  # other columns (they may hold text): the careful parser
    stream = io.BytesIO(data)
    stream.seek(body_start)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            arr = np.loadtxt(
                stream,
                dtype=np.float64,
                delimiter=delim,
                comments="#",
                skiprows=1 if has_header else 0,
                ndmin=2,
                quotechar=None,
                encoding="ascii",
            )
    except (ValueError, IndexError):
        return None
    if arr.shape[0] == 0 or arr.shape[1] != len(cols) or not np.isfinite(arr).all():
        return None
    return arr


def bulk_points(data: bytes, path: str) -> np.ndarray | None:
    """The (n, 3) float64 vertices :func:`read_points` returns for a file whose bytes are
    ``data``, when its bulk path reads them (plain ASCII numeric rows, see
    :func:`_read_bulk`); None whenever that is not certain (then :func:`read_points`, the
    careful parser, decides and names the problem). ``data`` must be the whole file, of at
    most the size limit; it is checked here as :func:`read_text_bytes` would (no NUL
    bytes; ASCII, so no BOM and valid UTF-8)."""
    if b"\x00" in data:
        return None
    arr = _read_bulk(data, path)
    return None if arr is None else _with_z(arr)


def _with_z(arr: np.ndarray) -> np.ndarray:
    """(n, 3) vertices: the rows of a 2-column file get z = 0."""
    if arr.shape[1] == 2:
        arr = np.column_stack([arr, np.zeros(len(arr))])
    return arr


def _delimiter(sample: str) -> str | None:
    for delim in (";", ",", "\t"):
        if delim in sample:
            return delim
    return None


def _columns(header: str, delim: str | None, ncol: int) -> list[int] | None:
    """Columns x, y(, z) named by the header line, else all ``ncol`` if 2 or 3; None if the
    header does not have ``ncol`` names or names no x, y among other counts."""
    names = _header_names(header, delim, ncol)
    if len(names) != ncol:
        return None
    return _named_columns(names) or (list(range(ncol)) if ncol in (2, 3) else None)


def _header_names(header: str, delim: str | None, ncol: int) -> list[str]:
    """The names of a header line, split as the rows are (by ``delim``, None: whitespace),
    else at any delimiter when that does not give ``ncol`` names."""
    names = [_unquote(t) for t in header.split(delim)]
    if len(names) != ncol:
        names = [_unquote(t) for t in _ANY_DELIMITER.split(header) if t]
    return names


def _named_columns(names: list[str]) -> list[int]:
    """The columns of x, y (and z) among ``names``, case-insensitively; [] without x and y."""
    lower = [n.lower() for n in names]
    if "x" in lower and "y" in lower:
        cols = [lower.index("x"), lower.index("y")]
        if "z" in lower:
            cols.append(lower.index("z"))
        return cols
    return []


def read_points(path: str | os.PathLike[str]) -> list[NDArray[np.float64]]:
    """The vertices of the one curve in a delimited text file.

    Returns
    -------
    list with one (n, 3) float64 array, rows in file order, not yet cleaned
    (duplicates and the closing vertex are removed when the Curve is built).

    Raises
    ------
    ReadError : missing file, a directory, unreadable.
    ParseError : empty, binary, header only, non-numeric cell, ragged rows,
        wrong column count (all with the 1-based line number where relevant).
    CurveError : NaN or Inf in a row (with its line number).
    """
    p = str(path)
    data = read_text_bytes(p)
    check_line_lengths(data, p, MAX_LINE_BYTES)
    arr = _read_bulk(data, p)
    if arr is not None:
        return [_with_z(arr)]
    text = data.decode("utf-8")
    del data
    return [_with_z(_read_careful(text, p))]


def _content_lines(text: str) -> list[tuple[int, str]]:
    """``(line number, text)`` of every line with content: comments cut, stripped, any
    line ends."""
    if "\r" in text:  # Windows (CRLF) and old Mac (CR) line ends
        text = text.replace("\r\n", "\n").replace("\r", "\n")
    content: list[tuple[int, str]] = []
    for lineno, raw in enumerate(text.split("\n"), 1):
        cut = raw.find("#")
        if cut >= 0:
            raw = raw[:cut]
        s = raw.strip()
        if s:
            content.append((lineno, s))
    return content


def _read_careful(text: str, p: str) -> np.ndarray:
    """The careful parser: the (n, 2 or 3) vertices of ``text``, row by row, or a
    ParseError/CurveError naming the first problem and its line."""
    content = _content_lines(text)
    if not content:
        raise ParseError("no data rows (only comments and blank lines)", path=p)
    first_line, first = content[0]
    has_header = not all(is_number(t) for t in _ANY_DELIMITER.split(first) if t)
    data = content[1:] if has_header else content
    if not data:
        raise ParseError("no data rows: the file holds only a header line", path=p, line=first_line)
    delim = _delimiter(data[0][1])
    rows = [s.split(delim) for _, s in data]  # delim None: at runs of whitespace
    ncol = len(rows[0])
    cols = _careful_columns(first_line, first if has_header else None, delim, ncol, data[0][0], p)
    lengths = np.fromiter((len(r) for r in rows), dtype=np.int64, count=len(rows))
    ragged = np.flatnonzero(lengths != ncol)
    if len(ragged):
        k = int(ragged[0])
        raise ParseError(f"expected {ncol} values (as on line {data[0][0]}), got {lengths[k]}", path=p, line=data[k][0])

    table = rows if cols == list(range(ncol)) else [[r[c] for c in cols] for r in rows]
    try:
        arr = np.array(table, dtype=np.float64)
    except ValueError:
        arr = None
    if arr is None or arr.shape != (len(rows), len(cols)):
        _raise_first_bad_cell(p, data, table, delim)
        raise ParseError("could not read the values as numbers", path=p)  # pragma: no cover

    finite = np.isfinite(arr).all(axis=1)
    if not finite.all():
        k = int(np.flatnonzero(~finite)[0])
        raise CurveError(f"value is not finite (NaN or Inf): {excerpt(data[k][1])!r}", path=p, line=data[k][0])
    return arr


def _careful_columns(first_line: int, header: str | None, delim, ncol: int, row_line: int, p: str) -> list[int]:
    """The columns read: x, y(, z) as the header names them, else all (2 or 3 of them);
    a ParseError for a header of another count than the first row (line ``row_line``), or
    a count other than 2 or 3 with no header naming x, y."""
    cols: list[int] = []
    if header is not None:
        names = _header_names(header, delim, ncol)
        if len(names) != ncol:
            raise ParseError(
                f"the header (line {first_line}) names {len(names)} columns but line {row_line} holds {ncol} values",
                path=p,
                line=row_line,
            )
        cols = _named_columns(names)
    if not cols:
        if ncol not in (2, 3):
            raise ParseError(
                f"{ncol} columns; expected 3 (x, y, z) or 2 (x, y), or a header line naming the x, y, z columns",
                path=p,
                line=row_line,
            )
        cols = list(range(ncol))
    return cols


def _raise_first_bad_cell(path, data, table, delim) -> None:
    for (lineno, _), row in zip(data, table):
        for token in row:
            try:
                float(token)
            except ValueError:
                tok = token.strip()
                if not tok:
                    raise ParseError("empty value", path=path, line=lineno) from None
                hint = ""
                if delim == ";" and re.fullmatch(r"[-+]?\d+,\d*([eE][-+]?\d+)?", tok):
                    hint = " (decimal commas are not supported; use a point)"
                raise ParseError(f"not a number: {excerpt(tok)!r}{hint}", path=path, line=lineno) from None


def write(path: str | os.PathLike[str], curves: CurvesLike) -> None:
    """Write exactly one curve: header ``x,y,z`` then one row per vertex.

    Parameters
    ----------
    path : target file; ``.tsv`` is tab separated, ``.txt`` / ``.xyz`` space
        separated, anything else comma separated.
    curves : :data:`~nfdmatch.curve.CurvesLike` holding exactly one curve (cleaned before
        writing: duplicates, repeated closing vertex).

    Raises
    ------
    ParameterError : not exactly one curve.
    CurveError : an invalid curve.
    WriteError : the file cannot be written.
    """
    p = str(path)
    arrays = points_list(curves, path=p)
    if len(arrays) != 1:
        raise ParameterError(
            f"a CSV file holds exactly one curve, got {len(arrays)}; write "
            "one file per curve, or use OBJ / VTP for several curves",
            path=p,
        )
    ext = os.path.splitext(p)[1].lower()
    d = {".tsv": "\t", ".txt": " ", ".xyz": " "}.get(ext, ",")
    out = [d.join("xyz")]
    out.extend(f"{x!r}{d}{y!r}{d}{z!r}" for x, y, z in arrays[0].tolist())
    write_text(p, "\n".join(out) + "\n")
