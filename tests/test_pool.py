"""The build's worker pool: batches, worker deaths (a crashing reader, the OOM killer), the
per-file time limit, and Ctrl-C / SIGTERM during a build (real signals to a real process group).

Worker deaths and hung readers are produced on demand by the test hook of
``nfdmatch.index.pool`` (environment variable ``NFDMATCH_TEST_WORKER_HOOK``), or by killing
the worker processes from here."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
from conftest import run_cli

import nfdmatch.index.pool as pool
from nfdmatch.errors import ParameterError, WorkerError
from nfdmatch.index import build_index, open_index

#: end-to-end as a whole (subprocesses, real files, pools): left out by `make test-fast`
pytestmark = pytest.mark.slow

HERE = os.path.dirname(os.path.abspath(__file__))
REPO = os.path.dirname(HERE)
HOOK = "NFDMATCH_TEST_WORKER_HOOK"
linux = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="uses fork, /proc and signals")


def _write_folder(folder, n, seed=0):
    """``n`` one-curve CSV files c000.csv ... in ``folder``; returns their paths, sorted."""
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    paths = []
    for i in range(n):
        t = np.linspace(0, 2 * np.pi, int(rng.integers(20, 40)), endpoint=False)
        a = rng.normal(size=(3, 4))
        pts = (
            np.outer(np.cos(t), a[:, 0])
            + np.outer(np.sin(t), a[:, 1])
            + np.outer(np.cos(2 * t), a[:, 2]) / 3
            + np.outer(np.sin(3 * t), a[:, 3]) / 5
        )
        path = folder / f"c{i:03d}.csv"
        path.write_text("x,y,z\n" + "".join(f"{x:.9f},{y:.9f},{z:.9f}\n" for x, y, z in pts))
        paths.append(str(path))
    return paths


@pytest.fixture
def folder(tmp_path):
    return tmp_path / "src"


def _ids(index_path):
    """The index's ids as absolute paths (stored ids are relative to the index's folder)."""
    home = os.path.dirname(os.path.abspath(index_path))
    with open_index(index_path) as idx:
        return sorted(os.path.normpath(os.path.join(home, i)) for i in idx.ids())


_invoke = run_cli


# --------------------------------------------------------------------------- batches


def test_batches_group_small_files_and_keep_large_ones_alone(tmp_path):
    small = _write_folder(tmp_path / "small", 300)
    big = tmp_path / "big.csv"
    big.write_text("x,y,z\n" + "1,2,3\n4,5,7\n2,8,1\n" * 30000)  # ~ 600 KB
    tasks = [(p, None, 128, 16, "rms", None) for p in small[:150] + [str(big)] + small[150:]]
    batches = pool._batches(tasks)
    assert sorted(i for b in batches for i in b) == list(range(len(tasks)))
    assert all(b == list(range(b[0], b[-1] + 1)) for b in batches)  # file order kept
    assert [150] in batches  # the large file alone
    assert all(len(b) <= pool._BATCH_FILES for b in batches)
    assert len(batches) >= pool._MIN_BATCHES
    assert max(len(b) for b in batches) > 10  # small files share


def test_serial_and_parallel_builds_of_many_files_are_identical(folder, tmp_path):
    paths = _write_folder(folder, 200)
    (folder / "bad.csv").write_text("x,y,z\n1,2,3\n")
    serial = build_index([str(folder)], tmp_path / "serial.h5", jobs=1)
    calls = []
    parallel = build_index(
        [str(folder)],
        tmp_path / "parallel.h5",
        jobs=2,
        file_timeout=60,
        progress=lambda done, total: calls.append((done, total)),
    )
    assert serial.changes == parallel.changes and serial.failures == parallel.failures
    assert (parallel.added, parallel.failed) == (200, 1)
    # progress is per file, even though files travel in batches
    assert calls[0] == (0, 201) and calls[-1] == (201, 201) and len(calls) == 202
    with open_index(tmp_path / "serial.h5") as a, open_index(tmp_path / "parallel.h5") as b:
        assert a.ids() == b.ids() == sorted(os.path.relpath(p, tmp_path) for p in paths)  # ids: relative to the index
        ra, rb = a.read_rows(0, a.n_curves), b.read_rows(0, b.n_curves)
        for key in ra:
            np.testing.assert_array_equal(ra[key], rb[key], err_msg=key)


# --------------------------------------------------------------------------- worker deaths


@linux
@pytest.mark.parametrize("jobs", [1, 2])
def test_a_file_that_kills_its_reader_fails_alone(folder, tmp_path, monkeypatch, jobs):
    paths = _write_folder(folder, 40)
    crasher, flaky, leaver = paths[7], paths[21], paths[30]
    # c007 kills every process that reads it; c021 kills its reader once (an OOM kill while
    # reading it); c030's reader exits abruptly once
    monkeypatch.setenv(HOOK, "kill:c007.csv,killonce:c021.csv,exitonce:c030.csv")
    index = tmp_path / "idx.h5"
    report = build_index([str(folder)], index, jobs=jobs, file_timeout=60)
    assert (report.added, report.failed, report.curves) == (39, 1, 39)
    assert report.failures == [
        (crasher, f"{crasher}: the process reading it died twice (killed by SIGKILL); the file crashes its reader")
    ]
    assert _ids(index) == sorted(set(paths) - {crasher})
    assert os.path.exists(flaky + ".hooked") and os.path.exists(leaver + ".hooked")


@linux
def test_cli_crashing_file_exit_3_at_jobs_1_without_traceback(folder, tmp_path):
    paths = _write_folder(folder, 12)
    index = tmp_path / "idx.h5"
    code, out, err = _invoke("index", "build", folder, "--index", index, "--jobs", "1", env={HOOK: "kill:c003.csv"})
    assert code == 3, err
    assert out == ""
    assert f"Error: {paths[3]}: the process reading it died twice (killed by SIGKILL)" in err
    assert "11 added" in err and "1 failed" in err and "Traceback" not in err
    assert _ids(index) == sorted(set(paths) - {paths[3]})


@linux
def test_cli_segfaulting_reader_in_a_parallel_build(folder, tmp_path):
    """Through a real process: nothing but the one error line reaches stderr (no worker
    traceback, no fatal-error dump), every other file is indexed, exit 3."""
    paths = _write_folder(folder, 25)
    index = tmp_path / "idx.h5"
    proc = _cli(["index", "build", folder, "--index", index, "--jobs", "2"], env={HOOK: "segv:c011.csv"})
    out, err = proc.communicate(timeout=120)
    assert proc.returncode == 3, err
    assert out == ""
    assert err.splitlines() == [
        f"Error: {paths[11]}: the process reading it died twice (killed by SIGSEGV); the file crashes its reader",
        err.splitlines()[1],
        "Error: 1 of 25 files could not be read",
    ]
    assert err.splitlines()[1].startswith(
        f"indexed into {index}: 24 added, 0 updated, 0 removed, 0 unchanged, 1 failed files; 24 curves;"
    )
    assert _ids(index) == sorted(set(paths) - {paths[11]})


@linux
def test_cli_workers_dying_for_no_file_exit_2_and_keep_the_index(folder, tmp_path):
    _write_folder(folder, 30)
    index = tmp_path / "idx.h5"
    assert _invoke("index", "build", folder, "--index", index, "--jobs", "1")[0] == 0
    before = index.read_bytes()
    code, out, err = _invoke("index", "build", folder, "--index", index, "--rebuild", env={HOOK: "killonce:*"})
    assert code == 2 and out == ""
    assert err.startswith("Error: worker processes keep dying (") and err.endswith("nothing was written\n")
    assert index.read_bytes() == before


@linux
def test_deaths_no_file_explains_abort_the_build_and_keep_the_index(folder, tmp_path, monkeypatch):
    paths = _write_folder(folder, 30)
    index = tmp_path / "idx.h5"
    build_index([str(folder)], index, jobs=1)
    before = index.read_bytes()
    # every file kills its reader the first time only: each one reads fine when retried, so
    # no file is to blame; the machine is (as with an OOM killer at work on every worker)
    monkeypatch.setenv(HOOK, "killonce:*")
    with pytest.raises(WorkerError, match=r"worker processes keep dying \(\d+ deaths, last: killed by SIGKILL\)"):
        build_index([str(folder)], index, jobs=2, rebuild=True, file_timeout=60)
    assert index.read_bytes() == before
    assert [n for n in os.listdir(tmp_path) if ".tmp-" in n] == []
    # the 9th death stops it; the other worker may have been killed meanwhile too
    assert pool._SPARE_DEATHS + 1 <= sum(os.path.exists(p + ".hooked") for p in paths) <= pool._SPARE_DEATHS + 2


def _children(pid):
    out = []
    try:
        tasks = os.listdir(f"/proc/{pid}/task")
    except OSError:
        return out
    for task in tasks:
        try:
            out += [int(x) for x in open(f"/proc/{pid}/task/{task}/children").read().split()]
        except OSError:
            continue
    return out


def _command(proc) -> int:
    """The process running the command: the one child of the program's watchdog process
    (``nfdmatch.cli.start``); the build's workers are its children."""
    _wait_for(lambda: len(_children(proc.pid)) == 1, proc)
    return _children(proc.pid)[0]


def _alive(pid):
    try:
        return open(f"/proc/{pid}/stat").read().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


def _as_a_terminal_starts_it() -> None:
    """SIGINT at its default in the child, as in a terminal's foreground job: a test run
    started in the background of a non-interactive shell (``make test &``) inherits SIGINT
    ignored, and Python then never turns it into KeyboardInterrupt."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def _cli(args, env=None, **kw):
    full_env = dict(os.environ, PYTHONPATH=REPO + os.pathsep + os.environ.get("PYTHONPATH", ""), **(env or {}))
    return subprocess.Popen(
        [sys.executable, "-m", "nfdmatch", *map(str, args)],
        env=full_env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        preexec_fn=_as_a_terminal_starts_it,
        **kw,
    )


def _wait_for(predicate, proc, seconds=60.0):
    deadline = time.monotonic() + seconds
    while not predicate():
        assert proc.poll() is None, proc.communicate()
        assert time.monotonic() < deadline, "timed out waiting"
        time.sleep(0.01)


@linux
def test_workers_killed_from_outside_are_replaced(folder, tmp_path):
    """The OOM killer's way: SIGKILL to the workers while they read; every file is indexed."""
    paths = _write_folder(folder, 60)
    index = tmp_path / "idx.h5"
    # c010 hangs the first time it is read, so that a worker is surely busy when we kill
    proc = _cli(["index", "build", folder, "--index", index, "--jobs", "2"], env={HOOK: "sleeponce:c010.csv"})
    _wait_for(lambda: os.path.exists(paths[10] + ".hooked"), proc)
    command = _command(proc)
    _wait_for(lambda: len(_children(command)) >= 1, proc)
    for pid in _children(command):
        os.kill(pid, signal.SIGKILL)
    out, err = proc.communicate(timeout=120)
    assert proc.returncode == 0, err
    assert "60 added" in err and "0 failed" in err and "Traceback" not in err
    assert _ids(index) == sorted(paths)


# --------------------------------------------------------------------------- time limit


@linux
@pytest.mark.parametrize("jobs", [1, 2])
def test_a_file_that_never_finishes_fails_alone(folder, tmp_path, monkeypatch, jobs):
    paths = _write_folder(folder, 30)
    monkeypatch.setenv(HOOK, "sleep:c005.csv")
    index = tmp_path / "idx.h5"
    report = build_index([str(folder)], index, jobs=jobs, file_timeout=1.5)
    assert (report.added, report.failed) == (29, 1)
    assert report.failures == [
        (paths[5], f"{paths[5]}: reading it took longer than 1.5 s (the per-file time limit, --file-timeout); stopped")
    ]
    assert _ids(index) == sorted(set(paths) - {paths[5]})


@linux
def test_cli_file_timeout(folder, tmp_path):
    paths = _write_folder(folder, 8)
    index = tmp_path / "idx.h5"
    code, out, err = _invoke(
        "index",
        "build",
        folder,
        "--index",
        index,
        "--jobs",
        "1",
        "--file-timeout",
        "1",
        "--format",
        "json",
        env={HOOK: "sleep:c002.csv"},
    )
    assert code == 3, err
    assert f"Error: {paths[2]}: reading it took longer than 1 s" in err and "Traceback" not in err
    assert '"failed": 1' in out and '"added": 7' in out
    code, _, err = _invoke("index", "build", folder, "--index", index, "--file-timeout", "-1")
    assert code == 2 and "--file-timeout" in err


def test_file_timeout_is_checked(folder, tmp_path):
    _write_folder(folder, 2)
    for bad in (-1, float("nan"), float("inf"), "10", True):
        with pytest.raises(ParameterError, match="file_timeout"):
            build_index([str(folder)], tmp_path / "idx.h5", file_timeout=bad)


# --------------------------------------------------------------------------- signals

_INT = (signal.SIGINT, 130, "interrupted (SIGINT)")
_TERM = (signal.SIGTERM, 143, "terminated (SIGTERM)")


@linux
@pytest.mark.parametrize(
    "sig, code, word, jobs, group",
    [
        (*_INT, 1, True),
        (*_INT, 2, True),
        (*_TERM, 1, True),
        (*_TERM, 2, True),
        # to the build's process alone, as `timeout -s INT 3 nfdmatch ...` or `kill PID` send it
        (*_INT, 2, False),
        (*_TERM, 2, False),
    ],
)
def test_signal_stops_a_build_cleanly(folder, tmp_path, sig, code, word, jobs, group):
    paths = _write_folder(folder, 300)
    index = tmp_path / "idx.h5"
    build_index([str(folder)], index, jobs=1)
    before = index.read_bytes()
    # c150 hangs: the build is surely under way (temporary file open, workers busy) when the
    # signal comes, as Ctrl-C in a terminal goes to the whole foreground process group
    proc = _cli(
        ["index", "build", folder, "--index", index, "--jobs", str(jobs), "--rebuild"],
        env={HOOK: "sleeponce:c150.csv"},
        start_new_session=True,
    )
    _wait_for(lambda: os.path.exists(paths[150] + ".hooked") and any(".tmp-" in n for n in os.listdir(tmp_path)), proc)
    workers = _children(_command(proc))
    if sig == signal.SIGINT:
        # workers ignore SIGINT (only the parent acts on it): not one of them may die of it
        for pid in workers:
            os.kill(pid, signal.SIGINT)
        time.sleep(0.5)
        if proc.poll() is not None or not all(_alive(pid) for pid in workers):
            os.killpg(proc.pid, signal.SIGKILL)
            pytest.fail(f"a worker died of SIGINT: {proc.communicate()}")
    if group:  # Ctrl-C in a terminal: the whole foreground process group
        os.killpg(proc.pid, sig)
    else:
        os.kill(proc.pid, sig)
    out, err = proc.communicate(timeout=30)  # a hang fails here
    assert proc.returncode == code, err
    assert out == ""
    assert err.strip().splitlines()[-1] == f"Error: {word}"
    assert "Traceback" not in err and "KeyboardInterrupt" not in err and "Aborted" not in err
    assert index.read_bytes() == before
    assert sorted(os.listdir(tmp_path)) == ["idx.h5", "idx.h5.lock", "src"]
    assert len(workers) >= 1
    assert not any(_alive(pid) for pid in workers)  # no worker outlives the build


# a build whose graph workers (forked by the command: nfdmatch._fork) never finish a block
# (or fail: {action}): the first says "ready" on stderr; the command itself (the watchdog's
# child) searches as usual
GRAPH_WORKERS = """
import os, time
from nfdmatch.search import graph

graph._BLOCK_ROWS = 4  # many blocks: every worker busy
watchdog = os.getpid()  # the program's first process (nfdmatch.cli.start): the command is its child
real = graph.{stage}

def hang(*args):
    if os.getppid() != watchdog:  # a worker of the command
        os.write(2, b"ready\\n")  # one write: two workers' lines never mix
        {action}
    return real(*args)

graph.{stage} = hang
from nfdmatch.cli.start import run
run()
"""


@linux
@pytest.mark.parametrize(
    "elastic, stage", [(False, "nearest_others"), (True, "_fused_block")], ids=["graph", "graph-elastic"]
)
@pytest.mark.parametrize("sig, code, word, group", [(*_INT, True), (*_TERM, False)], ids=["SIGINT-group", "SIGTERM"])
def test_signal_stops_a_build_while_workers_search_the_graph(folder, tmp_path, sig, code, word, group, elastic, stage):
    """Ctrl-C / SIGTERM while forked workers are inside a block of the graph's search (or
    of its fused lists, --elastic): they are stopped at once, so that the command cleans up
    itself (exit 130 / 143, its one line, no temporary file) within its watchdog's grace
    rather than being killed with its temporary file left behind."""
    from test_signals import _finish, _none_left, _start

    _write_folder(folder, 24)
    index = tmp_path / "idx.h5"
    build_index([str(folder)], index, jobs=1, graph=8)
    before = index.read_bytes()
    args = ["index", "build", str(folder), "--index", str(index), "--graph", "8", "--jobs", "2", "--rebuild"]
    proc = _start(
        GRAPH_WORKERS.format(stage=stage, action="time.sleep(3600)"),
        tmp_path,
        *args,
        *(["--elastic"] if elastic else []),
    )
    got, out, err = _finish(proc, "ready", sig, group)
    assert got == code, err
    assert out == ""
    assert err.strip().splitlines()[-1] == f"Error: {word}", err  # not "... did not stop within 0.8 s; killed"
    assert "Traceback" not in err
    assert index.read_bytes() == before
    assert sorted(os.listdir(tmp_path)) == ["idx.h5", "idx.h5.lock", "program.py", "src"]
    assert _none_left(proc.pid)  # no worker outlives the build


@linux
@pytest.mark.parametrize(
    "elastic, stage", [(False, "nearest_others"), (True, "_fused_block")], ids=["graph", "graph-elastic"]
)
def test_a_graph_worker_that_fails_is_one_line_and_keeps_the_index(folder, tmp_path, elastic, stage):
    """A block of the graph's search raising in a forked worker (here MemoryError): one
    line naming it, exit 2, no traceback, the old index as it was, no temporary file and no
    worker left (it was "cannot write the index: a worker process failed:" and nothing more)."""
    from test_signals import LIMIT, _none_left, _start

    _write_folder(folder, 24)
    index = tmp_path / "idx.h5"
    build_index([str(folder)], index, jobs=1, graph=8)
    before = index.read_bytes()
    args = ["index", "build", str(folder), "--index", str(index), "--graph", "8", "--jobs", "2", "--rebuild"]
    action = "raise MemoryError('no room for the lists')"
    proc = _start(
        GRAPH_WORKERS.format(stage=stage, action=action), tmp_path, *args, *(["--elastic"] if elastic else [])
    )
    out, err = proc.communicate(timeout=LIMIT)
    assert proc.returncode == 2, err
    assert out == ""
    lines = [line for line in err.splitlines() if line != "ready"]
    assert lines == ["Error: a worker process failed: MemoryError: no room for the lists"], err
    assert index.read_bytes() == before
    assert sorted(os.listdir(tmp_path)) == ["idx.h5", "idx.h5.lock", "program.py", "src"]
    assert _none_left(proc.pid)


@linux
def test_workers_of_a_fork_server_see_the_environment_of_now(folder, tmp_path, monkeypatch):
    """With other threads alive, workers come from a fork server, whose environment is that
    of when it started: the NFDMATCH_* variables (limits, the test hook) are sent along."""
    import threading

    paths = _write_folder(folder, 20)
    stop = threading.Event()
    t = threading.Thread(target=stop.wait)
    t.start()
    try:
        build_index([str(folder)], tmp_path / "first.h5", jobs=2)  # the fork server starts here
        monkeypatch.setenv(HOOK, "kill:c004.csv")
        monkeypatch.setenv("NFDMATCH_MAX_FILE_BYTES", "100")
        report = build_index([str(folder)], tmp_path / "second.h5", jobs=2)
    finally:
        stop.set()
        t.join()
    assert report.failed == 20
    assert "the process reading it died twice" in dict(report.failures)[paths[4]]
    assert "more than the limit of 100 bytes" in dict(report.failures)[paths[5]]
