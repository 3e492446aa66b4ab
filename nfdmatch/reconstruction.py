"""Curves rebuilt from their first K harmonics, and how far each is from its input: the
data behind ``nfdmatch reconstruct`` (what the descriptor sees of a curve). In the layer of
pictures (docs/architecture.md), as :mod:`nfdmatch.show`: it measures with the distance."""

from __future__ import annotations

from typing import TYPE_CHECKING

from dataclasses import dataclass

from .curve import Curve
from .descriptors import DEFAULT_SAMPLES, descriptors, reconstruct
from .errors import ParameterError
from .matching import distance

if TYPE_CHECKING:
    from collections.abc import Sequence
    from .curve import Curve

__all__ = ["Reconstruction", "reconstruct_curves", "reconstruction_samples"]


@dataclass(frozen=True)
class Reconstruction:
    """One rebuilt curve.

    Attributes
    ----------
    source_id : str, the id of the input curve.
    curve : :class:`~nfdmatch.curve.Curve`, the rebuilt curve (id ``"<source_id> K=<K>"``),
        vertices (m, 3) float64.
    harmonics : int, K.
    distance : float, the distance (default matching parameters) from the rebuilt curve to
        the input (the distance ignores pose and size: the same for a normalized one).
    """

    source_id: str
    curve: Curve
    harmonics: int
    distance: float


def reconstruction_samples(harmonics: int, samples: int | None = None) -> int:
    """The arc-length samples of the transform: ``samples``, by default max(128, 4K).
    Raises :class:`ParameterError` unless 2K < samples."""
    n = samples if samples is not None else max(DEFAULT_SAMPLES, 4 * harmonics)
    if 2 * harmonics >= n:
        raise ParameterError(f"harmonics ({harmonics}) must be below samples/2 ({n}/2)")
    return n


def reconstruct_curves(
    curves: Sequence[Curve],
    *,
    harmonics: int,
    samples: int | None = None,
    points: int | None = None,
    normalized: bool = False,
) -> list[Reconstruction]:
    """Rebuild every curve of ``curves`` (Curves) from its first ``harmonics`` harmonics.

    samples : arc-length samples of the transform (default :func:`reconstruction_samples`).
    points : vertices of each rebuilt curve (default: the samples).
    normalized : rebuild in the normalized frame (centred, unit scale, limit plane on z = 0)
        instead of the input's pose.
    """
    n = reconstruction_samples(harmonics, samples)
    out = []
    for curve in curves:
        pts = reconstruct(descriptors(curve, samples=n, harmonics=harmonics), points=points, normalized=normalized)
        out.append(
            Reconstruction(
                source_id=curve.id,
                curve=Curve(pts, id=f"{curve.id} K={harmonics}"),
                harmonics=harmonics,
                distance=float(distance(curve, pts).distance),  # invariant: the same for the normalized pose
            )
        )
    return out
