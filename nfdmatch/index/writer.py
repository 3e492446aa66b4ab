"""Writing a new index file: the /curves and /files datasets, fsync, temporary files.

Test hook: ``write_files_table`` (writes the /files table) is called by tests with
crafted records and replaced, where :mod:`.commit` looks it up, to act out a full disk.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import errno
import os
import re

import numpy as np

from ..errors import MAX_MESSAGE_CHARS, excerpt
from ..matching.statistics import curve_statistics
from .schema import _SHA, STR, CRC_ROWS, FileRecord, curve_layout, block_crcs, create_checked, fill_value, set_text

if TYPE_CHECKING:
    import h5py
    from collections.abc import Sequence
    from .reader import Index

#: rows per HDF5 chunk of the /curves datasets (any layout is valid for readers)
CHUNK_ROWS = 4096
#: smaller chunks for what a search reads row by row (descriptors of the rows that need an
#: exact distance, ids of the answers; the invariant features of the objects a mesh query
#: bounds): a scattered read then touches 96 KB per row, not 1.5 MB (16 scattered rows of
#: 1M: 1.6 ms instead of 16 ms; 534 objects' features of 100,000: 20 MB, not 300 MB)
_SCATTERED_CHUNK_ROWS = {"coefficients": 256, "id": 256, "inv_sv": 256, "inv_block": 256}
#: rows buffered before one write per dataset
_WRITE_ROWS = 65536


#: bytes reserved beyond each estimate (HDF5's metadata: B-trees, heaps, the superblock)
_SLACK = 1 << 20


class Space:
    """Disk space for a new index file, reserved before HDF5 writes into it.

    HDF5 does not survive a failed write: after ENOSPC (or EFBIG, EIO) its file can no longer
    be closed, the library keeps retrying the write and the process crashes at exit
    (SIGSEGV). So the space for each large write is reserved first (``fallocate``, keeping
    the file size; within ``ulimit -f``), and a full disk is an ``OSError`` raised here,
    before HDF5 tries. :meth:`abandon` then points HDF5's file descriptor at memory so that
    closing the dead file cannot fail either. File systems without ``fallocate`` are
    written unreserved (as before)."""

    def __init__(self, h5: h5py.File) -> None:
        try:
            self.fd = int(h5.id.get_vfd_handle())
        except Exception:  # another driver: nothing to reserve on
            self.fd = None
        self.reserved = 0
        self.abandoned = False

    def reserve(self, nbytes: int) -> None:
        """Make sure twice ``nbytes`` more (plus slack) can be written; OSError when not."""
        if self.fd is None:
            return
        want = max(os.fstat(self.fd).st_size, self.reserved) + 2 * int(nbytes) + _SLACK
        if want <= self.reserved:
            return
        import resource

        soft = resource.getrlimit(resource.RLIMIT_FSIZE)[0]
        if soft != resource.RLIM_INFINITY and want > soft:
            raise OSError(errno.EFBIG, f"{os.strerror(errno.EFBIG)} (the file-size limit, ulimit -f)")
        code = _fallocate_keep_size(self.fd, want)
        if code in (errno.EOPNOTSUPP, errno.ENOSYS, errno.EINVAL, errno.ENODEV):
            self.fd = None
            return
        if code:
            raise OSError(code, os.strerror(code))
        self.reserved = want

    def abandon(self) -> None:
        """The file is given up: HDF5's later writes (while closing it) go to memory."""
        if self.fd is None or self.abandoned:
            return
        self.abandoned = True
        try:
            mem = os.memfd_create("nfdmatch-abandoned-index")
        except (AttributeError, OSError):
            mem = os.open(os.devnull, os.O_RDWR)
        try:
            os.dup2(mem, self.fd)
        except OSError:
            pass
        finally:
            os.close(mem)

    @staticmethod
    def release(path: str) -> None:
        """Free the reserved blocks beyond the end of the closed file."""
        try:
            os.truncate(path, os.path.getsize(path))
        except OSError:
            pass


def _fallocate_keep_size(fd: int, length: int) -> int:
    """``fallocate(fd, FALLOC_FL_KEEP_SIZE, 0, length)``; 0 or the errno."""
    import ctypes
    import ctypes.util

    global _LIBC
    if _LIBC is None:
        try:
            _LIBC = ctypes.CDLL(ctypes.util.find_library("c") or None, use_errno=True)
            _LIBC.fallocate.argtypes = [ctypes.c_int, ctypes.c_int, ctypes.c_longlong, ctypes.c_longlong]  # type: ignore[attr-defined]
        except (OSError, AttributeError):
            _LIBC = False
    if not _LIBC:
        return errno.ENOSYS
    if _LIBC.fallocate(fd, 1, 0, length) == 0:
        return 0
    return ctypes.get_errno() or errno.EIO


_LIBC = None


def _nbytes(piece: dict) -> int:
    """Bytes a piece of rows takes in the file (strings: their UTF-8 length plus heap overhead)."""
    total = 0
    for value in piece.values():
        value = np.asarray(value)
        if value.dtype == object:
            strings = [v if type(v) is str else str(v) for v in value.reshape(-1).tolist()]
            total += len("".join(strings).encode("utf-8", "surrogateescape")) + 32 * len(strings)
        else:
            total += value.nbytes
    return total


class CurveWriter:
    """Appends rows to resizable /curves datasets with few large writes.

    The datasets are created at the first write, chunked by ``min(CHUNK_ROWS, rows of that
    write)`` rows, so that a small index is not padded to whole large chunks. ``space``: a
    :class:`Space` that each write reserves its bytes in first."""

    def __init__(self, h5: h5py.File, K: int, space: Space | None = None) -> None:
        self.group = h5.create_group("curves")
        self.space = space
        self.K = K
        self.ds = None
        self.pending: list[dict] = []
        self.pending_rows = 0
        self.rows = 0
        #: CRC-32 blocks of the ids written so far (/curves/id_crc32, computed as they are
        #: written rather than read back), and the ids of the unfinished last block
        self._id_crcs: list[np.ndarray] = []
        self._id_tail: list = []

    def _create(self, first_rows: int) -> None:
        self.ds = {}
        for name, (dtype, tail) in curve_layout(self.K).items():
            chunk = max(1, min(_SCATTERED_CHUNK_ROWS.get(name, CHUNK_ROWS), first_rows))
            # Fletcher-32 per chunk: a damaged chunk fails when read (HDF5 filters no strings)
            self.ds[name] = self.group.create_dataset(
                name,
                shape=(0,) + tail,
                maxshape=(None,) + tail,
                chunks=(chunk,) + tail,
                dtype=dtype,
                fletcher32=dtype is not STR,
                fillvalue=fill_value(dtype),
            )

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
        if self.space is not None:
            self.space.reserve(sum(_nbytes(p) for p in self.pending))
        for name, ds in self.ds.items():  # type: ignore[attr-defined]
            parts = [p[name] for p in self.pending]
            data = parts[0] if len(parts) == 1 else np.concatenate(parts)
            ds.resize(self.rows + n, axis=0)
            ds[self.rows : self.rows + n] = data
            if name == "id":
                self._check_ids(data)
        self.rows += n
        self.pending, self.pending_rows = [], 0

    def _check_ids(self, ids) -> None:
        if self._id_crcs is None:
            return
        values = self._id_tail + np.asarray(ids, dtype=object).reshape(-1).tolist()
        if any(type(v) is not str for v in values):
            self._id_crcs = None  # read back from the file at the end instead
            return
        whole = len(values) - len(values) % CRC_ROWS
        if whole:
            self._id_crcs.append(block_crcs(values[:whole]))
        self._id_tail = values[whole:]

    def id_crcs(self) -> np.ndarray | None:
        """``/curves/id_crc32`` of the ids written (:func:`~.schema.block_crcs`), or None when
        some id was not a ``str`` (then they are read back from the file)."""
        if self._id_crcs is None:
            return None
        values = self._id_tail
        if any(type(v) is not str for v in values):
            return None
        parts = self._id_crcs + ([block_crcs(values)] if values else [])
        return np.concatenate(parts) if parts else np.zeros(0, dtype=np.uint32)


def write_files_table(h5: h5py.File, records: list[FileRecord], space: Space | None = None) -> None:
    g = h5.create_group("files")
    F = len(records)
    if space is not None:
        space.reserve(
            sum(
                len(r.path.encode("utf-8", "surrogateescape")) + len(r.error.encode("utf-8", "replace")) + 200
                for r in records
            )
        )
    checked = {
        "path": ([r.path for r in records], STR),
        "size": ([r.size for r in records], np.int64),
        "mtime_ns": ([r.mtime_ns for r in records], np.int64),
        "sha256": ([r.sha256.encode("ascii") for r in records], _SHA),
        "status": ([0 if r.status == "ok" else 1 for r in records], np.uint8),
        # cut here too: a message from outside NfdError (a worker's crash) is stored as is
        "error": ([excerpt(r.error, MAX_MESSAGE_CHARS) for r in records], STR),
        "curve_start": ([r.curve_start for r in records], np.int64),
        "curve_count": ([r.curve_count for r in records], np.int64),
    }
    for name, (values, dtype) in checked.items():
        create_checked(g, name, np.array(values, dtype=object if dtype is STR else dtype).reshape(F), dtype)


def write_sources(h5: h5py.File, paths: list[str], glob: str | None, exclude: Sequence[str] = ()) -> None:
    """/sources: the stored sources of this build, its glob and the stored paths its walk
    leaves out (written only when there are some; docs/index-format.md)."""
    g = h5.create_group("sources")
    create_checked(g, "path", np.array(list(paths), dtype=object), STR)
    set_text(g.attrs, "glob", glob or "")
    if exclude:
        create_checked(g, "exclude", np.array(list(exclude), dtype=object), STR)


def fsync_path(path: str, directory: bool = False, strict: bool = False) -> None:
    """fsync ``path``. ``strict``: a failure raises (the new index's own data: a full disk
    can surface only here); else it is ignored (a folder's fsync is best effort)."""
    try:
        fd = os.open(path, os.O_RDONLY | (getattr(os, "O_DIRECTORY", 0) if directory else 0))
    except OSError:
        if strict:
            raise
        return
    try:
        os.fsync(fd)
    except OSError:
        if strict:
            raise
    finally:
        os.close(fd)


def _temp_pattern(index_path: str):
    name = os.path.basename(index_path)
    return re.compile(rf"^\.{re.escape(name)}\.tmp-\d+-[0-9a-f]+\.h5$")


def remove_stale_temps(index_path: str) -> list[str]:
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


class CopyRun:
    """Rows copied from the old index, merged into contiguous runs (one read per run)."""

    def __init__(self, old: Index, writer: CurveWriter) -> None:
        self.old, self.writer = old, writer
        self.start = self.stop = 0
        self.file_rows: list[int] = []
        self.counts: list[int] = []
        self.ids: list = []

    @property
    def rows(self) -> int:
        return self.stop - self.start

    def add(self, start: int, count: int, file_row: int, ids: list | None = None) -> None:
        """Copy old rows ``[start, start + count)`` as file ``file_row``; ``ids``: new ids for
        them (a file whose stored path changed), None to keep the stored ones."""
        if count == 0:
            return
        if self.rows and start != self.stop:
            self.flush()
        if not self.rows:
            self.start = self.stop = start
            self.file_rows, self.counts, self.ids = [], [], []
        self.stop += count
        self.file_rows.append(file_row)
        self.counts.append(count)
        self.ids.append(ids)
        if self.rows >= _WRITE_ROWS:
            self.flush()

    def flush(self) -> None:
        if not self.rows:
            return
        file_col = np.repeat(np.asarray(self.file_rows, dtype=np.int32), self.counts)
        new_ids = None
        if any(ids is not None for ids in self.ids):
            new_ids, at = [], self.start
            for count, ids in zip(self.counts, self.ids):
                new_ids.extend(self.old.ids(at, at + count) if ids is None else ids)
                at += count
            new_ids = np.asarray(new_ids, dtype=object)
        for a in range(self.start, self.stop, _WRITE_ROWS):
            b = min(self.stop, a + _WRITE_ROWS)
            piece = self.old._raw_rows(a, b)
            if "statistics" not in piece:  # an index of format 1 or 2, upgraded
                statistics = curve_statistics(np.asarray(piece["coefficients"], dtype=np.complex128))
                piece["statistics"] = statistics.reshape(b - a, -1).astype(np.float32)
            piece["file"] = file_col[a - self.start : b - self.start]
            if new_ids is not None:
                piece["id"] = new_ids[a - self.start : b - self.start]
            self.writer.append(piece)
        self.start = self.stop = 0
        self.file_rows, self.counts, self.ids = [], [], []
