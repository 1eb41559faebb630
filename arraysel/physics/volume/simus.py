"""SIMUS3/PFIELD3 in PyTorch: echoes of point scatterers for a matrix probe (3-D acoustics).

The 2-D model of :mod:`arraysel.physics.simus` (pulse spectrum, transducer response, frequency
grid, RF synthesis) with 3-D radiation. Each rectangular element (``width`` along x, ``height``
along y) is split into ``M x N`` sub-elements (``M = ceil(width / lambda_min)``,
``N = ceil(height / lambda_min)``, lambda_min the wavelength at the upper -6 dB band edge, or
``SimOptions.element_splitting`` in both directions); a sub-element of size ``(a, b)`` radiates
towards a point at ``d = p - s`` (distance ``r = |d|``) as the Fraunhofer field

    exp(i k r - alpha(f) r) / r * sinc(k_c a/2 * d_x/r) * sinc(k_c b/2 * d_y/r) * O(d_z/r)

(spherical spreading ``1/r``; the directivity at the centre frequency, or at every frequency
with ``full_frequency_directivity``; the obliquity ``O`` of the baffle as in 2-D with
``cos theta = d_z / r``; r clamped below at half a wavelength at fc); the element's response
``R_e(f)`` is the mean over its sub-elements. Scatterers behind the array (z < 0) receive
nothing. As in 2-D, the field at a scatterer is ``T(f) = P(f) H(f) sum_j a_j R_j(f) e^{i w tau_j}``
and element ``e`` receives ``S_e(f) = H(f) sum_s RC_s T_s(f) R_{s,e}(f)`` times its receive
weight (unlike 2-D, no ``df * width`` factor: SIMUS3's RF amplitude). Differentiable with
respect to the TX and RX weights.
"""
from __future__ import annotations

import math

import numpy as np
import torch

from arraysel.errors import ParameterError
from arraysel.physics.probes import Acquisition, MatrixProbe, PlanarProbe
from arraysel.physics.simus import (NEPER_PER_DB, FrequencyGrid, SimOptions, _as_tensor, frequency_grid,
                                    probe_response, pulse_spectrum, sinc, spectra_to_rf)

__all__ = ["n_subelements3", "element_responses3", "grid_for_points3", "rx_spectra3", "simulate_rf3"]

_EPS32 = float(np.finfo(np.float32).eps)


def n_subelements3(probe: MatrixProbe, c: float, options: SimOptions = SimOptions()) -> tuple[int, int]:
    """Sub-elements ``(M, N)`` along x and y of each element."""
    if options.element_splitting is not None:
        return int(options.element_splitting), int(options.element_splitting)
    lambda_min = c / (probe.fc * (1 + probe.bandwidth / 200))
    return (max(1, int(math.ceil(probe.width / lambda_min - 1e-12))),
            max(1, int(math.ceil(probe.height / lambda_min - 1e-12))))


def _points(points, dtype, device) -> torch.Tensor:
    p = _as_tensor(points, dtype, device)
    if p.dim() == 1:
        p = p[None]
    if p.dim() != 2 or p.shape[-1] != 3:
        raise ParameterError(f"points must have shape (P, 3) (x, y, z in metres), got {tuple(p.shape)}")
    if not bool(torch.isfinite(p).all()):
        raise ParameterError("points must be finite")
    return p


def element_responses3(points, f: torch.Tensor, probe: MatrixProbe, c: float, attenuation: float = 0.0,
                       options: SimOptions = SimOptions()) -> torch.Tensor:
    """One-way radiation ``R_e(f)`` between every element and every point.

    points: (P, 3) metres (float64 recommended); f: (F,) Hz. Returns (P, Ne, F) complex (of the
    points' dtype). Points with z < 0 radiate nothing.
    """
    pts = _points(points, points.dtype if isinstance(points, torch.Tensor) else torch.float64,
                  points.device if isinstance(points, torch.Tensor) else None)
    dtype, device = pts.dtype, pts.device
    pos = torch.as_tensor(probe.element_positions(), dtype=dtype, device=device)
    M, N = n_subelements3(probe, c, options)
    a, b = probe.width / M, probe.height / N
    sx = -probe.width / 2 + a / 2 + a * torch.arange(M, dtype=dtype, device=device)
    sy = -probe.height / 2 + b / 2 + b * torch.arange(N, dtype=dtype, device=device)
    f = f.to(device=device, dtype=dtype)
    k = 2 * math.pi * f / c
    kc = 2 * math.pi * probe.fc / c
    alpha = attenuation * NEPER_PER_DB * (f / 1e6) * 1e2  # Np/m
    cdt = torch.complex128 if dtype == torch.float64 else torch.complex64
    out = torch.zeros(pts.shape[0], pos.shape[0], f.numel(), dtype=cdt, device=device)
    dz = pts[:, 2, None]  # (P, 1)
    for i in range(M):
        dx = pts[:, 0, None] - (pos[None, :, 0] + sx[i])  # (P, Ne)
        for j in range(N):
            dy = pts[:, 1, None] - (pos[None, :, 1] + sy[j])
            d = torch.sqrt(dx * dx + dy * dy + dz * dz)
            r = torch.clamp(d, min=c / probe.fc / 2)  # the model is not meant for the near field
            cos_t = (dz + _EPS32) / (d + _EPS32)
            if probe.baffle == "soft":
                obliquity = cos_t
            elif probe.baffle == "rigid":
                obliquity = torch.ones_like(cos_t)
            else:
                obliquity = cos_t / (cos_t + float(probe.baffle))
            obliquity = torch.where(cos_t <= 0, torch.full_like(cos_t, _EPS32), obliquity)
            ux = (dx + _EPS32) / (d + _EPS32)
            uy = (dy + _EPS32) / (d + _EPS32)
            if options.full_frequency_directivity:
                direc = sinc(k * a / 2 * ux[..., None]) * sinc(k * b / 2 * uy[..., None])
                amp = (obliquity / r)[..., None] * direc
            else:
                amp = (obliquity / r * sinc(kc * a / 2 * ux) * sinc(kc * b / 2 * uy))[..., None]
            mag = amp * torch.exp(-r[..., None] * alpha)
            out = out + torch.polar(mag, r[..., None] * k)
    out = out / (M * N)
    behind = pts[:, 2] < 0
    if bool(behind.any()):
        out = out * (~behind).to(dtype)[:, None, None]
    return out


def grid_for_points3(points, delays, probe: MatrixProbe, acq: Acquisition,
                     options: SimOptions = SimOptions()) -> FrequencyGrid:
    """The frequency grid SIMUS3 uses for scatterers at ``points`` (P, 3) and TX ``delays`` (Ne,)."""
    pts = np.asarray(points.detach().cpu() if isinstance(points, torch.Tensor) else points,
                     dtype=np.float64).reshape(-1, 3)
    pos = probe.element_positions()
    dmax = float(np.sqrt(np.max(np.sum((pts[:, None, :] - pos[None]) ** 2, axis=-1))))
    dl = delays.detach().cpu().numpy() if isinstance(delays, torch.Tensor) else np.asarray(delays, dtype=np.float64)
    return frequency_grid(probe.fc, acq.fs, probe.bandwidth, acq.tx_cycles, acq.c, dmax,
                          float(np.nanmax(dl)) if dl.size else 0.0, options)


def rx_spectra3(resp: torch.Tensor, rc: torch.Tensor, f: torch.Tensor, delays: torch.Tensor,
                tx_apod: torch.Tensor, rx_apod: torch.Tensor, probe: MatrixProbe,
                tx_cycles: float) -> torch.Tensor:
    """Spectra received by the elements: resp (P, Ne, F), rc (P,), delays (Ne,) s, tx_apod and
    rx_apod (..., Ne). Returns (..., Ne, F) complex."""
    rdt = resp.real.dtype
    cdt = resp.dtype
    w = 2 * math.pi * f.to(rdt)
    steer = torch.polar(torch.ones_like(delays[:, None] * w), delays[:, None] * w)  # (Ne, F)
    tx = torch.einsum("...j,pjf->...pf", tx_apod.to(cdt), resp * steer[None])
    H = probe_response(f, probe.fc, probe.bandwidth).to(rdt)
    P = pulse_spectrum(f, probe.fc, tx_cycles).to(cdt)
    tx = tx * (P * H)
    rx = torch.einsum("...pf,p,pef->...ef", tx, rc.to(cdt), resp)
    rx = rx * H
    return rx * rx_apod.to(cdt)[..., None]


def simulate_rf3(points, rc, delays, probe: MatrixProbe, acq: Acquisition, tx_apod=None, rx_apod=None,
                 options: SimOptions = SimOptions(), dtype=torch.float64, device=None):
    """RF signals of point scatterers for one transmit of a matrix probe (SIMUS3).

    points: (P, 3) m; rc: (P,) reflection coefficients; delays: (Ne,) s (finite);
    tx_apod, rx_apod: (..., Ne) weights (default ones), differentiable.
    Returns ``(rf, grid)``: rf (..., n_time, Ne) sampled at ``acq.fs`` (time first, like MUST).
    """
    if not isinstance(probe, (MatrixProbe, PlanarProbe)):
        raise ParameterError(f"probe must be a MatrixProbe or a PlanarProbe, got {type(probe).__name__}")
    pts = _points(points, dtype, device)
    rc = _as_tensor(rc, dtype, device).reshape(-1)
    if rc.numel() != pts.shape[0]:
        raise ParameterError(f"rc must have one value per point ({pts.shape[0]}), got {rc.numel()}")
    delays = _as_tensor(delays, dtype, device).reshape(-1)
    ne = probe.n_elements
    if delays.numel() != ne:
        raise ParameterError(f"delays must have {ne} entries (one per element), got {delays.numel()}")
    if not bool(torch.isfinite(delays).all()):
        raise ParameterError("delays must be finite: an inactive element has zero tx_apod, not a NaN delay")
    tx_apod = torch.ones(ne, dtype=dtype, device=device) if tx_apod is None else _as_tensor(tx_apod, dtype, device)
    rx_apod = torch.ones(ne, dtype=dtype, device=device) if rx_apod is None else _as_tensor(rx_apod, dtype, device)
    grid = grid_for_points3(pts, delays, probe, acq, options)
    f = grid.f.to(device)
    resp = element_responses3(pts, f, probe, acq.c, acq.attenuation, options)
    spectra = rx_spectra3(resp, rc, f, delays, tx_apod, rx_apod, probe, acq.tx_cycles)
    return spectra_to_rf(spectra, grid).transpose(-1, -2), grid
