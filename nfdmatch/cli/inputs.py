"""Reading a command's inputs: :func:`read_inputs` (files, folders, ``-`` for stdin) and
:func:`read_one`. One policy: every input that can be read is answered, each bad one is
named on stderr, :func:`~nfdmatch.cli.options.finish` exits 3 when some failed, and nothing
read at all is exit 2. Also which match is the query itself (``--exclude-self``)."""

from __future__ import annotations

import os
import sys
import tempfile
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import click

from ..curve import STDIN_ID
from ..errors import NfdError, NoCurvesError
from .options import NothingRead, count_failures, detail, error, finish, note_inputs, report_errors

if TYPE_CHECKING:
    from collections.abc import Callable, Sequence

    from ..curve import Curve

    #: a progress bar's update (:func:`~.output.progress_bar`): files done, of how many
    Update = Callable[[int, int | None], None]

#: the id of a curve read from stdin (``-`` on the command line)


@dataclass
class Inputs:
    """What :func:`read_inputs` read: ``curves`` in input order, ``errors`` (each already
    named on stderr) and ``total``, the number of inputs (files found plus bad sources)."""

    curves: list
    errors: list = field(default_factory=list)
    total: int = 0

    def finish(self, what: str = "inputs") -> None:
        finish(len(self.errors), self.total, what)


def _stdin_curves(input_format: str | None) -> list:
    """The curves of the file on stdin, read as ``input_format``; ids ``<stdin>``, ``<stdin>#i``."""
    from ..curve import Curve
    from ..formats import FORMATS, read_curves
    from ..formats._stream import copy_capped, stdin_line_limit

    if input_format is None:
        raise click.UsageError("reading a curve from stdin ('-') needs --input-format")
    fd, temp = tempfile.mkstemp(suffix=FORMATS[input_format][0])
    try:
        try:
            with os.fdopen(fd, "wb") as f:  # the caps checked while reading, not after
                copy_capped(sys.stdin.buffer, f, name=STDIN_ID, line_limit=stdin_line_limit(input_format))
            curves = read_curves(temp, format=input_format)
        except NfdError as exc:
            raise type(exc)(exc.message, path=STDIN_ID, line=exc.line, curve=exc.curve) from None
    finally:
        os.remove(temp)
    if len(curves) == 1:
        return [Curve(curves[0].points, id=STDIN_ID)]
    return [Curve(c.points, id=f"{STDIN_ID}#{i}") for i, c in enumerate(curves)]


def read_one(spec: str, input_format: str | None = None) -> Curve:
    """One curve (``FILE``, ``FILE#I`` or ``-``): a curve the command cannot do without."""
    if spec == "-":
        curves = _stdin_curves(input_format)
        if len(curves) != 1:
            raise click.UsageError(f"stdin holds {len(curves)} curves; one is expected here")
        curve = curves[0]
    else:
        from ..formats import read_curve

        curve = read_curve(spec, format=input_format)
        note_inputs([curve.source or spec])
    detail(f"read {curve.id} ({len(curve.points)} vertices)")
    return curve


#: files read between two updates of a progress bar
_PROGRESS_CHUNK = 64


def read_inputs(
    specs: Sequence[str | os.PathLike[str]],
    *,
    glob: str | None = None,
    input_format: str | None = None,
    progress: str | None = None,
) -> Inputs:
    """Read every curve of the files and folders ``specs`` (``-``: stdin).

    A missing file, an empty folder (no curve file, or none matching ``glob``) and a file
    that cannot be read are each named on stderr and counted as failed inputs; raises
    :class:`NothingRead` (exit 2) when no curve was read at all. ``progress``: the label
    of a progress bar over the files read (on a terminal only, :func:`progress_bar`)."""
    from ..sources import find_curve_files, read_all

    update, finish_bar = (None, None) if progress is None else _progress_bar(progress)
    try:
        return _read_inputs(specs, glob, input_format, update, find_curve_files, read_all)
    finally:
        if finish_bar is not None:
            finish_bar()


def _progress_bar(label: str) -> tuple[Update | None, Callable[[], None]]:
    from .output import progress_bar

    return progress_bar(label)


def _read_inputs(
    specs: Sequence[str | os.PathLike[str]],
    glob: str | None,
    input_format: str | None,
    update: Update | None,
    find_curve_files: Callable[..., list[str]],
    read_all: Callable[..., tuple[list[Curve], list[NfdError]]],
) -> Inputs:
    expected = None
    if update is not None:  # the files to read, for the bar's total (a second walk: cheap beside reading)
        expected = 0
        for spec in dict.fromkeys(str(s) for s in specs):
            try:
                expected += 1 if spec == "-" else len(find_curve_files([spec], glob=glob))
            except NfdError:
                pass
        update(0, expected)
    done = 0

    def read_files(paths: list[str]) -> tuple[list[Curve], list[NfdError]]:
        nonlocal done
        if update is None:
            return read_all(paths, format=input_format)
        read, read_errors = [], []
        for start in range(0, len(paths), _PROGRESS_CHUNK):
            chunk_read, chunk_errors = read_all(paths[start : start + _PROGRESS_CHUNK], format=input_format)
            read += chunk_read
            read_errors += chunk_errors
            done += len(paths[start : start + _PROGRESS_CHUNK])
            update(done, max(expected, done))
        return read, read_errors

    seen: set[str] = set()
    curves, errors, total = [], [], 0
    for spec in dict.fromkeys(str(s) for s in specs):  # stdin is read once
        if spec == "-":
            total += 1
            try:
                curves += _stdin_curves(input_format)
            except NfdError as exc:
                errors.append(exc)
                error(exc)
            continue
        try:
            found = find_curve_files([spec], glob=glob)
            if not found:
                raise NoCurvesError(
                    "no curve files found" + (f" matching {glob!r}" if glob else "") + _meshes_hint(spec, glob),
                    path=spec,
                )
        except NfdError as exc:
            total += 1
            errors.append(exc)
            error(exc)
            continue
        new = [path for path in found if os.path.normpath(path) not in seen]
        note_inputs(new)
        seen.update(os.path.normpath(path) for path in new)
        total += len(new)
        read, read_errors = read_files(new)
        curves += read
        errors += read_errors
        report_errors(read_errors)
    if errors:
        count_failures(len(errors), errors)
    if not curves:
        raise NothingRead()
    detail(f"read {len(curves)} curve{'' if len(curves) == 1 else 's'} from {total - len(errors)} of {total} inputs")
    return Inputs(curves, errors, total)


def _meshes_hint(folder: str, glob: str | None) -> str:
    """For a folder without curve files: what to do when it holds meshes (a mesh query
    needs an index built from meshes; this index, or this command, takes curves)."""
    from ..sources import find_curve_files

    if not os.path.isdir(folder):
        return ""
    meshes = find_curve_files([folder], glob=glob, meshes=True)
    if not meshes:
        return ""
    return (
        f" (it holds {len(meshes)} mesh file{'s' if len(meshes) != 1 else ''}: a mesh query needs an index built "
        "from meshes, `nfdmatch index build MESHES --index I`; or extract contours first, `nfdmatch extract`)"
    )
