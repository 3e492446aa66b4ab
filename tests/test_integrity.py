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


# --------------------------------------------------------------------------- checksums

import shutil  # noqa: E402

import h5py  # noqa: E402
from click.testing import CliRunner  # noqa: E402

from nfdmatch.cli import main  # noqa: E402
from nfdmatch.errors import IndexFormatError  # noqa: E402
from nfdmatch.index import build_index, open_index  # noqa: E402
from nfdmatch.index.verify import verify_index  # noqa: E402

LIBRARY = os.path.join(REPO, "sample_curves", "library")
QUERY = os.path.join(REPO, "sample_curves", "queries", "4_1-control.csv")


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    """A format-2 index of the sample library, with checksums (built once; tests copy it)."""
    path = tmp_path_factory.mktemp("built") / "lib.h5"
    build_index([LIBRARY], str(path), jobs=1)
    return path


@pytest.fixture
def index_copy(built, tmp_path):
    path = tmp_path / "copy.h5"
    shutil.copyfile(built, path)
    return path


def _flip(path, dataset, chunk=0, at=None):
    """Flip one bit in chunk ``chunk`` of ``dataset``; returns the rows that chunk holds."""
    with h5py.File(path, "r") as f:
        ds = f[dataset]
        info = ds.id.get_chunk_info(chunk)
        rows = (info.chunk_offset[0], info.chunk_offset[0] + ds.chunks[0] - 1)
    with open(path, "r+b") as fh:
        fh.seek(info.byte_offset + (info.size // 2 if at is None else at))
        byte = fh.read(1)[0]
        fh.seek(-1, 1)
        fh.write(bytes([byte ^ 0x10]))
    return rows


def _cli(*args):
    result = CliRunner().invoke(main, list(args), catch_exceptions=False)
    return result


def test_a_built_index_checksums_every_dataset(built):
    with h5py.File(built, "r") as f:
        assert f.attrs["checksums"] == "fletcher32+crc32"
        seen = []

        def visit(name, obj):
            if isinstance(obj, h5py.Dataset):
                seen.append(name)
                if obj.dtype.kind == "O":
                    assert f"{name}_crc32" in f, name          # strings: the CRC companion
                else:
                    assert obj.fletcher32, name
        f.visititems(visit)
        assert {"curves/coefficients", "curves/id", "curves/id_crc32", "files/path_crc32", "files/error_crc32",
                "search/features", "search/head"} <= set(seen)
    with open_index(built) as idx:
        assert idx.checksums
    assert verify_index(built).ok


@pytest.mark.parametrize("dataset", ["curves/coefficients", "search/features", "search/head", "search/sqnorm",
                                     "search/row"])
def test_a_flipped_bit_in_what_a_query_reads_is_an_error_not_an_answer(index_copy, dataset):
    first, last = _flip(index_copy, dataset)
    result = _cli("query", QUERY, "--index", str(index_copy), "--top", "30")
    assert result.exit_code == 1, result.stdout
    assert result.stdout == ""
    assert result.stderr.startswith(f"Error: {index_copy}: corrupted nfdmatch index: checksum mismatch in ")
    assert "Traceback" not in result.stderr
    # verify names the dataset and the rows of the damaged chunk
    result = _cli("index", "verify", "--index", str(index_copy))
    assert result.exit_code == 1
    assert f"bad\t/{dataset}\t{first}..{min(last, 23)}\tchecksum mismatch" in result.stdout
    assert result.stderr.startswith("Error: ") and "1 problem found" in result.stderr


def test_a_flipped_bit_in_an_id_is_detected(index_copy):
    # ids live in HDF5's global heap, which no filter covers: their CRC-32 blocks catch it
    with open(index_copy, "rb") as fh:
        data = fh.read()
    target = b"knotess/4_1.csv"
    at = data.index(target)
    with open(index_copy, "r+b") as fh:
        fh.seek(at + len(target) - 5)
        fh.write(b"X")
    result = _cli("query", QUERY, "--index", str(index_copy), "--top", "1")
    assert result.exit_code == 1 and result.stdout == ""
    assert "checksum mismatch in /" in result.stderr
    result = _cli("index", "verify", "--index", str(index_copy))
    assert result.exit_code == 1
    assert "checksum mismatch (CRC-32 of the strings)" in result.stdout


def test_verify_passes_a_sound_index_and_says_format_1_has_no_checksums(built):
    result = _cli("index", "verify", "--index", str(built))
    assert result.exit_code == 0, result.stderr
    assert result.stdout == ""
    assert "ok (" in result.stderr and "every checksum verified" in result.stderr
    v1 = os.path.join(HERE, "data", "index", "v1-sample.h5")
    result = _cli("index", "verify", "--index", v1, "--format", "json")
    assert result.exit_code == 0
    import json
    report = json.loads(result.stdout)
    assert report["ok"] and report["checksums"] is False and report["format_version"] == 1
    assert "has no checksums" in result.stderr


def _rewrite(path, dataset, index, value):
    """Store ``value`` at ``dataset[index]`` through HDF5 (checksums stay valid)."""
    with h5py.File(path, "r+") as f:
        ds = f[dataset]
        data = ds[...]
        data[index] = value
        ds[...] = data


@pytest.mark.parametrize("dataset, index, where", [
    ("curves/coefficients", (5, 1, 2), "/curves/coefficients, row 5"),
    ("search/features", (3, 0), "/search/features, position 3"),
    ("search/sqnorm", (2, 1), "/search/sqnorm, position 2"),
])
def test_a_stored_nan_is_an_index_format_error_naming_dataset_and_row(index_copy, dataset, index, where):
    _rewrite(index_copy, dataset, index, np.nan)
    with open_index(index_copy) as idx:
        with pytest.raises(IndexFormatError, match=f"non-finite value \\(NaN or Inf\\) in {where}"):
            if dataset.startswith("curves"):
                idx.coefficients_at([5])
            else:
                table = idx.search_table()
                table.cell_rows(np.arange(table.n_cells))
    result = _cli("query", QUERY, "--index", str(index_copy), "--top", "30", "--exhaustive"
                  if dataset.startswith("curves") else "--top=30")
    assert result.exit_code == 1 and "non-finite value" in result.stderr and "Traceback" not in result.stderr
    result = _cli("index", "verify", "--index", str(index_copy))
    assert result.exit_code == 1
    assert f"bad\t/{dataset}\t" in result.stdout and "non-finite values" in result.stdout
