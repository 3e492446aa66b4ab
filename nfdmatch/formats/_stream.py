"""Copying a stream (stdin) into a file under the readers' caps, checked while it is read:
a hostile input fails after reading at most the cap, in bounded memory, not after holding
all of it (tests/test_read_limits.py)."""

from __future__ import annotations

import numpy as np

from ..errors import ParseError, ReadError
from ._chain import max_file_bytes

#: bytes read from the stream at a time
_PIECE = 1 << 20


def copy_capped(src, dst, *, name: str, line_limit: int | None = None) -> int:
    """Copy binary stream ``src`` into binary file ``dst`` piece by piece; returns the bytes
    copied. Stops with a :class:`ReadError` once more than :func:`max_file_bytes` bytes came
    (the size cap of every reader), and, with ``line_limit``, with a :class:`ParseError`
    naming the line as soon as one line holds more than ``line_limit`` bytes. Memory: one
    piece (1 MiB) whatever the input."""
    limit = max_file_bytes()
    total = 0
    line, line_start = 1, 0  # the current line's number and the offset where it began
    while True:
        piece = src.read(_PIECE)
        if not piece:
            return total
        if line_limit is not None:
            ends = np.flatnonzero(np.frombuffer(piece, dtype=np.uint8) == 10) + total
            starts = np.concatenate([[line_start], ends[:-1] + 1]) if len(ends) else np.array([line_start])
            lengths = ends - starts[: len(ends)]
            over = np.flatnonzero(lengths > line_limit)
            if len(over):
                raise ParseError(_too_long(line_limit), path=name, line=line + int(over[0]))
            if len(ends):
                line += len(ends)
                line_start = int(ends[-1]) + 1
            if total + len(piece) - line_start > line_limit:
                raise ParseError(_too_long(line_limit), path=name, line=line)
        total += len(piece)
        if total > limit:
            raise ReadError(
                f"is more than the limit of {limit} bytes (set the environment variable "
                "NFDMATCH_MAX_FILE_BYTES to allow more)",
                path=name,
            )
        dst.write(piece)


def _too_long(limit: int) -> str:
    return f"a line longer than {limit} bytes; a row holds one vertex (2 or 3 numbers, with a header other columns)"


def check_line_lengths(data: bytes, name: str, line_limit: int) -> None:
    """Raise :class:`ParseError` naming the first line of ``data`` longer than ``line_limit``
    bytes; in pieces of 16 MiB, so the check needs little memory beyond ``data``."""
    step = 16 << 20
    line, line_start = 1, 0
    for a in range(0, len(data), step):
        view = np.frombuffer(data, dtype=np.uint8, count=min(step, len(data) - a), offset=a)
        ends = np.flatnonzero(view == 10) + a
        if len(ends):
            starts = np.concatenate([[line_start], ends[:-1] + 1])
            over = np.flatnonzero(ends - starts > line_limit)
            if len(over):
                raise ParseError(_too_long(line_limit), path=name, line=line + int(over[0]))
            line += len(ends)
            line_start = int(ends[-1]) + 1
        if min(len(data), a + step) - line_start > line_limit:
            raise ParseError(_too_long(line_limit), path=name, line=line)


#: Longest line of a CSV file, in bytes (1 MiB): a row holds one vertex. Checked before any
#: line is split (the CSV reader, and stdin's copy), so that one huge line (a hostile input of
#: hundreds of MB) fails in a second instead of being split into millions of cells.
MAX_LINE_BYTES = 1 << 20


def stdin_line_limit(format: str) -> int | None:
    """The longest line a stream of ``format`` may hold (checked while it is copied): the
    CSV reader's :data:`MAX_LINE_BYTES`; None for formats whose lines may legitimately be
    long (an OBJ ``l`` line lists a whole polyline)."""
    return MAX_LINE_BYTES if format == "csv" else None
