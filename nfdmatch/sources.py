"""Finding curve files under files and folders given on the command line."""

from __future__ import annotations

import fnmatch
import os
from pathlib import Path

from .errors import ReadError
from .formats import supported_extensions

__all__ = ["find_curve_files", "walk_folder"]


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
    found = UniquePaths()

    from .formats import split_selector

    for source in sources:
        source = str(source)
        path, selected = split_selector(source)
        if selected is not None and os.path.isfile(path):
            found.add(source)                  # file#i: one curve of a multi-curve file
        elif os.path.isdir(source):
            for file in walk_folder(source, extensions, glob=glob):
                found.add(file)
        elif os.path.exists(source):
            found.add(source)
        else:
            raise ReadError("no such file or folder", path=source)
    return found.paths


def walk_folder(folder: str, extensions, *, glob: str | None = None, exclude=()):
    """Yield the files below ``folder`` whose extension (lower-cased, with the dot) is in
    ``extensions`` and whose name matches ``glob``, recursively, sorted within each folder,
    skipping hidden files and folders and the folders in ``exclude``."""
    skip = {os.path.realpath(str(e)) for e in exclude}
    if os.path.realpath(folder) in skip:
        return
    for root, dirs, files in os.walk(folder):
        dirs[:] = sorted(d for d in dirs if not d.startswith(".")
                         and not (skip and os.path.realpath(os.path.join(root, d)) in skip))
        for name in sorted(files):
            if name.startswith(".") or Path(name).suffix.lower() not in extensions:
                continue
            if glob and not fnmatch.fnmatch(name, glob):
                continue
            yield os.path.join(root, name)


class UniquePaths:
    """Paths in first-seen order, a path given twice (up to normpath) kept once."""

    def __init__(self):
        self.paths: list[str] = []
        self._seen: set[str] = set()

    def add(self, path: str) -> None:
        key = os.path.normpath(path)
        if key not in self._seen:
            self._seen.add(key)
            self.paths.append(path)


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
