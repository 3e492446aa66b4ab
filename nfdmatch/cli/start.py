"""The ``nfdmatch`` program's first steps: gone within a second of SIGINT or SIGTERM, whatever
it is doing.

Python runs a signal handler only between two bytecodes of the main thread: inside a long C
call that keeps the GIL (HDF5 through h5py does; an HDF5 loop on a damaged file never
returns, issue 34) no handler runs, and no Python thread either, so no watchdog thread can
help. So :func:`run` forks before anything heavy is imported: the **command** runs in the
child; the parent, the **watchdog**, holds nothing but the interpreter and waits. On
SIGINT/SIGTERM (its own, or its process group's: a terminal, ``timeout``, systemd) the
watchdog passes the signal on to a command still running :data:`PASS_ON_AFTER` seconds
later (a group's signal reached it already) and gives it :data:`GRACE` seconds to clean
up and exit as usual (130 / 143, one line: ``cli/options.py``); a command still there then
is killed (SIGKILL) and the watchdog exits 130 / 143 with one line. What such a command
leaves is what ``kill -9`` leaves: its temporary index file (removed by the next build into
that index, docs/index-format.md) and its lock (released by the kernel at its death).
``kill -9`` of the watchdog (the program's pid) kills the command with it (Linux:
:func:`_die_with`), as it would a program of one process.

Until a command runs (imports, argument parsing) a signal ends the process at once with
that one line and exit code: nothing is held yet. While a command runs, the first signal
raises in the main thread (:class:`KeyboardInterrupt`, or ``signals.Terminated`` for
SIGTERM) and later ones are ignored, so that the first unwinds with its clean-ups
uninterrupted (``signals.raising``, installed by the group for the duration of a command).

The command's exit status is the watchdog's: its exit code, or, when a signal killed it
(a crash), the same signal. ``NFDMATCH_NO_WATCHDOG=1`` runs the command in the one process
(no fork; a command inside a long C call then waits for the call).

Its first statement holds SIGINT/SIGTERM (blocked; those ignored when the program started
stay ignored) until :func:`run` has installed their handlers: from there on a signal at any
moment ends the program as above, never as a ``KeyboardInterrupt`` traceback. Importing
this module is starting the program: only an entry point imports it (the console script,
``python -m nfdmatch``). What comes before is Python's own start-up, where Python's
behaviour stays (docs/performance.md, "Signals at start-up": the window, measured).

Imports here: the standard library's cheapest modules only (it runs before numpy).
"""

from __future__ import annotations

# first: ``_signal`` is the interpreter's own module, loaded before any Python code runs
# (``signal`` would import its enums first)
import _signal

#: the signals held from the first statement until :func:`run` has set their handlers
HELD = [s for s in (_signal.SIGINT, _signal.SIGTERM) if _signal.getsignal(s) != _signal.SIG_IGN]
if hasattr(_signal, "pthread_sigmask"):
    _signal.pthread_sigmask(_signal.SIG_BLOCK, HELD)

import os  # noqa: E402
import signal  # noqa: E402
import time  # noqa: E402

from . import signals  # noqa: E402
from .signals import WAITED, exit_code, heeded, install, message, say  # noqa: E402

#: seconds a command has after SIGINT/SIGTERM before the watchdog kills it (the goal: gone
#: within 1 s; a command's own clean-up takes milliseconds)
GRACE = 0.8
#: seconds after which the watchdog passes its signal on to a command still running
PASS_ON_AFTER = 0.05


def _mirror(status: int) -> None:
    """Exit as the command did: its code, or killed by the same signal."""
    if os.WIFSIGNALED(status):
        sig = os.WTERMSIG(status)
        if sig not in (signal.SIGKILL, signal.SIGSTOP):  # those two have no handler to reset
            signal.signal(sig, signal.SIG_DFL)
            signal.pthread_sigmask(signal.SIG_UNBLOCK, [sig])
        os.kill(os.getpid(), sig)
        os._exit(128 + sig)
    os._exit(os.WEXITSTATUS(status) if os.WIFEXITED(status) else 1)


def _watch(pid: int) -> None:
    """The watchdog's life: wait for the command; on SIGINT/SIGTERM/SIGHUP pass it on and
    keep the deadline. Never returns."""
    signum = deadline = None
    passed_on, passed_on_at = False, 0.0
    waited = heeded(WAITED)
    while True:
        if deadline is None:
            info = signal.sigwaitinfo(waited)
        else:
            wake = deadline if passed_on else min(deadline, passed_on_at)
            info = signal.sigtimedwait(waited, max(0.0, wake - time.monotonic()))
        done, status = os.waitpid(pid, os.WNOHANG)
        if done:
            _mirror(status)
        now = time.monotonic()
        if signum is not None and not passed_on and now >= passed_on_at:
            # still there: the signal was this process's alone (`kill PID`), or the command
            # is inside a long call (where the signal waits, and the deadline ends it)
            os.kill(pid, signum)
            passed_on = True
        if deadline is not None and now >= deadline:
            os.kill(pid, signal.SIGKILL)
            os.waitpid(pid, 0)
            say(f"{message(signum)}: the command did not stop within {GRACE} s (inside a long call); killed")
            os._exit(exit_code(signum))
        if info is not None and info.si_signo != signal.SIGCHLD and signum is None:
            signum = info.si_signo
            # a signal to the process group (a terminal, `timeout`) reached the command too:
            # it is passed on only if the command has not ended a moment later, so that it
            # does not come twice
            passed_on_at = now + PASS_ON_AFTER
            deadline = now + GRACE


def _die_with(watchdog: int) -> None:
    """The command's side: killed (SIGKILL) when its watchdog dies, which only SIGKILL does
    (``kill -9`` of the program's pid, the watchdog's): the program then ends as a program
    of one process would, never leaving its command running on, orphaned, with an index's
    lock held, to replace that index later. Linux (``prctl(PR_SET_PDEATHSIG)``) only."""
    import sys

    if not sys.platform.startswith("linux"):
        return
    try:
        import ctypes

        if ctypes.CDLL(None, use_errno=True).prctl(1, int(signal.SIGKILL), 0, 0, 0) != 0:  # PR_SET_PDEATHSIG
            return
    except (OSError, AttributeError):
        return
    if os.getppid() != watchdog:  # it died before the call
        os.kill(os.getpid(), signal.SIGKILL)


def run() -> None:
    """The console script ``nfdmatch`` and ``python -m nfdmatch``."""
    watchdog = hasattr(os, "fork") and hasattr(signal, "sigtimedwait") and not os.environ.get("NFDMATCH_NO_WATCHDOG")
    if watchdog:
        # blocked before the fork (SIGINT/SIGTERM since the first statement, HELD): in the
        # watchdog for good, in the command until its handlers are set
        signal.pthread_sigmask(signal.SIG_BLOCK, heeded(WAITED))
        child_handler = signal.signal(signal.SIGCHLD, signal.SIG_DFL)  # ignored: no status to wait for
        parent = os.getpid()
        pid = os.fork()
        if pid:
            _watch(pid)
        _die_with(parent)
        signal.signal(signal.SIGCHLD, child_handler)
    signals.program = True
    install()
    if hasattr(signal, "pthread_sigmask"):  # a signal held until now comes, to its handler
        signal.pthread_sigmask(signal.SIG_UNBLOCK, heeded(WAITED) if watchdog else HELD)
    from . import main

    try:
        main(prog_name="nfdmatch")
    finally:
        signals.deaf()  # done: a signal now would only turn a finished command into a killed one
