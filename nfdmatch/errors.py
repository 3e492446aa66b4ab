"""The exception hierarchy: every error nfdmatch raises derives from :class:`NfdError`.

Each subclass also derives from the builtin a caller would naturally catch
(``ValueError`` for bad data, ``OSError`` for I/O), so ``except ValueError``
keeps working for code that does not know about nfdmatch.

Messages name where the problem is: ``"<path>: line <n>: <what>"`` or
``"<path>#<curve>: <what>"``. The CLI prints them as ``Error: <message>``.
Messages are valid UTF-8 (a file name's undecodable bytes escaped, see
:func:`escape_name`) and at most :data:`MAX_MESSAGE_CHARS` characters.
"""

from __future__ import annotations

#: Longest message an error keeps (characters); longer ones are cut with a marker. The
#: places that build messages quote file contents through :func:`excerpt` already; this
#: is the backstop, so that nothing from a file can make a message (or the failure
#: record an index stores) megabytes long.
MAX_MESSAGE_CHARS = 1000


def escape_name(text: str) -> str:
    """``text`` as valid UTF-8: the undecodable bytes of a file name, which Python's
    ``os.fsdecode`` (surrogateescape) turns into lone surrogates ``\\udc80``-``\\udcff``,
    are written as ``\\xNN`` (byte 0xff -> the four characters ``\\xff``); any other
    lone surrogate as ``\\udNNN``. Valid text is returned unchanged. Curve ids and the
    file names in messages use this form, so they can be printed and stored in HDF5
    (whose UTF-8 strings cannot hold a lone surrogate); to open the file, use the name
    as the operating system gave it (``Curve.source``). A name that really contains
    the text ``\\xff`` looks the same; the escape is not meant to be undone."""
    text = str(text)
    try:
        text.encode("utf-8")
        return text
    except UnicodeEncodeError:
        pass
    try:
        return text.encode("utf-8", "surrogateescape").decode("utf-8", "backslashreplace")
    except UnicodeEncodeError:
        return text.encode("utf-8", "backslashreplace").decode("utf-8")


def excerpt(text: str | bytes, limit: int = 80) -> str:
    """``text`` (str, or bytes shown as Latin-1) cut to ``limit`` characters, marking the
    cut with how much was left out: ``"12345...[cut: 5000000 characters in all]"``."""
    if isinstance(text, (bytes, bytearray)):
        text = bytes(text).decode("latin-1")
    text = str(text)
    if len(text) <= limit:
        return text
    return f"{text[:limit]}...[cut: {len(text)} characters in all]"


def os_error_message(exc: OSError, known: dict, otherwise: str) -> str:
    """What an I/O failure means, for a message: the message ``known`` gives the first
    kind of ``OSError`` that ``exc`` is (``{PermissionError: "cannot write: permission
    denied"}``), else ``"<otherwise> (<the system's words>)"``."""
    for kind, message in known.items():
        if isinstance(exc, kind):
            return message
    return f"{otherwise} ({exc.strerror or exc})"


class NfdError(Exception):
    """Base of every nfdmatch error.

    Parameters
    ----------
    message : what is wrong, without the location.
    path : the file concerned, if any.
    line : 1-based line number in that file, if known.
    curve : 0-based curve number within a multi-curve file, if known.
    """

    def __init__(
        self, message: str, *, path: str | None = None, line: int | None = None, curve: int | None = None
    ) -> None:
        message = str(message)
        if len(message) > MAX_MESSAGE_CHARS:
            message = excerpt(message, MAX_MESSAGE_CHARS)
        self.message = message
        self.path = None if path is None else str(path)
        self.line = line
        self.curve = curve
        super().__init__(self._format())

    def _format(self) -> str:
        where = ""
        if self.path is not None:
            where = escape_name(self.path)
            if self.curve is not None:
                where += f"#{self.curve}"
        parts = [p for p in (where, f"line {self.line}" if self.line is not None else "") if p]
        parts.append(self.message)
        return ": ".join(parts)

    def __reduce__(self):  # keep picklable across process pools
        return (_rebuild, (type(self), self.message, self.path, self.line, self.curve))


def _rebuild(cls, message, path, line, curve):
    return cls(message, path=path, line=line, curve=curve)


class InputError(NfdError, ValueError):
    """Input data that cannot be used: a malformed file or an invalid curve."""


class ParseError(InputError):
    """A file whose contents do not follow its format (bad rows, bad indices, garbage)."""


class CurveError(InputError):
    """A curve that is not a usable closed contour (NaN, too few points, zero length)."""


class UnknownFormatError(InputError):
    """A file extension or ``format=`` name that no reader is registered for."""


class NoCurvesError(InputError):
    """A file that parsed but holds no closed polyline (e.g. an OBJ with only faces)."""


class CurveSelectionError(InputError):
    """A ``file#i`` selector out of range, or a multi-curve file where one curve is needed."""


class ReadError(NfdError, OSError):
    """A file that cannot be opened or read (missing, a directory, no permission)."""


class WriteError(NfdError, OSError):
    """A file that cannot be written (missing folder, a directory in the way, no permission)."""


class OverwriteRefusedError(WriteError):
    """A file in the way of one extract writes that extract did not write (its output
    folder's manifest does not list it, or its content changed since): never replaced
    without ``force``. ``mesh`` is the mesh whose contour it would have been."""

    mesh: str = ""


class IndexFormatError(NfdError, ValueError):
    """A file that is not a readable nfdmatch index: another kind, a newer format, corrupted."""


class IndexLockedError(NfdError, OSError):
    """Another build holds the index lock."""


class ShrinkRefusedError(NfdError, ValueError):
    """A build that would remove more than half of an index's files (or all of them: an
    empty or unmounted source folder) and was not allowed to (``allow_shrink``).
    ``removed`` of ``of`` files would have gone."""

    removed: int = 0
    of: int = 0


class WorkerError(NfdError, RuntimeError):
    """A build's worker processes kept dying for no file's fault (memory exhausted, killed
    from outside): the build stops without writing, so the index keeps every curve it had.
    Also a task that raised in a forked worker (the graph's search, a distance matrix):
    ``detail`` is then the worker's traceback."""

    detail: str = ""

    @classmethod
    def failed_task(cls, summary: str, detail: str) -> WorkerError:
        """A task of a forked worker raised: its one-line ``summary``, its traceback ``detail``."""
        exc = cls(f"a worker process failed: {summary}")
        exc.detail = detail
        return exc


class ParameterError(NfdError, ValueError):
    """An invalid parameter value (samples, harmonics, scale, method, ...)."""


class MeshError(InputError):
    """A file that is not a readable triangle mesh, or a mesh with nothing to extract."""


class RenderError(NfdError, RuntimeError):
    """A picture that cannot be drawn: no usable renderer on this machine, or it failed."""
