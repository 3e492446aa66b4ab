"""HDF5 global heap collections checked before HDF5 parses them.

Variable-length strings (``/curves/id``, ``/files/path``, ``/files/error``, ``/sources/path``;
string attributes of files written before December 2026) keep their characters in global
heap collections, the one HDF5 structure without a checksum in any file format. HDF5 parses
a whole collection when it reads one string of it, walking its objects by their stored
sizes: a size damaged to 0 (a free-space object) never advances the walk and HDF5 loops
forever (issue 34: one flipped byte, a ``query`` that never stopped). So nfdmatch walks a
collection itself, with the same rules and a walk that always advances, before HDF5 may
read it (docs/index-format.md, "Global heap collections"):

* :func:`check_string_rows`: the collections that the rows about to be read refer to (their
  references read from the dataset's raw storage, a few bytes a row);
* :func:`check_every_collection`: every collection of the file, found by its signature
  (files whose string attributes live in the global heap: their references sit in
  attribute messages that h5py does not expose).

Each collection is checked once per process and file (by device, inode, size and mtime).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import mmap
import os
import struct

import h5py
import numpy as np

if TYPE_CHECKING:
    from collections.abc import Callable, Iterable

_SIGNATURE = b"GCOL"
#: HDF5 never allocates a smaller collection (H5HG_MINSIZE)
_MIN_SIZE = 4096
_OBJECT_HEADER = 16  # object index (2), reference count (2), reserved (4), size (8)
_CHECKED: dict[tuple, set] = {}
_EVERY = -1  # in a file's set: every collection of the file was checked


class HeapProblem(Exception):
    """A global heap collection HDF5 must not parse (the message says where and why)."""


def _file_key(fd: int) -> tuple:
    st = os.fstat(fd)
    return (st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns)


def _sizes(fid) -> tuple[int, int]:
    """(size of offsets, size of lengths) of file ``fid`` (8 and 8 unless a writer chose otherwise)."""
    offsets, lengths = (int(x) for x in fid.get_create_plist().get_sizes())
    return offsets, lengths


def _fd(fid) -> int:
    return int(fid.get_vfd_handle())


def collection_problem(
    read: Callable[[int, int], bytes], address: int, file_size: int, length_size: int = 8
) -> str | None:
    """Why the collection at ``address`` would mislead HDF5, or None. ``read(offset, n)``
    returns file bytes. Walks the objects as HDF5 does (H5HG__cache_heap_deserialize): each
    object a 16-byte header then its size rounded up to 8 bytes; the free-space object
    (index 0) counts its header in its size; a tail shorter than a header is free space."""
    where = f"global heap collection at byte {address}"
    header = 8 + length_size
    if address < 0 or address + header > file_size:
        return f"{where} lies outside the {file_size}-byte file"
    head = read(address, header)
    if head[:4] != _SIGNATURE or head[4] != 1:
        return f"{where} has no collection signature"
    size = int.from_bytes(head[8:header], "little")
    if size < _MIN_SIZE or address + size > file_size:
        return f"{where} declares {size} bytes (at least {_MIN_SIZE}, within the file)"
    data = read(address, size)
    at = header
    while at < size:
        if at + _OBJECT_HEADER > size:
            break  # a tail too small for an object: free space
        index, _refs = struct.unpack_from("<HH", data, at)
        object_size = int.from_bytes(data[at + 8 : at + 8 + length_size], "little")
        need = object_size if index == 0 else _OBJECT_HEADER + (object_size + 7) // 8 * 8
        if need < _OBJECT_HEADER:
            return f"{where}: object {index} at byte {address + at} has size {object_size} (damaged)"
        if at + need > size:
            return f"{where}: object {index} at byte {address + at} runs past the collection's end"
        at += need
    return None


def _check_addresses(fid, addresses) -> None:
    fd = _fd(fid)
    checked = _CHECKED.setdefault(_file_key(fd), set())
    if _EVERY in checked:
        return
    file_size = os.fstat(fd).st_size
    _, length_size = _sizes(fid)
    for address in addresses:
        address = int(address)
        if address in checked:
            continue
        problem = collection_problem(lambda at, n: os.pread(fd, n, at), address, file_size, length_size)
        if problem:
            raise HeapProblem(problem)
        checked.add(address)


def _raw_rows(ds, a: int, b: int, item: int) -> bytes | None:
    """The stored bytes of rows [a, b) of 1-D dataset ``ds`` (``item`` bytes a row), or None
    when its layout does not say where they are (compact storage: checked another way)."""
    dcpl = ds.id.get_create_plist()
    layout = dcpl.get_layout()
    fd = _fd(ds.file.id)
    if layout == h5py.h5d.CONTIGUOUS:
        offset = ds.id.get_offset()
        if offset is None:
            return b""  # never written: fill values, no heap
        return os.pread(fd, (b - a) * item, offset + a * item)
    if layout != h5py.h5d.CHUNKED or dcpl.get_nfilters():
        return None
    rows = ds.chunks[0]
    out = []
    for first in range(a // rows * rows, b, rows):
        info = ds.id.get_chunk_info_by_coord((first,))
        if info.byte_offset is None:
            continue
        lo, hi = max(a, first), min(b, first + rows, ds.shape[0])
        out.append(os.pread(fd, (hi - lo) * item, info.byte_offset + (lo - first) * item))
    return b"".join(out)


def check_string_rows(ds: h5py.Dataset, runs: Iterable[tuple[int, int]]) -> None:
    """Check the collections that rows ``[a, b)`` of each run of variable-length string
    dataset ``ds`` refer to; raises :class:`HeapProblem`."""
    fid = ds.file.id
    fd = _fd(fid)
    if _EVERY in _CHECKED.get(_file_key(fd), ()):
        return
    address_size, _ = _sizes(fid)
    item = 4 + address_size + 4  # sequence length, collection address, object index
    n = ds.shape[0] if ds.shape else 0
    addresses: set[int] = set()
    for a, b in runs:
        a, b = max(0, int(a)), min(n, int(b))
        if b <= a:
            continue
        raw = _raw_rows(ds, a, b, item)
        if raw is None:
            check_every_collection(fid)
            return
        if len(raw) % item:
            raise HeapProblem(f"{ds.name}: stored rows of {len(raw)} bytes, not whole references")
        refs = np.frombuffer(raw, dtype=np.uint8).reshape(-1, item)
        at = np.zeros((len(refs), 8), dtype=np.uint8)
        at[:, :address_size] = refs[:, 4 : 4 + address_size]
        # an empty string has a heap object too (of size 0); address 0: no object (HDF5's nil)
        addresses.update(np.unique(at.view("<u8").ravel()).tolist())
    addresses.discard(0)
    _check_addresses(fid, sorted(addresses))


def check_every_collection(fid: h5py.h5f.FileID) -> None:
    """Check every global heap collection of file ``fid`` (an h5py FileID), each found by
    its signature and version (8 bytes: stored numbers hold them by chance about once in
    2**64 positions); raises :class:`HeapProblem`."""
    fd = _fd(fid)
    key = _file_key(fd)
    checked = _CHECKED.setdefault(key, set())
    if _EVERY in checked:
        return
    file_size = key[2]
    _, length_size = _sizes(fid)
    if file_size:
        with mmap.mmap(fd, 0, access=mmap.ACCESS_READ) as view:
            at = view.find(_SIGNATURE)
            while at >= 0:
                if view[at + 4 : at + 8] == b"\1\0\0\0":
                    problem = collection_problem(lambda o, n: view[o : o + n], at, file_size, length_size)
                    if problem:
                        raise HeapProblem(problem)
                at = view.find(_SIGNATURE, at + 1)
    checked.add(_EVERY)
