"""Fuzz the index reader with seeded damage to a whole index file; print the outcomes.

    python benchmarks/fuzz_index.py [--tries 2000] [--seed 1] [--timeout 60]
                                    [--index FILE] [--graph K] [--workdir DIR] [--show 5]
                                    [--sweep [--stride S]]

The index (default: the sample library, ``sample_curves/library``, built into
``--workdir``; with ``--graph K`` built with ``index build --graph K``) is damaged ``--tries`` times, each time afresh from the intact file, by one of:

* ``bit``: one bit flipped at a uniform offset of the whole file;
* ``byte``: one byte replaced by a different random value, uniform over the whole file;
* ``meta-bit`` / ``meta-byte``: the same at an offset outside every dataset's stored
  values (the superblock, object headers, chunk indexes, heaps: HDF5's metadata);
* ``run``: 1 to 16 consecutive bytes set to random values at a uniform offset.

With ``--sweep`` the tries are instead every ``--stride``-th metadata byte in turn (all of
them with ``--stride 1``), each XORed with a seeded random non-zero value (``sweep``).

Each damaged file is then read by ``nfdmatch query`` (three queries, ``--top 5``; with
``--graph``, each also with ``--rerank``) and by ``nfdmatch index verify``, in a forked
child killed after ``--timeout`` seconds (a crash is a signal, a hang a kill, not a lost
run), with click's test runner, so exit codes and both streams are seen as a shell would
see them. (The hang of issue 34, a flipped size in an HDF5 global heap collection, came
from ``--kinds byte --seed 3``: 400 tries, try 315 = byte 5456 XOR 97 of that build.)
Outcomes per try:

* ``same``: every query answers exactly as on the intact file (exit 0, same stdout);
* ``refused``: a query stops with a clear ``Error:`` (exit 2, no traceback: the exit codes
  of issue 40, 0 found, 1 nothing matched, 2 error, 3 partial);
* ``different, verify caught``: a query answers differently with exit 0, and verify
  reports the damage (exit 1);
* ``SILENT``: a query answers differently with exit 0 and verify says the index is sound;
* ``crash``: a child died by a signal, printed a traceback, or exited otherwise;
* ``hang``: no answer within ``--timeout`` seconds.

The last line sums them up as the issue counts them: hangs, crashes, silent answers (SILENT),
clear errors (refused, and different but caught by verify).

Also counted: verify's verdict (``verify: sound`` / ``verify: damaged``) on the tries whose
query answered the same (damage that changed no answer, e.g. in an unused attribute). Goal:
0 SILENT, 0 crash, 0 hang.
"""

from __future__ import annotations

import argparse
import os
import random
import shutil
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
sys.path.insert(0, os.path.join(ROOT, "tests"))
from fuzzing import in_child, metadata_offsets, value_ranges  # noqa: E402

QUERIES = ("trefoil-posed.obj", "ellipse-posed.csv", "4_1-control.csv")
KINDS = ("bit", "byte", "meta-bit", "meta-byte", "run")


def run_cli(*args):
    from click.testing import CliRunner

    from nfdmatch.cli import main

    result = CliRunner().invoke(main, [str(a) for a in args], catch_exceptions=True)
    tb = None
    if result.exception is not None and not isinstance(result.exception, SystemExit):
        import traceback

        tb = "".join(traceback.format_exception(result.exception))[-2000:]
    return result.exit_code, result.stdout, result.stderr, tb


def queries_of(workdir: str) -> list[str]:
    folder = os.path.join(workdir, "sample_curves", "queries")
    have = sorted(os.listdir(folder))
    return [os.path.join(folder, q) for q in QUERIES if q in have] or [os.path.join(folder, have[0])]


def answer(index: str, queries: list[str], rerank: bool = False) -> dict:
    out = {"query": [], "verify": None}
    for q in queries:
        out["query"].append(run_cli("query", q, "--index", index, "--top", 5, "--format", "csv"))
        if rerank:
            out["query"].append(run_cli("query", q, "--index", index, "--top", 5, "--format", "csv", "--rerank"))
    out["verify"] = run_cli("index", "verify", "--index", index)
    return out


def _has_graph(path: str) -> bool:
    import h5py

    with h5py.File(path, "r", locking=False) as f:
        return "graph" in f


def mutate(data: bytes, kind: str, rng: random.Random, meta: list[int]) -> tuple[bytearray, str]:
    out = bytearray(data)
    if kind in ("bit", "meta-bit"):
        at = rng.choice(meta) if kind == "meta-bit" else rng.randrange(len(out))
        bit = rng.randrange(8)
        out[at] ^= 1 << bit
        return out, f"{kind} at {at} bit {bit}"
    if kind in ("byte", "meta-byte"):
        at = rng.choice(meta) if kind == "meta-byte" else rng.randrange(len(out))
        xor = rng.randrange(1, 256)
        out[at] ^= xor
        return out, f"{kind} at {at} xor 0x{xor:02x}"
    n = rng.randint(1, 16)
    at = rng.randrange(len(out) - n)
    for i in range(n):
        out[at + i] = rng.randrange(256)
    return out, f"run of {n} at {at}"


def classify(ref: dict, got) -> str:
    status, value = got
    if status == "hang":
        return "hang"
    if status != "ok":
        return "crash"
    runs = value["query"] + [value["verify"]]
    if any(tb is not None for *_, tb in runs):
        return "crash"
    if any(code not in (0, 1, 2, 3) for code, *_ in runs):
        return "crash"
    for code, _, err, _ in runs:
        if code == 2 and "Error:" not in err:
            return "crash"  # a failure without our words
    verify_code = value["verify"][0]
    differs = False
    for (rcode, rout, _, _), (code, out, _, _) in zip(ref["query"], value["query"]):
        if code != 2 and (code != rcode or out != rout):  # an answer, or none, without an error
            differs = True
    if differs:
        return "different, verify caught" if verify_code in (1, 2) else "SILENT"
    if any(code != 0 for code, *_ in value["query"]):
        return "refused"
    return "same"


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--tries", type=int, default=2000)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--timeout", type=float, default=60.0, help="seconds per try (queries and verify)")
    ap.add_argument("--index", help="an index to damage (default: the sample library, built here)")
    ap.add_argument(
        "--graph", type=int, default=0, help="build the sample index with --graph K (queries also --rerank)"
    )
    ap.add_argument("--kinds", default=",".join(KINDS), help=f"comma-separated, of {', '.join(KINDS)}")
    ap.add_argument("--workdir", default="/tmp/nfdmatch-fuzz-index")
    ap.add_argument("--show", type=int, default=5, help="SILENT/crash/hang cases listed")
    ap.add_argument("--sweep", action="store_true", help="flip every --stride-th metadata byte instead")
    ap.add_argument("--stride", type=int, default=1)
    args = ap.parse_args()
    kinds = ["sweep"] if args.sweep else args.kinds.split(",")
    import nfdmatch.cli  # noqa: F401 - imported once, before the children fork: each try runs the same code

    shutil.rmtree(args.workdir, ignore_errors=True)
    os.makedirs(args.workdir)
    shutil.copytree(os.path.join(ROOT, "sample_curves"), os.path.join(args.workdir, "sample_curves"))
    os.chdir(args.workdir)  # ids relative to the index's folder, as a user would build it
    intact = os.path.join(args.workdir, "intact.h5")
    if args.index:
        shutil.copyfile(args.index, intact)
    else:
        graph = ["--graph", args.graph] if args.graph else []
        status, built = in_child(
            lambda: run_cli("index", "build", "sample_curves/library", "--index", intact, *graph), 600
        )
        if status != "ok" or built[0] != 0:
            sys.exit(f"cannot build the sample index: {status} {built}")
    queries = queries_of(args.workdir)
    with open(intact, "rb") as fh:
        data = fh.read()
    rerank = bool(args.graph) or _has_graph(intact)
    status, ref = in_child(lambda: answer(intact, queries, rerank), args.timeout)
    if status != "ok" or any(code != 0 for code, *_ in ref["query"]) or ref["verify"][0] != 0:
        sys.exit(f"the intact index does not answer: {status} {ref}")
    meta = metadata_offsets(len(data), value_ranges(intact))
    print(
        f"index {args.index or 'sample library'}: {len(data)} bytes, {len(meta)} of them metadata; "
        f"{len(queries)} queries{' (and --rerank)' if rerank else ''} + verify per try; seed {args.seed}",
        file=sys.stderr,
    )
    rng = random.Random(args.seed)
    sweep = meta[:: max(1, args.stride)] if args.sweep else None
    if sweep is not None:
        args.tries = len(sweep)
    damaged = os.path.join(args.workdir, "damaged.h5")
    table: dict[str, dict[str, int]] = {k: {} for k in kinds}
    sound_same: dict[str, int] = {k: 0 for k in kinds}
    bad_cases = []
    t0 = time.perf_counter()
    for i in range(args.tries):
        kind = kinds[i % len(kinds)]
        if sweep is not None:
            mutant, xor = bytearray(data), rng.randrange(1, 256)
            mutant[sweep[i]] ^= xor
            how = f"sweep at {sweep[i]} xor 0x{xor:02x}"
        else:
            mutant, how = mutate(data, kind, rng, meta)
        with open(damaged, "wb") as fh:
            fh.write(mutant)
        got = in_child(lambda: answer(damaged, queries, rerank), args.timeout)
        outcome = classify(ref, got)
        table[kind][outcome] = table[kind].get(outcome, 0) + 1
        if outcome == "same" and got[1]["verify"][0] == 0:
            sound_same[kind] += 1
        if outcome in ("SILENT", "crash", "hang"):
            keep = os.path.join(args.workdir, f"case-{i:05d}.h5")
            shutil.copyfile(damaged, keep)
            bad_cases.append((outcome, how, keep, got))
        if (i + 1) % 200 == 0:
            print(f"  {i + 1} tries, {time.perf_counter() - t0:.0f} s", file=sys.stderr)
    outcomes = ["same", "refused", "different, verify caught", "SILENT", "crash", "hang"]
    width = max(len(o) for o in outcomes)
    print(f"{'damage':<10} {'tries':>6} " + " ".join(f"{o:>{width}}" for o in outcomes) + "  same+verify sound")
    totals = dict.fromkeys(outcomes, 0)
    for kind in kinds:
        row = table[kind]
        n = sum(row.values())
        for o in outcomes:
            totals[o] += row.get(o, 0)
        print(
            f"{kind:<10} {n:>6} "
            + " ".join(f"{row.get(o, 0):>{width}}" for o in outcomes)
            + f"  {sound_same[kind]:>17}"
        )
    print(
        f"{'all':<10} {args.tries:>6} "
        + " ".join(f"{totals[o]:>{width}}" for o in outcomes)
        + f"  {sum(sound_same.values()):>17}"
    )
    print(
        f"hangs {totals['hang']}, crashes {totals['crash']}, silent {totals['SILENT']}, "
        f"clear errors {totals['refused'] + totals['different, verify caught']} "
        f"(of which verify only {totals['different, verify caught']}), same {totals['same']}"
    )
    print(f"{time.perf_counter() - t0:.0f} s", file=sys.stderr)
    for outcome, how, keep, got in bad_cases[: args.show]:
        print(f"{outcome}: {how} ({keep}): {str(got)[:1500]}", file=sys.stderr)
    sys.exit(1 if bad_cases else 0)


if __name__ == "__main__":
    main()
