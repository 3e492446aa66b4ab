"""What reading a file may cost and what it may open (issue 9): regular files only, a size
cap, bounded memory, bounded messages; non-UTF-8 file names; folders that cannot be listed."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import threading
import tracemalloc
from pathlib import Path

import h5py
import numpy as np
import pytest

from nfdmatch.errors import MAX_MESSAGE_CHARS, CurveError, NfdError, ParseError, ReadError, escape_name, excerpt
from nfdmatch.formats import read_curve, read_curves, supported_extensions, write_curves
from nfdmatch.formats import _chain
from nfdmatch.sources import find_curve_files, read_all, walk_folder

#: end-to-end as a whole (subprocesses, real files, pools): left out by `make test-fast`
pytestmark = pytest.mark.slow

SQUARE = [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1.0, 1.0, 0.0], [0.0, 1.0, 0.0]]


def _square(path) -> str:
    write_curves(str(path), [SQUARE])
    return str(path)


# ---------------------------------------------------------------------------
# non-regular files
# ---------------------------------------------------------------------------


def _run_with_timeout(fn, seconds=10):
    """fn() in a thread; fails the test instead of hanging it."""
    box = {}

    def target():
        try:
            box["value"] = fn()
        except BaseException as exc:  # noqa: BLE001 - handed to the test
            box["error"] = exc

    t = threading.Thread(target=target, daemon=True)
    t.start()
    t.join(seconds)
    assert not t.is_alive(), "the read hung"
    if "error" in box:
        raise box["error"]
    return box.get("value")


@pytest.mark.parametrize("ext", [".csv", ".obj", ".vtp"])
def test_fifo_named_directly_fails_clearly_without_blocking(tmp_path, ext):
    fifo = str(tmp_path / f"pipe{ext}")
    os.mkfifo(fifo)
    with pytest.raises(ReadError) as info:
        _run_with_timeout(lambda: read_curves(fifo))
    assert str(info.value) == f"{fifo}: is a FIFO (named pipe), not a regular file; only regular files are read"


def test_dev_zero_through_a_symlink_fails_clearly(tmp_path):
    link = tmp_path / "zero.csv"
    link.symlink_to("/dev/zero")
    with pytest.raises(ReadError, match="is a character device, not a regular file"):
        _run_with_timeout(lambda: read_curves(str(link)))


def test_socket_fails_clearly(tmp_path):
    path = str(tmp_path / "s.obj")
    server = socket.socket(socket.AF_UNIX)
    try:
        server.bind(path)
        with pytest.raises(ReadError, match="is a socket, not a regular file"):
            read_curves(path)
    finally:
        server.close()


def test_folder_walk_skips_non_regular_files_with_a_notice(tmp_path):
    good = _square(tmp_path / "a.csv")
    os.mkfifo(tmp_path / "b.csv")
    (tmp_path / "c.csv").symlink_to("/dev/zero")
    (tmp_path / "d.txt").symlink_to(good)  # a link to a regular file: read
    problems = []
    files = _run_with_timeout(lambda: find_curve_files([str(tmp_path)], problems=problems))
    assert files == [good, str(tmp_path / "d.txt")]
    assert [(type(p), p.path) for p in problems] == [
        (ReadError, str(tmp_path / "b.csv")),
        (ReadError, str(tmp_path / "c.csv")),
    ]
    assert "FIFO (named pipe), not a regular file; skipped" in str(problems[0])
    assert "character device, not a regular file; skipped" in str(problems[1])
    curves, errors = _run_with_timeout(lambda: read_all(files))
    assert len(curves) == 2 and errors == []


def test_folder_walk_without_a_problem_list_still_skips(tmp_path):
    os.mkfifo(tmp_path / "b.csv")
    assert find_curve_files([str(tmp_path)]) == []


# ---------------------------------------------------------------------------
# size cap, memory, message length
# ---------------------------------------------------------------------------


@pytest.mark.parametrize("ext", [".csv", ".obj", ".vtk"])
def test_size_cap_refuses_before_reading(tmp_path, monkeypatch, ext):
    path = _square(tmp_path / f"sq{ext}")
    size = os.path.getsize(path)
    monkeypatch.setattr(_chain, "MAX_FILE_BYTES", size - 1)
    with pytest.raises(ReadError) as info:
        read_curves(path)
    assert f"is {size} bytes, more than the limit of {size - 1} bytes" in str(info.value)
    assert "NFDMATCH_MAX_FILE_BYTES" in str(info.value)
    monkeypatch.setattr(_chain, "MAX_FILE_BYTES", size)
    assert len(read_curves(path)) == 1


def test_size_cap_from_the_environment(tmp_path, monkeypatch):
    path = _square(tmp_path / "sq.csv")
    monkeypatch.setenv("NFDMATCH_MAX_FILE_BYTES", "10")
    with pytest.raises(ReadError, match="more than the limit of 10 bytes"):
        read_curves(path)
    monkeypatch.setenv("NFDMATCH_MAX_FILE_BYTES", "ten")
    with pytest.raises(NfdError, match="NFDMATCH_MAX_FILE_BYTES must be a number"):
        read_curves(path)


def test_size_cap_reaches_the_cli(tmp_path):
    path = _square(tmp_path / "sq.csv")
    env = dict(os.environ, NFDMATCH_MAX_FILE_BYTES="10")
    proc = subprocess.run([sys.executable, "-m", "nfdmatch", "describe", path], env=env, capture_output=True, text=True)
    assert proc.returncode == 2
    assert "more than the limit of 10 bytes" in proc.stderr and "Traceback" not in proc.stderr


def test_csv_peak_memory_is_a_few_times_the_file(tmp_path):
    rng = np.random.default_rng(2)
    pts = rng.normal(size=(200_000, 3)) * 100
    path = tmp_path / "big.csv"
    path.write_text("x,y,z\n" + "\n".join(f"{x!r},{y!r},{z!r}" for x, y, z in pts.tolist()) + "\n")
    size = path.stat().st_size
    tracemalloc.start()
    try:
        (curve,) = read_curves(str(path))
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert np.array_equal(curve.points, pts)
    assert peak < 4 * size, (peak, size)  # was 21x (every row as Python strings)


def test_csv_bulk_and_careful_parsers_agree(tmp_path):
    # the same rows, once in the bulk path's layout, once with a non-ASCII comment that
    # sends the file to the careful parser
    rng = np.random.default_rng(4)
    pts = rng.normal(size=(50, 3))
    rows = "\n".join(f" {x!r} ;{y!r}; {z!r}  # c" for x, y, z in pts.tolist())
    bulk = tmp_path / "bulk.csv"
    bulk.write_text(f"# head\n\nX;Y;Z\n{rows}\n\n")
    careful = tmp_path / "careful.csv"
    careful.write_text(f"# héad\n\nX;Y;Z\n{rows}\n\n", encoding="utf-8")
    assert np.array_equal(read_curve(str(bulk)).points, read_curve(str(careful)).points)
    assert np.array_equal(read_curve(str(bulk)).points, pts)


@pytest.mark.parametrize("layout", ["x,y,z\n0,0,0\n{big},1,2\n1,0,0\n0,1,0\n", "0,0,0\n1,{big},2\n1,0,0\n0,1,0\n"])
def test_a_huge_token_makes_a_short_message(tmp_path, layout):
    path = tmp_path / "huge.csv"
    path.write_text(layout.format(big="9" * 1_000_000 + "x"))  # within the line cap (1 MiB)
    with pytest.raises(ParseError) as info:
        read_curves(str(path))
    message = str(info.value)
    assert len(message) < 400, len(message)
    assert "[cut: 1000001 characters in all]" in message


def test_a_huge_obj_token_makes_a_short_message(tmp_path):
    path = tmp_path / "huge.obj"
    path.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nl 1 2 " + "7" * 3_000_000 + "q\n")
    with pytest.raises(ParseError) as info:
        read_curves(str(path))
    assert len(str(info.value)) < 400 and "[cut: 3000001 characters in all]" in str(info.value)


def test_a_huge_non_finite_row_makes_a_short_message(tmp_path):
    path = tmp_path / "nan.csv"
    path.write_text("0,0,0\n1,0,0\nnan,0," + "1" * 1_000_000 + "\n")
    with pytest.raises(CurveError) as info:
        read_curves(str(path))
    assert len(str(info.value)) < 400


def test_every_error_message_is_bounded():
    err = ParseError("x" * 10 * MAX_MESSAGE_CHARS, path="f.csv")
    assert len(err.message) < MAX_MESSAGE_CHARS + 60
    assert err.message.endswith(f"[cut: {10 * MAX_MESSAGE_CHARS} characters in all]")
    assert excerpt("abc", 5) == "abc" and excerpt(b"abcdef", 3) == "abc...[cut: 6 characters in all]"


# ---------------------------------------------------------------------------
# file names that are not UTF-8
# ---------------------------------------------------------------------------


def _bad_name(folder: Path, stem: bytes, ext: str) -> str:
    name = os.fsdecode(stem + ext.encode())
    return os.path.join(str(folder), name)


def test_escape_name_rule():
    assert escape_name("plain/ä.csv") == "plain/ä.csv"
    assert escape_name(os.fsdecode(b"a\xff\xfe.csv")) == "a\\xff\\xfe.csv"
    assert escape_name("x\ud800") == "x\\ud800"


@pytest.mark.parametrize("ext", supported_extensions())
def test_non_utf8_file_name_reads_with_an_escaped_id(tmp_path, ext):
    path = _bad_name(tmp_path, b"curve\xff", ext)
    write_curves(path, [SQUARE], format=ext)
    (curve,) = read_curves(path)
    assert curve.id == os.path.join(str(tmp_path), "curve\\xff" + ext)
    assert curve.source == path  # the name that opens the file
    curve.id.encode("utf-8")


def test_non_utf8_multi_curve_ids_and_h5py(tmp_path):
    path = _bad_name(tmp_path, b"two\xfe", ".obj")
    write_curves(path, [SQUARE, [[0, 0, 1], [2, 0, 1], [0, 2, 1]]])
    curves = read_curves(path)
    ids = [c.id for c in curves]
    assert ids == [os.path.join(str(tmp_path), "two\\xfe.obj") + f"#{i}" for i in range(2)]
    with h5py.File(tmp_path / "ids.h5", "w") as h5:
        h5.create_dataset("ids", data=np.array(ids, dtype=object), dtype=h5py.string_dtype("utf-8"))
    with h5py.File(tmp_path / "ids.h5", "r") as h5:
        assert [s.decode() for s in h5["ids"][:]] == ids


def test_non_utf8_names_in_a_folder_and_their_errors(tmp_path):
    good = _bad_name(tmp_path, b"a\xff", ".csv")
    write_curves(good, [SQUARE])
    bad = _bad_name(tmp_path, b"b\xff", ".csv")
    Path(bad).write_text("not, a, curve\n1,2\n")
    files = find_curve_files([str(tmp_path)])
    assert files == [good, bad]
    curves, errors = read_all(files)
    assert [c.id for c in curves] == [escape_name(good)]
    (error,) = errors
    message = str(error)
    message.encode("utf-8")  # printable and storable
    assert message.startswith(str(tmp_path) + "/b\\xff.csv: ")


def test_non_utf8_name_through_the_cli(tmp_path):
    path = _bad_name(tmp_path, b"c\xff", ".csv")
    write_curves(path, [SQUARE])
    proc = subprocess.run([sys.executable, "-m", "nfdmatch", "describe", path], capture_output=True)
    assert proc.returncode == 0, proc.stderr
    # the name's raw bytes on a pipe, as ls and find print it (issue 40)
    assert b"c\xff.csv" in proc.stdout and b"Traceback" not in proc.stderr


# ---------------------------------------------------------------------------
# folders that cannot be listed
# ---------------------------------------------------------------------------


def test_unlistable_sub_folder_is_reported(tmp_path, monkeypatch):
    _square(tmp_path / "a.csv")
    locked = tmp_path / "locked"
    locked.mkdir()
    _square(locked / "hidden.csv")
    (tmp_path / "z").mkdir()
    _square(tmp_path / "z" / "b.csv")
    real_scandir = os.scandir

    def scandir(path="."):
        if os.fspath(path) == str(locked):
            raise PermissionError(13, "Permission denied", os.fspath(path))
        return real_scandir(path)

    monkeypatch.setattr(os, "scandir", scandir)  # root reads any folder: simulate chmod 000
    problems = []
    files = find_curve_files([str(tmp_path)], problems=problems)
    assert files == [str(tmp_path / "a.csv"), str(tmp_path / "z" / "b.csv")]
    (problem,) = problems
    assert isinstance(problem, ReadError) and problem.path == str(locked)
    assert str(problem) == f"{locked}: cannot list the folder (Permission denied); its files are skipped"


def test_walk_folder_reports_the_top_folder_too(tmp_path, monkeypatch):
    def scandir(path="."):
        raise PermissionError(13, "Permission denied", os.fspath(path))

    monkeypatch.setattr(os, "scandir", scandir)
    problems = []
    assert list(walk_folder(str(tmp_path), {".csv"}, problems=problems)) == []
    assert [p.path for p in problems] == [str(tmp_path)]


def test_a_csv_line_above_the_line_cap_fails_before_it_is_split(tmp_path):
    from nfdmatch.formats.csv import MAX_LINE_BYTES

    path = tmp_path / "line.csv"
    path.write_bytes(b"x,y,z\n0,0,0\n" + b"1," * (MAX_LINE_BYTES // 2 + 1) + b"\n1,1,0\n")
    with pytest.raises(ParseError, match=f"line 3: a line longer than {MAX_LINE_BYTES} bytes"):
        read_curves(str(path))
    path.write_bytes(b"0,0,0\n1,0,0\n0,1,0\n" + b"9" * (MAX_LINE_BYTES + 1))  # the last line, no newline
    with pytest.raises(ParseError, match="line 4: a line longer than"):
        read_curves(str(path))


# the peak resident memory of this process alone: VmHWM starts afresh at exec (ru_maxrss keeps
# the forking parent's peak on Linux, the test runner's)
_MEASURED = (
    "import sys\n"
    "from nfdmatch.cli import main\n"
    "try:\n"
    "    main(sys.argv[1:])\n"
    "finally:\n"
    "    hwm = [l.split()[1] for l in open('/proc/self/status') if l.startswith('VmHWM:')][0]\n"
    "    sys.stderr.write(f'maxrss_kb={hwm}\\n')\n"
)


def test_one_300_mb_line_on_stdin_fails_while_it_is_read(tmp_path):
    """Issue 24, item 5: '1,' * 150,000,000 on stdin took 164 s and 1.77 GB before a clear
    error; the caps are now checked while stdin is copied (1 MiB at a time), so the run stops
    after the first MiB of the line and its memory stays that of a query's start-up."""
    index = tmp_path / "lib.h5"
    from nfdmatch.index import build_index

    build_index([_square(tmp_path / "sq.csv")], str(index))
    proc = subprocess.Popen(
        [sys.executable, "-c", _MEASURED, "query", "-", "--input-format", "csv", "--index", str(index)],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
    )
    piece = b"1," * (1 << 19)  # 1 MiB
    sent = 0
    try:
        while sent < 300_000_000:
            proc.stdin.write(piece)
            sent += len(piece)
        proc.stdin.close()
    except BrokenPipeError:  # the reader stopped early: what the cap is for
        pass
    out, err = proc.communicate(timeout=600)
    err = err.decode()
    assert proc.returncode == 2, err
    assert "Error: <stdin>: line 1: a line longer than 1048576 bytes" in err and "Traceback" not in err
    assert sent < 300_000_000  # not read to the end
    rss = int(err.split("maxrss_kb=")[1].split()[0]) * 1024
    assert rss < 300 * 2**20, rss


def test_stdin_above_the_size_cap_fails_while_it_is_read(tmp_path):
    index = tmp_path / "lib.h5"
    from nfdmatch.index import build_index

    build_index([_square(tmp_path / "sq.csv")], str(index))
    env = dict(os.environ, NFDMATCH_MAX_FILE_BYTES="1000")
    proc = subprocess.run(
        [sys.executable, "-m", "nfdmatch", "query", "-", "--input-format", "obj", "--index", str(index)],
        input=b"v 0 0 0\n" * 10_000,
        env=env,
        capture_output=True,
    )
    assert proc.returncode == 2
    assert "Error: <stdin>: is more than the limit of 1000 bytes" in proc.stderr.decode()
