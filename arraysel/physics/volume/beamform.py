"""Delay-and-sum onto 3-D points for matrix probes (as MUST's ``dasmtx3``, linear interpolation).

The round-trip time of point ``p`` for receive element ``e`` is ``(d_TX(p) + |p - r_e|) / c``
where ``d_TX(p) = min_j (c tau_j + |p - r_j|)`` over the transmitting elements (finite delays),
the earliest arrival of the transmitted wave (no resampling of the aperture, unlike the 1-D
rule). The I/Q sample at that time is linearly interpolated, rotated by ``exp(2i pi fc t)`` and
summed over every element (f-number 0, t0 = 0 by default); samples outside ``[0, n_t - 2]``
contribute nothing. The plan is a :class:`~arraysel.physics.beamform.DASPlan` applied by
:func:`~arraysel.physics.beamform.das_apply`, as in 1-D.
"""
from __future__ import annotations

import math

import numpy as np
import torch

from arraysel.errors import ParameterError, check_number
from arraysel.physics.beamform import DASPlan
from arraysel.physics.probes import MatrixProbe

__all__ = ["transmit_distance3", "receive_distance3", "das_plan3"]


def _pts(points: torch.Tensor) -> torch.Tensor:
    if not isinstance(points, torch.Tensor):
        points = torch.as_tensor(np.asarray(points, dtype=np.float64))
    if points.shape[-1] != 3:
        raise ParameterError(f"points must have shape (..., 3) (x, y, z in metres), got {tuple(points.shape)}")
    return points.reshape(-1, 3)


def transmit_distance3(points, delays, probe: MatrixProbe, c: float) -> torch.Tensor:
    """Earliest transmit arrival as a distance (m) at ``points`` (..., 3): shape (N,) (flattened),
    the minimum over the elements with a finite delay of ``c tau_j + |p - r_j|``."""
    p = _pts(points)
    delays = np.asarray(delays, dtype=np.float64).reshape(-1)
    if delays.size != probe.n_elements:
        raise ParameterError(f"delays must have {probe.n_elements} entries, got {delays.size}")
    active = np.isfinite(delays)
    if not active.any():
        raise ParameterError("delays: at least one element must transmit (finite delay)")
    pos = torch.as_tensor(probe.element_positions()[active], dtype=p.dtype, device=p.device)
    dl = torch.as_tensor(delays[active] * c, dtype=p.dtype, device=p.device)
    out = torch.empty(p.shape[0], dtype=p.dtype, device=p.device)
    step = max(1, 2 ** 20 // pos.shape[0])
    for i in range(0, p.shape[0], step):
        out[i:i + step] = (_distances(p[i:i + step], pos) + dl).min(dim=1).values
    return out


def _distances(p: torch.Tensor, pos: torch.Tensor) -> torch.Tensor:
    """|p_i - r_j| (N, Ne), component by component (exact to rounding, unlike a matrix-product form)."""
    dx = p[:, 0, None] - pos[None, :, 0]
    dy = p[:, 1, None] - pos[None, :, 1]
    dz = p[:, 2, None] - pos[None, :, 2]
    return torch.sqrt(dx * dx + dy * dy + dz * dz)


def receive_distance3(points, probe: MatrixProbe) -> torch.Tensor:
    """Distances (N, Ne) in metres from ``points`` (..., 3) (flattened) to every element."""
    p = _pts(points)
    return _distances(p, torch.as_tensor(probe.element_positions(), dtype=p.dtype, device=p.device))


def das_plan3(points, delays, probe: MatrixProbe, fs: float, c: float, n_t: int, fc: float,
              t0: float = 0.0, iq: bool = True) -> DASPlan:
    """DAS plan (flattened points x Ne) of one transmit with full-aperture receive (f-number 0)."""
    check_number("fs", fs, lo=0, lo_open=True)
    p = _pts(points)
    dtx = transmit_distance3(p, delays, probe, c)
    tau = (dtx[:, None] + receive_distance3(p, probe)) / c
    pos = (tau - t0) * fs
    valid = (pos >= 0) & (pos <= n_t - 2)
    posc = torch.where(valid, pos, torch.zeros_like(pos))
    i0 = torch.floor(posc)
    cdt = torch.complex128 if p.dtype == torch.float64 else torch.complex64
    if iq:
        rot = torch.polar(valid.to(p.dtype), 2 * math.pi * fc * tau)
    else:
        rot = valid.to(cdt)
    return DASPlan(i0=i0.to(torch.long), w=posc - i0, rot=rot.to(cdt))
