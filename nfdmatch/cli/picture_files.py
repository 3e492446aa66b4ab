"""The picture files of ``show`` and ``matrix``: one name per query, checked writable before
any long work, written only when every input was read, reported on stderr."""

from __future__ import annotations

import os
from collections.abc import Sequence
from typing import Any

import click

from .options import error, note, say

__all__ = ["report_picture", "not_written", "check_pictures", "picture_names"]


def report_picture(result: Any) -> None:
    if result.note:
        note(result.note)
    say(f"wrote {result.path} ({result.renderer}, {result.seconds:.2f} s)")


def not_written(pictures: Sequence[str]) -> list[str]:
    """Pictures, like row files, are written only when every input was read."""
    for path in pictures:
        error(f"{path} not written: some inputs could not be read")
    return []


def check_pictures(pictures: Sequence[str]) -> None:
    """Every picture path writable, before any long work."""
    from ..render import check_output

    for path in pictures:
        check_output(path)


def _stem(curve_id: str) -> str:
    """The {stem} of a query's pictures: its file name without extension, ``-I`` for curve I."""
    from ..formats import split_selector

    path, selected = split_selector(curve_id)
    stem = os.path.splitext(os.path.basename(path))[0].strip("<>") or "curve"
    return stem if selected is None else f"{stem}-{selected}"


def picture_names(pattern: str, queries: Sequence[Any]) -> list[str]:
    """One picture file per query, from ``pattern`` with ``{stem}`` and ``{n}`` (1-based)."""
    if "{" not in pattern:
        if len(queries) > 1:
            raise click.UsageError(
                f"{len(queries)} queries give {len(queries)} pictures: name them with a "
                "pattern, e.g. -o 'matches-{stem}.png' ({stem}: the query file's name, "
                "{n}: its number)"
            )
        return [pattern]
    try:
        names = [pattern.format(stem=_stem(q.id), n=n) for n, q in enumerate(queries, start=1)]
    except (KeyError, IndexError, ValueError) as exc:
        raise click.UsageError(f"-o {pattern!r}: the pattern may use {{stem}} and {{n}} only ({exc})") from None
    if len(set(names)) < len(names):
        raise click.UsageError(f"-o {pattern!r} gives two queries the same picture name; add {{n}}")
    return names
