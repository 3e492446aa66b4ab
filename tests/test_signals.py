"""SIGINT and SIGTERM at any moment (issue 34, item 2): during start-up (imports), inside a
long C call that keeps the GIL (HDF5 looping on a damaged heap: no Python handler or thread
runs), inside one that releases it; each ends the program with 130 / 143 and one line.

Each program runs as the console script runs it (``nfdmatch.cli.start.run``) in its own
session, from a small script that adds a test command or slows an import down; every wait
has a limit that only a hang reaches (the 1-s figure is measured by
``benchmarks/sigint_trials.py``, not asserted)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time

import pytest

HERE = os.path.dirname(os.path.abspath(__file__))
REPO = os.path.dirname(HERE)
HANG = os.path.join(HERE, "data", "index", "hang-heap-v2.h5")
LIMIT = 60  # seconds: reached only by a program that does not stop

linux = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="/proc and sigtimedwait")

SIGNALS = [(signal.SIGINT, 130, "interrupted (SIGINT)"), (signal.SIGTERM, 143, "terminated (SIGTERM)")]

# a command that says "ready" on stderr, then enters a C call that does not return
STUCK = """
import ctypes, sys
import click
from nfdmatch.cli import main

@main.command("stuck")
@click.argument("how")
def stuck(how):
    if how == "hdf5":  # HDF5's loop on the damaged heap of issue 34, GIL held (h5py's way)
        import h5py
        f = h5py.File({hang!r}, "r", locking=False)
        print("ready", file=sys.stderr, flush=True)
        f.attrs["format"]
    else:  # a C call that releases the GIL, as the compiled kernels do
        print("ready", file=sys.stderr, flush=True)
        ctypes.CDLL(None).sleep(3600)

from nfdmatch.cli.start import run
run()
"""

# start-up: the import of the command modules says "importing" and takes its time
SLOW_IMPORT = """
import importlib.abc, sys, time

class Slow(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path, target=None):
        if name == "nfdmatch.cli.curves":
            print("importing", file=sys.stderr, flush=True)
            time.sleep(3600)
        return None

sys.meta_path.insert(0, Slow())
from nfdmatch.cli.start import run
run()
"""


# the program's own first imports (before run() installs the handlers): the import of
# cli/signals, which start.py imports, says "importing" and takes a second; the signal meets
# the program there, before any handler of its own exists
SLOW_FIRST_IMPORT = """
import importlib.abc, sys, time

class Slow(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path, target=None):
        if name == "nfdmatch.cli.signals":
            print("importing", file=sys.stderr, flush=True)
            time.sleep(1)
        return None

sys.meta_path.insert(0, Slow())
from nfdmatch.cli.start import run
run()
"""


def _start(script: str, tmp_path, *args):
    path = tmp_path / "program.py"
    path.write_text(textwrap.dedent(script))
    env = dict(os.environ, PYTHONPATH=REPO + os.pathsep + os.environ.get("PYTHONPATH", ""))
    return subprocess.Popen(
        [sys.executable, str(path), *args],
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,  # a process group of its own, as a terminal's job
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),  # as a terminal starts it
    )


def _finish(proc, first_line: str, sig, group: bool, settle: float = 0.0):
    assert proc.stderr.readline() == first_line + "\n", proc.communicate()
    time.sleep(settle)  # from "ready" into the C call (no Python runs there to say so)
    if group:  # Ctrl-C in a terminal, `timeout`: the whole process group
        os.killpg(proc.pid, sig)
    else:  # `kill PID`: the program's process alone
        os.kill(proc.pid, sig)
    try:
        out = proc.stdout.read()
        err = proc.stderr.read()
        proc.wait(LIMIT)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        pytest.fail(f"the program did not stop after {sig.name}")
    return proc.returncode, out, err


def _none_left(pgid: int) -> bool:
    for name in os.listdir("/proc"):
        if name.isdigit():
            try:
                fields = open(f"/proc/{name}/stat").read().rsplit(")", 1)[1].split()
            except OSError:
                continue
            if int(fields[2]) == pgid and fields[0] != "Z":
                return False
    return True


@linux
@pytest.mark.parametrize("group", [True, False], ids=["group", "alone"])
@pytest.mark.parametrize("sig, code, words", SIGNALS, ids=["SIGINT", "SIGTERM"])
def test_a_signal_ends_a_command_stuck_in_hdf5(tmp_path, sig, code, words, group):
    proc = _start(STUCK.format(hang=HANG), tmp_path, "stuck", "hdf5")
    got, out, err = _finish(proc, "ready", sig, group, settle=0.5)
    assert got == code
    assert out == ""
    assert err.startswith(f"Error: {words}: the command did not stop") and len(err.splitlines()) == 1
    assert _none_left(proc.pid)  # the command was killed with its watchdog


@linux
@pytest.mark.parametrize("sig, code, words", SIGNALS, ids=["SIGINT", "SIGTERM"])
def test_a_signal_ends_a_command_in_a_c_call_that_releases_the_gil(tmp_path, sig, code, words):
    proc = _start(STUCK.format(hang=HANG), tmp_path, "stuck", "sleep")
    got, out, err = _finish(proc, "ready", sig, True)
    assert (got, out, err) == (code, "", f"Error: {words}\n")  # its own handler: unwound as usual


@linux
@pytest.mark.parametrize("group", [True, False], ids=["group", "alone"])
@pytest.mark.parametrize("sig, code, words", SIGNALS, ids=["SIGINT", "SIGTERM"])
def test_a_signal_during_the_imports_is_one_line(tmp_path, sig, code, words, group):
    proc = _start(SLOW_IMPORT, tmp_path, "describe", os.path.join(REPO, "sample_curves", "library", "circle.tsv"))
    got, out, err = _finish(proc, "importing", sig, group)
    assert (got, out, err) == (code, "", f"Error: {words}\n")


@linux
def test_the_program_exits_as_its_command_did(tmp_path):
    env = dict(os.environ, PYTHONPATH=REPO + os.pathsep + os.environ.get("PYTHONPATH", ""))
    run = [sys.executable, "-m", "nfdmatch"]
    done = subprocess.run([*run, "describe", str(tmp_path / "missing.csv")], env=env, capture_output=True, text=True)
    assert done.returncode == 2 and done.stderr.startswith("Error: ") and done.stdout == ""
    done = subprocess.run([*run, "nosuchcommand"], env=env, capture_output=True, text=True)
    assert done.returncode == 2
    circle = os.path.join(REPO, "sample_curves", "library", "circle.tsv")
    done = subprocess.run([*run, "describe", circle, "--format", "csv"], env=env, capture_output=True, text=True)
    assert done.returncode == 0 and done.stdout.count("\n") == 2, done.stderr  # a header and its row


@linux
@pytest.mark.parametrize("group", [True, False], ids=["group", "alone"])
@pytest.mark.parametrize("sig, code, words", SIGNALS, ids=["SIGINT", "SIGTERM"])
def test_a_signal_before_the_handlers_exist_is_held_for_them(tmp_path, sig, code, words, group):
    # held from start.py's first statement: no KeyboardInterrupt traceback (SIGINT), no
    # silent death (SIGTERM): the handlers, once installed, end the program with one line
    proc = _start(SLOW_FIRST_IMPORT, tmp_path, "--help")
    got, out, err = _finish(proc, "importing", sig, group)
    assert (got, out, err) == (code, "", f"Error: {words}\n")


@linux
def test_a_command_killed_by_sigkill_is_mirrored_without_a_traceback(tmp_path):
    """The OOM killer (or `kill -9` of the command's process): the program dies of SIGKILL
    as its command did, nothing more on stderr (it was an OSError traceback of the
    watchdog's, which cannot set a handler for SIGKILL, and exit 1)."""
    proc = _start(STUCK.format(hang=HANG), tmp_path, "stuck", "sleep")
    assert proc.stderr.readline() == "ready\n", proc.communicate()
    command = int(open(f"/proc/{proc.pid}/task/{proc.pid}/children").read().split()[0])
    os.kill(command, signal.SIGKILL)
    try:
        out, err = proc.communicate(timeout=LIMIT)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        pytest.fail("the program did not end with its command")
    assert (proc.returncode, out, err) == (-signal.SIGKILL, "", "")


@linux
def test_kill_9_of_the_program_ends_its_command(tmp_path):
    """`kill -9 PID` of the program (the watchdog's pid): its command dies too, as a program
    of one process would (it ran on, orphaned, holding a build's lock until it replaced the
    index), and its own children (a build's workers) follow it."""
    proc = _start(STUCK.format(hang=HANG), tmp_path, "stuck", "sleep")
    assert proc.stderr.readline() == "ready\n", proc.communicate()
    command = int(open(f"/proc/{proc.pid}/task/{proc.pid}/children").read().split()[0])
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait(LIMIT)
    deadline = time.monotonic() + 10
    while not _none_left(proc.pid) and time.monotonic() < deadline:
        time.sleep(0.05)
    if not _none_left(proc.pid):
        os.killpg(proc.pid, signal.SIGKILL)
        pytest.fail(f"the command {command} outlived its program")
