"""Fuzzing the readers (issue 9): whatever the bytes, a read gives curves or an NfdError,
never a crash, a hang or another exception.

Seeded mutants of valid files of every format and variant are read in child processes
with a time and a memory limit (tests/fuzzing.py), many per child; hypothesis drives the
parsers in process where a crash is impossible (pure Python/numpy) but an unexpected
exception or a wrong acceptance is not.
"""

from __future__ import annotations

import base64
import struct
import zlib

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import fuzzing
from nfdmatch.errors import MAX_MESSAGE_CHARS, NfdError
from nfdmatch.formats import read_curves

#: end-to-end as a whole (subprocesses, real files, pools): left out by `make test-fast`
pytestmark = pytest.mark.slow

MUTANTS_PER_FORMAT = 250  # 16 formats: 4,000 mutants, about 15 s


@pytest.fixture(scope="module")
def seeds(tmp_path_factory):
    return fuzzing.seed_files(tmp_path_factory.mktemp("seeds"))


def test_the_seeds_are_valid_and_cover_every_format(seeds):
    assert set(seeds) == {"csv", "obj", "vtk-ascii", "vtk-binary"} | {
        f"{ext}-{mode}"
        for ext in ("vtp", "vtu")
        for mode in ("ascii", "binary", "appended-raw", "appended-base64", "zlib", "zlib-appended")
    }
    for files in seeds.values():
        for path in files:
            assert read_curves(path)


def test_the_harness_tells_crash_hang_and_traceback_apart(tmp_path):
    contents = [
        b"x,y,z\n0,0,0\n1,0,0\n0,1,0\n",
        b"CRASH",
        b"x,y\n0,0\n1,0\n0,1\n",
        b"HANG",
        b"RAISE",
        b"not, a, curve\n",
        b"CRASH",
        b"0 0 0\n1 0 0\n0 1 1\n",
    ]
    paths = []
    for k, data in enumerate(contents):
        path = tmp_path / f"f{k}.csv"
        path.write_bytes(data)
        paths.append(str(path))
    results = fuzzing.run_mutants(paths, timeout=2.0, reader="test", batch=3)
    assert [r["outcome"] for r in results] == [
        "accepted",
        "crash",
        "accepted",
        "hang",
        "traceback",
        "error",
        "crash",
        "accepted",
    ]
    assert results[4]["type"] == "IndexError"


def test_mutants_of_every_format_are_read_or_refused(seeds, tmp_path):
    table, details = fuzzing.fuzz(seeds, tmp_path, MUTANTS_PER_FORMAT, seed=20261128, timeout=10.0)
    bad = [
        (path, result)
        for rows in details.values()
        for path, result in rows
        if result["outcome"] not in ("error", "accepted")
    ]
    assert not bad, fuzzing.format_table(table) + "\n" + "\n".join(map(str, bad[:10]))
    long = [
        (path, result["length"])
        for rows in details.values()
        for path, result in rows
        if result["outcome"] == "error" and result["length"] > MAX_MESSAGE_CHARS + 300
    ]
    assert not long
    for label, counts in table.items():  # the mutants reach both outcomes
        assert counts["error"] > 0, label


# ---------------------------------------------------------------------------
# hypothesis, in process
# ---------------------------------------------------------------------------


def _read(tmp_path, name, data: bytes):
    path = tmp_path / name
    path.write_bytes(data)
    try:
        curves = read_curves(str(path))
    except NfdError as exc:
        assert len(str(exc)) <= MAX_MESSAGE_CHARS + len(str(path)) + 10
        return None
    for curve in curves:
        assert curve.points.ndim == 2 and curve.points.shape[1] == 3
        assert np.isfinite(curve.points).all()
    return curves


LEGACY_HEAD = b"# vtk DataFile Version 5.1\nvtk output\n"

_tokens = st.one_of(
    st.integers(-3, 12).map(str),
    st.sampled_from(
        [
            "1e308",
            "2147483648",
            "9223372036854775807",
            "-1",
            "nan",
            "0.5",
            "x",
            "OFFSETS",
            "CONNECTIVITY",
            "vtktypeint64",
            "double",
            "LINES",
            "POINTS",
            "CELLS",
            "CELL_TYPES",
            "METADATA",
            "\n",
            "\n\n",
        ]
    ),
)


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(dataset=st.sampled_from(["POLYDATA", "UNSTRUCTURED_GRID"]), body=st.lists(_tokens, max_size=60))
def test_legacy_ascii_token_soup(tmp_path, dataset, body):
    text = LEGACY_HEAD + f"ASCII\nDATASET {dataset}\n".encode() + " ".join(body).encode()
    _read(tmp_path, "soup.vtk", text)


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    counts=st.tuples(st.integers(0, 2**40), st.integers(0, 2**40)), payload=st.binary(max_size=200), v51=st.booleans()
)
def test_legacy_binary_counts_and_bytes(tmp_path, counts, payload, v51):
    n_points, n_lines = counts
    head = LEGACY_HEAD + b"BINARY\nDATASET POLYDATA\n" + f"POINTS {n_points % 50} double\n".encode()
    points = np.arange(3 * (n_points % 50), dtype=">f8").tobytes()
    if v51:
        lines = f"LINES {n_lines} {n_lines + 3}\nOFFSETS vtktypeint64\n".encode() + payload
    else:
        lines = f"LINES {n_lines} {n_lines * 4}\n".encode() + payload
    _read(tmp_path, "bin.vtk", head + points + b"\n" + lines)


def _compressed_array(values: bytes, header: tuple[int, ...], blocks: list[bytes]) -> str:
    return (
        base64.b64encode(struct.pack(f"<{len(header)}I", *header)).decode()
        + base64.b64encode(b"".join(blocks)).decode()
    )


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    n_blocks=st.integers(0, 5),
    block=st.integers(0, 2**31),
    last=st.integers(0, 2**31),
    sizes=st.lists(st.integers(0, 2**31), max_size=5),
    cut=st.integers(0, 64),
)
def test_xml_compression_headers(tmp_path, n_blocks, block, last, sizes, cut):
    conn = np.array([0, 1, 2, 3, 0], "<i8").tobytes()
    packed = zlib.compress(conn)
    header = (n_blocks, block, last, *sizes)
    conn_text = _compressed_array(conn, header, [packed[: len(packed) - cut]])
    pts = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], "<f8").tobytes()
    pts_text = _compressed_array(pts, (1, len(pts), len(pts), len(zlib.compress(pts))), [zlib.compress(pts)])
    off = np.array([5], "<i8").tobytes()
    off_text = _compressed_array(off, (1, 8, 8, len(zlib.compress(off))), [zlib.compress(off)])
    xml = (
        f'<VTKFile type="PolyData" version="0.1" byte_order="LittleEndian" '
        f'header_type="UInt32" compressor="vtkZLibDataCompressor"><PolyData>'
        f'<Piece NumberOfPoints="4" NumberOfLines="1"><Points>'
        f'<DataArray type="Float64" NumberOfComponents="3" format="binary">{pts_text}'
        f"</DataArray></Points><Lines>"
        f'<DataArray type="Int64" Name="connectivity" format="binary">{conn_text}</DataArray>'
        f'<DataArray type="Int64" Name="offsets" format="binary">{off_text}</DataArray>'
        f"</Lines></Piece></PolyData></VTKFile>"
    ).encode()
    curves = _read(tmp_path, "z.vtp", xml)
    honest = (n_blocks, block, last, *sizes) == (1, len(conn), len(conn), len(packed)) and cut == 0
    assert (curves is not None) == honest


@settings(max_examples=100, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(text=st.text(alphabet=st.sampled_from(list("0123456789.,;-+eE \t\n#xyzna")), max_size=200))
def test_csv_character_soup(tmp_path, text):
    _read(tmp_path, "soup.csv", text.encode())


@settings(max_examples=100, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(text=st.text(alphabet=st.sampled_from(list("0123456789.-/ \nvlf#\\")), max_size=200))
def test_obj_character_soup(tmp_path, text):
    _read(tmp_path, "soup.obj", text.encode())
