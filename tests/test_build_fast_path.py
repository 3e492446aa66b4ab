"""The build's fast path for small one-curve CSV files (index.pool: the bytes read for the
hash parsed by the CSV reader's bulk path, curves cleaned many at once) against the
careful way (``read_curves`` file by file): same acceptance, same vertices and ids, same
error messages; and the bulk path never accepts what the careful parser rejects."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from nfdmatch.formats import csv as csv_format
from nfdmatch.formats import read_curves
from nfdmatch.index import pool

_number = st.one_of(
    st.floats(-1e6, 1e6, allow_nan=False).map(repr),
    st.integers(-1000, 1000).map(str),
    st.floats(-10, 10, allow_nan=False).map(lambda x: f"{x:.6f}"),
    st.floats(-10, 10, allow_nan=False).map(lambda x: f"{x:.3e}"),
    st.sampled_from(
        [
            "nan",
            "inf",
            "-inf",
            "1e999",
            "",
            " ",
            "1,5",
            "0x1p3",
            "1_0",
            "abc",
            "+.5",
            "5.",
            '"1"',
            "'2'",
            "1e",
            "--1",
            "\x00",
            "\xe9",
        ]
    ),
)


@st.composite
def _csv_files(draw):
    """Mostly plausible one-curve CSV files, with every kind of small fault mixed in."""
    ncol = draw(st.sampled_from([2, 3, 3, 3, 4]))
    delim = draw(st.sampled_from([",", ",", ";", "\t", " ", ", ", "  "]))
    rows = draw(st.integers(0, 12))
    plausible = draw(st.booleans())
    lines = []
    header = draw(st.sampled_from([None, "x,y,z", "x y z", "X;Y;Z", "a,b,c", "x,y", "z,x,y", "# comment", "x,y,z,w"]))
    if header is not None:
        lines.append(header)
    base = draw(
        st.lists(
            st.lists(st.floats(-100, 100, allow_nan=False), min_size=ncol, max_size=ncol), min_size=rows, max_size=rows
        )
    )
    for values in base:
        cells = [f"{v:.4f}" for v in values]
        if not plausible and draw(st.integers(0, 3)) == 0:
            cells[draw(st.integers(0, ncol - 1))] = draw(_number)
        if not plausible and draw(st.integers(0, 6)) == 0:
            cells = cells[:-1]
        line = delim.join(cells)
        if draw(st.integers(0, 8)) == 0:
            line += draw(st.sampled_from([" # note", "\r", "  ", ","]))
        lines.append(line)
        if draw(st.integers(0, 10)) == 0:
            lines.append(draw(st.sampled_from(["", "# c", "   ", lines[-1]])))
    text = "\n".join(lines) + draw(st.sampled_from(["\n", "", "\n\n"]))
    data = text.encode("utf-8")
    if draw(st.integers(0, 12)) == 0:
        data = b"\xef\xbb\xbf" + data
    return data


def _careful(path: str):
    """(vertices list, None) or (None, message) of the careful way: read_curves."""
    try:
        return [c.points for c in read_curves(path)], None
    except Exception as exc:  # noqa: BLE001 - compared with the pool's message
        return None, pool._failure(path, exc)


@settings(max_examples=120, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(files=st.lists(_csv_files(), min_size=1, max_size=12))
def test_batch_fast_path_agrees_with_read_curves(tmp_path, files):
    paths = []
    for k, data in enumerate(files):
        path = tmp_path / f"f{k}.csv"
        path.write_bytes(data)
        paths.append(str(path))
    batch = [(k, (p, None, 32, 4, "rms", None)) for k, p in enumerate(paths)]
    results, arrays = pool._compute_batch(batch)
    expected = [_careful(p) for p in paths]
    rows = 0
    for p, out, (points, message) in zip(paths, results, expected):
        if points is None:
            assert out["status"] == "failed" and out["error"] == message
            assert "ids" not in out and "rows" not in out
            continue
        assert out["status"] == "ok", out["error"]
        assert out["ids"] == [p] and out["rows"] == 1
        rows += 1
    if rows == 0:
        assert arrays is None
        return
    good = [points[0] for points, _ in expected if points is not None]
    from nfdmatch.descriptors import descriptors_batch

    ref = descriptors_batch(
        [read_curves(p)[0] for p, (pts, _) in zip(paths, expected) if pts is not None], samples=32, harmonics=4
    )
    assert len(good) == len(arrays["coefficients"])
    np.testing.assert_array_equal(arrays["coefficients"], ref.coefficients.astype(np.complex64))
    np.testing.assert_array_equal(arrays["centroid"], ref.centroid)


@settings(max_examples=200, deadline=None)
@given(data=_csv_files())
def test_bulk_path_never_accepts_what_the_careful_parser_rejects(data, tmp_path_factory):
    path = str(tmp_path_factory.mktemp("bulk") / "c.csv")
    with open(path, "wb") as fh:
        fh.write(data)
    fast = pool._fast_points(path, data, None)
    if fast is None:
        return
    # the careful parser alone (the bulk path switched off) reads the same vertices
    real = csv_format._read_bulk
    csv_format._read_bulk = lambda data, path: None
    try:
        careful = csv_format.read_points(path)
    finally:
        csv_format._read_bulk = real
    assert len(careful) == 1
    np.testing.assert_array_equal(fast, careful[0])
    # and the whole read (cleaning included) agrees
    points, message = _careful(path)
    out, curves = pool._read_file(path, None, None)
    if points is None:
        assert out["status"] == "failed" and out["error"] == message
    else:
        assert out["status"] == "ok"
        np.testing.assert_array_equal(curves[0].points, points[0])


@pytest.mark.parametrize("content", [b"x,y,z\n0,0,0\n1,0,0\n0,1,0\n", b"0 0\n1 0\n0 1\n1 1\n"])
def test_fast_path_reads_plain_files_and_declines_other_formats(tmp_path, content):
    path = tmp_path / "c.csv"
    path.write_bytes(content)
    assert pool._fast_points(str(path), content, None) is not None
    assert pool._fast_points(str(path), content, "obj") is None
    assert pool._fast_points(str(path), b"\x00" + content, None) is None
