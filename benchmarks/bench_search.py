"""Exact search at scale: this checkout against a baseline commit, side by side in one run.

    python benchmarks/bench_search.py [--families 20000] [--random 100000] [--baseline REV]
                                      [--workdir /tmp/nfdmatch-bench-search] [--repeat 5]

Two collections (generated once, cached in the work folder):

* **families**: ``--families`` random smooth curves (harmonics 3..6), 50 members each:
  32 vertices at a random warp of the parameter, noise 1% of the size, random rotation,
  scale (0.1..10), translation and start vertex, half reversed; members shuffled over 100
  OBJ files (1,000,000 curves by default). Queries: a fresh member of 20 random families.
* **random**: ``--random`` unrelated random smooth curves (harmonics <= 6), 48 vertices, in
  20 OBJ files: no families, the invariant bounds are loose. Queries: a noisy re-posed,
  re-sampled copy of 20 stored curves.

For each collection and each code version (this checkout, and ``--baseline``, default the
commit this search work started from, checked out as a git worktree in the work folder):
build time and peak RSS (`index build`, new process); single-query process time (`query
q.csv --top 10`, median of ``--repeat`` runs) next to bare ``nfdmatch --help``; a batch of
20 queries in one command (ms per query, start-up excluded); exact distances per query
(`--stats`); bytes read per query (the process's read() bytes above those of ``--help``);
and whether both versions return the same ids and distances.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import statistics
import subprocess
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
#: the commit the issue's search work started from (the figures are ratios against it)
DEFAULT_BASELINE = "646aae63ea297348d6f1045d7b9ee4ddc244d789"
QUERIES = 20


# --------------------------------------------------------------------------- generators


def _smooth_coefficients(rng, count, harmonics, decay=1.5):
    k = np.arange(1, harmonics.max() + 1)
    amp = (k**-decay)[None, :, None] * (k[None, :] <= harmonics[:, None])[:, :, None]
    return rng.standard_normal((count, len(k), 3)) * amp, rng.standard_normal((count, len(k), 3)) * amp


def _rotations(rng, count):
    q = rng.standard_normal((count, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    w, x, y, z = q.T
    return np.stack(
        [
            1 - 2 * (y * y + z * z),
            2 * (x * y - z * w),
            2 * (x * z + y * w),
            2 * (x * y + z * w),
            1 - 2 * (x * x + z * z),
            2 * (y * z - x * w),
            2 * (x * z - y * w),
            2 * (y * z + x * w),
            1 - 2 * (x * x + y * y),
        ],
        1,
    ).reshape(count, 3, 3)


def _sample(a, b, vertices, rng, noise):
    """Curves (count, vertices, 3): each at its own monotone warp of the parameter, with
    noise (relative to the curve's RMS radius), re-posed, start-shifted, half reversed."""
    count, H, _ = a.shape
    u = np.arange(vertices) / vertices
    t = np.broadcast_to(u, (count, vertices)).copy()
    c = rng.uniform(-1, 1, (count, 3))
    c *= 0.6 / np.maximum(np.abs(c).sum(1, keepdims=True), 1e-12)
    ph = rng.uniform(0, 2 * np.pi, (count, 3))
    for m in range(1, 4):
        t += (
            c[:, m - 1 : m]
            * (np.sin(2 * np.pi * m * u[None] + ph[:, m - 1 : m]) - np.sin(ph[:, m - 1 : m]))
            / (2 * np.pi * m)
        )
    arg = 2 * np.pi * t[:, :, None] * np.arange(1, H + 1)[None, None, :]
    pts = np.einsum("nvh,nhd->nvd", np.cos(arg), a) + np.einsum("nvh,nhd->nvd", np.sin(arg), b)
    size = np.sqrt(((pts - pts.mean(1, keepdims=True)) ** 2).sum(2).mean(1))
    pts += rng.normal(size=pts.shape) * (noise * size)[:, None, None]
    shift = rng.integers(0, vertices, count)
    pts = np.take_along_axis(pts, ((np.arange(vertices)[None] + shift[:, None]) % vertices)[:, :, None], axis=1)
    rev = rng.random(count) < 0.5
    pts[rev] = pts[rev, ::-1]
    scale = np.exp(rng.uniform(np.log(0.1), np.log(10), count))
    return (
        np.einsum("nvd,ned->nve", pts, _rotations(rng, count)) * scale[:, None, None]
        + rng.uniform(-100, 100, (count, 3))[:, None, :]
    )


def _write_obj(path, curves):
    count, V, _ = curves.shape
    text = ("v %.6f %.6f %.6f\n" * (count * V)) % tuple(curves.reshape(-1).tolist())
    base = np.arange(count)[:, None] * V + np.arange(1, V + 1)[None, :]
    lines = np.concatenate([base, base[:, :1]], axis=1)
    fmt = "l" + " %d" * (V + 1) + "\n"
    with open(path + ".part", "w") as f:
        f.write(text)
        f.write((fmt * count) % tuple(lines.reshape(-1).tolist()))
    os.replace(path + ".part", path)


def _write_csv(path, points):
    np.savetxt(path, points, delimiter=",", header="x,y,z", comments="", fmt="%.9g")


def generate_families(folder, families, members=50, files=100, vertices=32, seed=11):
    rng = np.random.default_rng(seed)
    a, b = _smooth_coefficients(rng, families, rng.integers(3, 7, families))
    owner = rng.permutation(np.repeat(np.arange(families), members))
    os.makedirs(os.path.join(folder, "curves"), exist_ok=True)
    for i, part in enumerate(np.array_split(owner, files)):
        path = os.path.join(folder, "curves", f"part-{i:03d}.obj")
        if not os.path.exists(path):
            _write_obj(path, _sample(a[part], b[part], vertices, np.random.default_rng([seed, i]), 0.01))
    qrng = np.random.default_rng([seed, 10**6])
    fam = qrng.choice(families, QUERIES, replace=False)
    return _write_queries(folder, _sample(a[fam], b[fam], vertices, qrng, 0.01))


def generate_random(folder, count, files=20, vertices=48, seed=12):
    rng = np.random.default_rng(seed)
    a, b = _smooth_coefficients(rng, count, np.full(count, 6))
    os.makedirs(os.path.join(folder, "curves"), exist_ok=True)
    for i, part in enumerate(np.array_split(np.arange(count), files)):
        path = os.path.join(folder, "curves", f"part-{i:03d}.obj")
        if not os.path.exists(path):
            _write_obj(path, _sample(a[part], b[part], vertices, np.random.default_rng([seed, i]), 0.0))
    qrng = np.random.default_rng([seed, 10**6])
    pick = qrng.choice(count, QUERIES, replace=False)
    return _write_queries(folder, _sample(a[pick], b[pick], vertices, qrng, 0.01))


def _write_queries(folder, curves):
    qdir = os.path.join(folder, "queries")
    os.makedirs(qdir, exist_ok=True)
    paths = []
    for i, pts in enumerate(curves):
        paths.append(os.path.join(qdir, f"q{i:02d}.csv"))
        _write_csv(paths[-1], pts)
    return paths


# --------------------------------------------------------------------------- measuring

_MEASURE = r"""
import os, runpy, sys
def rchar():
    with open("/proc/self/io") as f:
        return int(next(l for l in f if l.startswith("rchar")).split()[1])
start = rchar()
sys.argv = ["nfdmatch"] + sys.argv[2:]
code = 0
try:
    runpy.run_module("nfdmatch", run_name="__main__", alter_sys=True)
except SystemExit as exc:
    code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
finally:
    with open(os.environ["NFDMATCH_BENCH_IO"], "w") as f:
        f.write(str(rchar() - start))
sys.exit(code)
"""


class Version:
    """One code version of nfdmatch run as a new process: `python -m nfdmatch` with its
    source folder first on the path. ``-P`` and the source folder as the working directory:
    Python would otherwise put the benchmark's working directory (this checkout) before
    PYTHONPATH, and every version would run this checkout's code."""

    def __init__(self, label, source):
        self.label, self.source = label, source
        # as an installed package runs: from bytecode (an environment with
        # PYTHONDONTWRITEBYTECODE would compile every module from source in every process)
        subprocess.run([sys.executable, "-m", "compileall", "-q", os.path.join(source, "nfdmatch")], check=True)
        # each version on its own compiled kernels, as `make install` leaves them (a worktree
        # of another commit has none: it would run on slower ones and flatter the new code)
        subprocess.run(
            [sys.executable, "-P", "-c", "from nfdmatch.matching import compile_kernels; compile_kernels()"],
            env=self.env(),
            cwd=source,
            check=True,
        )

    def env(self, **extra):
        env = dict(os.environ, PYTHONPATH=self.source, **extra)
        env.pop("PYTHONDONTWRITEBYTECODE", None)
        return env

    def run(self, args, io_file=None):
        env = self.env()
        env["NFDMATCH_BENCH_IO"] = io_file or os.devnull
        t0 = time.perf_counter()
        proc = subprocess.Popen(
            [sys.executable, "-P", "-c", _MEASURE, "x"] + list(args),
            env=env,
            cwd=self.source,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        out, err = proc.communicate()
        dt = time.perf_counter() - t0
        if proc.returncode != 0:
            raise SystemExit(f"[{self.label}] nfdmatch {' '.join(args)} failed ({proc.returncode}):\n{err}")
        return dt, out, err

    def timed(self, args, repeat):
        times, last = [], None
        for _ in range(repeat):
            dt, out, err = self.run(args)
            times.append(dt)
            last = (out, err)
        return statistics.median(times), min(times), max(times), last


def _peak_rss(version, args):
    """(seconds, peak RSS bytes, stdout) of one process."""
    env = version.env(NFDMATCH_BENCH_IO=os.devnull)
    t0 = time.perf_counter()
    proc = subprocess.Popen(
        [sys.executable, "-P", "-m", "nfdmatch"] + list(args),
        env=env,
        cwd=version.source,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    out = proc.stdout.read()
    err = proc.stderr.read()
    _, status, usage = os.wait4(proc.pid, 0)
    dt = time.perf_counter() - t0
    if os.waitstatus_to_exitcode(status) not in (0, 3):
        raise SystemExit(f"[{version.label}] nfdmatch {' '.join(args)} failed:\n{err}")
    return dt, usage.ru_maxrss * 1024, out


_STATS = re.compile(r"(\d+) queries x (\d+) rows: (\d+) exact distances")


def _exact_per_query(stderr):
    m = _STATS.search(stderr)
    return int(m.group(3)) / int(m.group(1)) if m else float("nan")


def _rows(csv_text):
    lines = csv_text.strip().splitlines()
    header = lines[0].split(",")
    qi, mi, di = header.index("query"), header.index("match"), header.index("distance")
    return [(r.split(",")[qi], r.split(",")[mi], float(r.split(",")[di])) for r in lines[1:]]


def _same(a, b):
    if [(q, m) for q, m, _ in a] == [(q, m) for q, m, _ in b]:
        return "same ids, max |d diff| %.1e" % max((abs(x[2] - y[2]) for x, y in zip(a, b)), default=0.0)
    # ties and float32 rounding may reorder equal distances: compare the distance lists
    da = sorted(round(x[2], 6) for x in a)
    db = sorted(round(x[2], 6) for x in b)
    return "same distances (tie order differs)" if da == db else "DIFFERENT"


def _warm_files(folder):
    """Read every source file once, so that each version's build finds them in the page
    cache (this machine reclaims the cache on its own: the first build would read a cold
    disk and the second a warm cache)."""
    for entry in os.scandir(folder):
        with open(entry.path, "rb") as f:
            while f.read(1 << 24):
                pass


def _warm_index(path):
    with open(path, "rb") as f:
        while f.read(1 << 24):
            pass


def measure(version, work, name, queries, repeat):
    index = os.path.join(work, f"{name}-{version.label}.h5")
    if os.path.exists(index):
        os.unlink(index)
    _warm_files(os.path.join(work, name, "curves"))
    build_t, rss, out = _peak_rss(
        version, ["index", "build", os.path.join(work, name, "curves"), "--index", index, "--format", "json"]
    )
    curves = json.loads(out)["curves"]
    io_file = os.path.join(work, "io.txt")
    _warm_index(index)
    version.run(["query", queries[0], "--index", index, "--top", "10"])  # warm caches and kernels
    single, lo, hi, (out1, err1) = version.timed(
        ["query", queries[0], "--index", index, "--top", "10", "--format", "csv", "--stats"], repeat
    )
    version.run(["query", queries[0], "--index", index, "--top", "10"], io_file=io_file)
    single_bytes = int(open(io_file).read())
    version.run(["--help"], io_file=io_file)
    help_bytes = int(open(io_file).read())
    batch_args = ["query", *queries, "--index", index, "--top", "10", "--format", "csv", "--stats"]
    # as many runs as the single query: a median of two swung 2x between runs here
    batch, _, _, (outb, errb) = version.timed(batch_args, repeat)
    version.run(batch_args, io_file=io_file)
    batch_bytes = int(open(io_file).read())
    return {
        "curves": curves,
        "build": build_t,
        "rss": rss,
        "single": single,
        "single_range": (lo, hi),
        "single_exact": _exact_per_query(err1),
        "batch": batch,
        "batch_exact": _exact_per_query(errb),
        "single_bytes": single_bytes - help_bytes,
        "batch_bytes": (batch_bytes - help_bytes) / QUERIES,
        "rows": _rows(outb),
    }


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--families", type=int, default=20_000, help="families of 50 curves (default 20000: 1M curves)")
    ap.add_argument("--random", type=int, default=100_000, help="unrelated random curves (default 100000)")
    ap.add_argument("--baseline", default=DEFAULT_BASELINE, help="git revision to compare with ('' for none)")
    ap.add_argument("--workdir", default="/tmp/nfdmatch-bench-search")
    ap.add_argument("--repeat", type=int, default=5)
    args = ap.parse_args()
    work = args.workdir
    os.makedirs(work, exist_ok=True)
    t0 = time.perf_counter()
    collections = []
    if args.families:
        name = f"families-{args.families}"
        collections.append((name, generate_families(os.path.join(work, name), args.families)))
    if args.random:
        name = f"random-{args.random}"
        collections.append((name, generate_random(os.path.join(work, name), args.random)))
    print(f"data ready in {time.perf_counter() - t0:.1f} s ({work})", file=sys.stderr)

    versions = [Version("new", ROOT)]
    if args.baseline:
        base = os.path.join(work, "baseline")
        rev = subprocess.run(
            ["git", "-C", ROOT, "rev-parse", args.baseline], capture_output=True, text=True, check=True
        ).stdout.strip()
        have = subprocess.run(["git", "-C", base, "rev-parse", "HEAD"], capture_output=True, text=True).stdout.strip()
        if have != rev:
            subprocess.run(["git", "-C", ROOT, "worktree", "remove", "--force", base], capture_output=True)
            subprocess.run(
                ["git", "-C", ROOT, "worktree", "add", "--detach", base, rev], check=True, capture_output=True
            )
        versions.append(Version("baseline", base))

    help_t = {v.label: v.timed(["--help"], args.repeat)[0] for v in versions}
    results = {}
    for name, queries in collections:
        for v in versions:
            print(f"measuring {name} with {v.label} ...", file=sys.stderr)
            results[name, v.label] = measure(v, work, name, queries, args.repeat)
            results[name, v.label]["help"] = help_t[v.label]

    labels = [v.label for v in versions]
    print("\n`nfdmatch --help`: " + ", ".join(f"{lab} {help_t[lab] * 1e3:.0f} ms" for lab in labels))
    head = "| collection | measure | " + " | ".join(labels) + (" | ratio |" if len(labels) > 1 else " |")
    print(head)
    print("|" + "---|" * (head.count("|") - 1))
    for name, _ in collections:
        r = {lab: results[name, lab] for lab in labels}
        c = f"{name} ({r['new']['curves']:,} curves)"
        rowspec = [
            ("index build", lambda x: f"{x['build']:.1f} s", lambda x: x["build"]),
            ("build peak RSS", lambda x: f"{x['rss'] / 2**30:.2f} GB", lambda x: x["rss"]),
            ("single query, new process", lambda x: f"{x['single'] * 1e3:.0f} ms", lambda x: x["single"]),
            ("single query above --help", lambda x: f"{(x['single'] - x['help']) * 1e3:.0f} ms", None),
            ("exact distances, single query", lambda x: f"{x['single_exact']:.0f}", lambda x: x["single_exact"]),
            ("bytes read, single query", lambda x: f"{x['single_bytes'] / 2**20:.1f} MiB", lambda x: x["single_bytes"]),
            (
                f"batch of {QUERIES}: ms/query above start-up",
                lambda x: f"{(x['batch'] - x['help']) / QUERIES * 1e3:.1f} ms",
                lambda x: x["batch"] - x["help"],
            ),
            ("exact distances per query, batch", lambda x: f"{x['batch_exact']:.0f}", lambda x: x["batch_exact"]),
            (
                "bytes read per query, batch",
                lambda x: f"{x['batch_bytes'] / 2**20:.1f} MiB",
                lambda x: x["batch_bytes"],
            ),
        ]
        for label, fmt, key in rowspec:
            cells = [fmt(r[lab]) for lab in labels]
            ratio = ""
            if len(labels) > 1 and key is not None:
                a, b = key(r["new"]), key(r["baseline"])
                ratio = f"{b / a:.1f}x" if a else ""
            print(f"| {c} | {label} | " + " | ".join(cells) + (f" | {ratio} |" if len(labels) > 1 else " |"))
        if len(labels) > 1:
            print(f"| {c} | answers (20 queries, top 10) | {_same(r['new']['rows'], r['baseline']['rows'])} | | |")
    print("\nratio = baseline / new (above 1: the new code is faster or smaller).")


if __name__ == "__main__":
    main()
