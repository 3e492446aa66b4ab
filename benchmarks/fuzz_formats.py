"""Fuzz the curve readers with seeded mutants of valid files; print outcomes per format.

    python benchmarks/fuzz_formats.py [--mutants 2000] [--seed 1] [--timeout 10]
                                      [--reader nfdmatch|pyvista] [--workdir DIR] [--show 5]

--mutants mutants are spread evenly over the formats (CSV, OBJ, legacy VTK ASCII and
binary, VTP and VTU in ascii, binary, appended raw / base64, zlib inline / appended), each
read in a child process (RLIMIT_AS, a per-file time limit; see tests/fuzzing.py).
Outcomes: error (an NfdError: a clear refusal), accepted (curves), crash (the child
died), hang (no answer within --timeout s), traceback (any other exception). The goal is
0 crash, 0 hang, 0 traceback. ``--reader pyvista`` reads the same mutants with VTK's own
readers (what nfdmatch did before) for comparison; it is meaningful for the VTK formats.
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, "..", "tests"))
import fuzzing  # noqa: E402


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--mutants", type=int, default=2000, help="in all, over every format")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--timeout", type=float, default=10.0, help="seconds per file")
    ap.add_argument("--reader", choices=["nfdmatch", "pyvista"], default="nfdmatch")
    ap.add_argument("--formats", help="comma-separated format labels (default: all)")
    ap.add_argument("--workdir", default="/tmp/nfdmatch-fuzz")
    ap.add_argument("--show", type=int, default=5, help="crash/hang/traceback cases listed")
    args = ap.parse_args()
    shutil.rmtree(args.workdir, ignore_errors=True)
    seeds = fuzzing.seed_files(os.path.join(args.workdir, "seeds"))
    if args.formats:
        wanted = args.formats.split(",")
        seeds = {k: v for k, v in seeds.items() if k in wanted}
    per_format = max(1, args.mutants // len(seeds))
    t0 = time.perf_counter()
    table, details = fuzzing.fuzz(
        seeds,
        os.path.join(args.workdir, "mutants"),
        per_format,
        seed=args.seed,
        timeout=args.timeout,
        reader=args.reader,
    )
    elapsed = time.perf_counter() - t0
    print(f"reader {args.reader}: {per_format} mutants per format, seed {args.seed}, {elapsed:.1f} s")
    print(fuzzing.format_table(table))
    shown = 0
    for rows in details.values():
        for path, result in rows:
            if result["outcome"] in ("crash", "hang", "traceback") and shown < args.show:
                print(
                    f"  {result['outcome']}: {path}: "
                    f"{result.get('detail') or result.get('type', '')} {result.get('message', '')}"
                )
                shown += 1
    bad = sum(t[o] for t in table.values() for o in ("crash", "hang", "traceback"))
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
