"""Ctrl-C / SIGTERM at any moment, as a terminal or `timeout -s INT` delivers them.

    python benchmarks/sigint_trials.py [--mode build|startup|stuck] [--trials 30] [--files 10000]
                                       [--jobs 2] [--workdir /tmp/nfdmatch-small]
                                       [--min-delay 0.5] [--max-delay 3.0]

``--mode build`` (the default), a parallel build:
Builds an index of ``--files`` one-curve CSV files once, then runs ``--trials`` rebuilds
(``nfdmatch index build FOLDER --index I.h5 --rebuild -j JOBS`` in a new session), each
sent SIGINT or SIGTERM (alternating, random order) to its whole process group after a
random delay, and counts per signal: exited within 1 s of the signal, exit codes,
tracebacks on stderr, hangs (no exit 10 s after the signal: the group is then SIGKILLed),
temporary files left, the previous index intact (same bytes), processes of the group left
alive, and builds that finished before the signal came. A signal that comes while Python
is still starting up (importing numpy, before nfdmatch's code runs and takes the lock) gets
Python's own behaviour (SIGINT: a KeyboardInterrupt traceback from the import, SIGTERM:
killed at once); those trials are counted apart ("while starting up"). The build's
process is the watchdog's child (``nfdmatch/cli/start.py``): the lock holds its pid.

``--mode startup``: ``nfdmatch describe`` of one sample curve, signalled ``--min-delay`` to
``--max-delay`` s after it starts (use 0 to 0.3: interpreter start-up, imports, the
command); counts exit codes, stderr lines and tracebacks per delay bucket of 25 ms.
Python's own start-up (before nfdmatch's first line, while ``site`` imports) keeps Python's
behaviour: the first bucket(s) show it.

``--mode startup-grid``: the console script as a user runs it (``--entry script``: the
``nfdmatch`` beside this Python, default; ``--entry module``: ``python -m nfdmatch``) with
``--args`` (default ``--help``), sent SIGINT (``--signal``) to its process group at each
delay from ``--min-delay`` to ``--max-delay`` in steps of ``--step`` (default 0 to 0.15 s by
0.01), ``--runs`` times each; one row per delay: clean ends (exit 130, one line on stderr,
no traceback), other exit codes, tracebacks, finished before the signal. E.g.

    python benchmarks/sigint_trials.py --mode startup-grid --min-delay 0 --max-delay 0.15 --runs 10

``--mode stuck``: a command inside a C call that never returns and holds the GIL (h5py
reading a root attribute of ``tests/data/index/hang-heap-v2.h5`` directly, HDF5's loop of
issue 34), signalled ``--min-delay`` to ``--max-delay`` s after it says it is about to call:
the watchdog must end it (signal-to-exit ~0.8 s).
"""

from __future__ import annotations

import argparse
import collections
import hashlib
import os
import random
import signal
import subprocess
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))
REPO = os.path.normpath(os.path.join(HERE, ".."))
sys.path.insert(0, HERE)
from bench_small_files import generate  # noqa: E402


def _digest(path: str) -> str:
    with open(path, "rb") as fh:
        return hashlib.sha256(fh.read()).hexdigest()


def _group_alive(pgid: int) -> list[int]:
    out = []
    for name in os.listdir("/proc"):
        if not name.isdigit():
            continue
        try:
            fields = open(f"/proc/{name}/stat").read().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[2]) == pgid and fields[0] != "Z":
            out.append(int(name))
    return out


def _parent(pid: int) -> int | None:
    try:
        return int(open(f"/proc/{pid}/stat").read().rsplit(")", 1)[1].split()[1])
    except (OSError, ValueError, IndexError):
        return None


STUCK = """
import sys
from nfdmatch.cli import main

@main.command("stuck")
def stuck():
    import h5py
    f = h5py.File({hang!r}, "r", locking=False)
    print("ready", file=sys.stderr, flush=True)
    f.attrs["format"]  # HDF5 loops here for ever, holding the GIL

from nfdmatch.cli.start import run
run()
"""


def short_trials(args) -> None:
    """``--mode startup`` and ``--mode stuck``: one short command per trial."""
    env = dict(os.environ, PYTHONPATH=REPO)
    os.makedirs(args.workdir, exist_ok=True)
    if args.mode == "startup":
        cmd = [sys.executable, "-m", "nfdmatch", "describe", os.path.join(REPO, "sample_curves/library/circle.tsv")]
    else:
        script = os.path.join(args.workdir, "stuck.py")
        with open(script, "w") as fh:
            fh.write(STUCK.format(hang=os.path.join(REPO, "tests/data/index/hang-heap-v2.h5")))
        cmd = [sys.executable, script, "stuck"]
    rnd = random.Random(args.seed)
    plan = [signal.SIGINT, signal.SIGTERM] * ((args.trials + 1) // 2)
    rnd.shuffle(plan)
    rows = collections.defaultdict(collections.Counter)
    latencies = collections.defaultdict(list)
    for sig in plan[: args.trials]:
        delay = rnd.uniform(args.min_delay, args.max_delay)
        proc = subprocess.Popen(
            cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, start_new_session=True
        )
        if args.mode == "stuck":
            proc.stderr.readline()  # "ready"
        time.sleep(delay)
        sent = time.monotonic()
        os.killpg(proc.pid, sig)
        try:
            _, err = proc.communicate(timeout=10)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            _, err = proc.communicate()
            err += "HANG"
        latency = time.monotonic() - sent
        key = (
            sig.name,
            f"{int(delay / 0.025) * 25:3d}-{int(delay / 0.025) * 25 + 25} ms" if args.mode == "startup" else "",
        )
        c = rows[key]
        c["trials"] += 1
        c["hangs"] += "HANG" in err
        c["within 1 s"] += latency <= 1.0
        c[f"exit {proc.returncode}"] += 1
        c["tracebacks"] += "Traceback" in err or "Fatal Python error" in err
        c["one line"] += len(err.splitlines()) == 1
        latencies[sig.name].append(latency)
        time.sleep(0.02)
        for pid in _group_alive(proc.pid):
            rows[key]["processes left"] += 1
            os.kill(pid, signal.SIGKILL)
    print(
        f"{args.trials} trials, --mode {args.mode}: `{' '.join(cmd[1:])}`, signal after {args.min_delay}-{args.max_delay} s"
    )
    for (name, bucket), c in sorted(rows.items()):
        print(f"{name} {bucket}: " + ", ".join(f"{k} {v}" for k, v in sorted(c.items())))
    for name, lat in sorted(latencies.items()):
        lat.sort()
        print(f"{name}: signal-to-exit median {lat[len(lat) // 2]:.3f} s, worst {lat[-1]:.3f} s")


def startup_grid(args) -> None:
    """``--mode startup-grid``: a signal at fixed delays after the program starts, per delay
    the ends counted."""
    sig = signal.Signals[args.signal]
    code = 143 if sig == signal.SIGTERM else 130
    if args.entry == "script":
        cmd = [os.path.join(os.path.dirname(sys.executable), "nfdmatch")]
    else:
        cmd = [sys.executable, "-m", "nfdmatch"]
    cmd += args.args.split()
    steps = int(round((args.max_delay - args.min_delay) / args.step)) + 1
    delays = [args.min_delay + i * args.step for i in range(steps)]
    print(
        f"`{' '.join(os.path.basename(c) if i == 0 else c for i, c in enumerate(cmd))}`, {sig.name} to its process group, {args.runs} runs per delay"
    )
    print(
        f"{'delay s':>8} {'clean':>6} {'tracebacks':>10} {'in site':>8} {'after site':>10} {'finished':>8}  other ends"
    )
    totals = collections.Counter()
    for delay in delays:
        c = collections.Counter()
        for _ in range(args.runs):
            proc = subprocess.Popen(
                cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, start_new_session=True
            )
            time.sleep(delay)
            finished = proc.poll() is not None
            if not finished:
                os.killpg(proc.pid, sig)
            try:
                _, err = proc.communicate(timeout=10)
            except subprocess.TimeoutExpired:
                os.killpg(proc.pid, signal.SIGKILL)
                _, err = proc.communicate()
                err += "HANG"
            traceback = "Traceback" in err or "Fatal Python error" in err
            # Python's own start-up (the site module, .pth files) or later (the console
            # script and what it imports before nfdmatch holds the signals)
            c["in site" if "init_import_site" in err else "after site"] += traceback
            if finished:
                c["finished"] += 1
            elif proc.returncode == code and len(err.splitlines()) == 1 and not traceback:
                c["clean"] += 1
            else:
                c[
                    f"exit {proc.returncode}"
                    + (" + traceback" if traceback else "")
                    + (" HANG" if "HANG" in err else "")
                ] += 1
            c["tracebacks"] += traceback
        totals.update(c)
        other = ", ".join(f"{k}: {v}" for k, v in sorted(c.items()) if k.startswith("exit"))
        print(
            f"{delay:8.4g} {c['clean']:6d} {c['tracebacks']:10d} {c['in site']:8d} {c['after site']:10d} "
            f"{c['finished']:8d}  {other or '-'}"
        )
    other = ", ".join(f"{k}: {v}" for k, v in sorted(totals.items()) if k.startswith("exit"))
    print(
        f"{'all':>8} {totals['clean']:6d} {totals['tracebacks']:10d} {totals['in site']:8d} {totals['after site']:10d} "
        f"{totals['finished']:8d}  {other or '-'}  (of {len(delays) * args.runs})"
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--mode", choices=("build", "startup", "startup-grid", "stuck"), default="build")
    ap.add_argument("--entry", choices=("script", "module"), default="script", help="startup-grid: what to start.")
    ap.add_argument("--args", default="--help", help="startup-grid: the command's arguments.")
    ap.add_argument("--step", type=float, default=0.01, help="startup-grid: seconds between delays.")
    ap.add_argument("--runs", type=int, default=5, help="startup-grid: runs per delay.")
    ap.add_argument("--signal", choices=("SIGINT", "SIGTERM"), default="SIGINT", help="startup-grid: the signal.")
    ap.add_argument("--trials", type=int, default=30)
    ap.add_argument("--files", type=int, default=10000)
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--workdir", default="/tmp/nfdmatch-small")
    ap.add_argument(
        "--min-delay",
        type=float,
        default=None,
        help="Earliest signal (s after start; before ~0.4 s the interpreter is still importing) "
        "[default: 0.5; startup-grid: 0].",
    )
    ap.add_argument("--max-delay", type=float, default=None, help="[default: 3.0; startup-grid: 0.15]")
    ap.add_argument("--seed", type=int, default=20261201)
    args = ap.parse_args()
    grid = args.mode == "startup-grid"
    args.min_delay = (0.0 if grid else 0.5) if args.min_delay is None else args.min_delay
    args.max_delay = (0.15 if grid else 3.0) if args.max_delay is None else args.max_delay
    if grid:
        return startup_grid(args)
    if args.mode != "build":
        return short_trials(args)
    folder = os.path.join(args.workdir, f"{args.files}-csv")
    generate(folder, args.files, "csv", 0)
    work = os.path.join(args.workdir, "sigint")
    os.makedirs(work, exist_ok=True)
    index = os.path.join(work, "idx.h5")
    env = dict(os.environ, PYTHONPATH=REPO)
    cmd = [sys.executable, "-m", "nfdmatch", "index", "build", folder, "--index", index, "-j", str(args.jobs)]
    subprocess.run(cmd + ["-q"], env=env, check=True)
    original = _digest(index)
    rnd = random.Random(args.seed)
    plan = [signal.SIGINT, signal.SIGTERM] * ((args.trials + 1) // 2)
    rnd.shuffle(plan)
    counts: dict = collections.defaultdict(collections.Counter)
    latencies = collections.defaultdict(list)
    for sig in plan[: args.trials]:
        c = counts[sig.name]
        c["trials"] += 1
        delay = rnd.uniform(args.min_delay, args.max_delay)
        proc = subprocess.Popen(
            cmd + ["--rebuild"],
            env=env,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
            text=True,
            start_new_session=True,
        )
        time.sleep(delay)
        if proc.poll() is not None:
            c["finished before the signal"] += 1
            proc.communicate()
            original = _digest(index)  # a finished rebuild is the new "previous index"
            continue
        try:  # the build writes its pid into the lock file once it runs (imports done, lock held)
            holder = int(open(index + ".lock").read().strip() or 0)
            started = holder == proc.pid or _parent(holder) == proc.pid  # the watchdog's child
        except (OSError, ValueError):
            started = False
        if not started:
            c["signalled while starting up"] += 1
        sent = time.monotonic()
        os.killpg(proc.pid, sig)
        try:
            _, err = proc.communicate(timeout=10)
        except subprocess.TimeoutExpired:
            c["hangs"] += 1
            os.killpg(proc.pid, signal.SIGKILL)
            _, err = proc.communicate()
        latency = time.monotonic() - sent
        latencies[sig.name].append(latency)
        c["exited within 1 s"] += latency <= 1.0
        c[f"exit {proc.returncode}"] += 1
        c["tracebacks"] += "Traceback" in err
        if not started:
            c["tracebacks while starting up"] += "Traceback" in err
        time.sleep(0.05)
        left = _group_alive(proc.pid)
        c["processes left"] += len(left)
        for pid in left:
            os.kill(pid, signal.SIGKILL)
        temps = [n for n in os.listdir(work) if ".tmp-" in n]
        c["temp files left"] += len(temps)
        for n in temps:
            os.remove(os.path.join(work, n))
        c["index intact"] += _digest(index) == original
    print(
        f"{args.trials} trials: `{' '.join(os.path.basename(a) if a == sys.executable else a for a in cmd)} "
        f"--rebuild` over {args.files} one-curve CSV files, signal after {args.min_delay}-{args.max_delay} s"
    )
    keys = [
        "trials",
        "finished before the signal",
        "signalled while starting up",
        "exited within 1 s",
        "hangs",
        "tracebacks",
        "tracebacks while starting up",
        "temp files left",
        "processes left",
        "index intact",
    ]
    for name, c in sorted(counts.items()):
        exits = ", ".join(f"{k}: {v}" for k, v in sorted(c.items()) if k.startswith("exit "))
        lat = sorted(latencies[name])
        worst = f"{lat[-1]:.2f}" if lat else "-"
        median = f"{lat[len(lat) // 2]:.2f}" if lat else "-"
        print(
            f"{name}: " + ", ".join(f"{k} {c[k]}" for k in keys) + f"; {exits}; "
            f"signal-to-exit median {median} s, worst {worst} s"
        )


if __name__ == "__main__":
    main()
