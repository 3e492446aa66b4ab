"""Contour file names (``<stem>_section-<axis><ii>_at<level>_loop<k>``) and writing them."""

from __future__ import annotations

import os
from collections.abc import Sequence

from ..curve import Curve
from ..errors import NfdError, WriteError
from ..formats import FORMATS, format_of, write_curves
from ..formats._chain import write_if_changed
from .contours import _UNSAFE, Contour, mesh_stem
from .manifest import _record


def _unique_stems(meshes: Sequence[str]) -> dict[str, str]:
    """Mesh path -> file-name stem, unique across ``meshes`` (see the module doc)."""
    ordered = list(dict.fromkeys(meshes))
    base = {m: mesh_stem(m) for m in ordered}
    count: dict[str, int] = {}
    for m in ordered:
        count[base[m]] = count.get(base[m], 0) + 1
    stems: dict[str, str] = {}
    taken: set[str] = set()
    for m in ordered:
        stem = base[m]
        if count[stem] > 1:
            ext = os.path.splitext(m)[1].lstrip(".").lower()
            stem = f"{stem}-{_UNSAFE.sub('_', ext)}" if ext else stem
        candidate, k = stem, 1
        while candidate in taken:
            k += 1
            candidate = f"{stem}-{k}"
        taken.add(candidate)
        stems[m] = candidate
    return stems


def write_contours(contours: Sequence[Contour], out_dir, *, format: str = "obj") -> list[str]:
    """Write each contour to its own curve file in ``out_dir`` (created if needed).

    Parameters
    ----------
    contours : the contours of one or several meshes (e.g. of several
        :func:`extract_contours` results).
    out_dir : the folder; existing files of the same name are replaced when their
        content changes and kept (same bytes, fresh mtime: a run that succeeds leaves its
        outputs newer than its inputs, so Make settles) when it would not; other files are
        left alone. Each file is written whole to a hidden temporary file, flushed, then
        renamed (nfdmatch._io). The
        folder's manifest (:data:`MANIFEST`) records every file written, for
        :func:`prune_contours`.
    format : a curve format of :data:`nfdmatch.formats.FORMATS` (``"obj"``,
        ``"csv"``, ``"vtp"``, ...); the file extension is its first one.

    Returns
    -------
    list of the written paths (``os.path.join(out_dir, name + ext)``), in the
    order of ``contours``. Names as :attr:`Contour.name`, made unique across
    meshes sharing a stem (module doc). Each file holds one curve, whose id when
    read back is its path.

    Raises
    ------
    UnknownFormatError : an unknown format.
    WriteError : the folder cannot be created, or a file cannot be written.
    """
    fmt = format_of("contour", format)
    ext = FORMATS[fmt][0]
    d = str(os.fspath(out_dir))
    try:
        os.makedirs(d, exist_ok=True)
    except FileExistsError:
        raise WriteError("cannot create the output folder: a file is in the way", path=d) from None
    except PermissionError:
        raise WriteError("cannot create the output folder: permission denied", path=d) from None
    except OSError as exc:
        raise WriteError(f"cannot create the output folder ({exc.strerror or exc})", path=d) from None
    stems = _unique_stems([c.mesh for c in contours])
    written = []
    produced: dict[str, str] = {}
    for c in contours:
        name = c.name_for(stems[c.mesh])
        target = os.path.join(d, name + ext)
        try:
            curve = Curve.trusted(c.points, name, c.mesh)
            write_if_changed(target, lambda temp: write_curves(temp, [curve], format=fmt))
        except WriteError:
            raise
        except NfdError as exc:
            raise WriteError(f"cannot write the contour: {exc}", path=target) from None
        except OSError as exc:
            raise WriteError(f"cannot write the file ({exc.strerror or exc})", path=target) from None
        except Exception as exc:  # a writer backend (VTK) failing its own way
            raise WriteError(f"cannot write the file ({type(exc).__name__}: {exc})", path=target) from None
        written.append(target)
        produced[os.path.basename(target)] = c.mesh
    _record(d, produced)
    return written


# ---------------------------------------------------------------------------
# the manifest: which files of the folder extract wrote (docs/extract.md)
# ---------------------------------------------------------------------------
