"""The geometry behind :mod:`arraysel.objective.lobes`: the surfaces of a point's PSF, its peak,
its main lobe along rays, its widths and the pixels near predicted grating lobes.

Everything here is detached (regions, seeds, distances); the metrics built on it are in
:mod:`arraysel.objective.lobes`, whose docstring states the definitions.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Mapping

import numpy as np
import torch
from torch import Tensor

from arraysel.errors import NumericalError, ParameterError, check_choice, check_number
from arraysel.physics.beampattern import direction_cosines

__all__ = ["FRAMES", "MainLobeRule", "LobeRegions", "surfaces", "find_regions", "widths", "grating_distance",
           "segment_distance"]

FRAMES = ("xyz", "uv")


@dataclass(frozen=True)
class MainLobeRule:
    """How the main lobe is found (:mod:`arraysel.objective.lobes`). ``method`` "null" or
    "contour"; ``ripple_db`` in (0, 20]; ``contour_db`` in [-40, -1]; ``contour_factor`` in
    [1, 10]; ``cap_factor`` None or in [1, 100] (method "null": no ray reaches further than
    ``cap_factor`` times its ``contour_db`` radius); ``n_rays`` 8..1024; ``max_radius`` None or
    > 0 (frame units; a speed setting)."""

    method: str = "null"
    ripple_db: float = 1.0
    contour_db: float = -6.0
    contour_factor: float = 2.0
    cap_factor: float | None = 3.0
    n_rays: int = 64
    max_radius: float | None = None

    def __post_init__(self):
        check_choice("method", self.method, ("null", "contour"))
        check_number("ripple_db", self.ripple_db, lo=0, lo_open=True, hi=20)
        check_number("contour_db", self.contour_db, lo=-40, hi=-1)
        check_number("contour_factor", self.contour_factor, lo=1, hi=10)
        check_number("n_rays", self.n_rays, lo=8, hi=1024, integer=True)
        if self.cap_factor is not None:
            check_number("cap_factor", self.cap_factor, lo=1, hi=100)
        if self.max_radius is not None:
            check_number("max_radius", self.max_radius, lo=0, lo_open=True)


@dataclass
class LobeRegions:
    """The main lobe of each item (flattened batch order), detached.

    Attributes
    ----------
    names : the surfaces, in input order
    seed : ``{name: LongTensor (B, 2)}``, each surface's main-lobe peak (row, column)
    has_lobe : ``{name: BoolTensor (B,)}``, whether the surface holds the main lobe
    rays : ``{name: Tensor (B, n_rays)}``, the main lobe's radius along each ray (frame units;
        inf where the ray met the surface's edge first)
    box : ``{name: (i0, i1, j0, j1)}``, the window of the surface that holds every main lobe
    main_box : ``{name: BoolTensor (B, i1 - i0, j1 - j0)}``, the main-lobe pixels in that window
    peak_plane : list of the surface holding each item's peak
    clipped : BoolTensor (B,), the main lobe touches a surface's edge
    shapes : ``{name: (H, W)}``
    """

    names: tuple
    seed: dict
    has_lobe: dict
    rays: dict
    box: dict
    main_box: dict
    peak_plane: list
    clipped: Tensor
    shapes: dict
    _main: dict = field(default_factory=dict, repr=False)

    @property
    def main(self) -> dict:
        """``{name: BoolTensor (B, H, W)}``, the main-lobe pixels."""
        if not self._main:
            for n in self.names:
                i0, i1, j0, j1 = self.box[n]
                m = torch.zeros((self.clipped.shape[0],) + tuple(self.shapes[n]), dtype=torch.bool,
                                device=self.clipped.device)
                m[:, i0:i1, j0:j1] = self.main_box[n]
                self._main[n] = m
        return self._main


# --------------------------------------------------------------------------
# the surfaces
# --------------------------------------------------------------------------

@dataclass
class Surface:
    name: str
    power: Tensor          # (B, H, W), differentiable
    pdet: Tensor           # (B, H, W), detached
    pos: Tensor            # (H, W, d) frame coordinates, float64
    step: tuple            # (row step, column step) in frame units
    weight: Tensor         # (H, W) >= 0, the power's dtype


def _power(name: str, x, power: bool) -> Tensor:
    if not isinstance(x, Tensor):
        raise ParameterError(f"planes[{name!r}] must be a torch tensor (..., H, W), got {type(x).__name__}")
    if x.dim() < 2:
        raise ParameterError(f"planes[{name!r}] must have shape (..., H, W), got {tuple(x.shape)}")
    if x.is_complex():
        if power:
            raise ParameterError(f"planes[{name!r}] is complex but power=True (a power is real)")
        return torch.view_as_real(x).square().sum(-1)
    if not x.is_floating_point():
        x = x.to(torch.float64)
    return x if power else x * x


def _array(name: str, c) -> Tensor:
    c = c.detach().cpu() if isinstance(c, Tensor) else c
    try:
        return torch.as_tensor(np.asarray(c, dtype=np.float64))
    except (TypeError, ValueError) as exc:
        raise ParameterError(f"{name} must be a numeric array: {exc}") from None


def pixel_map(name: str, v, hw, device, dtype) -> Tensor:
    """A per-pixel map (H, W), finite and >= 0."""
    t = _array(name, v)
    if tuple(t.shape) != tuple(hw) or not bool(torch.isfinite(t).all()) or bool((t < 0).any()):
        raise ParameterError(f"{name} must be finite, >= 0 and of shape {tuple(hw)}")
    return t.to(device, dtype)


def _steps(name: str, pos: Tensor) -> tuple[float, float]:
    sr = float((pos[1:] - pos[:-1]).norm(dim=-1).median())
    sc = float((pos[:, 1:] - pos[:, :-1]).norm(dim=-1).median())
    if not (sr > 0 and sc > 0):
        raise ParameterError(f"coords[{name!r}]: neighbouring pixels must differ along rows and columns")
    return sr, sc


def surfaces(planes, coords, weights, power: bool, frame: str) -> tuple[list[Surface], tuple]:
    """Checked surfaces (their power flattened to (B, H, W)) and the planes' leading shape;
    NumericalError for a non-finite or all-zero item."""
    if not isinstance(planes, Mapping) or not planes:
        raise ParameterError("planes must be a non-empty dict {name: tensor (..., H, W)}")
    if not isinstance(coords, Mapping):
        raise ParameterError("coords must be a dict {name: array (H, W, 3)}")
    check_choice("frame", frame, FRAMES)
    out, lead, tops = [], None, []
    for name, x in planes.items():
        p = _power(name, x, power)
        if lead is None:
            lead = tuple(p.shape[:-2])
        elif tuple(p.shape[:-2]) != lead:
            raise ParameterError(f"planes[{name!r}] has leading shape {tuple(p.shape[:-2])}, not {lead}")
        h, w = p.shape[-2:]
        if h < 2 or w < 2:
            raise ParameterError(f"planes[{name!r}] must be at least 2 x 2 pixels, got {h} x {w}")
        if name not in coords:
            raise ParameterError(f"coords has no entry for plane {name!r}")
        c = _array(f"coords[{name!r}]", coords[name])
        if tuple(c.shape) != (h, w, 3) or not bool(torch.isfinite(c).all()):
            raise ParameterError(f"coords[{name!r}] must be finite, of shape {(h, w, 3)}, got {tuple(c.shape)}")
        pos = (c if frame == "xyz" else c[..., :2]).to(p.device)
        wt = torch.ones(h, w, dtype=p.dtype, device=p.device)
        if weights is not None and name in weights:
            wt = pixel_map(f"weights[{name!r}]", weights[name], (h, w), p.device, p.dtype)
        p = p.reshape((-1, h, w))
        pdet = p.detach()
        lo, hi = torch.aminmax(pdet.reshape(pdet.shape[0], -1), dim=1)      # one pass: NaN shows in both
        if not bool(torch.isfinite(hi).all()) or not bool((lo >= 0).all()):
            raise NumericalError(f"planes[{name!r}] holds NaN, Inf or (power=True) negative values")
        out.append(Surface(name, p, pdet, pos, _steps(name, pos), wt))
        tops.append(hi)
    top = torch.stack(tops).amax(0)
    if bool((top <= 0).any()):
        idx = torch.nonzero(top <= 0).flatten().tolist()[:5]
        raise NumericalError(f"the PSF is identically zero at batch index(es) {idx}; its lobe metrics are undefined")
    return out, lead


# --------------------------------------------------------------------------
# the peak
# --------------------------------------------------------------------------

def _nearest(s: Surface, where: Tensor) -> tuple[Tensor, Tensor]:
    """Nearest pixel (B, 2) of ``s`` to positions ``where`` (B, d) and whether it lies within one
    pixel step of it."""
    flat = s.pos.reshape(-1, s.pos.shape[-1])
    uniq, inv = torch.unique(where, dim=0, return_inverse=True)
    best, idx = (flat[None] - uniq[:, None, :]).norm(dim=-1).min(dim=1)
    w = s.pos.shape[1]
    return torch.stack([idx // w, idx % w], dim=-1)[inv], (best <= max(s.step) * (1 + 1e-9))[inv]


def _climb(p: Tensor, seed: Tensor) -> Tensor:
    """Steepest ascent over the 8 neighbours from ``seed`` (B, 2) to a local maximum of ``p``."""
    b, h, w = p.shape
    offs = torch.tensor([(0, 0)] + [(i, j) for i in (-1, 0, 1) for j in (-1, 0, 1) if (i, j) != (0, 0)],
                        device=p.device)
    flat = p.reshape(b, -1)
    for _ in range(h + w):
        ij = seed[:, None, :] + offs[None]                               # (B, 9, 2)
        ok = (ij[..., 0] >= 0) & (ij[..., 0] < h) & (ij[..., 1] >= 0) & (ij[..., 1] < w)
        idx = ij[..., 0].clamp(0, h - 1) * w + ij[..., 1].clamp(0, w - 1)
        vals = torch.where(ok, flat.gather(1, idx), torch.full_like(idx, -1, dtype=p.dtype))
        best = vals.argmax(1)
        if not bool((best != 0).any()):
            break
        seed = seed + offs[best]
    return seed


def _where_peak(surfs: list[Surface], target) -> Tensor:
    b = surfs[0].pdet.shape[0]
    d = surfs[0].pos.shape[-1]
    dev = surfs[0].pdet.device
    if target is None:
        tops = torch.stack([s.pdet.reshape(b, -1).amax(1) for s in surfs])          # (S, B)
        which = tops.argmax(0)
        where = torch.empty(b, d, dtype=torch.float64, device=dev)
        for k, s in enumerate(surfs):
            sel = which == k
            if bool(sel.any()):
                where[sel] = s.pos.reshape(-1, d)[s.pdet.reshape(b, -1)[sel].argmax(1)]
        return where
    t = _array("target", target).to(dev)
    if t.dim() == 1:
        t = t[None].expand(b, -1)
    if t.dim() != 2 or t.shape[0] != b or t.shape[1] < d or not bool(torch.isfinite(t).all()):
        raise ParameterError(f"target must be a finite position ({d},) or ({b}, {d}) in the coords' frame, "
                             f"got shape {tuple(t.shape)}")
    return t[:, :d]


def _seeds(surfs: list[Surface], target) -> tuple[dict, dict, list]:
    b = surfs[0].pdet.shape[0]
    where = _where_peak(surfs, target)
    seed, has = {}, {}
    for s in surfs:
        sd, ok = _nearest(s, where)
        seed[s.name], has[s.name] = _climb(s.pdet, sd), ok
    cover = torch.stack([has[s.name] for s in surfs]).any(0)
    if not bool(cover.all()):
        raise ParameterError("target: no surface passes within a pixel of the point (items "
                             f"{torch.nonzero(~cover).flatten().tolist()[:5]})")
    vals = torch.stack([torch.where(has[s.name], s.pdet.reshape(b, -1).gather(
        1, (seed[s.name][:, 0] * s.pdet.shape[2] + seed[s.name][:, 1])[:, None])[:, 0],
        torch.full((b,), -1.0, dtype=s.pdet.dtype, device=s.pdet.device)) for s in surfs])
    return seed, has, [surfs[int(i)].name for i in vals.argmax(0).tolist()]


# --------------------------------------------------------------------------
# rays and the main lobe
# --------------------------------------------------------------------------

def _window_amp(p: Tensor, fi: Tensor, fj: Tensor) -> Tensor:
    """The amplitude (square root of ``p`` (B, H, W)) interpolated bilinearly at fractional
    indices ``fi``, ``fj`` (B, K, n) (clamped to the grid), read from the window they reach only."""
    b, h, w = p.shape
    i0 = max(0, int(math.floor(float(fi.min()))))
    i1 = min(h - 1, int(math.ceil(float(fi.max()))))
    j0 = max(0, int(math.floor(float(fj.min()))))
    j1 = min(w - 1, int(math.ceil(float(fj.max()))))
    i1, j1 = max(i1, i0 + 1), max(j1, j0 + 1)
    win = p[:, i0:i1 + 1, j0:j1 + 1].clamp(min=0).sqrt()
    gy = (fi.clamp(0, h - 1) - i0) / (i1 - i0) * 2 - 1
    gx = (fj.clamp(0, w - 1) - j0) / (j1 - j0) * 2 - 1
    grid = torch.stack([gx, gy], dim=-1).to(win.dtype)
    out = torch.nn.functional.grid_sample(win[:, None], grid, mode="bilinear", padding_mode="border",
                                          align_corners=True)
    return out[:, 0].double()


def _contour_radius(a: Tensor, inside: Tensor, db: float, dt: float) -> Tensor:
    """Distance (B, K) at which each ray first falls to ``db`` below its start (inf: never)."""
    level = (10.0 ** (db / 20.0)) * a[..., :1]
    below = inside & (a <= level)
    j = below.double().argmax(-1).clamp(min=1)
    a1, a0 = a.gather(-1, j[..., None])[..., 0], a.gather(-1, (j - 1)[..., None])[..., 0]
    frac = torch.where(a0 > a1, (a0 - level[..., 0]) / (a0 - a1), torch.ones_like(a0))
    return torch.where(below.any(-1), (j - 1 + frac) * dt, torch.full_like(a0, math.inf))


def _null_radius(a: Tensor, inside: Tensor, ripple_db: float, dt: float) -> Tensor:
    """Distance (B, K) of each ray's first null (the lowest amplitude before it first rises more
    than ``ripple_db`` above the lowest so far; its first occurrence); inf: never."""
    cm = torch.cummin(torch.where(inside, a, torch.full_like(a, math.inf)), dim=-1).values
    stop = inside & (a > 10.0 ** (ripple_db / 20.0) * cm)
    found = stop.any(-1)
    first = torch.where(found, stop.double().argmax(-1), torch.zeros_like(found, dtype=torch.long))
    low = cm.gather(-1, first[..., None])
    idx = torch.arange(a.shape[-1], device=a.device)
    at = ((a <= low) & (idx <= first[..., None])).double().argmax(-1)
    return torch.where(found, at * dt, torch.full_like(at, math.inf, dtype=torch.float64))


def _ray_radii(s: Surface, seed: Tensor, rule: MainLobeRule, limit: float | None) -> tuple[Tensor, Tensor]:
    """The main lobe's radius along each ray (B, K) and, per item, whether a ray stopped at
    ``limit`` undecided while still inside the surface."""
    b, h, w = s.pdet.shape
    sr, sc = s.step
    dt = 0.5 * min(sr, sc)
    full = math.hypot((h - 1) * sr, (w - 1) * sc)
    length = full if limit is None else min(full, limit)
    n = int(math.ceil(length / dt)) + 1
    dev = s.pdet.device
    phi = torch.arange(rule.n_rays, dtype=torch.float64, device=dev) * (2 * math.pi / rule.n_rays)
    t = torch.arange(n, dtype=torch.float64, device=dev) * dt
    fi = seed[:, 0, None, None].double() + (t[None, None] * torch.sin(phi)[None, :, None]) / sr
    fj = seed[:, 1, None, None].double() + (t[None, None] * torch.cos(phi)[None, :, None]) / sc
    eps = 1e-9
    inside = (fi >= -eps) & (fi <= h - 1 + eps) & (fj >= -eps) & (fj <= w - 1 + eps)
    a = _window_amp(s.pdet, fi, fj)                                      # (B, K, n)
    r_cont = _contour_radius(a, inside, rule.contour_db, dt)
    if rule.method == "contour":
        r = rule.contour_factor * r_cont
    else:
        r = _null_radius(a, inside, rule.ripple_db, dt)
        if rule.cap_factor is not None:
            r = torch.minimum(r, rule.cap_factor * r_cont)
    limited = (torch.isinf(r) & inside[..., -1]).any(-1) if length < full else torch.zeros(
        b, dtype=torch.bool, device=dev)
    return r, limited


def _main_box(s: Surface, seed: Tensor, r: Tensor) -> tuple[tuple, Tensor]:
    """The window that the finite radii reach and the main-lobe pixels (B, hh, ww) in it (within
    the rays' radii, linear in angle between rays)."""
    b, h, w = s.pdet.shape
    sr, sc = s.step
    k = r.shape[1]
    if bool(torch.isinf(r).any()):
        box = (0, h, 0, w)
    else:
        big = float(r.max()) * (1 + 1e-9)
        di, dj = int(math.ceil(big / sr)), int(math.ceil(big / sc))
        box = (max(0, int(seed[:, 0].min()) - di), min(h, int(seed[:, 0].max()) + di + 1),
               max(0, int(seed[:, 1].min()) - dj), min(w, int(seed[:, 1].max()) + dj + 1))
    i0, i1, j0, j1 = box
    hh, ww = i1 - i0, j1 - j0
    di = (torch.arange(i0, i1, device=r.device)[None, :, None] - seed[:, 0, None, None]).double() * sr
    dj = (torch.arange(j0, j1, device=r.device)[None, None, :] - seed[:, 1, None, None]).double() * sc
    d = torch.sqrt(di * di + dj * dj)                                     # (B, hh, ww)
    x = torch.remainder(torch.atan2(di.expand(b, hh, ww), dj.expand(b, hh, ww)), 2 * math.pi) / (2 * math.pi / k)
    k0 = x.floor().long() % k
    frac = x - x.floor()
    r0 = r.gather(1, k0.reshape(b, -1)).reshape(b, hh, ww)
    r1 = r.gather(1, ((k0 + 1) % k).reshape(b, -1)).reshape(b, hh, ww)
    rr = torch.where(torch.isinf(r0) | torch.isinf(r1), torch.full_like(r0, math.inf), (1 - frac) * r0 + frac * r1)
    return box, d <= rr * (1 + 1e-9) + 1e-12 * max(sr, sc)


def find_regions(surfs: list[Surface], target, rule: MainLobeRule) -> LobeRegions:
    """The main lobe of every item on every surface (:class:`LobeRegions`)."""
    seed, has, peak_plane = _seeds(surfs, target)
    b = surfs[0].pdet.shape[0]
    rays, boxes, mains = {}, {}, {}
    clipped = torch.zeros(b, dtype=torch.bool, device=surfs[0].pdet.device)
    for s in surfs:
        r, limited = _ray_radii(s, seed[s.name], rule, rule.max_radius)
        if bool(limited.any()):                  # walk those items again, to the edge
            sub = Surface(s.name, s.power, s.pdet[limited], s.pos, s.step, s.weight)
            r[limited] = _ray_radii(sub, seed[s.name][limited], rule, None)[0]
        r = torch.where(has[s.name][:, None], r, torch.zeros_like(r))
        boxes[s.name], m = _main_box(s, seed[s.name], r)
        mains[s.name] = m & has[s.name][:, None, None]
        rays[s.name] = r
        clipped |= torch.isinf(r).any(1)
    return LobeRegions(names=tuple(s.name for s in surfs), seed=seed, has_lobe=has, rays=rays, box=boxes,
                       main_box=mains, peak_plane=peak_plane, clipped=clipped,
                       shapes={s.name: tuple(s.pdet.shape[1:]) for s in surfs})


# --------------------------------------------------------------------------
# widths
# --------------------------------------------------------------------------

def _axis_along(pos: Tensor, comp: int) -> int | None:
    """The grid axis (0 rows, 1 columns) whose step runs mostly along component ``comp``, read at the
    grid's middle (at a corner of a wide sphere in u-v, a step runs mostly along z)."""
    i, j = max(pos.shape[0] // 2 - 1, 0), max(pos.shape[1] // 2 - 1, 0)
    for axis in (0, 1):
        if pos.shape[axis] < 2:
            continue
        step = (pos[i + 1, j] - pos[i, j]) if axis == 0 else (pos[i, j + 1] - pos[i, j])
        if abs(float(step[comp])) >= 0.5 * float(step.norm()) > 0:
            return axis
    return None


def _crossing(sv: Tensor, a: Tensor, j0: Tensor, level: Tensor, step: int) -> Tensor:
    """Coordinate of the first sample at or below ``level`` walking from ``j0`` by ``step``,
    interpolated linearly in amplitude towards the peak; NaN where none."""
    n = a.shape[1]
    idx = torch.arange(n, device=a.device)[None]
    below = (idx > j0[:, None] if step > 0 else idx < j0[:, None]) & (a <= level[:, None])
    found = below.any(1)
    j = below.double().argmax(1) if step > 0 else n - 1 - below.flip(1).double().argmax(1)
    prev = (j - step).clamp(0, n - 1)
    a1, a0 = a.gather(1, j[:, None])[:, 0], a.gather(1, prev[:, None])[:, 0]
    s1, s0 = sv.gather(1, j[:, None])[:, 0], sv.gather(1, prev[:, None])[:, 0]
    frac = torch.where(a0 > a1, (a0 - level) / (a0 - a1), torch.ones_like(a0))
    return torch.where(found, s0 + frac * (s1 - s0), torch.full_like(a0, math.nan))


def _surface_width(s: Surface, seed: Tensor, comp: int, axis: int, level: float) -> Tensor:
    b, h, w = s.pdet.shape
    rows = torch.arange(b, device=seed.device)
    if axis == 1:
        a, sv, j0 = s.pdet[rows, seed[:, 0], :], s.pos[seed[:, 0], :, comp], seed[:, 1]
    else:
        a, sv, j0 = s.pdet[rows, :, seed[:, 1]], s.pos[:, seed[:, 1], comp].T, seed[:, 0]
    a = a.double().clamp(min=0).sqrt()
    lev = level * a.gather(1, j0[:, None])[:, 0]
    width = (_crossing(sv, a, j0, lev, +1) - _crossing(sv, a, j0, lev, -1)).abs()
    return torch.where(torch.isfinite(width), width, torch.full_like(width, math.inf))


def widths(surfs, regions: LobeRegions, letters, level: float) -> dict[str, Tensor]:
    """``{"width_<letter>_6dB": (B,)}``: for each letter (x/u: component 0, y/v: component 1), on
    the first surface with a grid axis along it that holds the item's main lobe."""
    b = surfs[0].pdet.shape[0]
    out = {}
    for letter in letters:
        comp = 0 if letter in "xu" else 1
        width = torch.full((b,), math.nan, dtype=torch.float64, device=surfs[0].pdet.device)
        for s in surfs:
            axis = _axis_along(s.pos, comp)
            todo = torch.isnan(width) & regions.has_lobe[s.name]
            if axis is None or not bool(todo.any()):
                continue
            width = torch.where(todo, _surface_width(s, regions.seed[s.name], comp, axis, level), width)
        if bool(torch.isnan(width).all()):
            raise ParameterError(f"width_{letter}_6dB: no surface holding the main lobe has a grid axis along "
                                 f"{letter}; leave it out of terms")
        out[f"width_{letter}_6dB"] = torch.nan_to_num(width, nan=math.inf)
    return out


# --------------------------------------------------------------------------
# grating lobes
# --------------------------------------------------------------------------

def surface_uv(s: Surface, frame: str, origin) -> Tensor:
    """Direction cosines (H, W, 2) of the surface's pixels."""
    return s.pos if frame == "uv" else direction_cosines(s.pos, origin).to(s.pos.device)


def segment_distance(p: Tensor, seg: Tensor) -> Tensor:
    """Distance (N,) of points ``p`` (N, 2) to the nearest of the segments ``seg`` (G, 2, 2)."""
    a, d = seg[:, 0], seg[:, 1] - seg[:, 0]                          # (G, 2)
    dd = (d * d).sum(-1)
    t = ((p[:, None, :] - a[None]) * d[None]).sum(-1) / torch.where(dd > 0, dd, torch.ones_like(dd))
    q = a[None] + t.clamp(0, 1)[..., None] * d[None]                 # (N, G, 2)
    return (p[:, None, :] - q).norm(dim=-1).min(1).values


def _segments(g) -> Tensor:
    g = _array("grating_uv", g)
    if g.numel() == 0:
        return torch.zeros(0, 2, 2, dtype=torch.float64)
    if g.shape[-1] != 2 or g.dim() not in (2, 3) or (g.dim() == 3 and g.shape[1] != 2):
        raise ParameterError(f"grating_uv: points (G, 2) or segments (G, 2, 2), got shape {tuple(g.shape)}")
    if not bool(torch.isfinite(g).all()):
        raise ParameterError("grating_uv must hold finite directions (u, v)")
    return g[:, None].expand(-1, 2, 2) if g.dim() == 2 else g


def grating_distance(surfs, grating_uv, b: int, frame: str, origin) -> list[dict]:
    """For each item, ``{name: (H, W)}``: the u-v distance of every pixel to the nearest predicted
    grating lobe (``grating_uv``: one array (tensor or ndarray) of points (G, 2) or segments
    (G, 2, 2), or a list of B of them; inf where there is none). Items given the same object share
    one map."""
    sets = list(grating_uv) if isinstance(grating_uv, (list, tuple)) else [grating_uv] * b
    if len(sets) != b:
        raise ParameterError(f"grating_uv must be one array (G, 2) or (G, 2, 2), or a list of {b} of them")
    uvs = None
    cache: dict = {}
    out = []
    for g in sets:
        if id(g) not in cache:
            seg = _segments(g)
            if uvs is None:
                uvs = {s.name: surface_uv(s, frame, origin) for s in surfs}
            maps = {}
            for s in surfs:
                h, w = s.pdet.shape[1:]
                maps[s.name] = (torch.full((h, w), math.inf, dtype=torch.float64, device=s.pdet.device)
                                if seg.shape[0] == 0 else
                                segment_distance(uvs[s.name].reshape(-1, 2), seg.to(s.pdet.device)).reshape(h, w))
            cache[id(g)] = (g, maps)
        out.append(cache[id(g)][1])
    return out
