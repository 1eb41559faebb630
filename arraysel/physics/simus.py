"""SIMUS/PFIELD in PyTorch: RF echoes of point scatterers for a uniform array (2-D).

Written from the published SIMUS model (Garcia, "SIMUS: an open-source
simulator for medical ultrasound imaging. Part I: theory & examples",
Comput. Methods Programs Biomed. 2022) and its 2-D predecessor (Shahriari &
Garcia, Phys. Med. Biol. 2018).  The model works in the frequency domain:

* the transmitted pulse is a windowed sine of ``tx_cycles`` cycles whose
  spectrum is ``P(w) = i [sinc(T(w - wc)/2) - sinc(T(w + wc)/2)]`` with
  ``T = tx_cycles / fc`` and ``sinc(x) = sin(x)/x``;
* the transducer's one-way response is the square root of a generalized
  normal window whose -6 dB pulse-echo width is the probe's bandwidth,
  ``H(w)^2 = exp(-(|w - wc| / (wB / 2 / ln(2)^(1/p)))^p)``,
  ``p = ln(126) / ln(2 wc / wB)``, ``wB = bandwidth * wc``;
* each element is split into ``M`` sub-elements whose far-field (Fraunhofer)
  radiation towards a point at distance ``r`` and angle ``theta`` is
  ``exp(i k r - alpha(f) r) / sqrt(r) * D(theta) * O(theta)`` in 2-D, with the
  directivity ``D = sinc(k_c (w/M)/2 sin theta)`` (at the centre frequency,
  or at each frequency with ``full_frequency_directivity``) and the baffle's
  obliquity factor ``O`` (soft: ``cos theta``; rigid: 1; a scalar ``b``:
  ``cos theta / (cos theta + b)``); the element's response ``R_e(f)`` is the
  mean over its sub-elements;
* the field at a scatterer for TX apodization ``a`` and delays ``tau`` is
  ``T(f) = P(f) H(f) sum_j a_j R_j(f) exp(i w tau_j)`` and the spectrum
  received by element ``e`` is ``S_e(f) = H(f) sum_s RC_s T_s(f) R_{s,e}(f)``
  times ``df * width`` (the 2-D correction factor);
* frequencies are sampled on ``[0, 2 fc]`` with a step small enough to avoid
  time aliasing of the longest echo, and only the band where ``|P H|`` is
  above ``db_thresh`` (dB) is kept;
* RF signals are the inverse real FFT of the conjugated spectra, sampled at
  ``fs``.

Conventions (the same everywhere in arraysel): SI units; ``x`` along the
array (x = 0 at its centre, from the first to the last element), ``z`` the
depth (positive into the medium, z = 0 at the array, or at the chord of a
convex array); delays in seconds, the earliest element fires at 0.

All functions take torch tensors or numbers and are differentiable with
respect to the apodizations (TX and RX element weights).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from arraysel.errors import ParameterError, check_number

NEPER_PER_DB = 1.0 / 8.69  # the conversion MUST uses (20 / ln 10 = 8.686)


@dataclass(frozen=True)
class SimOptions:
    """Accuracy settings of the simulator.

    db_thresh: frequency components whose pulse-echo amplitude is below this
        level (dB, < 0) relative to its maximum are skipped (SIMUS: -100 dB).
    element_splitting: sub-elements per element (None: ``ceil(width / lambda_min)``,
        lambda_min the wavelength at the upper -6 dB band edge).
    full_frequency_directivity: evaluate the sub-element directivity at every
        frequency instead of the centre frequency only.
    frequency_step: scale factor of the automatic frequency step (> 1 risks
        time aliasing).
    """

    db_thresh: float = -100.0
    element_splitting: int | None = None
    full_frequency_directivity: bool = False
    frequency_step: float = 1.0

    def __post_init__(self):
        check_number("db_thresh", self.db_thresh, hi=0.0, hi_open=True)
        if self.element_splitting is not None:
            check_number("element_splitting", self.element_splitting, lo=1, hi=1000, integer=True)
        check_number("frequency_step", self.frequency_step, lo=0.0, lo_open=True, hi=10.0)


def _as_tensor(x, dtype=torch.float64, device=None) -> torch.Tensor:
    if isinstance(x, torch.Tensor):
        return x.to(dtype=dtype, device=device)
    return torch.as_tensor(np.asarray(x), dtype=dtype, device=device)


def sinc(x: torch.Tensor) -> torch.Tensor:
    """Unnormalised sinc, ``sin(x)/x``, equal to 1 at 0 with a finite gradient there."""
    small = x.abs() < 1e-8
    safe = torch.where(small, torch.ones_like(x), x)
    return torch.where(small, torch.ones_like(x) - x * x / 6, torch.sin(safe) / safe)


def pulse_spectrum(f: torch.Tensor, fc: float, tx_cycles: float = 1.0) -> torch.Tensor:
    """Spectrum of a windowed sine of ``tx_cycles`` cycles at ``fc`` (complex, same shape as f)."""
    w = 2 * math.pi * f
    wc = 2 * math.pi * fc
    T = tx_cycles / fc
    val = sinc(T * (w - wc) / 2) - sinc(T * (w + wc) / 2)
    return torch.complex(torch.zeros_like(val), val)


def probe_response(f: torch.Tensor, fc: float, bandwidth: float) -> torch.Tensor:
    """One-way amplitude response of the transducer (real, >= 0).

    Its square (the pulse-echo response) is a generalized normal window whose
    -6 dB width is ``bandwidth`` percent of ``fc``.
    """
    wc = 2 * math.pi * fc
    wB = bandwidth / 100.0 * wc
    p = math.log(126.0) / math.log(2 * wc / wB)
    scale = wB / 2 / math.log(2.0) ** (1 / p)
    w = 2 * math.pi * f
    return torch.exp(-0.5 * (torch.abs(w - wc) / scale) ** p)


def pulse_echo_duration(fc: float, bandwidth: float, tx_cycles: float = 1.0, dt: float = 1e-9) -> float:
    """Duration (s) of the two-way pulse ``P(f) H(f)^2``, measured where it exceeds 1/1023 of its peak.

    Used to size the time window (and so the frequency step) of a simulation.
    """
    df = fc / tx_cycles / 32
    n = 2 ** int(math.ceil(math.log2(1 / dt / 2 / df)))
    f = torch.linspace(0, 1 / dt / 2, n, dtype=torch.float64)
    spec = pulse_spectrum(f, fc, tx_cycles) * probe_response(f, fc, bandwidth) ** 2
    pulse = torch.fft.fftshift(torch.fft.irfft(spec))
    pulse = pulse / pulse.abs().max()
    above = torch.nonzero(pulse > 1 / 1023).flatten()
    first, last = int(above[0]), int(above[-1])
    half = min(first + 1, pulse.numel() - last - 1)  # symmetric support around the centre
    return (pulse.numel() - 2 * half + 1) * dt


@dataclass(frozen=True)
class FrequencyGrid:
    """Frequency samples of a simulation.

    ``f`` holds the kept samples (Hz); they are samples ``start .. start+len(f)-1``
    of ``linspace(0, 2 fc, n_full)``; RF signals have ``n_time`` samples at ``fs``
    obtained from an inverse real FFT of length ``n_fft``.
    """

    f: torch.Tensor
    start: int
    n_full: int
    df: float
    n_fft: int
    n_time: int

    @property
    def fs(self) -> float:
        return self.n_fft * self.df


def frequency_grid(fc: float, fs: float, bandwidth: float, tx_cycles: float, c: float,
                   max_distance: float, max_delay: float, options: SimOptions = SimOptions()) -> FrequencyGrid:
    """Frequency sampling that avoids time aliasing of echoes up to ``max_distance`` (m, one way).

    ``max_delay`` is the largest TX (or RX) delay in seconds.
    """
    if fs < 4 * fc * (1 - 1e-9):
        raise ParameterError(f"fs = {fs:g} Hz is too low for the simulator; allowed: fs >= 4 fc = {4 * fc:g} Hz")
    dmax = max_distance + pulse_echo_duration(fc, bandwidth, tx_cycles) * c
    df = 1.0 / 2.0 / (2 * dmax / c + max_delay) * options.frequency_step
    n_full = 2 * int(math.ceil(fc / df)) + 1
    f_all = torch.linspace(0, 2 * fc, n_full, dtype=torch.float64)
    df = float(f_all[1])
    gain = (pulse_spectrum(f_all, fc, tx_cycles) * probe_response(f_all, fc, bandwidth)).abs()
    gain_db = 20 * torch.log10(1e-200 + gain / gain.max())
    keep = torch.nonzero(gain_db > options.db_thresh).flatten()
    start, stop = int(keep[0]), int(keep[-1]) + 1
    n_fft = int(math.ceil(fs / 2 / fc * (n_full - 1)))
    return FrequencyGrid(f=f_all[start:stop], start=start, n_full=n_full, df=df, n_fft=n_fft,
                         n_time=(n_fft + 1) // 2)


def n_subelements(width: float, fc: float, bandwidth: float, c: float, options: SimOptions) -> int:
    if options.element_splitting is not None:
        return int(options.element_splitting)
    lambda_min = c / (fc * (1 + bandwidth / 200))
    return max(1, int(math.ceil(width / lambda_min - 1e-12)))


def element_responses(x: torch.Tensor, z: torch.Tensor, f: torch.Tensor, probe, c: float,
                      attenuation: float = 0.0, options: SimOptions = SimOptions()) -> torch.Tensor:
    """One-way radiation ``R_e(f)`` between every element and every point.

    Parameters
    ----------
    x, z : (P,) point coordinates (m), float64 recommended.
    f : (F,) frequencies (Hz).
    probe : :class:`arraysel.physics.probes.Probe`.
    c : speed of sound (m/s); attenuation in dB/cm/MHz (linear in frequency).

    Returns
    -------
    (P, Ne, F) complex tensor (complex128 for float64 inputs). Points above the
    array (z < 0, or inside a convex array's arc) radiate nothing.
    """
    dtype = x.dtype
    device = x.device
    xe, ze, the, h = probe.element_positions()
    xe = _as_tensor(xe, dtype, device)
    ze = _as_tensor(ze, dtype, device)
    the = _as_tensor(the, dtype, device)
    fc = probe.fc
    M = n_subelements(probe.width, fc, probe.bandwidth, c, options)
    seg = probe.width / M
    s = -probe.width / 2 + seg / 2 + seg * torch.arange(M, dtype=dtype, device=device)  # (M,)
    # sub-element centres (Ne, M), tangent to the array
    xi = xe[:, None] + s[None, :] * torch.cos(the)[:, None]
    zi = ze[:, None] - s[None, :] * torch.sin(the)[:, None]
    dx = x[:, None, None] - xi[None]  # (P, Ne, M)
    dz = z[:, None, None] - zi[None]
    d = torch.sqrt(dx * dx + dz * dz)
    r = torch.clamp(d, min=c / fc / 2)  # the model is not meant for the near field
    eps32 = float(np.finfo(np.float32).eps)
    theta = torch.asin(torch.clamp((dx + eps32) / (d + eps32), -1.0, 1.0)) - the[None, :, None]
    if probe.baffle == "soft":
        obliquity = torch.cos(theta)
    elif probe.baffle == "rigid":
        obliquity = torch.ones_like(theta)
    else:
        obliquity = torch.cos(theta) / (torch.cos(theta) + float(probe.baffle))
    obliquity = torch.where(theta.abs() >= math.pi / 2, torch.full_like(theta, eps32), obliquity)
    amp = obliquity / torch.sqrt(r)
    sin_t = torch.sin(theta)
    k = 2 * math.pi * f.to(dtype) / c  # (F,)
    alpha = attenuation * NEPER_PER_DB * (f.to(dtype) / 1e6) * 1e2  # Np/m
    phase = r[..., None] * k  # (P, Ne, M, F)
    decay = -r[..., None] * alpha
    if options.full_frequency_directivity:
        directivity = sinc(k * seg / 2 * sin_t[..., None])
    else:
        kc = 2 * math.pi * fc / c
        directivity = sinc(kc * seg / 2 * sin_t)[..., None]
    mag = (amp[..., None] * directivity) * torch.exp(decay)
    resp = torch.polar(torch.ones_like(phase), phase) * mag
    resp = resp.mean(dim=2)  # average over sub-elements
    outside = z < 0
    if math.isfinite(probe.radius):
        outside = outside | (x ** 2 + (z + h) ** 2 <= probe.radius ** 2)
    if bool(outside.any()):
        resp = resp * (~outside).to(dtype)[:, None, None]
    return resp


def rx_spectra(resp: torch.Tensor, rc: torch.Tensor, f: torch.Tensor, delays: torch.Tensor,
               tx_apod: torch.Tensor, rx_apod: torch.Tensor, probe, tx_cycles: float,
               df: float) -> torch.Tensor:
    """Spectra received by the elements.

    resp : (P, Ne, F) element responses; rc : (P,) reflection coefficients;
    delays : (Ne,) TX delays (s); tx_apod, rx_apod : (..., Ne) real weights.
    Returns (..., Ne, F) complex, scaled by ``df * width``.
    """
    w = 2 * math.pi * f.to(resp.real.dtype)
    steer = torch.polar(torch.ones_like(delays[:, None] * w), delays[:, None] * w)  # (Ne, F)
    cdt = resp.dtype
    tx = torch.einsum("...j,pjf->...pf", tx_apod.to(cdt), resp * steer[None])  # (..., P, F)
    H = probe_response(f, probe.fc, probe.bandwidth).to(resp.real.dtype)
    P = pulse_spectrum(f, probe.fc, tx_cycles).to(cdt)
    tx = tx * (P * H)
    rx = torch.einsum("...pf,p,pef->...ef", tx, rc.to(cdt), resp)  # (..., Ne, F)
    rx = rx * (H * (df * probe.width))
    return rx * rx_apod.to(cdt)[..., None]


def spectra_to_rf(spectra: torch.Tensor, grid: FrequencyGrid) -> torch.Tensor:
    """RF signals (..., Ne, n_time) from spectra (..., Ne, F) on ``grid``."""
    n_bins = grid.n_fft // 2 + 1
    lead = spectra.shape[:-1]
    full = spectra.new_zeros(lead + (max(n_bins, grid.start + spectra.shape[-1]),))
    full[..., grid.start:grid.start + spectra.shape[-1]] = spectra.conj()
    rf = torch.fft.irfft(full[..., :n_bins], n=grid.n_fft, dim=-1)
    return rf[..., :grid.n_time]


def spectra_to_rf_maps(grid: FrequencyGrid) -> tuple[torch.Tensor, torch.Tensor]:
    """Real matrices ``(A, B)``, each (F, n_time) float64, of the linear map :func:`spectra_to_rf`:
    ``spectra_to_rf(S, grid) == S.real @ A + S.imag @ B`` for spectra ``S`` (..., F) on ``grid``.

    Built by applying :func:`spectra_to_rf` itself to unit spectra, so both forms agree exactly.
    """
    eye = torch.eye(int(grid.f.numel()), dtype=torch.complex128)
    return spectra_to_rf(eye, grid), spectra_to_rf(1j * eye, grid)


def simulate_rf(x, z, rc, delays, probe, acq, tx_apod=None, rx_apod=None,
                options: SimOptions = SimOptions(), dtype=torch.float64, device=None):
    """RF signals of a medium of point scatterers for one transmit (SIMUS, 2-D).

    Parameters
    ----------
    x, z, rc : (P,) scatterer positions (m) and reflection coefficients.
    delays : (Ne,) TX delays (s).
    probe, acq : :class:`~arraysel.physics.probes.Probe`, :class:`~arraysel.physics.probes.Acquisition`.
    tx_apod, rx_apod : (..., Ne) weights (default ones); differentiable.

    Returns
    -------
    rf : (..., n_time, Ne) real tensor sampled at ``acq.fs`` (time first, like MUST).
    grid : the :class:`FrequencyGrid` used.
    """
    x = _as_tensor(x, dtype, device).reshape(-1)
    z = _as_tensor(z, dtype, device).reshape(-1)
    rc = _as_tensor(rc, dtype, device).reshape(-1)
    delays = _as_tensor(delays, dtype, device).reshape(-1)
    ne = probe.n_elements
    if delays.numel() != ne:
        raise ParameterError(f"delays must have {ne} entries (one per element), got {delays.numel()}")
    tx_apod = torch.ones(ne, dtype=dtype, device=device) if tx_apod is None else _as_tensor(tx_apod, dtype, device)
    rx_apod = torch.ones(ne, dtype=dtype, device=device) if rx_apod is None else _as_tensor(rx_apod, dtype, device)
    grid = grid_for_points(x, z, delays, probe, acq, options)
    resp = element_responses(x, z, grid.f.to(device), probe, acq.c, acq.attenuation, options)
    spectra = rx_spectra(resp, rc, grid.f.to(device), delays, tx_apod, rx_apod, probe, acq.tx_cycles, grid.df)
    rf = spectra_to_rf(spectra, grid)
    return rf.transpose(-1, -2), grid


def grid_for_points(x, z, delays, probe, acq, options: SimOptions = SimOptions()) -> FrequencyGrid:
    """The frequency grid SIMUS uses for scatterers at (x, z) and TX ``delays``."""
    xe, ze, _, _ = probe.element_positions()
    xn = np.asarray(x.detach().cpu() if isinstance(x, torch.Tensor) else x, dtype=np.float64).reshape(-1, 1)
    zn = np.asarray(z.detach().cpu() if isinstance(z, torch.Tensor) else z, dtype=np.float64).reshape(-1, 1)
    dmax = float(np.sqrt(np.max((xn - xe[None]) ** 2 + (zn - ze[None]) ** 2)))
    dl = delays.detach().cpu().numpy() if isinstance(delays, torch.Tensor) else np.asarray(delays)
    return frequency_grid(probe.fc, acq.fs, probe.bandwidth, acq.tx_cycles, acq.c, dmax,
                          float(np.nanmax(dl)) if dl.size else 0.0, options)
