"""The exact point-spread functions of a steered sector: point targets imaged on surfaces sampled in
angle that cover the whole sector (``docs/sector.md``).

A sector scene images a few point scatterers (on the axis at several depths, and off the axis)
with the same transmits (diverging waves steered over the sector). Each point is imaged on the
sphere of its own range ``R`` around the array centre, sampled on a grid of direction cosines
``(u, v)`` that covers the sector and a margin past its edge
(:func:`~arraysel.physics.beampattern.sphere_surface`): every direction a beam of the sector can
put a side lobe in, at the range where the point's echo focuses, so that a grating lobe or a far
side lobe shows wherever it falls. The image on that surface is the exact compounded
delay-and-sum of :class:`~arraysel.physics.volume.psf.MatrixPSF` (SIMUS3 echoes of the one point,
I/Q demodulation, DAS on the surface's pixels).

:func:`sector_grid` gives the grid of directions, :func:`beam_point` a point's position from its
angles and range, :class:`SectorSetup` everything the images depend on and :class:`SectorPSF`
the images of a batch of selections, point by point: exact, or from a point's fast model
(:class:`~arraysel.physics.volume.fast.MatrixFastPSF` on its surface, :meth:`SectorPSF.build_fast`
with :data:`SECTOR_FAST_LADDER`), once one is installed.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import torch

from arraysel.errors import ParameterError, check_number
from arraysel.physics.beamgeometry import sphere_surface
from arraysel.physics.probes import Acquisition, MatrixProbe, PlanarProbe
from arraysel.physics.simus import SimOptions
from arraysel.physics.volume.fast import FastSettings, MatrixFastPSF
from arraysel.physics.volume.psf import MatrixPSF, MatrixPSFSetup

__all__ = ["SURFACE", "SECTOR_FAST", "SECTOR_FAST_LADDER", "MIRRORS", "mirrors", "MirroredModel",
           "sector_grid", "beam_point", "SectorSetup", "SectorPSF"]

#: the name of each point's surface in the dicts :meth:`SectorPSF.surfaces` returns
SURFACE = "sector"
#: the fast path's settings on a sector surface, tried in this order until one passes its check:
#: a pixel far from the point (the sector's edge) sees receive delays spanning up to about 70 rad
#: of the band's phase, so it needs up to about 52 interpolation nodes (the planes of a 3-D scene
#: need at most 48); the check is held to a relative squared error of 1e-6. Without interpolation
#: harmonics the error is below that for a 1024-element probe, whose many elements average the
#: linear interpolation's ripple out; a small probe needs one harmonic each side. The two large
#: tensors are stored in scaled float16 (half the memory of float32; the check, which measures the
#: model as stored, holds them to the same 1e-6)
SECTOR_FAST_LADDER = (FastSettings(max_nodes=128, check_tol=1e-6, storage="float16"),
                      FastSettings(max_nodes=128, check_tol=1e-6, replicas=1, storage="float16"))
SECTOR_FAST = SECTOR_FAST_LADDER[0]


def sector_grid(half_u: float, half_v: float, step: float) -> tuple[np.ndarray, np.ndarray]:
    """The direction cosines ``(u, v)`` of the grid: steps of ``step``, ``0`` on a sample, reaching
    at least ``half_u`` (``half_v``) on each side; float64 arrays (Hu,), (Hv,)."""
    step = check_number("step", step, lo=0, lo_open=True, hi=0.5)
    out = []
    for name, half in (("half_u", half_u), ("half_v", half_v)):
        half = check_number(name, half, lo=0, lo_open=True, hi=0.99)
        n = int(math.ceil(half / step - 1e-9))
        out.append(np.arange(-n, n + 1, dtype=np.float64) * step)
    if out[0][-1] ** 2 + out[1][-1] ** 2 > 1:
        raise ParameterError(f"half_u = {half_u:.4g}, half_v = {half_v:.4g}: the grid's corners leave the visible "
                             "region (u^2 + v^2 > 1); make the sector or its margin smaller")
    return out[0], out[1]


def beam_point(theta_x_deg: float, theta_y_deg: float, range_m: float) -> tuple[float, float, float]:
    """The position (x, y, z) in metres of a point at distance ``range_m`` from the array centre in
    the direction ``u = sin theta_x``, ``v = sin theta_y`` (degrees; the steering of a tilt pair)."""
    u, v = math.sin(math.radians(theta_x_deg)), math.sin(math.radians(theta_y_deg))
    if u * u + v * v >= 1:
        raise ParameterError(f"angles ({theta_x_deg}, {theta_y_deg}) degrees point outside the visible region")
    r = check_number("range", range_m, lo=0, lo_open=True, hi=2)
    return (r * u, r * v, r * math.sqrt(1 - u * u - v * v))


#: the mirror symmetries of a square grid that a sector scene may have, each its own inverse, as
#: ``(flip x, flip y, swap x and y)`` (the swap first): the flip of x, of y, of both, the swap of x
#: and y, and the swap with both flipped. Positions (x, y) and directions (u, v) mirror alike.
MIRRORS = {"x": (True, False, False), "y": (False, True, False), "xy": (True, True, False),
           "swap": (False, False, True), "antiswap": (True, True, True)}


def _mirrored(name: str, x, y):
    """Position (or direction) ``(x, y)`` seen in mirror ``name``."""
    flip_x, flip_y, swap = MIRRORS[name]
    if swap:
        x, y = y, x
    return (-x if flip_x else x, -y if flip_y else y)


def _mirror_perm(setup: "SectorSetup", name: str) -> np.ndarray | None:
    """The element permutation of mirror ``name`` (:data:`MIRRORS`), None when the scene lacks that
    symmetry: the elements' positions and sizes, the set of the transmits' delays and the grid of
    directions must all be unchanged by it."""
    probe = setup.probe
    flip_u, flip_v, swap = MIRRORS[name]
    pos = np.asarray(probe.element_positions(), dtype=np.float64)
    tol = 1e-9 * max(1.0, float(np.abs(pos).max()) * 1e3)
    gx, gy = _mirrored(name, pos[:, 0], pos[:, 1])
    moved = np.stack([gx, gy, pos[:, 2]], axis=1)
    d = np.abs(moved[:, None, :] - pos[None, :, :]).sum(-1)
    perm = d.argmin(1)
    if d[np.arange(len(pos)), perm].max() > tol:
        return None
    u, v = np.asarray(setup.u), np.asarray(setup.v)
    if swap and (getattr(probe, "width", None) != getattr(probe, "height", None) or u.shape != v.shape
                 or not np.allclose(u, v, rtol=0, atol=1e-12)):
        return None
    for flip, g in ((flip_u, u), (flip_v, v)):
        if flip and not np.allclose(g, -g[::-1], rtol=0, atol=1e-12):
            return None
    dl = setup.delays
    scale = max(float(np.abs(dl).max()), 1e-30)
    for row in dl[:, perm]:
        if not (np.abs(dl - row[None]).max(1) <= 1e-9 * scale).any():
            return None
    return perm


def mirrors(setup: "SectorSetup") -> tuple[dict[str, np.ndarray], dict[int, tuple[int, str]]]:
    """The scene's mirror symmetries (:data:`MIRRORS`) and the points they relate: ``(perms, pairs)``.

    ``perms`` maps each mirror the scene has to its element permutation (``perm[e]``: the element at
    the mirror image of element ``e``'s position); ``pairs`` maps a point ``j`` to ``(i, name)``, an
    earlier point ``i`` whose mirror image it is (the first such ``i``). Point ``j``'s image of
    weights ``w`` is then point ``i``'s image of ``w[:, perm]``, mirrored (:class:`MirroredModel`): the
    same delay-and-sum seen in a mirror, which needs no model of its own."""
    perms = {}
    for name in MIRRORS:
        perm = _mirror_perm(setup, name)
        if perm is not None:
            perms[name] = perm
    pairs = {}
    pts = [tuple(map(float, q)) for q in setup.points]
    for j, (x, y, z) in enumerate(pts):
        for i, q in enumerate(pts[:j]):
            hit = next((name for name in perms
                        if np.allclose(q, (*_mirrored(name, x, y), z), rtol=0, atol=1e-12)), None)
            if hit is not None:
                pairs[j] = (i, hit)
                break
    return perms, pairs


def _mirror_image(x: torch.Tensor, name: str) -> torch.Tensor:
    """An image (..., Hv, Hu) seen in mirror ``name``: rows are v, columns u."""
    flip_u, flip_v, swap = MIRRORS[name]
    if swap:
        x = x.transpose(-1, -2)
    dims = ((-1,) if flip_u else ()) + ((-2,) if flip_v else ())
    return x.flip(dims) if dims else x


class MirroredModel:
    """Point ``j``'s images from the model of its mirror point ``i`` (:func:`mirrors`): the weights
    permuted, the image mirrored. ``planes(weights, receive=None)`` as the model's. ``name``: the
    mirror (:data:`MIRRORS`; default the swap of x and y)."""

    def __init__(self, model, perm: np.ndarray, name: str = "swap"):
        if name not in MIRRORS:
            raise ParameterError(f"mirror name {name!r} is not one of {sorted(MIRRORS)}")
        self.model, self.name = model, name
        self.perm = torch.as_tensor(np.asarray(perm), dtype=torch.long)

    def planes(self, weights, receive=None, base=None) -> dict[str, torch.Tensor]:
        def mirrored(x):
            x = x if isinstance(x, torch.Tensor) else torch.as_tensor(np.asarray(x))
            x = x[None] if x.dim() == 1 else x
            return x[:, self.perm.to(x.device)]

        w = mirrored(weights)
        b = None if base is None else mirrored(base)[0]
        out = self.model.planes(w, base=b) if receive is None else self.model.planes(w, receive=mirrored(receive))
        return {k: _mirror_image(v, self.name) for k, v in out.items()}


@dataclass(frozen=True, eq=False)
class SectorSetup:
    """Everything the sector's images depend on.

    probe, acq, delays (n_tx, Ne), reflectivity, iq_bandwidth, options: as :class:`MatrixPSFSetup`.
    points: the scatterers (x, y, z) in metres, one image each. u, v: the grid of direction cosines
    (:func:`sector_grid`). sines: ``(sin theta_x, sin theta_y)`` of the sector's edge.
    """

    probe: MatrixProbe
    acq: Acquisition
    delays: np.ndarray
    points: tuple
    u: np.ndarray
    v: np.ndarray
    sines: tuple = (0.5, 0.5)
    reflectivity: float = 1.0
    iq_bandwidth: float | None = None
    options: SimOptions = field(default_factory=SimOptions)

    def __post_init__(self):
        if not isinstance(self.probe, (MatrixProbe, PlanarProbe)):
            raise ParameterError(f"probe must be a MatrixProbe or a PlanarProbe, got {type(self.probe).__name__}")
        pts = tuple(tuple(float(c) for c in p) for p in self.points)
        if not pts or any(len(p) != 3 for p in pts):
            raise ParameterError(f"points must be a non-empty list of (x, y, z) in metres, got {self.points!r}")
        object.__setattr__(self, "points", pts)
        for name in ("u", "v"):
            a = np.asarray(getattr(self, name), dtype=np.float64).reshape(-1)
            if a.size < 2 or not np.isfinite(a).all() or np.any(np.diff(a) <= 0):
                raise ParameterError(f"{name} must hold at least 2 increasing, finite direction cosines")
            object.__setattr__(self, name, a)

    def point_setup(self, i: int) -> MatrixPSFSetup:
        """The :class:`MatrixPSFSetup` of point ``i`` (its planes are not used: the image is taken on
        the point's surface, :meth:`surface`)."""
        pixel = float(self.acq.c / self.probe.fc / 4)
        return MatrixPSFSetup(probe=self.probe, acq=self.acq, delays=self.delays, scatterer=self.points[i],
                              half_x=pixel, half_y=pixel, half_z=pixel, pixel=pixel, planes=("xy",),
                              reflectivity=self.reflectivity, iq_bandwidth=self.iq_bandwidth, options=self.options)

    def range_of(self, i: int) -> float:
        return float(np.linalg.norm(self.points[i]))

    def direction_of(self, i: int) -> tuple[float, float]:
        """``(u, v)`` of point ``i`` seen from the array centre."""
        x, y, _ = self.points[i]
        r = self.range_of(i)
        return (x / r, y / r)

    def surface(self, i: int) -> torch.Tensor:
        """Point ``i``'s surface (Hv, Hu, 3), float64 metres: the sphere of its range sampled on
        the grid ``(u, v)``."""
        return sphere_surface(self.range_of(i), self.u, self.v)


class SectorPSF:
    """The exact images of every point of a :class:`SectorSetup` on its surface, batched over
    selections (weights (B, Ne), as :class:`MatrixPSF`), differentiable in the weights.

    :attr:`coords` is one ``{SURFACE: (Hv, Hu, 3)}`` per point; :meth:`surfaces` ``(weights, i)``
    the complex image ``{SURFACE: (B, Hv, Hu)}`` of point ``i`` in units of that point's
    ``image_scale``. The points' models are built on first use (about 0.2 GB each for a grid of
    5,000 directions and 1,024 elements).
    """

    def __init__(self, setup: SectorSetup, dtype=torch.float32, device="cpu"):
        if not isinstance(setup, SectorSetup):
            raise ParameterError(f"setup must be a SectorSetup, got {type(setup).__name__}")
        self.setup = setup
        self.dtype, self.device = dtype, torch.device(device)
        self.n_points = len(setup.points)
        self.n_elements = setup.probe.n_elements
        self.coords = [{SURFACE: setup.surface(i)} for i in range(self.n_points)]
        self._models: dict[int, MatrixPSF] = {}
        self._fast: dict[int, MatrixFastPSF] = {}

    def model(self, i: int) -> MatrixPSF:
        """Point ``i``'s :class:`MatrixPSF` on its surface."""
        i = int(check_number("point", i, lo=0, hi=self.n_points - 1, integer=True))
        if i not in self._models:
            self._models[i] = MatrixPSF(self.setup.point_setup(i), dtype=self.dtype, device=self.device,
                                        coords=self.coords[i])
        return self._models[i]

    def release(self, i: int) -> None:
        """Free point ``i``'s exact model (rebuilt on its next use): a scan of many points holds one at a time."""
        self._models.pop(int(i), None)

    def surfaces(self, weights, i: int, exact: bool = False, receive=None, base=None) -> dict[str, torch.Tensor]:
        """Point ``i``'s image ``{SURFACE: complex (B, Hv, Hu)}`` for element weights (B, Ne)
        (``receive``: separate receive weights (B, Ne), ``weights`` then the transmit apodization):
        from its fast model when one is installed (:meth:`install_fast`) and ``exact`` is False,
        else from the exact :class:`MatrixPSF`. ``base`` (Ne,): weights each row differs from in a
        few elements (a local search's moves), for the fast model's receive sums
        (:meth:`MatrixFastPSF.image`); the images are the same."""
        fast = None if exact else self._fast.get(int(i))
        if fast is not None and base is not None and receive is None:
            return fast.planes(weights, base=base)
        model = fast if fast is not None else self.model(i)
        return model.planes(weights) if receive is None else model.planes(weights, receive=receive)

    def build_fast(self, i: int, settings: FastSettings | None = None, check_masks=None) -> MatrixFastPSF:
        """Point ``i``'s fast model (:class:`~arraysel.physics.volume.fast.MatrixFastPSF` on its
        surface: the image is bilinear in the weights, so its transmit and receive sums are
        precomputed per pixel), built in float64 from an exact model of the point and checked
        against it on ``check_masks``; raises
        :class:`~arraysel.physics.volume.fast.FastPathUnavailable` when refused."""
        i = int(check_number("point", i, lo=0, hi=self.n_points - 1, integer=True))
        exact = MatrixPSF(self.setup.point_setup(i), dtype=torch.float64, coords=self.coords[i])
        return MatrixFastPSF(exact, settings or SECTOR_FAST, dtype=self.dtype, check_masks=check_masks)

    def fast_from_state(self, i: int, state: dict, settings: FastSettings | None = None) -> MatrixFastPSF:
        """Point ``i``'s fast model restored from :meth:`MatrixFastPSF.state` (ValueError when the
        tensors do not fit the point's surface)."""
        i = int(check_number("point", i, lo=0, hi=self.n_points - 1, integer=True))
        return MatrixFastPSF.from_state(self.setup.point_setup(i), state, settings or SECTOR_FAST, dtype=self.dtype,
                                        device=self.device, coords=self.coords[i])

    def install_fast(self, i: int, model: "MatrixFastPSF | MirroredModel | None") -> None:
        """Use ``model`` for point ``i``'s images (None: the exact path again)."""
        i = int(check_number("point", i, lo=0, hi=self.n_points - 1, integer=True))
        if model is None:
            self._fast.pop(i, None)
        else:
            self._fast[i] = model

    def has_fast(self, i: int) -> bool:
        return int(i) in self._fast
