"""The strict VTK reader (nfdmatch.formats._vtk_read) against what pyvista/VTK reads.

Every variant VTK can write for PolyData and UnstructuredGrid (legacy ASCII and binary in
file versions 4.2 and 5.1; XML ascii, inline binary, appended raw and base64; no
compression, zlib, LZ4, LZMA; UInt32 and UInt64 headers) must give the same points and
line cells as VTK's own reader. Then malformed files: each is refused with its reason.
"""

from __future__ import annotations

import itertools
import struct
import zlib
from pathlib import Path

import numpy as np
import pytest

from nfdmatch.errors import NoCurvesError, ParseError
from nfdmatch.formats import read_curves
from nfdmatch.formats import vtk as vtk_format
from nfdmatch.formats import _vtk_read

#: end-to-end as a whole (subprocesses, real files, pools): left out by `make test-fast`
pytestmark = pytest.mark.slow


def _mesh(pv):
    """PolyData with polylines (closed and not), chained 2-point segments, a triangle and
    vertex cells; 5,000+ points so that compressed arrays span several 32 KiB blocks."""
    rng = np.random.default_rng(7)
    n_big = 5000
    big = rng.normal(size=(n_big, 3)) * 1e3
    square = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], float) + 1e6
    tri = np.array([[5, 5, 5], [6, 5, 5], [5, 6, 5.5]])
    points = np.concatenate([big, square, tri])
    s = n_big
    lines = [
        n_big + 1,
        *range(n_big),
        0,  # closed polyline
        2,
        s,
        s + 1,
        2,
        s + 2,
        s + 1,
        2,
        s + 3,
        s + 2,
        2,
        s,
        s + 3,  # segments
        3,
        s + 4,
        s + 5,
        s + 6,
    ]  # open polyline
    mesh = pv.PolyData(points, lines=np.array(lines), faces=np.array([3, s + 4, s + 5, s + 6]), verts=np.array([1, 3]))
    return mesh


def _write_variants(tmp_path: Path):
    """(file name, kind) of every variant, written by VTK itself."""
    import vtk

    pv = vtk_format._pyvista()
    poly = _mesh(pv)
    grid = poly.cast_to_unstructured_grid()
    out = []
    for data, tag in ((poly, "poly"), (grid, "grid")):
        for version, binary in itertools.product((42, 51), (False, True)):
            name = str(tmp_path / f"{tag}_{version}_{'bin' if binary else 'ascii'}.vtk")
            writer = vtk.vtkDataSetWriter() if tag == "poly" else vtk.vtkUnstructuredGridWriter()
            writer.SetInputData(data)
            writer.SetFileName(name)
            writer.SetFileVersion(version)
            writer.SetFileTypeToBinary() if binary else writer.SetFileTypeToASCII()
            writer.Write()
            out.append(name)
        ext = ".vtp" if tag == "poly" else ".vtu"
        for mode, encode, compressor, header in itertools.product(
            ("ascii", "binary", "appended"), (True, False), ("none", "zlib", "lz4", "lzma"), ("UInt32", "UInt64")
        ):
            if mode != "appended" and not encode:
                continue  # encoding applies to appended only
            if mode == "ascii" and (compressor != "none" or header != "UInt32"):
                continue
            writer = vtk.vtkXMLPolyDataWriter() if tag == "poly" else vtk.vtkXMLUnstructuredGridWriter()
            writer.SetInputData(data)
            {
                "ascii": writer.SetDataModeToAscii,
                "binary": writer.SetDataModeToBinary,
                "appended": writer.SetDataModeToAppended,
            }[mode]()
            writer.SetEncodeAppendedData(encode)
            {
                "none": writer.SetCompressorTypeToNone,
                "zlib": writer.SetCompressorTypeToZLib,
                "lz4": writer.SetCompressorTypeToLZ4,
                "lzma": writer.SetCompressorTypeToLZMA,
            }[compressor]()
            writer.SetHeaderTypeToUInt32() if header == "UInt32" else writer.SetHeaderTypeToUInt64()
            name = str(tmp_path / f"{tag}_{mode}_{'b64' if encode else 'raw'}_{compressor}_{header}{ext}")
            writer.SetFileName(name)
            assert writer.Write() == 1
            out.append(name)
    # and what pyvista's own save() writes
    for data, tag, ext in (
        (poly, "poly", ".vtp"),
        (grid, "grid", ".vtu"),
        (poly, "poly", ".vtk"),
        (grid, "grid", ".vtk"),
    ):
        for binary in (False, True):
            name = str(tmp_path / f"pyvista_{tag}_{'bin' if binary else 'ascii'}{ext}")
            data.save(name, binary=binary)
            out.append(name)
    return out


def _vtk_lines(pv, mesh):
    """(points, offsets, connectivity) of the line cells as VTK's reader gives them."""
    if isinstance(mesh, pv.PolyData):
        return (
            np.asarray(mesh.points, float),
            np.asarray(mesh.line_offsets, np.int64),
            np.asarray(mesh.line_connectivity, np.int64),
        )
    types = np.asarray(mesh.celltypes)
    offsets = np.asarray(mesh.cell_offsets, np.int64)
    conn = np.asarray(mesh.cell_connectivity, np.int64)
    cells = [conn[offsets[c] : offsets[c + 1]] for c in np.flatnonzero((types == 3) | (types == 4))]
    return (
        np.asarray(mesh.points, float),
        np.concatenate([[0], np.cumsum([len(c) for c in cells])]),
        np.concatenate(cells),
    )


@pytest.fixture(scope="module")
def variants(tmp_path_factory):
    return _write_variants(tmp_path_factory.mktemp("variants"))


def test_variant_list_covers_every_mode(variants):
    names = [Path(v).name for v in variants]
    assert len(names) == 2 * (4 + 1 + 8 + 16) + 8
    for needle in (
        "_42_bin.vtk",
        "_51_ascii.vtk",
        "appended_raw_lz4_UInt64",
        "binary_b64_lzma",
        "appended_b64_zlib_UInt32",
        "_ascii_b64_none_UInt32",
    ):
        assert any(needle in n for n in names), needle


def test_every_variant_reads_as_vtk_reads_it(variants):
    pv = vtk_format._pyvista()
    for name in variants:
        kind = Path(name).suffix[1:]
        ours = _vtk_read.parse(Path(name).read_bytes(), kind, name)
        points, offsets, conn = _vtk_lines(pv, pv.read(name))
        assert np.array_equal(ours.points, points), name
        assert np.array_equal(ours.line_offsets, offsets), name
        assert np.array_equal(ours.line_connectivity, conn), name
        assert ours.n_other == 1, name  # the triangle


def test_every_variant_gives_the_same_curves(variants):
    reference = [c.points for c in read_curves(variants[1])]  # legacy binary
    assert len(reference) == 3 and len(reference[0]) == 5000
    for name in variants:
        curves = read_curves(name)
        assert len(curves) == 3, name
        for got, want in zip(curves, reference):
            if name.endswith("ascii.vtk"):  # VTK writes legacy ASCII with fewer digits
                assert np.allclose(got.points, want, rtol=1e-5), name
            else:
                assert np.array_equal(got.points, want), name


# ---------------------------------------------------------------------------
# malformed files are refused with the reason
# ---------------------------------------------------------------------------

LEGACY_HEAD = "# vtk DataFile Version 3.0\nx\nASCII\nDATASET POLYDATA\nPOINTS 4 double\n0 0 0\n1 0 0\n1 1 0\n0 1 0\n"
V51_HEAD = "# vtk DataFile Version 5.1\nx\nASCII\nDATASET POLYDATA\nPOINTS 4 double\n0 0 0 1 0 0 1 1 0 0 1 0\n"


def _refused(tmp_path, name, content, *needles, error=ParseError):
    p = tmp_path / name
    p.write_bytes(content if isinstance(content, bytes) else content.encode())
    with pytest.raises(error) as info:
        read_curves(str(p))
    message = str(info.value)
    assert message.startswith(str(p)), message
    for needle in needles:
        assert needle in message, (needle, message)
    assert len(message) < 600
    return message


@pytest.mark.parametrize(
    "content, needles",
    [
        (LEGACY_HEAD + "LINES 5 6\n5 0 1 2 3 0\n", ("declares 5 cells", "hold only 1")),
        (LEGACY_HEAD + "LINES 1 9\n5 0 1 2 3 0\n", ("LINES declares 9 values",)),
        (LEGACY_HEAD + "LINES 1 6\n7 0 1 2 3 0\n", ("cell 0 declares 7 points",)),
        (LEGACY_HEAD + "LINES 1 7\n5 0 1 2 3 0 2\n", ("use 6 of the 7 values",)),
        (LEGACY_HEAD + "LINES 1 6\n-5 0 1 2 3 0\n", ("negative point count",)),
        (
            V51_HEAD + "LINES 2 5\nOFFSETS vtktypeint64\n0 9\nCONNECTIVITY vtktypeint64\n0 1 2 3 0\n",
            ("offset 1 (9) is past the end",),
        ),
        (
            V51_HEAD + "LINES 2 5\nOFFSETS vtktypeint64\n0 -5\nCONNECTIVITY vtktypeint64\n0 1 2 3 0\n",
            ("is below the one before",),
        ),
        (
            V51_HEAD + "LINES 2 5\nOFFSETS vtktypeint64\n0 4611686018427387904\nCONNECTIVITY vtktypeint64\n0 1 2 3 0\n",
            ("past the end",),
        ),
        (
            V51_HEAD + "LINES 3 5\nOFFSETS vtktypeint64\n0 5\nCONNECTIVITY vtktypeint64\n0 1 2 3 0\n",
            ("not an integer", "'CONNECTIVITY'"),
        ),
        (
            V51_HEAD + "LINES 2 5\nOFFSETS vtktypeint64\n1 5\nCONNECTIVITY vtktypeint64\n0 1 2 3 0\n",
            ("first offset is not 0",),
        ),
        (
            "# vtk DataFile Version 5.1\nx\nASCII\nDATASET POLYDATA\nPOINTS 4 double\n"
            "0 0 0 1 0 0 1 1 0 0 1 0 1e308 1e308\nLINES 1 6\n5 0 1 2 3 0\n",
            ("found '1e308 1e308' where a section", "POINTS"),
        ),
        (
            LEGACY_HEAD.replace("POINTS 4", "POINTS 2147483648") + "LINES 1 6\n5 0 1 2 3 0\n",
            ("POINTS declares 6442450944 values",),
        ),
        (LEGACY_HEAD + "LINES 1 6\n5 0 1 2 3 0.5\n", ("not an integer", "'0.5'")),
        (
            V51_HEAD + "LINES 2 5\nOFFSETS vtktypeint64\n0 5\nCONNECTIVITY vtktypeint64\n0 1 2 3-0\n",
            ("CONNECTIVITY declares 5 values but the file holds only 4",),
        ),
        (
            V51_HEAD.replace("0 0 0 1 0 0 1 1 0 0 1 0", "0 0 0 1 0 0 1 1 0 0 1-0") + "LINES 1 6\n",
            ("not a number", "'1-0'"),
        ),
        (LEGACY_HEAD.replace("0 1 0\n", "0 1 zero\n") + "LINES 1 6\n5 0 1 2 3 0\n", ("not a number", "'zero'")),
        ("# vtk DataFile Version 3.0\nx\nTEXT\n", ("ASCII or BINARY",)),
        (
            V51_HEAD.replace("POINTS 4", "POINTS 1e308") + "LINES 1 6\n5 0 1 2 3 0\n",
            ("the POINTS count is not a non-negative integer: '1e308'",),
        ),
        (V51_HEAD + "LINES 1e308 5\nOFFSETS vtktypeint64\n0 5\n", ("LINES cell count",)),
        (
            V51_HEAD.replace("ASCII", "BINARY").replace(
                "POINTS 4 double\n0 0 0 1 0 0 1 1 0 0 1 0\n", "POINTS 4 double\n" + "\0" * 10
            ),
            ("POINTS declares 12 values (96 bytes) but only 10 bytes follow",),
        ),
        ("#vtk nope\n", ("# vtk DataFile Version",)),
    ],
)
def test_malformed_legacy_is_refused_with_the_reason(tmp_path, content, needles):
    _refused(tmp_path, "bad.vtk", content, "could not be read as VTK", *needles)


def test_cell_of_five_points_in_a_four_point_grid(tmp_path):
    _refused(
        tmp_path,
        "five.vtk",
        LEGACY_HEAD.replace("POLYDATA", "UNSTRUCTURED_GRID") + "CELLS 1 6\n5 0 1 2 3 4\nCELL_TYPES 1\n4\n",
        "line cell 0 refers to point 4 but the file holds 4 points",
    )


def test_other_dataset_type_is_no_curves(tmp_path):
    _refused(
        tmp_path,
        "img.vtk",
        "# vtk DataFile Version 3.0\nx\nASCII\nDATASET STRUCTURED_POINTS\n",
        "STRUCTURED_POINTS",
        error=NoCurvesError,
    )


def _vtp(
    points_attr='NumberOfPoints="4"',
    comps="3",
    lines_attr='NumberOfLines="1"',
    offsets="5",
    conn="0 1 2 3 0",
    points="0 0 0 1 0 0 1 1 0 0 1 0",
    extra="",
):
    return (
        f'<?xml version="1.0"?>\n<VTKFile type="PolyData" version="0.1" '
        f'byte_order="LittleEndian"{extra}>\n<PolyData>\n<Piece {points_attr} {lines_attr}>\n'
        f'<Points><DataArray type="Float64" NumberOfComponents="{comps}" format="ascii">'
        f"{points}</DataArray></Points>\n<Lines>"
        f'<DataArray type="Int64" Name="connectivity" format="ascii">{conn}</DataArray>'
        f'<DataArray type="Int64" Name="offsets" format="ascii">{offsets}</DataArray>'
        f"</Lines>\n</Piece>\n</PolyData>\n</VTKFile>\n"
    )


def test_the_xml_template_is_valid(tmp_path):
    p = tmp_path / "ok.vtp"
    p.write_text(_vtp())
    (curve,) = read_curves(str(p))
    assert len(curve.points) == 4


@pytest.mark.parametrize(
    "kwargs, needles",
    [
        (dict(points_attr='NumberOfPoints="2147483648"'), ("declares 6442450944 values",)),
        (dict(comps="9223372036854775807"), ("NumberOfComponents is 9223372036854775807",)),
        (dict(offsets="9"), ("connectivity declares 9 values",)),
        (dict(offsets="-5"), ("last offset is negative",)),
        (dict(offsets="4611686018427387904"), ("declares 4611686018427387904 values",)),
        (dict(lines_attr='NumberOfLines="5"'), ("offsets declares 5 values",)),
        (dict(conn="0 1 2 3 0 1", offsets="5"), ("holds more than the 5 values",)),
        (dict(points="0 0 0 1 0 0 1 1 0 0 1 1e999x"), ("not a number",)),
        (dict(points="0 0 0 1 0 0 1 1 0 0 1-0"), ("not a number", "'1-0'")),
        (dict(conn="0 1 2 3-0", offsets="5"), ("not an integer", "'3-0'")),
        (dict(extra=' compressor="vtkBogus"'), ("compressor",)),
        (dict(extra=' header_type="UInt16"'), ("header_type",)),
    ],
)
def test_malformed_xml_is_refused_with_the_reason(tmp_path, kwargs, needles):
    _refused(tmp_path, "bad.vtp", _vtp(**kwargs), "could not be read as VTK", *needles)


def test_xml_wrong_dataset_for_extension(tmp_path):
    _refused(tmp_path, "bad.vtu", _vtp(), "must hold UnstructuredGrid")


def _zlib_vtp(n_values: int, compressed: bytes, stated_sizes=None) -> bytes:
    """A VTP whose connectivity is one zlib block of ``n_values`` Int64 (inline binary)."""
    import base64

    block = n_values * 8
    header = struct.pack("<4I", 1, block, block, len(compressed))
    conn = (base64.b64encode(header) + base64.b64encode(compressed)).decode()
    pts = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], float).tobytes()
    praw = zlib.compress(pts)
    ph = struct.pack("<4I", 1, len(pts), len(pts), len(praw))
    points = (base64.b64encode(ph) + base64.b64encode(praw)).decode()
    offs = np.array([n_values], np.int64).tobytes()
    oraw = zlib.compress(offs)
    oh = struct.pack("<4I", 1, 8, 8, len(oraw))
    offsets = (base64.b64encode(oh) + base64.b64encode(oraw)).decode()
    return (
        f'<?xml version="1.0"?>\n<VTKFile type="PolyData" version="0.1" '
        f'byte_order="LittleEndian" header_type="UInt32" compressor="vtkZLibDataCompressor">'
        f'<PolyData><Piece NumberOfPoints="4" NumberOfLines="1">'
        f'<Points><DataArray type="Float64" NumberOfComponents="3" format="binary">{points}'
        f"</DataArray></Points><Lines>"
        f'<DataArray type="Int64" Name="connectivity" format="binary">{conn}</DataArray>'
        f'<DataArray type="Int64" Name="offsets" format="binary">{offsets}</DataArray>'
        f"</Lines></Piece></PolyData></VTKFile>\n"
    ).encode()


def test_zlib_within_the_cap_reads(tmp_path):
    conn = np.array([0, 1, 2, 3, 0], np.int64).tobytes()
    p = tmp_path / "ok.vtp"
    p.write_bytes(_zlib_vtp(5, zlib.compress(conn)))
    assert len(read_curves(str(p))[0].points) == 4


def test_zlib_bomb_is_refused_before_inflating(tmp_path):
    # 400 MB of zeros compress to ~400 KB; the file states 400 MB in one block
    n = 50_000_000
    bomb = zlib.compress(bytes(8 * n), 9)
    assert len(bomb) < 600_000
    content = _zlib_vtp(n, bomb)
    _refused(
        tmp_path,
        "bomb.vtp",
        content,
        "more than the limit",
        f"{_vtk_read.inflated_cap(len(content))} bytes",
        "MAX_INFLATED_BYTES",
    )


def test_blocks_inflating_past_the_cap_together_are_refused(tmp_path, monkeypatch):
    # each array is under the cap, their sum is not
    conn = np.array([0, 1, 2, 3, 0], np.int64).tobytes()
    content = _zlib_vtp(5, zlib.compress(conn))
    monkeypatch.setattr(_vtk_read, "MAX_INFLATED_BYTES", 100)
    monkeypatch.setattr(_vtk_read, "MAX_INFLATION_RATIO", 0)
    _refused(tmp_path, "sum.vtp", content, "inflate to more than the limit", "100 bytes")


def test_zlib_block_larger_than_stated_is_refused(tmp_path):
    conn = np.array([0, 1, 2, 3, 0, 0, 0], np.int64).tobytes()  # 7 values, 5 stated
    _refused(tmp_path, "long.vtp", _zlib_vtp(5, zlib.compress(conn)), "inflates past")


def test_lz4_decoder_overlapping_match():
    # literal "ab", then a match of 6 at offset 2 -> "abababab"; then a final literal "c"
    block = bytes([0x22]) + b"ab" + bytes([2, 0]) + bytes([0x10]) + b"c"
    assert _vtk_read._lz4_block(block, 9, "x") == b"ababababc"
    with pytest.raises(_vtk_read._Bad):
        _vtk_read._lz4_block(block, 5, "x")  # past the stated size
    with pytest.raises(_vtk_read._Bad):
        _vtk_read._lz4_block(bytes([0x02]) + bytes([9, 0]), 9, "x")  # offset before the start


# ---------------------------------------------------------------------------
# garbage that would only cost time is cut short
# ---------------------------------------------------------------------------


def test_endless_sections_are_refused(tmp_path):
    _refused(
        tmp_path,
        "meta.vtk",
        V51_HEAD + "METADATA\n\n" * (_vtk_read.MAX_SECTIONS + 5),
        f"more than {_vtk_read.MAX_SECTIONS} sections",
    )


def test_endless_metadata_ends_at_the_end_of_the_file(tmp_path):
    _refused(tmp_path, "meta.vtk", V51_HEAD + "METADATA\n" + "INFORMATION 1\n" * 100_000, error=NoCurvesError)


def test_a_mile_of_whitespace_is_just_whitespace(tmp_path):
    p = tmp_path / "space.vtk"
    p.write_text(
        V51_HEAD.replace("0 0 0 1", "0 0 0" + " \n" * 2_000_000 + "1")
        + "LINES 2 4\nOFFSETS vtktypeint64\n0 4\nCONNECTIVITY vtktypeint64\n0 1 2 3\n"
    )
    assert len(read_curves(str(p))[0].points) == 4


def test_too_many_pieces_are_refused(tmp_path):
    piece = '<Piece NumberOfPoints="0" NumberOfLines="0"/>'
    xml = f'<VTKFile type="PolyData" version="0.1"><PolyData>{piece * (_vtk_read.MAX_PIECES + 1)}</PolyData></VTKFile>'
    _refused(tmp_path, "pieces.vtp", xml, f"more than the {_vtk_read.MAX_PIECES} accepted")


def test_base64_in_too_many_pieces_is_refused(tmp_path):
    xml = _vtp().replace(
        'format="ascii">0 0 0 1 0 0 1 1 0 0 1 0', 'format="binary">' + "AA==" * (_vtk_read.MAX_BASE64_PIECES + 1)
    )
    _refused(tmp_path, "b64.vtp", xml, "separately padded pieces")


def _binary_points_vtp(points_b64: str) -> str:
    """The template with its points as inline binary (base64 of a UInt32 byte count, then the values)."""
    return _vtp().replace('format="ascii">0 0 0 1 0 0 1 1 0 0 1 0', f'format="binary">{points_b64}')


def _square_b64() -> str:
    """The unit square's points with their UInt32 byte count, in one base64 stream (ends in '==')."""
    import base64

    raw = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], np.float64).tobytes()
    return base64.b64encode(struct.pack("<I", len(raw)) + raw).decode()


def test_base64_reads_without_strict_mode(tmp_path, monkeypatch):
    """Python 3.10's a2b_base64 has no strict_mode: the reader must not ask for it."""
    real = _vtk_read.binascii.a2b_base64

    def a2b_base64_of_python_310(data, /):  # the 3.10 signature: a keyword is a TypeError
        return real(data)

    monkeypatch.setattr(_vtk_read.binascii, "a2b_base64", a2b_base64_of_python_310)
    p = tmp_path / "binary.vtp"
    p.write_text(_binary_points_vtp(_square_b64()))
    (curve,) = read_curves(str(p))
    assert curve.points.dtype == np.float64
    np.testing.assert_array_equal(curve.points, [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]])


@pytest.mark.parametrize(
    "damage, needle",
    [
        (lambda t: t[:-1] + "A", "padding inside a 4-character group"),  # '...x=A': the one-piece path
        (lambda t: t[:-2] + "=A", "padding inside a 4-character group"),
        (lambda t: t[:-4] + "=" + t[-3:], "cut short"),  # padding mid-text: the piece before it is short
        (lambda t: "=" + t[1:], "cut short"),
        (lambda t: t + "====", "cut short"),  # excess padding
        (lambda t: t[:-3], "cut short"),
        (lambda t: t[:8] + "*" + t[9:], "'*' is not base64"),
    ],
)
def test_malformed_base64_is_refused_naming_the_file(tmp_path, damage, needle):
    good = _square_b64()
    assert good.endswith("==") and "=" not in good[:-2]
    _refused(tmp_path, "b64.vtp", _binary_points_vtp(damage(good)), "could not be read as VTK", needle)


def test_reading_vtk_files_never_loads_vtk(variants):
    import subprocess
    import sys

    code = (
        "import sys\nfrom nfdmatch.formats import read_curves\n"
        f"for name in {variants[::7]!r}:\n    assert read_curves(name)\n"
        "loaded = [m for m in ('pyvista', 'vtk', 'vtkmodules') if m in sys.modules]\n"
        "assert not loaded, loaded\n"
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
