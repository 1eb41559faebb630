"""Per-beam lobe metrics: the main lobe of a point found from its own PSF, and what lies outside it.

The input is one point's PSF as a set of surfaces: ``planes`` maps a name to a real or complex
tensor ``(..., H, W)`` (one leading shape for every surface, typically ``(B,)`` for B selections;
``power=True``: the tensors hold ``|value|^2``), ``coords`` maps the same names to ``(H, W, 3)``
arrays. With ``frame="xyz"`` the coords are positions in metres (planes, or surfaces sampled in
angle such as :func:`~arraysel.physics.beampattern.sphere_surface`); with ``frame="uv"`` their first
two components are direction cosines ``(u, v)`` (a beam pattern,
:class:`~arraysel.physics.beampattern.BeamPattern`), the third ignored.

**The peak.** With ``target`` (the point's position in the coords' frame) each surface is seeded
at its pixel nearest the target; without, at its pixel nearest the largest ``|value|`` over every
surface. A surface whose nearest pixel lies more than one pixel step from that position holds no
main lobe. From its seed, each surface climbs to the local maximum (steepest ascent over the 8
neighbours): that pixel is the surface's main-lobe peak; the point's peak is the largest of them.

**The main lobe** (:class:`MainLobeRule`) is found on each surface along ``n_rays`` rays from its
peak, uniform in angle in the surface's own metric (pixel steps measured in metres, or in u-v),
sampled every half pixel by bilinear interpolation of the amplitude ``|value|``:

* ``method="null"`` (default): walking outward, the ray's **first null** is the lowest amplitude
  met before the amplitude first rises more than ``ripple_db`` (default 1 dB) above the lowest value
  met so far; the main lobe reaches the null (its first occurrence). A dip on the flank that the
  amplitude climbs out of by less than ``ripple_db`` is not a null (ripple, sampling, speckle); a
  ring of dips deeper than that is (a 2-D dip that is not a ring is walked round by the other rays);
* ``method="contour"``: the main lobe reaches ``contour_factor`` times the distance at which the ray
  first falls to ``contour_db`` (default -6 dB, interpolated linearly in amplitude); e.g. 1.66
  puts the null of a sinc at its -6 dB radius times 1.66.

A pixel belongs to the main lobe when its distance from the peak is at most the radius of the
rays on either side of its direction, interpolated linearly in angle. A ray that reaches the
surface's edge before its null has an infinite radius: the main lobe **touches the edge** there
(``clipped`` in :class:`LobeRegions`), and reaches the edge over that ray's angular sector; the
metrics are then computed on what is left. ``max_radius`` bounds the rays (a speed setting):
an item whose ray reaches it without a null is walked again to the edge.

**The metrics** (lower is better; the point's peak power ``p0``, pixel powers ``p``, pixel weights
``w`` (default 1; 0 = not part of the region), ``side`` = weighted pixels outside the main lobe):

* ``PSL_dB = 10 log10(max_side p / p0)``, the peak side-lobe level (MSLL of 2-D array papers);
* ``ISLR_dB = 10 log10(sum_side w p / sum_main w p)``, the integrated side-lobe ratio;
* ``GLL_dB``: the grating-lobe level: ``10 log10(max p / p0)`` over the side pixels whose direction
  ``(u, v)`` (:func:`~arraysel.physics.beampattern.direction_cosines` from ``origin`` in the
  frame ``"xyz"``) lies within ``grating_radius`` of a predicted grating-lobe direction
  (``grating_uv``: :func:`~arraysel.physics.beampattern.grating_lobe_directions`, from the lattice
  pitch and the band's wavelengths); ``grating_radius`` defaults to the main lobe's own radius in
  u-v (the largest u-v distance of a main-lobe pixel from the peak), since a grating lobe is a
  copy of the main lobe;
* ``width_x_6dB``, ``width_y_6dB`` (frame ``"xyz"``, metres) or ``width_u_6dB``, ``width_v_6dB``
  (frame ``"uv"``): on the first surface with a grid axis along x (u) and a main lobe, the profile
  along that axis through the surface's peak; the distance between the first samples at or below
  -6 dB on either side, interpolated linearly in amplitude (as
  :func:`arraysel.objective.metrics3d.main_lobe_widths`, but through the point's own peak).

Every dB value is floored at :data:`~arraysel.objective.metrics3d.PSL_FLOOR_DB` (no side pixel, no
grating-lobe pixel); a width that does not fall to -6 dB inside the surface is ``+inf``.
``PSL_dB``, ``ISLR_dB`` and ``GLL_dB`` are differentiable with respect to the planes (the regions
and peaks' positions detached, the maximum's sub-gradient); the widths are not. An all-zero or
non-finite PSF raises :class:`~arraysel.errors.NumericalError`.
"""
from __future__ import annotations

from typing import Iterable, Mapping

import torch
from torch import Tensor

from arraysel.errors import ParameterError, check_number
from arraysel.objective.lobe_regions import (FRAMES, LobeRegions, MainLobeRule, find_regions, grating_distance,
                                             pixel_map, surface_uv, surfaces, widths)
from arraysel.objective.metrics3d import PSL_FLOOR_DB, SIX_DB
from arraysel.physics.beampattern import direction_cosines, sphere_surface

__all__ = ["MainLobeRule", "LobeRegions", "FRAMES", "LOBE_TERMS", "main_lobe_regions", "lobe_metrics",
           "lobe_widths", "direction_cosines", "sphere_surface"]

#: every name :func:`lobe_metrics` returns, by frame
LOBE_TERMS = {"xyz": ("PSL_dB", "ISLR_dB", "GLL_dB", "width_x_6dB", "width_y_6dB"),
              "uv": ("PSL_dB", "ISLR_dB", "GLL_dB", "width_u_6dB", "width_v_6dB")}
_FLOOR = 10.0 ** (PSL_FLOOR_DB / 10.0)


def main_lobe_regions(planes: Mapping[str, Tensor], coords: Mapping[str, object], *, target=None,
                      rule: MainLobeRule = MainLobeRule(), power: bool = False, frame: str = "xyz") -> LobeRegions:
    """The main lobe of each item of a point's PSF (:class:`LobeRegions`, its ``main`` the pixels
    ``{name: (B, H, W)}``; module docstring). No gradient. Raises NumericalError for an all-zero
    or non-finite item."""
    surfs, _ = surfaces(planes, coords, None, power, frame)
    return find_regions(surfs, target, rule)


def lobe_widths(planes: Mapping[str, Tensor], coords: Mapping[str, object], *, target=None,
                rule: MainLobeRule = MainLobeRule(), power: bool = False, frame: str = "xyz",
                level_db: float = -6.0) -> dict[str, Tensor]:
    """The main-lobe widths at ``level_db`` (default -6 dB) along x and y (frame ``"xyz"``, metres)
    or u and v (frame ``"uv"``) through the point's own peak (module docstring), float64 of the
    planes' leading shape."""
    level = 10.0 ** (check_number("level_db", level_db, lo=-60, hi=0, hi_open=True) / 20.0)
    surfs, lead = surfaces(planes, coords, None, power, frame)
    reg = find_regions(surfs, target, rule)
    return {k: v.reshape(lead) for k, v in widths(surfs, reg, _letters(frame), level).items()}


def _letters(frame: str) -> tuple[str, str]:
    return ("x", "y") if frame == "xyz" else ("u", "v")


def _db(ratio: Tensor) -> Tensor:
    return 10.0 * torch.log10(torch.clamp(ratio, min=_FLOOR))


def _wanted(terms, frame: str, have_grating: bool) -> tuple[str, ...]:
    if frame not in LOBE_TERMS:
        raise ParameterError(f"frame = {frame!r} is not allowed; choose one of {list(FRAMES)}")
    names = LOBE_TERMS[frame]
    if terms is None:
        return tuple(t for t in names if t != "GLL_dB" or have_grating)
    want = tuple([terms] if isinstance(terms, str) else terms)
    for t in want:
        if t not in names:
            raise ParameterError(f"unknown lobe metric {t!r} for frame {frame!r}; choose among {list(names)}")
    if "GLL_dB" in want and not have_grating:
        raise ParameterError("GLL_dB needs grating_uv (the predicted grating-lobe directions)")
    return want


def _uv_radius(surfs, reg: LobeRegions, frame: str, origin) -> Tensor:
    """The largest u-v distance (B,) of a main-lobe pixel from the item's peak."""
    b = reg.clipped.shape[0]
    dev = reg.clipped.device
    uvs = {s.name: surface_uv(s, frame, origin) for s in surfs}
    puv = torch.zeros(b, 2, dtype=torch.float64, device=dev)
    for s in surfs:
        sel = torch.as_tensor([p == s.name for p in reg.peak_plane], device=dev)
        sd = reg.seed[s.name]
        puv[sel] = uvs[s.name][sd[sel, 0], sd[sel, 1]]
    radius = torch.zeros(b, dtype=torch.float64, device=dev)
    for s in surfs:
        i0, _, j0, _ = reg.box[s.name]
        bi, ii, jj = torch.nonzero(reg.main_box[s.name], as_tuple=True)
        d = (uvs[s.name][ii + i0, jj + j0] - puv[bi]).norm(dim=-1)
        radius = radius.scatter_reduce(0, bi, d, reduce="amax")
    return radius


def _grating_top(t: Tensor, maps: list, name: str, radius: Tensor) -> Tensor:
    """The largest value (B,) of ``t`` (B, H, W) within ``radius`` of each item's grating lobes."""
    b = t.shape[0]
    top = torch.zeros(b, dtype=t.dtype, device=t.device)
    groups: dict = {}
    for i, m in enumerate(maps):
        groups.setdefault(id(m[name]), (m[name], []))[1].append(i)
    flat = t.reshape(b, -1)
    for dist, items in groups.values():
        it = torch.as_tensor(items, device=t.device)
        r = radius[it]
        cand = torch.nonzero(dist.reshape(-1) <= float(r.max())).flatten()
        if cand.numel() == 0:
            continue
        near = dist.reshape(-1)[cand][None] <= r[:, None]             # (n, C)
        vals = flat[it][:, cand] * near
        top = top.index_put((it,), vals.amax(1))
    return top


def lobe_metrics(planes: Mapping[str, Tensor], coords: Mapping[str, object], *, target=None,
                 rule: MainLobeRule = MainLobeRule(), grating_uv=None, grating_radius: float | None = None,
                 weights: Mapping[str, object] | None = None, peak_weights: Mapping[str, object] | None = None,
                 power: bool = False, frame: str = "xyz", origin=(0.0, 0.0, 0.0), terms: Iterable[str] | None = None,
                 regions: LobeRegions | None = None, grating_maps: list | None = None) -> dict[str, Tensor]:
    """The per-beam lobe metrics of one point's PSF (module docstring).

    Parameters
    ----------
    planes, coords : the point's surfaces ``{name: (..., H, W)}`` and ``{name: (H, W, 3)}``
    target : the point's position in the coords' frame, (3,) or (B, 3); None: the largest value
    rule : :class:`MainLobeRule`
    grating_uv : predicted grating-lobe directions: one tensor or ndarray of points (G, 2) or of
        segments (G, 2, 2) (a band of wavelengths), or a list of B of them; None: ``GLL_dB`` is
        left out (asking for it in ``terms`` is then an error)
    grating_radius : u-v radius around each predicted direction (default: the main lobe's own)
    weights : ``{name: (H, W)}`` pixel weights >= 0 of the sums (default 1; 0 takes a pixel out of
        the region)
    peak_weights : ``{name: (H, W)}`` >= 0, multiplying the power before the maxima of ``PSL_dB``
        and ``GLL_dB`` (default 1 inside the region); e.g. the largest view of a pixel over a
        sector's beams relative to each beam's peak (a beam pattern's ``peak_weight``)
    power : the planes hold ``|value|^2`` (e.g. an energy beam pattern)
    frame : ``"xyz"`` (coords in metres) or ``"uv"`` (coords hold direction cosines)
    origin : the array centre, for the directions of pixels in the frame ``"xyz"``
    terms : names among ``LOBE_TERMS[frame]`` (default: all that the inputs allow)
    regions : :func:`main_lobe_regions` of the same planes, if already computed
    grating_maps : instead of ``grating_uv``, a list of B dicts ``{name: (H, W)}``: each pixel's
        u-v distance to the item's nearest predicted grating lobe (inf: none); items sharing a
        map object are scored together

    Returns ``{name: Tensor of the planes' leading shape}``.
    """
    surfs, lead = surfaces(planes, coords, weights, power, frame)
    want = _wanted(terms, frame, grating_uv is not None or grating_maps is not None)
    reg = regions if regions is not None else find_regions(surfs, target, rule)
    b = surfs[0].power.shape[0]
    peak = torch.stack([s.power.reshape(b, -1).gather(1, (reg.seed[s.name][:, 0] * s.power.shape[2]
                        + reg.seed[s.name][:, 1])[:, None])[:, 0] * reg.has_lobe[s.name] for s in surfs]).amax(0)
    out: dict[str, Tensor] = {}
    if "PSL_dB" in want or "GLL_dB" in want:
        maps = radius = None
        if "GLL_dB" in want:
            maps = grating_maps if grating_maps is not None else grating_distance(surfs, grating_uv, b, frame, origin)
            if len(maps) != b:
                raise ParameterError(f"grating_maps must hold one dict a batch item ({b}), got {len(maps)}")
            radius = (_uv_radius(surfs, reg, frame, origin) if grating_radius is None else torch.full(
                (b,), check_number("grating_radius", grating_radius, lo=0, lo_open=True), dtype=torch.float64))
        psl, gll = [], []
        for s in surfs:
            pw = ((s.weight > 0).to(s.power.dtype) if peak_weights is None or s.name not in peak_weights else
                  pixel_map(f"peak_weights[{s.name!r}]", peak_weights[s.name], s.pdet.shape[1:], s.power.device,
                            s.power.dtype))
            t = s.power * pw
            i0, i1, j0, j1 = reg.box[s.name]
            t[:, i0:i1, j0:j1] = t[:, i0:i1, j0:j1].masked_fill(reg.main_box[s.name], 0)
            psl.append(t.reshape(b, -1).amax(1))
            if maps is not None:
                gll.append(_grating_top(t, maps, s.name, radius.to(t.device)))
        if "PSL_dB" in want:
            out["PSL_dB"] = _db(torch.stack(psl).amax(0) / peak)
        if "GLL_dB" in want:
            out["GLL_dB"] = _db(torch.stack(gll).amax(0) / peak)
    if "ISLR_dB" in want:
        e_side = e_main = 0
        for s in surfs:
            i0, i1, j0, j1 = reg.box[s.name]
            total = s.power.reshape(b, -1) @ s.weight.reshape(-1)
            main = (s.power[:, i0:i1, j0:j1] * (s.weight[i0:i1, j0:j1] * reg.main_box[s.name])).sum((1, 2))
            e_side, e_main = e_side + torch.clamp(total - main, min=0), e_main + main
        out["ISLR_dB"] = _db(e_side / torch.clamp(e_main, min=torch.finfo(e_main.dtype).tiny))
    wnames = [t for t in want if t.startswith("width_")]
    if wnames:
        w = widths(surfs, reg, tuple(t[6] for t in wnames), SIX_DB)
        out.update({t: w[t].to(surfs[0].power.dtype) for t in wnames})
    return {t: out[t].reshape(lead) for t in want}
