"""Where an index's files are: the stored path of a found file, and back (docs/index-format.md,
"Paths and ids").

A stored path is relative to the index's folder (the folder of its real file) when the file
lies inside it, else absolute; it never depends on the build's working directory or on how
the source was spelled. These functions are pure path arithmetic plus ``realpath``: they
never open a curve file.
"""

from __future__ import annotations

import os

from ..formats import split_selector
from ..names import decode_name, encode_name


def index_file(index_path: str) -> str:
    """The index's real file: a symbolic link at ``index_path`` resolved (the link stays a
    link: builds replace its target, and lock it)."""
    return os.path.realpath(index_path)


def index_folder(index_path: str) -> str:
    """The folder stored paths are relative to: that of the index's real file."""
    return os.path.dirname(index_file(index_path))


def _real_parent(path: str) -> str:
    """``path`` with its folder resolved and its own name kept (a link to a file keeps its name)."""
    folder, name = os.path.split(os.path.abspath(path))
    return os.path.join(os.path.realpath(folder), name)


def stored(location: str, base: str) -> str:
    """The stored form of an absolute real ``location``: relative to ``base`` inside it, else
    absolute; as an id (:func:`~nfdmatch.names.encode_name`: HDF5 strings are UTF-8, and two
    names never share a stored form)."""
    # a string prefix first: relpath costs ~70 us, and a build calls this once per file
    prefix = base if base.endswith(os.sep) else base + os.sep
    if location.startswith(prefix) and os.pardir not in location.split(os.sep):
        return encode_name(location[len(prefix) :])
    rel = os.path.relpath(location, base)
    if rel == os.pardir or rel.startswith(os.pardir + os.sep):
        return encode_name(location)
    return encode_name(rel)


def source_location(source: str) -> str:
    """The real location of a source as given: a folder resolved (``lib``, ``./lib/``,
    ``/abs/lib`` and a link to it are one place); a file (or ``file#i``) by its folder."""
    path, selected = split_selector(source)
    if selected is not None and os.path.isfile(path):
        return _real_parent(path) + f"#{selected}"
    if os.path.isdir(source):
        return os.path.realpath(source)
    return _real_parent(source)


def found_location(found: str, source: str, source_real: str, is_folder: bool) -> str:
    """The real location of ``found``, a path that a walk of ``source`` (real location
    ``source_real``; ``is_folder``: the source is a folder) yielded: the part below the source
    is kept as found (a walk follows no folder links below the source, and a link to a file
    keeps its name)."""
    if not is_folder:
        return source_real
    prefix = source if source.endswith(os.sep) else source + os.sep
    if found.startswith(prefix):  # the walk joins below the source as given
        below = os.path.normpath(found[len(prefix) :])
        if not below.startswith(os.pardir):
            return os.path.join(source_real, below)
    return os.path.join(source_real, os.path.relpath(found, source))


def curve_ids(path: str, count: int) -> list[str]:
    """Ids of a file's ``count`` curves from its stored path: ``path`` alone, else ``path#i``
    (the readers' rule, :func:`nfdmatch.formats._chain.curve_id`)."""
    return [path] if count == 1 else [f"{path}#{i}" for i in range(count)]


def id_collision(counts: dict) -> tuple[str, str] | None:
    """Two files whose curve ids would meet, from ``{stored path: curve count}``: ``(P, P#i)``
    when the file P holds more than i curves (ids ``P#0``, ``P#1``, ...) and another file is
    named ``P#i``; None when every id is unique. The one collision the id rule cannot avoid
    (names are encoded one-to-one, :mod:`nfdmatch.names`, but ``#`` is the rule's own)."""
    for path in counts:
        head, sep, tail = path.rpartition("#")
        if sep and tail.isdigit() and str(int(tail)) == tail and counts.get(head, 0) > max(1, int(tail)):
            return head, path
    return None


def openable(path: str, base: str) -> str:
    """A path that opens the stored ``path`` (``file#i`` kept) from the working directory:
    a stored absolute path as it is (the spelling ``index ls`` shows, in messages and the
    build's failures alike, from any working directory: cron runs in ``/``); a stored
    relative one relative to the working directory when the file is below it (messages
    stay short), else absolute. The file's name, decoded (:func:`~nfdmatch.names.decode_name`)."""
    path = decode_name(path)
    if os.path.isabs(path):
        return path
    return display(os.path.join(base, path))


def display(path: str) -> str:
    """An absolute ``path`` as the user would type it from the working directory (itself
    from ``/``, as cron runs: ``abs/x`` there would only hide the leading slash)."""
    try:
        cwd = os.getcwd()
        if os.path.dirname(cwd) == cwd:  # the root
            return path
        rel = os.path.relpath(path, cwd)
    except (ValueError, OSError):
        return path
    if rel == os.pardir or rel.startswith(os.pardir + os.sep):
        return path
    return rel
