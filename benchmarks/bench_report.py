"""Time and size of `nfdmatch report` for a batch of 1,000 queries (issue 37's goal: at most
60 s on 2 cores and 25 MB, and the page opens in Chromium).

    python benchmarks/bench_report.py [--queries 1000] [--library 2000] [--top 5] [--out DIR]

The library: --library closed 3-D curves of random low harmonics (200 vertices each), one
CSV file per curve (what `show` and `report` read back to draw a match), indexed with
`nfdmatch index build`. The queries: --queries noisy, re-posed copies of library curves in
one OBJ file (ids ``queries.obj#i``). Measured: the wall time of the `nfdmatch report`
process (Python's start-up, the search, the drawing of every match read back from its file,
and writing the page), the page's size, and Chromium's screenshot of the page (the page
opens, and the first screen shows drawn pictures: pixels of the match colour).
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
sys.path.insert(0, ROOT)

from nfdmatch.formats import csv as csv_format  # noqa: E402
from nfdmatch.formats import obj as obj_format  # noqa: E402

NFDMATCH = [sys.executable, "-m", "nfdmatch"]


def loops(n: int, seed: int, points: int = 200) -> np.ndarray:
    rng = np.random.default_rng(seed)
    t = np.linspace(0.0, 2 * np.pi, points, endpoint=False)
    h = np.arange(1, 5)
    a = rng.normal(size=(n, 3, 4)) / h**1.5
    b = rng.normal(size=(n, 3, 4)) / h**1.5
    a[:, 0, 0] += 2.0
    b[:, 1, 0] += 2.0
    phase = np.outer(h, t)
    return np.einsum("ncj,jp->npc", a, np.cos(phase)) + np.einsum("ncj,jp->npc", b, np.sin(phase))


def random_rotation(rng) -> np.ndarray:
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q *= np.sign(np.diag(r))
    return q if np.linalg.det(q) > 0 else -q


def prepare(out: str, library: int, queries: int) -> tuple[str, str]:
    lib = os.path.join(out, "library")
    os.makedirs(lib, exist_ok=True)
    curves = loops(library, seed=1)
    for i, c in enumerate(curves):
        path = os.path.join(lib, f"loop-{i:05d}.csv")
        if not os.path.exists(path):
            csv_format.write(path, [c])
    rng = np.random.default_rng(2)
    picked = rng.integers(0, library, size=queries)
    posed = [
        3.0 * (curves[i] + 0.02 * rng.normal(size=curves[i].shape)) @ random_rotation(rng).T + rng.normal(size=3)
        for i in picked
    ]
    qfile = os.path.join(out, "queries.obj")
    obj_format.write(qfile, posed)
    index = os.path.join(out, "library.h5")
    subprocess.run([*NFDMATCH, "-q", "index", "build", lib, "--index", index], check=True)
    return index, qfile


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--queries", type=int, default=1000)
    ap.add_argument("--library", type=int, default=2000)
    ap.add_argument("--top", type=int, default=5)
    ap.add_argument("--out", default="/tmp/nfdmatch-bench-report")
    args = ap.parse_args()
    os.makedirs(args.out, exist_ok=True)
    index, qfile = prepare(args.out, args.library, args.queries)
    page = os.path.join(args.out, "report.html")
    t0 = time.perf_counter()
    subprocess.run([*NFDMATCH, "report", qfile, "--index", index, "--top", str(args.top), "-o", page], check=True)
    seconds = time.perf_counter() - t0
    size = os.path.getsize(page)
    print(
        f"report of {args.queries} queries (top {args.top}) against {args.library} curves: {seconds:.1f} s, {size / 1e6:.1f} MB"
    )
    chromium = shutil.which("chromium")
    if chromium is None:
        print("chromium: not installed (apt-get install -y chromium): not opened")
        return
    shot = os.path.join(args.out, "report.png")
    t0 = time.perf_counter()
    subprocess.run(
        [
            chromium, "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
            "--disable-background-networking", "--disable-component-update", "--disable-sync",
            f"--user-data-dir={os.path.join(args.out, 'profile')}", "--window-size=1400,1400",
            f"--screenshot={shot}", f"file://{os.path.abspath(page)}",
        ],
        check=True, capture_output=True, timeout=300,
    )  # fmt: skip
    from PIL import Image

    pixels = np.asarray(Image.open(shot).convert("RGB"), dtype=np.int64)
    drawn = int((np.abs(pixels - np.array([0xD1, 0x42, 0x1B])).sum(axis=2) < 60).sum())
    print(
        f"chromium: opened and screenshot in {time.perf_counter() - t0:.1f} s; {drawn} pixels of match colour ({shot})"
    )


if __name__ == "__main__":
    main()
