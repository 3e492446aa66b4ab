"""The index file format: names, dataset layout and dtypes, and opening with validation."""

from __future__ import annotations

from typing import Any, TYPE_CHECKING

import os
import stat as _stat
from dataclasses import dataclass

import h5py
import numpy as np

from ..defaults import default_index_path  # noqa: F401  (re-exported: nfdmatch.index.default_index_path)
from ..descriptors import validate_parameters
from ..errors import ParameterError, ReadError
from ..matching.statistics import LENGTH as STATISTICS_LENGTH
from .heap import check_every_collection
from .search_layout import check_search_group, not_numbers

if TYPE_CHECKING:
    from collections.abc import Sequence
    from numpy.typing import DTypeLike, NDArray

INDEX_FORMAT = "nfdmatch-index"
FORMAT_VERSION = 3
#: format versions this code reads (format 1: no /search group; queries scan every row;
#: formats 1 and 2: no /curves/statistics, the elastic stage computes them on read, and no
#: /objects group, meshes were not indexed)
READABLE_VERSIONS = (1, 2, 3)

_HDF5_SIGNATURE = b"\x89HDF\r\n\x1a\n"
STR = h5py.string_dtype("utf-8")
_SHA = "S64"
STATUS = {0: "ok", 1: "failed"}

FILE_FIELDS = ("path", "size", "mtime_ns", "sha256", "status", "error", "curve_start", "curve_count")
#: the type of each /files dataset, in the order of FILE_FIELDS
_FILE_DTYPES = (STR, np.int64, np.int64, _SHA, np.uint8, STR, np.int64, np.int64)

# --------------------------------------------------------------------------- integrity
#: root attribute ``checksums``: every dataset has HDF5's Fletcher-32 filter, every string
#: dataset a ``NAME_crc32`` companion (docs/index-format.md, "Checksums")
CHECKSUMS = "fletcher32+crc32"
#: rows per CRC-32 block of a string dataset (divides the /curves/id chunk rows; small, because
#: a query decodes whole blocks to check the ids it prints: 10 answers, ~320 strings)
CRC_ROWS = 32
#: string datasets with a ``NAME_crc32`` companion, per group
STRING_DATASETS = {"curves": ("id",), "files": ("path", "error")}
#: sane limits checked before any allocation (docs/index-format.md, "Limits")
MAX_SAMPLES = 1 << 20
MAX_CHUNK_BYTES = 64 << 20
#: declared bytes per stored byte allowed for a compressed dataset (deflate tops out ~1032)
_MAX_COMPRESSION = 1100
#: HDF5 filters that only check or reorder bytes (no compression)
_PLAIN_FILTERS = {h5py.h5z.FILTER_FLETCHER32, h5py.h5z.FILTER_SHUFFLE}
_CHUNK_ROWS = 4096


def block_crcs(values: Sequence[str], rows: int = CRC_ROWS) -> NDArray[np.uint32]:
    """(ceil(len(values) / rows),) uint32: CRC-32 of each block of ``rows`` strings, every
    string's UTF-8 bytes followed by one NUL (the ``NAME_crc32`` companion datasets)."""
    import zlib

    values = list(values)
    out = np.empty((len(values) + rows - 1) // rows, dtype=np.uint32)
    if len(values) > rows and all(type(v) is str for v in values):
        # one encode of everything; blocks cut at every rows-th NUL (when no string holds a NUL)
        data = ("\0".join(values) + "\0").encode("utf-8", "surrogateescape")
        nul = np.flatnonzero(np.frombuffer(data, dtype=np.uint8) == 0)
        if len(nul) == len(values):
            ends = np.append(nul[rows - 1 :: rows] + 1, len(data))[: len(out)].tolist()
            view = memoryview(data)
            start = 0
            for b, end in enumerate(ends):
                out[b] = zlib.crc32(view[start:end])
                start = end
            return out
    for b in range(len(out)):
        block = values[b * rows : (b + 1) * rows]
        out[b] = zlib.crc32(b"".join(v.encode("utf-8", "surrogateescape") + b"\0" for v in block))
    return out


def create_checked(
    group: h5py.Group,
    name: str,
    data: Any,
    dtype: DTypeLike = None,
    *,
    chunk_rows: int = _CHUNK_ROWS,
    chunk_columns: int = 0,
) -> h5py.Dataset:
    """Create dataset ``name`` in ``group`` holding ``data`` (rows along axis 0), with the
    checksums of the format: numbers chunked with Fletcher-32 (``chunk_rows`` rows and, if
    given, ``chunk_columns`` along the second axis per chunk); strings (HDF5 does not filter
    variable-length data) plain, plus their ``NAME_crc32`` block checksums."""
    data = np.asarray(data) if dtype is None else np.asarray(data, dtype=dtype if dtype is not STR else object)
    if dtype is STR:
        ds = group.create_dataset(name, data=data, dtype=STR, shape=data.shape)
        write_string_checks(group, name, data.tolist())
        return ds
    rows = max(1, min(chunk_rows, data.shape[0] if data.ndim else 1))
    chunks = (rows,) + tuple(max(1, x) for x in data.shape[1:]) if data.ndim else None
    if chunk_columns and data.ndim > 1:
        chunks = (rows, max(1, min(chunk_columns, data.shape[1]))) + chunks[2:]
    # an empty dataset can be chunked only when resizable
    maxshape = (None,) + data.shape[1:] if data.ndim and not data.shape[0] else None
    return group.create_dataset(
        name,
        data=data,
        dtype=dtype or data.dtype,
        shape=data.shape,
        chunks=chunks,
        maxshape=maxshape,
        fletcher32=True,
        fillvalue=fill_value(dtype or data.dtype),
    )


def fill_value(dtype: DTypeLike) -> Any:
    """The fill value nfdmatch gives a new dataset of ``dtype``: NaN for floats (NaN + NaN j
    for complex), so that a chunk HDF5 cannot find (damaged chunk index) reads as NaN, which
    every reader refuses, instead of zeros; None (HDF5's default) for other types."""
    kind = np.dtype(dtype).kind if dtype is not STR else "O"
    if kind == "f":
        return np.nan
    if kind == "c":
        return complex(np.nan, np.nan)
    return None


def _chunk_problem(ds, where: str, walk: bool = True) -> str | None:
    """Why the chunk index of chunked dataset ``ds`` does not hold exactly one chunk at each
    position of its chunk grid, or None. A damaged chunk index can lose a chunk or move it
    (a flipped byte in a chunk's stored offset): HDF5 then returns the fill value for the
    place it left, with no error, and that is not data. Reads the index only (no chunk).
    ``walk``: also check every chunk's position (~2-4 us a chunk, needed where the index
    stores offsets: files of HDF5's older structures); else only the count."""
    shape, chunks = ds.shape, ds.chunks
    grid = [-(-n // c) for n, c in zip(shape, chunks)]
    expected = int(np.prod(grid, dtype=np.int64))
    dsid = ds.id
    count = int(dsid.get_num_chunks())
    if count != expected:
        return f"{where} has {count} stored chunks, expected {expected} for its shape {shape}: damaged chunk index"
    if not expected or not walk:
        return None
    offsets = []
    if hasattr(dsid, "chunk_iter"):
        dsid.chunk_iter(lambda info: offsets.append(info.chunk_offset))
    else:  # pragma: no cover - HDF5 before 1.12.3
        offsets = [dsid.get_chunk_info(i).chunk_offset for i in range(count)]
    if len(offsets) != expected:
        return f"{where} lists {len(offsets)} chunks, expected {expected}: damaged chunk index"
    at = np.asarray(offsets, dtype=np.int64).reshape(len(offsets), len(shape))
    step = np.asarray(chunks, dtype=np.int64)
    if (at % step).any() or (at < 0).any() or (at >= np.asarray(shape, dtype=np.int64)).any():
        return f"{where} has a chunk at a position outside its chunk grid: damaged chunk index"
    cells = at // step
    flat = np.ravel_multi_index(tuple(cells.T), grid)
    if len(np.unique(flat)) != expected:
        return f"{where} has two chunks at one position: damaged chunk index"
    return None


def write_string_checks(group: h5py.Group, name: str, values: Sequence[str]) -> None:
    """The ``NAME_crc32`` companion of string dataset ``name`` (values: its strings in row order)."""
    group.create_dataset(f"{name}_crc32", data=block_crcs(values), chunks=True, fletcher32=True)


def check_stored(ds: h5py.Dataset, where: str, file_size: int, checksums: bool) -> str | None:
    """Why dataset ``ds`` (at path ``where``) cannot be read safely, from its metadata only, or None.

    Refuses external storage and virtual datasets (their bytes live in other files), a
    declared size the file cannot hold (uncompressed: the allocated storage must cover every
    declared byte; compressed: at most :data:`_MAX_COMPRESSION` times the stored bytes),
    chunks above :data:`MAX_CHUNK_BYTES`, when the file declares checksums, a numeric
    dataset without Fletcher-32, and a chunk index that does not hold exactly one chunk per
    position of the chunk grid (:func:`_chunk_problem`)."""
    if ds.is_virtual:
        return f"{where} is a virtual dataset (data in other files): refused"
    dcpl = ds.id.get_create_plist()
    if dcpl.get_external_count() > 0:
        return f"{where} has external storage (data in another file): refused"
    vlen = ds.dtype.kind == "O"
    itemsize = 16 if vlen else ds.dtype.itemsize  # variable length: 16-byte heap references
    declared = int(np.prod(ds.shape, dtype=np.float64)) * itemsize
    if ds.chunks is not None:
        chunk_bytes = int(np.prod(ds.chunks, dtype=np.float64)) * itemsize
        if chunk_bytes > MAX_CHUNK_BYTES:
            return f"{where} has chunks of {chunk_bytes} bytes (at most {MAX_CHUNK_BYTES})"
    filters = {dcpl.get_filter(i)[0] for i in range(dcpl.get_nfilters())}
    stored = int(ds.id.get_storage_size())
    if declared:
        if filters - _PLAIN_FILTERS:
            if declared > _MAX_COMPRESSION * max(stored, 1):
                return (
                    f"{where} declares {declared} bytes ({ds.shape}) in {stored} stored bytes, "
                    f"more than any compression gives"
                )
        elif stored < declared:
            return (
                f"{where} declares {ds.shape} ({declared} bytes) but stores {stored} bytes of a {file_size}-byte file"
            )
    if checksums and not vlen and h5py.h5z.FILTER_FLETCHER32 not in filters:
        return f"{where} has no checksum filter, but the file declares checksums"
    if ds.chunks is not None:
        return _chunk_problem(ds, where, walk=not _positional_chunks(ds))
    return None


def checked_metadata(h5: h5py.File) -> bool:
    """Whether HDF5 parses nothing of file ``h5`` before a check: HDF5 1.10's structures
    (superblock 3: checksummed metadata) and no root attribute in the unchecksummed global
    heap (variable-length strings; heap.py checks the heap collections of the string
    datasets as rows are read). nfdmatch writes such files since issue 34; others are read
    after a check of every heap collection of the file, and a build rewrites them."""
    try:
        if h5.id.get_create_plist().get_version()[0] < 3:
            return False
        return not any(heap_attribute(h5.attrs, name) for name in h5.attrs.keys())
    except Exception:  # noqa: BLE001 - unknown: the older kind
        return False


def _positional_chunks(ds) -> bool:
    """True when ``ds``'s file has HDF5 1.10's structures (superblock version 3, which nfdmatch
    writes since December 2026): chunk indexes then find a chunk by its position (fixed and
    extensible arrays; no stored offset a flipped byte could change) and carry checksums."""
    try:
        return ds.file.id.get_create_plist().get_version()[0] >= 3
    except Exception:  # noqa: BLE001 - unknown: walk the chunk index
        return False


def curve_layout(K: int, version: int = FORMAT_VERSION) -> dict:
    """/curves dataset name -> (storage dtype, shape after the row axis), in format ``version``."""
    layout = {
        "id": (STR, ()),
        "file": (np.int32, ()),
        "coefficients": (np.complex64, (K, 3)),
        "rotation": (np.float32, (3, 3)),
        "centroid": (np.float64, (3,)),
        "scale": (np.float64, ()),
        "plane_degenerate": (np.uint8, ()),
        "inv_norm": (np.float32, (K,)),
        "inv_sv": (np.float32, (2 * K,)),
        "inv_block": (np.float32, (3,)),
    }
    if version >= 3:
        layout["statistics"] = (np.float32, (STATISTICS_LENGTH,))
    return layout


@dataclass(frozen=True)
class FileRecord:
    """One row of the ``/files`` table.

    ``status`` is ``"ok"`` or ``"failed"``; ``error`` is ``""`` when ok; the file's
    curves are index rows ``[curve_start, curve_start + curve_count)``.
    """

    path: str
    size: int
    mtime_ns: int
    sha256: str
    status: str
    error: str
    curve_start: int
    curve_count: int


# --------------------------------------------------------------------------- opening


class Problem(Exception):
    """Why a file is not a readable index; ``kind`` drives what a build may do with it:
    ``empty``, ``not_hdf5``, ``foreign``, ``unopenable`` (HDF5 that does not open: never
    overwritten), ``corrupt``, ``newer``."""

    def __init__(self, kind: str, message: str) -> None:
        super().__init__(message)
        self.kind, self.message = kind, message


def _short(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
    return text[:200]


def _has_hdf5_signature(path: str) -> bool:
    """The HDF5 signature at offset 0, 512, 1024, 2048, ... (where HDF5 looks for it)."""
    try:
        with open(path, "rb") as fh:
            size = os.fstat(fh.fileno()).st_size
            offset = 0
            while offset + 8 <= size:
                fh.seek(offset)
                if fh.read(8) == _HDF5_SIGNATURE:
                    return True
                offset = 512 if offset == 0 else offset * 2
    except OSError:
        return False
    return False


def set_text(attrs: h5py.AttributeManager, name: str, value: str) -> None:
    """Attribute ``name`` = ``value`` as a fixed-length UTF-8 string: its characters stay in
    the (checksummed) object header, never in the global heap (heap.py)."""
    data = value.encode("utf-8")
    attrs.create(name, np.bytes_(data), dtype=h5py.string_dtype("utf-8", max(1, len(data))))


def heap_attribute(attrs: h5py.AttributeManager, name: str) -> bool:
    """Whether attribute ``name`` keeps its value in the global heap (variable length)."""
    tid = attrs.get_id(name).get_type()
    return isinstance(tid, h5py.h5t.TypeVlenID) or (isinstance(tid, h5py.h5t.TypeStringID) and tid.is_variable_str())


def text_attr(attrs: h5py.AttributeManager, name: str) -> str | None:
    """String attribute ``name`` (None when absent or not a string). One whose value lives in
    the global heap is read only after every heap collection of the file passed
    :func:`~nfdmatch.index.heap.check_every_collection` (raises HeapProblem)."""
    if name not in attrs:
        return None
    if heap_attribute(attrs, name):
        check_every_collection(h5py.h5i.get_file_id(attrs.get_id(name)))
    value = attrs.get(name)
    if value is None:
        return None
    if isinstance(value, np.ndarray) and value.shape == ():
        value = value[()]
    if isinstance(value, bytes):
        return value.decode("utf-8", "replace")
    return value if isinstance(value, str) else None


def _attr_int(attrs, name):
    value = attrs.get(name)
    if isinstance(value, np.ndarray) and value.shape in ((), (1,)):
        value = value.reshape(())[()]
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
        return None
    return int(value)


def open_checked(path: str) -> tuple[h5py.File, dict[str, Any], dict[str, Any]]:
    """Open ``path`` read-only and validate it as a format-1 or format-2 index.

    Returns ``(h5py.File, meta dict, files dict of arrays)``.
    Raises ReadError (missing, directory, unreadable) or Problem.
    """
    try:
        st = os.stat(path)
    except FileNotFoundError:
        raise ReadError(f"no index at {path}; build one with `nfdmatch index build`") from None
    except OSError as exc:
        raise ReadError(f"cannot read the index: {exc.strerror or exc}", path=path) from None
    if _stat.S_ISDIR(st.st_mode):
        raise ReadError("is a directory, not an index file", path=path)
    try:
        with open(path, "rb"):
            pass
    except OSError as exc:
        raise ReadError(f"cannot read the index: {exc.strerror or exc}", path=path) from None
    if st.st_size == 0:
        raise Problem("empty", "empty file, not an nfdmatch index")
    try:
        h5 = h5py.File(path, "r", locking=False)
    except Exception as exc:  # h5py raises OSError, sometimes others, for damaged files
        if not _has_hdf5_signature(path):
            raise Problem("not_hdf5", "not an nfdmatch index (not an HDF5 file)") from None
        raise Problem("unopenable", f"truncated or corrupted HDF5 file ({_short(exc)})") from None
    try:
        meta, files = _validate(h5)
    except Problem:
        h5.close()
        raise
    except Exception as exc:
        h5.close()
        if "filter returned failure" in _short(exc):  # a Fletcher-32 mismatch
            raise Problem(
                "corrupt", "corrupted nfdmatch index: checksum mismatch in the file table (/files; the file is damaged)"
            ) from None
        raise Problem("corrupt", f"corrupted nfdmatch index ({_short(exc)})") from None
    return h5, meta, files


def _validate(h5) -> tuple[dict, dict]:
    """``(meta, files)`` of an open index after checking its attributes, the shapes and
    lengths of its tables, their checksum datasets, the /files blocks and /search; raises
    Problem at the first fault."""
    meta = _root_attributes(h5.attrs)
    meta["checked_metadata"] = checked_metadata(h5)
    file_size = int(h5.id.get_filesize())
    checksums = meta["checksums"]

    def dataset(group, name, tail):
        return _shaped_dataset(h5, group, name, tail, file_size, checksums)

    fds, cds = _tables(dataset, meta["harmonics"], checksums, meta["format_version"])
    F, N = fds["path"].shape[0], cds["id"].shape[0]
    if cds["coefficients"].dtype.kind != "c":
        raise Problem("corrupt", "corrupted nfdmatch index: /curves/coefficients is not complex")
    counts = fds["curve_count"][...].astype(np.int64)
    starts = fds["curve_start"][...].astype(np.int64)
    expected = np.concatenate([[0], np.cumsum(counts)[:-1]]) if F else starts
    if (counts < 0).any() or not np.array_equal(starts, expected) or int(counts.sum()) != N:
        raise Problem(
            "corrupt",
            "corrupted nfdmatch index: the /files curve_start/curve_count blocks do not tile the /curves rows",
        )
    if meta["format_version"] >= 2:
        problem = check_search_group(
            h5, int(N), meta["harmonics"], lambda name: stored_dataset(h5, f"search/{name}", file_size, checksums)
        )
        if problem:
            raise Problem("corrupt", f"corrupted nfdmatch index: {problem}")
    files = {
        "datasets": {k: v for k, v in fds.items() if k in FILE_FIELDS},
        "curve_start": starts,
        "curve_count": counts,
        "crc": {k: v for k, v in fds.items() if k.endswith("_crc32")},
    }
    meta["crc"] = {k: v for k, v in cds.items() if k.endswith("_crc32")}
    meta["datasets"] = {k: v for k, v in cds.items() if not k.endswith("_crc32")}
    meta["n_curves"], meta["n_files"] = int(N), int(F)
    return meta, files


def _root_attributes(attrs) -> dict:
    """The checked root attributes of an index (format, version, descriptor parameters,
    checksums) as the start of its ``meta``; raises Problem."""
    fmt = text_attr(attrs, "format")
    if fmt != INDEX_FORMAT:
        what = "no 'format' attribute" if fmt is None else f"format attribute {fmt!r}"
        raise Problem("foreign", f"an HDF5 file but not an nfdmatch index ({what})")
    version = _attr_int(attrs, "format_version")
    if version is None or version < 1:
        raise Problem("corrupt", f"corrupted nfdmatch index: bad format_version {attrs.get('format_version')!r}")
    if version > FORMAT_VERSION:
        raise Problem(
            "newer",
            f"written by a newer nfdmatch (format {version}); "
            f"this version reads formats {', '.join(map(str, READABLE_VERSIONS[:-1]))} and {READABLE_VERSIONS[-1]}",
        )
    samples, harmonics, scale = _attr_int(attrs, "samples"), _attr_int(attrs, "harmonics"), text_attr(attrs, "scale")
    try:
        validate_parameters(samples, harmonics, scale)
    except ParameterError as exc:
        raise Problem("corrupt", f"corrupted nfdmatch index: {exc.message}") from None
    if samples > MAX_SAMPLES:
        raise Problem("corrupt", f"corrupted nfdmatch index: samples {samples} above the limit {MAX_SAMPLES}")
    checksums_attr = text_attr(attrs, "checksums")
    if checksums_attr not in (None, CHECKSUMS):
        raise Problem("corrupt", f"corrupted nfdmatch index: unknown checksums {checksums_attr!r}")
    return {
        "format_version": version,
        "samples": samples,
        "harmonics": harmonics,
        "scale": scale,
        "checksums": checksums_attr == CHECKSUMS,
        "nfdmatch_version": text_attr(attrs, "nfdmatch_version") or "",
        "created": text_attr(attrs, "created") or "",
        "updated": text_attr(attrs, "updated") or "",
    }


def _shaped_dataset(h5, group: str, name: str, tail: tuple, file_size: int, checksums: bool):
    """The stored dataset ``/group/name`` if its shape is ``(rows, *tail)`` and, where the
    format stores numbers in it (:func:`layout_dtype`), it holds numbers; raises Problem."""
    obj = stored_dataset(h5, f"{group}/{name}", file_size, checksums)
    if len(obj.shape) != 1 + len(tail) or tuple(obj.shape[1:]) != tail:
        raise Problem(
            "corrupt",
            f"corrupted nfdmatch index: /{group}/{name} has shape {obj.shape}, "
            f"expected (rows, {', '.join(map(str, tail))})".replace(", )", ")"),
        )
    want = layout_dtype(group, name)
    problem = not_numbers(obj, f"/{group}/{name}") if want is not STR and np.dtype(want).kind != "S" else None
    if problem:
        raise Problem("corrupt", f"corrupted nfdmatch index: {problem}")
    return obj


def layout_dtype(group: str, name: str) -> Any:
    """The type docs/index-format.md gives dataset ``/group/name`` of ``/files`` or ``/curves``
    (a numpy dtype, or :data:`STR`); ``*_crc32`` companions: uint32."""
    if name.endswith("_crc32"):
        return np.uint32
    if group == "files":
        return dict(zip(FILE_FIELDS, _FILE_DTYPES, strict=True))[name]
    return curve_layout(1)[name][0]


def _tables(dataset, harmonics: int, checksums: bool, version: int = FORMAT_VERSION) -> tuple[dict, dict]:
    """The /files and /curves datasets by name, each table's of one length, with their
    ``*_crc32`` datasets of the right length when the file has checksums; ``dataset(group,
    name, tail)`` opens one (:func:`_shaped_dataset`)."""
    fds = {name: dataset("files", name, ()) for name in FILE_FIELDS}
    F = fds["path"].shape[0]
    if any(d.shape[0] != F for d in fds.values()):
        raise Problem("corrupt", "corrupted nfdmatch index: the /files datasets differ in length")
    cds = {name: dataset("curves", name, tail) for name, (_, tail) in curve_layout(harmonics, version).items()}
    N = cds["id"].shape[0]
    if any(d.shape[0] != N for d in cds.values()):
        raise Problem("corrupt", "corrupted nfdmatch index: the /curves datasets differ in length")
    if checksums:
        for group, names in STRING_DATASETS.items():
            for name in names:
                rows = F if group == "files" else N
                crc = dataset(group, f"{name}_crc32", ())
                if crc.shape[0] != (rows + CRC_ROWS - 1) // CRC_ROWS or crc.dtype.kind != "u":
                    raise Problem(
                        "corrupt",
                        f"corrupted nfdmatch index: /{group}/{name}_crc32 has shape "
                        f"{crc.shape}, expected ({(rows + CRC_ROWS - 1) // CRC_ROWS},)",
                    )
                (fds if group == "files" else cds)[f"{name}_crc32"] = crc
    return fds, cds


def stored_dataset(h5: h5py.File | h5py.Group, name: str, file_size: int, checksums: bool) -> h5py.Dataset:
    """The dataset at ``name`` (no leading slash) if it is a hard link to a dataset stored in
    this file that passes :func:`check_stored`; else raises Problem. Links are not followed:
    a soft or external link could point anywhere, including into another file."""
    where = f"/{name}"
    link = None
    try:
        parent = h5
        parts = name.split("/")
        for i, part in enumerate(parts):
            link = parent.get(part, getlink=True)
            if link is None:
                break
            if not isinstance(link, h5py.HardLink):
                raise Problem(
                    "corrupt",
                    f"corrupted nfdmatch index: {'/' + '/'.join(parts[: i + 1])} is a "
                    f"{type(link).__name__}, not stored in the file: refused",
                )
            parent = parent[part]
    except Problem:
        raise
    except Exception as exc:
        raise Problem("corrupt", f"corrupted nfdmatch index: cannot open {where} ({_short(exc)})") from None
    if link is None or not isinstance(parent, h5py.Dataset):
        raise Problem("corrupt", f"corrupted nfdmatch index: missing dataset {where}")
    problem = check_stored(parent, where, file_size, checksums)
    if problem:
        raise Problem("corrupt", f"corrupted nfdmatch index: {problem}")
    return parent
