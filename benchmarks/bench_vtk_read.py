"""Reading 5,000-curve VTK files: nfdmatch's own reader against pyvista, in and out of process.

    python benchmarks/bench_vtk_read.py [--curves 5000] [--repeat 5] [--workdir /tmp/nfdmatch-bench-vtk]

Files are made by the project's writers from the curve families of bench_index.py
(60-200 vertices per curve): ``.vtp`` (XML, inline binary, zlib: what ``write_curves``
writes), ``.vtk`` (legacy binary), and with VTK's writer directly a ``.vtp`` in appended raw
and in ASCII, and a legacy ASCII ``.vtk``. For each file, the median seconds of:

* ``strict``: ``nfdmatch.formats._vtk_read.parse`` of the file's bytes (this process);
* ``read_curves``: the whole ``nfdmatch.formats.read_curves`` (strict parse + cleaning);
* ``pyvista``: ``pyvista.read`` plus fetching points and line cells (this process, pyvista
  already imported): what the reader did before, with no protection;
* ``child``: ``pyvista.read`` in a fresh child process (``python -c``, the way a crash or
  hang can be contained per file with a time and memory limit), points and cells sent back
  as .npy bytes through a pipe: start-up + pyvista import + read + transfer;
* ``warm child``: the same read in an already running child that has pyvista imported
  (the least a process-isolated read could cost with a pool of pre-started readers;
  every crash would still cost a restart).
"""

from __future__ import annotations

import argparse
import io
import os
import shutil
import statistics
import subprocess
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)
from bench_index import family_members  # noqa: E402

from nfdmatch.formats import read_curves, write_curves  # noqa: E402
from nfdmatch.formats import _vtk_read  # noqa: E402

CHILD = r"""
import io, os, sys
import numpy as np
os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")
import pyvista as pv

def one(path):
    mesh = pv.read(path)
    if isinstance(mesh, pv.PolyData):
        arrays = [mesh.points, mesh.line_offsets, mesh.line_connectivity]
    else:
        arrays = [mesh.points, mesh.cell_offsets, mesh.cell_connectivity, mesh.celltypes]
    out = io.BytesIO()
    for a in arrays:
        np.save(out, np.asarray(a))
    data = out.getvalue()
    sys.stdout.buffer.write(len(data).to_bytes(8, "little") + data)
    sys.stdout.buffer.flush()

if len(sys.argv) > 1:
    one(sys.argv[1])
else:
    for line in sys.stdin:
        one(line.strip())
"""


def timed(fn, repeat):
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def read_reply(stream):
    size = int.from_bytes(stream.read(8), "little")
    blob = io.BytesIO(stream.read(size))
    return [np.load(blob) for _ in range(3)]


def make_files(work, n_curves):
    import vtk

    rng = np.random.default_rng(1)
    curves = []
    while len(curves) < n_curves:
        curves.extend(family_members(rng, 10))
    curves = curves[:n_curves]
    files = {}
    files["vtp binary zlib (write_curves)"] = os.path.join(work, "curves.vtp")
    files["vtk legacy binary (write_curves)"] = os.path.join(work, "curves.vtk")
    for path in list(files.values()):
        write_curves(path, curves)
    from nfdmatch.formats.vtk import _pyvista

    mesh = _pyvista().read(files["vtp binary zlib (write_curves)"])
    for label, name, setup in (
        ("vtp appended raw", "appended.vtp", lambda w: (w.SetDataModeToAppended(), w.SetEncodeAppendedData(0))),
        ("vtp ascii", "ascii.vtp", lambda w: w.SetDataModeToAscii()),
    ):
        writer = vtk.vtkXMLPolyDataWriter()
        writer.SetInputData(mesh)
        setup(writer)
        writer.SetFileName(os.path.join(work, name))
        writer.Write()
        files[label] = os.path.join(work, name)
    legacy = vtk.vtkPolyDataWriter()
    legacy.SetInputData(mesh)
    legacy.SetFileTypeToASCII()
    legacy.SetFileName(os.path.join(work, "ascii.vtk"))
    legacy.Write()
    files["vtk legacy ascii"] = os.path.join(work, "ascii.vtk")
    return files


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--curves", type=int, default=5000)
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--workdir", default="/tmp/nfdmatch-bench-vtk")
    args = ap.parse_args()
    shutil.rmtree(args.workdir, ignore_errors=True)
    os.makedirs(args.workdir)
    files = make_files(args.workdir, args.curves)
    from nfdmatch.formats.vtk import _pyvista

    pv = _pyvista()
    warm = subprocess.Popen([sys.executable, "-c", CHILD], stdin=subprocess.PIPE, stdout=subprocess.PIPE)

    def warm_read(path):
        warm.stdin.write((path + "\n").encode())
        warm.stdin.flush()
        return read_reply(warm.stdout)

    def child_read(path):
        proc = subprocess.run([sys.executable, "-c", CHILD, path], capture_output=True, check=True)
        return read_reply(io.BytesIO(proc.stdout))

    print(f"{args.curves} curves per file; median of {args.repeat} runs, seconds")
    header = ("file", "MB", "strict", "read_curves", "pyvista", "child", "warm child")
    print(f"{header[0]:34} {header[1]:>6} " + " ".join(f"{h:>11}" for h in header[2:]))
    for label, path in files.items():
        kind = path.rsplit(".", 1)[1]
        size = os.path.getsize(path) / 1e6
        row = [
            timed(lambda: _vtk_read.parse(open(path, "rb").read(), kind, path), args.repeat),
            timed(lambda: read_curves(path), args.repeat),
            timed(lambda: (lambda m: (np.asarray(m.points), np.asarray(m.lines)))(pv.read(path)), args.repeat),
            timed(lambda: child_read(path), args.repeat),
            timed(lambda: warm_read(path), args.repeat),
        ]
        print(f"{label:34} {size:6.1f} " + " ".join(f"{t:11.3f}" for t in row))
    warm.stdin.close()
    warm.wait()


if __name__ == "__main__":
    main()
