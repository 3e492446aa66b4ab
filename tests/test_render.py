"""nfdmatch.render: the PNGs of `show` and `matrix` (size, content, 2-D/3-D view, labels,
errors, renderer fallback, pyvista off-screen or a clear error)."""

from __future__ import annotations

import io
import os
import subprocess
import sys

import numpy as np
import pytest
from PIL import Image

from oracle import ellipse, random_rotation, torus_knot

from nfdmatch import render
from nfdmatch.render import layout, matrix, pyvista_backend
from nfdmatch.errors import NfdError, ParameterError, RenderError, WriteError
from nfdmatch.records import RankedMatch, ShownMatch
from nfdmatch.render import (
    DEFAULT_RENDERER,
    RENDERERS,
    RenderResult,
    is_coplanar,
    render_matches,
    render_matrix,
    short_label,
    short_labels,
)

#: end-to-end as a whole (subprocesses, real files, pools): left out by `make test-fast`
pytestmark = pytest.mark.slow

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
SMALL = (640, 360)


# --------------------------------------------------------------------------- helpers


def _shown(curve_id, distance, points, start, forward, *, reversed=False, mirrored=False, source="file") -> ShownMatch:
    return ShownMatch(
        RankedMatch(rank=1, id=curve_id, distance=distance, reversed=reversed, mirrored=mirrored),
        points=points,
        start=start,
        forward=forward,
        source=source,
    )


def _panel(points, curve_id="lib/knot.csv", distance=0.1234567, **flags) -> ShownMatch:
    points = np.asarray(points, float)
    return _shown(curve_id, distance, points, points[0].copy(), points[3].copy(), **flags)


def _knot_scene(rng, n_matches=3):
    q = torus_knot(2, 3, 300)
    panels = []
    for i in range(n_matches):
        noisy = q + rng.normal(scale=0.03 * (i + 1), size=q.shape)
        panels.append(_panel(np.roll(noisy, 7 * i, axis=0), f"/data/lib/knot-{i}.csv#{i}", 0.01 * (i + 1)))
    return q, panels


def _ellipse_scene(n_matches=2, tilt=None):
    q = ellipse(2.0, 1.0, 120)
    panels = [_panel(ellipse(2.0, 1.1 + 0.2 * i, 90 + i), f"lib/e{i}.csv", 0.02 * (i + 1)) for i in range(n_matches)]
    if tilt is not None:
        q = q @ tilt.T
        panels = [_shown(p.id, p.distance, p.points @ tilt.T, tilt @ p.start, tilt @ p.forward) for p in panels]
    return q, panels


def _read_png(path) -> np.ndarray:
    with open(path, "rb") as f:
        data = f.read()
    assert data[:8] == PNG_SIGNATURE
    with Image.open(io.BytesIO(data)) as im:
        return np.asarray(im.convert("RGB"))


def _check_picture(path, size) -> np.ndarray:
    img = _read_png(path)
    assert (img.shape[1], img.shape[0]) == tuple(size)
    ink = np.any(img < 200, axis=2)  # clearly not white background
    assert ink.mean() > 0.004, "picture is (almost) blank"
    colours = np.unique(img.reshape(-1, 3)[::7], axis=0)
    assert len(colours) > 10
    return img


def _reddish(img) -> int:
    r, g, b = (img[..., i].astype(int) for i in range(3))
    return int(np.sum((r > 150) & (r - g > 60) & (r - b > 60)))


def _greyish(img) -> int:
    r, g, b = (img[..., i].astype(int) for i in range(3))
    return int(np.sum((np.abs(r - g) < 8) & (np.abs(g - b) < 8) & (r > 110) & (r < 190)))


# --------------------------------------------------------------------------- matplotlib pictures


def test_default_picture_is_exact_size_and_drawn(tmp_path, rng, capfd):
    q, panels = _knot_scene(rng, 5)
    out = tmp_path / "show.png"
    r = render_matches(q, "queries/knot.obj", panels, out, renderer="matplotlib")
    assert isinstance(r, RenderResult) and r.renderer == "matplotlib" and r.note is None
    assert r.path == str(out) and r.seconds > 0
    img = _check_picture(out, (1600, 900))
    assert _reddish(img) > 2000 and _greyish(img) > 200  # matches in colour over a grey query
    assert capfd.readouterr().out == ""  # stdout is the CLI's data channel


@pytest.mark.parametrize("size", [(1234, 567), (333, 777)])
def test_odd_sizes_are_exact(tmp_path, size):
    q, panels = _ellipse_scene(1)
    out = tmp_path / "odd.png"
    render_matches(q, "e", panels, out, size=size, renderer="matplotlib")
    _check_picture(out, size)


def test_picture_changes_with_the_match_and_the_distance(tmp_path, rng):
    q, panels = _knot_scene(rng, 2)
    paths = [tmp_path / f"{k}.png" for k in "abc"]
    render_matches(q, "q", panels, paths[0], size=SMALL, renderer="matplotlib")
    other = [panels[0], _panel(panels[1].points * [1.0, 0.6, 1.0], panels[1].id, panels[1].distance)]
    render_matches(q, "q", other, paths[1], size=SMALL, renderer="matplotlib")
    relabelled = [panels[0], _panel(panels[1].points, panels[1].id, 0.9876)]
    render_matches(q, "q", relabelled, paths[2], size=SMALL, renderer="matplotlib")
    a, b, c = (_read_png(p) for p in paths)
    assert np.any(a != b)
    diff = np.argwhere(np.any(a != c, axis=2))
    assert len(diff) > 0
    assert diff[:, 0].max() < SMALL[1] * 0.6  # only a title changed ...
    assert np.array_equal(a[SMALL[1] // 2 + 40 :], c[SMALL[1] // 2 + 40 :])  # ... not the curves


def test_no_matches_draws_the_query_alone(tmp_path, rng):
    q, _ = _knot_scene(rng, 0)
    out = tmp_path / "q.png"
    render_matches(q, "q.csv", [], out, size=SMALL, renderer="matplotlib")
    img = _check_picture(out, SMALL)
    assert _reddish(img) == 0


def test_flags_change_the_title(tmp_path, rng):
    q, panels = _knot_scene(rng, 1)
    p = panels[0]
    plain, flagged = tmp_path / "a.png", tmp_path / "b.png"
    render_matches(q, "q", [p], plain, size=SMALL, renderer="matplotlib")
    render_matches(
        q,
        "q",
        [_shown(p.id, p.distance, p.points, p.start, p.forward, reversed=True, mirrored=True)],
        flagged,
        size=SMALL,
        renderer="matplotlib",
    )
    assert np.any(_read_png(plain) != _read_png(flagged))


# --------------------------------------------------------------------------- 2-D / 3-D


def test_is_coplanar():
    rot = random_rotation(np.random.default_rng(1))
    flat = ellipse(3.0, 1.0, 50)
    assert is_coplanar(flat)
    assert is_coplanar(flat @ rot.T + [5.0, -2.0, 7.0])  # a tilted, moved plane
    assert is_coplanar(flat[:, :2], flat + [0.0, 0.0, 0.0])  # 2 columns: z = 0
    assert not is_coplanar(flat[:, :2], flat + [0.0, 0.0, 0.5])
    assert is_coplanar(flat @ rot.T + 3.0, flat @ rot.T * 0.5 + 3.0)  # same plane through both
    assert is_coplanar(flat[:, :2])
    assert not is_coplanar(torus_knot(2, 3, 100))
    assert not is_coplanar(flat, flat + [0.0, 0.0, 1.0])  # two parallel planes
    bumped = flat.copy()
    bumped[10, 2] = 1e-4 * 6.0
    assert not is_coplanar(bumped)
    assert is_coplanar(bumped, tol=1e-3)
    with pytest.raises(ParameterError):
        is_coplanar(np.array([[0.0, 0.0, np.nan], [1, 0, 0], [0, 1, 0], [1, 1, 1]]))


def test_planar_input_takes_the_2d_view_in_the_query_plane(tmp_path):
    tilt = random_rotation(np.random.default_rng(5))
    q, panels = _ellipse_scene(2, tilt=tilt)
    scene = layout.build_scene(q, "e", panels, SMALL)
    assert scene.planar
    for p in scene.panels:
        assert np.abs(p.points[:, 2]).max() < 1e-9  # the plane faces the viewer
    # the 2:1 ellipse's long axis is horizontal in the view
    span = np.ptp(scene.query, axis=0)
    assert span[0] == pytest.approx(2 * span[1], rel=0.02)
    out = tmp_path / "2d.png"
    render_matches(q, "e", panels, out, size=SMALL, renderer="matplotlib")
    _check_picture(out, SMALL)


def test_z0_input_keeps_x_and_y():
    q, panels = _ellipse_scene(1)
    scene = layout.build_scene(q, "e", panels, SMALL)
    assert scene.planar
    np.testing.assert_allclose(scene.query - scene.query[0], q - q[0], atol=1e-12)


def test_3d_input_takes_the_tilted_3d_view(tmp_path, rng):
    q, panels = _knot_scene(rng, 2)
    scene = layout.build_scene(q, "k", panels, SMALL)
    assert not scene.planar
    # the view is a rotation of the query (no stretching, no mirror) ...
    centred = q - q.mean(axis=0)
    view = np.linalg.lstsq(centred, scene.query - scene.query.mean(axis=0), rcond=None)[0]
    np.testing.assert_allclose(view.T @ view, np.eye(3), atol=1e-9)
    assert np.linalg.det(view) == pytest.approx(1.0)
    # ... looking 30 degrees off the smallest principal axis
    smallest = np.linalg.svd(centred)[2][2]
    towards_viewer = view[:, 2]
    assert abs(smallest @ towards_viewer) == pytest.approx(np.cos(np.radians(30)), abs=1e-9)
    out = tmp_path / "3d.png"
    render_matches(q, "k", panels, out, size=SMALL, renderer="matplotlib")
    _check_picture(out, SMALL)


def test_the_view_depends_on_the_shape_not_on_its_vertices(rng):
    from nfdmatch.descriptors import points_at

    q = (torus_knot(2, 3, 300) * [1.6, 1.0, 0.7]) @ random_rotation(rng).T
    crowded = np.concatenate([[0.0], np.sort(rng.random(899) ** 3)])  # vertices bunched near the start
    uneven = points_at(q, crowded)
    marks = points_at(q, [0.1, 0.37, 0.66])
    probe = [_panel(np.vstack([marks, marks[::-1] * 1.001]))]
    a = layout.build_scene(q, "k", probe, SMALL)
    b = layout.build_scene(uneven, "k", probe, SMALL)
    span = np.ptp(a.query, axis=0).max()
    np.testing.assert_allclose(a.panels[1].points, b.panels[1].points, atol=0.02 * span)


def test_panels_share_one_window_with_equal_aspect(rng):
    q, panels = _knot_scene(rng, 3)
    scene = layout.build_scene(q, "k", panels, (1600, 900))
    x0, x1, y0, y1 = scene.window
    bw, bh = scene.box
    assert (x1 - x0) / (y1 - y0) == pytest.approx(bw / bh)
    everything = np.vstack([p.points for p in scene.panels])
    assert everything[:, 0].min() >= x0 and everything[:, 0].max() <= x1
    assert everything[:, 1].min() >= y0 and everything[:, 1].max() <= y1


@pytest.mark.parametrize("count, grid", [(1, (1, 1)), (2, (1, 2)), (4, (2, 2)), (6, (2, 3)), (12, (3, 4))])
def test_grid_shape_for_the_count(count, grid):
    assert layout.choose_grid(count, (1600, 900), 1.0, 1.0) == grid


# --------------------------------------------------------------------------- labels


def test_short_label():
    assert short_label("/data/knots/trefoil.csv") == "trefoil.csv"
    assert short_label("/data/knots/lissajous.obj#3") == "lissajous.obj#3"
    assert short_label(r"C:\curves\bunny.vtp#12") == "bunny.vtp#12"
    assert short_label("plain") == "plain"
    assert short_label("#3") == "#3"
    long_id = "/x/" + "a_very_long_name_from_a_scanner_" * 3 + "0042.csv#7"
    s = short_label(long_id, 24)
    assert len(s) == 24 and "\u2026" in s
    assert s.startswith("a_very_long") and s.endswith("0042.csv#7")


def test_short_labels_tell_equal_base_names_apart():
    got = short_labels(["a/x.csv", "b/x.csv", "c/y.csv#2", "c/y.csv#3", "r/a/x.csv"])
    assert got[2:4] == ["y.csv#2", "y.csv#3"]
    assert len(set(got)) == 5
    assert got[1] == "b/x.csv" and got[4].endswith("a/x.csv")


# --------------------------------------------------------------------------- errors


def test_unknown_renderer(tmp_path):
    q, panels = _ellipse_scene(1)
    with pytest.raises(ParameterError, match="renderer"):
        render_matches(q, "e", panels, tmp_path / "x.png", renderer="povray")
    assert not (tmp_path / "x.png").exists()


def test_bad_output_paths(tmp_path):
    q, panels = _ellipse_scene(1)
    missing = tmp_path / "no-such-folder" / "x.png"
    with pytest.raises(WriteError, match="folder does not exist") as e:
        render_matches(q, "e", panels, missing, size=SMALL)
    assert str(missing) in str(e.value)
    folder = tmp_path / "adir.png"
    folder.mkdir()
    with pytest.raises(WriteError, match="directory") as e:
        render_matches(q, "e", panels, folder, size=SMALL)
    assert str(folder) in str(e.value)
    with pytest.raises(WriteError) as e:
        render_matrix(np.zeros((2, 2)), ["a", "b"], missing)
    assert str(missing) in str(e.value)
    with pytest.raises(ParameterError, match="PNG"):
        render_matches(q, "e", panels, tmp_path / "x.jpg", size=SMALL)


def test_invalid_arrays(tmp_path):
    q, panels = _ellipse_scene(1)
    out = tmp_path / "x.png"
    bad = q.copy()
    bad[4, 1] = np.nan
    with pytest.raises(ParameterError, match="NaN"):
        render_matches(bad, "e", panels, out)
    p = panels[0]
    with pytest.raises(ParameterError, match="match 1"):
        render_matches(q, "e", [_panel(np.where(np.arange(len(p.points))[:, None] == 3, np.inf, p.points))], out)
    with pytest.raises(ParameterError, match="shape"):
        render_matches(q[:, :1], "e", panels, out)
    with pytest.raises(ParameterError, match="start"):
        render_matches(q, "e", [_shown("m", 0.1, p.points, np.array([np.nan, 0, 0]), p.forward)], out)
    with pytest.raises(ParameterError, match="ShownMatch"):
        render_matches(q, "e", [p.points], out)
    with pytest.raises(ParameterError, match="size"):
        render_matches(q, "e", panels, out, size=(50, 900))
    assert not out.exists()


# --------------------------------------------------------------------------- fallback


def _broken(exc):
    def draw(scene):
        raise exc

    return draw


def test_auto_falls_back_when_the_default_is_unavailable(tmp_path, monkeypatch):
    q, panels = _ellipse_scene(1)
    other = [r for r in RENDERERS if r != DEFAULT_RENDERER][0]
    monkeypatch.setattr(
        render,
        "draw_" + DEFAULT_RENDERER,
        _broken(ImportError(f"No module named {DEFAULT_RENDERER!r}", name=DEFAULT_RENDERER)),
    )
    monkeypatch.setattr(render, "draw_" + other, lambda scene: _tiny_png(scene.size))
    out = tmp_path / "x.png"
    r = render_matches(q, "e", panels, out, size=SMALL)
    assert r.renderer == other
    assert DEFAULT_RENDERER in r.note and "not installed" in r.note and other in r.note
    _read_png(out)


def _tiny_png(size) -> bytes:
    buf = io.BytesIO()
    Image.new("RGB", size, (200, 10, 10)).save(buf, format="PNG")
    return buf.getvalue()


def test_pyvista_unavailable_auto_falls_back_explicit_raises(tmp_path, monkeypatch):
    q, panels = _ellipse_scene(1)
    monkeypatch.setattr(render, "DEFAULT_RENDERER", "pyvista")
    monkeypatch.setattr(render, "draw_pyvista", _broken(render.Unavailable("a test render crashed (signal 11)")))
    out = tmp_path / "x.png"
    r = render_matches(q, "e", panels, out, size=SMALL)
    assert r.renderer == "matplotlib"
    assert "pyvista could not draw" in r.note and "signal 11" in r.note
    _check_picture(out, SMALL)
    os.remove(out)
    with pytest.raises(RenderError) as e:
        render_matches(q, "e", panels, out, size=SMALL, renderer="pyvista")
    msg = str(e.value)
    assert "pyvista cannot render off-screen on this machine" in msg
    assert "signal 11" in msg and "--renderer matplotlib" in msg and str(out) in msg
    assert isinstance(e.value, NfdError) and not out.exists()
    # a failure while drawing (not the machine's off-screen support) is not blamed on the machine
    monkeypatch.setattr(render, "draw_pyvista", _broken(ValueError("bad scalars")))
    with pytest.raises(RenderError, match=r"pyvista could not draw the picture \(ValueError: bad scalars\)"):
        render_matches(q, "e", panels, out, size=SMALL, renderer="pyvista")


def test_every_renderer_failing_is_a_render_error(tmp_path, monkeypatch):
    q, panels = _ellipse_scene(1)
    monkeypatch.setattr(render, "draw_pyvista", _broken(ImportError("No module named 'pyvista'", name="pyvista")))
    monkeypatch.setattr(render, "draw_matplotlib", _broken(RuntimeError("Agg exploded")))
    with pytest.raises(RenderError, match="no renderer could draw") as e:
        render_matches(q, "e", panels, tmp_path / "x.png", size=SMALL)
    assert "pyvista is not installed" in str(e.value) and "Agg exploded" in str(e.value)
    with pytest.raises(RenderError, match="matplotlib could not draw.*--renderer pyvista"):
        render_matches(q, "e", panels, tmp_path / "x.png", size=SMALL, renderer="matplotlib")


def test_probe_failure_is_reported_without_drawing(tmp_path, monkeypatch):
    q, panels = _ellipse_scene(1)
    monkeypatch.setattr(
        pyvista_backend, "_probe_pyvista", lambda: "a test render crashed (signal 11): libOSMesa not found"
    )
    with pytest.raises(RenderError, match=r"off-screen on this machine \(a test render crashed .*libOSMesa"):
        render_matches(q, "e", panels, tmp_path / "x.png", size=SMALL, renderer="pyvista")


def test_probe_reason_reads_vtk_messages():
    stderr = (
        "\x1b[0m\x1b[33m2026-11-23 15:50:44.829 (   0.985s) [    7FAC2807BB80]vtkXOpenGLRenderWindow.:1452"
        "  WARN| bad X server connection. DISPLAY=\x1b[0m\n"
        "\x1b[0m\x1b[33m2026 (0.9s) [7F]vtkOSOpenGLRenderWindow:150   WARN| libOSMesa not found. It appears"
        "\x1b[0m\n"
    )
    reason = pyvista_backend.probe_reason(-11, stderr)
    assert reason.startswith("a test render crashed (signal 11): bad X server connection")
    assert "libOSMesa not found" in reason and "\x1b" not in reason
    assert pyvista_backend.probe_reason(1, "") == "a test render failed (exit status 1)"


# --------------------------------------------------------------------------- pyvista, for real


def test_pyvista_renders_off_screen_or_says_why(tmp_path, rng, capfd):
    """This machine may lack EGL: then a RenderError with a clear message, never a crash."""
    q, panels = _knot_scene(rng, 2)
    out = tmp_path / "pv.png"
    try:
        r = render_matches(q, "k", panels, out, size=SMALL, renderer="pyvista")
    except RenderError as exc:
        msg = str(exc)
        assert "pyvista cannot render off-screen on this machine (" in msg
        assert "; use --renderer matplotlib" in msg
        assert not out.exists()
    else:
        assert r.renderer == "pyvista" and r.note is None
        img = _check_picture(out, SMALL)
        assert _reddish(img) > 300
    assert capfd.readouterr().out == ""


def test_importing_the_cli_does_not_import_a_renderer():
    code = (
        "import sys, nfdmatch.cli, nfdmatch.render\n"
        "heavy = [m for m in ('matplotlib', 'pyvista', 'vtk', 'vtkmodules', 'PIL') if m in sys.modules]\n"
        "assert not heavy, heavy\n"
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr


# --------------------------------------------------------------------------- matrix


def _dark_pixels(path) -> int:
    return int(np.sum(_read_png(path).max(axis=2) < 40))


def test_matrix_picture(tmp_path):
    rng = np.random.default_rng(3)
    pts = rng.random((12, 2))
    m = np.linalg.norm(pts[:, None] - pts[None], axis=2)
    ids = [f"/data/curves/c{i:02d}.csv" for i in range(12)]
    out = tmp_path / "m.png"
    r = render_matrix(m, ids, out, title="exact distance, 12 curves")
    assert r.renderer == "matplotlib" and r.path == str(out)
    _check_picture(out, matrix.matrix_size(12))
    assert matrix.matrix_size(12) == (920, 800)
    sized = tmp_path / "s.png"
    render_matrix(m, ids, sized, size=(700, 650))
    _check_picture(sized, (700, 650))


def test_matrix_darker_is_more_similar(tmp_path):
    n = 6
    near_diagonal = 1.0 - np.eye(n)  # zero on the diagonal only
    far_diagonal = np.eye(n)  # zero everywhere but the diagonal
    a, b = tmp_path / "a.png", tmp_path / "b.png"
    render_matrix(near_diagonal, list("abcdef"), a)
    render_matrix(far_diagonal, list("abcdef"), b)
    assert _dark_pixels(b) > 3 * _dark_pixels(a) > 0


def test_matrix_many_labels(tmp_path):
    n = 90
    m = np.abs(np.subtract.outer(np.arange(n), np.arange(n))).astype(float)
    out = tmp_path / "big.png"
    render_matrix(m, [f"curves/shape-{i:03d}.vtp#{i % 3}" for i in range(n)], out)
    w, h = matrix.matrix_size(n)
    assert 800 <= h <= 3000 and 800 <= w <= 3000
    _check_picture(out, (w, h))


def test_matrix_errors(tmp_path):
    out = tmp_path / "m.png"
    with pytest.raises(ParameterError, match="square"):
        render_matrix(np.zeros((2, 3)), ["a", "b"], out)
    with pytest.raises(ParameterError, match="labels"):
        render_matrix(np.zeros((2, 2)), ["a"], out)
    with pytest.raises(ParameterError, match="NaN"):
        render_matrix(np.array([[0.0, np.nan], [1.0, 0.0]]), ["a", "b"], out)
    assert not out.exists()


def test_no_egl_in_a_real_process_is_an_error_or_a_fallback_never_a_crash(tmp_path):
    """VTK kills the process when it cannot open an off-screen window; the probe must catch
    it. glvnd's EGL finds no driver with this variable (elsewhere it may have no effect)."""
    code = (
        "import sys, numpy as np\n"
        "from nfdmatch import render\n"
        "from nfdmatch.errors import RenderError\n"
        "t = np.linspace(0, 2 * np.pi, 60, endpoint=False)\n"
        "q = np.c_[np.cos(t), np.sin(t), 0.3 * np.sin(3 * t)]\n"
        "from nfdmatch.records import RankedMatch, ShownMatch\n"
        "p = ShownMatch(RankedMatch(1, 'm.csv', 0.1), q * 1.1, q[0] * 1.1, q[3] * 1.1)\n"
        "try:\n"
        "    r = render.render_matches(q, 'q', [p], sys.argv[1], size=(400, 300), renderer='pyvista')\n"
        "    print('drew', r.renderer)\n"
        "except RenderError as e:\n"
        "    print('error', e)\n"
        "render.DEFAULT_RENDERER = 'pyvista'\n"
        "r = render.render_matches(q, 'q', [p], sys.argv[1], size=(400, 300))\n"
        "print('auto', r.renderer, r.note)\n"
    )
    env = dict(os.environ, __EGL_VENDOR_LIBRARY_FILENAMES=os.devnull)
    env.pop("VTK_DEFAULT_OPENGL_WINDOW", None)
    out = tmp_path / "x.png"
    proc = subprocess.run([sys.executable, "-c", code, str(out)], capture_output=True, text=True, env=env)
    assert proc.returncode == 0, proc.stderr
    first, second = proc.stdout.splitlines()
    if first.startswith("error"):
        assert "pyvista cannot render off-screen on this machine (a test render" in first
        assert second.startswith("auto matplotlib pyvista could not draw (a test render")
    else:
        assert first == "drew pyvista" and second == "auto pyvista None"
    _check_picture(out, (400, 300))


def test_short_labels_drop_the_common_affixes_of_long_similar_names():
    ids = [f"contours/column_section-z{i:02d}_at{i / 3:g}_loop0.obj" for i in range(12)]
    labels = short_labels(ids, 28)
    assert labels[5] == "\u2026z05_at1.66667\u2026" and len(set(labels)) == 12
    # short names are left whole
    assert short_labels(["a/x.csv", "b/y.csv"]) == ["x.csv", "y.csv"]


def test_panel_subtitles_carry_distance_flags_and_note(tmp_path):

    q, panels = _ellipse_scene(n_matches=2)
    panels = [
        panels[0],
        _shown(panels[1].id, 0.5, panels[1].points, panels[1].start, panels[1].forward, reversed=True, source="index"),
    ]
    scene = layout.build_scene(q, "q.csv", panels, SMALL)
    assert scene.panels[1].subtitle == "d = 0.02"
    assert scene.panels[2].subtitle == "d = 0.5  \u00b7  reversed  \u00b7  drawn from index harmonics"
    plain = _read_png(
        render_matches(
            q,
            "q.csv",
            panels[:1] + [_panel(panels[1].points, panels[1].id, 0.5, reversed=True)],
            tmp_path / "a.png",
            size=SMALL,
        ).path
    )
    noted = _read_png(render_matches(q, "q.csv", panels, tmp_path / "b.png", size=SMALL).path)
    assert not np.array_equal(plain, noted)


def test_same_picture_again_keeps_the_file_with_a_fresh_mtime(tmp_path):
    q, panels = _ellipse_scene(2)
    out = tmp_path / "same.png"
    render_matches(q, "e", panels, out, size=SMALL)
    os.utime(out, ns=(1, 1))
    inode = out.stat().st_ino
    render_matches(q, "e", panels, out, size=SMALL)
    assert out.stat().st_mtime_ns > 1 and out.stat().st_ino == inode and os.listdir(tmp_path) == ["same.png"]
    render_matches(q, "e", panels[:1], out, size=SMALL)  # a different picture replaces it
    assert out.stat().st_ino != inode and os.listdir(tmp_path) == ["same.png"]


def test_long_ids_that_differ_in_the_middle_get_distinct_titles():
    """Issue 25, item 14: cutting long ids in the middle gave two panels the same title (the
    section number and the minus sign were cut away)."""
    stem, tail = "scans/2026-11-28/blade_root_scan", "loop0_cleaned_resampled_v2.obj"
    ids = [
        f"{stem}_section-z05_at-1.5_{tail}",
        f"{stem}_section-z06_at-1.5_{tail}",
        f"{stem}_section-z05_at1.5_{tail}",
        f"{stem}_section-z15_at-1.5_{tail}",
    ]
    q = ellipse(2.0, 1.0, 120)
    panels = [_panel(ellipse(2.0, 1.1 + 0.1 * i, 90), curve_id, 0.01 * (i + 1)) for i, curve_id in enumerate(ids)]
    scene = layout.build_scene(q, "queries/some_rather_long_query_name_from_the_scanner.obj", panels, SMALL)
    titles = [p.title for p in scene.panels]
    names = [t.split(". ", 1)[1] for t in titles[1:]]  # the ids, without "rank. "
    assert len(set(names)) == len(names) and all(len(n) <= layout.LABEL_WIDTH for n in names), titles
    assert "z06" in titles[2] and "-1.5" in titles[1]
    # the same for the plain shortening of a few ids
    labels = short_labels(ids)
    assert len(set(labels)) == len(ids) and all(len(label) <= layout.LABEL_WIDTH for label in labels)
