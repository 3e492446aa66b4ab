"""What the index checksums cost: build and query time with and without them, side by side.

    python benchmarks/bench_checksums.py [--curves 100000] [--workdir /tmp/nfdmatch-bench-checksums]
                                         [--repeat 5] [--flips 200]

The collection is bench_search.py's **random** one (unrelated random smooth curves, 48
vertices, 20 OBJ files; cached in the work folder), or with ``--collection families`` its
families of 50 noisy re-posed members (a query then reads only a few cells). Two indexes are built from it in this
process, one as nfdmatch writes it (Fletcher-32 on every numeric chunk, CRC-32 per 32
strings) and one with the checksums switched off (the filter dropped, no CRC datasets, no
``checksums`` attribute: what an older writer made). Printed: build seconds (dominated by parsing the curve
files, which varies with the machine's load) and, for the write alone, the median time of an
incremental build after touching one file (every other row copied into a new file); file size
of each; the median time of one query (open the index, search top 10, read the ids; in
this process, after one warm-up, the two indexes alternating) and of a batch of 20 queries;
`index verify` seconds.

``--flips N`` then flips N random single bits in the data chunks of the checksummed index
(each on a fresh copy) and counts by outcome: detected when opened, detected by the query,
same answer (bit in a part the query did not read), answer changed silently (must be 0);
then N flips anywhere in the file (metadata, string heaps, free space included).
"""

from __future__ import annotations

import argparse
import os
import shutil
import statistics
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)
sys.path.insert(0, os.path.dirname(HERE))

import bench_search  # noqa: E402

import nfdmatch  # noqa: E402
from nfdmatch.errors import NfdError  # noqa: E402
from nfdmatch.index import build_index, open_index  # noqa: E402
from nfdmatch.index import schema, search_group  # noqa: E402
from nfdmatch.search import search_index  # noqa: E402


class _NoChecksums:
    """Within: index writes without any checksum (patched in this process only)."""

    def __enter__(self):
        import h5py

        self.saved = (h5py.Group.create_dataset, search_group._finish_checksums, schema.write_string_checks)
        real = h5py.Group.create_dataset

        def create_dataset(group, name, *args, **kwargs):
            kwargs.pop("fletcher32", None)
            return real(group, name, *args, **kwargs)

        h5py.Group.create_dataset = create_dataset
        search_group._finish_checksums = lambda h5: None
        schema.write_string_checks = lambda *a, **k: None
        return self

    def __exit__(self, *exc):
        import h5py

        h5py.Group.create_dataset, search_group._finish_checksums, schema.write_string_checks = self.saved


def _build(sources, path):
    if os.path.exists(path):
        os.unlink(path)
    t0 = time.perf_counter()
    build_index(sources, path, jobs=2, rebuild=True)
    return time.perf_counter() - t0


def _answer(path, curves):
    with open_index(path) as idx:
        results, _ = search_index(idx, curves, top=10)
    return [[(r.id, r.distance) for r in res] for res in results]


def _flips(path, query, count, workdir, seed=5, anywhere=False):
    import h5py

    rng = np.random.default_rng(seed)
    reference = _answer(path, [query])
    chunks = []
    with h5py.File(path, "r") as f:

        def visit(name, obj):
            if isinstance(obj, h5py.Dataset) and obj.chunks is not None:
                for i in range(obj.id.get_num_chunks()):
                    info = obj.id.get_chunk_info(i)
                    chunks.append((name, info.byte_offset, info.size))

        f.visititems(visit)
    sizes = np.array([c[2] for c in chunks], dtype=np.float64)
    outcomes = {"detected on open": 0, "detected by the query": 0, "same answer": 0, "changed silently": 0}
    copy = os.path.join(workdir, "flipped.h5")
    file_size = os.path.getsize(path)
    for _ in range(count):
        if anywhere:  # metadata, heaps and free space too
            at = int(rng.integers(file_size))
        else:
            name, offset, size = chunks[rng.choice(len(chunks), p=sizes / sizes.sum())]
            at = offset + int(rng.integers(size))
        shutil.copyfile(path, copy)
        with open(copy, "r+b") as fh:
            fh.seek(at)
            byte = fh.read(1)[0]
            fh.seek(at)
            fh.write(bytes([byte ^ (1 << int(rng.integers(8)))]))
        try:
            idx = open_index(copy)
        except NfdError:
            outcomes["detected on open"] += 1
            continue
        try:
            with idx:
                results, _ = search_index(idx, [query], top=10)
            got = [[(r.id, r.distance) for r in res] for res in results]
        except NfdError:
            outcomes["detected by the query"] += 1
            continue
        outcomes["same answer" if got == reference else "changed silently"] += 1
    return outcomes


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--curves", type=int, default=100_000)
    ap.add_argument("--workdir", default="/tmp/nfdmatch-bench-checksums")
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--flips", type=int, default=200)
    ap.add_argument(
        "--collection",
        choices=("random", "families"),
        default="random",
        help="bench_search.py's collection: random (loose bounds: a query reads most of the "
        "index) or families of 50 (tight bounds: a query reads a few cells)",
    )
    args = ap.parse_args(argv)
    folder = os.path.join(args.workdir, f"{args.collection}-{args.curves}")
    if args.collection == "random":
        queries = bench_search.generate_random(folder, args.curves)
    else:
        queries = bench_search.generate_families(folder, max(1, args.curves // 50))
    sources = [os.path.join(folder, "curves")]
    curves = [nfdmatch.read_curve(q) for q in queries]
    plain, checked = (os.path.join(args.workdir, f"{args.collection}-{kind}.h5") for kind in ("plain", "checked"))
    with _NoChecksums():
        t_plain = _build(sources, plain)
    t_checked = _build(sources, checked)
    with open_index(plain) as a, open_index(checked) as b:
        assert not a.checksums and b.checksums
    print(f"{args.curves} curves ({args.collection}), nfdmatch {nfdmatch.__version__}")
    print(f"{'':24}{'no checksums':>16}{'checksums':>16}{'ratio':>8}")
    print(f"{'build (s)':24}{t_plain:16.2f}{t_checked:16.2f}{t_checked / t_plain:8.3f}")
    # the write itself, without the parsing (which dominates a full build and varies with the
    # machine's load): touch one file, so an incremental build copies every other row into a
    # new file (read, check, write, search cells); interleaved, median of --repeat
    touched = os.path.join(sources[0], sorted(os.listdir(sources[0]))[0])
    rewrite = {plain: [], checked: []}
    for _i in range(args.repeat):
        for path in (plain, checked):
            st = os.stat(touched)
            os.utime(touched, ns=(st.st_atime_ns, st.st_mtime_ns + 1_000_000_000))
            t0 = time.perf_counter()
            if path == plain:
                with _NoChecksums():
                    build_index(sources, path, jobs=1)
            else:
                build_index(sources, path, jobs=1)
            rewrite[path].append(time.perf_counter() - t0)
    wp, wc = statistics.median(rewrite[plain]), statistics.median(rewrite[checked])
    print(f"{'rewrite, 1 file new (s)':24}{wp:16.2f}{wc:16.2f}{wc / wp:8.3f}")
    sp, sc = os.path.getsize(plain), os.path.getsize(checked)
    print(f"{'file size (MB)':24}{sp / 1e6:16.2f}{sc / 1e6:16.2f}{sc / sp:8.3f}")
    for label, batch in (("1 query (ms)", curves[:1]), ("20 queries (ms/query)", curves)):
        _answer(plain, batch), _answer(checked, batch)  # warm-up
        times = {plain: [], checked: []}
        for _ in range(args.repeat):  # interleaved: same conditions
            for path in (plain, checked):
                t0 = time.perf_counter()
                _answer(path, batch)
                times[path].append(time.perf_counter() - t0)
        tp, tc = (statistics.median(times[p]) * 1e3 / len(batch) for p in (plain, checked))
        print(f"{label:24}{tp:16.2f}{tc:16.2f}{tc / tp:8.3f}")
    assert _answer(plain, curves) == _answer(checked, curves), "the checksums changed an answer"
    from nfdmatch.index.verify import verify_index

    t0 = time.perf_counter()
    report = verify_index(checked)
    print(f"{'index verify (s)':24}{'':16}{time.perf_counter() - t0:16.2f}   ok={report.ok}")
    if args.flips:
        for anywhere in (False, True):
            outcomes = _flips(checked, curves[0], args.flips, args.workdir, anywhere=anywhere)
            print(
                f"{args.flips} random bit flips {'anywhere in the file' if anywhere else 'in data chunks'}: "
                + ", ".join(f"{k} {v}" for k, v in outcomes.items())
            )
    return 0


if __name__ == "__main__":
    sys.exit(main())
