"""The output folder's manifest of the files extract wrote, and ``--prune``
(``docs/extract.md``, "Stale files")."""

from __future__ import annotations

from typing import Any, TYPE_CHECKING

import os
from dataclasses import dataclass, field

from ..errors import WriteError
from ..formats._chain import write_if_changed

if TYPE_CHECKING:
    import os
    from collections.abc import Iterable


#: the manifest's file name in an output folder (hidden: no curve reader or walk sees it)
MANIFEST = ".nfdmatch-extract.json"
_MANIFEST_FORMAT = "nfdmatch-extract-manifest"


@dataclass
class PruneResult:
    """What :func:`prune_contours` did: ``removed`` (paths deleted), ``kept`` (``(path,
    reason)`` of files the manifest lists that were left alone: changed since extract wrote
    them, or their mesh failed this run) and ``notes`` (a manifest that could not be read)."""

    removed: list = field(default_factory=list)
    kept: list = field(default_factory=list)
    notes: list = field(default_factory=list)


def sha256_file(path: str) -> str | None:
    import hashlib

    try:
        with open(path, "rb") as fh:
            return hashlib.sha256(fh.read()).hexdigest()
    except OSError:
        return None


def read_manifest(out_dir: str | os.PathLike[str]) -> tuple[dict[str, dict[str, Any]], str | None]:
    """The manifest of ``out_dir``: ``({file name: {"mesh": real path, "sha256": hex}}, problem)``;
    ``problem`` is None, or why an existing manifest could not be used (it is then empty)."""
    import json

    path = os.path.join(str(os.fspath(out_dir)), MANIFEST)
    try:
        with open(path, encoding="utf-8") as fh:
            data = json.load(fh)
    except FileNotFoundError:
        return {}, None
    except (OSError, ValueError) as exc:
        return {}, f"{path}: cannot read the manifest ({type(exc).__name__}); nothing pruned by it"
    except RecursionError:  # brackets nested deeper than Python's JSON parser goes
        return {}, f"{path}: cannot read the manifest (nested too deeply); nothing pruned by it"
    files = data.get("files") if isinstance(data, dict) and data.get("format") == _MANIFEST_FORMAT else None
    if not isinstance(files, dict):
        return {}, f"{path}: not an nfdmatch extract manifest; nothing pruned by it"
    entries = {}
    for name, entry in files.items():
        # only plain names of this folder: a manifest never points elsewhere
        if (
            isinstance(name, str)
            and isinstance(entry, dict)
            and name == os.path.basename(name)
            and name not in ("", ".", "..", MANIFEST)
            and isinstance(entry.get("sha256"), str)
        ):
            entries[name] = {"mesh": str(entry.get("mesh", "")), "sha256": entry["sha256"]}
    return entries, None


def _write_manifest(d: str, entries: dict) -> None:
    import json

    text = (
        json.dumps(
            {"format": _MANIFEST_FORMAT, "version": 1, "files": {name: entries[name] for name in sorted(entries)}},
            indent=1,
            sort_keys=True,
        )
        + "\n"
    )
    target = os.path.join(d, MANIFEST)

    def produce(temp):
        with open(temp, "w", encoding="utf-8", newline="\n") as fh:
            fh.write(text)

    try:
        write_if_changed(target, produce)  # whole, atomically; kept (mtime refreshed) when the same
    except OSError as exc:
        raise WriteError(f"cannot write the manifest ({exc.strerror or exc})", path=target) from None


def _record(d: str, produced: dict) -> None:
    """Add this run's files (name -> mesh) to the manifest; entries of files gone are dropped."""
    entries, _ = read_manifest(d)
    entries = {name: e for name, e in entries.items() if os.path.lexists(os.path.join(d, name))}
    for name, mesh in produced.items():
        sha = sha256_file(os.path.join(d, name))
        if sha is not None:
            entries[name] = {"mesh": os.path.realpath(mesh), "sha256": sha}
    _write_manifest(d, entries)


def prune_contours(
    out_dir: str | os.PathLike[str], written: Iterable[str], *, keep_meshes: Iterable[str] = ()
) -> PruneResult:
    """Remove the contour files of ``out_dir`` that extract wrote in an earlier run and this
    run (``written``, the paths :func:`write_contours` returned) no longer produces: a mesh
    whose levels moved, a deleted mesh. Only files the folder's manifest lists are candidates,
    and only while their content is what extract wrote (same SHA-256): files extract did not
    write, or that were changed since, are never touched. Contours of ``keep_meshes`` (meshes
    that failed to read this run) are kept.

    Raises WriteError when the manifest cannot be rewritten.
    """
    d = str(os.fspath(out_dir))
    entries, problem = read_manifest(d)
    result = PruneResult(notes=[problem] if problem else [])
    produced = {os.path.basename(str(p)) for p in written}
    keep = {os.path.realpath(str(m)) for m in keep_meshes}
    for name in sorted(entries):
        if name in produced:
            continue
        path = os.path.join(d, name)
        entry = entries[name]
        if entry["mesh"] in keep:
            result.kept.append((path, "its mesh could not be read this run"))
            continue
        if not os.path.lexists(path):
            del entries[name]
            continue
        if os.path.islink(path) or sha256_file(path) != entry["sha256"]:
            result.kept.append((path, "changed since extract wrote it; left alone"))
            del entries[name]  # no longer extract's file
            continue
        try:
            os.remove(path)
        except OSError as exc:
            result.kept.append((path, f"cannot remove it ({exc.strerror or exc})"))
            continue
        del entries[name]
        result.removed.append(path)
    _write_manifest(d, entries)
    return result
