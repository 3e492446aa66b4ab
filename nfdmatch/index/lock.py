"""The build lock: one build at a time per index file."""

from __future__ import annotations

import errno
import fcntl
import os
import time

from ..errors import IndexLockedError, WriteError


class Lock:
    """``flock(LOCK_EX)`` on ``INDEX.lock``; released by the kernel when the process dies.

    ``index_path`` should be the index's real file (symbolic links resolved), so that every
    name of one index takes one lock; ``name`` is the index as the user named it (messages)."""

    def __init__(self, index_path: str, wait: float, name: str | None = None) -> None:
        self.path = index_path + ".lock"
        index_path = index_path if name is None else name
        deadline = time.monotonic() + max(0.0, float(wait or 0.0))
        while True:
            self.fd, self.created = self._open(index_path)
            self._lock(index_path, deadline, wait)
            if self._still_the_file():
                break
            # the build holding it removed the file (it wrote no index): lock the new one
            os.close(self.fd)
        try:  # the pid is for other builds' messages only: a full disk must not stop this one here
            os.ftruncate(self.fd, 0)
            os.pwrite(self.fd, f"{os.getpid()}\n".encode(), 0)
        except OSError:
            pass

    def _open(self, index_path: str) -> tuple[int, bool]:
        """The lock file's descriptor, and whether this call created it."""
        flags = os.O_RDWR | getattr(os, "O_CLOEXEC", 0)
        try:
            while True:
                try:
                    return os.open(self.path, flags | os.O_CREAT | os.O_EXCL, 0o644), True
                except FileExistsError:
                    pass
                try:
                    return os.open(self.path, flags), False
                except FileNotFoundError:
                    continue  # its holder removed it between the two opens: create it
        except OSError as exc:
            raise WriteError(
                f"cannot create the lock file {self.path}: {exc.strerror or exc}", path=index_path
            ) from None

    def _lock(self, index_path: str, deadline: float, wait) -> None:
        while True:
            try:
                fcntl.flock(self.fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                return
            except OSError as exc:
                if exc.errno not in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
                    os.close(self.fd)
                    raise WriteError(f"cannot lock {self.path}: {exc.strerror or exc}", path=index_path) from None
                left = deadline - time.monotonic()
                if left <= 0:
                    holder = self._holder()
                    os.close(self.fd)
                    waited = f" (waited {wait:g} s)" if wait else ""
                    raise IndexLockedError(
                        f"another build holds the lock on {self.path} (pid {holder}){waited}; "
                        f"retry later or pass --wait SECONDS",
                        path=index_path,
                    ) from None
                time.sleep(min(0.05, left))

    def _still_the_file(self) -> bool:
        """Whether the locked descriptor is still the file at the lock's path (a lock on a
        file removed meanwhile would exclude nobody)."""
        try:
            held, there = os.fstat(self.fd), os.stat(self.path)
        except OSError:
            return False
        return (held.st_dev, held.st_ino) == (there.st_dev, there.st_ino)

    def _holder(self) -> str:
        try:
            text = os.pread(self.fd, 32, 0).decode("ascii", "replace").strip()
            return text if text.isdigit() else "unknown"
        except OSError:
            return "unknown"

    def release(self, remove: bool = False) -> None:
        """Unlock; ``remove``: delete the lock file first, while still holding it (a build
        that created it and wrote no index leaves nothing beside an index that does not
        exist; a build waiting on it sees the file gone and locks a new one)."""
        if self.fd is not None:
            if remove:
                try:
                    os.unlink(self.path)
                except OSError:
                    pass
            try:
                fcntl.flock(self.fd, fcntl.LOCK_UN)
            finally:
                os.close(self.fd)
                self.fd = None
