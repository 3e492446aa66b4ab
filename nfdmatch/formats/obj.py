"""Wavefront OBJ polylines (``l`` elements); a small parser of its own.

Reading (:func:`read`):

* ``v x y z [w]`` vertices (``w`` ignored; ``v x y z r g b`` vertex colours
  are accepted too, the colours ignored);
* every ``l`` element with 3 or more indices is one curve, as given (closing
  index repeated or not);
* ``l a b`` elements with 2 indices are segments: they are chained into loops
  (each connected component of segments is one curve, see
  :func:`nfdmatch._graph.chain_segments`);
* indices are 1-based; negative indices count back from the last vertex
  defined so far; ``v/vt`` forms (``l 1/1 2/2``) use the vertex part;
* ``\\`` at the end of a line continues it; ``#`` starts a comment; every other
  statement (``vt``, ``vn``, ``f``, ``o``, ``g``, ``usemtl``, ``s``, ...) is ignored.

Writing (:func:`write`): all vertices as ``v`` lines (``repr`` precision,
exact round trip), then one ``l`` element per curve with the closing index
repeated (``l 1 2 3 ... n 1``).

Test hook: ``_read_points_fast`` (the bulk numpy parser of the common case, which returns
None to hand a file to the careful parser) is called and replaced by tests, which check that
it is taken and that both parsers read the same curves.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import warnings

import numpy as np

from .._graph import chain_segments
from ..errors import CurveError, NoCurvesError, ParseError, excerpt
from ._chain import is_number, ordered_curves, points_list, read_text, write_text

if TYPE_CHECKING:
    import os
    from numpy.typing import NDArray
    from ..curve import CurvesLike

__all__ = ["read_points", "write"]


def _logical_lines(text: str):
    """Yield ``(first_line_number, statement)``: comments cut, ``\\`` continuations joined."""
    lines = text.split("\n")
    i, n = 0, len(lines)
    while i < n:
        start = i + 1
        line = lines[i]
        i += 1
        while True:
            stripped = line.rstrip()
            if not stripped.endswith("\\") or "#" in stripped:
                break
            line = stripped[:-1] + " " + (lines[i] if i < n else "")
            i += 1
        cut = line.find("#")
        if cut >= 0:
            line = line[:cut]
        if line.strip():
            yield start, line


def read_points(path: str | os.PathLike[str]) -> list[NDArray[np.float64]]:
    """The vertices of every curve of an OBJ file, in file order.

    Returns
    -------
    list of (n_i, 3) float64 arrays, not yet cleaned. Curves are ordered by
    their first ``l`` element (for chained segments: the earliest segment).

    Raises
    ------
    ReadError : missing file, a directory, unreadable.
    ParseError : empty, binary, bad ``v`` (coordinate count or non-numeric),
        bad ``l`` index (non-numeric, 0, out of range), fewer than 2 indices in
        an ``l``, a branching vertex among 2-point segments (line numbers given).
    CurveError : NaN / Inf in a ``v`` (with its line number).
    NoCurvesError : no ``l`` elements (a mesh with faces, or nothing at all).
    """
    p = str(path)
    text = read_text(p)
    fast = _read_points_fast(text, p)
    if fast is not None:
        return fast
    coords, v_lines, elements, checks, n_faces = _parse(text, p)
    if not elements:
        if n_faces:
            raise NoCurvesError(
                f"holds {n_faces} faces but no polylines (`l` elements): it is a mesh; "
                "extract contours from it first (`nfdmatch extract`: sections or boundary loops)",
                path=p,
            )
        raise NoCurvesError("no polylines (`l` elements) in the file", path=p)
    nv = len(coords)
    for lineno, largest in checks:
        if largest > nv:
            raise ParseError(
                f"vertex index {largest} is out of range: the file defines {nv} vertices", path=p, line=lineno
            )
    V = np.array(coords, dtype=np.float64).reshape(-1, 3)
    finite = np.isfinite(V).all(axis=1)
    if not finite.all():
        k = int(np.flatnonzero(~finite)[0])
        raise CurveError(f"vertex {k + 1} is not finite (NaN or Inf): {V[k].tolist()}", path=p, line=v_lines[k])
    return _curves(V, elements, p)


def _parse(text: str, p: str):
    """The careful parse of every statement: ``(coords, their line numbers, elements as
    (line, 0-based indices), (line, largest positive 1-based index) per element, the number
    of faces)``. Raises ParseError for a bad ``v`` or ``l``."""
    coords: list[tuple[float, float, float]] = []
    v_lines: list[int] = []
    elements: list[tuple[int, list[int]]] = []  # (line, 0-based indices)
    checks: list[tuple[int, int]] = []  # (line, largest positive 1-based index)
    n_faces = 0
    for lineno, line in _logical_lines(text):
        tokens = line.split()
        kw = tokens[0]
        if kw == "v":
            coords.append(_vertex(tokens[1:], p, lineno))
            v_lines.append(lineno)
        elif kw == "l":
            idx, largest = _element(tokens[1:], len(coords), p, lineno)
            elements.append((lineno, idx))
            checks.append((lineno, largest))
        elif kw == "f":
            n_faces += 1
    return coords, v_lines, elements, checks, n_faces


def _vertex(vals: list[str], p: str, lineno: int) -> tuple[float, float, float]:
    """x, y, z of a ``v`` statement's values (w, or r g b colours, ignored)."""
    if len(vals) not in (3, 4, 6):
        raise ParseError(
            f"a vertex (`v`) needs 3 coordinates x y z (optionally w), got {len(vals)}", path=p, line=lineno
        )
    try:
        return (float(vals[0]), float(vals[1]), float(vals[2]))
    except ValueError:
        bad = next(t for t in vals[:3] if not is_number(t))
        raise ParseError(f"vertex coordinate is not a number: {excerpt(bad)!r}", path=p, line=lineno) from None


def _element(refs: list[str], nv: int, p: str, lineno: int) -> tuple[list[int], int]:
    """The 0-based vertex indices of an ``l`` statement (``nv`` vertices defined so far:
    negative indices count back from there) and its largest positive 1-based index (checked
    against the whole file's vertices later)."""
    if len(refs) < 2:
        raise ParseError(f"an `l` element needs at least 2 vertex indices, got {len(refs)}", path=p, line=lineno)
    idx: list[int] = []
    largest = 0
    for ref in refs:
        head = ref.split("/", 1)[0]
        try:
            k = int(head)
        except ValueError:
            raise ParseError(f"bad vertex index {excerpt(ref)!r} in `l` element", path=p, line=lineno) from None
        if k == 0:
            raise ParseError("vertex index 0 is invalid (OBJ indices start at 1)", path=p, line=lineno)
        if k < 0:
            if nv + k < 0:
                raise ParseError(
                    f"relative vertex index {k} points before the first vertex ({nv} vertices defined so far)",
                    path=p,
                    line=lineno,
                )
            idx.append(nv + k)
        else:
            idx.append(k - 1)
            largest = max(largest, k)
    return idx, largest


def _curves(V: np.ndarray, elements, p: str) -> list[np.ndarray]:
    """The curves of the elements in file order: polylines as given, 2-index segments
    chained into loops."""
    polylines: list[tuple[int, np.ndarray]] = []
    segments: list[list[int]] = []
    seg_pos: list[int] = []
    for pos, (_, idx) in enumerate(elements):
        if len(idx) == 2:
            segments.append(idx)
            seg_pos.append(pos)
        else:
            polylines.append((pos, np.array(idx, dtype=np.int64)))
    loops = chain_segments(
        np.array(segments, dtype=np.int64).reshape(-1, 2),
        path=p,
        vertex_label=lambda v: str(v + 1),
        segment_where=lambda s: f"line {elements[seg_pos[s]][0]}",
    )
    loops = [(seg_pos[s], verts) for s, verts in loops]
    return [V[idx] for idx in ordered_curves(polylines, loops)]


def _read_points_fast(text: str, p: str):
    """The common case (``v x y z``, ``l`` with positive plain indices, 3 or more each,
    whole-line comments, no continuations, ASCII, no indented statements) parsed in bulk
    by numpy. Returns the curves, or
    None whenever anything falls outside that case (including any error): the careful
    parser then reads the file and reports problems with line numbers.
    """
    if "\\" in text or "/" in text or not text.isascii():
        return None
    # the parser splits statements on any whitespace and reads indented ones: here spaces
    # are the only separators and no statement is indented, else the parser decides
    if any(ch in text for ch in "\t\r\v\f\x1c\x1d\x1e\x1f") or text.startswith(" ") or "\n " in text:
        return None
    rows = _block_rows(text)
    if rows is None:
        rows = _line_rows(text)
        if rows is None:
            return None
    v_rows, l_rows = rows
    l_text = " ".join(l_rows)
    if "-" in l_text:
        return None
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            V = np.loadtxt(v_rows, dtype=np.float64, ndmin=2)
        flat = np.array(l_text.split(), dtype=np.int64)
    except (ValueError, OverflowError):  # an index past int64: the parser says which
        return None
    counts = _token_counts(l_rows)
    if V.shape != (len(v_rows), 3) or len(flat) != counts.sum() or counts.min() < 3:
        return None
    if not np.isfinite(V).all() or flat.min() < 1 or flat.max() > len(V):
        return None
    P = V[flat - 1]
    ends = np.cumsum(counts).tolist()
    return [P[a:e] for a, e in zip([0] + ends[:-1], ends)]


def _line_rows(text: str):
    """The text after the keyword of every ``v`` and ``l`` line, a loop over lines; None
    when a ``#`` is anywhere but at the start of a line, or a bare ``v`` / ``l``."""
    v_rows, l_rows = [], []
    comments = 0
    for line in text.split("\n"):
        head = line[:2]
        if head == "v ":
            v_rows.append(line[2:])
        elif head == "l ":
            l_rows.append(line[2:])
        elif head[:1] == "#":
            comments += 1
        elif head[:1] in ("v", "l") and (head == "v" or head == "l"):
            return None  # a bare `v` / `l`: let the parser say so
    if not v_rows or not l_rows or text.count("#") != comments:
        return None
    return v_rows, l_rows


def _block_rows(text: str):
    """What :func:`_line_rows` returns, without a loop over lines, for the layout :func:`write`
    makes: whole-line comments first, then one run of ``v`` lines, then one run of ``l``
    lines, then nothing but empty lines; None for any other layout."""
    start = 0
    while text.startswith("#", start):  # the leading comment lines
        start = text.find("\n", start) + 1
        if start == 0:
            return None
    body = text[start:].rstrip("\n")
    cut = body.find("\nl ")
    if not body.startswith("v ") or cut < 0 or "#" in body:
        return None
    v_block, l_block = body[:cut], body[cut + 1 :]
    # every line of each block starts with its keyword and a space
    if v_block.count("\nv ") != v_block.count("\n") or l_block.count("\nl ") != l_block.count("\n"):
        return None
    return v_block[2:].split("\nv "), l_block[2:].split("\nl ")


def _token_counts(rows: list[str]) -> np.ndarray:
    """``[len(row.split()) for row in rows]`` for rows of spaces and printable ASCII."""
    b = np.frombuffer("\n".join(rows).encode("ascii"), dtype=np.uint8)
    gap = (b == 32) | (b == 10)
    first = ~gap
    first[1:] &= gap[:-1]
    row = np.cumsum(b == 10)
    return np.bincount(row[first], minlength=len(rows))


def write(path: str | os.PathLike[str], curves: CurvesLike) -> None:
    """Write curves as ``v`` lines then one closed ``l`` element per curve.

    Parameters
    ----------
    path : target file.
    curves : :data:`~nfdmatch.curve.CurvesLike`, one or more (cleaned before writing).

    Raises
    ------
    ParameterError : no curves. CurveError : an invalid curve.
    WriteError : the file cannot be written.
    """
    p = str(path)
    arrays = points_list(curves, path=p)
    out = [f"# nfdmatch: {len(arrays)} closed curve{'s' if len(arrays) != 1 else ''}"]
    for pts in arrays:
        out.extend(f"v {x!r} {y!r} {z!r}" for x, y, z in pts.tolist())
    offset = 1
    for pts in arrays:
        n = len(pts)
        out.append("l " + " ".join(map(str, range(offset, offset + n))) + f" {offset}")
        offset += n
    write_text(p, "\n".join(out) + "\n")
