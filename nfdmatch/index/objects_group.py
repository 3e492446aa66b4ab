"""``/objects``: the meshes of an index as objects (docs/index-format.md, format 3): the
rule their contours were cut by, each contour row's axis, level and measures, and each
object's file, profile, area and frame. Written by a build whose sources hold meshes; read
(and checked) only by what needs it (a mesh query), as ``/graph`` is."""

from __future__ import annotations

from typing import TYPE_CHECKING

from dataclasses import dataclass

import numpy as np

from ..errors import IndexFormatError
from ..mesh.objects import MEASURES, PROFILE_FEATURES, ObjectRule
from .schema import Problem, create_checked, set_text, stored_dataset, text_attr

if TYPE_CHECKING:
    import h5py

__all__ = ["ObjectEntry", "ObjectsGroup", "write_objects", "read_objects", "rule_of"]

#: per-row datasets (N rows, the /curves rows) and their dtype and shape after the rows
ROW_LAYOUT = {"axis": (np.int8, ()), "level": (np.int16, ()), "measures": (np.float64, (len(MEASURES),))}


@dataclass
class ObjectEntry:
    """One object of a build: its /files row, its rows ``[start, start + count)`` and its
    record (``axis``, ``level``, ``measures`` per row; ``profile``, ``area``, ``frame``)."""

    file_row: int
    start: int
    count: int
    record: dict


@dataclass
class ObjectsGroup:
    """``/objects`` read into memory (small: a few numbers per contour)."""

    rule: ObjectRule
    axis: np.ndarray  # (N,) int8, -1 for a row that is not an object's contour
    level: np.ndarray  # (N,) int16
    measures: np.ndarray  # (N, 3) float64
    file: np.ndarray  # (M,) int64 /files rows, ascending
    profile: np.ndarray  # (M, 12 S)
    area: np.ndarray  # (M,)
    frame: np.ndarray  # (M, 4, 3)

    def record(self, m: int, start: int, count: int) -> dict:
        """Object ``m``'s record (its rows ``[start, start + count)``), as a build's worker
        makes it: copied into a new index for an unchanged mesh."""
        rows = slice(start, start + count)
        return {
            "axis": self.axis[rows],
            "level": self.level[rows],
            "measures": self.measures[rows],
            "profile": self.profile[m],
            "area": float(self.area[m]),
            "frame": self.frame[m],
        }


def write_objects(h5: h5py.File, rule: ObjectRule, entries: list[ObjectEntry], n_rows: int) -> None:
    """Write ``/objects`` for ``entries`` (in /files order) over ``n_rows`` curve rows;
    nothing when there is no object (a curve-only index has no ``/objects``)."""
    if not entries:
        return
    g = h5.create_group("objects")
    set_text(g.attrs, "rule", rule.name)
    g.attrs["sections"] = np.int64(rule.sections)
    g.attrs["min_vertices"] = np.int64(rule.min_vertices)
    g.attrs["boundaries"] = np.int64(int(rule.boundaries))
    axis = np.full(n_rows, -1, dtype=np.int8)
    level = np.full(n_rows, -1, dtype=np.int16)
    measures = np.zeros((n_rows, len(MEASURES)))
    for e in entries:
        rows = slice(e.start, e.start + e.count)
        axis[rows] = e.record["axis"]
        level[rows] = e.record["level"]
        measures[rows] = e.record["measures"]
    create_checked(g, "axis", axis)
    create_checked(g, "level", level)
    create_checked(g, "measures", measures)
    create_checked(g, "file", np.array([e.file_row for e in entries], dtype=np.int64))
    create_checked(g, "profile", np.array([e.record["profile"] for e in entries], dtype=np.float64))
    create_checked(g, "area", np.array([e.record["area"] for e in entries], dtype=np.float64))
    create_checked(g, "frame", np.array([e.record["frame"] for e in entries], dtype=np.float64).reshape(-1, 4, 3))


def _attr(attrs, name):
    """An attribute as a Python str or int (None when absent or of another kind)."""
    value = attrs.get(name)
    if isinstance(value, bytes):
        value = value.decode("utf-8", "replace")
    if isinstance(value, np.ndarray) and value.shape in ((), (1,)):
        value = value.reshape(())[()]
    if isinstance(value, np.integer):
        value = int(value)
    return value if isinstance(value, (str, int)) and not isinstance(value, bool) else None


def rule_of(h5: h5py.File) -> ObjectRule | None:
    """The recorded rule of ``/objects`` (None without the group); IndexFormatError for a
    rule this version does not know."""
    g = h5.get("objects")
    if g is None:
        return None
    name, sections = text_attr(g.attrs, "rule"), _attr(g.attrs, "sections")
    min_vertices, boundaries = _attr(g.attrs, "min_vertices"), _attr(g.attrs, "boundaries")
    try:
        return ObjectRule(sections=sections, min_vertices=min_vertices, boundaries=bool(boundaries), name=name)
    except Exception:
        raise IndexFormatError(
            f"corrupted nfdmatch index: /objects records an unknown or bad rule "
            f"({name!r}, sections {sections!r}, min_vertices {min_vertices!r})",
            path=h5.filename,
        ) from None


def read_objects(h5: h5py.File, n_rows: int, n_files: int, file_size: int, checksums: bool) -> ObjectsGroup | None:
    """``/objects`` checked (shapes, rows, finite values; docs/index-format.md) or None when
    the index has none; IndexFormatError when it is bad."""
    rule = rule_of(h5)
    if rule is None:
        return None
    S = rule.sections
    tails = {
        **{k: t for k, (_, t) in ROW_LAYOUT.items()},
        "file": (),
        "profile": (3 * S * len(PROFILE_FEATURES),),
        "area": (),
        "frame": (4, 3),
    }
    data = {}
    try:
        for name, tail in tails.items():
            ds = stored_dataset(h5, f"objects/{name}", file_size, checksums)
            if tuple(ds.shape[1:]) != tail or len(ds.shape) != 1 + len(tail):
                raise Problem("corrupt", f"/objects/{name} has shape {ds.shape}")
            data[name] = ds[...]
    except Problem as exc:
        raise IndexFormatError(exc.message if exc.message.startswith("corrupted") else
                               f"corrupted nfdmatch index: {exc.message}", path=h5.filename) from None  # fmt: skip
    except Exception as exc:
        raise IndexFormatError(f"corrupted nfdmatch index: cannot read /objects ({exc})", path=h5.filename) from None
    M = len(data["file"])
    bad = None
    if any(len(data[k]) != n_rows for k in ROW_LAYOUT):
        bad = "its per-row datasets do not have one row per curve"
    elif any(len(data[k]) != M for k in ("profile", "area", "frame")):
        bad = "its per-object datasets differ in length"
    elif M and (np.any(np.diff(data["file"]) <= 0) or data["file"][0] < 0 or data["file"][-1] >= n_files):
        bad = "its file rows are not ascending rows of /files"
    elif not all(np.isfinite(data[k]).all() for k in ("measures", "profile", "area", "frame")):
        bad = "a non-finite value"
    elif np.any((data["axis"] < -1) | (data["axis"] > 3)) or np.any(data["level"] >= S):
        bad = "an axis or level out of range"
    if bad:
        raise IndexFormatError(f"corrupted nfdmatch index: /objects: {bad}", path=h5.filename)
    return ObjectsGroup(rule=rule, **{k: np.asarray(v) for k, v in data.items()})
