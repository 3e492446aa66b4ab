"""The signal handling of a command's process (``start.py`` has the watchdog process):
SIGINT/SIGTERM before a command runs end the process at once with one line
(:func:`install`); while it runs the first raises in the main thread, later ones are
ignored (:func:`raising`, set by the group for the duration of a command). Signals ignored
when the program started (a background job of a non-interactive shell, nohup) stay ignored.

Imports here: the standard library's cheapest modules only (``start.py`` runs it before numpy).
"""

from __future__ import annotations

import os
import signal
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from collections.abc import Callable, Iterable
    from types import FrameType

EXIT_INTERRUPTED, EXIT_TERMINATED = 130, 143
STOPPING = (signal.SIGINT, signal.SIGTERM)
#: what the watchdog waits for, blocked in it (no handler: nothing raises at a bad moment)
WAITED = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP, signal.SIGCHLD)


class Terminated(KeyboardInterrupt):
    """Raised in the main thread on SIGTERM, so that a command unwinds as on Ctrl-C
    (temporary files removed, worker processes stopped) and exits 143."""


def exit_code(signum: int) -> int:
    return EXIT_TERMINATED if signum == signal.SIGTERM else EXIT_INTERRUPTED


def message(signum: int) -> str:
    return "terminated (SIGTERM)" if signum == signal.SIGTERM else "interrupted (SIGINT)"


def say(line: str) -> None:
    try:
        os.write(2, f"Error: {line}\n".encode())
    except OSError:
        pass


def _exit_now(signum: int, frame: FrameType | None) -> None:
    """Before a command runs: nothing to clean up, so the one line and the exit code now."""
    for s in STOPPING:  # a second signal would run this again, between two of its lines
        signal.signal(s, signal.SIG_IGN)
    say(message(signum))
    os._exit(exit_code(signum))


_raised = False
#: set by start.run: this process runs the program's command, not a test's or a library caller's
program = False


def deaf() -> None:
    """SIGINT/SIGTERM ignored from now on: the process is on its way out (a signal passed on
    by the watchdog after the first must not cut its clean-up or its exit short; Python's
    finalisation resets handlers, not an ignored signal)."""
    for s in heeded(STOPPING):
        signal.signal(s, signal.SIG_IGN)


def _raise_once(signum: int, frame: FrameType | None) -> None:
    global _raised
    if _raised:
        return  # the first signal is unwinding; the watchdog keeps the deadline
    _raised = True
    raise Terminated() if signum == signal.SIGTERM else KeyboardInterrupt()


def raising() -> Callable[[], None] | None:
    """While a command runs (main thread only): the first SIGINT/SIGTERM raises
    KeyboardInterrupt/Terminated, later ones are ignored. Returns what restores the
    previous handlers, or None off the main thread."""
    import threading

    global _raised
    if threading.current_thread() is not threading.main_thread():
        return None
    _raised = False
    previous = {s: signal.signal(s, _raise_once) for s in heeded(STOPPING)}

    def restore() -> None:
        if _raised and program:
            deaf()
            return
        for s, handler in previous.items():
            signal.signal(s, handler)

    return restore


def heeded(signals: Iterable[signal.Signals]) -> list[signal.Signals]:
    """``signals`` minus those ignored when the program started (a job started in the
    background of a non-interactive shell, or by nohup: it must stay deaf to them)."""
    return [s for s in signals if s not in _IGNORED]


_IGNORED = frozenset(s for s in WAITED if s != signal.SIGCHLD and signal.getsignal(s) == signal.SIG_IGN)


def install() -> None:
    """The command's side: until a command runs, SIGINT/SIGTERM exit at once."""
    for s in heeded(STOPPING):
        signal.signal(s, _exit_now)
