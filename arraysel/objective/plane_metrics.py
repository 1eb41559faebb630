"""The metrics of a :class:`~arraysel.physics.imaging.PlaneSet` against its reference.

One entry point for every imager: a plane set that is one plane on a regular pixel grid (a 1-D
point's kernel) is scored by :func:`~arraysel.objective.metrics.psf_metrics` on that grid (its
compiled batch pass included); any other set of planes by
:func:`~arraysel.objective.metrics3d.psf3d_metrics` on the pixels' positions, all planes together,
with the figures of merit of 2-D arrays (``PSL_dB`` and, on a set holding the C-plane, the -6 dB
widths) besides the Table-1 terms. The two are the same definitions (``docs/metrics.md``); a
kernel's pixel grid is what lets the first use offset tables instead of positions.

:func:`plane_scorer` gives the scoring of one imager's plane sets against its own reference: the
above, or for a plane set in the u-v frame (a sector scene's beam pattern,
:class:`~arraysel.physics.imaging.PatternImager`) the search terms of
:meth:`~arraysel.objective.beam_objective.BeamPatternScorer.search_terms`.
"""
from __future__ import annotations

from typing import Callable

from torch import Tensor

from arraysel.objective.metrics import METRIC_NAMES, psf_metrics
from arraysel.objective.metrics3d import C_PLANE, MERIT_NAMES, psf3d_metrics
from arraysel.physics.imaging import PlaneSet

__all__ = ["plane_metrics", "plane_metric_names", "plane_scorer"]


def plane_metric_names(plane_names, pitch) -> tuple[str, ...]:
    """The names :func:`plane_metrics` returns for planes ``plane_names`` (``pitch``: the plane set's,
    None off a pixel grid) when no ``terms`` are asked."""
    if pitch is not None and len(plane_names) == 1:
        return tuple(METRIC_NAMES)
    return tuple(METRIC_NAMES) + (MERIT_NAMES if C_PLANE in plane_names else ("PSL_dB",))


def plane_metrics(planes: PlaneSet, reference: PlaneSet, *, wavelength: float, r_main: float = 1.5,
                  r_guard: float = 2.5, quantile: float = 0.99, terms=None) -> dict[str, Tensor]:
    """The metrics ``{name: (B,)}`` of ``planes`` (B items) against the full array's ``reference``
    (batch 1, the same planes), differentiable in the planes (module docstring); ``terms`` limits
    them (default: :func:`plane_metric_names`). Radii in wavelengths, ``wavelength`` in metres."""
    radii = dict(wavelength=wavelength, r_main=r_main, r_guard=r_guard, quantile=quantile, terms=terms)
    if planes.pitch is not None and len(planes.images) == 1:
        kappa = planes.kernel
        return psf_metrics(kappa, kappa_ref=reference.kernel[0].to(kappa.dtype), pitch=planes.pitch, **radii)
    ref = {k: v.to(planes.images[k].dtype) for k, v in reference.images.items()}
    return psf3d_metrics(planes.images, planes.coords, planes_ref=ref, **radii)


def plane_scorer(imager, *, wavelength: float, r_main: float = 1.5, r_guard: float = 2.5,
                 quantile: float = 0.99) -> tuple[tuple[str, ...], Callable]:
    """``(names, score)`` of an :class:`~arraysel.physics.imaging.Imager`: ``score(planes, terms=None)``
    gives the metrics ``{name: (B,)}`` of its plane sets against its full-array plane set
    (:meth:`~arraysel.physics.imaging.Imager.reference`), differentiable in the planes; ``names``
    what it gives without ``terms`` (module docstring; radii as :func:`plane_metrics`)."""
    if imager.frame == "uv":
        from arraysel.objective.beam_objective import SEARCH_NAMES, BeamPatternScorer

        scorer = BeamPatternScorer(imager.model)

        def pattern_terms(planes: PlaneSet, terms=None) -> dict[str, Tensor]:
            return scorer.search_terms(planes.kernel, imager.reference().kernel[0], terms)

        return SEARCH_NAMES, pattern_terms
    radii = dict(wavelength=wavelength, r_main=r_main, r_guard=r_guard, quantile=quantile)

    def metrics(planes: PlaneSet, terms=None) -> dict[str, Tensor]:
        return plane_metrics(planes, imager.reference(), terms=terms, **radii)

    return plane_metric_names(imager.plane_names, imager.pitch), metrics
