"""A strict reader of the VTK file formats nfdmatch reads curves from, in numpy.

Why not VTK's own readers: their C++ code trusts declared counts and offsets, so
a malformed file can crash the process (segfault, heap corruption) or spin for
ever (``benchmarks/fuzz_formats.py --reader pyvista``: 52 crashes and 6 hangs in
1,988 mutants of valid VTK/VTP/VTU files; this reader: none in 20,000), and that
cannot be caught from Python. Running them in a child process with
time and memory limits contains that but costs a process start and a pyvista
import per file. Measured on 5,000-curve files (``benchmarks/bench_vtk_read.py``,
median seconds, here / fresh child per file / warm pre-started child / VTK in
process, unprotected): zlib VTP 20 MB 0.47 / 1.22 / 0.43 / 0.29; legacy binary
.vtk 21 MB 0.02 / 0.78 / 0.06 / 0.01; appended raw VTP 15 MB 0.11 / 0.73 / 0.14 /
0.10; ASCII VTP 45 MB 1.49 / 1.66 / 1.01 / 1.01; legacy ASCII 31 MB 0.70 / 1.72 /
1.00 / 0.65. Own parsing beats a child per file everywhere (35x on binary legacy),
is level with a warm child except on ASCII XML (1.5x slower), needs no worker pool
to restart after every crash, and gives a reason for every refusal. So this module
parses the files itself; pyvista stays for writing and pictures.

Supported (everything pyvista/VTK writes for PolyData and UnstructuredGrid):

* legacy ``.vtk``, ASCII or BINARY (big-endian), ``DATASET POLYDATA`` (VERTICES,
  LINES, POLYGONS, TRIANGLE_STRIPS) or ``UNSTRUCTURED_GRID`` (CELLS, CELL_TYPES),
  cells in the classic ``n i0 i1 ...`` layout (file version < 5) or the
  OFFSETS / CONNECTIVITY layout (version 5.1); ``METADATA`` blocks are skipped,
  everything from ``POINT_DATA`` / ``CELL_DATA`` / ``FIELD`` on is ignored;
* XML ``.vtp`` (PolyData) and ``.vtu`` (UnstructuredGrid), any number of pieces,
  data arrays in ``ascii``, ``binary`` (base64) or ``appended`` format (raw or
  base64 encoded), header type UInt32 or UInt64, little- or big-endian, without
  compression or with the zlib, LZMA or LZ4 compressor (block header
  ``[n_blocks, block_size, last_block_size, compressed sizes...]``).

Every declared count, size and offset is checked against the bytes actually in
the file *before* anything is allocated from it, and inflated (decompressed)
data may not exceed :func:`inflated_cap` bytes. Every problem is a
:class:`~nfdmatch.errors.ParseError` saying what is wrong (or
:class:`~nfdmatch.errors.NoCurvesError` for another kind of dataset).

The result of :func:`parse` is a :class:`Dataset`: points (n, 3) float64 and the
line cells as CSR arrays (offsets (c + 1,) int64 starting at 0, connectivity
(m,) int64), plus the number of polygon-like cells.

An internal module, tested directly (``tests/test_vtk_reader.py``, also its ``_lz4_block``
decoder) against what pyvista/VTK reads.
"""

from __future__ import annotations

import binascii
import lzma
import re
import warnings
import zlib
import xml.etree.ElementTree as ET
from dataclasses import dataclass

import numpy as np

from ..errors import NoCurvesError, ParseError, excerpt

__all__ = ["Dataset", "parse", "MAX_INFLATED_BYTES", "MAX_INFLATION_RATIO", "inflated_cap"]

#: Decompressed data of one file may reach ``max(MAX_INFLATED_BYTES,
#: MAX_INFLATION_RATIO * file size)`` bytes; past that the file is refused (so a
#: 544 KB file cannot inflate to 400 MB). Curve data compresses by far less than
#: 16:1 (float coordinates hardly at all). Change the module attributes to allow more.
MAX_INFLATED_BYTES = 256 * 2**20
MAX_INFLATION_RATIO = 16

#: a legacy file has a handful of sections (POINTS, LINES, METADATA, ...) and an XML
#: file a few pieces; far more is garbage that would only cost time
MAX_SECTIONS = 10_000
MAX_PIECES = 10_000
MAX_BASE64_PIECES = 10_000

_CHUNK_TOKENS = 1 << 20  # ASCII numbers are converted this many at a time

_VTK_VERTEX, _VTK_POLY_VERTEX, _VTK_LINE, _VTK_POLY_LINE = 1, 2, 3, 4


def inflated_cap(file_size: int) -> int:
    """Most bytes of decompressed data accepted from a file of ``file_size`` bytes."""
    return max(MAX_INFLATED_BYTES, MAX_INFLATION_RATIO * int(file_size))


@dataclass
class Dataset:
    """What the curve reader needs of a VTK dataset.

    points : (n, 3) float64. line_offsets : (c + 1,) int64, 0 first, non-decreasing,
    last = len(line_connectivity). line_connectivity : (m,) int64, not yet range
    checked. n_other : number of polygon / triangle / strip / 3-D cells.
    """

    points: np.ndarray
    line_offsets: np.ndarray
    line_connectivity: np.ndarray
    n_other: int


class _Bad(Exception):
    """Internal: a problem with the file; turned into a ParseError with the path."""


def parse(data: bytes, kind: str, path: str) -> Dataset:
    """Parse the bytes of a ``kind`` ("vtk", "vtp" or "vtu") file named ``path``.

    Raises
    ------
    ParseError : anything malformed, truncated or beyond the limits.
    NoCurvesError : a valid file of another dataset type (image data, ...).
    """
    try:
        if kind == "vtk":
            return _Legacy(data).parse(path)
        return _parse_xml(data, kind, path)
    except _Bad as exc:
        raise ParseError(f"could not be read as VTK: {exc}", path=path) from None
    except RecursionError:
        raise ParseError("could not be read as VTK: XML nested too deeply", path=path) from None


# ---------------------------------------------------------------------------
# shared checks
# ---------------------------------------------------------------------------


def _count(text, what: str) -> int:
    """A non-negative decimal integer from the file (declared count / size / offset)."""
    s = text.decode("ascii", "replace") if isinstance(text, bytes) else str(text)
    s = s.strip()
    if not re.fullmatch(r"\+?[0-9]{1,19}", s):
        raise _Bad(f"{what} is not a non-negative integer: {_short(s)!r}")
    return int(s)


def _short(s, limit: int = 60) -> str:
    return excerpt(s, limit)


def _as_index(values: np.ndarray, what: str) -> np.ndarray:
    """Integer array -> int64, refusing values that do not fit (uint64 past 2^63)."""
    if values.dtype.kind == "f":
        raise _Bad(f"{what} are floating-point numbers, not integers")
    if (
        values.dtype.kind == "u"
        and values.dtype.itemsize == 8
        and len(values)
        and int(values.max()) > np.iinfo(np.int64).max
    ):
        raise _Bad(f"{what} hold a value past 2^63")
    return values.astype(np.int64, copy=False)


def _check_offsets(offsets: np.ndarray, n_connectivity: int, what: str) -> None:
    """``offsets`` (c + 1,) with 0 first: non-decreasing, ending at ``n_connectivity``."""
    if len(offsets) == 0 or offsets[0] != 0:
        raise _Bad(f"{what}: the first offset is not 0")
    steps = np.diff(offsets)
    if len(steps) and steps.min() < 0:
        k = int(np.flatnonzero(steps < 0)[0])
        raise _Bad(f"{what}: offset {k + 1} ({int(offsets[k + 1])}) is below the one before ({int(offsets[k])})")
    if offsets[-1] != n_connectivity:
        bad = offsets > n_connectivity
        if bad.any():
            k = int(np.flatnonzero(bad)[0])
            raise _Bad(
                f"{what}: offset {k} ({int(offsets[k])}) is past the end of the {n_connectivity} connectivity entries"
            )
        raise _Bad(f"{what}: the offsets end at {int(offsets[-1])} but there are {n_connectivity} connectivity entries")


def _split_lines(types: np.ndarray | None, offsets: np.ndarray, conn: np.ndarray):
    """Line cells (types 3 and 4; all cells when ``types`` is None) as (offsets, conn)."""
    if types is None:
        return offsets, conn
    is_line = (types == _VTK_LINE) | (types == _VTK_POLY_LINE)
    if is_line.all():
        return offsets, conn
    starts, ends = offsets[:-1][is_line], offsets[1:][is_line]
    lengths = ends - starts
    new_offsets = np.concatenate([[0], np.cumsum(lengths)]).astype(np.int64)
    if len(lengths) == 0:
        return new_offsets, np.zeros(0, np.int64)
    # gather conn[starts[i]:ends[i]] for every line cell without a Python loop
    pos = np.arange(int(new_offsets[-1]), dtype=np.int64)
    cell = np.repeat(np.arange(len(lengths)), lengths)
    return new_offsets, conn[starts[cell] + pos - new_offsets[:-1][cell]]


def _n_other(types: np.ndarray) -> int:
    other = (
        (types != _VTK_LINE)
        & (types != _VTK_POLY_LINE)
        & (types != _VTK_VERTEX)
        & (types != _VTK_POLY_VERTEX)
        & (types != 0)
    )
    return int(np.count_nonzero(other))


#: VTK's numeric data types, one row each: the XML name (``type="Float32"``), the legacy
#: name (matched in any case) and the numpy dtype code
_VTK_TYPES = (
    ("Int8", "vtktypeint8", "i1"),
    ("UInt8", "vtktypeuint8", "u1"),
    ("Int16", "vtktypeint16", "i2"),
    ("UInt16", "vtktypeuint16", "u2"),
    ("Int32", "vtktypeint32", "i4"),
    ("UInt32", "vtktypeuint32", "u4"),
    ("Int64", "vtktypeint64", "i8"),
    ("UInt64", "vtktypeuint64", "u8"),
    ("Float32", "vtktypefloat32", "f4"),
    ("Float64", "vtktypefloat64", "f8"),
    ("Char", "char", "i1"),
    ("UChar", "unsigned_char", "u1"),
    ("Short", "short", "i2"),
    ("UShort", "unsigned_short", "u2"),
    ("Int", "int", "i4"),
    ("UInt", "unsigned_int", "u4"),
    ("Long", "long", "i8"),
    ("ULong", "unsigned_long", "u8"),
    ("Float", "float", "f4"),
    ("Double", "double", "f8"),
    ("IdType", "vtkidtype", "i8"),
)
#: legacy names; ``bit`` is known but not read, ``signed_char`` has no XML name
_LEGACY_TYPES = {"bit": None, "signed_char": "i1", **{legacy: code for _, legacy, code in _VTK_TYPES}}
_XML_TYPES = {xml: code for xml, _, code in _VTK_TYPES}


# ---------------------------------------------------------------------------
# legacy .vtk
# ---------------------------------------------------------------------------

_NEXT_KEYWORD_LINE = re.compile(rb"\n[ \t\r\x00]*[A-Za-z_]")
_SPACE = re.compile(rb"[ \t\r\n\x00]*")
_BLANK_AT = re.compile(rb"[ \t\r]*(?:\n|\Z)")
_BLANK_LINE = re.compile(rb"\n[ \t\r]*(?:\n|\Z)")
_KEYWORD = re.compile(rb"[ \t\r\n\x00]*([A-Za-z_]+)")
_ATTRIBUTE_SECTIONS = {b"POINT_DATA", b"CELL_DATA", b"FIELD"}
_POLYDATA_SECTIONS = {b"VERTICES", b"LINES", b"POLYGONS", b"TRIANGLE_STRIPS"}


class _Legacy:
    """Cursor over the bytes of a legacy VTK file."""

    def __init__(self, data: bytes):
        self.buf = data
        self.pos = 0
        self.binary = False
        self.version = (0, 0)

    # -- low level ---------------------------------------------------------

    def _skip_space(self) -> None:
        self.pos = _SPACE.match(self.buf, self.pos).end()

    def line(self, what: str, *, skip_blank: bool = True) -> bytes:
        """The next (non-blank) line, without its line end."""
        if skip_blank:
            self._skip_space()
        if self.pos >= len(self.buf):
            raise _Bad(f"the file ends where {what} was expected")
        end = self.buf.find(b"\n", self.pos)
        end = len(self.buf) if end < 0 else end
        text = self.buf[self.pos : end].rstrip(b"\r")
        self.pos = end + 1
        return text

    def peek_word(self) -> bytes:
        """The keyword starting the next non-blank line, upper case; the cursor stays."""
        m = _KEYWORD.match(self.buf, self.pos)
        return m.group(1).upper() if m else b""

    def values(self, count: int, type_name: str, what: str) -> np.ndarray:
        """``count`` numbers of the legacy type ``type_name`` at the cursor."""
        code = _LEGACY_TYPES.get(type_name.lower(), "?")
        if code is None or code == "?":
            raise _Bad(f"{what}: data type {_short(type_name)!r} is not supported")
        dtype = np.dtype(code)
        if self.binary:
            big = dtype.newbyteorder(">")
            need = count * big.itemsize
            if need > len(self.buf) - self.pos:
                raise _Bad(
                    f"{what} declares {count} values ({need} bytes) but only {len(self.buf) - self.pos} bytes follow"
                )
            out = np.frombuffer(self.buf, big, count, self.pos).astype(dtype.newbyteorder("="))
            self.pos += need
            return out
        return self._ascii_values(count, dtype, what)

    def _ascii_values(self, count: int, dtype: np.dtype, what: str) -> np.ndarray:
        self._skip_space()
        room = (len(self.buf) - self.pos + 1) // 2  # a number and a separator
        if count > room:
            raise _Bad(
                f"{what} declares {count} values but the rest of the file "
                f"({len(self.buf) - self.pos} bytes) cannot hold that many"
            )
        # usually the values run to the next line starting with a keyword: parse that span
        # in one go; if it does not hold exactly `count` numbers, go token by token
        if count:
            m = _NEXT_KEYWORD_LINE.search(self.buf, self.pos)
            end = len(self.buf) if m is None else m.start()
            if end - self.pos <= 64 * count + 64:
                fast = _fast_numbers(self.buf[self.pos : end], dtype)
                if fast is not None and len(fast) == count:
                    self.pos = end
                    return fast.astype(dtype, copy=False)
        out = np.empty(count, dtype=dtype)
        done = 0
        rest = self.buf[self.pos :] if count else b""
        consumed = 0
        while done < count:
            take = min(_CHUNK_TOKENS, count - done)
            parts = rest.split(None, take)
            if len(parts) < take:
                raise _Bad(f"{what} declares {count} values but the file holds only {done + len(parts)}")
            new_rest = parts[take] if len(parts) > take else b""
            span = rest[: len(rest) - len(new_rest)]
            del parts[take:]
            out[done : done + take] = _numbers(span, parts, dtype, what)
            done += take
            consumed += len(span)
            rest = new_rest
        self.pos += consumed
        return out

    # -- structure ---------------------------------------------------------

    def parse(self, path: str) -> Dataset:
        dataset = self._header(path)
        found = self._sections(dataset)
        points, lines, n_other = found["points"], found["lines"], found["n_other"]
        if points is None:
            raise _Bad("no POINTS section")
        if dataset == b"UNSTRUCTURED_GRID":
            if found["cells"] is None:
                return Dataset(points, np.zeros(1, np.int64), np.zeros(0, np.int64), 0)
            offsets, conn = found["cells"]
            types = found["types"]
            if types is None:
                raise _Bad("CELLS without CELL_TYPES")
            if len(types) != len(offsets) - 1:
                raise _Bad(f"CELL_TYPES gives {len(types)} types for {len(offsets) - 1} cells")
            n_other = _n_other(types)
            offsets, conn = _split_lines(types, offsets, conn)
            return Dataset(points, offsets, conn, n_other)
        if lines is None:
            return Dataset(points, np.zeros(1, np.int64), np.zeros(0, np.int64), n_other)
        return Dataset(points, lines[0], lines[1], n_other)

    def _header(self, path: str) -> bytes:
        """The four header lines (version, title, ASCII or BINARY, DATASET); returns the
        dataset type, POLYDATA or UNSTRUCTURED_GRID (others hold no curves: NoCurvesError)."""
        head = self.line("the header", skip_blank=False)
        m = re.match(rb"#\s*vtk\s+DataFile\s+Version\s+([0-9]+)\.([0-9]+)", head, re.IGNORECASE)
        if not m:
            raise _Bad("the first line is not '# vtk DataFile Version x.y'")
        self.version = (int(m.group(1)[:6]), int(m.group(2)[:6]))
        if self.pos >= len(self.buf):
            raise _Bad("the file ends after the first line")
        self.line("the title line", skip_blank=False)  # title: anything
        mode = self.line("ASCII or BINARY").strip().upper()
        if mode not in (b"ASCII", b"BINARY"):
            raise _Bad(f"line 3 must be ASCII or BINARY, not {_short(mode)!r}")
        self.binary = mode == b"BINARY"
        words = self.line("the DATASET line").split()
        if len(words) != 2 or words[0].upper() != b"DATASET":
            raise _Bad(f"expected 'DATASET <type>', found {_short(b' '.join(words))!r}")
        dataset = words[1].upper()
        if dataset not in (b"POLYDATA", b"UNSTRUCTURED_GRID"):
            raise NoCurvesError(
                f"holds a dataset of type {dataset.decode('latin-1')}; curves "
                "are read from the line cells of PolyData or UnstructuredGrid "
                "only",
                path=path,
            )
        return dataset

    def _sections(self, dataset: bytes) -> dict:
        """The geometry sections up to the attribute data: ``points``, ``lines`` (PolyData
        LINES), ``n_other`` (polygons and strips), ``cells`` and ``types`` (an
        UnstructuredGrid's CELLS and CELL_TYPES); None for a section not found."""
        found = {"points": None, "lines": None, "n_other": 0, "cells": None, "types": None}
        last = ""
        for _ in range(MAX_SECTIONS + 1):
            word = self.peek_word()
            if not word:
                rest = self.buf[self.pos :].split(None, 2)
                if rest:
                    raise _Bad(
                        f"found {_short(b' '.join(rest[:2]))!r} where a section "
                        f"keyword was expected (after {last or 'the header'}: more "
                        "values than declared?)"
                    )
                return found
            if word in _ATTRIBUTE_SECTIONS:
                return found
            header = self.line("a section").split()
            last = header[0].upper().decode("latin-1")
            self._section(header, dataset, found)
        raise _Bad(f"more than {MAX_SECTIONS} sections before the attribute data")

    def _section(self, header: list, dataset: bytes, found: dict) -> None:
        """Read the section whose header line split into ``header`` into ``found``."""
        key = header[0].upper()
        if key == b"METADATA":
            self._skip_metadata()
        elif key == b"POINTS":
            if len(header) != 3:
                raise _Bad("the POINTS line must be 'POINTS n type'")
            n = _count(header[1], "the POINTS count")
            flat = self.values(3 * n, header[2].decode("latin-1"), "POINTS")
            found["points"] = flat.astype(np.float64).reshape(n, 3)
        elif dataset == b"POLYDATA" and key in _POLYDATA_SECTIONS:
            offsets, conn = self._cells(header, key.decode())
            if key == b"LINES":
                found["lines"] = (offsets, conn)
            elif key in (b"POLYGONS", b"TRIANGLE_STRIPS"):
                found["n_other"] += len(offsets) - 1
        elif dataset == b"UNSTRUCTURED_GRID" and key == b"CELLS":
            found["cells"] = self._cells(header, "CELLS")
        elif dataset == b"UNSTRUCTURED_GRID" and key == b"CELL_TYPES":
            if len(header) != 2:
                raise _Bad("the CELL_TYPES line must be 'CELL_TYPES n'")
            n = _count(header[1], "the CELL_TYPES count")
            found["types"] = self.values(n, "int", "CELL_TYPES").astype(np.int64)
        else:
            raise _Bad(f"unexpected section {_short(key)!r} in a {dataset.decode('latin-1')} dataset")

    def _skip_metadata(self) -> None:
        """METADATA blocks end at the first blank line (or the end of the file)."""
        m = _BLANK_AT.match(self.buf, self.pos) or _BLANK_LINE.search(self.buf, self.pos)
        self.pos = len(self.buf) if m is None else m.end()

    def _cells(self, header, what: str):
        """A cell section -> (offsets (c + 1,) int64 from 0, connectivity (m,) int64)."""
        if len(header) != 3:
            raise _Bad(f"the {what} line must be '{what} n size'")
        first = _count(header[1], f"the {what} cell count")
        second = _count(header[2], f"the {what} size")
        if self.peek_word() == b"OFFSETS":  # version 5 layout
            off_type = self.line("OFFSETS").split()
            if len(off_type) != 2:
                raise _Bad(f"{what}: the OFFSETS line must be 'OFFSETS type'")
            offsets = _as_index(self.values(first, off_type[1].decode("latin-1"), f"{what} OFFSETS"), f"{what} offsets")
            if self.peek_word() != b"CONNECTIVITY":
                raise _Bad(f"{what}: CONNECTIVITY expected after OFFSETS")
            conn_type = self.line("CONNECTIVITY").split()
            if len(conn_type) != 2:
                raise _Bad(f"{what}: the CONNECTIVITY line must be 'CONNECTIVITY type'")
            conn = _as_index(
                self.values(second, conn_type[1].decode("latin-1"), f"{what} CONNECTIVITY"), f"{what} connectivity"
            )
            if first == 0:
                if second:
                    raise _Bad(f"{what}: connectivity without offsets")
                offsets = np.zeros(1, np.int64)
            _check_offsets(offsets, len(conn), what)
            return offsets, conn
        # classic layout: size values "n i0 i1 ... n i0 ..." for `first` cells
        flat = _as_index(self.values(second, "int", what), what)
        return _walk_counts(flat, first, what)


def _walk_counts(flat: np.ndarray, n_cells: int, what: str):
    """``[n, i0..i(n-1), n, ...]`` holding exactly ``n_cells`` cells -> (offsets, connectivity)."""
    if n_cells > len(flat):
        raise _Bad(f"{what} declares {n_cells} cells but its {len(flat)} values cannot hold them")
    values = flat.tolist()
    size = len(values)
    heads = [0] * n_cells
    k = 0
    for c in range(n_cells):
        if k >= size:
            raise _Bad(f"{what} declares {n_cells} cells but its {size} values hold only {c}")
        n = values[k]
        if n < 0:
            raise _Bad(f"{what}: cell {c} has a negative point count ({n})")
        heads[c] = k
        k += 1 + n
        if k > size:
            raise _Bad(f"{what}: cell {c} declares {n} points, past the end of the {size} values")
    if k != size:
        raise _Bad(f"{what}: the {n_cells} cells use {k} of the {size} values declared")
    head_idx = np.array(heads, dtype=np.int64)
    counts = flat[head_idx] if n_cells else np.zeros(0, np.int64)
    offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    keep = np.ones(size, dtype=bool)
    keep[head_idx] = False
    return offsets, flat[keep]


_INTEGER_CHARS = b"0123456789+- \t\r\n\x0b\x0c"


def _fast_numbers(span: bytes, dtype: np.dtype) -> np.ndarray | None:
    """All whitespace-separated numbers of ``span`` parsed in C, or None if any token is not
    a number of that kind (or an integer may have overflowed): then parse token by token."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            if dtype.kind == "f":
                fast = np.fromstring(span, dtype=np.float64, sep=" ")
            elif not span.translate(None, _INTEGER_CHARS):
                fast = np.fromstring(span, dtype=np.int64, sep=" ")
                limits = np.iinfo(np.int64)
                if len(fast) and (fast.max() == limits.max or fast.min() == limits.min):
                    fast = None  # numpy clamps overflow: decide exactly below
            else:
                fast = None
        except ValueError:
            fast = None
    # numpy's separator " " also matches *no* whitespace ("5-3" reads as 5, -3): the
    # count must equal the number of whitespace-separated tokens
    if fast is not None and len(fast) != _token_count(span):
        return None
    return fast


_WHITESPACE = np.zeros(256, dtype=bool)
_WHITESPACE[list(b" \t\n\r\x0b\x0c")] = True


def _token_count(span: bytes) -> int:
    """Number of runs of non-whitespace bytes (vectorized ``len(span.split())``)."""
    if not span:
        return 0
    solid = ~_WHITESPACE[np.frombuffer(span, dtype=np.uint8)]
    return int(solid[0]) + int(np.count_nonzero(solid[1:] & ~solid[:-1]))


def _numbers(span: bytes, tokens, dtype: np.dtype, what: str) -> np.ndarray:
    """The whitespace-separated numbers of ``span`` (its tokens are ``tokens``, or None if
    not split yet) as ``dtype``; a token that is not a number of that kind is an error."""
    fast = _fast_numbers(span, dtype)
    if fast is not None and (tokens is None or len(fast) == len(tokens)):
        return fast
    if tokens is None:
        tokens = span.split()
    try:
        if dtype.kind == "f":
            return np.array([float(t) for t in tokens], dtype=np.float64)
        values = [int(t) for t in tokens]
        return np.array(values, dtype=np.int64) if values else np.zeros(0, np.int64)
    except (ValueError, OverflowError):
        bad = next((t for t in tokens if not _is_number(t, dtype.kind)), b"?")
        raise _Bad(
            f"{what}: not {'a number' if dtype.kind == 'f' else 'an integer'} (or out of range): {_short(bad)!r}"
        ) from None


def _is_number(token: bytes, kind: str) -> bool:
    try:
        if kind == "f":
            float(token)
        else:
            np.int64(int(token))
    except (ValueError, OverflowError):
        return False
    return True


# ---------------------------------------------------------------------------
# XML .vtp / .vtu
# ---------------------------------------------------------------------------

_B64_CHUNK = re.compile(rb"[A-Za-z0-9+/]*={0,2}")
_NOT_B64 = re.compile(rb"[^A-Za-z0-9+/=\s]")
_B64_ALPHABET = b"ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/= \t\r\n\x0b\x0c"


def _b64decode(text: bytes, what: str) -> bytes:
    """Base64 that may be several padded pieces in a row (VTK encodes headers apart)."""
    if text.translate(None, _B64_ALPHABET):
        bad = _NOT_B64.search(text)
        raise _Bad(f"{what}: {_short(bad.group(0) if bad else b'?')!r} is not base64")
    text = text.translate(None, b" \t\r\n\x0b\x0c")
    if b"=" not in text[:-2]:  # one piece: the common case
        pieces = [text]
    else:
        pieces = [p for p in _B64_CHUNK.findall(text) if p]
        if len(pieces) > MAX_BASE64_PIECES:
            raise _Bad(f"{what}: base64 text in {len(pieces)} separately padded pieces")
        if sum(map(len, pieces)) != len(text):
            raise _Bad(f"{what}: misplaced base64 padding")
    out = []
    for piece in pieces:
        if len(piece) % 4:
            raise _Bad(f"{what}: base64 text of {len(piece)} characters is cut short")
        # checked here, not by a2b_base64's strict_mode (Python 3.11+; the package supports 3.10):
        # a piece of whole 4-character groups whose only padding is its last one or two
        # characters holds nothing a strict decoder refuses, and decodes the same without it
        if not _B64_CHUNK.fullmatch(piece):
            raise _Bad(f"{what}: invalid base64 (padding inside a 4-character group)")
        try:
            out.append(binascii.a2b_base64(piece))
        except (binascii.Error, ValueError):
            raise _Bad(f"{what}: invalid base64") from None
    return b"".join(out)


class _Xml:
    def __init__(self, data: bytes, root, kind: str, appended: bytes | None, appended_base64: bool, path: str):
        self.data_size = len(data)
        self.root = root
        self.kind = kind
        self.appended = appended
        self.appended_base64 = appended_base64
        self.path = path
        order = root.get("byte_order", "LittleEndian")
        if order not in ("LittleEndian", "BigEndian"):
            raise _Bad(f"byte_order {_short(order)!r} is neither LittleEndian nor BigEndian")
        self.order = "<" if order == "LittleEndian" else ">"
        header = root.get("header_type", "UInt32")
        if header not in ("UInt32", "UInt64"):
            raise _Bad(f"header_type {_short(header)!r} is neither UInt32 nor UInt64")
        self.header = np.dtype(self.order + ("u4" if header == "UInt32" else "u8"))
        compressor = root.get("compressor")
        if compressor not in (None, "", "vtkZLibDataCompressor", "vtkLZMADataCompressor", "vtkLZ4DataCompressor"):
            raise _Bad(f"compressor {_short(compressor)!r} is not supported")
        self.compressor = compressor or None
        self.inflated = 0
        self.cap = inflated_cap(self.data_size)
        self._b64_cache: dict[int, bytes] = {}
        self._b64_offsets = None

    def _limit(self) -> str:
        return (
            f"more than the limit of {self.cap} bytes of data for a file of "
            f"{self.data_size} bytes (nfdmatch.formats._vtk_read.MAX_INFLATED_BYTES, "
            f"MAX_INFLATION_RATIO)"
        )

    # -- one DataArray -> numpy --------------------------------------------

    def array(self, element, count: int, components: int, what: str) -> np.ndarray:
        """The values of a DataArray, checked to be exactly ``count * components``."""
        if element is None:
            raise _Bad(f"{what}: the DataArray is missing")
        code = _XML_TYPES.get(element.get("type", ""))
        if code is None:
            raise _Bad(f"{what}: unsupported DataArray type {_short(element.get('type', ''))!r}")
        n_comp = _count(element.get("NumberOfComponents", "1"), f"{what} NumberOfComponents")
        if n_comp != components:
            raise _Bad(f"{what}: NumberOfComponents is {n_comp}, expected {components}")
        expected = count * components
        fmt = element.get("format", "ascii")
        if fmt == "ascii":
            values = self._ascii(element.text or "", expected, np.dtype(code), what)
        else:
            dtype = np.dtype(self.order + code)
            if expected * dtype.itemsize > self.cap:
                raise _Bad(f"{what} declares {expected} values ({expected * dtype.itemsize} bytes): {self._limit()}")
            if fmt == "binary":
                raw = _b64decode((element.text or "").encode("ascii", "replace"), what)
                blob = self._unpack(raw, 0, what)
            elif fmt == "appended":
                blob = self._appended(element, what)
            else:
                raise _Bad(f"{what}: unknown DataArray format {_short(fmt)!r}")
            if len(blob) != expected * dtype.itemsize:
                raise _Bad(f"{what}: {len(blob)} bytes of data for {expected} values of {dtype.itemsize} bytes")
            values = np.frombuffer(blob, dtype).astype(dtype.newbyteorder("="))
        return values

    def _ascii(self, text: str, expected: int, dtype: np.dtype, what: str) -> np.ndarray:
        if expected > (len(text) + 1) // 2:
            raise _Bad(f"{what} declares {expected} values but holds at most {(len(text) + 1) // 2}")
        raw = text.encode("ascii", "replace")
        values = _numbers(raw, None, dtype, what)
        if len(values) == expected:
            return values.astype(dtype, copy=False)
        reader = _Legacy(raw)  # says how the count is wrong
        values = reader._ascii_values(expected, dtype, what)
        reader._skip_space()
        if reader.pos < len(reader.buf):
            raise _Bad(f"{what} holds more than the {expected} values declared")
        return values

    def _unpack(self, raw: bytes, start: int, what: str) -> bytes:
        """Header + data at ``raw[start:]`` -> the (inflated) data bytes."""
        h = self.header.itemsize
        if len(raw) - start < h:
            raise _Bad(f"{what}: the data header is cut short")
        if self.compressor is None:
            n = int(np.frombuffer(raw, self.header, 1, start)[0])
            if n > len(raw) - start - h:
                raise _Bad(f"{what}: the header declares {n} bytes but only {len(raw) - start - h} follow")
            return raw[start + h : start + h + n]
        if len(raw) - start < 3 * h:
            raise _Bad(f"{what}: the compression header is cut short")
        n_blocks, block, last = (int(v) for v in np.frombuffer(raw, self.header, 3, start))
        if n_blocks > (len(raw) - start - 3 * h) // h:
            raise _Bad(f"{what}: the compression header declares {n_blocks} blocks, more than the data holds")
        sizes = np.frombuffer(raw, self.header, n_blocks, start + 3 * h).astype(np.uint64)
        if n_blocks == 0:
            return b""
        if block == 0 or last > block:
            raise _Bad(f"{what}: bad compression block sizes ({block}, last {last})")
        total = (n_blocks - 1) * block + (last or block)
        self.inflated += total
        if self.inflated > self.cap:
            raise _Bad(f"{what}: the compressed data would inflate to {self._limit()}")
        pos = start + (3 + n_blocks) * h
        if int(sizes.sum()) > len(raw) - pos:
            raise _Bad(
                f"{what}: the compressed blocks declare {int(sizes.sum())} bytes but only {len(raw) - pos} follow"
            )
        out = []
        for b, size in enumerate(sizes.tolist()):
            want = last if (b == n_blocks - 1 and last) else block
            out.append(_inflate(self.compressor, raw[pos : pos + size], want, what))
            pos += size
        return b"".join(out)

    def _appended(self, element, what: str) -> bytes:
        if self.appended is None:
            raise _Bad(f"{what}: format 'appended' but the file has no AppendedData")
        offset = _count(element.get("offset", ""), f"{what} offset")
        if offset >= len(self.appended) and not (offset == len(self.appended) == 0):
            raise _Bad(f"{what}: offset {offset} is past the end of the {len(self.appended)} bytes of appended data")
        if not self.appended_base64:
            return self._unpack(self.appended, offset, what)
        # base64: each array is encoded apart; it runs to the next array's offset
        if self._b64_offsets is None:
            self._b64_offsets = sorted(
                {
                    _count(e.get("offset", "0"), "offset")
                    for e in self.root.iter("DataArray")
                    if e.get("format") == "appended"
                }
            )
        k = np.searchsorted(self._b64_offsets, offset, side="right")
        end = self._b64_offsets[k] if k < len(self._b64_offsets) else len(self.appended)
        return self._unpack(_b64decode(self.appended[offset:end], what), 0, what)


def _inflate(compressor: str, blob: bytes, want: int, what: str) -> bytes:
    """One compressed block -> exactly ``want`` bytes, never inflating past ``want``."""
    try:
        if compressor == "vtkZLibDataCompressor":
            d = zlib.decompressobj()
            out = d.decompress(blob, want)
            if not d.eof:
                raise _Bad(f"{what}: a compressed block is cut short or inflates past its stated size ({want} bytes)")
        elif compressor == "vtkLZMADataCompressor":
            d = lzma.LZMADecompressor()
            out = d.decompress(blob, want)
            if not d.eof:
                raise _Bad(f"{what}: a compressed block is cut short or inflates past its stated size ({want} bytes)")
        else:
            out = _lz4_block(blob, want, what)
    except (zlib.error, lzma.LZMAError, EOFError) as exc:
        raise _Bad(f"{what}: corrupt compressed data ({exc})") from None
    if len(out) != want:
        raise _Bad(f"{what}: a compressed block inflates to {len(out)} bytes, not the {want} stated")
    return out


def _lz4_block(src: bytes, want: int, what: str) -> bytes:
    """Decode one raw LZ4 block (the format vtkLZ4DataCompressor writes), bounded by ``want``."""
    out = bytearray()
    i, n = 0, len(src)
    while i < n:
        token = src[i]
        i += 1
        lit = token >> 4
        if lit == 15:
            more, i = _lz4_length(src, i, what)
            lit += more
        if i + lit > n or len(out) + lit > want:
            raise _Bad(f"{what}: corrupt LZ4 data")
        out += src[i : i + lit]
        i += lit
        if i >= n:
            break  # the last sequence has literals only
        if i + 2 > n:
            raise _Bad(f"{what}: corrupt LZ4 data")
        offset = src[i] | (src[i + 1] << 8)
        i += 2
        match = (token & 15) + 4
        if (token & 15) == 15:
            more, i = _lz4_length(src, i, what)
            match += more
        if offset == 0 or offset > len(out) or len(out) + match > want:
            raise _Bad(f"{what}: corrupt LZ4 data")
        start = len(out) - offset
        if match <= offset:
            out += out[start : start + match]
        else:  # overlapping copy repeats the pattern
            pattern = bytes(out[start:])
            reps = -(-match // offset)
            out += (pattern * reps)[:match]
    return bytes(out)


def _lz4_length(src: bytes, i: int, what: str) -> tuple[int, int]:
    """The bytes LZ4 adds to a length of 15 (a literal run's or a match's): every byte from
    ``src[i]`` up to and including the first one below 255, summed; ``(sum, next i)``."""
    n, more = len(src), 0
    while True:
        if i >= n:
            raise _Bad(f"{what}: corrupt LZ4 data")
        b = src[i]
        i += 1
        more += b
        if b != 255:
            return more, i


def _parse_xml(data: bytes, kind: str, path: str) -> Dataset:
    if not data.lstrip()[:1] == b"<":
        raise _Bad("not an XML file")
    head, appended, appended_base64 = _split_appended(data)
    root, dtype_name = _xml_root(head, kind, path)
    xml = _Xml(data, root, kind, appended, appended_base64, path)
    body = root.find(dtype_name)
    if body is None:
        raise _Bad(f"no <{dtype_name}> element")
    all_points, all_offsets, all_conn = [], [], []
    n_other = 0
    base = 0
    conn_base = 0
    pieces = body.findall("Piece")
    if len(pieces) > MAX_PIECES:
        raise _Bad(f"{len(pieces)} pieces, more than the {MAX_PIECES} accepted")
    for p, piece in enumerate(pieces):
        pts, offsets, conn, others = _xml_piece(xml, piece, f"piece {p}", dtype_name)
        n_other += others
        all_points.append(pts)
        all_offsets.append(offsets[1:] + conn_base)
        all_conn.append(conn + base)
        base += len(pts)
        conn_base += len(conn)
    if not all_points:
        raise _Bad(f"no <Piece> in <{dtype_name}>")
    points = np.concatenate(all_points) if len(all_points) > 1 else all_points[0]
    offsets = np.concatenate([np.zeros(1, np.int64), *all_offsets])
    conn = np.concatenate(all_conn) if len(all_conn) > 1 else all_conn[0]
    return Dataset(points, offsets, conn, n_other)


def _split_appended(data: bytes) -> tuple[bytes, bytes | None, bool]:
    """``(XML head, appended data, whether it is base64)``: an <AppendedData> section is cut
    off (its bytes are not XML) and the head closed; no section: ``(data, None, True)``."""
    start_tag = data.find(b"<AppendedData")
    if start_tag < 0:
        return data, None, True
    close = data.find(b">", start_tag)
    if close < 0:
        raise _Bad("the AppendedData tag is not closed")
    tag = data[start_tag : close + 1]
    m = re.search(rb'encoding\s*=\s*"([^"]*)"', tag)
    encoding = m.group(1) if m else b"raw"
    if encoding not in (b"raw", b"base64"):
        raise _Bad(f"AppendedData encoding {_short(encoding)!r} is not raw or base64")
    appended_base64 = encoding == b"base64"
    underscore = data.find(b"_", close)
    if underscore < 0:
        raise _Bad("AppendedData without the '_' that starts the data")
    end = data.rfind(b"</AppendedData>")
    if end < underscore:
        end = len(data)
    appended = data[underscore + 1 : end]
    if appended_base64:
        appended = appended.rstrip()
    return data[:start_tag] + b"</VTKFile>", appended, appended_base64


def _xml_root(head: bytes, kind: str, path: str):
    """The <VTKFile> root element and its dataset type, the one of a .vtp (PolyData) or
    .vtu (UnstructuredGrid) file; other types hold no curves (NoCurvesError)."""
    try:
        root = ET.fromstring(head)
    except ET.ParseError as exc:
        raise _Bad(f"not well-formed XML ({exc})") from None
    if root.tag != "VTKFile":
        raise _Bad(f"the root element is <{_short(root.tag)}>, not <VTKFile>")
    dtype_name = root.get("type", "")
    want = {"vtp": "PolyData", "vtu": "UnstructuredGrid"}[kind]
    if dtype_name not in ("PolyData", "UnstructuredGrid"):
        raise NoCurvesError(
            f"holds a dataset of type {_short(dtype_name) or '(none)'}; curves "
            "are read from the line cells of PolyData or UnstructuredGrid only",
            path=path,
        )
    if dtype_name != want:
        raise _Bad(f"a .{kind} file must hold {want}, this one holds {dtype_name}")
    return root, dtype_name


def _xml_piece(xml: _Xml, piece, where: str, dtype_name: str):
    """One <Piece>: its points, its line cells (offsets from 0, connectivity) and the
    number of its other cells (polygons, strips, ...)."""
    n_other = 0
    n_points = _count(piece.get("NumberOfPoints", "0"), f"{where} NumberOfPoints")
    if n_points:
        pts_el = piece.find("Points/DataArray")
        pts = xml.array(pts_el, n_points, 3, f"{where} Points").astype(np.float64)
        pts = pts.reshape(n_points, 3)
    else:
        pts = np.zeros((0, 3))
    if dtype_name == "PolyData":
        offsets, conn = _xml_cells(xml, piece, "Lines", "NumberOfLines", where)
        for section, attr in (("Polys", "NumberOfPolys"), ("Strips", "NumberOfStrips")):
            o, _ = _xml_cells(xml, piece, section, attr, where)
            n_other += len(o) - 1
        _xml_cells(xml, piece, "Verts", "NumberOfVerts", where)
    else:
        offsets, conn = _xml_cells(xml, piece, "Cells", "NumberOfCells", where)
        n_cells = len(offsets) - 1
        types = (
            _as_index(
                xml.array(_named(piece, "Cells", "types"), n_cells, 1, f"{where} cell types"), f"{where} cell types"
            )
            if n_cells
            else np.zeros(0, np.int64)
        )
        n_other += _n_other(types)
        offsets, conn = _split_lines(types, offsets, conn)
    return pts, offsets, conn, n_other


def _named(piece, section: str, name: str):
    for element in piece.findall(f"{section}/DataArray"):
        if element.get("Name") == name:
            return element
    return None


def _xml_cells(xml: _Xml, piece, section: str, count_attr: str, where: str):
    """Cells of one section -> (offsets (c + 1,) from 0, connectivity), checked."""
    n_cells = _count(piece.get(count_attr, "0"), f"{where} {count_attr}")
    if n_cells == 0:
        return np.zeros(1, np.int64), np.zeros(0, np.int64)
    what = f"{where} {section}"
    offsets = _as_index(xml.array(_named(piece, section, "offsets"), n_cells, 1, f"{what} offsets"), f"{what} offsets")
    last = int(offsets[-1])
    if last < 0:
        raise _Bad(f"{what} offsets: the last offset is negative ({last})")
    conn_el = _named(piece, section, "connectivity")
    if conn_el is None:
        raise _Bad(f"{what} connectivity: the DataArray is missing")
    conn = _as_index(xml.array(conn_el, last, 1, f"{what} connectivity"), f"{what} connectivity")
    offsets = np.concatenate([np.zeros(1, np.int64), offsets])
    _check_offsets(offsets, len(conn), f"{what}")
    return offsets, conn
