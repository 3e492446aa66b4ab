"""Finding curve files under files and folders given on the command line."""

from __future__ import annotations

import fnmatch
import os
from pathlib import Path

from .errors import ReadError
from .formats import supported_extensions

__all__ = ["find_curve_files"]


def find_curve_files(sources, *, glob: str | None = None) -> list[str]:
    """Curve files named by ``sources``, in a deterministic order.

    Parameters
    ----------
    sources : iterable of paths. A file is taken as given (whatever its extension, so
        that ``--input-format`` can apply), ``file#i`` too; a folder is walked recursively, keeping
        files with a supported extension, skipping hidden files and folders.
    glob : optional fnmatch pattern on the file name (``"*.csv"``) for files found in folders.

    Returns
    -------
    list of str paths, sorted within each folder, without duplicates.

    Raises
    ------
    ReadError : a source that does not exist.
    """
    extensions = {e.lower() for e in supported_extensions()}
    found: list[str] = []
    seen: set[str] = set()

    def add(path: str) -> None:
        key = os.path.normpath(path)
        if key not in seen:
            seen.add(key)
            found.append(path)

    from .formats import split_selector

    for source in sources:
        source = str(source)
        path, selected = split_selector(source)
        if selected is not None and os.path.isfile(path):
            add(source)                        # file#i: one curve of a multi-curve file
        elif os.path.isdir(source):
            for root, dirs, files in os.walk(source):
                dirs[:] = sorted(d for d in dirs if not d.startswith("."))
                for name in sorted(files):
                    if name.startswith("."):
                        continue
                    if Path(name).suffix.lower() not in extensions:
                        continue
                    if glob and not fnmatch.fnmatch(name, glob):
                        continue
                    add(os.path.join(root, name))
        elif os.path.exists(source):
            add(source)
        else:
            raise ReadError("no such file or folder", path=source)
    return found


def read_all(paths, *, format: str | None = None):
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
