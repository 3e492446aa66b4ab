"""Contour file names (``<stem>_section-<axis><ii>_at<level>_loop<k>``) and writing them."""

from __future__ import annotations

from typing import TYPE_CHECKING

import os
from collections.abc import Sequence

from ..curve import Curve
from ..errors import NfdError, OverwriteRefusedError, WriteError, os_error_message
from ..formats import FORMATS, format_of, write_curves
from ..formats._chain import temp_beside, write_if_changed
from .contours import UNSAFE, Contour, mesh_stem
from .manifest import _record, sha256_file, read_manifest

if TYPE_CHECKING:
    import os


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
            stem = f"{stem}-{UNSAFE.sub('_', ext)}" if ext else stem
        candidate, k = stem, 1
        while candidate in taken:
            k += 1
            candidate = f"{stem}-{k}"
        taken.add(candidate)
        stems[m] = candidate
    return stems


def _targets(contours: Sequence[Contour], d: str, fmt: str) -> list[tuple[Contour, str]]:
    """(contour, path) of every contour, in order: the names :func:`write_contours` writes."""
    ext = FORMATS[fmt][0]
    stems = _unique_stems([c.mesh for c in contours])
    return [(c, os.path.join(d, c.name_for(stems[c.mesh]) + ext)) for c in contours]


def _same_as_written(c: Contour, target: str, fmt: str) -> bool:
    """True when ``target`` holds exactly the bytes extract would write for ``c`` (replacing
    it loses nothing); written to a hidden temporary file beside it and compared."""
    import filecmp

    temp = temp_beside(target)
    try:
        name = os.path.splitext(os.path.basename(target))[0]
        write_curves(temp, [Curve.trusted(c.points, name, c.mesh)], format=fmt)
        return filecmp.cmp(temp, target, shallow=False)
    except (NfdError, OSError):
        return False
    finally:
        if os.path.lexists(temp):
            os.remove(temp)


def refused_targets(
    contours: Sequence[Contour], out_dir: str | os.PathLike[str], *, format: str = "obj"
) -> list[OverwriteRefusedError]:
    """The files :func:`write_contours` would have to replace without ``force`` although they
    are not extract's: one :class:`~nfdmatch.errors.OverwriteRefusedError` per mesh (naming
    its first such file, ``.mesh`` set), in contour order; empty when none.

    A file in the way is extract's own when the folder's manifest lists it and its content
    still has the SHA-256 recorded there (it is not a symbolic link); a file holding exactly
    what would be written is not in the way either. Anything else (a file you put there
    under a contour's name, a contour file you edited since) is refused."""
    fmt = format_of("contour", format)
    d = str(os.fspath(out_dir))
    if not os.path.isdir(d):
        return []
    entries, _ = read_manifest(d)
    found: dict[str, list[str]] = {}
    why: dict[str, str] = {}
    for c, target in _targets(contours, d, fmt):
        if not os.path.lexists(target):
            continue
        entry = entries.get(os.path.basename(target))
        if not os.path.islink(target) and os.path.isfile(target):
            if entry is not None and sha256_file(target) == entry["sha256"]:
                continue
            if _same_as_written(c, target, fmt):
                continue
        found.setdefault(c.mesh, []).append(target)
        why[target] = (
            "extract did not write this file (the folder's manifest does not list it)"
            if entry is None
            else "changed since extract wrote it"
        )
    refused = []
    for mesh, paths in found.items():
        more = f" (and {len(paths) - 1} more of its contour files)" if len(paths) > 1 else ""
        exc = OverwriteRefusedError(
            f"not replaced: {why[paths[0]]}{more}; the contours of {mesh} were not written "
            "(move the file away, or use --force to replace it)",
            path=paths[0],
        )
        exc.mesh = mesh
        refused.append(exc)
    return refused


def write_contours(
    contours: Sequence[Contour], out_dir: str | os.PathLike[str], *, format: str = "obj", force: bool = False
) -> list[str]:
    """Write each contour to its own curve file in ``out_dir`` (created if needed).

    Parameters
    ----------
    contours : the contours of one or several meshes (e.g. of several
        :func:`extract_contours` results).
    out_dir : the folder; existing files of the same name that extract wrote (the
        folder's manifest lists them, content unchanged since) are replaced when their
        content changes and kept (same bytes, fresh mtime: a run that succeeds leaves its
        outputs newer than its inputs, so Make settles) when it would not; other files are
        left alone. Each file is written whole to a hidden temporary file, flushed, then
        renamed (nfdmatch._io). The
        folder's manifest (:data:`MANIFEST`) records every file written, for
        :func:`prune_contours`.
    format : a curve format of :data:`nfdmatch.formats.FORMATS` (``"obj"``,
        ``"csv"``, ``"vtp"``, ...); the file extension is its first one.
    force : replace files of the same name that extract did not write
        (:func:`refused_targets`) and take them over; without it such a file stops the
        call before anything is written.

    Returns
    -------
    list of the written paths (``os.path.join(out_dir, name + ext)``), in the
    order of ``contours``. Names as :attr:`Contour.name`, made unique across
    meshes sharing a stem (module doc). Each file holds one curve, whose id when
    read back is its path.

    Raises
    ------
    UnknownFormatError : an unknown format.
    OverwriteRefusedError : a file extract did not write is in the way (without ``force``).
    WriteError : the folder cannot be created, or a file cannot be written.
    """
    fmt = format_of("contour", format)
    d = str(os.fspath(out_dir))
    try:
        os.makedirs(d, exist_ok=True)
    except OSError as exc:
        known = {
            FileExistsError: "cannot create the output folder: a file is in the way",
            PermissionError: "cannot create the output folder: permission denied",
        }
        raise WriteError(os_error_message(exc, known, "cannot create the output folder"), path=d) from None
    if not force:
        refused = refused_targets(contours, d, format=fmt)
        if refused:
            raise refused[0]
    written = []
    produced: dict[str, str] = {}
    for c, target in _targets(contours, d, fmt):
        name = os.path.splitext(os.path.basename(target))[0]
        try:
            curve = Curve.trusted(c.points, name, c.mesh)
            write_if_changed(target, lambda temp: write_curves(temp, [curve], format=fmt))
        except WriteError as exc:  # named after the file the user asked for, not the hidden temporary one
            raise WriteError(exc.message, path=target) from None
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
