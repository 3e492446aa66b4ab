"""Writing a new index file: the /curves and /files datasets, fsync, temporary files."""

from __future__ import annotations

import os
import re

import numpy as np

from ..errors import MAX_MESSAGE_CHARS, excerpt
from .schema import _SHA, _STR, FileRecord, _curve_layout, create_checked

#: rows per HDF5 chunk of the /curves datasets (any layout is valid for readers)
CHUNK_ROWS = 4096
#: smaller chunks for what a search reads row by row (descriptors of the rows that need an
#: exact distance, ids of the answers): a scattered read then touches 96 KB per row, not
#: 1.5 MB (16 scattered rows of 1M: 1.6 ms instead of 16 ms)
_SCATTERED_CHUNK_ROWS = {"coefficients": 256, "id": 256}
#: rows buffered before one write per dataset
_WRITE_ROWS = 65536


class _CurveWriter:
    """Appends rows to resizable /curves datasets with few large writes.

    The datasets are created at the first write, chunked by ``min(CHUNK_ROWS, rows of that
    write)`` rows, so that a small index is not padded to whole large chunks."""

    def __init__(self, h5, K: int):
        self.group = h5.create_group("curves")
        self.K = K
        self.ds = None
        self.pending: list[dict] = []
        self.pending_rows = 0
        self.rows = 0

    def _create(self, first_rows: int) -> None:
        self.ds = {}
        for name, (dtype, tail) in _curve_layout(self.K).items():
            chunk = max(1, min(_SCATTERED_CHUNK_ROWS.get(name, CHUNK_ROWS), first_rows))
            # Fletcher-32 per chunk: a damaged chunk fails when read (HDF5 filters no strings)
            self.ds[name] = self.group.create_dataset(name, shape=(0,) + tail, maxshape=(None,) + tail,
                                                      chunks=(chunk,) + tail, dtype=dtype,
                                                      fletcher32=dtype is not _STR)

    def append(self, piece: dict) -> None:
        n = len(piece["file"])
        if n == 0:
            return
        self.pending.append(piece)
        self.pending_rows += n
        if self.pending_rows >= _WRITE_ROWS:
            self.flush()

    def flush(self) -> None:
        if self.ds is None:
            self._create(self.pending_rows)
        if not self.pending:
            return
        n = self.pending_rows
        for name, ds in self.ds.items():
            parts = [p[name] for p in self.pending]
            data = parts[0] if len(parts) == 1 else np.concatenate(parts)
            ds.resize(self.rows + n, axis=0)
            ds[self.rows:self.rows + n] = data
        self.rows += n
        self.pending, self.pending_rows = [], 0


def _write_files_table(h5, records: list[FileRecord]) -> None:
    g = h5.create_group("files")
    F = len(records)
    checked = {"path": ([r.path for r in records], _STR), "size": ([r.size for r in records], np.int64),
               "mtime_ns": ([r.mtime_ns for r in records], np.int64),
               "sha256": ([r.sha256.encode("ascii") for r in records], _SHA),
               "status": ([0 if r.status == "ok" else 1 for r in records], np.uint8),
               # cut here too: a message from outside NfdError (a worker's crash) is stored as is
               "error": ([excerpt(r.error, MAX_MESSAGE_CHARS) for r in records], _STR),
               "curve_start": ([r.curve_start for r in records], np.int64),
               "curve_count": ([r.curve_count for r in records], np.int64)}
    for name, (values, dtype) in checked.items():
        create_checked(g, name, np.array(values, dtype=object if dtype is _STR else dtype).reshape(F), dtype)


def _fsync_path(path: str, directory: bool = False) -> None:
    try:
        fd = os.open(path, os.O_RDONLY | (getattr(os, "O_DIRECTORY", 0) if directory else 0))
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def _temp_pattern(index_path: str):
    name = os.path.basename(index_path)
    return re.compile(rf"^\.{re.escape(name)}\.tmp-\d+-[0-9a-f]+\.h5$")


def _remove_stale_temps(index_path: str) -> list[str]:
    """Temporary files of builds into this index that were killed (call with the lock held)."""
    folder = os.path.dirname(index_path) or "."
    pattern = _temp_pattern(index_path)
    removed = []
    try:
        names = os.listdir(folder)
    except OSError:
        return removed
    for name in names:
        if pattern.match(name):
            try:
                os.unlink(os.path.join(folder, name))
                removed.append(os.path.join(folder, name))
            except OSError:
                pass
    return removed


class _CopyRun:
    """Rows copied from the old index, merged into contiguous runs (one read per run)."""

    def __init__(self, old, writer: _CurveWriter):
        self.old, self.writer = old, writer
        self.start = self.stop = 0
        self.file_rows: list[int] = []
        self.counts: list[int] = []

    @property
    def rows(self) -> int:
        return self.stop - self.start

    def add(self, start: int, count: int, file_row: int) -> None:
        if count == 0:
            return
        if self.rows and start != self.stop:
            self.flush()
        if not self.rows:
            self.start = self.stop = start
            self.file_rows, self.counts = [], []
        self.stop += count
        self.file_rows.append(file_row)
        self.counts.append(count)
        if self.rows >= _WRITE_ROWS:
            self.flush()

    def flush(self) -> None:
        if not self.rows:
            return
        file_col = np.repeat(np.asarray(self.file_rows, dtype=np.int32), self.counts)
        for a in range(self.start, self.stop, _WRITE_ROWS):
            b = min(self.stop, a + _WRITE_ROWS)
            piece = self.old._raw_rows(a, b)
            piece["file"] = file_col[a - self.start:b - self.start]
            self.writer.append(piece)
        self.start = self.stop = 0
        self.file_rows, self.counts = [], []
