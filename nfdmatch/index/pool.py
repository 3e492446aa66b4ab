"""Per-file work of a build (stat, hash, read, describe) and the worker pool that runs it.

Tasks (one per file to read) are grouped into batches by bytes (:func:`_batches`): many
small files per batch, a large file alone, so that a folder of one-curve files costs one
message and one ``descriptors_batch`` call per batch rather than per file.

The pool (:class:`_Pool`) is our own rather than ``concurrent.futures``: it must know
which file a worker was reading when it died or ran out of time, and it must stop at once
on Ctrl-C. Each worker publishes the task it is reading in a shared slot; the parent waits
on the workers' pipes and process sentinels together, so that

- a worker that dies (a reader's segfault, the OOM killer, a kill) costs a *strike* to the
  file it was reading; the rest of its batch is queued again and a fresh worker started.
  A file with two strikes (it killed a worker, then killed another reading it alone) fails
  with a message; a file with one strike is read again alone. More deaths than the files
  to blame explain abort the build (:class:`WorkerError`): nothing is written, so a sick
  machine cannot shrink an index;
- a file still being read after ``file_timeout`` seconds fails alone: its worker is
  killed, the rest of its batch queued again;
- SIGINT/SIGTERM: workers ignore SIGINT (the terminal sends it to the whole group; only
  the parent acts on it) and die silently on SIGTERM; the parent's KeyboardInterrupt (or
  whatever the caller's SIGTERM handler raises) kills every worker on its way out.

Test hooks: ``_batches`` (the grouping above) and ``_compute_batch`` (a worker's work on
one batch; a test replaces it on cluster workers to kill them) are used by tests.
"""

from __future__ import annotations

import collections
import gc
import hashlib
import os
import signal
import stat as _stat
from typing import Any, Iterator
import threading
import time

import numpy as np

from .._fork import SIGNALS, become_worker
from ..curve import Curve, clean_many
from ..descriptors import descriptors_batch
from ..errors import NfdError, ReadError, WorkerError
from ..formats import format_of, read_curves
from ..formats._chain import curve_id, make_curves, max_file_bytes
from ..formats.csv import bulk_points
from ..matching import invariants
from ..matching.statistics import curve_statistics
from ..mesh.objects import ObjectRule, cut_object, is_mesh_file

#: curves described per descriptors_batch call (bounds the (rows x samples x 3) work arrays)
_DESCRIBE_ROWS = 4096
#: the per-file time limit of the CLI's ``index build`` (seconds; a generous bound for a
#: 100 MB file on a slow disk)
DEFAULT_FILE_TIMEOUT = 600.0
#: at most this many bytes of files per batch (a larger file is a batch alone) ...
_BATCH_BYTES = 256 * 1024
#: ... and at most this many files: one message and one descriptors_batch call per batch
_BATCH_FILES = 128
#: ... and at least this many batches when there is enough to split (keeps both cores busy
#: on a small folder); batch boundaries depend on the task list only, never on ``jobs``, so
#: serial and parallel builds describe the same groups and write identical bits
_MIN_BATCHES = 16
#: worker deaths that no file explains (not followed by the same file killing a worker
#: again) before the build gives up
_SPARE_DEATHS = 8
#: signals a worker must not receive before it has set its handlers
_BLOCKED = SIGNALS


def _sha256_and_size(path: str, size: int) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        if size <= _BATCH_BYTES:  # one read: small files are the common case
            h.update(fh.read())
        else:
            buf = bytearray(1 << 20)
            view = memoryview(buf)
            while True:
                n = fh.readinto(buf)
                if not n:
                    break
                h.update(view[:n])
    return h.hexdigest()


def _sha256(path: str) -> str:
    return _sha256_and_size(path, os.stat(path).st_size)


def _describe(curves, samples: int, harmonics: int, scale: str) -> dict:
    """Storage-dtype arrays of the /curves datasets (except id and file) for ``curves``:
    coefficients (m, K, 3) complex64, rotation (m, 3, 3) float32, centroid (m, 3) and
    scale (m,) float64, plane_degenerate (m,) uint8, inv_norm (m, K), inv_sv (m, 2K),
    inv_block (m, 3) and statistics (m, LENGTH) float32 (the elastic stage's, of the stored
    coefficients)."""
    parts = []
    for i in range(0, len(curves), _DESCRIBE_ROWS):
        b = descriptors_batch(curves[i : i + _DESCRIBE_ROWS], samples=samples, harmonics=harmonics, scale=scale)
        m = len(b)
        c64 = b.coefficients.astype(np.complex64)
        inv = invariants(c64.astype(np.complex128))
        parts.append(
            {
                "coefficients": c64,
                "rotation": b.rotation.astype(np.float32),
                "centroid": np.asarray(b.centroid, dtype=np.float64),
                "scale": np.asarray(b.scale, dtype=np.float64),
                "plane_degenerate": np.asarray(b.plane_degenerate, dtype=np.uint8),
                "inv_norm": inv["norm"].reshape(m, harmonics).astype(np.float32),
                "inv_sv": inv["sv"].reshape(m, 2 * harmonics).astype(np.float32),
                "inv_block": inv["block"].reshape(m, 3).astype(np.float32),
                "statistics": curve_statistics(c64.astype(np.complex128)).reshape(m, -1).astype(np.float32),
            }
        )
    if len(parts) == 1:
        return parts[0]
    return {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}


def _failure(path: str, exc: BaseException) -> str:
    if isinstance(exc, NfdError):
        return str(exc)
    if isinstance(exc, OSError):
        return str(ReadError(f"cannot read: {exc.strerror or exc}", path=path))
    return f"{path}: unexpected error: {type(exc).__name__}: {exc}"


def _test_hook(path: str) -> None:
    """``NFDMATCH_TEST_WORKER_HOOK="ACTION:NAME[,ACTION:NAME...]"`` (for tests: worker deaths
    and hung readers on demand): on reading a file whose base name is NAME (``*``: any),
    ``kill`` SIGKILLs the reading process, ``segv`` sends it SIGSEGV, ``exit`` calls ``os._exit(70)``, ``sleep``
    sleeps an hour; ``killonce`` and ``sleeponce`` do so only the first time (they leave a
    marker file ``NAME.hooked`` next to the file)."""
    spec = os.environ.get("NFDMATCH_TEST_WORKER_HOOK")
    if not spec:
        return
    for item in spec.split(","):
        action, _, name = item.partition(":")
        if name not in ("*", os.path.basename(path)):
            continue
        if action.endswith("once"):
            marker = path + ".hooked"
            if os.path.exists(marker):
                continue
            open(marker, "w").close()
            action = action[:-4]
        if action == "kill":
            os.kill(os.getpid(), signal.SIGKILL)
        elif action == "segv":  # as a C reader's crash
            signal.signal(signal.SIGSEGV, signal.SIG_DFL)
            os.kill(os.getpid(), signal.SIGSEGV)
        elif action == "exit":
            os._exit(70)
        elif action == "sleep":
            time.sleep(3600)


def _fast_points(path: str, data: bytes, input_format) -> np.ndarray | None:
    """The raw vertices of a one-curve CSV file from its bytes ``data`` (read once, for the
    hash too), when the CSV reader's bulk path certainly reads them as :func:`read_curves`
    would; None otherwise (then :func:`read_curves` reads the file, the careful way)."""
    try:
        if format_of(path, input_format) != "csv":
            return None
    except NfdError:
        return None
    if len(data) > max_file_bytes():
        return None
    return bulk_points(data, path)


def _read_file(path: str, input_format, old_sha, raw: bool = False, rule=None) -> tuple[dict, Any]:
    """Stat, hash and read one file: ``(result, curves)``. Never raises (except
    BaseException such as KeyboardInterrupt): a failure is ``status "failed"`` with its
    message; ``status "same"`` when the hash equals ``old_sha`` (the file is not parsed);
    else ``status "ok"`` with its curves.

    ``raw``: a small one-curve CSV file read by the bulk path may come back as its
    uncleaned (n, 3) vertex array instead of a list of curves (the caller cleans many
    at once: :func:`_clean_raw`).

    ``rule``: the object rule as a tuple (:meth:`ObjectRule.as_tuple`): a mesh file (no
    ``input_format``, :func:`~nfdmatch.mesh.objects.is_mesh_file`) is then cut into its
    contours, and the result has ``object``: their axes, levels and measures and the
    object's profile, area and frame (docs/index-format.md, ``/objects``)."""
    out = {"path": path, "size": 0, "mtime_ns": 0, "sha256": "", "status": "failed", "error": ""}
    try:
        st = os.stat(path)
        out["size"], out["mtime_ns"] = int(st.st_size), int(st.st_mtime_ns)
        if _stat.S_ISDIR(st.st_mode):
            raise ReadError("is a directory, not a curve file", path=path)
        if not _stat.S_ISREG(st.st_mode):  # opening a FIFO to hash it would block
            raise ReadError("is not a regular file (a FIFO, device or socket)", path=path)
        _test_hook(path)
        fast = None
        if st.st_size <= _BATCH_BYTES:  # read once: hashed, and parsed when plain CSV
            with open(path, "rb") as fh:
                data = fh.read(st.st_size + 1)
            if len(data) == st.st_size:
                out["sha256"] = hashlib.sha256(data).hexdigest()
                if not (old_sha and out["sha256"] == old_sha):
                    fast = _fast_points(path, data, input_format)
            else:  # it changed since stat: the careful way
                out["sha256"] = _sha256_and_size(path, st.st_size)
            del data
        else:
            out["sha256"] = _sha256_and_size(path, st.st_size)
        if old_sha and out["sha256"] == old_sha:
            out["status"] = "same"
            return out, []
        if fast is not None:
            out["ids"] = [curve_id(path, 0, 1)]
            out["status"] = "ok"
            if raw:
                return out, fast
            curves = make_curves(path, [fast])
            return out, curves
        if rule is not None and input_format is None and is_mesh_file(path):
            curves = _cut(path, rule, out)
        else:
            curves = read_curves(path, format=input_format)
        out["ids"] = [c.id for c in curves]
        out["status"] = "ok"
        return out, curves
    except Exception as exc:  # a bug must not sink the build: record it against the file
        out["error"] = _failure(path, exc)
        out.pop("ids", None)
        out.pop("object", None)
        out["status"] = "failed"
        return out, []


def _cut(path: str, rule: tuple, out: dict) -> list:
    """The contours of the mesh at ``path`` as curves ``path#i``, its object record in
    ``out["object"]``."""
    cut = cut_object(path, ObjectRule.from_tuple(rule))
    n = len(cut.loops)
    out["object"] = {
        "axis": cut.axis,
        "level": cut.level,
        "measures": cut.measures,
        "profile": cut.profile,
        "area": cut.area,
        "frame": cut.frame,
    }
    return [Curve.trusted(pts, curve_id(path, i, n), path, i) for i, pts in enumerate(cut.loops)]


def _clean_raw(results: list, raw: list) -> list:
    """Curves of the files read raw (``(result index, path, vertices)``, each one curve), cleaned
    in one vectorized pass (:func:`clean_many`); should any curve be bad, file by file as
    :func:`read_curves` does, a bad one marking its result failed with the same message.
    Returns ``[(result index, [Curve])]`` of the good ones."""
    try:
        cleaned = clean_many([a for _, _, a in raw])
        return [(r, [Curve.trusted(pts, curve_id(p, 0, 1), p, None)]) for (r, p, _), pts in zip(raw, cleaned)]
    except Exception:
        pass
    good = []
    for r, p, a in raw:
        try:
            good.append((r, make_curves(p, [a])))
        except Exception as exc:
            out = results[r]
            out.update(status="failed", error=_failure(p, exc))
            out.pop("ids", None)
    return good


def _compute_file(path: str, input_format, samples: int, harmonics: int, scale: str, old_sha, rule=None) -> dict:
    """One file's result: as :func:`_read_file`, with ``arrays`` (see :func:`_describe`)
    when ``status`` is "ok"."""
    out, curves = _read_file(path, input_format, old_sha, rule=rule)
    if out["status"] == "ok":
        try:
            out["arrays"] = _describe(curves, samples, harmonics, scale)
        except Exception as exc:
            out.update(status="failed", error=_failure(path, exc))
            out.pop("ids", None)
    return out


def _compute_batch(batch: list[tuple[int, tuple]], slot=None) -> tuple[list, dict | None]:
    """Read every file of ``batch`` (``(task_number, task)`` pairs; a task is ``(path,
    input_format, samples, harmonics, scale, old_sha)``, the same parameters throughout)
    and describe all their curves with one call.

    Returns ``(results, arrays)``: one result per task (as :func:`_read_file`, with
    ``rows`` for an "ok" one) and the arrays of :func:`_describe` of the "ok" files'
    curves, in batch order (None when there are none). ``slot`` (a shared double array of
    2), when given, holds the task being read and since when (``time.monotonic()``), -1
    between files: the pool reads it to blame a death or a timeout on one file.
    """
    results, raw, per_file = [], [], []
    for number, (path, input_format, _samples, _harmonics, _scale, old_sha, *rule) in batch:
        if slot is not None:
            slot[1] = time.monotonic()
            slot[0] = number
        out, file_curves = _read_file(path, input_format, old_sha, raw=True, rule=rule[0] if rule else None)
        if isinstance(file_curves, np.ndarray):
            raw.append((len(results), path, file_curves))
        elif file_curves:
            per_file.append((len(results), file_curves))
        results.append(out)
    if raw:
        if slot is not None:  # cleaning many at once: no one file to blame
            slot[0] = -1
        per_file.extend(_clean_raw(results, raw))
        per_file.sort(key=lambda rc: rc[0])
    if slot is not None:
        slot[0] = -1
    curves, owners = [], []
    for r, file_curves in per_file:
        results[r]["rows"] = len(file_curves)
        owners.append(r)
        curves.extend(file_curves)
    if not curves:
        return results, None
    samples, harmonics, scale = batch[0][1][2:5]
    try:
        return results, _describe(curves, samples, harmonics, scale)
    except Exception:
        pass
    # something in the batch cannot be described: describe file by file to blame one
    parts, start = [], 0
    for r in owners:
        out = results[r]
        n = out["rows"]
        try:
            parts.append(_describe(curves[start : start + n], samples, harmonics, scale))
        except Exception as exc:
            out.update(status="failed", error=_failure(out["path"], exc))
            out.pop("ids", None)
            out.pop("rows", None)
            out.pop("object", None)
        start += n
    if not parts:
        return results, None
    return results, {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}


def _split(results: list, arrays: dict | None):
    """``(result, ...)`` per file of a batch, each "ok" one with its rows of ``arrays``."""
    start = 0
    for out in results:
        n = out.pop("rows", 0)
        if out["status"] == "ok":
            out["arrays"] = {k: v[start : start + n] for k, v in arrays.items()}
            start += n
        yield out


def _batches(tasks: list[tuple]) -> list[list[int]]:
    """Task numbers grouped in file order into batches of at most ``_BATCH_FILES`` files
    and about ``_BATCH_BYTES`` bytes (a larger file alone), smaller when that many bytes
    would make fewer than ``_MIN_BATCHES`` batches. Depends on the tasks only."""
    sizes = []
    for t in tasks:
        try:
            sizes.append(os.stat(t[0]).st_size)
        except OSError:
            sizes.append(0)
    limit = max(1, min(_BATCH_BYTES, sum(sizes) // _MIN_BATCHES))
    files = max(1, min(_BATCH_FILES, -(-len(tasks) // _MIN_BATCHES)))
    out, current, current_bytes = [], [], 0
    for i, size in enumerate(sizes):
        if current and (
            current_bytes + size > limit or len(current) >= files or tasks[i][2:5] != tasks[current[0]][2:5]
        ):
            out.append(current)
            current, current_bytes = [], 0
        current.append(i)
        current_bytes += size
    if current:
        out.append(current)
    return out


# --------------------------------------------------------------------------- worker processes


def _worker_main(conn, slot, lock_fd) -> None:
    """A pool worker: ``(batch_id, batch, NFDMATCH_* environment)`` in on ``conn`` (None:
    exit), ``(batch_id, results, arrays)`` out (see :func:`_compute_batch`)."""
    # SIGINT ignored (the terminal's reaches the whole process group: only the parent acts
    # on it), the index lock closed (a worker outliving its parent must not keep the index
    # locked), and an end with the parent
    become_worker([lock_fd])
    try:
        while True:
            msg = conn.recv()
            if msg is None:
                break
            batch_id, batch, env = msg
            _set_environment(env)
            results, arrays = _compute_batch(batch, slot)
            conn.send((batch_id, results, arrays))
    except (EOFError, OSError):  # the parent went away: nothing to report to
        pass
    os._exit(0)  # no atexit handlers: the parent owns every open file


def _environment() -> dict:
    """The NFDMATCH_* variables of this process (limits such as NFDMATCH_MAX_FILE_BYTES)."""
    return {k: v for k, v in os.environ.items() if k.startswith("NFDMATCH_")}


def _set_environment(env: dict) -> None:
    """Make a worker's NFDMATCH_* variables the parent's: a forkserver worker inherits the
    environment of when the fork server started, not the parent's of now."""
    for k in [k for k in os.environ if k.startswith("NFDMATCH_") and k not in env]:
        del os.environ[k]
    os.environ.update(env)


def _signal_name(code) -> str:
    if code is None:
        return "unknown cause"
    if code < 0:
        try:
            return f"killed by {signal.Signals(-code).name}"
        except ValueError:
            return f"killed by signal {-code}"
    return f"exit status {code}"


class _Worker:
    def __init__(self, ctx, lock_fd):
        self.conn, child = ctx.Pipe()
        self.slot = ctx.RawArray("d", [-1.0, 0.0])
        self.proc = ctx.Process(
            target=_worker_main, args=(child, self.slot, lock_fd), daemon=True, name="nfdmatch-build-worker"
        )
        self.batch: list[int] | None = None  # task numbers sent, not answered yet
        self.batch_id = -1
        self.proc.start()
        child.close()

    def reading(self) -> tuple[int, float]:
        """(task number, since when) of the file being read, task -1 if none."""
        number, since = int(self.slot[0]), float(self.slot[1])
        return number, since

    def kill(self) -> None:
        try:
            self.proc.kill()
        except Exception:
            pass

    def close(self) -> None:
        self.kill()
        self.proc.join(5)
        try:
            self.conn.close()
        except OSError:
            pass


def _context(tasks):
    import multiprocessing  # build-only imports: kept out of query start-up

    if "fork" in multiprocessing.get_all_start_methods() and threading.active_count() == 1:
        if _needs_pyvista(tasks):  # imported once here rather than once per worker
            try:
                import pyvista  # noqa: F401
            except Exception:
                pass
        return multiprocessing.get_context("fork"), True  # fast, and safe without threads
    # forking a multi-threaded process can deadlock
    method = "forkserver" if "forkserver" in multiprocessing.get_all_start_methods() else "spawn"
    ctx = multiprocessing.get_context(method)
    if method == "forkserver":
        ctx.set_forkserver_preload(["nfdmatch.index"] + (["pyvista"] if _needs_pyvista(tasks) else []))
    return ctx, False


def _needs_pyvista(tasks) -> bool:
    """True when some task reads a VTK-family file (pyvista costs ~0.3 s to import)."""
    for path, input_format, *_ in tasks:
        try:
            if format_of(path, input_format) in ("vtk", "vtp", "vtu"):
                return True
        except NfdError:
            continue
    return False


def _failed(path: str, message: str) -> dict:
    return {"path": path, "size": 0, "mtime_ns": 0, "sha256": "", "status": "failed", "error": message}


class _Pool:
    """The worker processes of one build and the work not done yet: batches queued (again,
    after a death), strikes against files whose reader died, deaths counted."""

    def __init__(self, tasks: list[tuple], jobs: int, lock_fd, file_timeout: float | None):
        self.tasks = tasks
        self.file_timeout = file_timeout
        self.ctx, self.forked = _context(tasks)
        self.lock_fd = lock_fd if self.forked else None
        self.env = _environment()
        self.queue = collections.deque(_batches(tasks))
        self.jobs = max(1, min(jobs, len(self.queue)))
        self.strikes: collections.Counter = collections.Counter()
        self.deaths = self.blamed = 0
        self.workers: list[_Worker] = []
        self.batches = 0

    def start(self) -> _Worker:
        # SIGINT/SIGTERM held back across the fork: a worker gets them only once it ignores them
        old = signal.pthread_sigmask(signal.SIG_BLOCK, _BLOCKED)
        if self.forked:
            # as _fork.fork_map: no garbage of the parent's is finalized in a forked worker (a
            # file object collected there would be flushed and closed behind the parent's
            # back); collected here first, the rest frozen for the worker's collector
            gc.collect()
            gc.freeze()
        try:
            w = _Worker(self.ctx, self.lock_fd)
            self.workers.append(w)
        finally:
            if self.forked:
                gc.unfreeze()
            signal.pthread_sigmask(signal.SIG_SETMASK, old)
        return w

    def feed(self, w: _Worker) -> None:
        """Send ``w`` the next batch queued (``w.batch`` None: nothing left for it)."""
        if not self.queue:
            w.batch = None
            return
        w.batch = self.queue.popleft()
        w.batch_id, self.batches = self.batches, self.batches + 1
        try:
            w.conn.send((w.batch_id, [(i, self.tasks[i]) for i in w.batch], self.env))
        except OSError:  # it died since its last answer: its death is handled by the loop
            self.queue.appendleft(w.batch)
            w.batch = []

    def replace(self, w: _Worker) -> None:
        w.close()
        self.workers.remove(w)
        if self.queue:
            self.feed(self.start())

    def busy(self) -> list[_Worker]:
        """The workers with a batch, after idle ones took work that a death queued again."""
        for w in self.workers:
            if w.batch is None and self.queue:
                self.feed(w)
        return [w for w in self.workers if w.batch is not None]

    def wait_time(self, busy: list[_Worker]) -> float | None:
        """How long to wait for answers: until the first file reaches the time limit (at
        most a second, at least 10 ms); None without a limit."""
        if not self.file_timeout:
            return None
        now = time.monotonic()
        ends = []
        for w in busy:
            number, since = w.reading()
            ends.append((since if number >= 0 else now) + self.file_timeout)
        return min(max(0.01, min(ends) - now), 1.0)

    def died(self, w: _Worker) -> tuple[str, tuple | None]:
        """The worker died: blame the file it was reading, queue the rest again. Returns the
        cause and, for a file that killed its reader twice, its ``(task, failed result)``."""
        w.proc.join(5)
        cause = _signal_name(w.proc.exitcode)
        number, _ = w.reading()
        batch = w.batch
        if number < 0 and len(batch) == 1:  # died describing or sending its one file
            number = batch[0]
        elif number < 0:  # ... one of these: try them one by one
            self.queue.extendleft([i] for i in reversed(batch))
            batch = []
        self.deaths += 1
        rest = [i for i in batch if i != number]
        if rest:
            self.queue.appendleft(rest)
        if number < 0 or number not in batch:
            return cause, None
        self.strikes[number] += 1
        if self.strikes[number] < 2:
            self.queue.appendleft([number])  # again, alone, in a fresh worker
            return cause, None
        self.blamed += 1
        path = self.tasks[number][0]
        return cause, (
            number,
            _failed(path, f"{path}: the process reading it died twice ({cause}); the file crashes its reader"),
        )

    def bury(self, w: _Worker, cause: str) -> None:
        """Replace a dead worker, unless more have died than the files to blame explain."""
        if self.deaths > _SPARE_DEATHS + 2 * self.blamed:
            raise WorkerError(
                f"worker processes keep dying ({self.deaths} deaths, last: {cause}), "
                f"not because of one file (out of memory?); nothing was written"
            )
        self.replace(w)

    def overtime(self, w: _Worker) -> tuple | None:
        """``(task, failed result)`` of the file ``w`` has been reading for longer than the
        time limit (``w`` is replaced, the rest of its batch queued again); else None."""
        number, since = w.reading()
        if number < 0 or time.monotonic() - since <= self.file_timeout:
            return None
        rest = [i for i in w.batch if i != number]
        if rest:
            self.queue.appendleft(rest)
        path = self.tasks[number][0]
        self.replace(w)
        return (
            number,
            _failed(
                path,
                f"{path}: reading it took longer than {self.file_timeout:g} s "
                f"(the per-file time limit, --file-timeout); stopped",
            ),
        )

    def stop(self) -> None:
        """Tell every worker there is no more work (they exit)."""
        for w in self.workers:
            try:
                w.conn.send(None)
            except OSError:
                pass

    def close(self) -> None:
        for w in self.workers:
            w.close()


def _answer(w: _Worker):
    """The worker's answer ``(batch id, results, arrays)``, None if it died instead."""
    try:
        if w.conn.poll():
            return w.conn.recv()
    except (EOFError, OSError):
        pass
    return None


def _run_pool(tasks: list[tuple], jobs: int, lock_fd, file_timeout: float | None):
    """Yield ``(task_number, result)`` as batches finish in worker processes (see the
    module docstring for deaths, time limits and signals)."""
    pool = _Pool(tasks, jobs, lock_fd, file_timeout)

    from multiprocessing.connection import wait

    try:
        for _ in range(pool.jobs):
            pool.feed(pool.start())
        while any(w.batch is not None for w in pool.workers):
            busy = pool.busy()
            ready = set(wait([w.conn for w in busy] + [w.proc.sentinel for w in busy], pool.wait_time(busy)))
            for w in busy:
                if w.conn in ready or w.proc.sentinel in ready:
                    msg = _answer(w)
                    if msg is not None:
                        batch = w.batch
                        pool.feed(w)
                        _, results, arrays = msg
                        for i, out in zip(batch, _split(results, arrays)):
                            yield i, out
                        continue
                    cause, failure = pool.died(w)
                    if failure is not None:
                        yield failure
                    pool.bury(w, cause)
                elif file_timeout:
                    failure = pool.overtime(w)
                    if failure is not None:
                        yield failure
        pool.stop()
    finally:
        pool.close()


def run_tasks(
    tasks: list[tuple], jobs: int, lock_fd: int | None, file_timeout: float | None = None
) -> Iterator[tuple[int, Any]]:
    """Yield ``(task_number, result)`` for every task (in batch order, not task order).

    In this process when ``jobs`` is 1 and there is no ``file_timeout`` (a hung or
    crashing reader then hangs or kills the caller: only a worker process can be stopped);
    else in worker processes (at least one, also for ``jobs`` 1).
    """
    if not tasks:
        return
    if jobs <= 1 and not file_timeout:
        for batch in _batches(tasks):
            results, arrays = _compute_batch([(i, tasks[i]) for i in batch])
            for i, out in zip(batch, _split(results, arrays)):
                yield i, out
        return
    yield from _run_pool(tasks, jobs, lock_fd, file_timeout)
