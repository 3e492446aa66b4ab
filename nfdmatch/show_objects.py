"""A mesh query's answers for pictures: the query's contours beside each best object's
matched contours (the data behind ``nfdmatch show MESH --index parts.h5``; docs/objects.md).

Every object is put in its own principal frame, the one its contours were cut in: its area
centroid at the origin, its principal axes as x, y, z, the square root of its surface area
as the unit (what the index records in ``/objects`` for an object and the cut gives for
the query). The query and its answers are then drawn alike whatever their pose and size,
and a principal axis that the object distance took the other way round
(``ObjectMatch.mirror``) is flipped, so that matched levels face each other.

A match's contours are cut again from its mesh when the file still holds what was indexed
(the same SHA-256), otherwise rebuilt from the harmonics the index stores (true size and
pose), with a note.
"""

from __future__ import annotations

import hashlib
import os
from dataclasses import dataclass
from typing import Any

import numpy as np

from .descriptors import reconstruct
from .errors import NfdError
from .mesh.objects import cut_object
from .search.knn import stored_descriptors
from .search.objects import ObjectMatch

__all__ = ["ShownObject", "ShownQuery", "in_frame", "show_objects"]


@dataclass(frozen=True)
class ShownObject:
    """One object answer ready to draw: ``match`` (its
    :class:`~nfdmatch.search.objects.ObjectMatch`), ``loops`` (its matched contours, (m, 3)
    float64 each, in its principal frame with the mirrored axes flipped) and ``source``
    (``"file"``: cut again from its mesh; ``"index"``: rebuilt from the stored harmonics)."""

    match: ObjectMatch
    loops: tuple
    source: str = "file"

    @property
    def rank(self) -> int:
        return self.match.rank

    @property
    def id(self) -> str:
        return self.match.id

    @property
    def distance(self) -> float:
        return self.match.distance

    @property
    def note(self) -> str | None:
        return "from the index" if self.source == "index" else None


@dataclass(frozen=True)
class ShownQuery:
    """One query mesh: its ``id`` (as named), every contour of its cut (``loops``, in its
    principal frame) and its answers (``shown``: :class:`ShownObject`, best first)."""

    id: str
    loops: tuple
    shown: tuple


def in_frame(
    points: np.ndarray, frame: np.ndarray, area: float, mirror: tuple[bool, bool, bool] = (False, False, False)
) -> np.ndarray:
    """``points`` (m, 3) in the principal frame ``frame`` ((4, 3): the area centroid, then
    the three axes as rows) with ``sqrt(area)`` as the unit; the axes marked in ``mirror``
    flipped."""
    local = (np.asarray(points, dtype=np.float64) - frame[0]) @ np.asarray(frame[1:], dtype=np.float64).T
    local /= np.sqrt(area) if area > 0 else 1.0
    return local * np.where(np.asarray(mirror, dtype=bool), -1.0, 1.0)


def show_objects(
    index: Any,
    meshes: Any,
    *,
    k: int = 5,
    max_distance: float | None = None,
    exclude_self: bool = False,
    names: list[str] | None = None,
    failures: list | None = None,
    processes: int | None = None,
    points: int = 256,
) -> tuple[list[ShownQuery | None], list[str]]:
    """Each query mesh's best ``k`` objects of the open ``index`` (an index of objects), ready
    to draw (:func:`~nfdmatch.render.render_objects`), and notes (which answer was drawn from
    the index, and why).

    ``meshes``, ``k``, ``max_distance``, ``exclude_self``, ``names``, ``failures`` and
    ``processes`` as :func:`~nfdmatch.search.objects.search_objects` takes them (a mesh in
    ``failures`` gets None); ``points``: vertices of a contour rebuilt from its harmonics.
    Raises what that search raises."""
    if not isinstance(meshes, (list, tuple)):
        meshes = [meshes]
    if names is None:
        names = [
            str(os.fspath(m)) if isinstance(m, (str, os.PathLike)) else f"<mesh {i}>" for i, m in enumerate(meshes)
        ]
    cuts: list = []
    results = index.search_objects(
        list(meshes), k=k, max_distance=max_distance, exclude_self=exclude_self, names=names, failures=failures,
        processes=processes, cuts=cuts,
    )  # fmt: skip
    groups = index.objects()
    position = {object_id: m for m, object_id in enumerate(index.object_ids())}
    records = {r.path: r for r in index.files()}
    notes: list[str] = []
    drawn: dict[str, tuple] = {}  # an object's contours, cut once for every query
    out: list[ShownQuery | None] = []
    for name, cut, answers in zip(names, cuts, results):
        if cut is None:
            out.append(None)
            continue
        shown = []
        for answer in answers:
            m = position[answer.id]
            loops, source = _matched_loops(index, answer, records[answer.id], groups.rule, points, notes, drawn)
            shown.append(ShownObject(answer, tuple(in_frame(p, groups.frame[m], groups.area[m], answer.mirror)
                                                   for p in loops), source))  # fmt: skip
        query_loops = tuple(in_frame(p, cut.frame, cut.area) for p in cut.loops)
        out.append(ShownQuery(name, query_loops, tuple(shown)))
    return out, notes


def _matched_loops(index, answer: ObjectMatch, record, rule, points: int, notes: list, drawn: dict):
    """``(contours, source)`` of an answer's matched contours (its ``#i`` curves) in its mesh's
    coordinates: cut again from the file when it still holds what was indexed (the cut kept
    in ``drawn`` for the next query), else rebuilt from the stored harmonics (a note why)."""
    numbers = [int(c.rsplit("#", 1)[1]) for c in answer.curves]
    if answer.id not in drawn:
        drawn[answer.id] = _cut_again(index, answer.id, record, rule)
    loops, reason = drawn[answer.id]
    if loops is not None:
        return [loops[i] for i in numbers], "file"
    if not any(n.startswith(f"{answer.id}: ") for n in notes):
        notes.append(f"{answer.id}: drawn from its {index.harmonics} indexed harmonics: {reason}")
    rebuilt = [
        reconstruct(stored_descriptors(index, record.curve_start + i, f"{answer.id}#{i}"), points=points)
        for i in numbers
    ]
    return rebuilt, "index"


def _cut_again(index, object_id: str, record, rule) -> tuple:
    """``(contours, None)`` of the object's mesh cut again, or ``(None, why not)``."""
    located = index.locate(object_id)
    try:
        with open(located, "rb") as f:
            digest = hashlib.sha256(f.read()).hexdigest()
    except OSError as exc:
        return None, f"cannot read it ({exc.strerror or exc})"
    if digest != record.sha256:
        return None, "the file changed since it was indexed"
    try:
        cut = cut_object(located, rule)
    except NfdError as exc:
        return None, f"cannot cut it ({exc})"
    if len(cut.loops) != record.curve_count:  # another version of the cut: not the rows matched
        return None, f"it cuts into {len(cut.loops)} contours, the index holds {record.curve_count}"
    return cut.loops, None
