"""Never destroy (issue 40): ``-o`` onto a FIFO, a device or a symbolic link leaves the path
what it was (a FIFO or a device written in place as a shell's ``>`` would, a link followed
and its target replaced), and ``-o`` naming one of the command's inputs is refused (exit 2),
the input untouched. Exit code, stdout and stderr apart."""

from __future__ import annotations

import os
import shutil
import stat
import subprocess
import sys
import threading

import pytest

from conftest import ROOT, run_cli as run

LIBRARY = os.path.join(ROOT, "sample_curves", "library")
TREFOIL = os.path.join(ROOT, "sample_curves", "queries", "trefoil-posed.obj")


@pytest.fixture(scope="module")
def index(tmp_path_factory):
    folder = tmp_path_factory.mktemp("never-destroy")
    shutil.copytree(LIBRARY, folder / "library")
    path = folder / "lib.h5"
    code, _, err = run("index", "build", folder / "library", "--index", path, "--jobs", "1", "-q")
    assert code == 0 and err == ""
    return path


def _rows(index) -> str:
    code, out, err = run("query", TREFOIL, "--index", index, "--top", 3, "--format", "csv")
    assert code == 0, err
    return out


# --------------------------------------------------------------------------- -o onto what is not a regular file


def test_a_fifo_is_written_in_place_and_its_reader_gets_the_rows(index, tmp_path):
    fifo = tmp_path / "rows.fifo"
    os.mkfifo(fifo)
    got = []
    # a daemon: were the FIFO replaced, its reader would wait for a writer for ever
    reader = threading.Thread(target=lambda: got.append(open(fifo, "rb").read()), daemon=True)
    reader.start()
    code, out, err = run("query", TREFOIL, "--index", index, "--top", 3, "--format", "csv", "-o", fifo)
    reader.join(timeout=60)
    assert code == 0, err
    assert out == ""
    assert got == [_rows(index).encode()]
    assert stat.S_ISFIFO(os.lstat(fifo).st_mode)
    assert os.listdir(tmp_path) == ["rows.fifo"]  # no temporary file left beside it


def _null_device(tmp_path):
    """A character device like /dev/null (1, 3) in ``tmp_path``; skipped when the OS refuses."""
    device = tmp_path / "null"
    try:
        os.mknod(device, 0o666 | stat.S_IFCHR, os.makedev(1, 3))
    except (PermissionError, OSError) as exc:
        pytest.skip(f"the OS refuses mknod here: {exc.strerror or exc}")
    return device


def test_a_character_device_is_written_in_place(index, tmp_path):
    device = _null_device(tmp_path)
    code, out, err = run("query", TREFOIL, "--index", index, "--format", "csv", "-o", device)
    assert code == 0, err
    info = os.lstat(device)
    assert stat.S_ISCHR(info.st_mode) and info.st_rdev == os.makedev(1, 3)
    assert os.listdir(tmp_path) == ["null"]


def test_dev_null_as_a_path_stays_a_device_also_as_root(index, tmp_path):
    # a regression would replace the machine's /dev/null when the tests run as root: the
    # same write onto a private device must pass first
    device = _null_device(tmp_path) if os.geteuid() == 0 else None
    if device is not None:
        run("query", TREFOIL, "--index", index, "--format", "csv", "-o", device)
        assert stat.S_ISCHR(os.lstat(device).st_mode), "a device was replaced: /dev/null is not tried"
    before = os.lstat("/dev/null")
    result = subprocess.run(
        [sys.executable, "-m", "nfdmatch", "query", TREFOIL, "--index", str(index), "--format", "csv"]
        + ["-o", "/dev/null"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert result.returncode == 0, result.stderr
    assert result.stdout == ""
    after = os.lstat("/dev/null")
    assert stat.S_ISCHR(after.st_mode) and (after.st_ino, after.st_rdev) == (before.st_ino, before.st_rdev)


def test_a_symlink_is_followed_and_its_target_replaced(index, tmp_path):
    (tmp_path / "real").mkdir()
    target = tmp_path / "real" / "rows.csv"
    target.write_text("old\n")
    link = tmp_path / "rows.csv"
    link.symlink_to(target)
    code, _, err = run("query", TREFOIL, "--index", index, "--top", 3, "-o", link)
    assert code == 0, err
    assert os.path.islink(link) and os.readlink(link) == str(target)
    assert target.read_text() == _rows(index)
    assert sorted(os.listdir(tmp_path)) == ["real", "rows.csv"] and os.listdir(tmp_path / "real") == ["rows.csv"]


def test_a_dangling_symlink_creates_its_target(index, tmp_path):
    link = tmp_path / "rows.csv"
    link.symlink_to(tmp_path / "new.csv")
    code, _, err = run("query", TREFOIL, "--index", index, "--top", 3, "-o", link)
    assert code == 0, err
    assert os.path.islink(link) and (tmp_path / "new.csv").read_text() == _rows(index)


def test_what_is_special_and_what_a_write_lands_in(tmp_path):
    from nfdmatch._io import is_special, resolve

    assert is_special("/dev/null") and not is_special(__file__) and not is_special(ROOT)
    assert resolve(__file__) == __file__
    (tmp_path / "link").symlink_to(__file__)
    assert resolve(str(tmp_path / "link")) == os.path.realpath(__file__)


# --------------------------------------------------------------------------- -o naming an input


def _query_folder(tmp_path):
    folder = tmp_path / "same"
    folder.mkdir()
    shutil.copy(os.path.join(LIBRARY, "trefoil.csv"), folder / "q.csv")
    return folder


@pytest.mark.parametrize("spelling", ["same", "dotted", "symlink", "hardlink"])
def test_output_naming_the_query_file_is_a_usage_error_and_the_file_stays(index, tmp_path, monkeypatch, spelling):
    monkeypatch.chdir(tmp_path)
    folder = _query_folder(tmp_path)
    before = (folder / "q.csv").read_bytes()
    output = {
        "same": "same/q.csv",
        "dotted": "./same/../same/q.csv",
        "symlink": "link.csv",
        "hardlink": "hard.csv",
    }[spelling]
    if spelling == "symlink":
        os.symlink("same/q.csv", "link.csv")
    if spelling == "hardlink":
        os.link("same/q.csv", "hard.csv")
    code, out, err = run("query", "same/q.csv", "--index", index, "-o", output, "--format", "csv")
    assert code == 2
    assert "is one of the inputs" in err and output in err
    assert (folder / "q.csv").read_bytes() == before


def test_output_naming_a_file_of_an_input_folder_is_refused(index, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    folder = _query_folder(tmp_path)
    before = (folder / "q.csv").read_bytes()
    code, _, err = run("query", "same", "--index", index, "-o", "same/q.csv", "--format", "csv")
    assert code == 2 and "is one of the inputs" in err
    assert (folder / "q.csv").read_bytes() == before


def test_output_naming_the_index_is_refused(index, tmp_path):
    copy = tmp_path / "lib.h5"
    shutil.copy(index, copy)
    before = copy.read_bytes()
    code, _, err = run("index", "ls", "--index", copy, "-o", copy, "--format", "csv")
    assert code == 2 and "is one of the inputs" in err
    assert copy.read_bytes() == before


@pytest.mark.parametrize("command", ["distance", "describe", "rank", "matrix", "reconstruct"])
def test_every_command_refuses_an_input_as_output(tmp_path, monkeypatch, command):
    monkeypatch.chdir(tmp_path)
    shutil.copy(os.path.join(LIBRARY, "trefoil.csv"), "a.csv")
    shutil.copy(os.path.join(LIBRARY, "circle.tsv"), "b.tsv")
    before = open("a.csv", "rb").read()
    args = {
        "distance": ["distance", "a.csv", "b.tsv", "--format", "json"],
        "describe": ["describe", "a.csv", "b.tsv"],
        "rank": ["rank", "b.tsv", "a.csv"],
        "matrix": ["matrix", "a.csv", "b.tsv"],
        "reconstruct": ["reconstruct", "a.csv", "-k", "4"],
    }[command]
    code, _, err = run(*args, "-o", "a.csv")
    assert code == 2, err
    assert "is one of the inputs" in err
    assert open("a.csv", "rb").read() == before


def test_a_new_output_beside_the_inputs_is_written(index, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    _query_folder(tmp_path)
    code, _, err = run("query", "same/q.csv", "--index", index, "-o", "same/out.csv")
    assert code == 0, err
    assert os.path.exists("same/out.csv")


# --------------------------------------------------------------------------- names that are not UTF-8


@pytest.mark.parametrize(
    "raw",
    [b"plain.csv", b"bad\xffbyte.csv", b"bad\\xffbyte.csv", b"back\\slash\\\\.csv", b"\xc3(\xe9.csv", "é.csv".encode()],
)
def test_a_name_and_its_id_round_trip_byte_for_byte(raw):
    from nfdmatch.names import decode_name, encode_name

    name = os.fsdecode(raw)
    encoded = encode_name(name)
    encoded.encode("utf-8")  # storable in HDF5
    assert os.fsencode(decode_name(encoded)) == raw


def test_two_names_never_share_an_id():
    from nfdmatch.names import encode_name

    names = [b"bad\xffbyte.csv", b"bad\\xffbyte.csv", b"bad\\\\xffbyte.csv", b"a\\b", b"a\\\\b"]
    assert len({encode_name(os.fsdecode(n)) for n in names}) == len(names)


def _odd_library(tmp_path):
    from nfdmatch.formats import write_curves

    from conftest import ellipse, torus_knot

    lib = tmp_path / "lib"
    lib.mkdir()
    names = [b"bad\xffbyte.csv", b"bad\\xffbyte.csv", b"ok.csv"]
    shapes = [torus_knot(2, 3, 120), ellipse(2.0, 1.0, 100), torus_knot(2, 5, 150)]
    for name, points in zip(names, shapes):
        write_curves(os.fsdecode(os.fsencode(str(lib)) + b"/" + name), points)
    return lib, names


def _nfd(*args, cwd):
    return subprocess.run(
        [sys.executable, "-m", "nfdmatch", *[os.fsencode(str(a)) if not isinstance(a, bytes) else a for a in args]],
        capture_output=True,
        cwd=cwd,
        timeout=300,
    )


def test_a_name_that_is_not_utf8_and_its_look_alike_are_both_indexed_and_found_again(tmp_path):
    lib, names = _odd_library(tmp_path)
    built = _nfd("index", "build", "lib", "--index", "i.h5", "-j", "1", cwd=tmp_path)
    assert built.returncode == 0, built.stderr
    listed = _nfd("index", "ls", "--index", "i.h5", "--format", "csv", cwd=tmp_path)
    assert listed.returncode == 0, listed.stderr
    files = [line.split(b",")[0] for line in listed.stdout.splitlines()[1:]]
    assert sorted(files) == sorted(b"lib/" + n for n in names)  # the raw bytes, none dropped
    # every row found again: --paths absolute names files that exist, byte for byte
    query = _nfd("query", b"lib/" + names[0], "--index", "i.h5", "--top", 3, "--paths", "absolute", cwd=tmp_path)
    assert query.returncode == 0, query.stderr
    matches = [line.split(b",")[2] for line in query.stdout.splitlines()[1:]]
    assert len(matches) == 3 and all(os.path.exists(m) for m in matches)
    assert matches[0] == os.fsencode(str(lib)) + b"/" + names[0]  # itself, at distance 0
    # show reads the matches' files again through the stored ids
    shown = _nfd("show", b"lib/" + names[0], "--index", "i.h5", "--top", 3, "-o", "s.svg", "-o", "s.csv", cwd=tmp_path)
    assert shown.returncode == 0 and b"cannot read it" not in shown.stderr, shown.stderr


def test_json_writes_such_a_byte_as_a_documented_escape(tmp_path):
    import json

    lib, names = _odd_library(tmp_path)
    assert _nfd("index", "build", "lib", "--index", "i.h5", "-j", "1", cwd=tmp_path).returncode == 0
    proc = _nfd("index", "ls", "--index", "i.h5", "--format", "json", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert b"\\udcff" in proc.stdout
    files = {os.fsencode(row["file"]) for row in json.loads(proc.stdout)}
    assert files == {b"lib/" + n for n in names}


def test_a_pipe_gets_the_raw_bytes_and_messages_stay_utf8(tmp_path):
    lib, names = _odd_library(tmp_path)
    bad = os.fsencode(str(lib)) + b"/broken\xfe.csv"
    with open(bad, "w") as fh:
        fh.write("not a curve\n")
    proc = _nfd("describe", "lib", cwd=tmp_path)
    assert proc.returncode == 3
    proc.stderr.decode("utf-8")  # valid UTF-8: the name escaped in the message
    assert b"broken\\xfe.csv" in proc.stderr
    assert b"lib/bad\xffbyte.csv" in proc.stdout  # the raw bytes on a pipe


def test_two_curves_that_would_share_an_id_stop_the_build_naming_both(tmp_path):
    from nfdmatch.formats import write_curves

    from conftest import ellipse, torus_knot

    write_curves(tmp_path / "two.obj", [torus_knot(2, 3, 120), ellipse(2.0, 1.0, 100)])
    write_curves(tmp_path / "one.obj", [torus_knot(2, 5, 150)])
    os.rename(tmp_path / "one.obj", tmp_path / "two.obj#1")  # a file named as curve 1 of two.obj is
    code, _, err = run(
        "index", "build", tmp_path / "two.obj", tmp_path / "two.obj#1", "--index", tmp_path / "i.h5",
        "--input-format", "obj",
    )  # fmt: skip
    assert code != 0 and not os.path.exists(tmp_path / "i.h5")
    assert "two.obj: curve 1 of this file and the file" in err and "two.obj#1 would share the id" in err


# --------------------------------------------------------------------------- progress bars


def _bar_output(monkeypatch, capsys, clock_step: float, steps: int = 3000) -> str:
    from nfdmatch.cli import output

    now = [0.0]

    def clock():
        now[0] += clock_step
        return now[0]

    monkeypatch.setattr(output, "stderr_is_terminal", lambda: True)
    monkeypatch.setattr(output, "_clock", clock)
    capsys.readouterr()
    update, finish = output.progress_bar("indexing files")
    for done in range(1, steps + 1):
        update(done, steps)
    finish()
    return capsys.readouterr().err


def test_a_progress_bar_is_redrawn_at_most_ten_times_a_second(monkeypatch, capsys):
    # 3,000 files in 3 s of the bar's clock: ~30 redraws, not 3,000
    err = _bar_output(monkeypatch, capsys, clock_step=0.001)
    assert 20 <= err.count("indexing files") <= 40
    assert len(err.encode()) < 200_000 / 10


def test_a_fast_run_draws_its_bar_a_few_times_and_ends_full(monkeypatch, capsys):
    err = _bar_output(monkeypatch, capsys, clock_step=0.0)
    assert err.count("indexing files") <= 4  # its start, the first step, the last, its end
    assert "3000/3000" in err


# --------------------------------------------------------------------------- exit status: grep's contract


def test_a_filter_that_leaves_every_query_empty_exits_1_with_the_header(index):
    code, out, err = run("query", TREFOIL, "--index", index, "--max-distance", "1e-9", "--format", "csv")
    assert code == 1
    assert out == "query,rank,match,distance\n"
    assert err == ""  # as grep: the exit status says it


def test_a_query_that_matches_exits_0(index):
    code, out, _ = run("query", TREFOIL, "--index", index, "--max-distance", "0.1", "--format", "csv")
    assert code == 0 and out.count("\n") > 1


def test_pairs_without_a_pair_exits_1(index):
    code, out, _ = run("pairs", "--index", index, "--max-distance", "1e-12", "--format", "csv")
    assert code == 1 and out == "a,b,distance\n"


def test_rank_with_nothing_close_enough_exits_1():
    code, _, _ = run("rank", TREFOIL, os.path.join(LIBRARY, "circle.tsv"), "--max-distance", "1e-9")
    assert code == 1


@pytest.mark.parametrize(
    "args",
    [
        ["query", "missing.csv"],  # nothing could be read
        ["query", TREFOIL, "--index", "no-such-index.h5"],  # an error
        ["query", TREFOIL, "--top", "0"],  # a usage error
    ],
)
def test_errors_exit_2(index, tmp_path, monkeypatch, args):
    monkeypatch.chdir(tmp_path)
    if "--index" not in args:
        args = [*args, "--index", index]
    code, out, err = run(*args)
    assert code == 2 and out == "" and "Error" in err


def test_a_partial_run_exits_3(index, tmp_path):
    code, out, err = run("query", TREFOIL, tmp_path / "missing.csv", "--index", index, "--format", "csv")
    assert code == 3 and out.count("\n") > 1 and "missing.csv" in err


# --------------------------------------------------------------------------- --format json when a command fails


@pytest.mark.parametrize("fmt", ["json", "jsonl"])
def test_a_command_that_cannot_answer_writes_one_json_error_object(tmp_path, fmt):
    import json

    code, out, _ = run("query", TREFOIL, "--index", tmp_path / "missing.h5", "--format", fmt)
    assert code == 2
    (line,) = out.splitlines()
    record = json.loads(line)
    assert record["exit"] == 2 and "no index" in record["error"] and record["failed"] == []


def test_nothing_read_lists_every_failed_input_in_json(index, tmp_path):
    import json

    code, out, _ = run("query", tmp_path / "a.csv", tmp_path / "b.csv", "--index", index, "--format", "jsonl")
    assert code == 2
    record = json.loads(out)
    assert [f["input"] for f in record["failed"]] == [str(tmp_path / "a.csv"), str(tmp_path / "b.csv")]


def test_a_partial_jsonl_run_ends_with_a_line_listing_the_failed_inputs(index, tmp_path):
    import json

    code, out, _ = run("query", TREFOIL, tmp_path / "gone.csv", "--index", index, "--format", "jsonl", "--top", 2)
    assert code == 3
    lines = [json.loads(line) for line in out.splitlines()]
    assert [row["rank"] for row in lines[:-1]] == [1, 2]
    assert lines[-1]["exit"] == 3 and [f["input"] for f in lines[-1]["failed"]] == [str(tmp_path / "gone.csv")]


def test_a_usage_error_with_format_json_writes_the_object_too(index):
    import json

    code, out, err = run("query", TREFOIL, "--index", index, "--format", "json", "--top", "0")
    assert code == 2 and "Usage" in err
    assert json.loads(out)["exit"] == 2


def test_a_json_list_on_stdout_stays_the_only_document(index, tmp_path):
    import json

    code, out, _ = run("query", TREFOIL, tmp_path / "gone.csv", "--index", index, "--format", "json", "--top", 2)
    assert code == 3 and len(json.loads(out)) == 2


# --------------------------------------------------------------------------- the build lock


def test_a_build_that_never_starts_leaves_no_lock(tmp_path):
    code, _, err = run("index", "build", tmp_path / "missing", "--index", tmp_path / "x.h5")
    assert code == 2 and "missing" in err
    assert os.listdir(tmp_path) == []


def test_a_build_keeps_the_lock_of_an_index_that_exists(tmp_path):
    code, _, _ = run("index", "build", LIBRARY, "--index", tmp_path / "x.h5", "-q", "-j", 1)
    assert code == 0 and sorted(os.listdir(tmp_path)) == ["x.h5", "x.h5.lock"]
    code, _, _ = run("index", "build", tmp_path / "missing", "--index", tmp_path / "x.h5")
    assert code == 2 and sorted(os.listdir(tmp_path)) == ["x.h5", "x.h5.lock"]


def test_a_lock_removed_while_a_build_waited_is_not_held_by_two(tmp_path):
    from nfdmatch.index.lock import Lock

    first = Lock(str(tmp_path / "x.h5"), 0)
    assert first.created
    got = []
    waiter = threading.Thread(target=lambda: got.append(Lock(str(tmp_path / "x.h5"), 30)), daemon=True)
    waiter.start()
    first.release(remove=True)
    waiter.join(timeout=30)
    (second,) = got
    # the waiter holds the file now at the path, not the removed one: a third build is excluded
    assert os.fstat(second.fd).st_ino == os.stat(tmp_path / "x.h5.lock").st_ino
    second.release()


# --------------------------------------------------------------------------- TSV


def test_tsv_escapes_a_tab_a_newline_and_a_backslash_so_cut_splits_right(tmp_path):
    from nfdmatch.formats import write_curves

    from conftest import ellipse

    odd = "tab\there\nnew\\line.csv"
    write_curves(tmp_path / odd, ellipse(2.0, 1.0, 80))
    write_curves(tmp_path / "plain.csv", ellipse(3.0, 1.0, 80))
    code, out, _ = run("rank", TREFOIL, tmp_path, "--format", "tsv", "--paths", "id")
    assert code == 0
    lines = out.splitlines()
    assert len(lines) == 3 and all(line.count("\t") == 3 for line in lines)
    matches = [line.split("\t")[2] for line in lines[1:]]
    assert str(tmp_path / "tab\\there\\nnew\\\\line.csv") in matches


def test_csv_keeps_its_quoting():
    from nfdmatch.cli.output import delimited_text

    assert delimited_text(["a"], [['x,"y"\nz']], "csv") == 'a\n"x,""y""\nz"\n'


# --------------------------------------------------------------------------- --version


@pytest.mark.parametrize("setting, name", [("numpy", "numpy"), ("auto", None)])
def test_version_names_the_kernels_that_compute(monkeypatch, setting, name):
    from nfdmatch.matching import kernels

    monkeypatch.setattr(kernels, "_chosen", None)  # decided afresh from the environment
    monkeypatch.setenv("NFDMATCH_KERNELS", setting)
    code, out, _ = run("--version")
    assert code == 0
    version, said = out.splitlines()
    assert version.startswith("nfdmatch, version ")
    assert said.startswith("kernels: ") and said.split()[1] in ((name,) if name else ("aot", "numba", "numpy"))


# --------------------------------------------------------------------------- index build --strict


def test_a_strict_build_with_a_failed_file_exits_3_and_keeps_the_index(tmp_path):
    lib = tmp_path / "lib"
    shutil.copytree(LIBRARY, lib)
    index = tmp_path / "i.h5"
    assert run("index", "build", lib, "--index", index, "-q", "-j", 1)[0] == 0
    os.utime(index, ns=(10**9, 10**9))  # long ago
    before = index.read_bytes()
    (lib / "broken.csv").write_text("x,y,z\n1,2,3\n4,oops,6\n")
    for _ in range(2):  # and again: a strict build never takes the failure for done
        code, _, err = run("index", "build", lib, "--index", index, "--strict", "-j", 1)
        assert code == 3 and "broken.csv" in err and "not written (--strict)" in err
        assert index.read_bytes() == before and index.stat().st_mtime_ns == 10**9
    assert run("index", "build", lib, "--index", index, "-q", "-j", 1)[0] == 3  # without: written
    assert index.read_bytes() != before
    os.utime(index, ns=(10**9, 10**9))
    code, _, _ = run("index", "build", lib, "--index", index, "--strict", "-j", 1)  # nothing to change
    assert code == 3 and index.stat().st_mtime_ns == 10**9  # not made newer: the build did not succeed


def test_a_strict_build_of_a_new_index_with_a_failed_file_writes_nothing(tmp_path):
    lib = tmp_path / "lib"
    shutil.copytree(os.path.join(LIBRARY, "knotess"), lib)
    (lib / "broken.csv").write_text("x,y,z\n1,2,3\n4,oops,6\n")
    code, out, _ = run("index", "build", lib, "--index", tmp_path / "i.h5", "--strict", "--format", "json")
    assert code == 3 and sorted(os.listdir(tmp_path)) == ["lib"]
    import json

    assert json.loads(out)["failed"] == 1


# --------------------------------------------------------------------------- help, completion, man page


def test_help_of_a_command_is_its_help():
    code, out, _ = run("help", "index", "build")
    assert code == 0 and out.splitlines()[0].endswith(" index build [OPTIONS] [SOURCE...]")
    assert out == run("index", "build", "--help")[1]
    code, _, err = run("help", "nope")
    assert code == 2 and "no command 'nope'" in err


@pytest.mark.parametrize("shell, marker", [("bash", "complete -o"), ("zsh", "compdef"), ("fish", "complete ")])
def test_completion_prints_the_script_of_each_shell(shell, marker):
    code, out, _ = run("completion", shell)
    assert code == 0 and "_NFDMATCH_COMPLETE" in out and marker in out


def test_the_committed_man_page_is_the_one_the_help_gives():
    from nfdmatch.cli import main
    from nfdmatch.cli.help_cmds import man_page

    with open(os.path.join(ROOT, "nfdmatch.1"), encoding="utf-8") as fh:
        assert fh.read() == man_page(main), "run `make install` (or `nfdmatch help --man > nfdmatch.1`)"
    assert ".SS nfdmatch index build" in man_page(main) and "\\-\\-strict" in man_page(main)


def test_the_man_page_renders_without_warnings(tmp_path):
    if shutil.which("man") is None:
        pytest.skip("no man(1) on this machine")
    proc = subprocess.run(
        ["man", "--warnings", "-l", os.path.join(ROOT, "nfdmatch.1")],
        capture_output=True,
        text=True,
        env={**os.environ, "MANWIDTH": "80", "MANPAGER": "cat", "PAGER": "cat"},
        timeout=60,
    )
    assert proc.returncode == 0 and "nfdmatch query" in proc.stdout
    assert proc.stderr == ""


# --------------------------------------------------------------------------- --glob


@pytest.fixture
def families(tmp_path):
    lib = tmp_path / "lib"
    for family, names in (("fam000", ["a.csv", "bad1.csv"]), ("fam001", ["b.csv", "LOUD.CSV"])):
        (lib / family).mkdir(parents=True)
        for name in names:
            shutil.copy(os.path.join(LIBRARY, "trefoil.csv"), lib / family / name)
    return lib


def _described(*args) -> list[str]:
    code, out, err = run("describe", *args, "--format", "csv")
    assert code == 0, err
    return sorted(line.split(",")[0].rsplit("lib/", 1)[1] for line in out.splitlines()[1:])


@pytest.mark.parametrize(
    "option, pattern, kept",
    [
        ("--glob", "**/fam000/*.csv", ["fam000/a.csv", "fam000/bad1.csv"]),
        ("--glob", "fam001/*", ["fam001/LOUD.CSV", "fam001/b.csv"]),
        ("--glob", "!bad*", ["fam000/a.csv", "fam001/LOUD.CSV", "fam001/b.csv"]),
        ("--glob", "*.csv", ["fam000/a.csv", "fam000/bad1.csv", "fam001/b.csv"]),
        ("--iglob", "*.csv", ["fam000/a.csv", "fam000/bad1.csv", "fam001/LOUD.CSV", "fam001/b.csv"]),
        ("--iglob", "FAM001/*.csv", ["fam001/LOUD.CSV", "fam001/b.csv"]),
    ],
)
def test_glob_takes_relative_paths_exclusions_and_case(families, option, pattern, kept):
    assert _described(families, option, pattern) == kept


def test_an_index_records_an_iglob_and_its_next_build_keeps_it(families, tmp_path):
    index = tmp_path / "i.h5"
    assert run("index", "build", families, "--index", index, "--iglob", "!BAD*", "-q")[0] == 0
    code, out, _ = run("index", "ls", "--index", index, "--format", "csv")
    assert code == 0 and len(out.splitlines()) == 4 and "bad1" not in out
    code, _, err = run("index", "build", "--index", index)
    assert code == 0 and "3 unchanged" in err and "removed" in err and "0 removed" in err


def test_glob_and_iglob_exclude_each_other(families):
    code, _, err = run("describe", families, "--glob", "*.csv", "--iglob", "*.csv")
    assert code == 2 and "exclude each other" in err


# --------------------------------------------------------------------------- the same rules on every command


def test_matrix_takes_any_rows_file_when_format_is_given(tmp_path):
    code, out, err = run("matrix", os.path.join(LIBRARY, "knotess"), "-o", tmp_path / "m.out", "--format", "csv")
    assert code == 0, err
    assert (tmp_path / "m.out").read_text().startswith("id,") and out == ""


def test_a_pattern_that_cannot_be_written_is_named_as_given(tmp_path):
    pattern = str(tmp_path / "nodir" / "m-{stem}.png")
    code, _, err = run("show", TREFOIL, "--against", LIBRARY, "-o", pattern)
    assert code == 2 and f"Error: {pattern}: cannot write: the folder does not exist" in err


@pytest.mark.slow
def test_show_takes_paths_max_distance_and_exclude_self(index, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    query = os.path.join(os.path.dirname(index), "library", "trefoil.csv")
    code, out, err = run(
        "show", query, "--index", index, "--exclude-self", "--paths", "absolute", "--max-distance", "0.5",
        "--top", 3, "-o", "s.svg", "--format", "csv",
    )  # fmt: skip
    assert code == 0, err
    rows = [line.split(",") for line in out.splitlines()[1:]]
    assert rows and all(os.path.isabs(r[0]) and os.path.isabs(r[2]) and os.path.exists(r[2]) for r in rows)
    assert all(r[2] != query and float(r[3]) <= 0.5 for r in rows)
    code, out, _ = run("show", query, "--index", index, "--exclude-self", "--max-distance", "1e-12", "-o", "t.svg")
    assert code == 1 and len(out.splitlines()) == 1  # nothing matched: the header alone


# --------------------------------------------------------------------------- index add / remove


def _ls(index) -> list[str]:
    code, out, _ = run("index", "ls", "--index", index, "--format", "csv")
    assert code == 0
    return sorted(line.split(",")[0] for line in out.splitlines()[1:])


def test_index_add_and_remove_one_file_and_the_next_plain_build_agrees(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    shutil.copytree(LIBRARY, "lib")
    os.mkdir("extra")
    shutil.copy(TREFOIL, "extra/one.obj")
    assert run("index", "build", "lib", "--index", "lib.h5", "-q", "-j", 1)[0] == 0
    everything = _ls("lib.h5")
    code, _, err = run("index", "add", "extra/one.obj", "--index", "lib.h5", "-j", 1)
    assert code == 0 and "1 added" in err and "0 removed" in err
    assert _ls("lib.h5") == sorted(everything + ["extra/one.obj"])
    code, _, err = run("index", "build", "--index", "lib.h5")
    assert code == 0 and "is up to date" in err  # the recorded sources followed
    code, _, err = run("index", "remove", "lib/circle.tsv", "extra/one.obj", "--index", "lib.h5", "-j", 1)
    assert code == 0 and "2 removed" in err
    assert _ls("lib.h5") == [f for f in everything if f != "lib/circle.tsv"]
    assert os.path.exists("lib/circle.tsv")  # the file itself stays
    code, _, err = run("index", "build", "--index", "lib.h5")
    assert code == 0 and "is up to date" in err and "lib/circle.tsv" not in _ls("lib.h5")
    assert "excluded\tlib/circle.tsv" in run("index", "info", "--index", "lib.h5")[1]
    code, _, err = run("index", "add", "lib/circle.tsv", "--index", "lib.h5", "-j", 1)
    assert code == 0 and _ls("lib.h5") == everything
    assert "excluded" not in run("index", "info", "--index", "lib.h5")[1]


def test_removing_a_file_that_is_not_in_the_index_is_an_error_naming_it(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    shutil.copytree(LIBRARY, "lib")
    assert run("index", "build", "lib", "--index", "lib.h5", "-q", "-j", 1)[0] == 0
    before = open("lib.h5", "rb").read()
    code, _, err = run("index", "remove", "lib/nothere.csv", "--index", "lib.h5")
    assert code == 2 and "lib/nothere.csv: not in the index" in err
    assert open("lib.h5", "rb").read() == before


def test_index_add_to_a_missing_index_builds_it(tmp_path):
    code, _, _ = run("index", "add", TREFOIL, "--index", tmp_path / "new.h5", "-q")
    assert code == 0 and len(_ls(tmp_path / "new.h5")) == 1
