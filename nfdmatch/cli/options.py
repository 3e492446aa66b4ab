"""The options and the behaviour every command shares, defined once so that every command
behaves the same.

- :class:`NfdGroup`, the group class of ``nfdmatch`` and ``nfdmatch index``: every
  :class:`~nfdmatch.errors.NfdError` raised while a command runs (its options included)
  becomes ``Error: <message>`` on stderr and exit 2, never a traceback; ``-q``/``-v``
  are added to every command.
- Messages: :func:`note` (hidden by ``-q``), :func:`detail` (shown by ``-v``), :func:`error`
  (always). stdout carries data only; everything else goes to stderr.
- The exit-code policy for inputs that failed: :func:`finish` exits 3 when some failed;
  :func:`nothing_matched` exits 1 when a filter left every query without a match.
- Shared click options: ``--format`` (:func:`format_option`), ``-o/--output``
  (:func:`output_option`), input format, descriptor and matching options, ``--index``.

Exit codes, grep's contract: 0 found (answered), 1 nothing matched (a filter such as
``--max-distance`` left every query without a match; ``index verify``: problems found),
2 error (a usage error, any NfdError, or no input could be read), 3 partial success (some
inputs failed, the rest was answered), 130 interrupted (SIGINT, Ctrl-C), 143 terminated
(SIGTERM); both without a traceback, after the command cleaned up.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, TypeVar

import functools
import os
import sys
import time
from dataclasses import dataclass, fields

import click

from ..errors import NfdError, WriteError
from .signals import EXIT_INTERRUPTED, EXIT_TERMINATED, Terminated, raising

if TYPE_CHECKING:
    from collections.abc import Callable, Iterable, Sequence
    from typing import TypeAlias

    from ..search.stages import ElasticStage

    #: a command function taking the values of some options packed into one argument
    #: (:func:`_packed`): its parameters change, so it is any callable again
    Packing: TypeAlias = Callable[[Callable[..., Any]], Callable[..., Any]]

#: a function that click decorates (a command's, or another option's decorator's result)
F = TypeVar("F", bound="Callable[..., Any]")

EXIT_OK, EXIT_NOTHING, EXIT_ERROR, EXIT_PARTIAL = 0, 1, 2, 3
#: click's own exit status of a usage error: the same as any other error
EXIT_USAGE = EXIT_ERROR
# EXIT_INTERRUPTED, EXIT_TERMINATED (signals.py): 128 + the signal number, as a shell
# reports a process ended by SIGINT / SIGTERM
ROW_FORMATS = ("table", "csv", "tsv", "json", "jsonl")

QUIET, NORMAL, VERBOSE = 0, 1, 2
_VERBOSITY = "nfdmatch.verbosity"


# --------------------------------------------------------------------------- errors and exit codes


class NothingRead(Exception):
    """Raised by commands when no input could be read (each was already named): exit 2."""


class NfdGroup(click.Group):
    """A click group whose commands all share the error policy and ``-q``/``-v``."""

    group_class = type  # subgroups (``index``) are NfdGroups too

    def add_command(self, cmd: click.Command, name: str | None = None) -> None:
        if not isinstance(cmd, click.Group):
            cmd.params.extend(_verbosity_params())
        super().add_command(cmd, name)

    def parse_args(self, ctx: click.Context, args: list[str]) -> list[str]:
        if ctx.parent is None:  # the words as given: --format of a command that fails to parse
            ctx.meta[_ARGS] = list(args)
        return super().parse_args(ctx, args)

    def invoke(self, ctx: click.Context) -> Any:
        started = time.perf_counter()
        # the first SIGINT/SIGTERM raises while the command runs, later ones are ignored
        restore = raising() if ctx.parent is None else None
        try:
            return super().invoke(ctx)
        except KeyboardInterrupt as exc:  # Ctrl-C or SIGTERM: the library cleaned up on its way out
            terminated = isinstance(exc, Terminated)
            message = "terminated (SIGTERM)" if terminated else "interrupted (SIGINT)"
            error(message)
            code = EXIT_TERMINATED if terminated else EXIT_INTERRUPTED
            json_failure(ctx, message, code)
            sys.exit(code)
        except NfdError as exc:
            error(exc)
            json_failure(ctx, str(exc), EXIT_ERROR)
            sys.exit(EXIT_ERROR)
        except NothingRead:
            json_failure(ctx, "no input could be read", EXIT_ERROR)
            sys.exit(EXIT_ERROR)
        except click.UsageError as exc:  # click prints it and exits 2
            if ctx.parent is None:
                json_failure(ctx, exc.format_message(), EXIT_USAGE)
            raise
        except BrokenPipeError:  # e.g. `nfdmatch describe ... | head`
            sys.stderr.close()
            sys.exit(EXIT_OK)
        finally:
            if ctx.parent is None:
                _say_kernels_unused()
            if ctx.parent is None and ctx.invoked_subcommand:
                detail(f"{ctx.invoked_subcommand}: {time.perf_counter() - started:.2f} s")
                kernels = sys.modules.get("nfdmatch.matching.kernels")  # loaded only by exact work
                if kernels is not None and kernels.chosen() is not None:
                    detail(f"kernels: {kernels.chosen().describe()}")
            if restore is not None:
                restore()


def _say_kernels_unused() -> None:
    """One line on stderr when this run found the compiled kernels damaged and used the
    others (the library only records why: ``matching.aot.unused_reason``)."""
    aot = sys.modules.get("nfdmatch.matching.aot")  # imported only when a command used it
    reason = aot.unused_reason() if aot is not None else None
    if reason:
        note(reason, prefix="Warning: ")


def _set_verbosity(ctx: click.Context, param: click.Parameter, value: bool) -> None:
    if value:
        level = QUIET if param.name == "quiet" else VERBOSE
        if ctx.meta.get(_VERBOSITY, level) != level:
            raise click.UsageError("-q/--quiet and -v/--verbose exclude each other", ctx=ctx)
        ctx.meta[_VERBOSITY] = level


_VERBOSITY_OPTIONS = (
    (("-q", "--quiet"), "Errors only: no notes, summaries or progress on stderr."),
    (("-v", "--verbose"), "Also say what is read, what is written and how long it took (stderr)."),
)


_COLOR = "nfdmatch.color"
COLOR_CHOICES = ("auto", "always", "never")
_COLOR_HELP = (
    "Styles (colour, bold) in tables and progress bars: auto, on a terminal unless $NO_COLOR is set "
    "(then none at all, bold included); always; never."
)


def _set_color(ctx: click.Context, param: click.Parameter, value: str | None) -> None:
    if value is not None:
        ctx.meta[_COLOR] = value


def _color_kwargs() -> dict[str, Any]:
    return dict(
        type=click.Choice(COLOR_CHOICES), default=None, expose_value=False, callback=_set_color, help=_COLOR_HELP
    )


def _verbosity_params() -> list[click.Option]:
    return [
        click.Option(list(names), is_flag=True, expose_value=False, callback=_set_verbosity, help=text)
        for names, text in _VERBOSITY_OPTIONS
    ] + [click.Option(["--color"], **_color_kwargs())]


def verbosity_options(f: F) -> F:
    """``-q``/``-v`` and ``--color`` on the group itself (``nfdmatch -q query ...``)."""
    f = click.option("--color", **_color_kwargs())(f)
    for names, text in reversed(_VERBOSITY_OPTIONS):
        f = click.option(*names, is_flag=True, expose_value=False, callback=_set_verbosity, help=text)(f)
    return f


def use_color(terminal: bool) -> bool:
    """Whether to style output going to a stream (``terminal``: it is one): ``--color
    always``/``never`` decide; ``auto`` (the default) styles a terminal unless ``$NO_COLOR``
    is set to anything but the empty string (no-color.org: then no colour, and here no bold
    either: no escape sequence at all)."""
    ctx = click.get_current_context(silent=True)
    choice = "auto"
    while ctx is not None:  # the command's own --color, else the group's
        if _COLOR in ctx.meta:
            choice = ctx.meta[_COLOR]
            break
        ctx = ctx.parent
    if choice != "auto":
        return choice == "always"
    return terminal and not os.environ.get("NO_COLOR")


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


def error(exc_or_message: object) -> None:
    """``Error: <message>`` on stderr, always (the message names the file and line)."""
    click.echo(f"Error: {exc_or_message}", err=True)


def report_errors(errors: Iterable[object]) -> None:
    for exc in errors:
        error(exc)


_FAILED = "nfdmatch.failed"
_FAILURES = "nfdmatch.failures"
_FORMAT = "nfdmatch.format"
_ARGS = "nfdmatch.args"
_STDOUT_USED = "nfdmatch.stdout-used"
JSON_FORMATS = ("json", "jsonl")


def count_failures(n: int, errors: Iterable[BaseException] = ()) -> None:
    """``n`` more inputs failed (``errors``: their exceptions, listed in the JSON failure
    record, :func:`json_failure`)."""
    ctx = click.get_current_context(silent=True)
    if ctx is not None:
        ctx.meta[_FAILED] = ctx.meta.get(_FAILED, 0) + n
        ctx.meta.setdefault(_FAILURES, []).extend(errors)


_Format = TypeVar("_Format", str, None)


def remember_format(fmt: _Format) -> _Format:
    """Record the output format this command resolved (the JSON failure record follows it)."""
    ctx = click.get_current_context(silent=True)
    if ctx is not None and fmt is not None:
        ctx.meta[_FORMAT] = fmt
    return fmt


def stdout_used() -> None:
    """Rows went to stdout (a JSON list there must stay the only document)."""
    ctx = click.get_current_context(silent=True)
    if ctx is not None:
        ctx.meta[_STDOUT_USED] = True


def _format_asked(meta: dict[str, Any]) -> str | None:
    if _FORMAT in meta:
        return meta[_FORMAT]
    words = meta.get(_ARGS, [])
    for i, word in enumerate(words):  # the command failed before its options were read
        if word == "--format" and i + 1 < len(words):
            return words[i + 1]
        if word.startswith("--format="):
            return word.split("=", 1)[1]
    return None


def json_failure(ctx: click.Context, message: str, code: int) -> None:
    """With ``--format json`` or ``jsonl``: one JSON object on stdout saying why the command
    did not answer in full, so that a log of JSON lines gets a line from every run:
    ``{"error": MESSAGE, "exit": CODE, "failed": [{"input": PATH, "error": MESSAGE}, ...]}``
    (``failed``: the inputs that could not be read). Not after a JSON list or object
    already on stdout (``index build``'s summary, a partial run's rows with ``json``): a
    second document would break its readers; JSON lines take one more line."""
    import json

    fmt = _format_asked(ctx.meta)
    if fmt not in JSON_FORMATS or (fmt == "json" and ctx.meta.get(_STDOUT_USED)):
        return
    failed = [
        {"input": getattr(exc, "path", None), "error": getattr(exc, "message", str(exc))}
        for exc in ctx.meta.get(_FAILURES, [])
    ]
    record = {"error": message, "exit": code, "failed": failed}
    try:
        click.echo(json.dumps(record))
        sys.stdout.flush()
    except (BrokenPipeError, OSError):
        pass


def some_failed() -> bool:
    """True once an input of this command could not be read."""
    ctx = click.get_current_context(silent=True)
    return bool(ctx is not None and ctx.meta.get(_FAILED))


def finish(failed: int, total: int, what: str = "inputs") -> None:
    """The end of every command that reads several inputs: exit 3 when some failed."""
    if failed:
        message = f"{failed} of {total} {what} could not be read"
        error(message)
        ctx = click.get_current_context(silent=True)
        if ctx is not None:
            json_failure(ctx, message, EXIT_PARTIAL)
        sys.exit(EXIT_PARTIAL)


def nothing_matched(found: int, what: str = "no match") -> None:
    """Exit 1 (grep's "nothing matched") when ``found`` is 0: every input was answered, but a
    filter left no row. Called after :func:`finish` (a partial run exits 3 first)."""
    if not found:
        detail(what)  # as grep, silent: the exit status says it
        sys.exit(EXIT_NOTHING)


# --------------------------------------------------------------------------- options


def format_option(
    formats: Sequence[str] = ROW_FORMATS, default: str | None = None, help_extra: str = ""
) -> Callable[[F], F]:
    """The one ``--format`` option: every command that writes rows or a summary uses it."""
    return click.option(
        "--format",
        "output_format",
        type=click.Choice(formats),
        callback=lambda ctx, param, value: remember_format(value),
        default=default,
        show_default=default is not None,
        help="Output format" + help_extra + ".",
    )


# rows formats with the default that every row-writing command has
def rows_format_option(f: F) -> F:
    return format_option(help_extra=" (default: by the extension of -o, else a table on a terminal and CSV otherwise)")(
        f
    )


#: ``-o -``: stdout, as ``-`` is stdin where a file is read
STDOUT = "-"


def _check_output_path(
    ctx: click.Context, param: click.Parameter, value: str | tuple[str, ...] | None
) -> str | tuple[str, ...] | None:
    """Fail before any work when an output file cannot be written (exit 2, named). ``-o -``
    is stdout: None for a single ``-o``; kept as ``-`` among several (:func:`split_outputs`)."""
    if value == STDOUT:
        return None
    paths = value if isinstance(value, tuple) else (() if value is None else (value,))
    for path in paths:
        if path == STDOUT:
            continue
        if "{" in path:  # a pattern (show): its folder is checked, and the pattern named
            try:
                check_writable(path.split("{", 1)[0] + "x")
            except WriteError as exc:
                raise WriteError(exc.message, path=path) from None
            continue
        check_writable(path)
    return value


_INPUTS = "nfdmatch.inputs"


def note_inputs(paths: Iterable[str | os.PathLike[str] | None]) -> None:
    """Remember files this command reads (curve files, the index), so that an output naming
    one of them is refused (:func:`refuse_input_as_output`)."""
    ctx = click.get_current_context(silent=True)
    if ctx is not None:
        ctx.meta.setdefault(_INPUTS, []).extend(os.fspath(p) for p in paths if p is not None and p != STDOUT)


def refuse_input_as_output(path: str | None) -> None:
    """A usage error (exit 2) when ``path`` is one of the files this command read, however
    spelled (the same file: device and inode, links followed), as ``cp a a`` refuses: the
    input is left untouched. Called just before an output is written; an output that does
    not exist yet, or is not a regular file (/dev/null, a FIFO), is no input's."""
    import stat

    from ..errors import escape_name

    ctx = click.get_current_context(silent=True)
    inputs = () if ctx is None else ctx.meta.get(_INPUTS, ())
    if path is None or path == STDOUT or not inputs:
        return
    try:
        out = os.stat(path)
    except OSError:
        return
    if not stat.S_ISREG(out.st_mode):
        return
    for name in dict.fromkeys(inputs):
        try:
            info = os.stat(name)
        except OSError:
            continue
        if (info.st_dev, info.st_ino) == (out.st_dev, out.st_ino):
            same = "" if name == path else f" ({escape_name(name)})"
            raise click.UsageError(f"-o {escape_name(path)} is one of the inputs{same}: not overwritten")


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
    help: str = "Write the rows to FILE (whole, and only when the command succeeds; an identical "
    "file keeps its bytes, with a fresh mtime) instead of stdout; '-': stdout.",
    multiple: bool = False,
    required: bool = False,
    names: tuple[str, ...] = ("--output", "-o"),
    dest: str = "output",
) -> Callable[[F], F]:
    """The one ``-o/--output`` option of commands that write rows (and pictures); ``names``
    and ``dest`` for another output file of that kind (``extract --list``)."""
    return click.option(
        *names,
        dest,
        type=click.Path(dir_okay=False),
        default=None,
        multiple=multiple,
        required=required,
        metavar="FILE",
        callback=_check_output_path,
        help=help,
    )


def int_option(
    *names: str, minimum: int = 1, default: int | None = None, metavar: str | None = None, help: str
) -> Callable[[F], F]:
    """A whole-number option of at least ``minimum`` (--top, --sections, --jobs, ...); its
    default, when it has one, shown in --help (when it has none, ``help`` says what then)."""
    return click.option(
        *names, type=click.IntRange(min=minimum), default=default, show_default=True, metavar=metavar, help=help
    )


def input_format_option(f: F) -> F:
    from ..formats import FORMATS

    return click.option(
        "--input-format",
        "input_format",
        type=click.Choice(sorted(FORMATS)),
        default=None,
        help="Read inputs as this format whatever their extension (needed for '-', stdin).",
    )(f)


def _descriptor_option_table() -> tuple[tuple[tuple[str, ...], click.ParamType, Any, str, str], ...]:
    """The three descriptor options, defined once: ``(names, type, default, help, short
    help)``, in the order --help lists them."""
    from ..descriptors import DEFAULT_HARMONICS, DEFAULT_SAMPLES, DEFAULT_SCALE, SCALES

    return (
        (
            ("--samples", "-n"),
            click.IntRange(min=3),
            DEFAULT_SAMPLES,
            "Arc-length samples per curve.",
            "Arc-length samples",
        ),
        (
            ("--harmonics", "-k"),
            click.IntRange(min=1),
            DEFAULT_HARMONICS,
            "Harmonics K: frequencies +-1..+-K are compared.",
            "Harmonics K",
        ),
        (
            ("--scale",),
            click.Choice(SCALES),
            DEFAULT_SCALE,
            "Scale normalization: RMS radius (robust) or |A_1| (the paper).",
            "Scale normalization",
        ),
    )


def _packed(
    command: Callable[..., Any], name: str, keys: tuple[str, ...], pack: Callable[..., Any] = dict
) -> Callable[..., Any]:
    """``command`` taking the values of the options ``keys`` as one argument ``name``:
    ``pack(**values)`` (a dict by default)."""

    @functools.wraps(command)
    def packed(*args: Any, **kwargs: Any) -> Any:
        values = {key: kwargs.pop(key) for key in keys}
        return command(*args, **{name: pack(**values)}, **kwargs)

    return packed


def _with_options(command: Callable[..., Any], *options: Callable[[Any], Any]) -> Callable[..., Any]:
    """``command`` with the click ``options`` (decorators), which ``--help`` lists in the order
    given (a decorator stack applies the last first)."""
    for option in reversed(options):
        command = option(command)
    return command


def options_bundle(name: str, bundle: type, *options: Callable[[Any], Any]) -> Packing:
    """The click ``options`` (decorators, listed by ``--help`` in the order given) whose values
    a command takes as one argument ``name``: ``bundle(**values)``, a dataclass with a field
    for each value it packs (the others reach the command as they are)."""

    def decorate(command: Callable[..., Any]) -> Callable[..., Any]:
        keys = tuple(field.name for field in fields(bundle))
        return _with_options(_packed(command, name, keys, pack=bundle), *options)

    return decorate


def _descriptor_options(command: Callable[..., Any], what: str | None = None) -> Callable[..., Any]:
    """--samples, --harmonics, --scale, passed on as ``descriptor``: a dict of the keyword
    arguments ``samples``, ``harmonics``, ``scale`` of the library. With the library's
    defaults; or, given ``what`` (who else decides), without: None where not given."""
    f = _packed(command, "descriptor", ("samples", "harmonics", "scale"))
    for names, kind, default, text, short in reversed(_descriptor_option_table()):
        if what is None:
            f = click.option(*names, type=kind, default=default, show_default=True, help=text)(f)
        else:
            f = click.option(*names, type=kind, default=None, help=f"{short} [default: {what}, else {default}].")(f)
    return f


def descriptor_options(command: Callable[..., Any]) -> Callable[..., Any]:
    """The descriptor options with the library's defaults (inputs read from files)."""
    return _descriptor_options(command)


def optional_descriptor_options(what: str) -> Packing:
    """The descriptor options without defaults: an index fixes them, files take the defaults."""
    return functools.partial(_descriptor_options, what=what)


def matching_options(command: Callable[..., Any]) -> Callable[..., Any]:
    """--method, --strict-direction and --mirror, passed on as ``matching``: a dict of
    the keyword arguments ``method``, ``direction``, ``mirror`` of the library."""
    from ..matching import DEFAULT_METHOD, METHODS

    f = _packed(command, "matching", ("method", "strict_direction", "mirror"), pack=matching)
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


def matching(method: str, strict_direction: bool, mirror: bool) -> dict[str, Any]:
    """The library's matching keyword arguments from the options of :func:`matching_options`."""
    from ..matching import DEFAULT_DIRECTION, STRICT_DIRECTION

    return {
        "method": method,
        "direction": STRICT_DIRECTION if strict_direction else DEFAULT_DIRECTION,
        "mirror": mirror,
    }


@dataclass(frozen=True)
class Comparison:
    """How a command without an index reads curves and compares them
    (:func:`comparison_options`; ``distance``, ``rank``, ``matrix``): the library's matching
    keywords (``matching``, :func:`matching_options`), its descriptor keywords
    (``descriptor``, :func:`descriptor_options`) and ``input_format`` (--input-format)."""

    matching: dict[str, Any]
    descriptor: dict[str, Any]
    input_format: str | None

    def keywords(self) -> dict[str, Any]:
        """The library's keyword arguments of a comparison: the descriptor's and the matching's."""
        return {**self.descriptor, **self.matching}


def comparison_options(command: Callable[..., Any]) -> Callable[..., Any]:
    """:func:`matching_options`, :func:`descriptor_options` (with the library's defaults)
    and --input-format, passed on as ``comparison``: a :class:`Comparison`."""
    return options_bundle("comparison", Comparison, matching_options, descriptor_options, input_format_option)(command)


def elastic_options(command: Callable[..., Any]) -> Callable[..., Any]:
    """--elastic and --elastic-depth M, passed on as ``stage``: the library's
    :class:`~nfdmatch.search.stages.ElasticStage`, or None without --elastic."""
    from ..defaults import DEFAULT_ELASTIC_DEPTH

    def pack(elastic: bool, elastic_depth: int | None) -> ElasticStage | None:
        if elastic_depth is not None and not elastic:
            raise click.UsageError("--elastic-depth needs --elastic")
        if not elastic:
            return None
        from ..search.stages import ElasticStage

        return ElasticStage(DEFAULT_ELASTIC_DEPTH if elastic_depth is None else elastic_depth)

    f = _packed(command, "stage", ("elastic", "elastic_depth"), pack=pack)
    f = int_option(
        "--elastic-depth",
        metavar="M",
        help=f"With --elastic: the exact nearest re-ordered [default: {DEFAULT_ELASTIC_DEPTH}].",
    )(f)
    f = click.option(
        "--elastic",
        is_flag=True,
        help="The elastic stage: the exact top M re-ordered by a fused distance (exact, elastic "
        "and shape statistics; docs/elastic.md); adds the columns elastic and fused.",
    )(f)
    return f


def _note_index(ctx: click.Context, param: click.Parameter, value: str | None) -> str | None:
    note_inputs([value])
    return value


@dataclass(frozen=True)
class Rerank:
    """The re-ranking by diffusion over the index's graph that ``--rerank`` asks for
    (:func:`rerank_options`): the candidates it re-orders besides the query's nearest
    (``depth``, --rerank-depth) and how they are found (``candidates``, --rerank-candidates)."""

    depth: int
    candidates: str


def rerank_options(command: Callable[..., Any]) -> Callable[..., Any]:
    """--rerank, --rerank-depth M and --rerank-candidates of every command that re-ranks by
    diffusion (``query``, ``report``), passed on as ``rerank``: a :class:`Rerank`, or None
    without --rerank (the other two then a usage error)."""
    from ..defaults import DEFAULT_RERANK_CANDIDATES, DEFAULT_RERANK_DEPTH, MIN_RERANK_DEPTH, RERANK_CANDIDATES

    def pack(rerank: bool, rerank_depth: int, rerank_candidates: str | None) -> Rerank | None:
        if rerank:
            return Rerank(rerank_depth, rerank_candidates or DEFAULT_RERANK_CANDIDATES)
        if rerank_depth != DEFAULT_RERANK_DEPTH:
            raise click.UsageError("--rerank-depth needs --rerank")
        if rerank_candidates is not None:
            raise click.UsageError("--rerank-candidates needs --rerank")
        return None

    return _with_options(
        _packed(command, "rerank", ("rerank", "rerank_depth", "rerank_candidates"), pack=pack),
        click.option(
            "--rerank",
            is_flag=True,
            help="Order the matches by a diffusion over the index's neighbour graph (needs `index build "
            "--graph`); adds the column score (higher is closer), distance stays the exact distance.",
        ),
        int_option(
            "--rerank-depth",
            minimum=MIN_RERANK_DEPTH,
            default=DEFAULT_RERANK_DEPTH,
            metavar="M",
            help="With --rerank: the candidates the diffusion re-orders besides the query's nearest.",
        ),
        click.option(
            "--rerank-candidates",
            type=click.Choice(RERANK_CANDIDATES),
            default=None,
            show_default=DEFAULT_RERANK_CANDIDATES,
            help="With --rerank: walk: the query's exact nearest (3 x --top, at least 8), the M curves its "
            "PageRank over the graph reaches most and the M/2 whose PageRank reaches it most; exact: its "
            "exact top M (~4x the time of a batch at 100,000 curves).",
        ),
    )


def index_option(f: F) -> F:
    from ..defaults import DEFAULT_INDEX, INDEX_ENV

    return click.option(
        "--index",
        "index_path",
        envvar=INDEX_ENV,
        default=DEFAULT_INDEX,
        show_default=f"${INDEX_ENV} or {DEFAULT_INDEX}",
        type=click.Path(dir_okay=False),
        callback=_note_index,
        help="The index file.",
    )(f)


_GLOB_HELP = (
    "Only files found in folders that match PATTERN: a name ('*.csv'), or a path below the folder "
    "('**/fam000/*.csv', ** spans folders); '!PATTERN' keeps those that do not match ('!bad*')."
)


def _glob_callback(dest: str, ignore_case: bool) -> Callable[[click.Context, click.Parameter, str | None], None]:
    def callback(ctx: click.Context, param: click.Parameter, value: str | None) -> None:
        if value is None:
            ctx.params.setdefault(dest, None)
            return
        if ctx.params.get(dest) is not None:
            raise click.UsageError("--glob and --iglob exclude each other", ctx=ctx)
        from ..sources import IGNORE_CASE

        ctx.params[dest] = IGNORE_CASE + value if ignore_case else value

    return callback


def glob_options(dest: str = "glob_pattern", extra: str = "") -> Callable[[F], F]:
    """``--glob PATTERN`` and ``--iglob PATTERN`` (the same, ignoring case), passed on as one
    argument ``dest``: the library's ``glob`` (:func:`nfdmatch.sources.glob_matcher`)."""

    def decorate(f: F) -> F:
        f = click.option(
            "--iglob",
            metavar="PATTERN",
            expose_value=False,
            callback=_glob_callback(dest, True),
            help="As --glob, ignoring case.",
        )(f)
        return click.option(
            "--glob",
            metavar="PATTERN",
            expose_value=False,
            callback=_glob_callback(dest, False),
            help=_GLOB_HELP + extra,
        )(f)

    return decorate


# --------------------------------------------------------------------------- rows

#: how ``query``/``rank`` spell the query and match columns (``--paths``)
PATH_SPELLINGS = ("id", "absolute", "relative")

paths_option = click.option(
    "--paths",
    "paths",
    type=click.Choice(PATH_SPELLINGS),
    default="id",
    show_default=True,
    help="How the query and match columns name files: id (the query as given, the match as stored: "
    "relative to the index's folder), absolute (both absolute: rows that work from any folder, "
    "e.g. piped to xargs), relative (both relative to the working directory).",
)

exclude_self_option = click.option(
    "--exclude-self",
    "exclude_self",
    is_flag=True,
    help="Drop the query itself from its matches: a match with the query's id, or the same curve of "
    "the same file (however the path is spelled).",
)


def check_max_distance(ctx: click.Context, param: click.Parameter, value: float | None) -> float | None:
    """``--max-distance`` by the library's rule (``search.limits``): a number >= 0, inf for
    no limit; NaN refused as a usage error, as a negative number is."""
    if value is not None:
        from ..search.limits import check_limits

        try:
            check_limits(max_distance=value)
        except NfdError:
            raise click.BadParameter(f"{value} is not a distance (a number >= 0; inf: no limit)") from None
    return value


def max_distance_option(*, help: str, **extra: Any) -> Callable[[F], F]:
    """``--max-distance``, a distance by the library's rule (:func:`check_max_distance`):
    the limit of the matches listed (``query``, ``rank``, ``report``; ``extra``
    ``default=None``), or the distance that makes a pair (``pairs``, ``groups``; ``extra``
    ``required=True``); ``extra``: click's other keywords."""
    return click.option("--max-distance", type=click.FloatRange(min=0), callback=check_max_distance, help=help, **extra)


@dataclass(frozen=True)
class MatchListing:
    """What a command that lists a query's matches was asked for (:func:`match_list_options`):
    how many matches (``top``, ``max_distance``, ``exclude_self``), from which inputs
    (``glob``) and in which columns (``details``, ``paths``)."""

    top: int
    max_distance: float | None
    glob: str | None
    details: bool
    paths: str
    exclude_self: bool

    def search(self) -> dict[str, Any]:
        """The library's keyword arguments among them: ``k`` (``--top``), ``max_distance``, ``exclude_self``."""
        return {"k": self.top, "max_distance": self.max_distance, "exclude_self": self.exclude_self}


def match_list_options(top_help: str, glob_help: str) -> Packing:
    """The options of every command that lists a query's matches (``rank``, ``query``):
    --top, --max-distance, --glob, --details, --paths, --exclude-self, passed on as
    ``listing``: a :class:`MatchListing`."""
    return options_bundle(
        "listing",
        MatchListing,
        int_option("--top", default=10, help=top_help),
        max_distance_option(default=None, help="Only list matches at most this far."),
        glob_options("glob", glob_help),
        click.option("--details", is_flag=True, help="Add the columns shift, reversed, mirrored."),
        paths_option,
        exclude_self_option,
    )


@dataclass(frozen=True)
class QueryBatch:
    """A batch of query curves searched in an index (:func:`query_batch_options`; ``query``,
    and ``report``, which draws what ``query`` lists): the queries (QUERY...), the index
    (``index_path``, --index), which matches, listed how (``listing``, a :class:`MatchListing`),
    ``exhaustive`` (--exhaustive), the re-ranking (``rerank``, a :class:`Rerank` or None), the
    elastic stage (``stage``, or None), the library's matching keywords (``matching``) and
    how the queries are read (``input_format``)."""

    queries: tuple[str, ...]
    index_path: str
    listing: MatchListing
    exhaustive: bool
    rerank: Rerank | None
    stage: ElasticStage | None
    matching: dict[str, Any]
    input_format: str | None


def query_batch_options(
    top_help: str, glob_help: str, exhaustive_help: str, *after_exhaustive: Callable[[Any], Any]
) -> Packing:
    """The argument QUERY... and the options of every command that answers a batch of
    queries from an index: --index, :func:`match_list_options`, --exhaustive, the command's
    own ``after_exhaustive`` (passed through), :func:`rerank_options`, :func:`elastic_options`,
    :func:`matching_options` and --input-format, passed on as ``batch``: a :class:`QueryBatch`."""
    return options_bundle(
        "batch",
        QueryBatch,
        click.argument("queries", nargs=-1, required=True, metavar="QUERY..."),
        index_option,
        match_list_options(top_help, glob_help),
        click.option("--exhaustive", is_flag=True, help=exhaustive_help),
        *after_exhaustive,
        rerank_options,
        elastic_options,
        matching_options,
        input_format_option,
    )
