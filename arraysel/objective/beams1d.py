"""Per-beam lobe metrics of a 1-D scene's points: its PSFs read the way a sector scene's are
(``docs/sector.md``, "1-D scenes").

Each point's PSF is the scene's own kernel (the window of ``grid.window`` pixels around its peak,
from the objective's fast or exact path). :func:`~arraysel.objective.lobes.lobe_metrics` finds the
point's main lobe from that PSF (the basin of its peak down to the first null along 64 rays, never
a fixed radius) and reports, per selection and point:

* ``PSL_dB``: the strongest pixel outside the main lobe, relative to the peak (power);
* ``ISLR_dB``: the energy outside the main lobe over the energy inside;
* ``width_x_6dB``: the lateral -6 dB width through the peak (metres); ``width_z_6dB``: the axial one;
* ``GLL_dB`` and ``width_y_6dB``: NaN (a linear array's grating lobes lie at ``asin(lambda / p)``,
  outside any PSF window of a 1-D scene; a 1-D PSF has no y axis).

A side lobe can hide only outside the window: choose a window that covers the angles that matter
(the ``-wide`` scenes use 60 wavelengths). An all-zero or non-finite PSF raises
:class:`~arraysel.errors.NumericalError`.
"""
from __future__ import annotations

import math

import numpy as np
import torch

from arraysel.errors import NumericalError, ParameterError
from arraysel.objective.lobes import lobe_metrics
from arraysel.selection import random_masks

__all__ = ["BEAM_NAMES", "PSFBeams", "kernel_lobe_metrics"]

#: what :meth:`PSFBeams.beam_metrics` returns (the sector scene's names, and the axial width)
BEAM_NAMES = ("PSL_dB", "ISLR_dB", "GLL_dB", "width_x_6dB", "width_y_6dB", "width_z_6dB")
_TERMS = ("PSL_dB", "ISLR_dB", "width_x_6dB", "width_y_6dB")


def kernel_lobe_metrics(kernels: torch.Tensor, pitch) -> dict[str, torch.Tensor]:
    """``{PSL_dB, ISLR_dB, width_x_6dB, width_z_6dB}`` (B,) of PSF kernels ``(B, nz, nx)`` (complex
    or real amplitudes) on pixels of ``pitch`` metres (one number, or ``(dz, dx)``)."""
    if not isinstance(kernels, torch.Tensor) or kernels.dim() != 3:
        raise ParameterError(f"kernels must be a tensor (B, nz, nx), got {getattr(kernels, 'shape', kernels)!r}")
    dz, dx = (pitch, pitch) if np.ndim(pitch) == 0 else tuple(pitch)
    if not all(isinstance(v, (int, float)) and math.isfinite(v) and v > 0 for v in (dz, dx)):
        raise ParameterError(f"pitch must be positive pixel sizes in metres, got {pitch!r}")
    nz, nx = kernels.shape[1:]
    z = (np.arange(nz) - (nz - 1) / 2) * dz
    x = (np.arange(nx) - (nx - 1) / 2) * dx
    Z, X = np.meshgrid(z, x, indexing="ij")
    # x along the columns, z in the place of y: lobe_metrics' second width is then the axial one
    coords = np.stack([X, Z, np.zeros_like(X)], axis=-1)
    with torch.no_grad():
        if not bool(torch.isfinite(torch.view_as_real(kernels) if kernels.is_complex() else kernels).all()):
            raise NumericalError("a PSF kernel is not finite")
        res = lobe_metrics({"psf": kernels.detach().to(torch.complex128 if kernels.is_complex() else torch.float64)},
                           {"psf": coords}, target=None, terms=_TERMS)
    return {"PSL_dB": res["PSL_dB"], "ISLR_dB": res["ISLR_dB"], "width_x_6dB": res["width_x_6dB"],
            "width_z_6dB": res["width_y_6dB"]}


class PSFBeams:
    """The per-beam view of a 1-D scene's objective (module docstring): ``beam_metrics``,
    ``fresh_random_masks`` and ``point_info``, as a sector scene's objective has them."""

    def __init__(self, objective, fresh_random: int = 16):
        self.objective = objective
        self.n_elements, self.k = int(objective.n_elements), int(objective.k)
        self.points = [tuple(float(v) for v in p) for p in objective.points]
        self.n_points = len(self.points)
        self.pitch = float(objective.metric_kw["pitch"])
        self.fresh_random = int(fresh_random)

    def point_info(self) -> list[tuple]:
        """``[(label, theta_x_deg, theta_y_deg, range_m)]`` of the points (``"13,0@20mm"``)."""
        out = []
        for x, z in self.points:
            theta = math.degrees(math.atan2(x, z))
            r = math.hypot(x, z)
            out.append((f"{theta:.3g},0@{r * 1e3:.4g}mm", theta, 0.0, r))
        return out

    def beam_metrics(self, masks, points=None) -> dict[str, np.ndarray]:
        """``{name: float64 (B, P)}`` for :data:`BEAM_NAMES` of hard masks (B, Ne) (dB; widths in
        metres; GLL and the y width NaN), one column per point of ``points`` (default all)."""
        m = np.asarray(masks, dtype=bool).reshape(-1, self.n_elements)
        pts = list(range(self.n_points)) if points is None else [int(p) for p in points]
        out = {k: np.full((m.shape[0], len(pts)), np.nan) for k in BEAM_NAMES}
        if not m.shape[0]:
            return out
        for j, i in enumerate(pts):
            with torch.no_grad():
                kern = self.objective.kernels(m.astype(np.float32), point=i)
            res = kernel_lobe_metrics(kern, self.pitch)
            for name, v in res.items():
                out[name][:, j] = v.cpu().numpy()
        return out

    def fresh_random_masks(self, n: int | None = None, seed: int = 0) -> np.ndarray:
        """``n`` (default ``fresh_random``) random selections of ``k`` elements, boolean (n, Ne)."""
        return random_masks(self.n_elements, self.k, self.fresh_random if n is None else int(n), seed)
