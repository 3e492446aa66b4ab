"""Per-file work of a build (stat, hash, read, describe) and the worker pool that runs it."""

from __future__ import annotations

import os
import stat as _stat
import threading
import time

import numpy as np

from ..descriptors import descriptors_batch
from ..errors import NfdError, ReadError
from ..formats import format_of, read_curves
from ..matching import invariants

#: curves described per descriptors_batch call (bounds the (rows x samples x 3) work arrays)
_DESCRIBE_ROWS = 4096


def _sha256(path: str) -> str:
    import hashlib

    h = hashlib.sha256()
    buf = bytearray(1 << 20)
    view = memoryview(buf)
    with open(path, "rb") as fh:
        while True:
            n = fh.readinto(buf)
            if not n:
                break
            h.update(view[:n])
    return h.hexdigest()


def _describe(curves, samples: int, harmonics: int, scale: str) -> dict:
    """Storage-dtype arrays of the /curves datasets (except id and file) for ``curves``."""
    parts = []
    for i in range(0, len(curves), _DESCRIBE_ROWS):
        b = descriptors_batch(curves[i:i + _DESCRIBE_ROWS], samples=samples, harmonics=harmonics, scale=scale)
        m = len(b)
        c64 = b.coefficients.astype(np.complex64)
        inv = invariants(c64.astype(np.complex128))
        parts.append({
            "coefficients": c64,
            "rotation": b.rotation.astype(np.float32),
            "centroid": np.asarray(b.centroid, dtype=np.float64),
            "scale": np.asarray(b.scale, dtype=np.float64),
            "plane_degenerate": np.asarray(b.plane_degenerate, dtype=np.uint8),
            "inv_norm": inv["norm"].reshape(m, harmonics).astype(np.float32),
            "inv_sv": inv["sv"].reshape(m, 2 * harmonics).astype(np.float32),
            "inv_block": inv["block"].reshape(m, 3).astype(np.float32),
        })
    if len(parts) == 1:
        return parts[0]
    return {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}


def _compute_file(path: str, input_format, samples: int, harmonics: int, scale: str, old_sha) -> dict:
    """Stat, hash, read and describe one file. Never raises (except BaseException such as
    KeyboardInterrupt): a failure is returned as ``status "failed"`` with its message.

    With ``old_sha`` given and equal to the file's hash, returns ``status "same"`` without
    parsing the file.
    """
    out = {"path": path, "size": 0, "mtime_ns": 0, "sha256": "", "status": "failed", "error": ""}
    try:
        st = os.stat(path)
        out["size"], out["mtime_ns"] = int(st.st_size), int(st.st_mtime_ns)
        if _stat.S_ISDIR(st.st_mode):
            raise ReadError("is a directory, not a curve file", path=path)
        out["sha256"] = _sha256(path)
        if old_sha and out["sha256"] == old_sha:
            out["status"] = "same"
            return out
        curves = read_curves(path, format=input_format)
        out["arrays"] = _describe(curves, samples, harmonics, scale)
        out["ids"] = [c.id for c in curves]
        out["status"] = "ok"
    except NfdError as exc:
        out["error"] = str(exc)
    except OSError as exc:
        out["error"] = str(ReadError(f"cannot read: {exc.strerror or exc}", path=path))
    except Exception as exc:  # a bug must not sink the build: record it against the file
        out["error"] = f"{path}: unexpected error: {type(exc).__name__}: {exc}"
    return out


def _worker_init(lock_fd) -> None:
    """Pool worker set-up: drop the inherited lock descriptor (so a worker outliving its
    parent cannot keep the index locked) and exit when the parent goes away."""
    if lock_fd is not None:
        try:
            os.close(lock_fd)
        except OSError:
            pass
    parent = os.getppid()

    def watch():
        while True:
            time.sleep(0.5)
            if os.getppid() != parent:
                os._exit(1)

    threading.Thread(target=watch, daemon=True, name="nfdmatch-parent-watch").start()


def _needs_pyvista(tasks) -> bool:
    """True when some task reads a VTK-family file (pyvista costs ~0.3 s to import)."""
    for path, input_format, *_ in tasks:
        try:
            if format_of(path, input_format) in ("vtk", "vtp", "vtu"):
                return True
        except NfdError:
            continue
    return False


def _run_tasks(tasks: list[tuple], jobs: int, lock_fd):
    """Yield ``(task_number, result)`` as tasks finish; in-process when jobs == 1."""
    if jobs <= 1 or len(tasks) <= 1:
        for i, t in enumerate(tasks):
            yield i, _compute_file(*t)
        return
    import multiprocessing  # build-only imports: kept out of query start-up
    from concurrent.futures import ProcessPoolExecutor, as_completed

    if "fork" in multiprocessing.get_all_start_methods() and threading.active_count() == 1:
        ctx, fd = multiprocessing.get_context("fork"), lock_fd      # fast, and safe without threads
        if _needs_pyvista(tasks):           # imported once here rather than once per worker
            try:
                import pyvista  # noqa: F401
            except Exception:
                pass
    else:                                   # forking a multi-threaded process can deadlock
        method = "forkserver" if "forkserver" in multiprocessing.get_all_start_methods() else "spawn"
        ctx, fd = multiprocessing.get_context(method), None
        if method == "forkserver":
            ctx.set_forkserver_preload(["nfdmatch.index"] + (["pyvista"] if _needs_pyvista(tasks) else []))
    executor = ProcessPoolExecutor(max_workers=min(jobs, len(tasks)), mp_context=ctx,
                                   initializer=_worker_init, initargs=(fd,))
    try:
        futures = {executor.submit(_compute_file, *t): i for i, t in enumerate(tasks)}
        for fut in as_completed(futures):
            i = futures[fut]
            try:
                result = fut.result()
            except Exception as exc:   # the worker process died (BrokenProcessPool), pickling, ...
                path = tasks[i][0]
                result = {"path": path, "size": 0, "mtime_ns": 0, "sha256": "", "status": "failed",
                          "error": f"{path}: the worker reading it failed: {type(exc).__name__}: {exc}"}
            yield i, result
    finally:
        executor.shutdown(wait=True, cancel_futures=True)
