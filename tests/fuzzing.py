"""Seeded mutation fuzzing of the curve readers, each read in a child process with a time and
memory limit, so that a crash or a hang is an outcome to count, not a dead run.

Used by tests/test_fuzz_formats.py and benchmarks/fuzz_formats.py.

* :func:`seed_files` writes small valid files of every format and variant.
* :func:`mutate` derives a mutant: byte flips, truncation, inserted huge numbers,
  duplicated / removed lines, changed counts (``POINTS n``, ``LINES n size``,
  ``NumberOfPoints="n"``, ``offset="n"``, ...), a repeated or deleted chunk.
* :func:`run_mutants` reads mutants in child processes (``python fuzzing.py child``),
  many per child: the child prints ``START i`` before each read and one JSON line after
  it. A child that dies after ``START i`` crashed on mutant ``i``; one that prints
  nothing for ``timeout`` seconds hangs on it; either way it is replaced by a fresh child
  that goes on with mutant ``i + 1``. Outcomes: ``accepted`` (a list of curves),
  ``error`` (an NfdError: the clear refusal), ``traceback`` (any other exception),
  ``crash``, ``hang``.

For index files (tests/test_index_damage.py, benchmarks/fuzz_index.py): :func:`in_child`
runs a function in a forked child (a crash is a signal, not a dead run);
:func:`value_ranges` and :func:`metadata_offsets` tell an HDF5 file's stored values from
its metadata.
"""

from __future__ import annotations

import json
import os
import pickle
import re
import select
import signal
import subprocess
import sys
import time
from collections import Counter
from pathlib import Path

import numpy as np

OUTCOMES = ("error", "accepted", "crash", "hang", "traceback")

#: memory a child may map (RLIMIT_AS), bytes: numpy + nfdmatch need ~0.5 GB of address
#: space; the readers' own caps keep a file's data far below the rest
CHILD_MEMORY = 2 * 2**30

HUGE_NUMBERS = [
    b"1e308",
    b"-1e308",
    b"2147483648",
    b"4294967296",
    b"9223372036854775807",
    b"18446744073709551615",
    b"4611686018427387904",
    b"-1",
    b"-2147483649",
    b"nan",
    b"inf",
    b"0",
    b"1" * 40,
    b"99999999999",
]

_COUNT = re.compile(
    rb"((?:POINTS|LINES|CELLS|CELL_TYPES|VERTICES|POLYGONS|OFFSETS)\s+)(\d+)"
    rb'|((?:Number\w*|offset|header_type)=")([^"]*)(")'
)
_NUMBER = re.compile(rb"-?\d+(?:\.\d+)?(?:[eE][-+]?\d+)?")


def seed_files(folder) -> dict[str, list[str]]:
    """Valid files per format label: csv, obj, vtk-ascii, vtk-binary, vtp/vtu in ascii,
    binary, appended-raw, appended-base64 and zlib variants. Needs VTK (for the variants
    write_curves does not write); the reading children never import it."""
    import vtk

    from nfdmatch.formats import write_curves
    from nfdmatch.formats.vtk import _pyvista

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(0)

    def curve(n):
        t = np.linspace(0, 2 * np.pi, n, endpoint=False)
        return np.column_stack([np.cos(t), np.sin(2 * t) * 0.5, rng.normal(size=n) * 0.1])

    curves = [curve(12), curve(7), curve(20)]
    seeds: dict[str, list[str]] = {}
    p = str(folder / "one.csv")
    write_curves(p, [curves[0]])
    seeds["csv"] = [p]
    p = str(folder / "many.obj")
    write_curves(p, curves)
    segments = folder / "segments.obj"
    segments.write_text("v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nl 1 2\nl 2 3\nl 3 4\nl 4 1\nl 1 3 2\n")
    seeds["obj"] = [p, str(segments)]
    pv = _pyvista()
    poly = pv.read(write_and_name(write_curves, folder / "base.vtp", curves))
    grid = poly.cast_to_unstructured_grid()
    for label, binary in (("vtk-ascii", False), ("vtk-binary", True)):
        names = []
        for version in (42, 51):
            for data, tag in ((poly, "poly"), (grid, "grid")):
                w = vtk.vtkDataSetWriter()
                w.SetInputData(data)
                w.SetFileVersion(version)
                w.SetFileTypeToBinary() if binary else w.SetFileTypeToASCII()
                name = str(folder / f"{tag}{version}_{label}.vtk")
                w.SetFileName(name)
                w.Write()
                names.append(name)
        seeds[label] = names
    for ext, data in (("vtp", poly), ("vtu", grid)):
        for label, setup in (
            ("ascii", lambda w: w.SetDataModeToAscii()),
            ("binary", lambda w: (w.SetDataModeToBinary(), w.SetCompressorTypeToNone())),
            (
                "appended-raw",
                lambda w: (w.SetDataModeToAppended(), w.SetEncodeAppendedData(0), w.SetCompressorTypeToNone()),
            ),
            (
                "appended-base64",
                lambda w: (w.SetDataModeToAppended(), w.SetEncodeAppendedData(1), w.SetCompressorTypeToNone()),
            ),
            ("zlib", lambda w: (w.SetDataModeToBinary(), w.SetCompressorTypeToZLib())),
            (
                "zlib-appended",
                lambda w: (
                    w.SetDataModeToAppended(),
                    w.SetEncodeAppendedData(0),
                    w.SetCompressorTypeToZLib(),
                    w.SetHeaderTypeToUInt64(),
                ),
            ),
        ):
            w = vtk.vtkXMLPolyDataWriter() if ext == "vtp" else vtk.vtkXMLUnstructuredGridWriter()
            w.SetInputData(data)
            setup(w)
            name = str(folder / f"{label}.{ext}")
            w.SetFileName(name)
            w.Write()
            seeds[f"{ext}-{label}"] = [name]
    return seeds


def write_and_name(write_curves, path, curves) -> str:
    write_curves(str(path), curves)
    return str(path)


def mutate(data: bytes, rng: np.random.Generator) -> bytes:
    """One mutant of ``data``: one to three random edits."""
    out = bytearray(data)
    for _ in range(int(rng.integers(1, 4))):
        out = bytearray(_edit(bytes(out), rng))
    return bytes(out)


def _edit(data: bytes, rng) -> bytes:
    n = len(data)
    if n == 0:
        return bytes(rng.integers(0, 256, 16, dtype=np.uint8))
    kind = int(rng.integers(0, 9))
    if kind == 0:  # flip bytes
        b = bytearray(data)
        for _ in range(int(rng.integers(1, 8))):
            b[int(rng.integers(n))] = int(rng.integers(256))
        return bytes(b)
    if kind == 1:  # truncate
        return data[: int(rng.integers(n))]
    if kind == 2:  # insert a huge number somewhere
        k = int(rng.integers(n + 1))
        return data[:k] + b" " + HUGE_NUMBERS[int(rng.integers(len(HUGE_NUMBERS)))] + b" " + data[k:]
    if kind == 3:  # replace a number by a huge one
        found = list(_NUMBER.finditer(data))
        if not found:
            return data[::-1]
        m = found[int(rng.integers(len(found)))]
        return data[: m.start()] + HUGE_NUMBERS[int(rng.integers(len(HUGE_NUMBERS)))] + data[m.end() :]
    if kind in (4, 5):  # duplicate or remove a line
        lines = data.split(b"\n")
        k = int(rng.integers(len(lines)))
        if kind == 4:
            lines.insert(k, lines[k])
        elif len(lines) > 1:
            del lines[k]
        return b"\n".join(lines)
    if kind == 6:  # change a declared count / offset
        found = list(_COUNT.finditer(data))
        if not found:
            return _edit(data, rng)
        m = found[int(rng.integers(len(found)))]
        new = (
            HUGE_NUMBERS[int(rng.integers(len(HUGE_NUMBERS)))]
            if rng.random() < 0.5
            else str(int(rng.integers(0, 40))).encode()
        )
        if m.group(2) is not None:
            return data[: m.start(2)] + new + data[m.end(2) :]
        if m.group(3).startswith(b"header_type"):
            new = [b"UInt32", b"UInt64", b"UInt16", b""][int(rng.integers(4))]
        return data[: m.start(4)] + new + data[m.end(4) :]
    if kind == 7:  # repeat a chunk
        a = int(rng.integers(n))
        b = min(n, a + int(rng.integers(1, 200)))
        return data[:b] + data[a:b] * int(rng.integers(1, 50)) + data[b:]
    a = int(rng.integers(n))  # delete a chunk
    return data[:a] + data[a + int(rng.integers(1, 200)) :]


# ---------------------------------------------------------------------------
# the child
# ---------------------------------------------------------------------------


def _child(reader: str) -> None:
    import resource

    resource.setrlimit(resource.RLIMIT_AS, (CHILD_MEMORY, CHILD_MEMORY))
    from nfdmatch.errors import NfdError
    from nfdmatch.formats import read_curves

    def test_reader(path):  # lets the tests check this harness
        data = open(path, "rb").read()
        if b"CRASH" in data:
            os.abort()
        if b"HANG" in data:
            while True:
                pass
        if b"RAISE" in data:
            raise IndexError("a reader bug")
        return read_curves(path)

    def pyvista_reader(path):  # the VTK C++ readers, for comparison
        from nfdmatch.formats.vtk import _pyvista

        mesh = _pyvista().read(path)
        if mesh is None or mesh.n_points == 0:
            raise NfdError("no points", path=path)
        return [mesh]

    read = {"nfdmatch": read_curves, "test": test_reader, "pyvista": pyvista_reader}[reader]
    # results go to a private copy of stdout; whatever a reader prints goes nowhere
    out = os.fdopen(os.dup(1), "w")
    os.dup2(os.open(os.devnull, os.O_WRONLY), 1)
    for line in sys.stdin:
        index, path = line.rstrip("\n").split("\t", 1)
        out.write(f"START {index}\n")
        out.flush()
        try:
            curves = read(path)
            result = {"i": int(index), "outcome": "accepted", "curves": len(curves)}
        except NfdError as exc:
            result = {
                "i": int(index),
                "outcome": "error",
                "type": type(exc).__name__,
                "message": str(exc)[:300],
                "length": len(str(exc)),
            }
        except BaseException as exc:  # noqa: BLE001 - a reader bug: the outcome to count
            result = {"i": int(index), "outcome": "traceback", "type": type(exc).__name__, "message": str(exc)[:300]}
        out.write(json.dumps(result) + "\n")
        out.flush()


def run_mutants(paths: list[str], *, timeout: float = 10.0, reader: str = "nfdmatch", batch: int = 200) -> list[dict]:
    """Read every path in child processes; one result dict per path, in order, with
    ``outcome`` one of :data:`OUTCOMES` (crash and hang results carry ``detail``)."""
    results: list[dict | None] = [None] * len(paths)
    env = dict(os.environ)
    root = str(Path(__file__).resolve().parents[1])
    env["PYTHONPATH"] = root + os.pathsep + env.get("PYTHONPATH", "")
    next_index = 0
    while next_index < len(paths):
        chunk = list(range(next_index, min(len(paths), next_index + batch)))
        proc = subprocess.Popen(
            [sys.executable, __file__, "child", reader],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=subprocess.DEVNULL,
            env=env,
        )
        proc.stdin.write("".join(f"{i}\t{paths[i]}\n" for i in chunk).encode("utf-8", "surrogateescape"))
        proc.stdin.close()
        current = None
        buffer = b""
        deadline = time.monotonic() + timeout + 20  # start-up: imports
        stopped_at = None
        while True:
            wait = deadline - time.monotonic()
            ready = select.select([proc.stdout], [], [], max(0.0, wait))[0] if wait > 0 else []
            if not ready:
                proc.kill()
                proc.wait()
                if current is None:
                    raise RuntimeError("a fuzz child did not start")
                results[current] = {"i": current, "outcome": "hang", "detail": f"no answer within {timeout} s"}
                stopped_at = current + 1
                break
            piece = os.read(proc.stdout.fileno(), 65536)
            if not piece:  # the child is gone
                code = proc.wait()
                if current is not None and results[current] is None:
                    results[current] = {"i": current, "outcome": "crash", "detail": f"child exit status {code}"}
                    stopped_at = current + 1
                else:
                    stopped_at = chunk[-1] + 1
                    if any(results[i] is None for i in chunk):
                        raise RuntimeError(f"a fuzz child stopped outside any read ({code})")
                break
            buffer += piece
            *lines, buffer = buffer.split(b"\n")
            for line in lines:
                if line.startswith(b"START "):
                    current = int(line[6:])
                    deadline = time.monotonic() + timeout
                else:
                    result = json.loads(line)
                    results[result["i"]] = result
        proc.stdout.close()
        next_index = stopped_at
    return results  # type: ignore[return-value]


def fuzz(
    seeds: dict[str, list[str]],
    folder,
    mutants_per_format: int,
    *,
    seed: int = 0,
    timeout: float = 10.0,
    reader: str = "nfdmatch",
    batch: int = 200,
):
    """Write ``mutants_per_format`` mutants of each format's seeds into ``folder`` and read
    them. Returns ``(table, results)``: Counter of outcomes per format, and per format the
    list of ``(mutant path, result)``."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    paths, labels = [], []
    for label, files in seeds.items():
        blobs = [(Path(f).read_bytes(), Path(f).suffix) for f in files]
        for k in range(mutants_per_format):
            data, ext = blobs[k % len(blobs)]
            path = folder / f"{label}-{k:05d}{ext}"
            path.write_bytes(mutate(data, rng))
            paths.append(str(path))
            labels.append(label)
    results = run_mutants(paths, timeout=timeout, reader=reader, batch=batch)
    table: dict[str, Counter] = {label: Counter() for label in seeds}
    details: dict[str, list] = {label: [] for label in seeds}
    for label, path, result in zip(labels, paths, results):
        table[label][result["outcome"]] += 1
        details[label].append((path, result))
    return table, details


def format_table(table: dict[str, Counter]) -> str:
    lines = [f"{'format':18}" + "".join(f"{o:>11}" for o in OUTCOMES) + f"{'total':>8}"]
    total = Counter()
    for label, counts in table.items():
        total.update(counts)
        lines.append(f"{label:18}" + "".join(f"{counts[o]:>11}" for o in OUTCOMES) + f"{sum(counts.values()):>8}")
    lines.append(f"{'all':18}" + "".join(f"{total[o]:>11}" for o in OUTCOMES) + f"{sum(total.values()):>8}")
    return "\n".join(lines)


# --------------------------------------------------------------------------- index files


def in_child(fn, timeout: float):
    """``fn()`` in a forked child: ``("ok", value)``, ``("signal", name)``, ``("exit", code)``
    or ``("hang", None)``."""
    r, w = os.pipe()
    pid = os.fork()
    if pid == 0:  # the child
        os.close(r)
        code = 0
        try:
            data = pickle.dumps(fn())
            with os.fdopen(w, "wb") as fh:
                fh.write(data)
        except BaseException:  # noqa: BLE001 - any escape is reported as an exit code
            code = 70
        os._exit(code)
    os.close(w)
    chunks, deadline = [], time.monotonic() + timeout
    with os.fdopen(r, "rb") as fh:
        while True:
            left = deadline - time.monotonic()
            if left <= 0:
                os.kill(pid, signal.SIGKILL)
                os.waitpid(pid, 0)
                return "hang", None
            ready, _, _ = select.select([fh], [], [], left)
            if ready:
                piece = os.read(fh.fileno(), 1 << 20)
                if not piece:
                    break
                chunks.append(piece)
    _, status = os.waitpid(pid, 0)
    if os.WIFSIGNALED(status):
        return "signal", signal.Signals(os.WTERMSIG(status)).name
    if os.WEXITSTATUS(status) != 0 or not chunks:
        return "exit", os.WEXITSTATUS(status)
    return "ok", pickle.loads(b"".join(chunks))


def value_ranges(path: str) -> list[tuple[int, int]]:
    """Byte ranges of the file holding dataset values (chunks, contiguous data): the rest is metadata."""
    import h5py

    ranges = []
    with h5py.File(path, "r") as h5:

        def visit(name, obj):
            if not isinstance(obj, h5py.Dataset):
                return
            if obj.chunks is None:
                off = obj.id.get_offset()
                if off is not None:
                    ranges.append((off, off + obj.id.get_storage_size()))
            else:
                obj.id.chunk_iter(lambda info: ranges.append((info.byte_offset, info.byte_offset + info.size)))

        h5.visititems(visit)
    return sorted(ranges)


def metadata_offsets(size: int, ranges) -> list[int]:
    inside = bytearray(size)
    for a, b in ranges:
        inside[a:b] = b"\1" * (b - a)
    return [i for i in range(size) if not inside[i]]


if __name__ == "__main__" and len(sys.argv) >= 2 and sys.argv[1] == "child":
    _child(sys.argv[2] if len(sys.argv) > 2 else "nfdmatch")
