"""The one way nfdmatch writes a file: whole, atomically, durably, and newer than its inputs.

:func:`write_file` writes the bytes (or lets a writer write them) to a hidden temporary
file in the target's folder (:func:`temp_beside`), flushes it to disk (``fsync``) and
renames it over the target (:func:`publish`, ``os.replace``): a reader sees the old file or
the new one, never half of one, and an interrupted write leaves the old file. When the
target already holds exactly those bytes it is kept (inode, permissions and links), but
its mtime is set to now all the same: a command that succeeds leaves its outputs newer
than its inputs, which is what Make reads (GNU Make, "a target is out of date if it is
older than any of its prerequisites").

What the target is decides how, as a shell's ``>`` would leave it (:func:`resolve`): a
symbolic link is followed and the file it points to is replaced (the link stays a link; the
temporary file is made beside the target, on its file system, so the rename is atomic); a
FIFO, a device or any other file that is not a regular file is written in place, opened
and truncated as ``>`` does (``-o /dev/null`` run as root must not make /dev/null a regular
file; a FIFO's reader must get the bytes), never replaced.

Every file the tool writes goes through here: ``-o`` outputs, ``extract``'s contours, its
manifest and ``--list``, pictures. (The index has its own writer: a temporary HDF5 file
moved into place, ``index/writer.py``.)
"""

from __future__ import annotations

import os
import re
import stat
import tempfile

__all__ = ["write_file", "temp_beside", "publish", "resolve", "is_special"]


def resolve(path: str) -> str:
    """The file a write to ``path`` lands in: symbolic links followed (a dangling link gives
    the name it points to, created as ``>`` would); ``path`` itself when it is no link."""
    path = os.fspath(path)
    return os.path.realpath(path) if os.path.islink(path) else path


def is_special(path: str) -> bool:
    """True when ``path`` (links followed) exists and is not a regular file: a FIFO, a
    character or block device, a socket. Such a file is written in place, never replaced."""
    try:
        mode = os.stat(path).st_mode
    except OSError:
        return False
    return not stat.S_ISREG(mode) and not stat.S_ISDIR(mode)


def _write_in_place(temp: str, path: str) -> None:
    """Copy ``temp``'s bytes into the existing special file ``path`` as ``>`` would (opened
    write-only and truncated; opening a FIFO waits for its reader)."""
    fd = os.open(path, os.O_WRONLY | os.O_TRUNC | getattr(os, "O_NOCTTY", 0))
    try:
        with open(temp, "rb") as src:
            while chunk := src.read(1 << 20):
                view = memoryview(chunk)
                while view:
                    view = view[os.write(fd, view) :]
    finally:
        os.close(fd)


def temp_beside(path: str, extension: str | None = None) -> str:
    """Create an empty hidden temporary file in ``path``'s folder and return its name:
    ``.<name>.<random>.tmp<ext>`` (``<name>`` with characters other than ``A-Z a-z 0-9 . _
    -`` made ``_``, so that libraries taking only UTF-8 names can write it; the same
    extension, or ``extension``, so writers that go by it work). Made by :func:`tempfile.mkstemp`:
    created exclusively (``O_EXCL``: never an existing file, never through a symbolic
    link another user planted), readable by the owner only until :func:`publish`. Beside
    the file a symbolic link ``path`` points to (:func:`resolve`), so that the rename stays
    on one file system. For a special file (:func:`is_special`), which is written in place,
    in the system's temporary folder: /dev is no place for it (nor writable but by root)."""
    folder, name = os.path.split(os.path.abspath(resolve(path)))
    if is_special(path):
        folder = tempfile.gettempdir()
    safe = re.sub(r"[^A-Za-z0-9._-]", "_", name)[:80]
    ext = os.path.splitext(name)[1] if extension is None else extension
    fd, temp = tempfile.mkstemp(prefix=f".{safe}.", suffix=".tmp" + ext, dir=folder)
    os.close(fd)
    return temp


def _umask() -> int:
    try:
        with open("/proc/self/status", encoding="ascii", errors="replace") as fh:
            for line in fh:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    mask = os.umask(0o022)  # no /proc: read it the only portable way
    os.umask(mask)
    return mask


def _fsync(path: str) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _fsync_folder(path: str) -> None:
    """Make the rename durable (best effort: some file systems refuse to sync a folder)."""
    try:
        _fsync(os.path.dirname(os.path.abspath(path)))
    except OSError:
        pass


def publish(temp: str, path: str) -> None:
    """Give ``temp`` (from :func:`temp_beside`) the permissions a new file would have (those
    of the file it replaces, if any), flush it to disk and rename it over ``path`` (over
    the file a link ``path`` points to). A special file ``path`` (:func:`is_special`) gets
    the bytes written into it instead, and ``temp`` is removed."""
    path = resolve(path)
    if is_special(path):
        try:
            _write_in_place(temp, path)
        finally:
            os.remove(temp)
        return
    try:
        info = os.stat(path)
        mode = stat.S_IMODE(info.st_mode) if stat.S_ISREG(info.st_mode) else None
    except OSError:
        mode = None
    os.chmod(temp, mode if mode is not None else 0o666 & ~_umask())
    _fsync(temp)
    os.replace(temp, path)
    _fsync_folder(path)


def _same_bytes(temp: str, path: str) -> bool:
    import filecmp

    try:
        return stat.S_ISREG(os.stat(path).st_mode) and filecmp.cmp(temp, path, shallow=False)
    except OSError:
        return False


def write_file(path, content) -> bool:
    """Write ``path`` whole: ``content`` is the bytes, or ``produce(temp)``, a function that
    writes the file at the temporary path it is given (writers that go by the extension
    get the same one). Returns True when the bytes changed (or the file is new), False when
    ``path`` already held them: it is then kept as it was, with a fresh mtime.

    Errors of ``produce`` and ``OSError`` propagate (callers name the file in their
    message); the temporary file never stays."""
    path = resolve(path)
    temp = temp_beside(path)
    try:
        if callable(content):
            content(temp)
        else:
            with open(temp, "wb") as f:
                f.write(content)
        if _same_bytes(temp, path):
            try:
                os.utime(path)  # the same bytes: keep the file, but it is newer than its inputs
                return False
            except OSError:
                pass  # not ours to touch (another owner): replace it, as a new file would
        publish(temp, path)
        return True
    finally:
        if os.path.lexists(temp):
            os.remove(temp)
