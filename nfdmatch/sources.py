"""Finding curve files under files and folders given on the command line.

A folder walk skips, and reports through ``problems`` (a list the caller passes), what it
cannot or must not read, so that one such entry does not stop the others and is not
skipped silently either:

* a sub-folder that cannot be listed (no permission, an I/O error): its files are not
  seen; ``ReadError(path=the folder, "cannot list the folder (...); its files are
  skipped")``;
* an entry with a curve extension that is not a regular file (a FIFO, socket, device, or
  a symbolic link to one, e.g. to ``/dev/zero``): never opened (opening a FIFO blocks,
  reading ``/dev/zero`` never ends); ``ReadError(path=the entry, "is a FIFO (named pipe),
  not a regular file; skipped")``.

A file named directly is taken as given; reading it then fails with a clear
:class:`~nfdmatch.errors.ReadError` if it is not a regular file.

File names that are not valid UTF-8 come back from the walk as Python ``str`` with the
undecodable bytes as lone surrogates (``os.fsdecode``); they open fine, and the curve ids
made from them escape those bytes (see :func:`nfdmatch.formats._chain.curve_id`).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import os
import stat
from pathlib import Path

from .errors import ReadError
from .formats import supported_extensions
from .formats._chain import file_kind

if TYPE_CHECKING:
    from collections.abc import Callable, Iterable, Iterator
    from .curve import Curve
    from .errors import NfdError

__all__ = ["find_curve_files", "walk_folder", "glob_matcher", "IGNORE_CASE"]

#: a glob starting with this is matched ignoring case (``--iglob``)
IGNORE_CASE = "(?i)"


def glob_matcher(glob: str | None) -> Callable[[str], bool] | None:
    """``match(relative_path) -> bool`` for a ``--glob`` pattern (None: no pattern), as
    ripgrep's ``-g`` and fd read one: a pattern without ``/`` matches a file's name at any
    depth (``*.csv``); one with ``/`` matches the path below the walked folder (``fam0/*.csv``,
    a leading ``/`` only anchors it there); ``**`` spans any number of folders
    (``**/fam000/*.csv``), ``*`` and ``?`` stay within one name, ``[...]`` a class (``[!...]``
    negated); a leading ``!`` keeps the files that do not match (``!bad*``); a leading
    ``(?i)`` (:data:`IGNORE_CASE`, ``--iglob``) ignores case."""
    if not glob:
        return None
    import re

    flags = 0
    if glob.startswith(IGNORE_CASE):
        glob, flags = glob[len(IGNORE_CASE) :], re.IGNORECASE
    negate = glob.startswith("!")
    pattern = glob[1:] if negate else glob
    by_path = "/" in pattern
    regex = re.compile(_glob_regex(pattern.lstrip("/")), flags)

    def match(relative: str) -> bool:
        subject = relative if by_path else relative.rsplit("/", 1)[-1]
        return (regex.match(subject) is not None) != negate

    return match


def _glob_regex(pattern: str) -> str:
    import re

    out, i, n = [], 0, len(pattern)
    while i < n:
        if pattern.startswith("**/", i):
            out.append("(?:.*/)?")
            i += 3
        elif pattern.startswith("/**", i) and i + 3 == n:
            out.append("/.*")
            i += 3
        elif pattern.startswith("**", i):
            out.append(".*")
            i += 2
        elif pattern[i] == "*":
            out.append("[^/]*")
            i += 1
        elif pattern[i] == "?":
            out.append("[^/]")
            i += 1
        elif pattern[i] == "[" and pattern.find("]", i + 2) > 0:
            end = pattern.find("]", i + 2)
            body = pattern[i + 1 : end]
            body = "^" + body[1:] if body.startswith("!") else body
            out.append("[" + body.replace("\\", "\\\\") + "]")
            i = end + 1
        else:
            out.append(re.escape(pattern[i]))
            i += 1
    return "(?s:" + "".join(out) + r")\Z"


#: extensions of mesh files a folder walk finds when asked for meshes (``index build``); an
#: ``.obj`` is found anyway (a curve format too) and read as a mesh when it has faces
MESH_EXTENSIONS = (".stl", ".ply", ".off", ".glb", ".gltf")


def find_curve_files(
    sources: Iterable[str], *, glob: str | None = None, problems: list | None = None, meshes: bool = False
) -> list[str]:
    """Curve files named by ``sources``, in a deterministic order.

    Parameters
    ----------
    sources : iterable of paths. A file is taken as given (whatever its extension, so
        that ``--input-format`` can apply), ``file#i`` too; a folder is walked recursively, keeping
        files with a supported extension, skipping hidden files and folders.
    glob : optional pattern for files found in folders (:func:`glob_matcher`): on the name
        (``"*.csv"``), or on the path below the folder (``"**/fam000/*.csv"``), ``!``
        excluding, ``(?i)`` ignoring case.
    problems : optional list; receives a :class:`~nfdmatch.errors.ReadError` for every
        sub-folder that could not be listed and every non-regular file skipped in a
        walk (see the module docstring). Without it they are skipped silently.
    meshes : also find mesh files in folders (:data:`MESH_EXTENSIONS`).

    Returns
    -------
    list of str paths, sorted within each folder, without duplicates.

    Raises
    ------
    ReadError : a source that does not exist.
    """
    extensions = {e.lower() for e in supported_extensions()}
    if meshes:
        extensions |= set(MESH_EXTENSIONS)
    found = UniquePaths()

    from .formats import split_selector

    for source in sources:
        source = str(source)
        path, selected = split_selector(source)
        if selected is not None and os.path.isfile(path):
            found.add(source)  # file#i: one curve of a multi-curve file
        elif os.path.isdir(source):
            for file in walk_folder(source, extensions, glob=glob, problems=problems):
                found.add(file)
        elif os.path.exists(source):
            found.add(source)
        else:
            raise ReadError("no such file or folder", path=source)
    return found.paths


def walk_folder(
    folder: str,
    extensions: Iterable[str],
    *,
    glob: str | None = None,
    exclude: Iterable[str] = (),
    problems: list | None = None,
) -> Iterator[str]:
    """Yield the files below ``folder`` whose extension (lower-cased, with the dot) is in
    ``extensions`` and that ``glob`` keeps (:func:`glob_matcher`), recursively, sorted within each folder,
    skipping hidden files and folders and the folders in ``exclude``.

    Sub-folders that cannot be listed and entries that are not regular files are skipped;
    each is appended to ``problems`` (if given) as a :class:`ReadError` naming it. Symbolic
    links to folders are not followed (no cycles); links to regular files are yielded."""
    skip = {os.path.realpath(str(e)) for e in exclude}
    if os.path.realpath(folder) in skip:
        return

    def unlisted(exc: OSError) -> None:
        if problems is not None:
            where = exc.filename if exc.filename is not None else folder
            problems.append(
                ReadError(f"cannot list the folder ({exc.strerror or exc}); its files are skipped", path=str(where))
            )

    keep = glob_matcher(glob)
    for root, dirs, files in os.walk(folder, onerror=unlisted):
        below = os.path.relpath(root, folder).replace(os.sep, "/")
        below = "" if below == "." else below + "/"
        dirs[:] = sorted(
            d for d in dirs if not d.startswith(".") and not (skip and os.path.realpath(os.path.join(root, d)) in skip)
        )
        for name in sorted(files):
            if name.startswith(".") or Path(name).suffix.lower() not in extensions:
                continue
            if keep is not None and not keep(below + name):
                continue
            path = os.path.join(root, name)
            kind = _irregular(path)
            if kind is not None:
                if problems is not None:
                    problems.append(ReadError(f"is {kind}, not a regular file; skipped", path=path))
                continue
            yield path


def _irregular(path: str) -> str | None:
    """What ``path`` is when it exists but is not a regular file (following links), else None
    (a regular file, or a broken link: reading that reports "no such file")."""
    try:
        mode = os.stat(path).st_mode
    except OSError:
        return None
    if stat.S_ISREG(mode):
        return None
    return file_kind(mode)


class UniquePaths:
    """Paths in first-seen order, a path given twice (up to normpath) kept once."""

    def __init__(self) -> None:
        self.paths: list[str] = []
        self._seen: set[str] = set()

    def add(self, path: str) -> None:
        key = os.path.normpath(path)
        if key not in self._seen:
            self._seen.add(key)
            self.paths.append(path)


def read_all(paths: Iterable[str], *, format: str | None = None) -> tuple[list[Curve], list[NfdError]]:
    """Read every curve of every file; a bad file does not stop the others.

    Parameters
    ----------
    paths : iterable of file paths (``file#i`` selects one curve).
    format : force this format name for every file.

    Returns
    -------
    ``(curves, errors)``: list of :class:`~nfdmatch.curve.Curve` in file order, and the
    list of :class:`~nfdmatch.errors.NfdError` raised by the files that failed.
    """
    from .errors import NfdError
    from .formats import read_curve, read_curves, split_selector

    curves, errors = [], []
    for spec in paths:
        try:
            path, index = split_selector(spec)
            if index is None:
                curves.extend(read_curves(path, format=format))
            else:
                curves.append(read_curve(spec, format=format))
        except NfdError as exc:
            errors.append(exc)
    return curves, errors
