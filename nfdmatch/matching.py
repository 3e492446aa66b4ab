"""Distances between normalized Fourier descriptors: the exact search, the paper's step,
and the lower bounds used for pruning (pure numpy, vectorized over batches of rows).

Conventions. ``A``, ``B`` are stored half-bands ``(K, 3) complex128`` (frequencies
1..K; the negative frequencies are the conjugates). With weights ``w_k`` (applied
to +k and -k alike)::

    mu^2(A, B) = 2 * sum_k w_k |A_k - B_k|^2

A start shift ``s`` (samples, real) of curve b multiplies ``B_k`` by
``exp(2 pi i s k / n)``: sample ``j`` of a then corresponds to sample ``j + s`` of b.
Reversed traversal replaces ``B_k`` by ``conj(B_k)``: with shift ``s``, sample ``j``
of a corresponds to sample ``-(j + s)`` of b. A rotation ``R`` multiplies every
``B_k`` on the left.

For a fixed shift, ``max_R Re sum A_k^H R B_k = max_R tr(R M)`` with
``M(s) = 2 Re sum_k w_k B_k(s) A_k^H`` (3x3), whose maximum over SO(3) is
``sigma1 + sigma2 + det(M) / (sigma1 sigma2)`` (Kabsch), over O(3)
``sigma1 + sigma2 + sigma3``.
"""

from __future__ import annotations

import os
import threading
from contextlib import contextmanager
from dataclasses import dataclass, field
from functools import lru_cache

import numpy as np

from .descriptors import Descriptors, descriptors, DEFAULT_HARMONICS, DEFAULT_SAMPLES, DEFAULT_SCALE
from .errors import ParameterError

__all__ = ["Match", "distance", "match_descriptors", "exact_search", "grid_maximum", "paper_search", "compile_kernels", "use_kernels",
           "invariants", "lower_bound", "METHODS", "DIRECTIONS"]

METHODS = ("exact", "paper")
DIRECTIONS = ("invariant", "strict")
_REFINE_CANDIDATES = 3        # integer local maxima refined per row


@dataclass(frozen=True)
class Match:
    """The best alignment of curve b onto curve a.

    Attributes
    ----------
    distance : float, the similarity distance mu (0 for the same shape).
    shift : float in [0, samples), the start shift of b in samples (see module doc).
    rotation : (3, 3) float64, in input coordinates: ``a ~ scale * rotation @ b + translation``.
        Proper (det +1) unless ``mirrored``.
    reversed : bool, b is traversed in the opposite direction.
    mirrored : bool, the rotation is a reflection (only with ``mirror=True``).
    method : str, ``"exact"`` or ``"paper"``.
    scale : float, size of a over size of b (by the descriptors' scale measure).
    translation : (3,) float64.
    """

    distance: float
    shift: float
    rotation: np.ndarray = field(repr=False)
    reversed: bool
    mirrored: bool
    method: str
    scale: float = 1.0
    translation: np.ndarray = field(default_factory=lambda: np.zeros(3), repr=False)

    def to_dict(self) -> dict:
        """JSON-ready dict: distance, shift, rotation (3x3 nested list), reversed, mirrored,
        method, scale, translation."""
        return {
            "distance": float(self.distance),
            "shift": float(self.shift),
            "rotation": np.asarray(self.rotation, dtype=float).tolist(),
            "reversed": bool(self.reversed),
            "mirrored": bool(self.mirrored),
            "method": self.method,
            "scale": float(self.scale),
            "translation": np.asarray(self.translation, dtype=float).tolist(),
        }

    def apply(self, points: np.ndarray) -> np.ndarray:
        """Map points of curve b into a's coordinates: ``scale * rotation @ p + translation``.

        points : (m, 3) float64 -> (m, 3) float64.
        """
        return self.scale * np.asarray(points, dtype=np.float64) @ self.rotation.T + self.translation

    def partner_fractions(self, fractions_a, samples: int) -> np.ndarray:
        """Where on b (fraction of b's length from its first vertex, in [0, 1)) the points of a
        at ``fractions_a`` ((m,) float, fractions of a's length) land under this match.

        Sample ``j`` of a corresponds to sample ``j + shift`` of b, or ``-(j + shift)`` when
        reversed; ``samples`` is the n the descriptors were computed with.
        """
        t = (np.asarray(fractions_a, dtype=np.float64) * samples + self.shift) / samples
        return np.mod(-t if self.reversed else t, 1.0)


# --------------------------------------------------------------------------- helpers

def _weights(weights, harmonics: int) -> np.ndarray:
    """(K,) float64 weights w_1..w_K, validated (uniform when None)."""
    if weights is None:
        return np.ones(harmonics)
    w = np.asarray(weights, dtype=np.float64).reshape(-1)
    if w.shape != (harmonics,) or not np.all(np.isfinite(w)) or np.any(w < 0):
        raise ParameterError(f"weights must be {harmonics} finite non-negative numbers "
                             f"(one per harmonic 1..{harmonics}), got shape {w.shape}")
    return w


def _check_direction(direction: str) -> None:
    if direction not in DIRECTIONS:
        raise ParameterError(f"direction must be one of {', '.join(DIRECTIONS)}, got {direction!r}")


_TINY = np.finfo(np.float64).tiny


def _lmax_soa(s00, s11, s22, s01, s02, s12):
    """Largest eigenvalue of symmetric PSD 3x3 matrices given entry-wise (trigonometric formula)."""
    q = (s00 + s11 + s22) * (1.0 / 3.0)
    d0, d1, d2 = s00 - q, s11 - q, s22 - q
    p = np.sqrt((d0 * d0 + d1 * d1 + d2 * d2 + 2.0 * (s01 * s01 + s02 * s02 + s12 * s12)) * (1.0 / 6.0))
    det = d0 * (d1 * d2 - s12 * s12) - s01 * (s01 * d2 - s12 * s02) + s02 * (s01 * s12 - d1 * s02)
    # p == 0 means three equal eigenvalues; then det == 0 and any r gives q
    r = np.minimum(np.maximum(det / np.maximum(2.0 * p * p * p, _TINY), -1.0), 1.0)
    return np.maximum(q + 2.0 * p * np.cos(np.arccos(r) * (1.0 / 3.0)), 0.0)


def _trace_soa(m: np.ndarray, mirror: bool) -> np.ndarray:
    """max_R tr(R M) for matrices given as m = (9, ...) row-major entries (structure of arrays).

    sigma1 from the largest eigenvalue of M^T M, sigma1*sigma2 from the largest of C^T C
    (C the cofactor matrix, singular values s2 s3, s1 s3, s1 s2), sigma3 = |det M| / (s1 s2).
    Only largest eigenvalues are taken: the sqrt of a small one would lose half the
    digits exactly when the curves are near-planar or near-linear.
    """
    a, b, c, d, e, f, g, h, i = m
    l1 = _lmax_soa(a * a + d * d + g * g, b * b + e * e + h * h, c * c + f * f + i * i,
                   a * b + d * e + g * h, a * c + d * f + g * i, b * c + e * f + h * i)
    c00, c01, c02 = e * i - f * h, f * g - d * i, d * h - e * g
    c10, c11, c12 = c * h - b * i, a * i - c * g, b * g - a * h
    c20, c21, c22 = b * f - c * e, c * d - a * f, a * e - b * d
    det = a * c00 + b * c01 + c * c02
    l12 = _lmax_soa(c00 * c00 + c10 * c10 + c20 * c20, c01 * c01 + c11 * c11 + c21 * c21,
                    c02 * c02 + c12 * c12 + c22 * c22, c00 * c01 + c10 * c11 + c20 * c21,
                    c00 * c02 + c10 * c12 + c20 * c22, c01 * c02 + c11 * c12 + c21 * c22)
    s1 = np.sqrt(l1)
    s12 = np.sqrt(l12)
    s2 = s12 / np.maximum(s1, _TINY)
    third = np.minimum(np.maximum(det / np.maximum(s12, _TINY), -s2), s2)
    if mirror:
        third = np.abs(third)
    return s1 + s2 + third


_SMALL_BATCH = 32


def _trace_svd(M: np.ndarray, mirror: bool) -> np.ndarray:
    """Same as :func:`_trace_soa` for (..., 3, 3) matrices through LAPACK (faster for a few)."""
    sv = np.linalg.svd(M, compute_uv=False)
    third = sv[..., 2] if mirror else np.copysign(sv[..., 2], np.linalg.det(M))
    return sv[..., 0] + sv[..., 1] + third


def kabsch_trace(M: np.ndarray, mirror: bool = False) -> np.ndarray:
    """max over rotations R of tr(R M), in closed form, for a stack of 3x3 matrices.

    Parameters
    ----------
    M : (..., 3, 3) float64.
    mirror : allow improper R (reflections): returns sigma1 + sigma2 + sigma3.

    Returns
    -------
    (...,) float64: ``sigma1 + sigma2 + sign(det M) sigma3`` (SO(3)), accurate to a few
    ulps of sigma1 even for rank-deficient M.
    """
    M = np.asarray(M, dtype=np.float64)
    return _trace_soa(np.moveaxis(M.reshape(*M.shape[:-2], 9), -1, 0), mirror)


def _kabsch_rotation(M: np.ndarray, mirror: bool) -> np.ndarray:
    """(..., 3, 3) the R maximizing tr(R M) (SO(3), or O(3) when mirror)."""
    U, _, Vh = np.linalg.svd(M)
    V = np.swapaxes(Vh, -1, -2)
    Ut = np.swapaxes(U, -1, -2)
    if not mirror:
        d = np.sign(np.linalg.det(V @ Ut))
        d = np.where(d == 0, 1.0, d)
        V = V.copy()
        V[..., :, 2] *= d[..., None]
    return V @ Ut


def _direction_variants(B: np.ndarray, direction: str) -> list[tuple[np.ndarray, bool]]:
    _check_direction(direction)
    variants = [(B, False)]
    if direction == "invariant":
        variants.append((np.conj(B), True))
    return variants


@lru_cache(maxsize=32)
def _integer_shift_basis(K: int, n: int) -> np.ndarray:
    """(2K, n) basis for the integer shifts 0..n-1 (cached: the same for every query)."""
    basis = _shift_basis(np.arange(n, dtype=np.float64), K, n)
    basis.setflags(write=False)
    return basis


def _shift_basis(shifts: np.ndarray, K: int, n: int) -> np.ndarray:
    """(..., 2K, m) real basis: [2 cos(2 pi k s / n); -2 sin(2 pi k s / n)] for shifts (..., m).

    With P = [Re P_k, Im P_k] (2K columns), ``P @ basis`` is ``M(s) = 2 Re sum_k P_k e^{2 pi i k s/n}``.
    """
    theta = (2.0 * np.pi / n) * np.arange(1, K + 1)[:, None] * shifts[..., None, :]
    return np.concatenate([2.0 * np.cos(theta), -2.0 * np.sin(theta)], axis=-2)


# --------------------------------------------------------------------------- exact

_REFINE_MID_OFFSETS = np.array([-2.0, -1.0, 0.0, 1.0, 2.0]) / 16.0   # around the first estimate
_REFINE_FINE_STEP = 1e-3                                           # spacing of the last parabola


def _parabola(x, h, f_minus, f_0, f_plus):
    """Maximum of the parabola through (x-h, x, x+h) within [x-h, x+h]: (location, value, concave).

    Not concave: x itself. The value is the parabola's at the (clipped) location, a
    model estimate that callers trust only at spacings where the model is exact to rounding.
    """
    curvature = f_plus - 2.0 * f_0 + f_minus
    slope = 0.5 * (f_plus - f_minus)
    concave = curvature < 0
    safe = np.where(concave, curvature, -1.0)
    t = np.where(concave, np.clip(-slope / safe, -1.0, 1.0), 0.0)
    value = f_0 + t * slope + 0.5 * t * t * np.where(concave, curvature, 0.0)
    return x + t * h, value, concave


def _refine_shifts(Pc, s0, f_minus, f_0, f_plus, n, mirror):
    """Continuous start shift around integer local maxima s0 (C,) with integer-shift values
    f(s0-1), f(s0), f(s0+1) (C,) each; products Pc (C, 9, 2K).

    The objective is smooth with its maximum within one sample of s0. Three parabolic
    steps with shrinking spacing (1 sample, 1/16, 1e-3) land within ~1e-9 samples: the
    error of a parabolic vertex is cubic in spacing and offset. Every evaluated point
    competes, so the result is never worse than s0. Returns (shift (C,), value (C,)).
    """
    C = len(s0)
    K = Pc.shape[2] // 2
    rows = np.arange(C)

    def evaluate(points):                                   # (C, m) -> (C, m)
        M = np.matmul(Pc, _shift_basis(points, K, n))       # (C, 9, m)
        if M.shape[0] * M.shape[2] <= _SMALL_BATCH:         # LAPACK beats ~100 numpy calls here
            return _trace_svd(M.transpose(0, 2, 1).reshape(*points.shape, 3, 3), mirror)
        return _trace_soa(np.moveaxis(M, 1, 0), mirror)

    x1, _, _ = _parabola(s0, 1.0, f_minus, f_0, f_plus)
    mid = x1[:, None] + _REFINE_MID_OFFSETS
    fm = evaluate(mid)
    j = np.clip(np.argmax(fm, axis=1), 1, len(_REFINE_MID_OFFSETS) - 2)
    x2, _, _ = _parabola(mid[rows, j], _REFINE_MID_OFFSETS[1] - _REFINE_MID_OFFSETS[0],
                         fm[rows, j - 1], fm[rows, j], fm[rows, j + 1])
    h = _REFINE_FINE_STEP
    fine = x2[:, None] + np.array([-h, 0.0, h])
    ff = evaluate(fine)
    x3, f3, concave = _parabola(x2, h, ff[:, 0], ff[:, 1], ff[:, 2])
    # at this spacing the parabola is exact to rounding; where it is not concave, x3 = x2
    points = np.concatenate([s0[:, None], mid, fine, x3[:, None]], axis=1)
    values = np.concatenate([f_0[:, None], fm, ff, np.where(concave, f3, -np.inf)[:, None]], axis=1)
    best = np.argmax(values, axis=1)
    return points[rows, best], values[rows, best]


# --------------------------------------------------------------------------- compiled kernels
#
# exact_search also exists as one numba kernel (nfdmatch/_kernels.py): ~7x faster per row
# batched, ~13x per single-pair call, same results (distances to ~1e-15, same shifts where
# the optimum is unique). numba is imported lazily, inside the exact path, once the process
# has done enough exact work to amortize importing it (~0.3 s with loading the cached
# machine code): a ski-rental rule -- switch once the numpy work done so far would have
# paid for the import -- keeps `import nfdmatch`, the CLI start-up and small queries free of
# numba, and costs a long run at most that one import. The very first use after an install
# or an edit of _kernels.py compiles (~10-15 s, once; cached next to the module or in
# numba's user cache). NFDMATCH_NUMBA=0 never uses numba, =1 uses it at once.

_NUMBA_ENV = "NFDMATCH_NUMBA"
#: numpy exact work (rows x directions x shifts, plus _CALL_WORK per call) worth one numba
#: import: the numpy path costs ~0.5 us per unit (~1 ms per call), importing numba and
#: loading the cached kernels ~0.4 s
_NUMBA_AMORTIZE = 800_000
_CALL_WORK = 2_000
#: rows from which a call made on the main thread splits the rows over threads (a call
#: made on another thread, e.g. from search_index's pool over queries, never does)
_THREAD_ROWS = 256
_MAX_THREADS = 4
_kernel_state = {"module": None, "failed": None, "work": 0}
_kernel_lock = threading.Lock()
#: per thread: True inside :func:`reference_path`
_reference = threading.local()


@contextmanager
def reference_path():
    """Within this block, exact_search and grid_maximum on this thread take the numpy path
    (the reference), whatever the process has loaded. Which path a call takes otherwise
    depends on the work the process has done so far, which with queries on threads depends
    on timing; the two paths agree to ~1e-15 but not bit for bit, so a search recomputes the
    distances it reports here to print the same digits run after run."""
    before = getattr(_reference, "on", False)
    _reference.on = True
    try:
        yield
    finally:
        _reference.on = before


def _mode_from_environment(value: str) -> str:
    mode = value.strip().lower()
    if mode in ("0", "off", "no", "false", "numpy"):
        return "off"
    if mode in ("1", "on", "yes", "true", "numba"):
        return "on"
    return "auto"


#: "auto", "on" (numba) or "off" (numpy): NFDMATCH_NUMBA, read once when this module is first
#: imported; :func:`use_kernels` changes it
_kernel_state["mode"] = _mode_from_environment(os.environ.get(_NUMBA_ENV, ""))


def use_kernels(mode: str) -> None:
    """Choose how this process computes exact distances.

    mode : ``"auto"`` (the default: the numba kernels once the process has done enough
        exact work to pay for importing them), ``"numba"`` (from the next call on) or
        ``"numpy"`` (the reference path, never numba). The environment variable
        ``NFDMATCH_NUMBA`` (``auto``, ``1``, ``0``) sets the default when nfdmatch is
        imported; this call is the explicit way for a long-running program.
    """
    modes = {"auto": "auto", "numba": "on", "numpy": "off"}
    if mode not in modes:
        raise ParameterError(f"kernels must be one of {', '.join(modes)}, got {mode!r}")
    with _kernel_lock:
        _kernel_state["mode"] = modes[mode]


def _numba_mode() -> str:
    return _kernel_state.get("mode", "auto")


def _compiled_kernels(work: int):
    """nfdmatch._kernels when it is (or has just become) worth using, else None (numpy path).

    ``work`` is this call's rows x directions x shifts (+ _CALL_WORK). Any failure to import
    numba or to load / compile the kernels (e.g. no writable cache directory: compiling in
    every process would cost more than it saves) falls back to numpy for the rest of the
    process; with NFDMATCH_NUMBA=1 that also warns.
    """
    state = _kernel_state
    mode = _numba_mode()
    if mode == "off" or getattr(_reference, "on", False):
        return None
    if state["module"] is not None or state["failed"] is not None:
        return state["module"]
    state["work"] += work
    if mode == "auto" and state["work"] < _NUMBA_AMORTIZE:
        return None
    with _kernel_lock:
        if state["module"] is None and state["failed"] is None:
            try:
                from . import _kernels
                _warm_up(_kernels)
            except Exception as exc:             # ImportError, numba errors: numpy it is
                state["failed"] = exc
                if mode == "on":
                    import warnings
                    warnings.warn(f"nfdmatch: numba kernels unavailable, using numpy ({exc!r})",
                                  RuntimeWarning, stacklevel=3)
            else:
                state["module"] = _kernels
    return state["module"]


def _warm_up(kernels) -> None:
    """Compile (or load from numba's cache) the kernel on a tiny input with the argument
    types exact_search passes, so that a failure shows here, once."""
    A = np.ones((2, 3), dtype=np.complex128)
    B = np.ones((1, 2, 3), dtype=np.complex128)
    basis, quarter = _folded_basis(2, 8)
    kernels.exact_rows(A, A, np.ones(2), B, 1, basis, quarter, 8, False, 1, True, 1.0)
    kernels.grid_maximum_rows(A, B, 1, basis, quarter, 8, False)


def compile_kernels() -> bool:
    """Compile (or load from numba's cache) the exact-search kernels now and keep them for
    this process. ``make install`` runs it once, so that the first query of a new install
    does not pay the ~15-20 s compile. Returns False when numba cannot be used (the numpy
    path then serves every search)."""
    try:
        from . import _kernels
        _warm_up(_kernels)
    except Exception:                      # ImportError, numba errors: the numpy path serves
        return False
    with _kernel_lock:
        _kernel_state["module"] = _kernels
    return True


@lru_cache(maxsize=32)
def _folded_basis(K: int, n: int) -> tuple[np.ndarray, bool]:
    """The integer-shift basis for the kernels: (2K, width) columns s = 0..n/4 (when n is
    divisible by 4, ``quarter``) or 0..n/2 of [2 cos(2 pi k s / n); -2 sin(2 pi k s / n)], the
    angle reduced exactly ((k s) mod n), zero-padded to a multiple of 8 columns."""
    quarter = n % 4 == 0
    count = n // 4 + 1 if quarter else n // 2 + 1
    width = -(-count // 8) * 8
    s = np.arange(count)
    theta = (2.0 * np.pi / n) * ((np.arange(1, K + 1)[:, None] * s[None, :]) % n)
    basis = np.zeros((2 * K, width))
    basis[:K, :count] = 2.0 * np.cos(theta)
    basis[K:, :count] = -2.0 * np.sin(theta)
    basis.setflags(write=False)
    return basis, quarter


def exact_search(A: np.ndarray, B: np.ndarray, samples: int, *, weights=None,
                 direction: str = "invariant", mirror: bool = False, refine: bool = True,
                 refine_below: float | None = None):
    """The global optimum over start shift x rotation for one query against many rows.

    Parameters
    ----------
    A : (K, 3) complex, the query's normalized half-band.
    B : (N, K, 3) complex, the rows' normalized half-bands (any rotation of each curve).
    samples : n, the sample count the descriptors were computed with.
    weights : (K,) float or None.
    direction : ``"invariant"`` (also score reversed traversal) or ``"strict"``.
    mirror : allow reflections.
    refine : refine the best integer shifts continuously (sub-sample start point).
    refine_below : only refine rows whose refined distance could be at most this (a search's
        current k-th distance); the others keep their integer-shift distance, which is then
        known to stay above ``refine_below``. The bound: refining gains at most C2/8 on the
        objective, C2 = sum_k 2 w_k (2 pi k / n)^2 |A_k| |B_k| bounding |F''(s)|.

    Returns
    -------
    dict of arrays over the N rows: ``distance`` (N,) float64, ``shift`` (N,) float64 in
    [0, n), ``rotation`` (N, 3, 3) float64 mapping B onto A, ``reversed`` (N,) bool,
    ``mirrored`` (N,) bool.

    Method: ``M(s)`` for every integer shift is one real matrix product with the
    2K x n DFT basis; the Kabsch optimum of each is a closed form; the best few local
    maxima per row are refined continuously; the final distance is the direct residual
    at the optimal rotation (no cancellation).
    """
    A = np.asarray(A, dtype=np.complex128)
    B = np.asarray(B, dtype=np.complex128)
    if B.ndim == 2:
        B = B[None]
    N, K, _ = B.shape
    n = int(samples)
    w = _weights(weights, K)
    _check_direction(direction)
    D = 2 if direction == "invariant" else 1
    C = min(_REFINE_CANDIDATES if refine else 1, D * n)
    Aw = np.conj(A) * w[:, None]
    kernels = _compiled_kernels(N * D * n + _CALL_WORK) if N else None
    if kernels is not None:
        # compiled: every stage per row in one call (F per row stays in cache)
        workers = (min(os.cpu_count() or 1, _MAX_THREADS)
                   if N >= _THREAD_ROWS and threading.current_thread() is threading.main_thread() else 1)
        limit = np.inf
        if refine and refine_below is not None and np.isfinite(refine_below):
            limit = refine_below ** 2 * (1 + 1e-9) + 1e-12
        basis, quarter = _folded_basis(K, n)
        dist, shift, R, reversed_, mirrored = kernels.exact_rows(
            np.ascontiguousarray(A), np.ascontiguousarray(Aw), np.ascontiguousarray(w, dtype=np.float64),
            np.ascontiguousarray(B), D, basis, quarter, n, bool(mirror), C, bool(refine), float(limit), workers)
        return {"distance": dist, "shift": shift, "rotation": R, "reversed": reversed_, "mirrored": mirrored}
    Bv = np.stack([v for v, _ in _direction_variants(B, direction)])          # (D, N, K, 3)
    # P[j, i, d, r, k] = 2 w_k B_k[j] conj(A_k[i]): M(s)[j, i] = Re sum_k P e^{2 pi i k s / n}
    P = np.einsum("drkj,ki->jidrk", Bv, Aw)
    Pcat = np.concatenate([P.real, P.imag], axis=-1).reshape(9, D, N, 2 * K)
    F = _trace_soa((Pcat.reshape(-1, 2 * K) @ _integer_shift_basis(K, n))
                   .reshape(9, D, N, n), mirror)                               # (D, N, n)
    F = F.transpose(1, 0, 2)                                                  # (N, D, n)

    local_max = (F >= np.roll(F, 1, axis=2)) & (F >= np.roll(F, -1, axis=2))
    Fm = np.where(local_max, F, -np.inf).reshape(N, D * n)
    cand = np.argpartition(-Fm, C - 1, axis=1)[:, :C]
    values = np.take_along_axis(Fm, cand, axis=1)
    Fmax = Fm.max(axis=1)
    dirs = (cand // n).reshape(-1)
    rows = np.repeat(np.arange(N), C)
    s_int = (cand % n).reshape(-1)
    shifts = s_int.astype(np.float64)
    values = values.reshape(-1)
    if refine:
        todo = np.ones(N * C, dtype=bool)
        if refine_below is not None and np.isfinite(refine_below):
            k = np.arange(1, K + 1)
            norm_a = np.linalg.norm(A, axis=1)
            norm_b = np.linalg.norm(B, axis=2)                                  # (N, K)
            curvature = (2.0 * w * (2.0 * np.pi * k / n) ** 2 * norm_a * norm_b).sum(axis=1)
            squared = 2.0 * (w * norm_a ** 2).sum() + 2.0 * (w * norm_b ** 2).sum(axis=1)
            lower2 = squared - 2.0 * (Fmax + curvature / 8.0)
            todo = np.repeat(lower2 <= refine_below ** 2 * (1 + 1e-9) + 1e-12, C)
        if todo.any():
            sel = np.flatnonzero(todo)
            Pc = Pcat[:, dirs[sel], rows[sel], :].transpose(1, 0, 2)            # (m, 9, 2K)
            Fr = F.reshape(N, D * n)
            base = cand.reshape(-1)[sel] - s_int[sel]
            shifts[sel], values[sel] = _refine_shifts(
                Pc, shifts[sel], Fr[rows[sel], base + (s_int[sel] - 1) % n], values[sel],
                Fr[rows[sel], base + (s_int[sel] + 1) % n], n, mirror)
    values = np.where(np.isfinite(Fmax).repeat(C), values, -np.inf).reshape(N, C)
    pick = np.arange(N) * C + np.argmax(values, axis=1)
    shift, direction_idx = shifts[pick], dirs[pick]

    Bsel = np.where((direction_idx == 1)[:, None, None], np.conj(B), B)       # (N, K, 3)
    Bs = Bsel * np.exp((2j * np.pi / n) * np.outer(shift, np.arange(1, K + 1)))[:, :, None]
    Mbest = 2.0 * np.einsum("nkj,ki->nji", Bs, Aw).real
    R = _kabsch_rotation(Mbest, mirror)
    resid = A[None] - np.einsum("nij,nkj->nki", R, Bs)
    dist = np.sqrt(2.0 * np.einsum("k,nk->n", w, np.sum(resid.real ** 2 + resid.imag ** 2, axis=2)))
    mirrored = np.linalg.det(R) < 0
    shift = np.mod(shift, n)
    shift = np.where(np.abs(shift - np.round(shift)) < 1e-9, np.round(shift), shift) % n  # 127.99999.. -> 0
    return {
        "distance": dist,
        "shift": shift,
        "rotation": R,
        "reversed": direction_idx == 1,        # variants: (B, False), (conj(B), True)
        "mirrored": mirrored,
    }


def grid_maximum(A: np.ndarray, B: np.ndarray, grid: int, *, direction: str = "invariant",
                 mirror: bool = False) -> np.ndarray:
    """max over ``grid`` equally spaced start shifts, both directions (when ``direction`` is
    invariant) and all rotations of the correlation objective, per row.

    Parameters
    ----------
    A : (K, 3) complex, the query's half-band; B : (N, K, 3) complex rows.
    grid : shifts s = g n / grid, g = 0..grid-1 (the objective is evaluated as if the curves
        had ``grid`` samples; 2K < grid).

    Returns
    -------
    (N,) float64: max_g F(g), F = max_R tr(R M(g)) with M(g) = sum_k 2 Re(conj(A_k) B_k^T
    e^{2 pi i k g / grid}) (the exact search's objective, unit weights):
    ``2 |A|^2 + 2 |B|^2 - 2 max F`` is the squared distance at the best grid shift.
    The integer stage of :func:`exact_search` alone (no refinement, no rotation).
    """
    A = np.asarray(A, dtype=np.complex128)
    B = np.asarray(B, dtype=np.complex128)
    N, K, _ = B.shape
    _check_direction(direction)
    D = 2 if direction == "invariant" else 1
    Aw = np.conj(A)
    kernels = _compiled_kernels(N * D * grid + _CALL_WORK) if N else None
    if kernels is not None:
        workers = (min(os.cpu_count() or 1, _MAX_THREADS)
                   if N >= _THREAD_ROWS and threading.current_thread() is threading.main_thread() else 1)
        basis, quarter = _folded_basis(K, grid)
        return kernels.grid_maximum_rows(np.ascontiguousarray(Aw), np.ascontiguousarray(B), D, basis, quarter,
                                         grid, bool(mirror), workers)
    Bv = np.stack([v for v, _ in _direction_variants(B, direction)])          # (D, N, K, 3)
    P = np.einsum("drkj,ki->jidrk", Bv, Aw)
    Pcat = np.concatenate([P.real, P.imag], axis=-1).reshape(9, D, N, 2 * K)
    F = _trace_soa((Pcat.reshape(-1, 2 * K) @ _integer_shift_basis(K, grid)).reshape(9, D, N, grid), mirror)
    return F.max(axis=(0, 2)) if N else np.zeros(0)


# --------------------------------------------------------------------------- paper

_PAPER_VARIANTS = {
    # (transform in the aligned frame, conjugate?, reversed, mirrored). Reversal or a
    # reflection flips the limit-plane normal; the paper's alignment would flip it back
    # to +z, which is what the transform does.
    "forward": (np.eye(3), False, False, False),
    "reversed": (np.diag([1.0, -1.0, -1.0]), True, True, False),
    "mirrored": (np.diag([1.0, -1.0, 1.0]), False, False, True),
    "mirrored_reversed": (np.diag([1.0, 1.0, -1.0]), True, True, True),
}


def _bisector_angle(c1: np.ndarray) -> np.ndarray:
    """Angle in the xy-plane of the bisector of p = Re c1, q = -Im c1; c1 (..., 3) complex."""
    p, q = c1.real[..., :2], -c1.imag[..., :2]
    tiny = np.finfo(float).tiny
    h = p / np.maximum(np.linalg.norm(p, axis=-1, keepdims=True), tiny) \
        + q / np.maximum(np.linalg.norm(q, axis=-1, keepdims=True), tiny)
    return np.arctan2(h[..., 1], h[..., 0])


def paper_search(A: np.ndarray, B: np.ndarray, samples: int, *, weights=None,
                 direction: str = "invariant", mirror: bool = False):
    """The paper's matching step (Zhang & Fiume 2002, section 4.2.3), one query against many rows.

    Both ``A`` (K, 3) and ``B`` (N, K, 3) must be limit-plane aligned (as returned by
    :func:`~nfdmatch.descriptors.descriptors`). For each integer shift, b is rotated about
    z so that the bisectors of its (p, q) and a's coincide; the smallest distance wins.
    Not optimal, kept to reproduce the paper. Direction and mirror handling are ours:
    the reversed / reflected b is re-aligned to +z as the paper would, then searched the same way.

    Returns the same dict as :func:`exact_search`.
    """
    A = np.asarray(A, dtype=np.complex128)
    B = np.asarray(B, dtype=np.complex128)
    if B.ndim == 2:
        B = B[None]
    N, K, _ = B.shape
    n = int(samples)
    w = _weights(weights, K)
    _check_direction(direction)
    names = ["forward"] + (["reversed"] if direction == "invariant" else [])
    if mirror:
        names += ["mirrored"] + (["mirrored_reversed"] if direction == "invariant" else [])
    k = np.arange(1, K + 1)
    shifts = np.arange(n)
    phase = np.exp(2j * np.pi * np.outer(shifts, k) / n)                 # (n, K)
    theta_a = _bisector_angle(A[0])
    best = {"distance": np.full(N, np.inf), "shift": np.zeros(N), "rotation": np.tile(np.eye(3), (N, 1, 1)),
            "reversed": np.zeros(N, bool), "mirrored": np.zeros(N, bool)}
    for name in names:
        T, conj, rev, mir = _PAPER_VARIANTS[name]
        Bv = (np.conj(B) if conj else B) @ T.T                            # (N, K, 3)
        Bs = Bv[:, None, :, :] * phase[None, :, :, None]                  # (N, n, K, 3)
        theta = theta_a - _bisector_angle(Bs[:, :, 0, :])                 # (N, n)
        c, s = np.cos(theta), np.sin(theta)
        x = c[..., None] * Bs[..., 0] - s[..., None] * Bs[..., 1]
        y = s[..., None] * Bs[..., 0] + c[..., None] * Bs[..., 1]
        d2 = 2.0 * np.einsum("k,nsk->ns", w, np.abs(A[:, 0] - x) ** 2 + np.abs(A[:, 1] - y) ** 2
                             + np.abs(A[:, 2] - Bs[..., 2]) ** 2)
        j = np.argmin(d2, axis=1)
        dist = np.sqrt(d2[np.arange(N), j])
        better = dist < best["distance"]
        th = theta[np.arange(N), j]
        Rz = np.zeros((N, 3, 3))
        Rz[:, 0, 0], Rz[:, 0, 1], Rz[:, 1, 0], Rz[:, 1, 1], Rz[:, 2, 2] = (
            np.cos(th), -np.sin(th), np.sin(th), np.cos(th), 1.0)
        best["distance"] = np.where(better, dist, best["distance"])
        best["shift"] = np.where(better, j.astype(float), best["shift"])
        best["rotation"] = np.where(better[:, None, None], Rz @ T, best["rotation"])
        best["reversed"] = np.where(better, rev, best["reversed"])
        best["mirrored"] = np.where(better, mir, best["mirrored"])
    return best


# --------------------------------------------------------------------------- bounds

def invariants(coefficients: np.ndarray, weights=None) -> dict[str, np.ndarray]:
    """Shift-, rotation-, reflection- and reversal-invariant features of descriptors.

    Parameters
    ----------
    coefficients : (..., K, 3) complex, normalized half-bands.
    weights : (K,) or None.

    Returns
    -------
    ``{"norm": (..., K), "sv": (..., 2K), "block": (..., 3)}`` float64, scaled so that
    the Euclidean distance between two curves' features is a lower bound of mu
    (docs/method.md, "Lower bounds": norms, Mirsky on each [Re A_k, Im A_k], and on all blocks).
    """
    C = np.asarray(coefficients, dtype=np.complex128)
    K = C.shape[-2]
    w = _weights(weights, K)
    root = np.sqrt(2.0 * w)
    blocks = np.stack([C.real, C.imag], axis=-1)                          # (..., K, 3, 2)
    norm = np.linalg.norm(C, axis=-1) * root
    sv = np.linalg.svd(blocks, compute_uv=False) * root[:, None]          # (..., K, 2)
    wide = (blocks * np.sqrt(w)[:, None, None]).swapaxes(-3, -2).reshape(*C.shape[:-2], 3, 2 * K)
    block = np.linalg.svd(wide, compute_uv=False) * np.sqrt(2.0)
    return {"norm": norm, "sv": sv.reshape(*C.shape[:-2], 2 * K), "block": block}


def lower_bound(A: np.ndarray, B: np.ndarray, weights=None) -> np.ndarray:
    """max of the three invariant lower bounds of mu(A, B): A (K, 3), B (..., K, 3) -> (...,)."""
    ia, ib = invariants(A, weights), invariants(B, weights)
    return np.max([np.linalg.norm(ib[key] - ia[key], axis=-1) for key in ia], axis=0)


# --------------------------------------------------------------------------- public API

def _as_descriptors(x, samples, harmonics, scale) -> Descriptors:
    if isinstance(x, Descriptors):
        if (x.samples, x.harmonics, x.scale_mode) != (samples, harmonics, scale):
            raise ParameterError(
                f"descriptors of {x.id} were computed with samples={x.samples}, harmonics={x.harmonics}, "
                f"scale={x.scale_mode}, not samples={samples}, harmonics={harmonics}, scale={scale}")
        return x
    return descriptors(x, samples=samples, harmonics=harmonics, scale=scale)


def match_descriptors(da: Descriptors, db: Descriptors, *, method: str = "exact", direction: str = "invariant",
                      mirror: bool = False, weights=None) -> Match:
    """Match two :class:`Descriptors` computed with the same parameters; see :func:`distance`."""
    if (da.samples, da.harmonics, da.scale_mode) != (db.samples, db.harmonics, db.scale_mode):
        raise ParameterError("descriptors were computed with different parameters")
    if method == "exact":
        r = exact_search(da.coefficients, db.coefficients, da.samples, weights=weights,
                         direction=direction, mirror=mirror)
    elif method == "paper":
        r = paper_search(da.coefficients, db.coefficients, da.samples, weights=weights,
                         direction=direction, mirror=mirror)
    else:
        raise ParameterError(f"method must be one of {', '.join(METHODS)}, got {method!r}")
    R_aligned = r["rotation"][0]
    # descriptors live in each curve's plane-aligned frame; map back to input coordinates
    R = da.rotation.T @ R_aligned @ db.rotation
    ratio = da.scale / db.scale
    return Match(distance=float(r["distance"][0]), shift=float(r["shift"][0]), rotation=R,
                 reversed=bool(r["reversed"][0]), mirrored=bool(r["mirrored"][0]), method=method,
                 scale=float(ratio), translation=da.centroid - ratio * R @ db.centroid)


def distance(a, b, *, samples: int = DEFAULT_SAMPLES, harmonics: int = DEFAULT_HARMONICS,
             scale: str = DEFAULT_SCALE, method: str = "exact", direction: str = "invariant",
             mirror: bool = False, weights=None) -> Match:
    """Similarity distance between two closed curves, with the alignment that achieves it.

    Parameters
    ----------
    a, b : :class:`~nfdmatch.curve.Curve`, :class:`~nfdmatch.descriptors.Descriptors`, or
        array-like (n, 3) / (n, 2) float (closed polylines, closing edge implicit).
    samples : arc-length samples per curve (default 128).
    harmonics : K, frequencies +-1..+-K compared (default 16).
    scale : ``"rms"`` (default) or ``"a1"``.
    method : ``"exact"`` (global optimum over shift x SO(3), sub-sample start) or
        ``"paper"`` (the published bisector step; not optimal).
    direction : ``"invariant"`` (default: either traversal direction) or ``"strict"``.
    mirror : also allow reflections.
    weights : (K,) float w_1..w_K or None (uniform).

    Returns
    -------
    :class:`Match`; ``rotation``, ``scale``, ``translation`` and ``shift`` map b onto a.
    """
    da = _as_descriptors(a, samples, harmonics, scale)
    db = _as_descriptors(b, samples, harmonics, scale)
    return match_descriptors(da, db, method=method, direction=direction, mirror=mirror, weights=weights)
