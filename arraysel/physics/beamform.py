"""RF -> I/Q demodulation and delay-and-sum (DAS) beamforming, in PyTorch.

Conventions: see :mod:`arraysel.physics.simus` (SI units, x along the array, z depth).
Images are indexed ``[..., iz, ix]``.

* I/Q demodulation (as MUST's ``rf2iq``): the RF signal is mixed down by
  ``exp(-2i pi fc t)``, low-pass filtered with a zero-phase (forward-backward)
  5th-order Butterworth filter of normalised cut-off ``fc * bandwidth / fs``
  and multiplied by 2. Being linear in the RF, the whole operation is one
  (n_t x n_t) complex matrix applied along time (:func:`iq_matrix`); the
  filter coefficients and the forward-backward filtering come from SciPy.
* DAS (as MUST's ``dasmtx`` with linear interpolation): the round-trip time
  of pixel ``p`` for receive element ``e`` is ``(d_TX(p) + |p - x_e|) / c``,
  where ``d_TX`` is the earliest arrival of the transmitted wave, i.e. the
  minimum over the transmitting aperture of ``c tau + distance``, the
  aperture being sampled four times per element with cubic interpolation of
  positions and delays (exact for plane waves on a linear array). The I/Q
  sample at that time is linearly interpolated, phase-rotated by
  ``exp(2i pi fc t)`` and summed over the receive elements within the
  f-number aperture (``f-number = 0``: all of them). Samples outside
  ``[0, n_t - 2]`` contribute nothing.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
import torch

from arraysel.errors import ParameterError, check_number


def iq_lowpass(fs: float, fc: float, bandwidth: float | None) -> tuple[np.ndarray, np.ndarray]:
    """Coefficients (b, a) of the I/Q demodulation's 5th-order Butterworth low-pass, of
    normalised cut-off ``fc * bandwidth / fs`` (bandwidth in percent of fc; None: ``min(2 fc / fs,
    0.5)``), applied forward and backward (:func:`iq_matrix`)."""
    wn = min(2 * fc / fs, 0.5) if bandwidth is None else fc * bandwidth / 100 / fs
    check_number("normalised IQ cut-off (fc * bandwidth / fs)", wn, lo=0, lo_open=True, hi=1, hi_open=True)
    return _butter(float(wn))


@lru_cache(maxsize=32)
def _butter(wn: float) -> tuple[np.ndarray, np.ndarray]:
    import scipy.signal  # imported on first use: it costs a noticeable part of a cold start

    return scipy.signal.butter(5, wn)


@lru_cache(maxsize=32)
def _filtfilt_matrix(n_t: int, fs: float, fc: float, bandwidth: float | None) -> np.ndarray:
    import scipy.signal

    b, a = iq_lowpass(fs, fc, bandwidth)
    return scipy.signal.filtfilt(b, a, np.eye(n_t), axis=0)


def iq_matrix(n_t: int, fs: float, fc: float, bandwidth: float | None, t0: float = 0.0,
              dtype=torch.complex128, device=None, rows: slice = slice(None)) -> torch.Tensor:
    """Matrix ``Q`` (n_t, n_t) such that ``IQ = Q @ RF`` along the time axis (only its ``rows``,
    the I/Q samples wanted, if given).

    bandwidth in percent of fc (None: cut-off at ``min(2 fc / fs, 0.5)``).
    """
    F = _filtfilt_matrix(int(n_t), float(fs), float(fc), None if bandwidth is None else float(bandwidth))
    t = np.arange(n_t) / fs + t0
    mix = np.exp(-2j * np.pi * fc * t)
    Q = 2 * F[rows] * mix[None, :]
    return torch.as_tensor(Q, dtype=dtype, device=device)


def resample_uniform(y: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Values at positions ``t`` (in ``[0, n - 1]``) of the interpolant of ``y`` (n,) given at
    0, 1, ..., n - 1: the cubic spline with not-a-knot end conditions for n > 3 (as MATLAB's
    and SciPy's cubic ``interp1``), linear for n <= 3.

    Written out (NumPy only) because SciPy's interpolation module alone costs about 0.9 s of a
    cold start; ``tests/test_delays.py`` checks it against SciPy's ``interp1d``."""
    y = np.asarray(y, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64)
    n = y.size
    i = np.clip(np.floor(t).astype(np.int64), 0, n - 2)
    b = t - i
    a = 1.0 - b
    if n <= 3:
        return a * y[i] + b * y[i + 1]
    rhs = np.zeros(n)
    j = np.arange(1, n - 1)
    rhs[j] = 6.0 * (y[j + 1] - 2.0 * y[j] + y[j - 1])
    M = _spline_system(n) @ rhs
    return a * y[i] + b * y[i + 1] + ((a ** 3 - a) * M[i] + (b ** 3 - b) * M[i + 1]) / 6.0


@lru_cache(maxsize=8)
def _spline_system(n: int) -> np.ndarray:
    """Inverse of the (n, n) system of a not-a-knot cubic spline's second derivatives M at unit
    spacing: ``M[j-1] + 4 M[j] + M[j+1] = 6 (y[j+1] - 2 y[j] + y[j-1])`` inside, and a
    continuous third derivative at the first and last interior knots (``M[0] - 2 M[1] + M[2] =
    0``, likewise at the end). It depends on n only, and the DAS plans resample the same
    aperture for every block."""
    A = np.zeros((n, n))
    j = np.arange(1, n - 1)
    A[j, j - 1], A[j, j], A[j, j + 1] = 1.0, 4.0, 1.0
    A[0, :3] = (1.0, -2.0, 1.0)
    A[n - 1, n - 3:] = (1.0, -2.0, 1.0)
    inv = np.linalg.inv(A)
    inv.setflags(write=False)
    return inv


def transmit_distance(x: torch.Tensor, z: torch.Tensor, delays, probe, c: float) -> torch.Tensor:
    """Earliest transmit arrival, as a distance (m), at the points (x, z): shape of x.

    The aperture of transmitting elements (finite delays) is resampled four
    times per element (cubic interpolation of positions and delays against
    the element index) and ``min_i(c tau_i + |p - s_i|)`` is taken.
    """
    delays = np.asarray(delays, dtype=np.float64).reshape(-1)
    xe, ze, _, _ = probe.element_positions()
    active = np.isfinite(delays)
    n_tx = int(active.sum())
    if n_tx == 0:
        raise ParameterError("delays: at least one element must transmit (finite delay)")
    if n_tx > 1:
        fine = np.linspace(0, n_tx - 1, 4 * n_tx)
        xs = resample_uniform(xe[active], fine)
        zs = np.zeros_like(xs) if probe.is_linear else resample_uniform(ze[active], fine)
        ds = resample_uniform(delays[active], fine)
    else:
        xs, zs, ds = xe[active], ze[active], delays[active]
    xs = torch.as_tensor(xs, dtype=x.dtype, device=x.device)
    zs = torch.as_tensor(zs, dtype=x.dtype, device=x.device)
    ds = torch.as_tensor(ds * c, dtype=x.dtype, device=x.device)
    shape = x.shape
    xf, zf = x.reshape(-1, 1), z.reshape(-1, 1)
    out = torch.empty(xf.shape[0], dtype=x.dtype, device=x.device)
    step = max(1, 2 ** 22 // max(1, xs.numel()))
    for i in range(0, xf.shape[0], step):
        dist = torch.sqrt((xf[i:i + step] - xs) ** 2 + (zf[i:i + step] - zs) ** 2) + ds
        out[i:i + step] = dist.min(dim=1).values
    return out.reshape(shape)


@dataclass
class DASPlan:
    """Interpolation plan of a DAS beamformer for one transmit.

    i0: (Npix, Ne) index of the first sample; w: (Npix, Ne) linear weight of
    the second sample; rot: (Npix, Ne) complex phase rotation times validity
    (0 where the sample is outside the record or the element outside the
    f-number aperture).
    """

    i0: torch.Tensor
    w: torch.Tensor
    rot: torch.Tensor


def das_positions(x: torch.Tensor, z: torch.Tensor, delays, probe, fs: float, c: float, n_t: int,
                  fnumber: float = 0.0, t0: float = 0.0, dtx: torch.Tensor | None = None):
    """Sample positions of a DAS plan: ``(tau, pos, valid)``, each (Npix, Ne): the two-way delay
    (s), its position in samples, and whether the sample lies in the record and the element in
    the f-number aperture (what :func:`das_plan` builds its plan from). ``dtx``: the pixels'
    :func:`transmit_distance` when the caller has it already."""
    check_number("fnumber", fnumber, lo=0.0)
    x = x.reshape(-1)
    z = z.reshape(-1)
    dtx = transmit_distance(x, z, delays, probe, c) if dtx is None else dtx.reshape(-1).to(x.dtype)
    xe, ze, the, _ = probe.element_positions()
    xe = torch.as_tensor(xe, dtype=x.dtype, device=x.device)
    ze = torch.as_tensor(ze, dtype=x.dtype, device=x.device)
    dxe = x[:, None] - xe[None]
    drx = torch.sqrt(dxe ** 2 + (z[:, None] - ze[None]) ** 2)
    tau = (dtx[:, None] + drx) / c
    pos = (tau - t0) * fs
    valid = (pos >= 0) & (pos <= n_t - 2)
    if fnumber > 0:
        if probe.is_linear:
            valid &= dxe.abs() <= z[:, None] / 2 / fnumber
        else:
            the_t = torch.as_tensor(the, dtype=x.dtype, device=x.device)
            valid &= (torch.asin(dxe / drx) - the_t).abs() <= math.atan(1 / 2 / fnumber)
    return tau, pos, valid


def das_plan(x: torch.Tensor, z: torch.Tensor, delays, probe, fs: float, c: float, n_t: int,
             fnumber: float = 0.0, t0: float = 0.0, iq: bool = True, fc: float | None = None,
             dtx: torch.Tensor | None = None) -> DASPlan:
    """Build the DAS interpolation plan for pixels (x, z) (flattened) and one transmit
    (``dtx``: the pixels' transmit distances, if known)."""
    tau, pos, valid = das_positions(x, z, delays, probe, fs, c, n_t, fnumber=fnumber, t0=t0, dtx=dtx)
    posc = torch.where(valid, pos, torch.zeros_like(pos))
    i0 = torch.floor(posc)
    w = posc - i0
    cdt = torch.complex128 if x.dtype == torch.float64 else torch.complex64
    if iq:
        if fc is None:
            raise ParameterError("fc is required to beamform I/Q signals")
        rot = torch.polar(valid.to(x.dtype), 2 * math.pi * fc * tau)
    else:
        rot = valid.to(cdt)
    return DASPlan(i0=i0.to(torch.long), w=w, rot=rot.to(cdt))


def das_apply(iq: torch.Tensor, i0: torch.Tensor, w: torch.Tensor, rot: torch.Tensor) -> torch.Tensor:
    """Linear-interpolation DAS: ``sum_e rot[p,e] ((1-w) iq[e,i0] + w iq[e,i0+1])``.

    iq: (..., Ne, n_t); i0, w, rot: (Npix, Ne). Returns (..., Npix). Differentiable in iq.
    """
    lead = iq.shape[:-2]
    ne, n_t = iq.shape[-2:]
    flat = iq.reshape(-1, ne * n_t)
    offs = (torch.arange(ne, device=iq.device) * n_t)[None, :]
    j0 = (i0 + offs).reshape(-1)
    a = flat[:, j0]
    b = flat[:, j0 + 1]
    wr = w.reshape(-1).to(iq.real.dtype)
    val = (a + (b - a) * wr) * rot.reshape(-1).to(iq.dtype)
    out = val.reshape(flat.shape[0], i0.shape[0], ne).sum(-1)
    return out.reshape(lead + (i0.shape[0],))
