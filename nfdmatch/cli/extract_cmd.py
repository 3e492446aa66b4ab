"""``extract``: closed contours of triangle meshes written as curve files."""

from __future__ import annotations

import os
import sys
from typing import TYPE_CHECKING, NoReturn

import click

from ..errors import NfdError
from .options import (
    EXIT_PARTIAL,
    NothingRead,
    ROW_FORMATS,
    count_failures,
    detail,
    error,
    finish,
    format_option,
    int_option,
    json_failure,
    note,
    note_inputs,
    output_option,
    report_errors,
    say,
)
from .output import FORMAT_OF_EXTENSION, deliver, write_rows
from .group import main

if TYPE_CHECKING:
    from ..errors import OverwriteRefusedError
    from ..mesh.contours import Contour, ExtractResult


@main.command()
@click.argument("meshes", nargs=-1, required=True, metavar="MESH...")
@click.option(
    "-o",
    "--output",
    "out_dir",
    required=True,
    multiple=True,  # to refuse a second -o, which click would let win silently
    type=click.Path(file_okay=False),
    help="Folder for the contour files (created if needed); once.",
)
@output_option(
    names=("--list",),
    dest="list_file",
    help="Write the list of contour files to FILE instead of stdout (whole, and only on success; "
    "a Make target): rows as its extension says (.csv, .tsv, .json, .jsonl), else one path per line.",
)
@int_option(
    "--sections",
    minimum=0,
    default=10,
    help="Number N of section planes (0: boundaries only, with --boundaries).",
)
@click.option(
    "--axis",
    type=click.Choice(["x", "y", "z", "auto", "principal"]),
    default="auto",
    show_default=True,
    help="Axis the planes are perpendicular to; auto: the longest side of the bounding box; principal: "
    "the rule `index build` cuts meshes by (N planes along each principal axis of the surface, pa, pb, "
    "pc, at area quantiles; docs/objects.md).",
)
@click.option("--boundaries", is_flag=True, help="Also extract the boundary loops of open meshes.")
@click.option(
    "--output-format",
    "curve_format",
    type=click.Choice(["obj", "csv", "vtp"]),
    default="obj",
    show_default=True,
    help="Curve file format of the written contours.",
)
@click.option(
    "--prune",
    is_flag=True,
    help="Remove DIR's contour files written by an earlier extract that this run no longer produces "
    "(levels moved, mesh deleted); files extract did not write are never touched.",
)
@click.option(
    "--force",
    is_flag=True,
    help="Replace files in DIR under a contour's name that extract did not write (or that were "
    "changed since); without it such a file is an error for its mesh (exit 3) and left alone.",
)
@format_option(help_extra=" of the list of written files (default: a table on a terminal, CSV otherwise)")
def extract(
    meshes: tuple[str, ...],
    out_dir: tuple[str, ...],
    list_file: str | None,
    sections: int,
    axis: str,
    boundaries: bool,
    curve_format: str,
    prune: bool,
    force: bool,
    output_format: str | None,
) -> None:
    """Write closed contours of triangle meshes (STL, PLY, OBJ, OFF, GLB/GLTF) as curve files.

    Each MESH (a file, or a folder searched recursively for mesh files) is cut by N
    planes perpendicular to the axis, at the middles of N equal slabs of its bounding
    box: lo + (i + 0.5) * (hi - lo) / N. Every closed loop of every section is written
    to its own file in DIR, named <mesh>_section-<axis><i>_at<level>_loop<k>; with
    --boundaries also the boundary loops of open meshes, <mesh>_boundary_loop<k>.
    The folder is then ready for `nfdmatch index build DIR`. DIR/.nfdmatch-extract.json
    records the files extract wrote; with --prune, those this run does not produce
    (stale levels, deleted meshes) are removed, unless changed since, or their mesh
    failed to read this run. A file in DIR under a contour's name that extract did
    not write (or that was changed since) is never replaced without --force: its mesh
    is reported as an error (exit 3) and its contours are not written.

    stdout lists the written files (file, mesh, kind, axis, level, loop, vertices).
    Notes on stderr: open section pieces skipped, meshes that gave nothing. A file
    that is not a readable mesh is named on stderr and skipped (exit 3); exit 2 when
    no mesh gave any contour.

    \b
    Examples:
      nfdmatch extract part.stl -o contours/ --sections 20
      nfdmatch extract scans/ -o contours/ --axis z --boundaries --output-format vtp
      nfdmatch extract part.stl -o contours/ --axis principal --sections 7   # as index build cuts it
      nfdmatch extract parts/ -o contours/ --prune   # the folder then holds this run's contours
      nfdmatch index build contours/ --index parts.h5
    """
    from ..errors import MeshError, ParameterError
    from ..mesh import find_mesh_files, write_contours

    if len(out_dir) > 1:
        raise click.UsageError(
            f"-o names the one folder for the contours, given {len(out_dir)} times ({', '.join(out_dir)}); "
            "the list of files goes to stdout or to --list FILE"
        )
    out_dir = out_dir[0]
    list_format = _list_format(list_file, output_format)
    if sections == 0 and not boundaries:
        raise click.UsageError("nothing to extract: --sections 0 needs --boundaries")
    files = find_mesh_files(meshes, exclude=[out_dir])
    if not files:
        raise ParameterError(f"no mesh files found in {', '.join(meshes)}")
    note_inputs(files)  # so that --list naming a mesh is refused
    results, errors = _extract_all(files, sections, axis, boundaries)
    contours, refused = _writable_contours(results, out_dir, curve_format, force)
    report_errors(errors + refused)
    if errors or refused:
        count_failures(len(errors) + len(refused), errors + refused)  # exit 3 to come: --list is not written
    if not contours:
        if refused:
            _exit_refused(refused, files)
        if results:  # Error: and, with --format json/jsonl, the JSON record (exit 2)
            raise MeshError(f"no closed contour in {'the mesh' if len(files) == 1 else 'any mesh'}; nothing written")
        raise NothingRead()  # each mesh named above
    written = write_contours(contours, out_dir, format=curve_format, force=force)
    _write_list(written, contours, list_file, list_format, output_format)
    pruned = _prune(out_dir, written, errors, refused) if prune else ""
    meshes_with = len({c.mesh for c in contours})
    say(f"{len(written)} contours from {meshes_with} of {len(files)} meshes written to {out_dir}{pruned}")
    if refused and not errors:
        _exit_refused(refused, files)
    if refused:
        error(_refused_text(refused, files))
    finish(len(errors), len(files), "meshes")


def _refused_text(refused: list[OverwriteRefusedError], files: list[str]) -> str:
    return f"{len(refused)} of {len(files)} meshes not written: files in the way (see above)"


def _exit_refused(refused: list[OverwriteRefusedError], files: list[str]) -> NoReturn:
    """Exit 3 for meshes refused (files in the way), with the JSON record of a partial run."""
    message = _refused_text(refused, files)
    error(message)
    json_failure(click.get_current_context(), message, EXIT_PARTIAL)
    sys.exit(EXIT_PARTIAL)


def _list_format(list_file: str | None, output_format: str | None) -> str | None:
    """The format of --list FILE: --format, else its extension's; "paths" (one a line) for
    a table or an unknown extension; None without --list."""
    if list_file is None:
        return None
    ext = os.path.splitext(list_file)[1].lower()
    list_format = output_format or FORMAT_OF_EXTENSION.get(ext)
    if list_format not in ROW_FORMATS or list_format == "table":
        list_format = "paths"
    return list_format


def _extract_all(
    files: list[str], sections: int, axis: str, boundaries: bool
) -> tuple[list[ExtractResult], list[NfdError]]:
    """The contours of every mesh file, and the errors of those that could not be read;
    each result's notes go to stderr."""
    from ..mesh import extract_contours

    from ..mesh.objects import principal_contours

    results, errors = [], []
    if axis == "principal" and sections < 1:
        raise click.UsageError("--axis principal needs --sections 1 or more")
    for path in files:
        try:
            if axis == "principal":  # the rule index build cuts objects by
                results.append(principal_contours(path, sections=sections, boundaries=boundaries))
            else:
                results.append(extract_contours(path, sections=sections, axis=axis, boundaries=boundaries))
        except NfdError as exc:
            errors.append(exc)
    for result in results:
        for message in result.notes:
            note(message)
    return results, errors


def _writable_contours(
    results: list[ExtractResult], out_dir: str, curve_format: str, force: bool
) -> tuple[list[Contour], list[OverwriteRefusedError]]:
    """The contours to write and the errors of the meshes refused: without --force, a mesh
    with a file in the way that extract did not write fails (exit 3), the others go on."""
    from ..mesh import read_manifest, refused_targets

    contours = [c for result in results for c in result.contours]
    refused = []
    if contours:
        problem = read_manifest(out_dir)[1]  # rewritten below: say so once
        if problem:
            note(problem)
    if contours and not force:
        refused = refused_targets(contours, out_dir, format=curve_format)
        blocked = {exc.mesh for exc in refused}
        contours = [c for c in contours if c.mesh not in blocked]
    return contours, refused


def _write_list(
    written: list[str],
    contours: list[Contour],
    list_file: str | None,
    list_format: str | None,
    output_format: str | None,
) -> None:
    """The list of the written files: rows (stdout or --list FILE), or paths one a line."""
    rows = [
        {
            "file": path,
            "mesh": c.mesh,
            "kind": c.kind,
            "axis": c.axis,
            "level": c.level,
            "loop": c.loop,
            "vertices": c.n_vertices,
        }
        for path, c in zip(written, contours)
    ]
    columns = ["file", "mesh", "kind", "axis", "level", "loop", "vertices"]
    if list_format == "paths":
        deliver("".join(f"{row['file']}\n" for row in rows), list_file)
    else:
        write_rows(rows, columns, list_format or output_format, list_file, group_by="mesh")


def _prune(out_dir: str, written: list[str], errors: list[NfdError], refused: list[OverwriteRefusedError]) -> str:
    """--prune: remove the stale contour files of earlier runs (keeping those of meshes
    that failed this run); returns the summary's clause."""
    from ..mesh import prune_contours

    kept = [e.path for e in errors if e.path] + [e.mesh for e in refused]
    result = prune_contours(out_dir, written, keep_meshes=kept)
    for message in result.notes:
        note(message)
    for path in result.removed:
        detail(f"removed {path}")
    for path, why in result.kept:
        note(f"{path}: not pruned: {why}")
    return f"; {len(result.removed)} stale contour file{'' if len(result.removed) == 1 else 's'} removed"
