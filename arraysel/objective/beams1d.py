"""Per-beam lobe metrics of a 1-D scene's points: its PSFs read the way a sector scene's are
(``docs/sector.md``, "1-D scenes").

Each point's PSF is the scene's own kernel (the window of ``grid.window`` pixels around its peak,
from the objective's fast or exact path), power ``p(z, x) = |value|^2``. A designer reads a linear
array's side lobes **across** the beam, so the main lobe is a band of columns found from the PSF's
lateral beam profile ``P(x) = max_z p(z, x)`` (the peak over depth of each column), never a fixed
radius: from the peak's column outward on each side, the **first null** is the lowest value met
before the profile rises more than 1 dB above the lowest value met so far (a ripple of less is
not a null); the band reaches the nulls. The pulse's own lobes along the beam (above and below
the peak, in the band's columns) belong to the main lobe: they do not depend on which elements
are on. Per selection and point:

* ``PSL_dB = 10 log10(max P outside the band / peak)``, the peak side-lobe level across the beam;
* ``ISLR_dB``: the energy of the columns outside the band over the energy of the band's columns;
* ``width_x_6dB``: the lateral -6 dB width through the peak (metres), ``width_z_6dB`` the axial
  one (the distance between the first samples at or below half the peak amplitude on either
  side, interpolated linearly in amplitude; ``+inf`` when the profile does not fall that far);
* ``GLL_dB`` and ``width_y_6dB``: NaN (a linear array's grating lobes lie at ``asin(lambda / p)``,
  outside any PSF window of a 1-D scene; a 1-D PSF has no y axis).

A band that reaches the window's edge leaves no side pixel on that side; with none on either side
the dB values are floored at :data:`~arraysel.objective.metrics3d.PSL_FLOOR_DB`. A side lobe can
hide only outside the window: choose a window that covers the angles that matter. An all-zero or
non-finite PSF raises :class:`~arraysel.errors.NumericalError`.
"""
from __future__ import annotations

import math

import numpy as np
import torch

from arraysel.errors import NumericalError, ParameterError
from arraysel.objective.metrics3d import PSL_FLOOR_DB
from arraysel.selection import random_masks

__all__ = ["BEAM_NAMES", "PSFBeams", "kernel_lobe_metrics", "main_lobe_band"]

#: what :meth:`PSFBeams.beam_metrics` returns (the sector scene's names, and the axial width)
BEAM_NAMES = ("PSL_dB", "ISLR_dB", "GLL_dB", "width_x_6dB", "width_y_6dB", "width_z_6dB")
#: a rise of the lateral profile above its running minimum that ends the main lobe (1 dB in power)
_RIPPLE = 10.0 ** 0.1


def main_lobe_band(profile: np.ndarray, centre: int) -> tuple[int, int]:
    """``(lo, hi)``: the columns of the main lobe of a lateral power profile (n,) around its peak
    column ``centre``, both inclusive, each the first null on its side (module docstring)."""
    def walk(step: int) -> int:
        i, low, at = centre, profile[centre], centre
        while 0 <= i + step < len(profile):
            i += step
            if profile[i] < low:
                low, at = profile[i], i
            elif profile[i] > low * _RIPPLE:
                return at
        return i                                  # the edge: no null on this side
    return walk(-1), walk(1)


def _half_width(amp: np.ndarray, c: int, pitch: float) -> float:
    """The -6 dB width (metres) of an amplitude profile through its peak sample ``c``."""
    half = 0.5 * amp[c]
    ends = []
    for step in (-1, 1):
        i = c
        while 0 <= i + step < len(amp) and amp[i + step] > half:
            i += step
        if not 0 <= i + step < len(amp):
            return math.inf
        a0, a1 = amp[i], amp[i + step]
        ends.append(i + step * (a0 - half) / (a0 - a1))
    return abs(ends[1] - ends[0]) * pitch


def kernel_lobe_metrics(kernels: torch.Tensor, pitch) -> dict[str, torch.Tensor]:
    """``{PSL_dB, ISLR_dB, width_x_6dB, width_z_6dB}`` (B,) float64 of PSF kernels ``(B, nz, nx)``
    (complex or real amplitudes) on pixels of ``pitch`` metres (one number, or ``(dz, dx)``)."""
    if not isinstance(kernels, torch.Tensor) or kernels.dim() != 3:
        raise ParameterError(f"kernels must be a tensor (B, nz, nx), got {getattr(kernels, 'shape', kernels)!r}")
    dz, dx = (pitch, pitch) if np.ndim(pitch) == 0 else tuple(pitch)
    if not all(isinstance(v, (int, float)) and math.isfinite(v) and v > 0 for v in (dz, dx)):
        raise ParameterError(f"pitch must be positive pixel sizes in metres, got {pitch!r}")
    power = (kernels.detach().abs().double() ** 2).cpu().numpy()
    if not np.isfinite(power).all():
        raise NumericalError("a PSF kernel is not finite")
    floor = 10.0 ** (PSL_FLOOR_DB / 10.0)
    out = {k: np.zeros(power.shape[0]) for k in ("PSL_dB", "ISLR_dB", "width_x_6dB", "width_z_6dB")}
    for b, p in enumerate(power):
        top = p.max()
        if not top > 0:
            raise NumericalError("a PSF kernel is all zero")
        zi, xi = np.unravel_index(int(p.argmax()), p.shape)
        lo, hi = main_lobe_band(p.max(axis=0), int(xi))
        side = np.concatenate([p[:, :lo], p[:, hi + 1:]], axis=1)
        main = p[:, lo:hi + 1].sum()
        out["PSL_dB"][b] = 10 * math.log10(max(side.max() / top if side.size else 0.0, floor))
        out["ISLR_dB"][b] = 10 * math.log10(max(side.sum() / main if side.size else 0.0, floor))
        amp = np.sqrt(p)
        out["width_x_6dB"][b] = _half_width(amp[zi], int(xi), dx)
        out["width_z_6dB"][b] = _half_width(amp[:, xi], int(zi), dz)
    return {k: torch.from_numpy(v) for k, v in out.items()}


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
