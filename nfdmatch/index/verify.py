"""``nfdmatch index verify``: read every chunk of an index and say what is bad.

Opening an index checks its structure (schema.py); a query then checks the checksums and
finiteness of what it reads. This reads everything: every chunk of every dataset (each
Fletcher-32 checksum verified by HDF5), every 32-row block of strings against its CRC-32,
every stored float for finiteness, every dataset's type against docs/index-format.md, and
the derived data against what it is derived from (``/curves/file`` and ``/curves/id``
against the file table, the bound features ``inv_*`` recomputed from the stored
coefficients, ``/search`` against ``/curves``), and, in an index that records its sources,
that no relative path leads out of the index's folder.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import os
from dataclasses import dataclass, field

import numpy as np

from ..errors import IndexFormatError
from ..search.bounds import feature_split, squared_norms
from ..matching import invariants
from ..matching.statistics import curve_statistics
from .changes import changes_problem, changes_rows
from .graph import GRAPH_CHECKSUMS, NEIGHBOUR_PROBLEMS, group_distance, list_problems, reverse_of
from .objects_group import read_objects
from .paths import curve_ids
from .schema import CRC_ROWS, STRING_DATASETS, Problem, _short, block_crcs, open_checked, stored_dataset
from .heap import check_string_rows
from .schema import _FILE_DTYPES, FILE_FIELDS, STR, curve_layout, text_attr

if TYPE_CHECKING:
    import os

__all__ = ["Finding", "VerifyReport", "verify_index"]

#: rows read at a time from a contiguous (unchunked) dataset
_BLOCK_ROWS = 65536
#: rows listed per finding before "... and N more"
_LIST_ROWS = 10
#: relative slack of the radius test (the writer rounds radii up by 1e-12; the features are float32)
_RADIUS_SLACK = 1e-6


@dataclass(frozen=True)
class Finding:
    """One thing wrong: ``dataset`` (e.g. ``/curves/coefficients``), ``rows`` (a text such as
    ``"256..511"`` or ``"17, 90"``, ``""`` for the whole dataset), ``what``."""

    dataset: str
    rows: str
    what: str


@dataclass
class VerifyReport:
    """What :func:`verify_index` found: ``path``, ``format_version``, ``checksums`` (the file
    carries them), ``datasets`` (checked), ``curves``, ``findings`` (list of :class:`Finding`)."""

    path: str
    format_version: int
    checksums: bool
    datasets: int = 0
    curves: int = 0
    findings: list = field(default_factory=list)
    #: dataset -> row ranges that could not be read (left out of the later checks)
    unreadable: dict = field(default_factory=dict, repr=False)

    @property
    def ok(self) -> bool:
        return not self.findings


def _rows_text(rows) -> str:
    rows = [int(r) for r in rows]
    text = ", ".join(map(str, rows[:_LIST_ROWS]))
    return text + (f" ... and {len(rows) - _LIST_ROWS} more" if len(rows) > _LIST_ROWS else "")


def _blocks(ds):
    """(a, b) row ranges of ``ds``: its chunks along the rows, or 64k-row blocks (always for
    strings: a multiple of the CRC-32 blocks)."""
    n = ds.shape[0] if ds.shape else 1
    step = ds.chunks[0] if ds.chunks and ds.dtype.kind != "O" else _BLOCK_ROWS
    return [(a, min(n, a + step)) for a in range(0, n, step)]


def _scan(ds, name, report, *, label="row", keep=None, crc=None):
    """Read ``ds`` chunk by chunk and check each block as it comes: unreadable chunks (a
    Fletcher-32 mismatch), non-finite rows, and, with ``crc`` (the stored CRC-32 blocks of a
    string dataset), each 32-row block of strings. Only what a later cross-check needs is
    kept: ``keep(block) -> array`` per block (None: nothing), concatenated; so a 1M-row
    index is verified without holding every dataset at once."""
    n = ds.shape[0] if ds.shape else 0
    strings = ds.dtype.kind == "O"
    kept, bad, nonfinite, crc_bad = [], [], [], []
    for a, b in _blocks(ds) if ds.shape else []:
        try:
            if strings:
                check_string_rows(ds, [(a, b)])
            values = ds.asstr()[a:b].tolist() if strings else ds[a:b]
        except Exception as exc:
            bad.append((a, b, exc))
            if keep is not None:
                kept.append(None)
            continue
        if strings:
            if crc is not None:
                first = a // CRC_ROWS  # blocks are multiples of CRC_ROWS
                want = block_crcs(values)
                got = np.asarray(crc[first : first + len(want)], dtype=np.uint32)
                crc_bad += [first + i for i in np.flatnonzero(got != want[: len(got)])]
                if len(got) < len(want):
                    crc_bad += list(range(first + len(got), first + len(want)))
        elif values.dtype.kind in "fc" and values.size:
            nonfinite += (a + np.flatnonzero(~np.isfinite(values.reshape(len(values), -1)).all(axis=1))).tolist()
        if keep is not None:
            kept.append(keep(values))
    for a, b, exc in bad:  # type: ignore[misc]
        report.findings.append(Finding(name, f"{a}..{b - 1}", _unreadable(exc)))
    if bad:
        report.unreadable[name] = [(a, b) for a, b, _ in bad]
    if nonfinite:
        report.findings.append(
            Finding(name, _rows_text(nonfinite), f"non-finite values (NaN or Inf), {len(nonfinite)} {label}s")
        )
    for blk in crc_bad[:_LIST_ROWS]:
        report.findings.append(
            Finding(
                name,
                f"{blk * CRC_ROWS}..{min(n, (blk + 1) * CRC_ROWS) - 1}",
                "checksum mismatch (CRC-32 of the strings)",
            )
        )
    if keep is None or bad:
        return None
    if not ds.shape:
        return ds[()]
    if not kept:
        return keep(ds[0:0])
    return kept[0] if len(kept) == 1 else np.concatenate(kept)


def verify_index(path: str | os.PathLike[str]) -> VerifyReport:
    """Check a whole index (formats 1, 2 and 3); returns a :class:`VerifyReport`.

    Raises ReadError (missing, unreadable) or IndexFormatError when the file does not even
    open as an index (its structure is checked first, as for any reader); everything found
    past that point is a :class:`Finding` in the report.
    """
    p = str(os.fspath(path))
    try:
        h5, meta, files = open_checked(p)
    except Problem as exc:
        raise IndexFormatError(exc.message, path=p) from None
    try:
        report = VerifyReport(p, meta["format_version"], meta["checksums"], curves=meta["n_curves"])
        _verify(h5, meta, files, report)
        _verify_graph(h5, meta, report)
        _verify_objects(h5, meta, report)
        _verify_changes(h5, meta, report)
    finally:
        h5.close()
    return report


def _expected_dtypes(K: int) -> dict:
    """Dataset -> what docs/index-format.md says it holds: a numpy dtype, or ``"string"``
    (variable-length UTF-8)."""
    files = dict(zip(FILE_FIELDS, _FILE_DTYPES, strict=True))
    out = {f"/files/{name}": dtype for name, dtype in files.items()}
    out.update({f"/curves/{name}": dtype for name, (dtype, _) in curve_layout(K).items()})
    # the /search table of docs/index-format.md
    search = {
        "row": np.int64,
        "cell_start": np.int64,
        "centre": np.float64,
        "radius": np.float64,
        "features": np.float32,
        "sqnorm": np.float64,
        "coefficients": np.complex64,
    }
    out.update({f"/search/{name}": dtype for name, dtype in search.items()})
    for group, names in STRING_DATASETS.items():
        for name in names:
            out[f"/{group}/{name}_crc32"] = np.uint32
    return {name: ("string" if dtype is STR else np.dtype(dtype)) for name, dtype in out.items()}


def _dtype_text(dtype) -> str:
    import h5py

    info = h5py.check_string_dtype(dtype)
    if info is not None:
        return f"{'variable-length' if info.length is None else f'{info.length}-byte'} {info.encoding} string"
    return str(dtype.newbyteorder("=") if dtype.byteorder not in "=|" else dtype)


def _check_dtypes(groups, K: int, report) -> None:
    """Every dataset's stored type against docs/index-format.md (any byte order: HDF5 converts)."""
    expected = _expected_dtypes(K)
    for group, datasets in groups.items():
        for name, ds in datasets.items():
            full = f"/{group}/{name}"
            want = expected.get(full)
            if want is None:
                continue
            problem = _dtype_problem(ds.dtype, want)
            if problem:
                report.findings.append(Finding(full, "", problem))


def _dtype_problem(got, want) -> str | None:
    """Why a dataset stored as ``got`` is not of the type ``want`` (a numpy dtype, or
    ``"string"``: variable-length UTF-8) docs/index-format.md gives it, or None."""
    import h5py

    if want == "string":
        info = h5py.check_string_dtype(got)
        ok = info is not None and info.length is None and info.encoding == "utf-8"
        shown = "a variable-length UTF-8 string"
    elif want.kind == "S":  # fixed-length ASCII (h5py marks it as a string type)
        ok = got.kind == "S" and got.itemsize == want.itemsize
        shown = f"a {want.itemsize}-byte ASCII string"
    else:
        ok = h5py.check_string_dtype(got) is None and got.newbyteorder("=") == want.newbyteorder("=")
        shown = str(want)
    return None if ok else f"stored as {_dtype_text(got)}; the format says {shown}"


def _escapes(path: str) -> bool:
    """True when a relative stored path leads out of the index's folder (``..``)."""
    if os.path.isabs(path):
        return False
    parts = path.replace("\\", "/").split("/")
    depth = 0
    for part in parts:
        if part == "..":
            depth -= 1
            if depth < 0:
                return True
        elif part not in ("", "."):
            depth += 1
    return False


def _check_paths_and_ids(h5, files, paths, ids, report) -> None:
    """Ids derived from the file table (``path`` or ``path#i``) and, when the index records
    its sources (relative paths are then relative to its folder), no relative path that
    leads out of that folder."""
    if paths is not None and "sources" in h5:
        bad = [i for i, p in enumerate(paths) if _escapes(str(p))]
        if bad:
            report.findings.append(
                Finding("/files/path", _rows_text(bad), "relative paths that lead out of the index's folder (..)")
            )
    if paths is None or ids is None:
        return
    want = [i for p, n in zip(paths, files["curve_count"]) for i in curve_ids(str(p), int(n))]
    if len(want) != len(ids):
        return  # the block check of /files reports this
    bad = [r for r, (got, exp) in enumerate(zip(ids, want)) if got != exp]
    if bad:
        report.findings.append(
            Finding("/curves/id", _rows_text(bad), "differs from the ids of the /files paths (path, path#i)")
        )


def _check_features(values, K: int, report) -> None:
    """``inv_norm``, ``inv_sv``, ``inv_block`` recomputed from the stored coefficients (the
    writer's computation, rounded to float32 as stored): a bound feature larger than it
    should be would make a search skip a true match."""
    coefficients = values.get("/curves/coefficients")
    if coefficients is None:
        return
    names = {"norm": "/curves/inv_norm", "sv": "/curves/inv_sv", "block": "/curves/inv_block"}
    bad = {name: [] for name in names.values()}
    N = len(coefficients)
    for a in range(0, N, _BLOCK_ROWS):
        b = min(N, a + _BLOCK_ROWS)
        C = np.asarray(coefficients[a:b], dtype=np.complex128)
        finite = np.flatnonzero(np.isfinite(C.reshape(b - a, -1)).all(axis=1))  # the others are reported already
        inv = invariants(C[finite])
        for key, name in names.items():
            stored = values.get(name)
            if stored is None:
                continue
            want = inv[key].reshape(len(finite), -1).astype(np.float32).astype(np.float64)
            got = np.asarray(stored[a:b], dtype=np.float64).reshape(b - a, -1)[finite]
            # float32 rounding of the same computation: a few units in the last place of the row's largest value
            tol = 1e-6 * np.maximum(np.abs(want).max(axis=1, initial=0.0), 1e-30)[:, None] + 1e-30
            with np.errstate(invalid="ignore"):
                off = ~(np.abs(got - want) <= tol)
            bad[name] += (a + finite[off.any(axis=1)]).tolist()
    for name, rows in bad.items():
        if rows:
            report.findings.append(
                Finding(name, _rows_text(rows), "differs from the features of the stored coefficients")
            )


def _check_statistics(values, report) -> None:
    """``statistics`` (format 3) recomputed from the stored coefficients, equal to float32
    rounding: the elastic stage ranks by them."""
    coefficients, stored = values.get("/curves/coefficients"), values.get("/curves/statistics")
    if coefficients is None or stored is None:
        return
    bad = []
    N = len(coefficients)
    for a in range(0, N, _BLOCK_ROWS):
        b = min(N, a + _BLOCK_ROWS)
        C = np.asarray(coefficients[a:b], dtype=np.complex128)
        finite = np.flatnonzero(np.isfinite(C.reshape(b - a, -1)).all(axis=1))  # the others are reported already
        want = curve_statistics(C[finite]).reshape(len(finite), -1).astype(np.float32).astype(np.float64)
        got = np.asarray(stored[a:b], dtype=np.float64).reshape(b - a, -1)[finite]
        # float32 rounding, and float64 sums in another order: relative to the row's largest value
        tol = 1e-5 * np.maximum(np.abs(want).max(axis=1, initial=0.0), 1.0)[:, None]
        with np.errstate(invalid="ignore"):
            off = ~(np.abs(got - want) <= tol)
        bad += (a + finite[off.any(axis=1)]).tolist()
    if bad:
        report.findings.append(
            Finding("/curves/statistics", _rows_text(bad), "differs from the statistics of the stored coefficients")
        )


def _verify(h5, meta, files, report) -> None:
    """Every dataset scanned block by block (readable, finite, checksums), then the
    cross-checks: dtypes, ids, features, the /files blocks, /search against /curves."""
    K = meta["harmonics"]
    groups, values = _scan_datasets(h5, meta, files, report)
    _check_dtypes(groups, K, report)
    N, F = meta["n_curves"], meta["n_files"]
    if report.unreadable:  # derived data cannot be compared with unreadable rows
        return
    _check_paths_and_ids(h5, files, values.get("/files/path"), values.get("/curves/id"), report)
    _check_features(values, K, report)
    _check_statistics(values, report)
    file_col = values["/curves/file"]
    want = np.repeat(np.arange(F), files["curve_count"]) if F else np.zeros(0, dtype=np.int64)
    bad = np.flatnonzero(np.asarray(file_col, dtype=np.int64) != want)
    if len(bad):
        report.findings.append(Finding("/curves/file", _rows_text(bad), "does not match the /files blocks"))
    if meta["format_version"] < 2 or not N:
        return
    split = feature_split(K)
    row = np.asarray(values["/search/row"], dtype=np.int64)
    if not np.array_equal(np.sort(row), np.arange(N)):
        report.findings.append(Finding("/search/row", "", "not a permutation of the /curves rows"))
        return
    _check_search_derived(values, row, split, report)
    _check_cells(values, row, split, report)


def _scan_datasets(h5, meta, files, report) -> tuple[dict, dict]:
    """Scan every dataset once (checksum datasets first); returns the datasets by group and
    the values the cross-checks need, by full name (the rest is scanned and dropped)."""
    whole = np.asarray
    needed = {
        "/curves/file": whole,
        "/curves/inv_sv": whole,
        "/curves/inv_block": whole,
        "/curves/inv_norm": whole,
        "/curves/coefficients": whole,
        "/curves/statistics": whole,
        "/curves/id": list,
        "/files/path": list,
    }
    groups = {"files": files["datasets"] | files.get("crc", {}), "curves": meta["datasets"] | meta.get("crc", {})}
    if meta["format_version"] >= 2:
        groups["search"] = {name: h5["search"][name] for name in h5["search"] if hasattr(h5["search"][name], "shape")}
        needed.update({f"/search/{name}": whole for name in groups["search"]})
    crcs = {}
    if meta["checksums"]:
        for group, names in STRING_DATASETS.items():
            for name in names:
                crc_ds = groups[group].get(f"{name}_crc32")
                crcs[f"/{group}/{name}"] = _scan(crc_ds, f"/{group}/{name}_crc32", report, keep=whole)
                report.datasets += 1
    values = {}
    for group, datasets in groups.items():
        for name, ds in datasets.items():
            full = f"/{group}/{name}"
            if full[: -len("_crc32")] in crcs and full.endswith("_crc32"):
                continue  # scanned above
            crc = crcs.get(full)
            values[full] = _scan(
                ds, full, report, label="position" if group == "search" else "row", keep=needed.get(full), crc=crc
            )
            report.datasets += 1
    return groups, values


def _check_search_derived(values, row, split: int, report) -> None:
    """/search features, squared norms and coefficients equal to the /curves rows they copy."""
    features = values["/search/features"]
    derived = np.concatenate([values.pop("/curves/inv_sv"), values.pop("/curves/inv_block")], axis=1)[row]
    checks = (
        ("/search/features", features, derived),
        ("/search/sqnorm", values["/search/sqnorm"], squared_norms(features, split)),
        ("/search/coefficients", values["/search/coefficients"], values.pop("/curves/coefficients")[row]),
    )
    for name, got, expected in checks:
        same = got == expected
        if got.dtype.kind != "c":
            same |= np.isnan(got) & np.isnan(expected)
        bad = np.flatnonzero(~same.reshape(len(got), -1).all(axis=1))
        if len(bad):
            report.findings.append(Finding(name, _rows_text(bad), "differs from what it is derived from (positions)"))


def _check_cells(values, row, split: int, report) -> None:
    """The /search cells: rows ascend within a cell, members lie within its radius."""
    features = values["/search/features"]
    N = len(row)
    start = np.asarray(values["/search/cell_start"], dtype=np.int64)
    centre, radius = values["/search/centre"], values["/search/radius"]
    cell = np.repeat(np.arange(len(start) - 1), np.diff(start))
    # the cells from their rows: within a cell, rows ascend (docs/index-format.md)
    falls = np.flatnonzero((np.diff(row) < 0) & (cell[1:] == cell[:-1]))
    if len(falls):
        report.findings.append(
            Finding("/search/row", _rows_text(np.unique(cell[falls])), "cells whose rows do not ascend")
        )
    for part, cols in ((0, slice(0, split)), (1, slice(split, None))):
        dist = np.empty(N)
        for a in range(0, N, _BLOCK_ROWS):  # blocks: no (N, D) float64 copy
            b = min(N, a + _BLOCK_ROWS)
            X = features[a:b, cols].astype(np.float64) - centre[cell[a:b], cols]
            dist[a:b] = np.sqrt((X**2).sum(axis=1))
        bad = np.flatnonzero(dist > radius[cell, part] * (1 + _RADIUS_SLACK) + 1e-9)
        if len(bad):
            report.findings.append(
                Finding(
                    "/search/radius",
                    _rows_text(np.unique(cell[bad])),
                    f"cells with members outside their radius (positions {_rows_text(bad)})",
                )
            )


# --------------------------------------------------------------------------- /changes


def _verify_changes(h5, meta, report) -> None:
    """``/changes``, when the index has it: the checks ``pairs --new`` makes of it."""
    try:
        runs = changes_rows(h5)
    except ValueError as exc:
        report.findings.append(Finding("/changes", "", str(exc).removeprefix("/changes ")))
        return
    except (OSError, TypeError) as exc:
        report.findings.append(Finding("/changes/rows", "", _unreadable(exc)))
        return
    problem = None if runs is None else changes_problem(runs, meta["n_curves"])
    if problem:
        report.findings.append(Finding("/changes/rows", "", problem.removeprefix("/changes/rows ")))


# --------------------------------------------------------------------------- /objects


def _verify_objects(h5, meta, report) -> None:
    """``/objects``, when the index has one: every check a reader makes of it (every chunk
    read: its checksums), and each object's file holding only contours."""
    try:
        groups = read_objects(h5, meta["n_curves"], meta["n_files"], int(h5.id.get_filesize()), meta["checksums"])
    except IndexFormatError as exc:
        what = exc.message.removeprefix("corrupted nfdmatch index: ").removeprefix("/objects: ")
        report.findings.append(Finding("/objects", "", what))
        return
    if groups is None:
        return
    starts = h5["files/curve_start"][...]
    counts = h5["files/curve_count"][...]
    for f in groups.file.tolist():
        rows = groups.axis[starts[f] : starts[f] + counts[f]]
        if counts[f] == 0 or (rows < 0).any():
            report.findings.append(Finding("/objects/axis", f"{starts[f]}..{starts[f] + counts[f] - 1}",
                                           f"object file row {f} has rows that are not contours"))  # fmt: skip


# --------------------------------------------------------------------------- /graph


def _verify_graph(h5, meta, report) -> None:
    """``/graph``, when the index has one: how it is stored, its types, its checksums (every chunk
    read), every list valid (:func:`~.graph.list_problems`), and the lists consistent with
    each other (docs/index-format.md, "/graph")."""
    g = h5.get("graph")
    if g is None:
        return
    N = meta["n_curves"]
    attr = (text_attr(g.attrs, "checksums") or g.attrs.get("checksums")) if "checksums" in g.attrs else None
    if attr not in (None, GRAPH_CHECKSUMS):
        report.findings.append(Finding("/graph", "", f"unknown checksums attribute {attr!r}"))
        return
    file_size = int(h5.id.get_filesize())
    datasets = {}
    for name in ("neighbour", "distance"):
        try:
            ds = stored_dataset(h5, f"graph/{name}", file_size, attr == GRAPH_CHECKSUMS)
        except Problem as exc:
            report.findings.append(
                Finding(f"/graph/{name}", "", exc.message.removeprefix("corrupted nfdmatch index: "))
            )
            continue
        if _graph_type_found(ds, name, report):
            datasets[name] = ds
    if len(datasets) < 2:
        return
    nb_ds, d_ds = datasets["neighbour"], datasets["distance"]
    k = g.attrs.get("k")
    k = int(k) if isinstance(k, (int, np.integer)) and not isinstance(k, bool) else k
    shape_ok = len(nb_ds.shape) == 2 and nb_ds.shape == d_ds.shape and nb_ds.shape[0] == N
    if not shape_ok or not isinstance(k, int) or k != nb_ds.shape[1] or k < 1:
        report.findings.append(
            Finding("/graph", "", f"shapes {nb_ds.shape} and {d_ds.shape} do not fit {N} curves and k = {k!r}")
        )
        return
    report.datasets += 2
    nb = np.empty(nb_ds.shape, dtype=np.int64)
    dist = np.empty(d_ds.shape, dtype=np.float64)
    unreadable = False
    for name, ds, out in (("neighbour", nb_ds, nb), ("distance", d_ds, dist)):
        for a, b in _blocks(ds):
            try:
                out[a:b] = ds[a:b]
            except Exception as exc:
                report.findings.append(Finding(f"/graph/{name}", f"{a}..{b - 1}", _unreadable(exc)))
                unreadable = True
    if unreadable:
        return
    found = False
    for what, bad in list_problems(np.arange(N), nb, dist, N).items():
        if len(bad):
            name = "/graph/neighbour" if what in NEIGHBOUR_PROBLEMS else "/graph/distance"
            report.findings.append(Finding(name, _rows_text(bad), f"{what}, {len(bad)} rows"))
            found = True
    if found or not N:
        return
    _verify_reverse(h5, g, nb, attr == GRAPH_CHECKSUMS, report)
    if group_distance(g) != "exact":
        # a fused graph's lists are each row's least fused among its exact nearest, not top-K
        # lists of one metric, and a pair whose exact optimum is ambiguous may bend otherwise
        # one way than the other: the cross-checks of exact lists do not hold
        return
    bad = _inconsistent_lists(nb, dist)
    if len(bad):
        report.findings.append(
            Finding(
                "/graph/distance",
                _rows_text(bad),
                f"lists inconsistent with each other (a distance that differs both ways, or a row "
                f"missing from a list it is near enough to be in), {len(bad)} rows",
            )
        )


#: each /graph dataset's type (docs/index-format.md, "/graph")
_GRAPH_TYPES = {
    "neighbour": np.dtype(np.int64),
    "distance": np.dtype(np.float64),
    "reverse_start": np.dtype(np.int64),
    "reverse_source": np.dtype(np.int64),
}


def _graph_type_found(ds, name: str, report) -> bool:
    """True when ``/graph/<name>`` is stored with the type the format gives it; else a
    finding says what it is (its values are then not read: a string or another kind of
    number converted to the right one would pass for a list)."""
    problem = _dtype_problem(ds.dtype, _GRAPH_TYPES[name])
    if problem:
        report.findings.append(Finding(f"/graph/{name}", "", problem))
    return problem is None


def _unreadable(exc: Exception) -> str:
    """What a failed read of stored values says: a Fletcher-32 mismatch, or why it failed."""
    text = _short(exc)
    return "checksum mismatch (damaged chunk)" if "filter returned failure" in text else f"unreadable ({text})"


def _verify_reverse(h5, g, nb: np.ndarray, checksums: bool, report) -> None:
    """``/graph/reverse_start`` and ``reverse_source``, when the graph stores them (graphs
    written from turn 4's second session): stored, every chunk readable, and exactly the
    valid lists ``nb`` turned round (:func:`~.graph.reverse_of`)."""
    if "reverse_start" not in g and "reverse_source" not in g:
        return
    file_size = int(h5.id.get_filesize())
    got = {}
    for name in ("reverse_start", "reverse_source"):
        try:
            ds = stored_dataset(h5, f"graph/{name}", file_size, checksums)
        except Problem as exc:
            report.findings.append(
                Finding(f"/graph/{name}", "", exc.message.removeprefix("corrupted nfdmatch index: "))
            )
            continue
        if not _graph_type_found(ds, name, report):
            continue
        try:
            got[name] = np.asarray(ds[...], dtype=np.int64)
        except Exception as exc:
            report.findings.append(Finding(f"/graph/{name}", "", _unreadable(exc)))
    if len(got) < 2:
        return
    report.datasets += 2
    start, source = reverse_of(nb, len(nb))
    if not (np.array_equal(got["reverse_start"], start) and np.array_equal(got["reverse_source"], source)):
        report.findings.append(Finding("/graph/reverse_source", "", "not the graph's lists turned round"))


#: relative tolerance of the graph's consistency checks (distances from complex64 coefficients)
_GRAPH_TOL = 1e-5


def _inconsistent_lists(nb: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """Rows whose list contradicts another's: for every stored edge i -> j at distance d,
    j -> i, when stored, has the same distance, and when d is below j's K-th distance
    (beyond rounding), i is in j's list (the lists are exact top-K lists of one metric)."""
    N, k = nb.shape
    i = np.repeat(np.arange(N), k)
    j, d = nb.reshape(-1), dist.reshape(-1)
    real = j >= 0
    i, j, d = i[real], j[real], d[real]
    full = (nb >= 0).all(axis=1)
    kth = np.where(full, dist[:, -1], np.inf)  # a padded list holds every other row
    key_ij = i * N + j
    order = np.argsort(key_ij)
    sorted_keys = key_ij[order]
    back = j * N + i
    at = np.searchsorted(sorted_keys, back)
    at_c = np.minimum(at, len(sorted_keys) - 1)
    present = sorted_keys[at_c] == back
    tol = _GRAPH_TOL * np.maximum(d, 1e-12) + 1e-9
    differs = present & (np.abs(d[order[at_c]] - d) > tol)
    with np.errstate(invalid="ignore"):
        near = np.where(np.isinf(kth[j]), True, d < kth[j] - (_GRAPH_TOL * kth[j] + 1e-9))
    missing = ~present & near
    return np.unique(np.concatenate([i[differs], j[missing]]))
