"""Writing a command's output: the row formats, ``-o`` (written whole and only on success,
through one atomic writer), :func:`write_rows` and :func:`deliver`, tables that fit the
terminal, progress bars on stderr (redrawn at most every :data:`REDRAW_SECONDS`).

Test hook: ``_clock``, the progress bars' clock, which tests replace to count redraws.
"""

from __future__ import annotations

import csv
import io
import json
import os
import sys
import time
from typing import TYPE_CHECKING, Any

import click

from ..errors import WriteError
from .options import (
    NORMAL,
    ROW_FORMATS,
    STDOUT,
    check_writable,
    detail,
    error,
    refuse_input_as_output,
    remember_format,
    some_failed,
    stdout_used,
    use_color,
    verbosity,
)

if TYPE_CHECKING:
    from collections.abc import Callable, Iterable, Sequence

    from ..records import RankedMatch
    from ..search.stages import Stage

#: the format a ``-o FILE`` gets from its extension when --format is not given (each
#: command accepts those of its formats); any other extension is a usage error
FORMAT_OF_EXTENSION = {
    ".csv": "csv",
    ".tsv": "tsv",
    ".json": "json",
    ".jsonl": "jsonl",
    ".npz": "npz",
    ".txt": "text",
}
#: the extensions of picture files (``show``, ``matrix``); any other ``-o`` gets rows
PICTURE_EXTENSIONS = (".png", ".svg", ".pdf")


def split_outputs(
    paths: Sequence[str], formats: Sequence[str] = ROW_FORMATS, fmt: str | None = None
) -> tuple[list[str], str | None]:
    """``-o`` paths of a picture command: pictures by extension (.png, .svg, .pdf), rows
    for the one other path (None: stdout; ``-o -`` is stdout too). An extension that is
    neither a picture's nor one of ``formats`` is a usage error naming both, unless
    ``--format`` (``fmt``) says what the rows are, as it does for every other command."""
    pictures = [p for p in paths if os.path.splitext(p)[1].lower() in PICTURE_EXTENSIONS]
    rows = [p for p in paths if p not in pictures]
    if len(rows) > 1:
        raise click.UsageError(
            f"one -o for the rows at most (pictures end in {', '.join(PICTURE_EXTENSIONS)}); got {', '.join(rows)}"
        )
    row_output = rows[0] if rows and rows[0] != STDOUT else None
    if row_output is not None and fmt is None:
        ext = os.path.splitext(row_output)[1].lower()
        if FORMAT_OF_EXTENSION.get(ext) not in formats:
            known = [e for e, f in FORMAT_OF_EXTENSION.items() if f in formats]
            raise click.UsageError(
                f"-o {row_output}: {_extension_text(ext)} is neither a picture ({', '.join(PICTURE_EXTENSIONS)}) "
                f"nor rows ({', '.join(known)})"
            )
    return pictures, row_output


def _extension_text(ext: str) -> str:
    return f"the extension {ext!r}" if ext else "no extension"


def resolve_format(
    fmt: str | None,
    output: str | None,
    formats: Sequence[str] = ROW_FORMATS,
    *,
    terminal: str = "table",
    piped: str = "csv",
) -> str:
    """The output format: as given (``--format``), else by the extension of ``output``
    (:data:`FORMAT_OF_EXTENSION`, among ``formats``: any other extension is a usage error
    naming the extensions and formats, as a box-drawing table in ``out.txt`` would
    surprise), else ``terminal`` when stdout is a terminal and ``piped`` otherwise.
    Commands call it before any work, so that the usage error comes first."""
    if fmt is not None:
        return remember_format(fmt)
    if output is not None:
        ext = os.path.splitext(output)[1].lower()
        found = FORMAT_OF_EXTENSION.get(ext)
        if found in formats:
            return remember_format(found)  # type: ignore[return-value]
        known = [e for e, f in FORMAT_OF_EXTENSION.items() if f in formats]
        raise click.UsageError(
            f"cannot tell the format of -o {output} from {_extension_text(ext)}: name the file "
            f"{', '.join(known)}, or give --format {'|'.join(formats)}"
        )
    return remember_format(terminal if stdout_is_terminal() else piped)


def path_speller(mode: str, locate: Callable[[str], str] | None = None) -> Callable[[str], str]:
    """``id -> id`` as ``--paths`` asks: ``id`` leaves it; ``absolute`` / ``relative`` (to the
    working directory) spell the file of the id, ``#i`` kept. ``locate``: a stored id -> a
    path that opens it from here (an index's ids are relative to its folder). Ids that are
    no file (stdin) stay as they are."""
    if mode == "id":
        return lambda curve_id: curve_id
    from ..curve import STDIN_ID

    from ..names import decode_name, encode_name

    def spell(curve_id: str) -> str:
        if curve_id.startswith(STDIN_ID):
            return curve_id
        where = locate(curve_id) if locate is not None else decode_name(curve_id)
        full = os.path.abspath(where)
        return encode_name(full if mode == "absolute" else os.path.relpath(full))

    return spell


def match_row(query_id: str, m: RankedMatch) -> dict[str, Any]:
    """The row `rank` and `query` print for one :class:`~nfdmatch.records.RankedMatch`
    (columns: :func:`match_columns`, and ``score`` after a re-ranking)."""
    return {
        "query": query_id,
        "rank": m.rank,
        "match": m.id,
        "distance": m.distance,
        "score": m.score,
        "elastic": m.elastic,
        "fused": m.fused,
        "shift": m.shift,
        "reversed": m.reversed,
        "mirrored": m.mirrored,
    }


def match_columns(details: bool, stage: Stage | None = None) -> list[str]:
    """Columns of the rows `rank` and `query` print; a re-ordering ``stage``'s columns
    follow the distance."""
    columns = ["query", "rank", "match", "distance"] + (["shift", "reversed", "mirrored"] if details else [])
    if stage is not None:
        at = columns.index("distance") + 1
        columns[at:at] = list(stage.columns)
    return columns


#: columns that hold curve ids (a file's name encoded, :mod:`nfdmatch.names`): printed as
#: the name itself (raw bytes) except in a table on a terminal
NAME_COLUMNS = ("query", "match", "id", "curve")


def decoded_names(rows: list[dict], names: Iterable[str] = NAME_COLUMNS) -> list[dict]:
    """``rows`` with the ids of the columns ``names`` decoded to the file names they encode
    (:func:`nfdmatch.names.decode_name`): what goes to a pipe or a file."""
    from ..names import decode_name

    names = [c for c in names if any(isinstance(row.get(c), str) and "\\" in row[c] for row in rows)]
    if not names:
        return rows
    return [{**row, **{c: decode_name(row[c]) for c in names if isinstance(row.get(c), str)}} for row in rows]


def write_rows(
    rows: list[dict],
    columns: list[str],
    fmt: str | None,
    output: str | None = None,
    *,
    group_by: str | None = None,
    names: Iterable[str] = NAME_COLUMNS,
) -> None:
    """Write rows to ``output`` (stdout when None) as a table, CSV, TSV, JSON (a list) or
    JSON lines. Machine formats carry no markup; floats keep full precision (repr).
    ``group_by``: in a table, a heading per value of this column instead of the column.
    ``names``: the columns holding ids, written as the file names they encode (the raw bytes
    of a name that is not UTF-8; in JSON, ``\\udcNN`` for such a byte), except in a table
    on a terminal, which shows the ids (``\\xNN``), as ``ls`` escapes on a terminal."""
    fmt = resolve_format(fmt, output)
    terminal = fmt == "table" and output is None and stdout_is_terminal()
    if not terminal:
        rows = decoded_names(rows, names)
    if fmt == "table":
        text = render_table(
            rows, columns, group_by=group_by, terminal=terminal, styled=output is None and use_color(terminal)
        )
    elif fmt in ("csv", "tsv"):
        text = delimited_text(columns, ([_cell_text(row.get(c)) for c in columns] for row in rows), fmt)
    elif fmt == "json":
        text = json.dumps([{c: row.get(c) for c in columns} for row in rows], indent=2) + "\n"
    elif fmt == "jsonl":
        text = "".join(json.dumps({c: row.get(c) for c in columns}) + "\n" for row in rows)
    else:  # pragma: no cover - click restricts the choices
        raise click.UsageError(f"unknown format {fmt}")
    deliver(text, output)


def delimiter(fmt: str) -> str:
    """The field separator of ``fmt`` (csv or tsv)."""
    return "," if fmt == "csv" else "\t"


#: TSV's escapes (as PostgreSQL's COPY and MySQL's TSV): a field never holds a TAB or a line
#: break, so ``cut -f`` and ``awk -F'\t'`` split every line right
TSV_ESCAPES = {"\\": "\\\\", "\t": "\\t", "\n": "\\n", "\r": "\\r"}
_TSV_SPECIAL = str.maketrans(TSV_ESCAPES)


def tsv_field(value: str) -> str:
    """``value`` as a TSV field: backslash, TAB, newline and carriage return written
    ``\\\\``, ``\\t``, ``\\n``, ``\\r``; nothing quoted."""
    return value.translate(_TSV_SPECIAL)


def delimited_text(header: list[str], rows: Iterable[Sequence[str]], fmt: str) -> str:
    """A header line then the rows (lists of str), as CSV (RFC 4180 quoting) or TSV
    (backslash escapes, :func:`tsv_field`)."""
    if fmt == "tsv":
        return "".join("\t".join(map(tsv_field, row)) + "\n" for row in (header, *rows))
    buf = io.StringIO()
    writer = csv.writer(buf, delimiter=delimiter(fmt), lineterminator="\n")
    writer.writerow(header)
    writer.writerows(rows)
    return buf.getvalue()


def delimited_fields(values: list[str], fmt: str) -> list[str]:
    """Each value as :func:`delimited_text` writes it as the first field of a row of
    several (CSV: quoted where it holds a separator, quote or line break; TSV: escaped)."""
    if fmt == "tsv":
        return [tsv_field(value) for value in values]
    buf = io.StringIO()
    writer = csv.writer(buf, delimiter=delimiter(fmt), lineterminator="\n")
    fields = []
    for value in values:
        buf.seek(0)
        buf.truncate()
        writer.writerow([value, ""])  # "<field><sep>\n"
        fields.append(buf.getvalue()[:-2])
    return fields


def _cell_text(value: object, pretty: bool = False) -> str:
    if value is None:
        return ""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        return f"{value:.6g}" if pretty else repr(value)
    if isinstance(value, (list, dict)):
        return json.dumps(value)
    return str(value)


#: columns that hold curve ids or file paths: their common folder is shown once
PATH_COLUMNS = ("query", "match", "id", "file", "curve", "mesh", "path")


def common_folder(values: Iterable[str]) -> str:
    """The longest folder prefix (ending in ``/``) shared by all ``values``; '' if none."""
    values = [v for v in values if v]
    if not values:
        return ""
    prefix = os.path.commonprefix(values)
    cut = prefix.rfind("/")
    return prefix[: cut + 1] if cut >= 0 else ""


def render_table(
    rows: list[dict],
    columns: list[str],
    *,
    group_by: str | None = None,
    terminal: bool = False,
    width: int | None = None,
    styled: bool | None = None,
) -> str:
    """A rich table as text that fits ``width`` (default: the terminal's): the folder all
    paths of a column share is said once above the table, long ids wrap inside their cell,
    and with ``group_by`` each value of that column heads its own table. ``styled``
    (default: ``terminal``): bold and dim as escape sequences; else none at all."""
    import shutil

    from rich.console import Console
    from rich.table import Table

    if width is None:
        width = shutil.get_terminal_size((120, 24)).columns
    shown = [c for c in columns if c != group_by]
    paths = [c for c in shown if c in PATH_COLUMNS]
    folder = common_folder([str(row.get(c) or "") for row in rows for c in paths])
    buf = io.StringIO()
    styled = terminal if styled is None else styled
    console = Console(
        file=buf,
        width=width,
        force_terminal=styled,
        color_system="standard" if styled else None,  # None: no escape sequence (NO_COLOR: no bold either)
        highlight=False,
        soft_wrap=False,
    )
    if folder and len(folder) > 1:
        console.print(f"[dim]paths under[/dim] {folder}", markup=True, overflow="fold")
    groups: list[tuple[str | None, list[dict]]] = []
    for row in rows:
        key = None if group_by is None else str(row.get(group_by))
        if not groups or groups[-1][0] != key:
            groups.append((key, []))
        groups[-1][1].append(row)
    if not groups:
        groups = [(None, [])]
    key_folder = common_folder([k for k, _ in groups if k]) if group_by in PATH_COLUMNS else ""
    if len(groups) > 1 and len(key_folder) > 1:
        console.print(f"[dim]{group_by} paths under[/dim] {key_folder}", markup=True, overflow="fold")
    else:
        key_folder = ""
    for key, group in groups:
        if key is not None:
            console.print(f"[bold]{group_by}:[/bold] {key[len(key_folder) :]}", markup=True, overflow="fold")
        table = Table(show_header=True, header_style="bold")
        for col in shown:
            sample = group[0].get(col) if group else None
            numeric = isinstance(sample, (int, float)) and not isinstance(sample, bool)
            table.add_column(col, justify="right" if numeric else "left", no_wrap=numeric, overflow="fold")
        for row in group:
            cells = []
            for col in shown:
                text = _cell_text(row.get(col), pretty=True)
                if col in paths and folder and text.startswith(folder):
                    text = text[len(folder) :]
                cells.append(text)
            table.add_row(*cells)
        console.print(table)
    return buf.getvalue()


# --------------------------------------------------------------------------- writing


def deliver(text: str, output: str | None) -> None:
    """``text`` on stdout, or written whole to the file ``output`` (see :func:`write_if_changed`).

    A file is written only when the command succeeds: after an input failed (exit 3 to
    come) it is left as it was, so that Make does not take a partial answer for done."""
    if output is None:
        stdout_used()
        try:
            text.isascii() or text.encode("utf-8")
        except UnicodeEncodeError:  # a name that is not UTF-8: its bytes, as ls and find print it
            click.echo(text.encode("utf-8", "surrogateescape"), nl=False)
            return
        click.echo(text, nl=False, color=True)  # escapes only in a styled table (--color decides)
        return
    if some_failed():
        error(f"{output} not written: some inputs could not be read")
        return
    if write_if_changed(output, text.encode("utf-8", "surrogateescape")):
        detail(f"wrote {output}")
    else:
        detail(f"{output} unchanged (mtime refreshed)")


def write_if_changed(path: str, data: bytes) -> bool:
    """Write ``data`` to ``path`` whole (:func:`nfdmatch._io.write_file`: a temporary file in
    the same folder, flushed, then renamed over it), so ``path`` is never seen half written;
    a file that already holds exactly ``data`` is kept but gets a fresh mtime (a command
    that succeeds leaves its outputs newer than its inputs: Make settles). Returns True when
    the bytes changed. I/O problems raise :class:`WriteError`; a ``path`` that is one of the
    command's inputs is a usage error (:func:`~.options.refuse_input_as_output`)."""
    from .._io import write_file

    check_writable(path)
    refuse_input_as_output(path)
    try:
        return write_file(path, data)
    except OSError as exc:
        raise WriteError(f"cannot write the file ({exc.strerror or exc})", path=path) from None


def stderr_is_terminal() -> bool:
    return sys.stderr.isatty()


def stdout_is_terminal() -> bool:
    return sys.stdout.isatty()


#: the shortest time between two redraws of a progress bar: at most ~10 a second
REDRAW_SECONDS = 0.1
#: the clock of the progress bars (a test hook: tests replace it to count redraws)
_clock = time.monotonic


def progress_bar(description: str) -> tuple[Callable[[int, int | None], None] | None, Callable[[], None]]:
    """(callback, finish) for a rich progress bar on stderr, only when stderr is a terminal
    and not ``-q``."""
    if not stderr_is_terminal() or verbosity() < NORMAL:
        return None, lambda: None
    from rich.console import Console
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

    # no auto-refresh thread: a running thread would force the build's workers off fork
    bar = Progress(
        TextColumn(description),
        BarColumn(),
        MofNCompleteColumn(),
        TimeRemainingColumn(),
        console=Console(stderr=True, force_terminal=True, color_system="standard" if use_color(True) else None),
        transient=True,
        auto_refresh=False,
    )
    task = bar.add_task(description, total=None)
    bar.start()
    last = -float("inf")

    def update(done: int, total: int | None) -> None:
        nonlocal last
        bar.update(task, completed=done, total=total)
        now = _clock()
        # a redraw per file made a terminal cost ~3x the piped time (10,000 files: 2 MB of
        # escapes); the last step is drawn so the bar ends full
        if now - last >= REDRAW_SECONDS or (total is not None and done >= total):
            last = now
            bar.refresh()

    return update, bar.stop
