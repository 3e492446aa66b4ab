"""What a progress bar costs on a terminal: the same command with stderr on a
pseudo-terminal (the bar drawn) and on a pipe (no bar), time and bytes written.

    python benchmarks/bench_progress.py [--files 3000] [--queries 1000] [--repeats 3]
                                        [--workdir /tmp/nfdmatch-progress]

Generates ``--files`` one-curve CSV files, then times, as whole new processes,
``nfdmatch index build FOLDER --index NEW.h5 -j 1`` and ``nfdmatch query`` of ``--queries``
of those files against the index, each with stderr on a pseudo-terminal (``pty.openpty``,
its other end drained by a thread that counts the bytes) and on a pipe. stdout goes to
/dev/null in both. Prints the median seconds of each, the ratio terminal / piped and the
bytes the terminal received (the issue's aim: at most 1.3x the piped time and 200 kB for
3,000 files; a bar redrawn at most ~10 times a second, ``cli.output.REDRAW_SECONDS``).
"""

from __future__ import annotations

import argparse
import os
import pty
import shutil
import statistics
import subprocess
import sys
import threading
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
REPO = os.path.normpath(os.path.join(HERE, ".."))


def generate(folder: str, files: int, seed: int = 7) -> None:
    stamp = os.path.join(folder, ".complete")
    if os.path.exists(stamp):
        return
    os.makedirs(folder, exist_ok=True)
    rng = np.random.default_rng(seed)
    for i in range(files):
        n = int(rng.integers(40, 65))
        t = np.linspace(0, 2 * np.pi, n, endpoint=False)
        pts = np.zeros((n, 3))
        for k in range(1, 4):
            a = rng.normal(size=(3, 2)) / k**2
            pts += np.outer(np.cos(k * t), a[:, 0]) + np.outer(np.sin(k * t), a[:, 1])
        with open(os.path.join(folder, f"c{i:05d}.csv"), "w") as fh:
            fh.write("x,y,z\n" + "".join(f"{x:.6f},{y:.6f},{z:.6f}\n" for x, y, z in pts))
    open(stamp, "w").close()


def run(args: list[str], terminal: bool) -> tuple[float, int]:
    """Seconds and bytes on stderr of ``nfdmatch ARGS`` with stderr on a pseudo-terminal or a pipe."""
    command = [sys.executable, "-m", "nfdmatch", *args]
    received = [0]
    if terminal:
        master, slave = pty.openpty()

        def drain():
            while True:
                try:
                    chunk = os.read(master, 65536)
                except OSError:  # the other end closed
                    return
                if not chunk:
                    return
                received[0] += len(chunk)

        reader = threading.Thread(target=drain, daemon=True)
        reader.start()
        started = time.perf_counter()
        subprocess.run(command, stdout=subprocess.DEVNULL, stderr=slave, check=True, cwd=REPO)
        seconds = time.perf_counter() - started
        os.close(slave)
        reader.join(timeout=10)
        os.close(master)
    else:
        started = time.perf_counter()
        proc = subprocess.run(command, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, check=True, cwd=REPO)
        seconds = time.perf_counter() - started
        received[0] = len(proc.stderr)
    return seconds, received[0]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--files", type=int, default=3000)
    parser.add_argument("--queries", type=int, default=1000)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--workdir", default="/tmp/nfdmatch-progress")
    opts = parser.parse_args()
    folder = os.path.join(opts.workdir, f"files-{opts.files}")
    generate(folder, opts.files)
    queries = os.path.join(opts.workdir, f"queries-{opts.queries}")
    if not os.path.isdir(queries):
        os.makedirs(queries)
        for name in sorted(os.listdir(folder))[: opts.queries]:
            if name.endswith(".csv"):
                shutil.copy(os.path.join(folder, name), queries)
    index = os.path.join(opts.workdir, "index.h5")
    commands = {
        f"index build ({opts.files} files)": lambda: (
            [os.remove(p) for p in (index,) if os.path.exists(p)],
            ["index", "build", folder, "--index", index, "-j", "1"],
        )[1],
        f"query ({opts.queries} queries)": lambda: ["query", queries, "--index", index, "--top", "1"],
    }
    print(f"{'command':32} {'terminal s':>10} {'piped s':>8} {'ratio':>6} {'bytes (terminal)':>17}")
    for name, make in commands.items():
        times = {True: [], False: []}
        sizes = []
        for _ in range(opts.repeats):
            for terminal in (True, False):  # interleaved: the same load on both
                seconds, size = run(make(), terminal)
                times[terminal].append(seconds)
                if terminal:
                    sizes.append(size)
        tty, piped = statistics.median(times[True]), statistics.median(times[False])
        print(f"{name:32} {tty:10.2f} {piped:8.2f} {tty / piped:6.2f} {int(statistics.median(sizes)):17,d}")


if __name__ == "__main__":
    main()
