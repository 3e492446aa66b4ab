"""Distances between normalized Fourier descriptors: the exact search, the paper's step,
and the lower bounds used for pruning (pure numpy, vectorized over batches of rows).

Modules: :mod:`.common` (names, Kabsch trace, shift bases), :mod:`.exact`, :mod:`.paper`,
:mod:`.bounds`, :mod:`.kernels` (which implementation: numpy, or the kernels of
:mod:`._kernels` compiled ahead of time or by numba); this one holds the public API
(:class:`Match`, :func:`distance`, :func:`match_descriptors`).

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

from dataclasses import dataclass, field
from typing import Any, TYPE_CHECKING

import numpy as np

from ..descriptors import DEFAULT_HARMONICS, DEFAULT_SAMPLES, DEFAULT_SCALE, Descriptors, descriptors
from ..errors import ParameterError
from .bounds import invariants, lower_bound
from .common import (
    DEFAULT_DIRECTION,
    DEFAULT_METHOD,
    DIRECTIONS,
    EXACT,
    INVARIANT,
    METHODS,
    PAPER,
    STRICT,
    STRICT_DIRECTION,
    kabsch_trace,
)
from .kernels import NUMPY, Kernels, compile_kernels, use_kernels
from .exact import exact_search, grid_bound, grid_maximum
from .paper import paper_search

if TYPE_CHECKING:
    from numpy.typing import ArrayLike

    from ..curve import Curve

__all__ = [
    "Match",
    "MatchParameters",
    "distance",
    "match_descriptors",
    "exact_search",
    "grid_bound",
    "grid_maximum",
    "paper_search",
    "compile_kernels",
    "use_kernels",
    "Kernels",
    "NUMPY",
    "kabsch_trace",
    "invariants",
    "lower_bound",
    "METHODS",
    "DIRECTIONS",
    "DEFAULT_METHOD",
    "DEFAULT_DIRECTION",
    "STRICT_DIRECTION",
    "EXACT",
    "PAPER",
    "INVARIANT",
    "STRICT",
]


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

    def partner_fractions(self, fractions_a: ArrayLike, samples: int) -> np.ndarray:
        """Where on b (fraction of b's length from its first vertex, in [0, 1)) the points of a
        at ``fractions_a`` ((m,) float, fractions of a's length) land under this match.

        Sample ``j`` of a corresponds to sample ``j + shift`` of b, or ``-(j + shift)`` when
        reversed; ``samples`` is the n the descriptors were computed with.
        """
        t = (np.asarray(fractions_a, dtype=np.float64) * samples + self.shift) / samples
        return np.mod(-t if self.reversed else t, 1.0)


# --------------------------------------------------------------------------- public API


@dataclass(frozen=True)
class MatchParameters:
    """The parameters of a distance between curves, in one object: how each curve is
    described (``samples``, ``harmonics``, ``scale``, as in
    :func:`~nfdmatch.descriptors.descriptors`) and how two descriptions are matched
    (``method``, ``direction``, ``mirror``, ``weights``, as in :func:`match_descriptors`).
    :func:`distance`, :func:`~nfdmatch.search.rank_curves` and
    :func:`~nfdmatch.search.distance_matrix` take these fields by keyword and make one.

    Attributes
    ----------
    samples : int, arc-length samples per curve (default 128).
    harmonics : int K, frequencies +-1..+-K compared (default 16).
    scale : ``"rms"`` (default) or ``"a1"``.
    method : ``"exact"`` (global optimum over shift x SO(3), sub-sample start) or
        ``"paper"`` (the published bisector step; not optimal).
    direction : ``"invariant"`` (default: either traversal direction) or ``"strict"``.
    mirror : bool, also allow reflections.
    weights : (K,) float w_1..w_K or None (uniform).
    """

    samples: int = DEFAULT_SAMPLES
    harmonics: int = DEFAULT_HARMONICS
    scale: str = DEFAULT_SCALE
    method: str = DEFAULT_METHOD
    direction: str = DEFAULT_DIRECTION
    mirror: bool = False
    weights: ArrayLike | None = None

    @property
    def descriptor(self) -> dict:
        """``samples``, ``harmonics``, ``scale``: keywords of :func:`~nfdmatch.descriptors.descriptors`."""
        return {"samples": self.samples, "harmonics": self.harmonics, "scale": self.scale}

    @property
    def matching(self) -> dict:
        """``method``, ``direction``, ``mirror``, ``weights``: keywords of :func:`match_descriptors`."""
        return {"method": self.method, "direction": self.direction, "mirror": self.mirror, "weights": self.weights}


def _as_descriptors(x, samples, harmonics, scale) -> Descriptors:
    if isinstance(x, Descriptors):
        if (x.samples, x.harmonics, x.scale_mode) != (samples, harmonics, scale):
            raise ParameterError(
                f"descriptors of {x.id} were computed with samples={x.samples}, harmonics={x.harmonics}, "
                f"scale={x.scale_mode}, not samples={samples}, harmonics={harmonics}, scale={scale}"
            )
        return x
    return descriptors(x, samples=samples, harmonics=harmonics, scale=scale)


def match_descriptors(
    da: Descriptors,
    db: Descriptors,
    *,
    method: str = DEFAULT_METHOD,
    direction: str = DEFAULT_DIRECTION,
    mirror: bool = False,
    weights: ArrayLike | None = None,
) -> Match:
    """Match two :class:`Descriptors` computed with the same parameters; see :func:`distance`.

    One pair is computed on the numpy reference path (about a millisecond): the same digits
    whichever compiled kernels the process has (they agree to ~1e-15, not bit for bit), so
    that `distance`, `show` and their pictures are the same bytes on every install."""
    if (da.samples, da.harmonics, da.scale_mode) != (db.samples, db.harmonics, db.scale_mode):
        raise ParameterError("descriptors were computed with different parameters")
    if method == EXACT:
        r = exact_search(
            da.coefficients,
            db.coefficients,
            da.samples,
            weights=weights,
            direction=direction,
            mirror=mirror,
            kernels=NUMPY,
        )
    elif method == "paper":
        r = paper_search(
            da.coefficients, db.coefficients, da.samples, weights=weights, direction=direction, mirror=mirror
        )
    else:
        raise ParameterError(f"method must be one of {', '.join(METHODS)}, got {method!r}")
    R_aligned = r["rotation"][0]
    # descriptors live in each curve's plane-aligned frame; map back to input coordinates
    R = da.rotation.T @ R_aligned @ db.rotation
    ratio = da.scale / db.scale
    return Match(
        distance=float(r["distance"][0]),
        shift=float(r["shift"][0]),
        rotation=R,
        reversed=bool(r["reversed"][0]),
        mirrored=bool(r["mirrored"][0]),
        method=method,
        scale=float(ratio),
        translation=da.centroid - ratio * R @ db.centroid,
    )


def distance(a: Curve | Descriptors | ArrayLike, b: Curve | Descriptors | ArrayLike, **parameters: Any) -> Match:
    """Similarity distance between two closed curves, with the alignment that achieves it.

    Parameters
    ----------
    a, b : :class:`~nfdmatch.curve.Curve`, :class:`~nfdmatch.descriptors.Descriptors`, or
        array-like (n, 3) / (n, 2) float (closed polylines, closing edge implicit).
    samples, harmonics, scale, method, direction, mirror, weights : by keyword, the fields
        of :class:`MatchParameters` (defaults 128, 16, ``"rms"``, ``"exact"``,
        ``"invariant"``, False, None).

    Returns
    -------
    :class:`Match`; ``rotation``, ``scale``, ``translation`` and ``shift`` map b onto a.
    """
    p = MatchParameters(**parameters)
    da = _as_descriptors(a, **p.descriptor)
    db = _as_descriptors(b, **p.descriptor)
    return match_descriptors(da, db, **p.matching)
