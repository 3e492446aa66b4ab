"""Index integrity and numeric faults (issue 9): checksums, non-finite values, crafted
indexes, `index verify`, cut error messages, huge coordinates, byte-identical queries."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys

from types import SimpleNamespace

import h5py
import numpy as np
import pytest

from conftest import run_cli
from oracle import random_smooth_curve

from nfdmatch import Curve, write_curves
from nfdmatch.errors import IndexFormatError
from nfdmatch.index import build_index, open_index
from nfdmatch.index.verify import verify_index

#: end-to-end as a whole (subprocesses, real files, pools): left out by `make test-fast`
pytestmark = pytest.mark.slow

HERE = os.path.dirname(os.path.abspath(__file__))
REPO = os.path.dirname(HERE)


def _run(args, env=None, **kw):
    full = dict(os.environ, PYTHONPATH=REPO + os.pathsep + os.environ.get("PYTHONPATH", ""), **(env or {}))
    return subprocess.run(
        [sys.executable, "-m", "nfdmatch"] + list(args), env=full, capture_output=True, timeout=600, **kw
    )


# --------------------------------------------------------------------------- determinism


@pytest.fixture(scope="module")
def random_index(tmp_path_factory):
    """An index of 3,000 random curves and 4 noisy re-posed queries of stored ones."""
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
    """Fresh processes on one kind of kernels (ahead of time, numba, numpy, the rule's
    choice) print the same bytes every time; the kinds agree on every row, and on every
    distance to ~1e-15 (the printed digits are the kernels' own: issue 8)."""
    args = ["query", str(random_index / "queries"), "--index", str(random_index / "lib.h5"), "--top", "10", "--details"]
    outputs = {}
    for mode in ("numpy", "numba", "aot", "auto", "numpy", "numba", "aot", "auto"):
        proc = _run(args, env={"NFDMATCH_KERNELS": mode})
        assert proc.returncode == 0, proc.stderr.decode()
        assert outputs.setdefault(mode, proc.stdout) == proc.stdout, mode
    rows = {mode: [line.split(",") for line in out.decode().splitlines()] for mode, out in outputs.items()}
    reference = rows["numpy"]
    assert len(reference) == 1 + 4 * 10
    column = reference[0].index("distance")
    for mode, got in rows.items():
        assert [r[:column] for r in got] == [r[:column] for r in reference], mode
        distances = np.array([float(r[column]) for r in got[1:]])
        expected = np.array([float(r[column]) for r in reference[1:]])
        np.testing.assert_allclose(distances, expected, rtol=1e-12, atol=1e-13, err_msg=mode)


# --------------------------------------------------------------------------- checksums

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
    """run_cli's answer with the names of click's result (exit_code, stdout, stderr)."""
    code, out, err = run_cli(*args)
    return SimpleNamespace(exit_code=code, stdout=out, stderr=err)


def test_a_built_index_checksums_every_dataset(built):
    with h5py.File(built, "r") as f:
        assert f.attrs["checksums"].decode() == "fletcher32+crc32"  # fixed-length: h5py gives bytes
        seen = []

        def visit(name, obj):
            if isinstance(obj, h5py.Dataset):
                seen.append(name)
                if obj.dtype.kind == "O":
                    assert f"{name}_crc32" in f, name  # strings: the CRC companion
                else:
                    assert obj.fletcher32, name

        f.visititems(visit)
        assert {
            "curves/coefficients",
            "curves/id",
            "curves/id_crc32",
            "files/path_crc32",
            "files/error_crc32",
            "search/features",
            "search/coefficients",
            "sources/path_crc32",
        } <= set(seen)
    with open_index(built) as idx:
        assert idx.checksums
    assert verify_index(built).ok


@pytest.mark.parametrize("dataset", ["curves/coefficients", "search/sqnorm"])
def test_a_flipped_bit_in_what_a_query_does_not_read_leaves_its_answer_and_verify_finds_it(built, index_copy, dataset):
    # a format-2 query reads /search only (the squared norms recomputed from the features,
    # the reported distances from the cells' descriptors): the damage cannot reach an answer
    expect = _cli("query", QUERY, "--index", str(built), "--top", "30", "--format", "csv")
    first, last = _flip(index_copy, dataset)
    result = _cli("query", QUERY, "--index", str(index_copy), "--top", "30", "--format", "csv")
    assert result.exit_code == 0 and result.stdout == expect.stdout
    result = _cli("index", "verify", "--index", str(index_copy))
    assert result.exit_code == 1
    assert f"bad\t/{dataset}\t{first}..{min(last, 23)}\tchecksum mismatch" in result.stdout


@pytest.mark.parametrize("dataset", ["search/features", "search/coefficients", "search/row"])
def test_a_flipped_bit_in_what_a_query_reads_is_an_error_not_an_answer(index_copy, dataset):
    first, last = _flip(index_copy, dataset)
    result = _cli("query", QUERY, "--index", str(index_copy), "--top", "30")
    assert result.exit_code == 2, result.stdout
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
    assert result.exit_code == 2 and result.stdout == ""
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


@pytest.mark.parametrize(
    "dataset, index, where",
    [
        ("curves/coefficients", (5, 1, 2), "/curves/coefficients, row 5"),
        ("search/features", (3, 0), "/search/features, position 3"),
        ("search/coefficients", (2, 1, 0), "/search/coefficients, position 2"),
    ],
)
def test_a_stored_nan_is_an_index_format_error_naming_dataset_and_row(index_copy, dataset, index, where):
    _rewrite(index_copy, dataset, index, np.nan)
    with open_index(index_copy) as idx:
        with pytest.raises(IndexFormatError, match=f"non-finite value \\(NaN or Inf\\) in {where}"):
            if dataset.startswith("curves"):
                idx.coefficients_at([5])
            else:
                table = idx.search_table()
                table.cell_rows(np.arange(table.n_cells))
    result = _cli(
        "query",
        QUERY,
        "--index",
        str(index_copy),
        "--top",
        "30",
        "--exhaustive" if dataset.startswith("curves") else "--top=30",
    )
    assert result.exit_code == 2 and "non-finite value" in result.stderr and "Traceback" not in result.stderr
    result = _cli("index", "verify", "--index", str(index_copy))
    assert result.exit_code == 1
    assert f"bad\t/{dataset}\t" in result.stdout and "non-finite values" in result.stdout


def test_a_stored_nan_in_the_squared_norms_is_not_read_by_a_query_and_verify_finds_it(built, index_copy):
    expect = _cli("query", QUERY, "--index", str(built), "--top", "30", "--format", "csv")
    _rewrite(index_copy, "search/sqnorm", (2, 1), np.nan)
    result = _cli("query", QUERY, "--index", str(index_copy), "--top", "30", "--format", "csv")
    assert result.exit_code == 0 and result.stdout == expect.stdout
    result = _cli("index", "verify", "--index", str(index_copy))
    assert result.exit_code == 1 and "bad\t/search/sqnorm\t" in result.stdout


# --------------------------------------------------------------------------- crafted indexes


def _index_info_limited(path):
    """`index info` in a child process with 3 GB of address space: a reader that allocated
    what a crafted file declares (tens of GB) would die, not answer."""
    import resource

    def limit():
        resource.setrlimit(resource.RLIMIT_AS, (3 << 30, 3 << 30))

    return _run(["index", "info", "--index", str(path)], preexec_fn=limit)


def _declare(f, name, rows):
    """Replace ``name`` by a dataset declaring ``rows`` rows whose chunks are never written."""
    ds = f[name]
    dtype, tail = ds.dtype, ds.shape[1:]
    del f[name]
    f.create_dataset(name, shape=(rows,) + tail, dtype=dtype, chunks=(4096,) + tail, fletcher32=dtype.kind != "O")


def _craft(path, fn):
    with h5py.File(path, "r+") as f:
        fn(f)


@pytest.mark.parametrize(
    "craft, message",
    [
        (lambda f: f.attrs.__setitem__("samples", np.int64(300_000_000)), "samples 300000000 above the limit"),
        (
            lambda f: (
                f.attrs.__setitem__("samples", np.int64(1 << 20)),
                f.attrs.__setitem__("harmonics", np.int64(400_000)),
            ),
            "/curves/coefficients has shape",
        ),
        (
            lambda f: [f["curves"][name].resize(100_000_000, axis=0) for name in f["curves"] if name != "id_crc32"],
            "declares (100000000",
        ),
        (
            lambda f: [
                _declare(f, f"files/{name}", 50_000_000) for name in list(f["files"]) if not name.endswith("crc32")
            ],
            "declares (50000000",
        ),
        (lambda f: _declare(f, "search/features", 50_000_000), "/search/features declares (50000000"),
    ],
)
def test_a_crafted_index_is_refused_before_any_allocation(index_copy, craft, message):
    _craft(index_copy, craft)
    assert os.path.getsize(index_copy) < 1 << 20
    with pytest.raises(IndexFormatError, match="corrupted nfdmatch index") as info:
        open_index(index_copy)
    assert message in str(info.value)
    proc = _index_info_limited(index_copy)
    assert proc.returncode == 2, proc.stderr
    assert proc.stdout == b""
    assert proc.stderr.decode().startswith(f"Error: {index_copy}: corrupted nfdmatch index: ")
    assert b"Traceback" not in proc.stderr and len(proc.stderr) < 1000


def _replace(f, name, **kwargs):
    del f[name]
    f.create_dataset(name, **kwargs)


def test_external_storage_is_refused_and_its_file_never_printed(index_copy, tmp_path):
    secret = tmp_path / "secret.txt"
    secret.write_bytes(b"TOP-SECRET-CONTENT-" * 200)
    with h5py.File(index_copy, "r") as f:
        N = f["curves/id"].shape[0]
    # fixed-length ids read the other file's bytes: exactly what a reader must never print
    _craft(index_copy, lambda f: _replace(f, "curves/id", shape=(N,), dtype="S16", external=[(str(secret), 0, 16 * N)]))
    for args in (["index", "ls", "--curves"], ["query", QUERY, "--top", "3"], ["index", "info"], ["index", "verify"]):
        result = _cli(*args, "--index", str(index_copy))
        assert result.exit_code == 2, args
        assert "SECRET" not in result.stdout + result.stderr
        assert "/curves/id has external storage (data in another file): refused" in result.stderr


def test_virtual_datasets_and_links_are_refused(index_copy, tmp_path):
    other = tmp_path / "other.h5"
    with h5py.File(other, "w") as g:
        g["scale"] = np.ones(24)
        g["coefficients"] = np.ones((24, 16, 3), np.complex64)
    layout = h5py.VirtualLayout(shape=(24,), dtype="f8")
    layout[:] = h5py.VirtualSource(str(other), "scale", shape=(24,))

    def virtual(f):
        del f["curves/scale"]
        f["curves"].create_virtual_dataset("scale", layout)

    def external_link(f):
        del f["curves/coefficients"]
        f["curves/coefficients"] = h5py.ExternalLink(str(other), "coefficients")

    def soft_link(f):
        f["curves/elsewhere"] = f["curves/centroid"]
        del f["curves/centroid"]
        f["curves/centroid"] = h5py.SoftLink("/curves/elsewhere")

    for craft, message in (
        (virtual, "/curves/scale is a virtual dataset"),
        (external_link, "/curves/coefficients is a ExternalLink, not stored in the file"),
        (soft_link, "/curves/centroid is a SoftLink, not stored in the file"),
    ):
        path = tmp_path / f"{craft.__name__}.h5"
        shutil.copyfile(index_copy, path)
        _craft(path, craft)
        with pytest.raises(IndexFormatError, match="refused"):
            open_index(path)
        result = _cli("query", QUERY, "--index", str(path))
        assert result.exit_code == 2 and message in result.stderr, result.stderr


def test_a_checksummed_file_with_a_dataset_stripped_of_its_checksum_is_corrupt(index_copy):
    def strip(f):
        data = f["curves/scale"][...]
        del f["curves/scale"]
        f["curves"].create_dataset("scale", data=data)

    _craft(index_copy, strip)
    with pytest.raises(IndexFormatError, match="/curves/scale has no checksum filter"):
        open_index(index_copy)


def test_a_huge_error_message_is_cut_where_it_is_stored(tmp_path):
    # a CSV whose one "number" is 1 MB (within the 1 MiB line cap): the error line, the stored
    # record and `index info` stay short
    bad = tmp_path / "lib" / "huge.csv"
    bad.parent.mkdir()
    bad.write_text("x,y,z\n1,2,3\n4,5,6\n" + "7" * 1_000_000 + "x,8,9\n")
    index = tmp_path / "i.h5"
    result = _cli("index", "build", str(bad.parent), "--index", str(index), "--jobs", "1")
    assert result.exit_code == 3
    assert max(len(line) for line in result.stderr.splitlines()) < 2000
    result = _cli("index", "info", "--index", str(index))
    assert result.exit_code == 0
    assert len(result.stdout) < 4000 and "characters in all]" in result.stdout


def test_a_crafted_huge_stored_error_is_cut_on_storing(tmp_path):
    from nfdmatch.index.schema import FileRecord
    from nfdmatch.index.writer import write_files_table

    path = tmp_path / "t.h5"
    with h5py.File(path, "w") as f:
        write_files_table(f, [FileRecord("a.csv", 1, 1, "", "failed", "a.csv: " + "9" * 5_000_000, 0, 0)])
    with h5py.File(path, "r") as f:
        stored = f["files/error"].asstr()[0]
    assert len(stored) < 1100 and stored.endswith("characters in all]")


# --------------------------------------------------------------------------- coordinates near 1e308


def _huge_curve(path, factor, offset=0.0):
    t = np.linspace(0, 2 * np.pi, 60, endpoint=False)
    pts = np.stack([np.cos(t), 0.5 * np.sin(2 * t), np.sin(t) + 0.3 * np.cos(3 * t)], 1)
    write_curves(path, pts * factor + offset)
    return pts


@pytest.mark.parametrize("factor", [1e308, 1.7e308 / 1.3])
def test_reconstruct_and_distance_work_at_1e308_without_warnings(tmp_path, factor):
    unit = _huge_curve(tmp_path / "huge.csv", factor)
    write_curves(tmp_path / "unit.csv", unit)
    with _no_warnings():
        result = _cli("reconstruct", str(tmp_path / "huge.csv"), "-k", "6", "-o", str(tmp_path / "r.csv"))
        assert result.exit_code == 0, result.stderr
        assert "Traceback" not in result.stderr
        rebuilt = np.loadtxt(tmp_path / "r.csv", delimiter=",", skiprows=1)
        assert np.isfinite(rebuilt).all() and np.abs(rebuilt).max() > 0.5 * factor
        # the shape at 1e308 is the shape at 1: distance 0 (scale invariant)
        result = _cli("distance", str(tmp_path / "huge.csv"), str(tmp_path / "unit.csv"))
        assert result.exit_code == 0, result.stderr
        assert float(result.stdout.split()[1]) < 1e-9
    from nfdmatch import descriptors, read_curve
    from nfdmatch.descriptors import reconstruct

    d = descriptors(read_curve(tmp_path / "huge.csv"))
    assert np.isfinite(d.scale) and np.isfinite(d.centroid).all()
    assert np.allclose(d.coefficients, descriptors(read_curve(tmp_path / "unit.csv")).coefficients, atol=1e-9)
    assert np.isfinite(reconstruct(d)).all()


def test_show_refuses_a_query_too_large_to_draw_clearly(tmp_path):
    _huge_curve(tmp_path / "huge.csv", 1e308)
    (tmp_path / "lib").mkdir()
    _huge_curve(tmp_path / "lib" / "small.csv", 1.0)
    with _no_warnings():
        result = _cli(
            "show", str(tmp_path / "huge.csv"), "--against", str(tmp_path / "lib"), "-o", str(tmp_path / "s.svg")
        )
    assert result.exit_code == 2
    assert result.stdout == ""
    assert result.stderr.startswith(f"Error: {tmp_path / 'huge.csv'}: coordinates up to 1.2e+308 are too large to draw")
    assert not (tmp_path / "s.svg").exists()


def test_a_position_beyond_float64_fails_clearly(tmp_path):
    # every coordinate finite, but the curve's centroid plus its size is not representable
    from nfdmatch import descriptors, read_curve
    from nfdmatch.errors import CurveError

    t = np.linspace(0, 2 * np.pi, 40, endpoint=False)
    pts = np.stack([np.cos(t), np.sin(t), 0 * t], 1) * 1e308
    pts[:, 0] = np.where(pts[:, 0] > 0, 1.79e308, -1.79e308) * np.abs(np.cos(t)) ** 0.01
    write_curves(tmp_path / "edge.csv", pts)
    try:
        d = descriptors(read_curve(tmp_path / "edge.csv"))
    except CurveError as exc:
        assert "beyond float64" in str(exc) and str(tmp_path / "edge.csv") in str(exc)
    else:
        assert np.isfinite(d.scale) and np.isfinite(d.centroid).all()


class _no_warnings:
    """Within: any warning is an error (a RuntimeWarning from numpy means an overflow)."""

    def __enter__(self):
        import warnings

        self.ctx = warnings.catch_warnings()
        self.ctx.__enter__()
        warnings.simplefilter("error")

    def __exit__(self, *exc):
        self.ctx.__exit__(*exc)


def test_verify_checks_the_derived_search_data_against_the_curves(index_copy):
    # a consistent-looking edit (checksums recomputed by HDF5): only verify's cross-checks see it
    with h5py.File(index_copy, "r") as f:
        value = f["search/features"][4, 0]
    _rewrite(index_copy, "search/features", (4, 0), value + 0.25)
    _rewrite(index_copy, "curves/file", 0, 3)
    result = _cli("index", "verify", "--index", str(index_copy))
    assert result.exit_code == 1
    lines = result.stdout.splitlines()
    assert "bad\t/search/features\t4\tdiffers from what it is derived from (positions)" in lines
    assert "bad\t/curves/file\t0\tdoes not match the /files blocks" in lines


def test_a_crafted_huge_stored_error_is_cut_when_read(index_copy):
    from nfdmatch.index.schema import block_crcs

    def craft(f):
        errors = f["files/error"].asstr()[...].tolist()
        errors[0] = "9" * 5_000_000
        del f["files/error"], f["files/error_crc32"]
        f["files"].create_dataset("error", data=np.array(errors, dtype=object), dtype=h5py.string_dtype())
        f["files"].create_dataset("error_crc32", data=block_crcs(errors), fletcher32=True, chunks=True)
        status = f["files/status"][...]
        status[0] = 1
        f["files/status"][...] = status

    _craft(index_copy, craft)
    result = _cli("index", "info", "--index", str(index_copy))
    assert result.exit_code == 0, result.stderr
    assert len(result.stdout) < 5000 and "[cut: 5000000 characters in all]" in result.stdout


def test_a_flipped_bit_in_the_file_table_is_named_on_open(index_copy):
    _flip(index_copy, "files/curve_count")
    for args in (["index", "info"], ["index", "verify"], ["query", QUERY]):
        result = _cli(*args, "--index", str(index_copy))
        assert result.exit_code == 2 and result.stdout == ""
        assert result.stderr == (
            f"Error: {index_copy}: corrupted nfdmatch index: checksum mismatch in the file "
            "table (/files; the file is damaged)\n"
        )


@pytest.mark.parametrize("dtype", [np.float32, np.float64, np.complex64])
def test_the_non_finite_scan_finds_the_first_bad_row_and_nothing_in_large_finite_values(dtype):
    from nfdmatch.index.arrays import first_nonfinite

    big = np.finfo(np.float32 if dtype != np.float64 else np.float64).max / 2
    values = np.full((50, 3), big, dtype=dtype)  # their sum overflows: the exact scan decides
    assert first_nonfinite(values, 100) is None
    for bad in (np.nan, np.inf, -np.inf):
        for row in (0, 17, 49):
            spoiled = values.copy()
            spoiled[row, 1] = bad
            spoiled[min(row + 1, 49), 2] = bad
            assert first_nonfinite(spoiled, 100) == 100 + row
            assert first_nonfinite(spoiled, np.arange(50) * 2) == 2 * row


def _retype(path, dataset, dtype):
    """Store ``dataset`` again with another type, same values, checksummed as the writer does."""
    from nfdmatch.index.schema import create_checked

    with h5py.File(path, "r+") as f:
        data = f[dataset][...]
        group, name = dataset.rsplit("/", 1)
        del f[dataset]
        create_checked(f[group], name, data.astype(dtype))


def _as_text(path, dataset, first="n/a"):
    """Store ``dataset`` again as variable-length strings: the text of its numbers, the
    first one replaced by ``first`` (a hand edit, or a writer that stored numbers as text)."""
    from nfdmatch.index.schema import STR

    with h5py.File(path, "r+") as f:
        data = f[dataset][...]
        text = data.astype(str).astype(object)
        text.reshape(-1)[0] = first
        group, name = dataset.rsplit("/", 1)
        del f[dataset]
        f[group].create_dataset(name, data=text, dtype=STR)


def _rewrite_strings(path, dataset, values):
    """Replace the strings of ``dataset`` and recompute their CRC-32 blocks (a consistent hand edit)."""
    from nfdmatch.index.schema import STR, block_crcs

    with h5py.File(path, "r+") as f:
        group, name = dataset.rsplit("/", 1)
        del f[dataset]
        f[group].create_dataset(name, data=np.array(values, dtype=object), dtype=STR)
        del f[f"{dataset}_crc32"]
        f[group].create_dataset(f"{name}_crc32", data=block_crcs(values), chunks=True, fletcher32=True)


def test_verify_recomputes_the_bound_features_from_the_stored_coefficients(index_copy):
    """Issue 24, item 3: an inv_norm multiplied by 1,000, checksums recomputed, passed verify
    (and a bound feature too large makes a search skip a true match)."""
    with h5py.File(index_copy, "r") as f:
        norm, sv = f["curves/inv_norm"][7], f["curves/inv_sv"][2]
    _rewrite(index_copy, "curves/inv_norm", 7, norm * 1000)
    _rewrite(index_copy, "curves/inv_sv", 2, sv * (1 + 1e-4))
    result = _cli("index", "verify", "--index", str(index_copy))
    assert result.exit_code == 1
    lines = result.stdout.splitlines()
    assert "bad\t/curves/inv_norm\t7\tdiffers from the features of the stored coefficients" in lines
    assert "bad\t/curves/inv_sv\t2\tdiffers from the features of the stored coefficients" in lines


def test_verify_checks_every_dtype_against_the_format(index_copy):
    """Issue 24, item 3: /curves/file stored as float passed verify."""
    _retype(index_copy, "curves/file", np.float64)
    _retype(index_copy, "search/features", np.float64)
    result = _cli("index", "verify", "--index", str(index_copy))
    assert result.exit_code == 1
    lines = result.stdout.splitlines()
    assert "bad\t/curves/file\t\tstored as float64; the format says int32" in lines
    assert "bad\t/search/features\t\tstored as float64; the format says float32" in lines


def test_verify_refuses_ids_that_leave_the_index_folder_or_differ_from_the_file_table(index_copy):
    """Issue 24, item 3: ids rewritten to ../../../../etc/passwd, CRC-32 recomputed, passed
    verify (and query printed them)."""
    with h5py.File(index_copy, "r") as f:
        ids = f["curves/id"].asstr()[...].tolist()
        paths = f["files/path"].asstr()[...].tolist()
    assert "sources" in h5py.File(index_copy, "r")  # relative paths are the index folder's
    _rewrite_strings(index_copy, "curves/id", ["../../../../etc/passwd"] + ids[1:])
    result = _cli("index", "verify", "--index", str(index_copy))
    assert result.exit_code == 1
    assert "bad\t/curves/id\t0\tdiffers from the ids of the /files paths (path, path#i)" in result.stdout
    # the file table rewritten to match: the path itself is refused
    with h5py.File(index_copy, "r") as f:
        count = f["files/curve_count"][0]
    assert count == 1
    _rewrite_strings(index_copy, "files/path", ["../../../../etc/passwd"] + paths[1:])
    result = _cli("index", "verify", "--index", str(index_copy))
    assert result.exit_code == 1
    assert "bad\t/files/path\t0\trelative paths that lead out of the index's folder (..)" in result.stdout
    assert "/curves/id" not in result.stdout


@pytest.mark.parametrize("dataset", ["curves/statistics", "curves/inv_sv", "files/curve_count", "search/features"])
def test_strings_where_numbers_are_stored_are_a_corrupt_index(index_copy, dataset):
    """Numbers stored as text were parsed by the readers (a text that is no number: a
    traceback from verify, query --elastic and Index.search): a corrupt index, on open."""
    _as_text(index_copy, dataset)
    message = f"Error: {index_copy}: corrupted nfdmatch index: /{dataset} holds strings, not numbers\n"
    for args in (("index", "verify"), ("query", QUERY, "--elastic"), ("query", QUERY)):
        result = _cli(*args, "--index", str(index_copy))
        assert (result.exit_code, result.stdout, result.stderr) == (2, "", message), args
    with pytest.raises(IndexFormatError, match=f"/{dataset} holds strings, not numbers"):
        with open_index(index_copy) as idx:
            idx.search(QUERY, k=3, elastic=True)
