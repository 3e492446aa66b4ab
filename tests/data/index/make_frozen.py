"""How the frozen indexes ``tests/data/index/vN-sample.h5`` are made (N = the format version).

Run from the repository root (paths in the index are as given here, relative)::

    .venv/bin/python tests/data/index/make_frozen.py

It indexes four sample curve files (1 + 1 + 2 + 3 curves) and one bad file
(``bad.csv``, recorded as failed) with samples=32, harmonics=4, scale=rms, in one
process, with the clock fixed at 2026-01-01T00:00:00Z. The build runs in a temporary
folder's name at the repository root (so that the ids are the relative paths above; no
lock file is left) and the result is copied next to this script.

For format 2 the search cells are made small (2 rows per cell) so that the file holds
several cells.

Each file is FROZEN: ``tests/test_index.py`` reads it with exact expected ids,
parameters and values, forever. Do not re-run this script to make a failing test
pass: a reader that cannot read this file is a format break (bump ``format_version``
and keep reading the old formats instead). ``v1-sample.h5`` was made by this script at
commit 646aae6 (format 1), ``v2-sample.h5`` at commit e3d24f2 (format 2: last regenerated
while format 2 was unreleased, to carry the checksums: Fletcher-32 chunks and CRC-32 string
blocks); today's code writes format 3 (with /curves/statistics), so running it now makes
``v3-sample.h5``, and ``v3-objects-sample.h5``: ``circle.tsv`` and ``part.off``, a mesh
indexed as an object (a squashed capsule, 21 contours: format 3's optional ``/objects``).
"""

import os
import shutil
import sys
import tempfile

from nfdmatch import index

SOURCES = [
    "sample_curves/library/circle.tsv",
    "sample_curves/library/trefoil.csv",
    "sample_curves/library/superellipses.vtp",
    "sample_curves/library/lissajous-family.obj",
    "tests/data/index/bad.csv",
]
#: format 3's optional /objects: a curve file and a mesh (its contours tied to it)
OBJECT_SOURCES = ["sample_curves/library/circle.tsv", "tests/data/index/part.off"]
TARGET = os.path.join(os.path.dirname(os.path.abspath(__file__)), f"v{index.FORMAT_VERSION}-sample.h5")


def main() -> int:
    if not os.path.isdir("sample_curves/library"):
        print("run from the repository root", file=sys.stderr)
        return 1
    index.commit._utcnow = lambda: "2026-01-01T00:00:00Z"
    from nfdmatch.search import cells

    cells.ROWS_PER_CELL = 2
    # built at the repository root (ids relative to the index's folder: the paths above,
    # on every machine), then moved here with nothing else left behind
    targets = [(SOURCES, TARGET)]
    if index.FORMAT_VERSION >= 3:
        targets.append((OBJECT_SOURCES, TARGET.replace("-sample.h5", "-objects-sample.h5")))
    for sources, target in targets:
        with tempfile.TemporaryDirectory(dir=".") as tmp:
            path = os.path.join(os.path.basename(tmp) + "-" + os.path.basename(target))
            try:
                report = index.build_index(sources, path, samples=32, harmonics=4, scale="rms", jobs=1)
                print(report.curves, "curves;", report.failed, "failed:", report.failures, file=sys.stderr)
                shutil.copyfile(path, target)
            finally:
                for leftover in (path, path + ".lock"):
                    if os.path.exists(leftover):
                        os.remove(leftover)
        print(target)
    return 0


if __name__ == "__main__":
    sys.exit(main())
