"""The geometry and band of the two-way beam pattern (:mod:`arraysel.physics.beampattern`): the
pulse-echo spectrum and the frequency nodes, the region of shifts a steered sector sees and each
beam's weights over it (with the element factor), predicted grating lobes, lattices, and the
directions of points seen from the array.
"""
from __future__ import annotations

import math

import numpy as np
import torch

from arraysel.errors import ParameterError, SelectionError, check_choice, check_number
from arraysel.physics.simus import probe_response, pulse_spectrum

__all__ = ["COMBINE", "REGIONS", "pulse_echo_spectrum", "band_nodes", "sector_sines", "steering_coverage",
           "element_factor", "steering_weights", "grating_lobe_directions", "grating_lobe_segments",
           "lattice_periods", "lattice_of", "direction_cosines", "sphere_surface"]

COMBINE = ("energy", "coherent")
REGIONS = ("visible", "sector")
#: the level (relative amplitude) that bounds the band of the coherent combination
COHERENT_BAND_LEVEL = 0.01
#: steering samples of the sector's width when the coverage is integrated over it
_COVERAGE_SAMPLES = 201


# --------------------------------------------------------------------------
# the band
# --------------------------------------------------------------------------

def pulse_echo_spectrum(f, fc: float, bandwidth: float, tx_cycles: float = 1.0) -> torch.Tensor:
    """``S(f) / i``: SIMUS's pulse-echo spectrum (the windowed-sine pulse times the squared one-way
    transducer response, :mod:`arraysel.physics.simus`) divided by ``i``, which makes it real;
    float64, the shape of ``f`` (Hz)."""
    f = torch.as_tensor(f, dtype=torch.float64)
    return pulse_spectrum(f, fc, tx_cycles).imag * probe_response(f, fc, bandwidth) ** 2


def band_nodes(fc: float, bandwidth: float, n: int, combine: str = "energy",
               tx_cycles: float = 1.0) -> tuple[torch.Tensor, torch.Tensor]:
    """The frequencies ``f`` (n,) in Hz and weights ``w`` (n,) of the broadband combination
    (float64, see the module docstring): ``"energy"``: the midpoints of n equal shares of
    ``|S|^2``, ``w = 1/n``; ``"coherent"``: n uniform midpoints of the band where ``|S|`` is at
    least 1 % of its peak, ``w ~ S(f)``, summing to 1."""
    check_number("fc", fc, lo=0, lo_open=True)
    n = check_number("n_freq", n, lo=1, hi=512, integer=True)
    check_choice("combine", combine, COMBINE)
    f = torch.linspace(0.0, 3.0 * fc, 30001, dtype=torch.float64)[1:]
    s = pulse_echo_spectrum(f, fc, bandwidth, tx_cycles)
    if combine == "energy":
        cdf = torch.cumsum(s * s, 0)
        cdf = cdf / cdf[-1]
        q = (torch.arange(n, dtype=torch.float64) + 0.5) / n
        i = torch.searchsorted(cdf, q).clamp(1, f.numel() - 1)
        t = (q - cdf[i - 1]) / (cdf[i] - cdf[i - 1])
        nodes = f[i - 1] + t * (f[i] - f[i - 1])
        return nodes, torch.full((n,), 1.0 / n, dtype=torch.float64)
    inside = torch.nonzero(s.abs() >= COHERENT_BAND_LEVEL * s.abs().max()).flatten()
    lo, hi = float(f[inside[0]]), float(f[inside[-1]])
    nodes = lo + (torch.arange(n, dtype=torch.float64) + 0.5) * (hi - lo) / n
    w = pulse_echo_spectrum(nodes, fc, bandwidth, tx_cycles)
    return nodes, w / w.sum()


# --------------------------------------------------------------------------
# the region of shifts
# --------------------------------------------------------------------------

def sector_sines(sector_deg) -> tuple[float, float]:
    try:
        ax, ay = (float(v) for v in sector_deg)
    except (TypeError, ValueError):
        raise ParameterError(f"sector_deg must be two angles (x, y) in degrees, got {sector_deg!r}") from None
    for name, a in (("sector_deg[0] (x)", ax), ("sector_deg[1] (y)", ay)):
        check_number(name, a, lo=0, hi=89)
    return math.sin(math.radians(ax)), math.sin(math.radians(ay))


def steering_coverage(du, dv, sin_x: float, sin_y: float, region: str = "visible") -> torch.Tensor:
    """The fraction (Hv, Hu) (float64) of the sector's steerings ``s`` (uniform over
    ``[-sin_x, sin_x] x [-sin_y, sin_y]``) for which ``s + (du, dv)`` lies in ``region``
    (``"visible"``: the unit disk; ``"sector"``: the sector itself). A zero half-width means that
    steering is fixed at 0."""
    check_choice("region", region, REGIONS)
    du = torch.as_tensor(du, dtype=torch.float64)
    dv = torch.as_tensor(dv, dtype=torch.float64)
    if region == "sector":
        cu = (1 - du.abs() / (2 * sin_x)).clamp(min=0) if sin_x > 0 else (du == 0).double()
        cv = (1 - dv.abs() / (2 * sin_y)).clamp(min=0) if sin_y > 0 else (dv == 0).double()
        return cv[:, None] * cu[None, :]
    n = _COVERAGE_SAMPLES if sin_x > 0 else 1
    su = (torch.arange(n, dtype=torch.float64) + 0.5) / n * 2 * sin_x - sin_x if sin_x > 0 else torch.zeros(1)
    x = su[None, :] + du[:, None]                                   # (Hu, n)
    r = torch.sqrt((1 - x * x).clamp(min=0))
    ok = (x.abs() <= 1)
    dvv = dv[:, None, None]                                         # (Hv, 1, 1)
    if sin_y > 0:
        hi = torch.minimum(torch.full_like(r, sin_y)[None], -dvv + r[None])
        lo = torch.maximum(torch.full_like(r, -sin_y)[None], -dvv - r[None])
        frac = (hi - lo).clamp(min=0) / (2 * sin_y)
    else:
        frac = (dvv.abs() <= r[None]).double()
    return (frac * ok[None]).mean(-1)


def element_factor(u, v, width: float, height: float, baffle, wavelength: float) -> torch.Tensor:
    """One-way far-field amplitude of a rectangular element (``width`` along x, ``height`` along y,
    metres) towards the directions ``(u, v)``, as SIMUS computes it at one wavelength:
    ``sinc(k width / 2 u) sinc(k height / 2 v) O(cos theta)``, ``O`` the baffle's obliquity (soft
    ``cos theta``, rigid 1, a number ``b``: ``cos theta / (cos theta + b)``); 0 outside the visible
    region. float64, the broadcast shape of u and v."""
    u = torch.as_tensor(u, dtype=torch.float64)
    v = torch.as_tensor(v, dtype=torch.float64)
    k = 2 * math.pi / wavelength
    cos = torch.sqrt((1 - u * u - v * v).clamp(min=0))
    if baffle == "soft":
        obl = cos
    elif baffle == "rigid":
        obl = torch.ones_like(cos)
    else:
        obl = cos / (cos + float(baffle))
    e = torch.sinc(k * width / 2 * u / math.pi) * torch.sinc(k * height / 2 * v / math.pi) * obl
    return torch.where(u * u + v * v <= 1, e, torch.zeros_like(e))


def steering_weights(du, dv, sin_x: float, sin_y: float, region: str, element=None,
                     n_steer: int = 33) -> tuple[torch.Tensor, torch.Tensor]:
    """The mean and the maximum (Hv, Hu), float64, over the sector's steerings ``s`` of
    ``g_s(du, dv) = E(s + d)^4 / E(s)^4`` where ``s + d`` lies in ``region`` (0 elsewhere), ``E``
    the one-way element factor ``element(u, v)`` (a callable; None: 1). A beam steered to ``s``
    sees the pattern times ``g_s``, relative to its own peak: the mean weights the sums over the
    sector's beams, the maximum the worst beam. ``n_steer`` samples an axis (midpoints; one when
    the sector's half-width is 0). Without an element factor the mean is
    :func:`steering_coverage` (exact) and the maximum 1 where it is positive."""
    check_choice("region", region, REGIONS)
    du = torch.as_tensor(du, dtype=torch.float64)
    dv = torch.as_tensor(dv, dtype=torch.float64)
    if element is None:
        cov = steering_coverage(du, dv, sin_x, sin_y, region)
        return cov, (cov > 0).double()
    n = check_number("n_steer", n_steer, lo=1, hi=1025, integer=True)
    axes = [((torch.arange(n, dtype=torch.float64) + 0.5) / n * 2 - 1) * h if h > 0 else torch.zeros(1)
            for h in (sin_x, sin_y)]
    su, sv = (a.reshape(-1) for a in torch.meshgrid(axes[0], axes[1], indexing="ij"))
    total = torch.zeros(dv.numel(), du.numel(), dtype=torch.float64)
    top = torch.zeros_like(total)
    for i in range(0, su.numel(), 64):
        a, b = su[i:i + 64, None, None], sv[i:i + 64, None, None]
        u, v = a + du[None, None, :], b + dv[None, :, None]
        inside = (u * u + v * v <= 1) if region == "visible" else ((u.abs() <= sin_x) & (v.abs() <= sin_y))
        g = (element(u, v) / element(a, b)) ** 4 * inside
        total += g.sum(0)
        top = torch.maximum(top, g.amax(0))
    return total / su.numel(), top


def grating_lobe_directions(pitch_x: float, pitch_y: float, wavelengths, *, steer=(0.0, 0.0),
                            bounds=None) -> torch.Tensor:
    """Where a lattice of pitches ``(pitch_x, pitch_y)`` (metres; ``inf``: no lattice along that
    axis) puts its grating lobes when steered to ``steer = (u0, v0)``: the directions
    ``(u0 + m lambda / pitch_x, v0 + n lambda / pitch_y)`` for every order ``(m, n) != (0, 0)``
    and every wavelength of ``wavelengths`` (metres), float64 (G, 2). ``bounds = (u_lo, u_hi,
    v_lo, v_hi)`` keeps those inside (default ``u0 +- 2``, ``v0 +- 2``); G may be 0."""
    lam = np.atleast_1d(np.asarray(wavelengths, dtype=np.float64)).reshape(-1)
    if lam.size == 0 or not np.all(np.isfinite(lam)) or np.any(lam <= 0):
        raise ParameterError(f"wavelengths must be positive and finite (metres), got {wavelengths!r}")
    px = check_number("pitch_x", pitch_x, lo=0, lo_open=True)
    py = check_number("pitch_y", pitch_y, lo=0, lo_open=True)
    u0, v0 = (float(s) for s in steer)
    b = (u0 - 2, u0 + 2, v0 - 2, v0 + 2) if bounds is None else tuple(float(v) for v in bounds)
    span = max(abs(b[0] - u0), abs(b[1] - u0), abs(b[2] - v0), abs(b[3] - v0))
    out = []
    for w in lam:
        mx = 0 if math.isinf(px) else int(math.floor(span * px / w))
        my = 0 if math.isinf(py) else int(math.floor(span * py / w))
        for m in range(-mx, mx + 1):
            for n in range(-my, my + 1):
                if m == 0 and n == 0:
                    continue
                u = u0 + (0.0 if m == 0 else m * w / px)
                v = v0 + (0.0 if n == 0 else n * w / py)
                if b[0] <= u <= b[1] and b[2] <= v <= b[3]:
                    out.append((u, v))
    return torch.tensor(out, dtype=torch.float64).reshape(-1, 2)


def grating_lobe_segments(pitch_x: float, pitch_y: float, band, *, steer=(0.0, 0.0), bounds=None) -> torch.Tensor:
    """The grating lobes of a lattice over a band of wavelengths ``band = (lambda_lo, lambda_hi)``
    (metres): for each order ``(m, n) != (0, 0)``, the segment (2, 2) from its direction at
    ``lambda_lo`` to its direction at ``lambda_hi`` (:func:`grating_lobe_directions`), float64
    (G, 2, 2); the orders whose segment reaches into ``bounds`` (default ``u0 +- 2``, ``v0 +- 2``)."""
    lo, hi = (float(v) for v in band)
    if not (0 < lo <= hi < math.inf):
        raise ParameterError(f"band must be (lambda_lo, lambda_hi) with 0 < lambda_lo <= lambda_hi, got {band!r}")
    u0, v0 = (float(s) for s in steer)
    b = (u0 - 2, u0 + 2, v0 - 2, v0 + 2) if bounds is None else tuple(float(v) for v in bounds)
    span = max(abs(b[0] - u0), abs(b[1] - u0), abs(b[2] - v0), abs(b[3] - v0))
    near = grating_lobe_directions(pitch_x, pitch_y, [lo], steer=steer,
                                   bounds=(u0 - span, u0 + span, v0 - span, v0 + span))
    out = []
    for u, v in near.tolist():
        end = (u0 + (u - u0) * hi / lo, v0 + (v - v0) * hi / lo)
        if min(u, end[0]) <= b[1] and max(u, end[0]) >= b[0] and min(v, end[1]) <= b[3] and max(v, end[1]) >= b[2]:
            out.append(((u, v), end))
    return torch.tensor(out, dtype=torch.float64).reshape(-1, 2, 2)


def lattice_periods(weights, nx: int, ny: int) -> torch.Tensor:
    """The periods ``(mx, my)`` (B, 2) int64, in elements, of the coarsest rectangular lattice that
    holds every element of non-zero weight (element ``iy * nx + ix``): ``mx`` is the greatest
    common divisor of the differences of their ``ix``; 0 when they all share one column (row).
    Periodic thinning by 2 gives 2; a random or spiral selection almost always 1."""
    w = weights.detach() if isinstance(weights, torch.Tensor) else torch.as_tensor(np.asarray(weights))
    w = w.reshape(-1, w.shape[-1]) if w.dim() > 1 else w[None]
    if w.shape[-1] != nx * ny:
        raise SelectionError(f"weights must have {nx * ny} entries (nx * ny), got {w.shape[-1]}")
    active = (w != 0).cpu()
    e = torch.arange(nx * ny)
    cols = []
    for idx in (e % nx, e // nx):
        big = torch.iinfo(torch.int64).max
        low = torch.where(active, idx[None], torch.full_like(idx[None], big)).amin(1, keepdim=True)
        d = torch.where(active, idx[None] - low, torch.zeros_like(idx[None]))   # gcd(x, 0) = x
        while d.shape[1] > 1:                                                   # a tree of gcds
            if d.shape[1] % 2:
                d = torch.cat([d, torch.zeros_like(d[:, :1])], 1)
            d = torch.gcd(d[:, 0::2], d[:, 1::2])
        cols.append(d[:, 0])
    return torch.stack(cols, 1)


# --------------------------------------------------------------------------
# directions of pixels
# --------------------------------------------------------------------------

def direction_cosines(coords, origin=(0.0, 0.0, 0.0)) -> torch.Tensor:
    """The direction ``(u, v) = ((x - x0) / r, (y - y0) / r)`` of points ``coords`` (..., 3)
    (metres) seen from ``origin`` (the array centre), ``r`` their distance; float64 (..., 2).
    ``u = sin theta_x`` for a direction in the xz-plane (``theta_x`` from the z axis towards x)."""
    c = torch.as_tensor(np.asarray(coords.detach().cpu() if isinstance(coords, torch.Tensor) else coords,
                                   dtype=np.float64))
    if c.shape[-1] != 3:
        raise ParameterError(f"coords must have shape (..., 3) (x, y, z in metres), got {tuple(c.shape)}")
    d = c - torch.as_tensor([float(v) for v in origin], dtype=torch.float64)
    r = d.norm(dim=-1, keepdim=True)
    if bool((r == 0).any()) or not bool(torch.isfinite(r).all()):
        raise ParameterError("coords: a point coincides with the origin or is not finite; its direction is undefined")
    return d[..., :2] / r


def sphere_surface(radius: float, u, v, origin=(0.0, 0.0, 0.0)) -> torch.Tensor:
    """Points (Hv, Hu, 3) (float64, metres) at distance ``radius`` from ``origin`` in the directions
    of the grid ``u`` (Hu,) x ``v`` (Hv,) (direction cosines, ``u^2 + v^2 <= 1``; z >= 0): a surface
    sampled in angle, rows along v, columns along u."""
    r = check_number("radius", radius, lo=0, lo_open=True)
    u = torch.as_tensor(np.asarray(u, dtype=np.float64)).reshape(-1)
    v = torch.as_tensor(np.asarray(v, dtype=np.float64)).reshape(-1)
    V, U = torch.meshgrid(v, u, indexing="ij")
    w2 = 1 - U * U - V * V
    if bool((w2 < -1e-12).any()):
        raise ParameterError("u, v: every direction needs u^2 + v^2 <= 1 (the visible region)")
    W = torch.sqrt(w2.clamp(min=0))
    o = [float(x) for x in origin]
    return torch.stack([o[0] + r * U, o[1] + r * V, o[2] + r * W], dim=-1)


# --------------------------------------------------------------------------
# the pattern
# --------------------------------------------------------------------------

def lattice_of(positions, rtol: float = 1e-6):
    """``(nx, ny, pitch_x, pitch_y, centre, index)`` when the planar positions (Ne, 2 or 3) lie on
    a rectangular lattice of at most ``max(64, 16 Ne)`` nodes (``index`` (Ne,) the node
    ``iy * nx + ix`` of each element; nodes may be empty; the pitch along an axis is the largest
    step, the smallest gap between coordinates divided by 1..8, that every coordinate is a multiple
    of), else None."""
    p = np.asarray(positions, dtype=np.float64)[:, :2]
    axes = []
    for col in (0, 1):
        x = np.unique(p[:, col])
        span = x[-1] - x[0]
        if x.size == 1:
            axes.append((1, math.inf, x[0], np.zeros(len(p), dtype=np.int64)))
            continue
        for k in range(1, 9):
            step = np.diff(x).min() / k
            idx = np.rint((p[:, col] - x[0]) / step)
            if np.abs(x[0] + idx * step - p[:, col]).max() <= rtol * span:
                break
        else:
            return None
        axes.append((int(idx.max()) + 1, float(step), x[0] + span / 2, idx.astype(np.int64)))
    (nx, px, cx, ix), (ny, py, cy, iy) = axes
    index = iy * nx + ix
    if np.unique(index).size != index.size or nx * ny > max(64, 16 * len(p)):
        return None
    return nx, ny, px, py, (cx, cy), index
