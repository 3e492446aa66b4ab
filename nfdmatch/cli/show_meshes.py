"""``show`` of a mesh query: the query's contours beside its best objects' matched contours
(docs/objects.md), with the options of ``show`` of a curve."""

from __future__ import annotations

import os
from types import SimpleNamespace
from typing import TYPE_CHECKING

import click

from .options import (
    finish,
    note,
    note_inputs,
    nothing_matched,
    refuse_input_as_output,
)
from .output import path_speller, write_rows
from .picture_files import check_pictures, not_written, picture_names, report_picture
from .query_cmd import mesh_queries, report_mesh_failures, require_objects

if TYPE_CHECKING:
    from ..index import Index

__all__ = ["show_meshes"]

#: the rows of a mesh query's picture
COLUMNS = ["query", "rank", "match", "distance", "curves", "source"]


def show_meshes(
    queries: tuple[str, ...], index_path: str | None, input_format: str | None, drawing: dict, outputs: tuple
) -> bool:
    """Draw each mesh query among ``queries`` and its best objects, and write the rows drawn;
    False (nothing done) for a query of curves. ``drawing``: top, max_distance, exclude_self,
    paths, size (parsed), renderer, stage (--elastic), matching; ``outputs``: the picture -o
    (a pattern for several queries), the rows' -o and format."""
    from ..index import open_index

    if input_format is not None or not any(_has_meshes(q) for q in queries):
        return False  # no mesh named or in a folder: the index is not opened twice
    with open_index(index_path) as idx:
        meshes = mesh_queries(idx, queries, None, input_format)
        if not meshes:
            return False
        drawn, rows, names, failures = _drawn(idx, meshes, drawing, outputs[0], outputs[1])
    results = []
    if failures:
        not_written(names)
    else:
        from ..render import render_objects

        results = [
            render_objects(q.id, q.loops, q.shown, name, size=drawing["size"], renderer=drawing["renderer"])
            for q, name in zip(drawn, names)
        ]
    write_rows(rows, COLUMNS, outputs[2], outputs[1], group_by="query")
    for result in results:
        report_picture(result)
    finish(len(failures), len(meshes), "meshes")
    nothing_matched(len(rows), f"no object matched any of the {len(meshes)} query meshes")
    return True


def _has_meshes(query: str) -> bool:
    """A mesh file, or a folder holding one."""
    from ..mesh.objects import is_mesh_file
    from ..sources import find_curve_files

    if query == "-":
        return False
    if os.path.isdir(query):
        return any(is_mesh_file(f) for f in find_curve_files([query], meshes=True))
    return os.path.isfile(query) and is_mesh_file(query)


def _drawn(
    idx: Index, meshes: list[str], drawing: dict, picture: str, rows_output: str | None
) -> tuple[list, list[dict], list[str], list]:
    """``(drawn, rows, picture names, failures)`` of the query meshes against the open index:
    usage errors first, the pictures checked writable before the search."""
    from ..matching import DEFAULT_DIRECTION, DEFAULT_METHOD
    from ..show_objects import show_objects

    default = {"method": DEFAULT_METHOD, "direction": DEFAULT_DIRECTION, "mirror": False}
    for name, on in (
        ("--elastic", drawing["stage"] is not None),
        ("--method, --strict-direction or --mirror", drawing["matching"] != default),
    ):
        if on:
            raise click.UsageError(f"{name} does not apply to a mesh query (it ranks objects)")
    require_objects(idx)
    note_inputs(meshes)
    names = picture_names(picture, [SimpleNamespace(id=m) for m in meshes])
    check_pictures(names)
    for path in [*names, rows_output]:
        refuse_input_as_output(path)
    failures: list = []
    drawn, notes = show_objects(
        idx, meshes, k=drawing["top"], max_distance=drawing["max_distance"], exclude_self=drawing["exclude_self"],
        failures=failures,
    )  # fmt: skip
    report_mesh_failures(failures, meshes)
    for message in notes:
        note(message)
    spell_query, spell_match = path_speller(drawing["paths"]), path_speller(drawing["paths"], idx.locate)
    rows = [
        {
            "query": spell_query(mesh),
            "rank": s.rank,
            "match": spell_match(s.id),
            "distance": s.distance,
            "curves": " ".join("#" + c.rsplit("#", 1)[1] for c in s.match.curves),
            "source": s.source,
        }
        for mesh, q in zip(meshes, drawn)
        if q is not None
        for s in q.shown
    ]
    return drawn, rows, names, failures
