"""The pyvista backend (PNG only): a scene drawn off-screen by VTK, after a probe in a
child process (VTK kills the process when no off-screen OpenGL window can be made)."""

from __future__ import annotations

import contextlib
import io
import os
import re
import subprocess
import sys
import warnings

import numpy as np

from .layout import MATCH_COLOR, QUERY_COLOR, Scene, TEXT_COLOR, UNDER_COLOR, Unavailable

# --------------------------------------------------------------------------- pyvista

_PROBE = r"""
import os, sys
os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")
from vtkmodules.vtkRenderingCore import vtkRenderWindow, vtkRenderer
import vtkmodules.vtkRenderingOpenGL2
w = vtkRenderWindow()
w.SetOffScreenRendering(1)
w.SetSize(8, 8)
w.AddRenderer(vtkRenderer())
w.Render()
sys.stdout.write("ok " + w.GetClassName())
"""
_probe_result: dict[str, str | None] = {}
_ANSI = re.compile(r"\x1b\[[0-9;]*m")


def _probe_pyvista() -> str | None:
    """None when VTK can open an off-screen window here, else why not.

    VTK kills the process (segmentation fault) when no off-screen OpenGL window can be
    created (no EGL device, no OSMesa, no X display), so the first pyvista picture of a
    process is preceded by a tiny render in a child process (about 0.3-0.6 s)."""
    key = os.environ.get("VTK_DEFAULT_OPENGL_WINDOW", "")
    if key in _probe_result:
        return _probe_result[key]
    if not sys.executable:
        return None  # cannot start a child: try in-process
    try:
        proc = subprocess.run(
            [sys.executable, "-c", _PROBE],
            capture_output=True,
            text=True,
            timeout=120,
            stdin=subprocess.DEVNULL,
            env=dict(os.environ),
        )
    except (OSError, subprocess.SubprocessError) as exc:
        if isinstance(exc, subprocess.TimeoutExpired):
            result = "a test render did not finish in 120 s"
        else:
            return None
    else:
        if proc.returncode == 0 and proc.stdout.startswith("ok"):
            result = None
        else:
            result = probe_reason(proc.returncode, proc.stderr)
    _probe_result[key] = result
    return result


def probe_reason(returncode: int, stderr: str) -> str:
    """Why the probe's child process could not render, from its exit status and stderr."""
    lines = [_ANSI.sub("", line).strip() for line in stderr.splitlines()]
    lines = [re.sub(r"^.*?(WARN|ERR|ERROR)\|\s*", "", line) for line in lines if line]
    lines = [re.sub(r"^vtk\w+ \(0x[0-9a-f]+\):\s*", "", line) for line in lines]
    useful = [line for line in lines if re.search(r"fail|not found|could not|cannot|bad x server|error", line, re.I)]
    how = (
        f"a test render crashed (signal {-returncode})"
        if returncode < 0
        else f"a test render failed (exit status {returncode})"
    )
    if useful:
        detail = "; ".join(dict.fromkeys(useful[:2]))
        return f"{how}: {detail[:240]}"
    if lines:
        return f"{how}: {lines[-1][:300]}"
    return how


@contextlib.contextmanager
def _stdout_to_stderr():
    """Send anything written to file descriptor 1 (VTK's C++ output) to stderr meanwhile:
    the CLI's stdout carries data."""
    try:
        sys.stdout.flush()
    except Exception:
        pass
    try:
        saved = os.dup(1)
    except OSError:
        yield
        return
    try:
        os.dup2(2, 1)
        yield
    finally:
        os.dup2(saved, 1)
        os.close(saved)


def draw_pyvista(scene: Scene) -> bytes:
    os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")
    with _stdout_to_stderr(), warnings.catch_warnings():
        warnings.simplefilter("ignore")
        import pyvista as pv
        from PIL import Image

        problem = _probe_pyvista()
        if problem is not None:
            raise Unavailable(problem)
        try:
            from vtkmodules.vtkCommonCore import vtkObject

            vtkObject.GlobalWarningDisplayOff()
        except ImportError:
            pass
        plotter = pv.Plotter(
            off_screen=True, window_size=list(scene.size), shape=(scene.rows, scene.cols), border=False
        )
        try:
            _fill_pyvista(pv, plotter, scene)
            img = plotter.screenshot(None, return_img=True)
        finally:
            plotter.close()
    if img is None or img.shape[:2] != (scene.size[1], scene.size[0]):
        got = None if img is None else f"{img.shape[1]}x{img.shape[0]}"
        raise Unavailable(f"the off-screen window gave a {got} picture, not {scene.size[0]}x{scene.size[1]}")
    buf = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(img[:, :, :3])).save(buf, format="PNG")
    return buf.getvalue()


def _fill_pyvista(pv, plotter, scene: Scene) -> None:
    cw, ch = scene.cell
    bw, bh = scene.box
    x0, x1, y0, y1 = scene.window
    units_per_px = (x1 - x0) / bw
    # the data box sits below the title band: centre the camera on the cell, not the box
    fx = (x0 + x1) / 2
    fy = (y0 + y1) / 2 + (ch / 2 - (scene.pad_px + bh / 2)) * units_per_px
    z0, z1 = scene.zrange
    depth = max(z1 - z0, x1 - x0, 1e-9)
    lift = 1e-3 * (x1 - x0)  # planar: draw the match just in front of the query
    tubes = not scene.planar
    n_cells = scene.rows * scene.cols
    for k in range(n_cells):
        r, c = divmod(k, scene.cols)
        plotter.subplot(r, c)
        plotter.set_background("white")
        if k < len(scene.panels):
            panel = scene.panels[k]
            if panel.is_query:
                _curve_pv(pv, plotter, panel.points, QUERY_COLOR, 4.0, tubes)
                _mark_pv(pv, plotter, panel.start, panel.forward, QUERY_COLOR, scene, lift, filled=False)
            else:
                _curve_pv(pv, plotter, scene.query, UNDER_COLOR, 2.0, False)
                _curve_pv(pv, plotter, panel.points + [0, 0, lift], MATCH_COLOR, 4.0, tubes)
                _mark_pv(pv, plotter, scene.query_start, scene.query_forward, UNDER_COLOR, scene, lift, filled=False)
                _mark_pv(pv, plotter, panel.start, panel.forward, MATCH_COLOR, scene, 2 * lift, filled=True)
            subtitle = (
                "dots: start, arrows: direction"
                if panel.is_query and scene.panels[1:]
                else panel.subtitle
                if not panel.is_query
                else ""
            )
            text = panel.title + ("\n" + subtitle if subtitle else "")
            longest = max(len(t) for t in text.splitlines())
            font = min(scene.font_pt * 0.75, (cw - 8) / (0.62 * longest))
            plotter.add_text(text, position="upper_edge", font_size=max(5, int(font)), color=TEXT_COLOR)
        plotter.enable_parallel_projection()
        plotter.camera_position = [(fx, fy, z1 + 4 * depth), (fx, fy, (z0 + z1) / 2), (0.0, 1.0, 0.0)]
        plotter.camera.parallel_scale = ch / 2 * units_per_px
        plotter.camera.clipping_range = (1e-3 * depth, 10 * depth)


def _curve_pv(pv, plotter, pts, color, width, tubes: bool) -> None:
    plotter.add_mesh(
        pv.lines_from_points(pts, close=True),
        color=color,
        line_width=width,
        render_lines_as_tubes=tubes,
        lighting=tubes,
        reset_camera=False,
    )


def _mark_pv(pv, plotter, start, forward, color, scene: Scene, lift: float, *, filled: bool) -> None:
    s = np.asarray(start, dtype=float) + [0, 0, lift]
    d = np.asarray(forward, dtype=float) - np.asarray(start, dtype=float)
    n = float(np.linalg.norm(d))
    if n > 0:
        arrow = pv.Arrow(
            start=s, direction=d / n, scale=scene.arrow, tip_length=0.35, tip_radius=0.2, shaft_radius=0.07
        )
        plotter.add_mesh(arrow, color=color, lighting=not scene.planar, reset_camera=False)
    plotter.add_points(
        s[None, :], color=color, point_size=14 if filled else 12, render_points_as_spheres=True, reset_camera=False
    )
