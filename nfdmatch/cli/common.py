"""What every command shares, defined once so that every command behaves the same.

- :class:`NfdGroup`, the group class of ``nfdmatch`` and ``nfdmatch index``: every
  :class:`~nfdmatch.errors.NfdError` raised while a command runs (its options included)
  becomes ``Error: <message>`` on stderr and exit 1, never a traceback; ``-q``/``-v``
  are added to every command.
- Messages: :func:`note` (hidden by ``-q``), :func:`detail` (shown by ``-v``), :func:`error`
  (always). stdout carries data only; everything else goes to stderr.
- Inputs: :func:`read_inputs` (files, folders, ``-`` for stdin) and :func:`read_one`. One
  policy: every input that can be read is answered, each bad one is named on stderr,
  :func:`finish` exits 3 when some failed, and nothing read at all is exit 1.
- Outputs: ``--format`` (:func:`format_option`), ``-o/--output`` (:func:`output_option`),
  the row writer :func:`write_rows` and :func:`deliver`, which writes a file whole and
  only on success, leaving an identical file untouched (mtime kept) for Make.

Exit codes: 0 ok, 1 error (bad input or any NfdError), 2 usage error, 3 partial success
(some inputs failed, the rest was answered), 130 interrupted (SIGINT, Ctrl-C), 143
terminated (SIGTERM); both without a traceback, after the command cleaned up.
"""

from __future__ import annotations

import csv
import io
import json
import os
import sys
import tempfile
import time
from dataclasses import dataclass, field

import click

from ..errors import NfdError, NoCurvesError, WriteError

EXIT_OK, EXIT_ERROR, EXIT_USAGE, EXIT_PARTIAL = 0, 1, 2, 3
#: 128 + the signal number, as a shell reports a process ended by SIGINT / SIGTERM
EXIT_INTERRUPTED, EXIT_TERMINATED = 130, 143
ROW_FORMATS = ("table", "csv", "tsv", "json", "jsonl")
#: the row format a ``-o FILE`` gets from its extension when --format is not given
FORMAT_OF_EXTENSION = {".csv": "csv", ".tsv": "tsv", ".json": "json", ".jsonl": "jsonl", ".txt": "table"}
#: the extensions of picture files (``show``, ``matrix``); any other ``-o`` gets rows
PICTURE_EXTENSIONS = (".png", ".svg", ".pdf")
#: the id of a curve read from stdin (``-`` on the command line)
STDIN_ID = "<stdin>"

QUIET, NORMAL, VERBOSE = 0, 1, 2
_VERBOSITY = "nfdmatch.verbosity"


# --------------------------------------------------------------------------- errors and exit codes


class NothingRead(Exception):
    """Raised by commands when no input could be read (each was already named): exit 1."""


class NfdGroup(click.Group):
    """A click group whose commands all share the error policy and ``-q``/``-v``."""

    group_class = type  # subgroups (``index``) are NfdGroups too

    def add_command(self, cmd, name=None):
        if not isinstance(cmd, click.Group):
            cmd.params.extend(_verbosity_params())
        super().add_command(cmd, name)

    def invoke(self, ctx):
        started = time.perf_counter()
        restore = _catch_sigterm() if ctx.parent is None else None
        try:
            return super().invoke(ctx)
        except KeyboardInterrupt as exc:  # Ctrl-C or SIGTERM: the library cleaned up on its way out
            terminated = isinstance(exc, Terminated)
            error(f"{'terminated (SIGTERM)' if terminated else 'interrupted (SIGINT)'}")
            sys.exit(EXIT_TERMINATED if terminated else EXIT_INTERRUPTED)
        except NfdError as exc:
            error(exc)
            sys.exit(EXIT_ERROR)
        except NothingRead:
            sys.exit(EXIT_ERROR)
        except BrokenPipeError:  # e.g. `nfdmatch describe ... | head`
            sys.stderr.close()
            sys.exit(EXIT_OK)
        finally:
            if ctx.parent is None:
                _say_kernels_unused()
            if ctx.parent is None and ctx.invoked_subcommand:
                detail(f"{ctx.invoked_subcommand}: {time.perf_counter() - started:.2f} s")
            if restore is not None:
                restore()


def _say_kernels_unused() -> None:
    """One line on stderr when this run found the compiled kernels damaged and used the
    others (the library only records why: ``matching.aot.unused_reason``)."""
    aot = sys.modules.get("nfdmatch.matching.aot")  # imported only when a command used it
    reason = aot.unused_reason() if aot is not None else None
    if reason:
        note(reason, prefix="Warning: ")


class Terminated(KeyboardInterrupt):
    """Raised in the main thread on SIGTERM, so that a command unwinds as on Ctrl-C
    (temporary files removed, worker processes stopped) and exits 143."""


def _raise_terminated(signum, frame):
    raise Terminated()


def _catch_sigterm():
    """SIGTERM raises :class:`Terminated` while a command runs; returns what restores the
    previous handler (None off the main thread, where handlers cannot be set)."""
    import signal
    import threading

    if threading.current_thread() is not threading.main_thread():
        return None
    previous = signal.signal(signal.SIGTERM, _raise_terminated)
    return lambda: signal.signal(signal.SIGTERM, previous)


def _set_verbosity(ctx, param, value):
    if value:
        level = QUIET if param.name == "quiet" else VERBOSE
        if ctx.meta.get(_VERBOSITY, level) != level:
            raise click.UsageError("-q/--quiet and -v/--verbose exclude each other", ctx=ctx)
        ctx.meta[_VERBOSITY] = level


_VERBOSITY_OPTIONS = (
    (("-q", "--quiet"), "Errors only: no notes, summaries or progress on stderr."),
    (("-v", "--verbose"), "Also say what is read, what is written and how long it took (stderr)."),
)


def _verbosity_params() -> list[click.Option]:
    return [
        click.Option(list(names), is_flag=True, expose_value=False, callback=_set_verbosity, help=text)
        for names, text in _VERBOSITY_OPTIONS
    ]


def verbosity_options(f):
    """``-q``/``-v`` on the group itself (``nfdmatch -q query ...``)."""
    for names, text in reversed(_VERBOSITY_OPTIONS):
        f = click.option(*names, is_flag=True, expose_value=False, callback=_set_verbosity, help=text)(f)
    return f


def verbosity() -> int:
    ctx = click.get_current_context(silent=True)
    return NORMAL if ctx is None else ctx.meta.get(_VERBOSITY, NORMAL)


def note(message: str, *, prefix: str = "Note: ") -> None:
    """A message for the user on stderr, unless ``-q``."""
    if verbosity() >= NORMAL:
        click.echo(f"{prefix}{message}", err=True)


def say(message: str) -> None:
    """A summary line on stderr (``wrote x``, counts), unless ``-q``."""
    note(message, prefix="")


def detail(message: str) -> None:
    """A line on stderr only with ``-v``."""
    if verbosity() >= VERBOSE:
        click.echo(message, err=True)


def error(exc_or_message) -> None:
    """``Error: <message>`` on stderr, always (the message names the file and line)."""
    click.echo(f"Error: {exc_or_message}", err=True)


def report_errors(errors) -> None:
    for exc in errors:
        error(exc)


_FAILED = "nfdmatch.failed"


def _count_failures(n: int) -> None:
    ctx = click.get_current_context(silent=True)
    if ctx is not None:
        ctx.meta[_FAILED] = ctx.meta.get(_FAILED, 0) + n


def some_failed() -> bool:
    """True once an input of this command could not be read."""
    ctx = click.get_current_context(silent=True)
    return bool(ctx is not None and ctx.meta.get(_FAILED))


def finish(failed: int, total: int, what: str = "inputs") -> None:
    """The end of every command that reads several inputs: exit 3 when some failed."""
    if failed:
        error(f"{failed} of {total} {what} could not be read")
        sys.exit(EXIT_PARTIAL)


# --------------------------------------------------------------------------- inputs


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


def read_one(spec: str, input_format: str | None = None):
    """One curve (``FILE``, ``FILE#I`` or ``-``): a curve the command cannot do without."""
    if spec == "-":
        curves = _stdin_curves(input_format)
        if len(curves) != 1:
            raise click.UsageError(f"stdin holds {len(curves)} curves; one is expected here")
        curve = curves[0]
    else:
        from ..formats import read_curve

        curve = read_curve(spec, format=input_format)
    detail(f"read {curve.id} ({len(curve.points)} vertices)")
    return curve


def read_inputs(specs, *, glob: str | None = None, input_format: str | None = None) -> Inputs:
    """Read every curve of the files and folders ``specs`` (``-``: stdin).

    A missing file, an empty folder (no curve file, or none matching ``glob``) and a file
    that cannot be read are each named on stderr and counted as failed inputs; raises
    :class:`NothingRead` (exit 1) when no curve was read at all."""
    from ..sources import find_curve_files, read_all

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
                raise NoCurvesError("no curve files found" + (f" matching {glob!r}" if glob else ""), path=spec)
        except NfdError as exc:
            total += 1
            errors.append(exc)
            error(exc)
            continue
        new = [path for path in found if os.path.normpath(path) not in seen]
        seen.update(os.path.normpath(path) for path in new)
        total += len(new)
        read, read_errors = read_all(new, format=input_format)
        curves += read
        errors += read_errors
        report_errors(read_errors)
    if errors:
        _count_failures(len(errors))
    if not curves:
        raise NothingRead()
    detail(f"read {len(curves)} curve{'' if len(curves) == 1 else 's'} from {total - len(errors)} of {total} inputs")
    return Inputs(curves, errors, total)


# --------------------------------------------------------------------------- options


def format_option(formats=ROW_FORMATS, default=None, help_extra=""):
    """The one ``--format`` option: every command that writes rows or a summary uses it."""
    return click.option(
        "--format",
        "output_format",
        type=click.Choice(formats),
        default=default,
        show_default=default is not None,
        help="Output format" + help_extra + ".",
    )


# rows formats with the default that every row-writing command has
def rows_format_option(f):
    return format_option(help_extra=" (default: by the extension of -o, else a table on a terminal and CSV otherwise)")(
        f
    )


def _check_output_path(ctx, param, value):
    """Fail before any work when an output file cannot be written (exit 1, named)."""
    paths = value if isinstance(value, tuple) else (() if value is None else (value,))
    for path in paths:
        if "{" in path:  # a pattern (show): its folder is checked
            path = path.split("{", 1)[0] + "x"
        check_writable(path)
    return value


def check_writable(path: str) -> str:
    """``path`` if a file can be written there; else :class:`WriteError`."""
    if not path:
        raise WriteError("cannot write: empty file name", path=path)
    if os.path.isdir(path):
        raise WriteError("cannot write: it is a directory", path=path)
    if not os.path.isdir(os.path.dirname(os.path.abspath(path))):
        raise WriteError("cannot write: the folder does not exist", path=path)
    return path


def output_option(
    help="Write the rows to FILE (whole, and only when the command succeeds; an identical "
    "file is left untouched) instead of stdout.",
    multiple=False,
    required=False,
):
    """The one ``-o/--output`` option of commands that write rows (and pictures)."""
    return click.option(
        "--output",
        "-o",
        "output",
        type=click.Path(dir_okay=False),
        default=None,
        multiple=multiple,
        required=required,
        metavar="FILE",
        callback=_check_output_path,
        help=help,
    )


def split_outputs(paths) -> tuple[list[str], str | None]:
    """``-o`` paths of a picture command: pictures by extension (.png, .svg, .pdf), rows
    for the one other path."""
    pictures = [p for p in paths if os.path.splitext(p)[1].lower() in PICTURE_EXTENSIONS]
    rows = [p for p in paths if p not in pictures]
    if len(rows) > 1:
        raise click.UsageError(
            f"one -o for the rows at most (pictures end in {', '.join(PICTURE_EXTENSIONS)}); got {', '.join(rows)}"
        )
    return pictures, (rows[0] if rows else None)


def input_format_option(f):
    from ..formats import FORMATS

    return click.option(
        "--input-format",
        "input_format",
        type=click.Choice(sorted(FORMATS)),
        default=None,
        help="Read inputs as this format whatever their extension (needed for '-', stdin).",
    )(f)


def descriptor_options(f):
    from ..descriptors import DEFAULT_HARMONICS, DEFAULT_SAMPLES, DEFAULT_SCALE, SCALES

    f = click.option(
        "--scale",
        type=click.Choice(SCALES),
        default=DEFAULT_SCALE,
        show_default=True,
        help="Scale normalization: RMS radius (robust) or |A_1| (the paper).",
    )(f)
    f = click.option(
        "--harmonics",
        "-k",
        type=click.IntRange(min=1),
        default=DEFAULT_HARMONICS,
        show_default=True,
        help="Harmonics K: frequencies +-1..+-K are compared.",
    )(f)
    f = click.option(
        "--samples",
        "-n",
        type=click.IntRange(min=3),
        default=DEFAULT_SAMPLES,
        show_default=True,
        help="Arc-length samples per curve.",
    )(f)
    return f


def optional_descriptor_options(what: str):
    """samples/harmonics/scale without defaults: an index fixes them, files take the defaults."""
    from ..descriptors import DEFAULT_HARMONICS, DEFAULT_SAMPLES, DEFAULT_SCALE, SCALES

    def decorate(f):
        f = click.option(
            "--scale",
            type=click.Choice(SCALES),
            default=None,
            help=f"Scale normalization [default: {what}, else {DEFAULT_SCALE}].",
        )(f)
        f = click.option(
            "--harmonics",
            "-k",
            type=click.IntRange(min=1),
            default=None,
            help=f"Harmonics K [default: {what}, else {DEFAULT_HARMONICS}].",
        )(f)
        f = click.option(
            "--samples",
            "-n",
            type=click.IntRange(min=3),
            default=None,
            help=f"Arc-length samples [default: {what}, else {DEFAULT_SAMPLES}].",
        )(f)
        return f

    return decorate


def matching_options(f):
    """--method, --strict-direction and --mirror, passed on as ``matching``: a dict of
    the keyword arguments ``method``, ``direction``, ``mirror`` of the library."""
    from ..matching import DEFAULT_METHOD, METHODS

    f = click.option("--mirror", is_flag=True, help="Also allow reflections (mirror images match).")(f)
    f = click.option(
        "--strict-direction", is_flag=True, help="Do not match a curve traversed in the opposite direction."
    )(f)
    f = click.option(
        "--method",
        type=click.Choice(list(METHODS)),
        default=DEFAULT_METHOD,
        show_default=True,
        help="exact: global optimum over start shift x rotation; paper: the published step.",
    )(f)
    return f


def matching(method: str, strict_direction: bool, mirror: bool) -> dict:
    """The library's matching keyword arguments from the options of :func:`matching_options`."""
    from ..matching import DEFAULT_DIRECTION, STRICT_DIRECTION

    return {
        "method": method,
        "direction": STRICT_DIRECTION if strict_direction else DEFAULT_DIRECTION,
        "mirror": mirror,
    }


def index_option(f):
    from ..defaults import DEFAULT_INDEX, INDEX_ENV

    return click.option(
        "--index",
        "index_path",
        envvar=INDEX_ENV,
        default=DEFAULT_INDEX,
        show_default=f"${INDEX_ENV} or {DEFAULT_INDEX}",
        type=click.Path(dir_okay=False),
        help="The index file.",
    )(f)


# --------------------------------------------------------------------------- rows

exclude_self_option = click.option(
    "--exclude-self",
    "exclude_self_",
    is_flag=True,
    help="Drop the query itself from its matches: a match with the query's id, or the same curve of "
    "the same file (however the path is spelled).",
)


def curve_key(curve_id: str) -> str:
    """The file (resolved: symlinks, relative spellings) and curve an id names."""
    from ..formats import split_selector

    path, selected = split_selector(curve_id)
    return os.path.realpath(path) + ("" if selected is None else f"#{selected}")


def exclude_self(query_id: str, matches: list, top: int, locate=None) -> list:
    """``matches`` (ranked :class:`~nfdmatch.records.RankedMatch` es) without those naming
    the query's curve, ranks renumbered, at most ``top``. The caller asks the search for one
    match more. ``locate``: id -> a path that opens it here (an index's ids are relative to
    its folder)."""
    if query_id == STDIN_ID:
        return matches[:top]
    return [
        m.replace(rank=rank)
        for rank, m in enumerate([m for m in matches if not is_query(query_id, m.id, locate)][:top], start=1)
    ]


def is_query(query_id: str, match_id: str, locate=None) -> bool:
    """Whether ``match_id`` names the query's curve: the same id, or the same curve of the
    same file however the path is spelled (never for stdin). ``locate`` as in
    :func:`exclude_self`."""
    if query_id == STDIN_ID:
        return False
    where = locate or (lambda i: i)
    return match_id == query_id or curve_key(where(match_id)) == curve_key(query_id)


def match_row(query_id: str, m) -> dict:
    """The row `rank` and `query` print for one :class:`~nfdmatch.records.RankedMatch`
    (columns: :func:`match_columns`, and ``score`` after a re-ranking)."""
    return {
        "query": query_id,
        "rank": m.rank,
        "match": m.id,
        "distance": m.distance,
        "score": m.score,
        "shift": m.shift,
        "reversed": m.reversed,
        "mirrored": m.mirrored,
    }


def match_columns(details: bool) -> list[str]:
    """Columns of the rows `rank` and `query` print."""
    return ["query", "rank", "match", "distance"] + (["shift", "reversed", "mirrored"] if details else [])


def resolve_format(fmt: str | None, output: str | None) -> str:
    """The row format: as given, else by the extension of ``output``, else a table on a
    terminal and CSV otherwise."""
    if fmt is not None:
        return fmt
    if output is not None:
        return FORMAT_OF_EXTENSION.get(os.path.splitext(output)[1].lower(), "csv")
    return "table" if sys.stdout.isatty() else "csv"


def write_rows(
    rows: list[dict], columns: list[str], fmt: str | None, output: str | None = None, *, group_by: str | None = None
) -> None:
    """Write rows to ``output`` (stdout when None) as a table, CSV, TSV, JSON (a list) or
    JSON lines. Machine formats carry no markup; floats keep full precision (repr).
    ``group_by``: in a table, a heading per value of this column instead of the column."""
    fmt = resolve_format(fmt, output)
    if fmt == "table":
        text = render_table(rows, columns, group_by=group_by, terminal=output is None and sys.stdout.isatty())
    elif fmt in ("csv", "tsv"):
        text = delimited_text(columns, ([_cell_text(row.get(c)) for c in columns] for row in rows), fmt)
    elif fmt == "json":
        text = json.dumps([{c: row.get(c) for c in columns} for row in rows], indent=2) + "\n"
    elif fmt == "jsonl":
        text = "".join(json.dumps({c: row.get(c) for c in columns}) + "\n" for row in rows)
    else:  # pragma: no cover - click restricts the choices
        raise click.UsageError(f"unknown format {fmt}")
    deliver(text, output)


def delimited_text(header: list[str], rows, fmt: str) -> str:
    """A header line then the rows (lists of str), as CSV or TSV."""
    buf = io.StringIO()
    writer = csv.writer(buf, delimiter="," if fmt == "csv" else "\t", lineterminator="\n")
    writer.writerow(header)
    writer.writerows(rows)
    return buf.getvalue()


def _cell_text(value, pretty: bool = False) -> str:
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


def common_folder(values) -> str:
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
) -> str:
    """A rich table as text that fits ``width`` (default: the terminal's): the folder all
    paths of a column share is said once above the table, long ids wrap inside their cell,
    and with ``group_by`` each value of that column heads its own table."""
    import shutil

    from rich.console import Console
    from rich.table import Table

    if width is None:
        width = shutil.get_terminal_size((120, 24)).columns
    shown = [c for c in columns if c != group_by]
    paths = [c for c in shown if c in PATH_COLUMNS]
    folder = common_folder([str(row.get(c) or "") for row in rows for c in paths])
    buf = io.StringIO()
    console = Console(
        file=buf, width=width, force_terminal=terminal, no_color=not terminal, highlight=False, soft_wrap=False
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
        click.echo(text, nl=False)
        return
    if some_failed():
        error(f"{output} not written: some inputs could not be read")
        return
    if write_if_changed(output, text.encode("utf-8")):
        detail(f"wrote {output}")
    else:
        detail(f"{output} unchanged")


def write_if_changed(path: str, data: bytes) -> bool:
    """Write ``data`` to ``path`` through a temporary file in the same folder that then
    replaces it, so ``path`` is never seen half written; a file that already holds
    exactly ``data`` is left untouched (mtime kept, so Make rebuilds nothing downstream).
    Returns True when ``path`` was (re)written. I/O problems raise :class:`WriteError`."""
    check_writable(path)
    try:
        if os.path.getsize(path) == len(data):
            with open(path, "rb") as f:
                if f.read() == data:
                    return False
    except OSError:
        pass
    folder, name = os.path.split(os.path.abspath(path))
    temp = None
    try:
        fd, temp = tempfile.mkstemp(prefix=f".{name}.", suffix=".tmp", dir=folder)
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        try:
            mode = os.stat(path).st_mode & 0o7777
        except OSError:
            umask = os.umask(0)
            os.umask(umask)
            mode = 0o666 & ~umask
        os.chmod(temp, mode)  # mkstemp makes 0600; keep the file readable as usual
        os.replace(temp, path)
        temp = None
    except OSError as exc:
        raise WriteError(f"cannot write the file ({exc.strerror or exc})", path=path) from None
    finally:
        if temp is not None and os.path.exists(temp):
            os.remove(temp)
    return True


def stderr_is_terminal() -> bool:
    return sys.stderr.isatty()


def progress_bar(description: str):
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
        console=Console(stderr=True, force_terminal=True),
        transient=True,
        auto_refresh=False,
    )
    task = bar.add_task(description, total=None)
    bar.start()

    def update(done, total):
        bar.update(task, completed=done, total=total)
        bar.refresh()

    return update, bar.stop
