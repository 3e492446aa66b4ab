"""Index integrity and numeric faults (issue 9): checksums, non-finite values, crafted
indexes, `index verify`, cut error messages, huge coordinates, byte-identical queries."""

from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import pytest

from oracle import random_smooth_curve

from nfdmatch import Curve, write_curves

HERE = os.path.dirname(os.path.abspath(__file__))
REPO = os.path.dirname(HERE)


def _run(args, env=None, **kw):
    full = dict(os.environ, PYTHONPATH=REPO + os.pathsep + os.environ.get("PYTHONPATH", ""), **(env or {}))
    return subprocess.run([sys.executable, "-m", "nfdmatch"] + list(args), env=full, capture_output=True,
                          timeout=600, **kw)


# --------------------------------------------------------------------------- determinism

@pytest.fixture(scope="module")
def random_index(tmp_path_factory):
    """An index of 3,000 random curves and 4 noisy re-posed queries of stored ones."""
    from nfdmatch.index import build_index

    rng = np.random.default_rng(9)
    folder = tmp_path_factory.mktemp("random")
    curves = [Curve(random_smooth_curve(rng, 40, 5), id=f"c{i}") for i in range(3000)]
    write_curves(folder / "lib.obj", curves)
    qdir = folder / "queries"
    qdir.mkdir()
    for i in range(4):
        pts = curves[i * 700].points
        pts = pts @ np.linalg.qr(rng.standard_normal((3, 3)))[0] + rng.normal(size=pts.shape) * 0.01
        write_curves(qdir / f"q{i}.csv", pts)
    build_index([str(folder / "lib.obj")], str(folder / "lib.h5"), jobs=1)
    return folder


def test_query_output_is_byte_identical_run_to_run(random_index):
    """Fresh processes, the compiled kernels forced on, off and left to decide (which path a
    row takes then depends on timing): the same bytes every time."""
    args = ["query", str(random_index / "queries"), "--index", str(random_index / "lib.h5"), "--top", "10",
            "--details"]
    outputs = []
    for mode in ("0", "1", "auto", "auto", "auto"):
        proc = _run(args, env={"NFDMATCH_NUMBA": mode})
        assert proc.returncode == 0, proc.stderr.decode()
        outputs.append(proc.stdout)
    assert len(outputs[0].splitlines()) == 1 + 4 * 10
    assert all(out == outputs[0] for out in outputs), [out.decode().splitlines()[:3] for out in outputs]
