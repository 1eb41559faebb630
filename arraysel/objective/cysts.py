"""Anechoic cysts in speckle, imaged with a sector scene's PSFs: contrast ratio and gCNR
(``docs/sector.md``, the ``[cysts]`` section). A final check of a handful of selections, never a
search objective.

**The phantom.** A cyst is centred on a point of the scene (``cysts.points``) at range ``R`` and
direction ``(u0, v0)``. Scatterers lie on the sphere of its range, at the shifts of the scene's
grid of direction cosines (steps ``du``, ``dv``) from the point, out to every shift at which the
point's PSF reaches the point's surface (``u0 + e_u du``, ``|e_u|`` below the grid's samples, the
same in ``v``), inside the visible region (``u^2 + v^2 < 1``): each shift holds a Poisson number of scatterers, ``density`` per resolution cell (the full
aperture's main lobe, ``(lambda0 / D_x)(lambda0 / D_y)`` in ``u``-``v``), each with a complex
Gaussian amplitude, so a sample's amplitude is complex Gaussian with that count as its variance.
The scatterers within ``radius`` of the centre (``R hypot(du, dv) <= radius``) are removed: the
anechoic disc. ``realisations`` fields are drawn from ``seed`` (and the point's index), the same
for every selection, so that selections are compared on the same phantom.

**The image: the locally shift-invariant model.** The image of the phantom is the convolution of
the scatterer field with the selection's PSF of the point, as the scene scores it (its compounded
delay-and-sum image on the point's surface): a scatterer shifted by ``(du, dv)`` from the point is
imaged as the point's PSF shifted by ``(du, dv)``. This holds where the PSF does not change with
the direction (the far field of the aperture, the same transmits seen from nearby directions); it
ignores how the PSF changes across the sector (steering, the transmits' coverage: a scatterer
outside the sector, which the transmits reach less, is imaged as brightly as the point) and
scatterers off the surface (the PSF's axial extent: a 2-D phantom on the C-surface, no slice
thickness); the PSF is known on the surface only, so a lobe beyond it brings nothing. It keeps what
sets a cyst's contrast between selections: every side lobe and grating lobe of the PSF over the
surface brings speckle into the cyst.

**The metrics**, on the envelope ``|image|``, pooled over the realisations, inside the disc of
``inside`` times the radius and in the ring from ``ring_inner`` to ``ring_outer`` radii:

* ``CR_dB = 20 log10(mean envelope inside / mean envelope in the ring)`` (envelope, not
  intensity; -240 dB when the inside is dark);
* ``gCNR = 1 - sum_b min(p_in(b), p_out(b))``, the overlap of the two envelope histograms on
  common bins (Rodriguez-Molares et al., IEEE TUFFC 2019): 0 for identical distributions, 1 for
  disjoint ones; ``sqrt(n)`` bins for ``n`` samples of the smaller region.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from arraysel.errors import NumericalError, ParameterError, check_number

__all__ = ["CystSettings", "contrast_ratio", "gcnr", "speckle_field", "CystPhantom", "score_cysts",
           "CYST_COLUMNS"]

#: the columns of :func:`score_cysts`, per point
CYST_COLUMNS = ("CR_dB", "gCNR")
_FLOOR_DB = -240.0


@dataclass(frozen=True)
class CystSettings:
    """The ``[cysts]`` section: ``points`` (indices of ``sector.points``), ``radius`` (m),
    ``density`` (scatterers per resolution cell), ``realisations``, ``seed``, ``inside`` (fraction
    of the radius read inside), ``ring`` (the background ring, in radii)."""

    points: tuple
    radius: float
    density: float = 10.0
    realisations: int = 8
    seed: int = 0
    inside: float = 0.8
    ring: tuple = (1.2, 2.0)

    def __post_init__(self):
        check_number("radius", self.radius, lo=0, lo_open=True, hi=0.05)
        check_number("density", self.density, lo=0, lo_open=True, hi=1000)
        check_number("realisations", self.realisations, lo=1, hi=1000, integer=True)
        check_number("inside", self.inside, lo=0, lo_open=True, hi=1)
        lo, hi = (float(r) for r in self.ring)
        check_number("ring[0]", lo, lo=1, hi=10)
        check_number("ring[1]", hi, lo=lo, lo_open=True, hi=10)

    @classmethod
    def from_scene(cls, scene) -> "CystSettings | None":
        """The settings of a scene's ``[cysts]`` section (None without one)."""
        if "cysts" not in scene.tree:
            return None
        idx = scene.value("cysts", "points")
        idx = tuple(range(len(scene.get("sector", "points")))) if idx is None else tuple(int(i) for i in idx)
        return cls(points=idx, radius=float(scene.length("cysts", "radius")),
                   density=float(scene.value("cysts", "density")),
                   realisations=int(scene.value("cysts", "realisations")), seed=int(scene.value("cysts", "seed")),
                   inside=float(scene.value("cysts", "inside")),
                   ring=(float(scene.value("cysts", "ring_inner")), float(scene.value("cysts", "ring_outer"))))


def _samples(name: str, x) -> np.ndarray:
    a = np.asarray(x, dtype=np.float64).reshape(-1)
    if a.size == 0:
        raise ParameterError(f"{name} is empty: a region of the image holds no pixel")
    if not np.isfinite(a).all() or (a < 0).any():
        raise NumericalError(f"{name} must hold finite, non-negative envelope values")
    return a


def contrast_ratio(inside, outside) -> float:
    """``20 log10(mean(inside) / mean(outside))`` of envelope samples, dB (-240 dB for a dark inside)."""
    a, b = _samples("inside", inside), _samples("outside", outside)
    if b.mean() <= 0:
        raise NumericalError("the background's envelope is zero: no contrast ratio")
    return float(max(20 * math.log10(a.mean() / b.mean()) if a.mean() > 0 else _FLOOR_DB, _FLOOR_DB))


def gcnr(inside, outside, bins: int | None = None) -> float:
    """The generalised contrast-to-noise ratio of envelope samples: 1 minus the overlap of their
    histograms on ``bins`` common bins over the pooled range (default ``sqrt(n)`` of the smaller
    set, at least 10)."""
    a, b = _samples("inside", inside), _samples("outside", outside)
    n = max(10, int(round(math.sqrt(min(a.size, b.size))))) if bins is None else \
        int(check_number("bins", bins, lo=2, hi=1 << 20, integer=True))
    lo, hi = min(a.min(), b.min()), max(a.max(), b.max())
    if hi <= lo:  # every sample equal: one distribution
        return 0.0
    edges = np.linspace(lo, hi, n + 1)
    pa = np.histogram(a, edges)[0] / a.size
    pb = np.histogram(b, edges)[0] / b.size
    return float(1.0 - np.minimum(pa, pb).sum())


def speckle_field(shape: tuple, per_sample: float, rng: np.random.Generator) -> np.ndarray:
    """Complex scatterer amplitudes on a grid: per sample a Poisson number of scatterers (mean
    ``per_sample``), each complex Gaussian of unit variance, summed: complex128 ``shape``."""
    lam = check_number("per_sample", per_sample, lo=0, lo_open=True)
    count = rng.poisson(lam, size=shape)
    z = (rng.standard_normal(shape) + 1j * rng.standard_normal(shape)) * math.sqrt(0.5)
    return np.sqrt(count) * z


class CystPhantom:
    """The cyst of the module docstring on one point's surface.

    Parameters: ``u`` (W,), ``v`` (H,) the surface's direction cosines (a regular grid);
    ``centre`` ``(u0, v0)``; ``range_m`` the point's range; ``lobe`` ``(lambda0 / D_x, lambda0 /
    D_y)``, the resolution cell; ``settings`` (:class:`CystSettings`); ``index`` the point's index
    (it seeds the point's own fields).
    """

    def __init__(self, u, v, centre, range_m: float, lobe, settings: CystSettings, index: int = 0):
        self.u, self.v = (np.asarray(a, dtype=np.float64).reshape(-1) for a in (u, v))
        if self.u.size < 2 or self.v.size < 2:
            raise ParameterError("u and v must hold at least 2 direction cosines each")
        self.du, self.dv = float(np.diff(self.u).mean()), float(np.diff(self.v).mean())
        self.centre = (float(centre[0]), float(centre[1]))
        self.range = check_number("range_m", range_m, lo=0, lo_open=True)
        self.settings = settings
        self.index = int(index)
        H, W = self.v.size, self.u.size
        # the sample nearest the centre, where the PSF's peak lies (the point itself, between samples)
        self.c0 = (int(round((self.centre[1] - self.v[0]) / self.dv)), int(round((self.centre[0] - self.u[0]) / self.du)))
        if not (0 <= self.c0[0] < H and 0 <= self.c0[1] < W):
            raise ParameterError(f"centre {self.centre} lies outside the surface")
        # the scatterers: at every shift (ey, ex) of the grid, |ey| < H, |ex| < W, from the point (a
        # scatterer there is imaged as the PSF shifted so), in the visible region
        ey, ex = np.meshgrid(np.arange(-(H - 1), H) * self.dv, np.arange(-(W - 1), W) * self.du, indexing="ij")
        visible = (self.centre[0] + ex) ** 2 + (self.centre[1] + ey) ** 2 < 1
        #: scatterers kept (in the visible region, outside the anechoic disc), (2H - 1, 2W - 1) bool
        self.keep = visible & (self.range * np.hypot(ex, ey) > settings.radius)
        py, px = np.meshgrid(self.v - self.centre[1], self.u - self.centre[0], indexing="ij")
        d = self.range * np.hypot(px, py)
        r = settings.radius
        #: the pixels read inside the cyst and in the background ring, (H, W) bool
        self.inside = d <= settings.inside * r
        self.ring = (d >= settings.ring[0] * r) & (d <= settings.ring[1] * r)
        if not self.inside.any() or not self.ring.any():
            raise ParameterError(f"radius = {r * 1e3:.4g} mm: the cyst's inside or its ring holds no sample of the "
                                 f"surface at range {self.range * 1e3:.4g} mm")
        self.per_sample = settings.density * abs(self.du * self.dv) / (float(lobe[0]) * float(lobe[1]))

    def fields(self) -> np.ndarray:
        """The seeded scatterer fields (realisations, 2H - 1, 2W - 1) on the shifts of :attr:`keep`,
        complex, zero inside the disc and outside the visible region."""
        rng = np.random.default_rng(np.random.SeedSequence([int(self.settings.seed), self.index]))
        shape = (int(self.settings.realisations), *self.keep.shape)
        return speckle_field(shape, self.per_sample, rng) * self.keep

    def images(self, psf) -> np.ndarray:
        """The phantom's envelope images (realisations, H, W) through the complex ``psf`` (H, W)
        on the surface (the convolution of the module docstring)."""
        k = np.asarray(psf, dtype=np.complex128)
        H, W = self.v.size, self.u.size
        if k.shape != (H, W):
            raise ParameterError(f"psf must have shape ({H}, {W}), got {k.shape}")
        if not np.isfinite(k).all():
            raise NumericalError("the PSF is not finite")
        # pixel p sums a_e psf[p - e] over the shifts e: the full convolution, read from H - 1 on
        shape = (3 * H - 2, 3 * W - 2)
        full = np.fft.ifft2(np.fft.fft2(self.fields(), shape) * np.fft.fft2(k, shape)[None])
        return np.abs(full[:, H - 1:2 * H - 1, W - 1:2 * W - 1])

    def metrics(self, psf) -> dict[str, float]:
        """``{"CR_dB", "gCNR"}`` of the phantom through ``psf`` (module docstring)."""
        env = self.images(psf)
        a, b = env[:, self.inside], env[:, self.ring]
        return {"CR_dB": contrast_ratio(a, b), "gCNR": gcnr(a, b)}


def score_cysts(objective, masks, settings: CystSettings | None = None, images: dict | None = None
                ) -> dict[str, np.ndarray]:
    """CR and gCNR of the cysts of a sector objective's scene for hard masks (B, Ne):
    ``{"CR_dB", "gCNR": float64 (B, P)}``, one column per point of ``settings.points`` (default:
    the scene's ``[cysts]``), and ``"points"``, those indices. ``images``: ``{point: complex (B, H,
    W)}`` already computed (:meth:`~arraysel.objective.sector_objective.SectorObjective.point_images`),
    else computed here."""
    st = CystSettings.from_scene(objective.scene) if settings is None else settings
    if st is None:
        raise ParameterError(f"scene {objective.scene.name!r} has no [cysts] section")
    setup = objective.setup
    lobe = objective.scene.sector_geometry()["lobe"]
    m = np.asarray(masks)
    m = m[None] if m.ndim == 1 else m
    out = {k: np.zeros((m.shape[0], len(st.points))) for k in CYST_COLUMNS}
    for j, i in enumerate(st.points):
        if not 0 <= int(i) < objective.n_points:
            raise ParameterError(f"cysts.points[{j}] = {i} is out of range; allowed: [0, {objective.n_points - 1}]")
        ph = CystPhantom(setup.u, setup.v, setup.direction_of(i), setup.range_of(i), lobe, st, index=int(i))
        img = images[int(i)] if images is not None and int(i) in images else objective.point_images(m, int(i))
        img = img.detach().cpu().numpy() if isinstance(img, torch.Tensor) else np.asarray(img)
        for b in range(m.shape[0]):
            res = ph.metrics(img[b])
            for key in CYST_COLUMNS:
                out[key][b, j] = res[key]
    out["points"] = np.asarray(st.points, dtype=int)
    return out
