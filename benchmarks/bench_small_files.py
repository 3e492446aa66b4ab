"""Build rate over folders of many one-curve files, with 1 and 2 jobs, against a baseline commit.

    python benchmarks/bench_small_files.py [--files 10000] [--repeats 3] [--workdir /tmp/nfdmatch-small]
                                           [--baseline 646aae63ea297348d6f1045d7b9ee4ddc244d789]

Generates ``--files`` one-curve CSV files and as many one-curve OBJ files (40-64 vertices,
about 2.5 KB each), then times ``nfdmatch index build FOLDER --index NEW.h5 -j J -q`` as a
whole new process (start-up, planning, reading, describing, writing: what a user waits for)
with J = 1 and 2, for this checkout and for the baseline commit checked out as a detached
``git worktree`` under the workdir, so that the gain is a ratio measured in the same run on
the same (shared) machine. Each figure is the median of ``--repeats`` runs, the runs of the
two checkouts interleaved. Prints seconds, files/s and the speed-up of 2 jobs over 1, and
the CPU seconds (user + system, workers included) of each build: on a machine shared with
other work the wall-clock speed-up of -j 2 needs two idle cores, the CPU time does not.
"""

from __future__ import annotations

import argparse
import os
import resource
import statistics
import subprocess
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
REPO = os.path.normpath(os.path.join(HERE, ".."))
BASELINE = "646aae63ea297348d6f1045d7b9ee4ddc244d789"


def _curve(rng) -> np.ndarray:
    n = int(rng.integers(40, 65))
    t = np.linspace(0, 2 * np.pi, n, endpoint=False)
    pts = np.zeros((n, 3))
    for k in range(1, 4):
        a = rng.normal(size=(3, 2)) / k**2
        pts += np.outer(np.cos(k * t), a[:, 0]) + np.outer(np.sin(k * t), a[:, 1])
    return pts


def generate(folder: str, files: int, fmt: str, seed: int) -> None:
    """``files`` one-curve files of format ``fmt`` ("csv" or "obj") in ``folder`` (skipped if done)."""
    stamp = os.path.join(folder, ".complete")
    if os.path.exists(stamp):
        return
    os.makedirs(folder, exist_ok=True)
    rng = np.random.default_rng(seed)
    for i in range(files):
        pts = _curve(rng)
        if fmt == "csv":
            text = "x,y,z\n" + "".join(f"{x:.6f},{y:.6f},{z:.6f}\n" for x, y, z in pts)
        else:
            text = (
                "".join(f"v {x:.6f} {y:.6f} {z:.6f}\n" for x, y, z in pts)
                + "l "
                + " ".join(str(j + 1) for j in range(len(pts)))
                + " 1\n"
            )
        with open(os.path.join(folder, f"c{i:05d}.{fmt}"), "w") as fh:
            fh.write(text)
    open(stamp, "w").close()


def baseline_checkout(workdir: str, commit: str) -> str:
    path = os.path.join(workdir, "baseline-" + commit[:8])
    if not os.path.isdir(path):
        subprocess.run(
            ["git", "-C", REPO, "worktree", "add", "--detach", path, commit], check=True, stdout=subprocess.DEVNULL
        )
    return path


def time_build(code: str, folder: str, index: str, jobs: int) -> tuple[float, float]:
    """(wall seconds, CPU seconds of the build and its workers) of one whole build process."""
    for p in (index, index + ".lock"):
        if os.path.exists(p):
            os.remove(p)
    env = dict(os.environ, PYTHONPATH=code)
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    start = time.perf_counter()
    # cwd: a folder without a nfdmatch package, or `python -m` would import the one in cwd
    proc = subprocess.run(
        [sys.executable, "-m", "nfdmatch", "index", "build", folder, "--index", index, "-j", str(jobs)],
        env=env,
        capture_output=True,
        text=True,
        cwd=os.path.dirname(index),
    )
    seconds = time.perf_counter() - start
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if proc.returncode != 0:
        raise SystemExit(f"build failed ({code}, {folder}, -j {jobs}): exit {proc.returncode}\n{proc.stderr}")
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return seconds, cpu


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--files", type=int, default=10000)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--workdir", default="/tmp/nfdmatch-small")
    ap.add_argument("--baseline", default=BASELINE)
    ap.add_argument("--no-baseline", action="store_true", help="Time this checkout only.")
    args = ap.parse_args()
    os.makedirs(args.workdir, exist_ok=True)
    codes = {"this checkout": REPO}
    if not args.no_baseline:
        codes[f"baseline {args.baseline[:8]}"] = baseline_checkout(args.workdir, args.baseline)
    folders = {}
    for seed, fmt in enumerate(("csv", "obj")):
        folders[fmt] = os.path.join(args.workdir, f"{args.files}-{fmt}")
        generate(folders[fmt], args.files, fmt, seed)
    index = os.path.join(args.workdir, "bench.h5")
    times: dict = {}
    cpus: dict = {}
    for _ in range(args.repeats):
        for fmt, folder in folders.items():
            for jobs in (1, 2):
                for name, code in codes.items():
                    wall, cpu = time_build(code, folder, index, jobs)
                    times.setdefault((name, fmt, jobs), []).append(wall)
                    cpus.setdefault((name, fmt, jobs), []).append(cpu)
    load = os.getloadavg()[0]
    print(
        f"{args.files} one-curve files per folder, {os.cpu_count()} cores (load average {load:.1f} at the "
        f"end), median of {args.repeats} runs (whole `nfdmatch index build` processes)"
    )
    print(
        f"{'code':<22} {'format':<6} {'-j 1 s':>8} {'files/s':>8} {'-j 2 s':>8} {'files/s':>8} {'j2/j1':>6}"
        f" {'cpu-s j1':>8} {'cpu-s j2':>8}"
    )
    for name in codes:
        for fmt in folders:
            t1 = statistics.median(times[(name, fmt, 1)])
            t2 = statistics.median(times[(name, fmt, 2)])
            c1 = statistics.median(cpus[(name, fmt, 1)])
            c2 = statistics.median(cpus[(name, fmt, 2)])
            print(
                f"{name:<22} {fmt:<6} {t1:8.2f} {args.files / t1:8.0f} {t2:8.2f} {args.files / t2:8.0f} "
                f"{t1 / t2:6.2f} {c1:8.2f} {c2:8.2f}"
            )
    print(
        "cpu-s: user + system seconds of the build and its workers (what a machine shared with "
        "other work cannot hide); wall times of all runs:"
    )
    print("; ".join(f"{n} {f} -j{j}: " + " ".join(f"{t:.2f}" for t in v) for (n, f, j), v in sorted(times.items())))


if __name__ == "__main__":
    main()
