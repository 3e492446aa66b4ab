"""Temporary files of the writers: made exclusively beside the target, never through a
symbolic link, never left behind; the result has a normal file's permissions."""

from __future__ import annotations

import os
import stat

import pytest

from nfdmatch.formats import write_curves
from nfdmatch.formats._chain import publish, temp_beside, write_if_changed

SQUARE = [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1.0, 1.0, 0.0], [0.0, 1.0, 0.0]]


def _umask() -> int:
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def test_temp_beside_is_new_private_and_beside(tmp_path):
    target = tmp_path / "out put é.vtp"
    temps = {temp_beside(str(target)) for _ in range(20)}
    assert len(temps) == 20
    for temp in temps:
        assert os.path.dirname(temp) == str(tmp_path)
        name = os.path.basename(temp)
        assert name.startswith(".out_put__.vtp.") and name.endswith(".tmp.vtp")
        info = os.lstat(temp)
        assert stat.S_ISREG(info.st_mode) and stat.S_IMODE(info.st_mode) == 0o600
        assert info.st_size == 0


@pytest.mark.parametrize("ext", [".csv", ".obj", ".vtk", ".vtp", ".vtu"])
def test_planted_symlinks_at_the_old_temp_names_are_not_followed(tmp_path, ext):
    victim = tmp_path / "victim.txt"
    victim.write_text("keep me")
    target = tmp_path / f"curves{ext}"
    # the names the writers used to write through, for this and nearby process ids
    for pid in range(os.getpid() - 2, os.getpid() + 3):
        (tmp_path / f".{target.name}.{pid}.tmp{ext}").symlink_to(victim)
    write_if_changed(str(target), lambda temp: write_curves(temp, [SQUARE], format=ext))
    write_curves(str(target), [SQUARE, [[0, 0, 1], [1, 0, 1], [0, 1, 1]]] if ext != ".csv" else [SQUARE])
    assert victim.read_text() == "keep me"
    leftovers = [n for n in os.listdir(tmp_path) if n.startswith(".") and not os.path.islink(tmp_path / n)]
    assert leftovers == []


@pytest.mark.parametrize("ext", [".vtp", ".csv"])
def test_written_files_have_normal_permissions(tmp_path, ext):
    new = tmp_path / f"new{ext}"
    write_if_changed(str(new), lambda temp: write_curves(temp, [SQUARE], format=ext))
    assert stat.S_IMODE(new.stat().st_mode) == 0o666 & ~_umask()
    if ext == ".vtp":
        direct = tmp_path / "direct.vtp"
        write_curves(str(direct), [SQUARE])
        assert stat.S_IMODE(direct.stat().st_mode) == 0o666 & ~_umask()
    old = tmp_path / f"old{ext}"
    old.write_text("x")
    old.chmod(0o640)
    write_if_changed(str(old), lambda temp: write_curves(temp, [SQUARE], format=ext))
    assert stat.S_IMODE(old.stat().st_mode) == 0o640


def test_failed_produce_leaves_nothing(tmp_path):
    def produce(temp):
        with open(temp, "w") as fh:
            fh.write("half")
        raise RuntimeError("disk on fire")

    with pytest.raises(RuntimeError):
        write_if_changed(str(tmp_path / "x.csv"), produce)
    assert os.listdir(tmp_path) == []


def test_publish_replaces(tmp_path):
    target = tmp_path / "t.obj"
    target.write_text("old")
    temp = temp_beside(str(target))
    with open(temp, "w") as fh:
        fh.write("new")
    publish(temp, str(target))
    assert target.read_text() == "new" and not os.path.exists(temp)


# --------------------------------------------------------------------------- nfdmatch._io.write_file


def test_write_file_replaces_changed_bytes_and_keeps_identical_ones_with_a_fresh_mtime(tmp_path):
    from nfdmatch._io import write_file

    target = tmp_path / "report.csv"
    assert write_file(target, b"a,b\n1,2\n") is True
    assert target.read_bytes() == b"a,b\n1,2\n" and stat.S_IMODE(target.stat().st_mode) == 0o666 & ~_umask()
    os.utime(target, ns=(1, 1))  # as if written long ago
    inode = target.stat().st_ino
    # the same bytes: the same file (inode), but newer than anything before the call
    assert write_file(target, b"a,b\n1,2\n") is False
    assert target.stat().st_ino == inode and target.stat().st_mtime_ns > 1
    # other bytes: a new file renamed over it
    assert write_file(target, lambda temp: open(temp, "wb").write(b"a,b\n3,4\n")) is True
    assert target.read_bytes() == b"a,b\n3,4\n" and target.stat().st_ino != inode
    assert os.listdir(tmp_path) == ["report.csv"]


def test_write_file_flushes_the_temporary_file_before_the_rename(tmp_path, monkeypatch):
    from nfdmatch import _io

    synced, renamed = [], []
    real_fsync, real_replace = os.fsync, os.replace
    monkeypatch.setattr(os, "fsync", lambda fd: (synced.append(os.readlink(f"/proc/self/fd/{fd}")), real_fsync(fd)))
    monkeypatch.setattr(os, "replace", lambda a, b: (renamed.append((list(synced), a)), real_replace(a, b)))
    _io.write_file(tmp_path / "x.json", b"{}\n")
    ((synced_before, temp),) = renamed
    assert temp in synced_before  # the data is on disk before the name points at it
