"""Metrics of a 3-D point-spread function given as a set of planes (matrix probes).

A 3-D PSF is a *plane set*: ``planes`` maps a plane name (``"xy"`` the C-plane at the scatterer's
depth, ``"xz"``, ``"yz"``, ...) to a real or complex tensor ``(..., H, W)`` (the same leading shape
for every plane, typically ``(B,)`` for B masks), and ``coords`` maps the same names to the
``(x, y, z)`` position in metres of each pixel, an array ``(H, W, 3)``. The reference (the full
array) is a plane set of the same names and windows whose leading shape broadcasts to the planes'
(usually ``(1,)``).

The definitions follow the 1-D ones of :mod:`arraysel.objective.metrics` (``docs/metrics.md``) with the
pixels of every plane taken together (``docs/metrics.md``, section "3-D PSF (matrix probes)"):

* the plane set is normalised jointly by its L2 norm (:func:`normalise_planes`; every metric is
  invariant to that scale, so the metrics need not apply it);
* the peak is the pixel of largest ``|kappa|`` over all planes (the first in plane order, then
  row-major order, on ties) and ``r`` is the 3-D distance in metres of each pixel from it;
* ``L_PSF`` is the SI-MSE over all planes jointly; ``L_contrast``, ``L_SLR_q``, ``L_SLR_i``,
  ``L_SLR`` and ``Mean`` are the 1-D formulas on ``m = |kappa| / max |kappa|`` with
  ``Omega_main = {r <= r_main lambda0}`` and ``Omega_side = {r >= r_guard lambda0}`` in 3-D;
* ``PSL_dB``: the peak side-lobe level, ``20 log10 max(m over Omega_side)`` (floored at
  :data:`PSL_FLOOR_DB`);
* ``width_x_6dB`` / ``width_y_6dB``: the -6 dB main-lobe widths in metres along x and y, from the
  profiles of the C-plane through its own peak, the crossings of ``10**(-6/20)`` found by linear
  interpolation of the amplitude between samples (``+inf`` when the profile does not fall to -6 dB
  inside the window).

The Table-1 terms are differentiable with respect to the planes (finite sub-gradients at the
non-smooth points, as in 1-D); ``PSL_dB`` is too (a max); the widths are not (they are computed on
detached values). A zero plane set gives ``L_PSF = 1``, ratios 0, ``PSL_dB`` at the floor and widths
``+inf`` (no NaN); :func:`check_planes` rejects it explicitly.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Iterable, Mapping

import numpy as np
import torch
from torch import Tensor

from arraysel.errors import NumericalError, ParameterError, check_number
from arraysel.objective.metrics import METRIC_NAMES, check_finite, si_mse
from arraysel.objective.reductions import (BOUNDARY_RTOL, broadcast_shapes, masked_quantile, peak_index, rowdot,
                                           safe_div, safe_sqrt, scaled_abs2)
from arraysel.objective.tensors import _abs2, _check_kernel_shape, _check_tensor

__all__ = ["MERIT_NAMES", "PSF3D_TERMS", "SIX_DB", "PSL_FLOOR_DB", "C_PLANE", "FlatPlanes", "PSF3DRegions",
           "plane_set", "normalise_planes", "psf3d_regions", "psf3d_metrics", "c_plane_profiles",
           "main_lobe_widths", "check_planes", "c_plane_axes", "level_crossing", "region_radii"]

#: the figures of merit of 2-D sparse-array papers (defined in :mod:`arraysel.objective.names`)
from arraysel.objective.names import MERIT_NAMES  # noqa: E402
#: every name :func:`psf3d_metrics` can return
PSF3D_TERMS: tuple[str, ...] = tuple(METRIC_NAMES) + MERIT_NAMES
#: the amplitude of -6 dB, the level of the main-lobe widths
SIX_DB = 10.0 ** (-6.0 / 20.0)
#: the lowest peak side-lobe level reported (an all-zero side region)
PSL_FLOOR_DB = -240.0
#: the default name of the C-plane (the plane at the scatterer's depth, spanned by x and y)
C_PLANE = "xy"


# --------------------------------------------------------------------------
# the plane set
# --------------------------------------------------------------------------

@dataclass
class FlatPlanes:
    """A validated plane set, its pixels concatenated (the metrics' working form of the planes of a
    :class:`~arraysel.physics.imaging.PlaneSet`).

    Attributes
    ----------
    names : the plane names, in the order of ``planes``
    flat : Tensor ``(B, N)``, the pixels of every plane, plane after plane, each row-major
    lead : the leading shape of the planes (``B`` is its product)
    coords : float64 Tensor ``(N, 3)`` on ``flat``'s device (float32 on MPS), metres
    shapes : ``{name: (H, W)}``
    offsets : ``{name: first column of the plane in flat}``
    """

    names: tuple[str, ...]
    flat: Tensor
    lead: torch.Size
    coords: Tensor
    shapes: dict
    offsets: dict

    def split(self, values: Tensor) -> dict[str, Tensor]:
        """``(..., N)`` per-pixel values -> ``{name: (..., H, W)}``."""
        out = {}
        for name in self.names:
            h, w = self.shapes[name]
            o = self.offsets[name]
            out[name] = values[..., o:o + h * w].reshape(tuple(values.shape[:-1]) + (h, w))
        return out


def _coords_tensor(name: str, c, hw: tuple[int, int], device) -> Tensor:
    if isinstance(c, Tensor):
        c = c.detach().cpu().to(torch.float64)
    else:
        try:
            c = torch.as_tensor(np.asarray(c, dtype=np.float64))
        except (TypeError, ValueError) as exc:
            raise ParameterError(f"{name} must be an array of (x, y, z) positions in metres: {exc}") from None
    if tuple(c.shape) != tuple(hw) + (3,):
        raise ParameterError(f"{name} must have shape {tuple(hw) + (3,)} (the plane's window and x, y, z), "
                             f"got {tuple(c.shape)}")
    if not bool(torch.isfinite(c).all()):
        raise ParameterError(f"{name} holds non-finite positions")
    dt = torch.float32 if torch.device(device).type == "mps" else torch.float64
    return c.to(device=device, dtype=dt)


def plane_set(planes: Mapping[str, Tensor], coords: Mapping[str, object], *, what: str = "planes") -> FlatPlanes:
    """Check a plane set and concatenate its pixels (:class:`FlatPlanes`).

    Every plane is a real or complex tensor ``(..., H, W)`` with the same leading shape; ``coords``
    has an ``(H, W, 3)`` array (numpy or torch, metres) for every plane. Raises
    :class:`ParameterError` naming the plane (``planes['xz']``) on a bad entry.
    """
    if not isinstance(planes, Mapping) or not planes:
        raise ParameterError(f"{what} must be a non-empty dict {{plane name: tensor (..., H, W)}}, "
                             f"got {type(planes).__name__}")
    if not isinstance(coords, Mapping):
        raise ParameterError(f"coords must be a dict {{plane name: array (H, W, 3)}}, got {type(coords).__name__}")
    names = tuple(planes)
    lead = None
    dtype = None
    for name in names:
        x = _check_tensor(f"{what}[{name!r}]", planes[name])
        _check_kernel_shape(f"{what}[{name!r}]", x)
        if lead is None:
            lead = x.shape[:-2]
        elif x.shape[:-2] != lead:
            raise ParameterError(f"{what}[{name!r}] has leading shape {tuple(x.shape[:-2])}; every plane must "
                                 f"have the leading shape {tuple(lead)} of {what}[{names[0]!r}]")
        dtype = x.dtype if dtype is None else torch.promote_types(dtype, x.dtype)
        if name not in coords:
            raise ParameterError(f"coords has no entry for plane {name!r} (it has {sorted(coords)})")
    device = planes[names[0]].device
    b = int(math.prod(lead))
    parts, cparts, shapes, offsets = [], [], {}, {}
    n = 0
    for name in names:
        x = planes[name]
        h, w = x.shape[-2:]
        shapes[name], offsets[name] = (int(h), int(w)), n
        n += int(h) * int(w)
        parts.append(x.to(device=device, dtype=dtype).reshape(b, -1))
        cparts.append(_coords_tensor(f"coords[{name!r}]", coords[name], (int(h), int(w)), device).reshape(-1, 3))
    return FlatPlanes(names=names, flat=torch.cat(parts, dim=-1), lead=lead, coords=torch.cat(cparts, dim=0),
                    shapes=shapes, offsets=offsets)


def _reference(ps: FlatPlanes, planes_ref: Mapping[str, Tensor], coords) -> Tensor:
    """The reference plane set as ``(Bref, N)`` in the planes' order, its leading shape broadcasting."""
    if not isinstance(planes_ref, Mapping) or set(planes_ref) != set(ps.names):
        have = sorted(planes_ref) if isinstance(planes_ref, Mapping) else type(planes_ref).__name__
        raise ParameterError(f"planes_ref must have the planes {sorted(ps.names)}, got {have}")
    ordered = {name: planes_ref[name] for name in ps.names}
    for name in ps.names:
        x = _check_tensor(f"planes_ref[{name!r}]", ordered[name])
        _check_kernel_shape(f"planes_ref[{name!r}]", x)
        if tuple(x.shape[-2:]) != ps.shapes[name]:
            raise ParameterError(f"planes_ref[{name!r}] has the window {tuple(x.shape[-2:])} but the plane "
                                 f"has {ps.shapes[name]}")
    ref = plane_set(ordered, coords, what="planes_ref")
    try:
        shape = broadcast_shapes(tuple(ps.lead) + (1,), tuple(ref.lead) + (1,))
    except RuntimeError:
        shape = None
    if shape is None or tuple(shape[:-1]) != tuple(ps.lead):
        raise ParameterError(f"planes_ref's leading shape {tuple(ref.lead)} must broadcast to the planes' "
                             f"{tuple(ps.lead)}")
    flat = ref.flat.to(ps.flat.device)
    if flat.shape[0] not in (1, ps.flat.shape[0]):
        flat = flat.reshape(tuple(ref.lead) + (-1,)).expand(tuple(ps.lead) + (flat.shape[-1],)).reshape(
            ps.flat.shape[0], -1)
    return flat


def normalise_planes(planes: Mapping[str, Tensor]) -> dict[str, Tensor]:
    """The plane set divided by its joint L2 norm: ``sum over every plane of |kappa|^2 = 1`` for each
    item of the batch (a zero set is returned unchanged). Differentiable; the planes keep their
    windows and leading shape. (No coordinates needed.)"""
    dummy = {name: np.zeros(tuple(p.shape[-2:]) + (3,)) for name, p in planes.items()
             if isinstance(p, Tensor) and p.dim() >= 2}
    ps = plane_set(planes, dummy)
    x = ps.flat
    xs = x / _joint_scale(x)[:, None]
    sq = _abs2(xs).sum(-1)
    norm = torch.sqrt(torch.where(sq > 0, sq, torch.ones_like(sq)))
    out = xs / norm[:, None]
    return {name: v.reshape(tuple(ps.lead) + v.shape[-2:]) for name, v in ps.split(out).items()}


def _joint_scale(x: Tensor) -> Tensor:
    """Detached max(|Re|, |Im|) of each row of ``x`` (B, N); 1 for a zero row."""
    x = x.detach()
    s = (torch.view_as_real(x).abs().amax(dim=(-2, -1)) if x.is_complex() else x.abs().amax(dim=-1))
    return torch.where(s > 0, s, torch.ones_like(s))


def check_planes(planes: Mapping[str, Tensor], coords: Mapping[str, object],
                 planes_ref: Mapping[str, Tensor] | None = None) -> None:
    """Raise :class:`NumericalError` when a plane set cannot be scored: a non-finite pixel, or a
    batch item whose planes are all zero (its metrics would be placeholders). Synchronises with the
    device; call it outside hot loops."""
    for what, p in (("planes", planes), ("planes_ref", planes_ref)):
        if p is None:
            continue
        ps = plane_set(p, coords, what=what)
        check_finite(what, ps.flat)
        zero = (ps.flat == 0).all(-1)
        if bool(zero.any()):
            idx = torch.nonzero(zero).flatten().tolist()[:5]
            where = "" if len(ps.lead) == 0 else f" at batch index(es) {idx}"
            raise NumericalError(f"{what} is identically zero{where}; its 3-D PSF metrics are undefined")


# --------------------------------------------------------------------------
# regions
# --------------------------------------------------------------------------

@dataclass
class PSF3DRegions:
    """Regions of a batch of plane sets, relative to each item's 3-D peak.

    Attributes
    ----------
    peak_plane : list of the plane name holding each item's peak (flattened batch order)
    peak_position : Tensor ``(..., 3)``, the peak's (x, y, z) in metres
    main, side : ``{name: BoolTensor (..., H, W)}``, ``r <= r_main`` and ``r >= r_guard``
    r : ``{name: Tensor (..., H, W)}``, the 3-D distance to the peak in metres
    """

    peak_plane: list
    peak_position: Tensor
    main: dict
    side: dict
    r: dict


def region_radii(wavelength, r_main, r_guard) -> tuple[float, float]:
    lam = check_number("wavelength", wavelength, lo=0, lo_open=True)
    rm = check_number("r_main", r_main, lo=0)
    rg = check_number("r_guard", r_guard, lo=0)
    if rg < rm:
        raise ParameterError(f"r_guard = {r_guard!r} must be >= r_main = {r_main!r} (both in wavelengths)")
    return rm * lam, rg * lam


def _distance2(coords: Tensor, position: Tensor) -> Tensor:
    """Squared 3-D distance ``(U, N)`` of every pixel from each of the points ``position`` (U, 3)."""
    return (coords[None, :, :] - position[:, None, :]).square().sum(-1)


def _region_masks(coords: Tensor, position: Tensor, rm: float, rg: float, dtype) -> tuple[Tensor, Tensor]:
    """0/1 masks ``(U, N)`` of ``r <= rm`` and ``r >= rg`` around each peak position (U, 3)."""
    d2 = _distance2(coords, position)
    main = (d2 <= rm * rm * (1 + BOUNDARY_RTOL)).to(dtype)
    side = (d2 >= rg * rg * (1 - BOUNDARY_RTOL)).to(dtype)
    return main, side


def psf3d_regions(planes: Mapping[str, Tensor], coords: Mapping[str, object], *, wavelength: float,
                  r_main: float = 1.5, r_guard: float = 2.5) -> PSF3DRegions:
    """The 3-D peak, distance map and regions of each item of a plane set (no gradient).

    ``r`` is the 3-D distance in metres of every pixel from the pixel of the largest ``|kappa|``
    over all planes; ``Omega_main = {r <= r_main wavelength}``, ``Omega_side = {r >= r_guard
    wavelength}``, boundaries inclusive (relative tolerance 1e-9 on ``r**2``, as in 1-D).
    """
    ps = plane_set(planes, coords)
    rm, rg = region_radii(wavelength, r_main, r_guard)
    with torch.no_grad():
        k2 = scaled_abs2(ps.flat[:, None, :])
        peak = peak_index(k2)
        d2 = _distance2(ps.coords, ps.coords[peak])
    lead = tuple(ps.lead)

    def per_plane(values: Tensor) -> dict:
        return {n: v.reshape(lead + v.shape[-2:]) for n, v in ps.split(values).items()}

    ends = np.cumsum([ps.shapes[n][0] * ps.shapes[n][1] for n in ps.names])
    plane_of = [ps.names[int(np.searchsorted(ends, int(i), side="right"))] for i in peak.tolist()]
    rdt = ps.flat.real.dtype if ps.flat.is_complex() else ps.flat.dtype
    return PSF3DRegions(peak_plane=plane_of, peak_position=ps.coords[peak].reshape(lead + (3,)),
                        main=per_plane(d2 <= rm * rm * (1 + BOUNDARY_RTOL)),
                        side=per_plane(d2 >= rg * rg * (1 - BOUNDARY_RTOL)),
                        r=per_plane(d2.sqrt().to(rdt)))


# --------------------------------------------------------------------------
# the C-plane's profiles and the -6 dB widths
# --------------------------------------------------------------------------

def c_plane_axes(name: str, c: np.ndarray) -> dict[str, int]:
    """Which window axis (0 rows, 1 columns) runs along x and along y in the plane ``c`` (H, W, 3)."""
    h, w = c.shape[:2]
    if h < 2 or w < 2:
        raise ParameterError(f"planes[{name!r}] must be at least 2 x 2 pixels for the main-lobe widths, "
                             f"got {h} x {w}")
    steps = (c[1, 0] - c[0, 0], c[0, 1] - c[0, 0])    # along rows (axis 0), along columns (axis 1)
    x_axis = 0 if abs(steps[0][0]) > abs(steps[1][0]) else 1
    y_axis = 1 - x_axis
    if abs(steps[x_axis][0]) <= 0 or abs(steps[y_axis][1]) <= 0:
        raise ParameterError(f"planes[{name!r}] is not a C-plane: its rows and columns must run along x "
                             f"and y (steps {steps[0].tolist()} and {steps[1].tolist()} m)")
    return {"x": x_axis, "y": y_axis}


def c_plane_profiles(plane, coords, *, name: str = C_PLANE) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """The profiles of ``|kappa|`` of a C-plane through its peak, along x and along y.

    ``plane`` is an array or tensor ``(..., H, W)`` and ``coords`` its ``(H, W, 3)`` positions
    (metres); the plane's rows and columns run along x and y (either order). Returns
    ``{"x": (s, a), "y": (s, a)}`` with ``s`` ``(B, n)`` the x (or y) coordinate of each sample in
    metres and ``a`` ``(B, n)`` the amplitude ``|kappa|`` (float64, detached), ``B`` the product of
    the leading shape, the profile through each item's own peak pixel (first maximum in row-major
    order).
    """
    a = plane.detach().cpu() if isinstance(plane, Tensor) else np.asarray(plane)
    a = np.abs(np.asarray(a)).astype(np.float64)
    if a.ndim < 2:
        raise ParameterError(f"planes[{name!r}] must have shape (..., H, W), got {a.shape}")
    c = _coords_tensor(f"coords[{name!r}]", coords, a.shape[-2:], "cpu").numpy()
    axes = c_plane_axes(name, c)
    a = a.reshape((-1,) + a.shape[-2:])
    b, h, w = a.shape
    flat_peak = np.argmax(a.reshape(b, -1), axis=1)
    i0, j0 = flat_peak // w, flat_peak % w
    rows = np.arange(b)
    out = {}
    for letter, comp in (("x", 0), ("y", 1)):
        if axes[letter] == 1:       # along the row i0: columns vary
            amp = a[rows, i0, :]
            s = c[i0, :, comp]
        else:
            amp = a[rows, :, j0]
            s = c[:, j0, comp].T
        out[letter] = (np.asarray(s, dtype=np.float64).reshape(b, -1), amp)
    return out


def level_crossing(s: np.ndarray, a: np.ndarray, j0: np.ndarray, level: np.ndarray, step: int) -> np.ndarray:
    """Position of the first sample at or below ``level`` walking from ``j0`` by ``step``, with the
    crossing interpolated linearly in amplitude; NaN where the profile never falls to ``level``."""
    b, n = a.shape
    idx = np.arange(n)[None, :]
    ahead = (idx > j0[:, None]) if step > 0 else (idx < j0[:, None])
    below = ahead & (a <= level[:, None])
    found = below.any(axis=1)
    if step > 0:
        j = np.where(found, np.argmax(below, axis=1), 0)
    else:
        j = np.where(found, n - 1 - np.argmax(below[:, ::-1], axis=1), 0)
    prev = np.clip(j - step, 0, n - 1)
    rows = np.arange(b)
    a1, a0 = a[rows, j], a[rows, prev]
    s1, s0 = s[rows, j], s[rows, prev]
    with np.errstate(invalid="ignore", divide="ignore"):
        frac = np.where(a0 > a1, (a0 - level) / (a0 - a1), 1.0)
    return np.where(found, s0 + frac * (s1 - s0), np.nan)


def main_lobe_widths(plane, coords, *, name: str = C_PLANE, level: float = SIX_DB) -> dict[str, np.ndarray]:
    """-6 dB main-lobe widths (metres) along x and y of a C-plane ``(..., H, W)``.

    On the profiles of :func:`c_plane_profiles`, relative to the profile's peak sample, the first
    sample at or below ``level`` (amplitude, default ``10**(-6/20)``) on each side of the peak is
    found and the crossing interpolated linearly in amplitude between it and its neighbour towards
    the peak; the width is the distance between the two crossings. ``+inf`` when the profile does
    not fall to ``level`` on both sides inside the window; ``+inf`` for a zero plane. Returns
    ``{"x": (B,), "y": (B,)}`` float64 arrays.
    """
    level = check_number("level", level, lo=0, hi=1, lo_open=True, hi_open=True)
    out = {}
    for letter, (s, a) in c_plane_profiles(plane, coords, name=name).items():
        j0 = np.argmax(a, axis=1)
        peak = a[np.arange(a.shape[0]), j0]
        thr = level * peak
        right = level_crossing(s, a, j0, thr, +1)
        left = level_crossing(s, a, j0, thr, -1)
        width = np.abs(right - left)
        out[letter] = np.where(np.isfinite(width) & (peak > 0), width, np.inf)
    return out


# --------------------------------------------------------------------------
# the metrics
# --------------------------------------------------------------------------

def _parse_terms(terms: Iterable[str] | None, have_ref: bool, have_c: bool) -> tuple[str, ...]:
    if terms is None:
        base = [t for t in PSF3D_TERMS if (have_ref or t not in ("L_PSF", "Mean"))]
        return tuple(t for t in base if have_c or t not in ("width_x_6dB", "width_y_6dB"))
    if isinstance(terms, str):
        terms = (terms,)
    out = []
    for t in terms:
        if t not in PSF3D_TERMS:
            raise ParameterError(f"unknown 3-D PSF metric {t!r}; choose among {list(PSF3D_TERMS)}")
        if t in ("L_PSF", "Mean") and not have_ref:
            raise ParameterError(f"metric {t!r} needs planes_ref")
        if t not in out:
            out.append(t)
    return tuple(out)


def _lobe_terms(k2: Tensor, peak: Tensor, main: Tensor, side: Tensor, lobe: set, q: float) -> dict[str, Tensor]:
    """The lobe terms of items ``k2`` (B, N) (``|kappa|^2`` up to a per-item constant) with peaks
    ``peak`` (B,) and 0/1 region masks ``main``, ``side``, (B, N) or shared (1, N)."""
    b = k2.shape[0]
    res: dict[str, Tensor] = {}
    if {"L_contrast", "L_SLR_i"} & lobe:
        s_main = rowdot(k2, main.expand(b, -1))
        s_side = rowdot(k2, side.expand(b, -1))
        if "L_SLR_i" in lobe:
            res["L_SLR_i"] = safe_div(s_side, s_main)
        if "L_contrast" in lobe:
            res["L_contrast"] = safe_div(safe_div(s_side, side.sum(-1).expand(b)),
                                          safe_div(s_main, main.sum(-1).expand(b)))
    k2_peak = k2.gather(-1, peak[:, None]).squeeze(-1)
    if "L_SLR_q" in lobe:
        q_side = masked_quantile(k2, side.expand(b, -1), q, transform=safe_sqrt)
        res["L_SLR_q"] = safe_div(q_side, safe_sqrt(k2_peak))
    if "PSL_dB" in lobe:
        side_max = (k2 * side).amax(-1)                                  # k2 >= 0: 0 outside the side region
        ratio = safe_div(side_max, k2_peak)
        res["PSL_dB"] = 10.0 * torch.log10(torch.clamp(ratio, min=10.0 ** (PSL_FLOOR_DB / 10.0)))
    return res


def psf3d_metrics(planes: Mapping[str, Tensor], coords: Mapping[str, object], *, wavelength: float,
                  planes_ref: Mapping[str, Tensor] | None = None, r_main: float = 1.5, r_guard: float = 2.5,
                  quantile: float = 0.99, terms: Iterable[str] | None = None,
                  c_plane: str = C_PLANE) -> dict[str, Tensor]:
    """Metrics of a batch of 3-D PSFs given as plane sets; lower is better for every name.

    Parameters
    ----------
    planes : ``{name: Tensor (..., H, W)}``, real or complex, one leading shape for all planes
    coords : ``{name: array (H, W, 3)}``, the (x, y, z) of every pixel in metres
    wavelength : lambda0 = c / fc in metres
    planes_ref : the full array's plane set (same names and windows, leading shape broadcasting,
        usually ``(1,)``); needed for ``L_PSF`` and ``Mean``
    r_main, r_guard : the radii of the main-lobe and side-lobe regions in wavelengths (3-D distance)
    quantile : q of ``L_SLR_q``
    terms : names to compute among :data:`PSF3D_TERMS` (default: every one the inputs allow:
        ``L_PSF``/``Mean`` need ``planes_ref``, the widths need the plane ``c_plane``)
    c_plane : the name of the C-plane (the widths are measured on it)

    Returns
    -------
    ``{name: real Tensor of the planes' leading shape}``: the Table-1 terms (``L_PSF``,
    ``L_contrast``, ``L_SLR_q``, ``L_SLR_i``, ``L_SLR``, ``Mean``, as in 1-D over the pixels of
    every plane together), ``PSL_dB`` (dB, <= 0) and ``width_x_6dB``, ``width_y_6dB`` (metres).
    """
    ps = plane_set(planes, coords)
    q = check_number("quantile", quantile, lo=0, hi=1)
    rm, rg = region_radii(wavelength, r_main, r_guard)
    want = _parse_terms(terms, planes_ref is not None, c_plane in ps.names)
    need = set(want)
    if "L_SLR" in need:
        need |= {"L_SLR_q", "L_SLR_i"}
    if "Mean" in need:
        need |= {"L_PSF", "L_contrast", "L_SLR_q", "L_SLR_i"}
    if {"width_x_6dB", "width_y_6dB"} & need and c_plane not in ps.names:
        raise ParameterError(f"the main-lobe widths need the C-plane {c_plane!r}; the planes are {list(ps.names)}")
    lead = tuple(ps.lead)
    flat = ps.flat
    b = flat.shape[0]
    out: dict[str, Tensor] = {}
    if "L_PSF" in need:
        ref = _reference(ps, planes_ref, coords)
        out["L_PSF"] = si_mse(flat[:, None, :], ref[:, None, :]).reshape(lead)

    lobe = need & {"L_contrast", "L_SLR_q", "L_SLR_i", "PSL_dB"}
    if lobe:
        # |kappa|^2 of the set up to a detached per-item scale (every ratio below is invariant to
        # the scale of the set, its joint L2 normalisation included, so no gradient is lost)
        k2 = scaled_abs2(flat[:, None, :])                              # (B, N)
        peak = peak_index(k2)
        # the regions of each distinct peak position once: the masks of a batch share a few peaks
        # (the scatterer's point lies on every plane, so its copies count as one)
        uniq, inv = torch.unique(ps.coords[peak], dim=0, return_inverse=True)
        main, side = _region_masks(ps.coords, uniq, rm, rg, k2.dtype)   # (U, N)
        if len(uniq) > 1:       # one (B, N) copy of each mask beats a loop over the groups
            main, side = main[inv], side[inv]
        res = _lobe_terms(k2, peak, main, side, lobe, q)
        out.update({name: v.reshape(lead) for name, v in res.items()})
    if "L_SLR" in need:
        out["L_SLR"] = 0.5 * (out["L_SLR_q"] + out["L_SLR_i"])
    if "Mean" in need:
        out["Mean"] = 0.25 * (out["L_PSF"] + out["L_contrast"] + out["L_SLR_q"] + out["L_SLR_i"])
    if {"width_x_6dB", "width_y_6dB"} & need:
        o = ps.offsets[c_plane]
        h, w = ps.shapes[c_plane]
        widths = main_lobe_widths(flat[:, o:o + h * w].reshape(b, h, w), coords[c_plane], name=c_plane)
        rdt = flat.real.dtype if flat.is_complex() else flat.dtype
        for letter in ("x", "y"):
            out[f"width_{letter}_6dB"] = torch.as_tensor(widths[letter], dtype=rdt, device=flat.device).reshape(lead)
    return {t: out[t] for t in want}
