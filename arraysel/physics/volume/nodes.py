"""Interpolation pieces of the fast 3-D path (:mod:`arraysel.physics.volume.fast`): the harmonics
of linear interpolation of a tone, Chebyshev nodes, the barycentric Lagrange basis on them, and how
wide a phase span a number of nodes interpolates to a tolerance."""
from __future__ import annotations

import math

import torch

__all__ = ["interpolation_harmonics", "chebyshev_nodes", "lagrange", "node_reach"]


def interpolation_harmonics(beta: torch.Tensor, orders) -> torch.Tensor:
    """Fourier coefficients ``h_q(beta)`` (len(orders), F) complex128 of the 1-periodic factor that
    linear interpolation of the samples ``exp(i beta m)`` multiplies the tone ``exp(i beta x)`` by:
    ``interp(x) = exp(i beta x) sum_q h_q exp(2i pi q x)`` (``h_q = sinc^2(beta / 2 pi + q)``)."""
    beta = torch.as_tensor(beta, dtype=torch.float64)
    u = beta / (2 * math.pi)
    return torch.stack([torch.sinc(u + q) ** 2 for q in orders]).to(torch.complex128)


def chebyshev_nodes(n: int) -> torch.Tensor:
    k = torch.arange(n, dtype=torch.float64)
    return torch.cos(math.pi * (2 * k + 1) / (2 * n))


def lagrange(nodes: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """Lagrange basis ``l_m(x)`` for the node sets ``nodes`` (..., S) at points ``x`` (..., E):
    (..., E, S), by the barycentric formula (exact at the nodes)."""
    s = nodes.shape[-1]
    diff = nodes[..., :, None] - nodes[..., None, :]  # (..., S, S)
    eye = torch.eye(s, dtype=torch.bool, device=nodes.device)
    wts = 1.0 / torch.where(eye, torch.ones_like(diff), diff).prod(-1)  # (..., S)
    d = x[..., :, None] - nodes[..., None, :]  # (..., E, S)
    hit = d == 0
    d = torch.where(hit, torch.ones_like(d), d)
    terms = wts[..., None, :] / d
    out = terms / terms.sum(-1, keepdim=True)
    if bool(hit.any()):
        exact = hit.to(out.dtype)
        out = torch.where(hit.any(-1, keepdim=True), exact, out)
    return out


def node_reach(n: int, tol: float, a_hi: float) -> float:
    """The largest phase half-span ``a <= a_hi`` for which ``n`` Chebyshev nodes interpolate
    ``exp(i a t)`` on [-1, 1] to ``tol`` (max error on a fine grid; bisection, the error growing with a)."""
    th = torch.linspace(-1, 1, 401, dtype=torch.float64)
    nd = chebyshev_nodes(n)
    ell = lagrange(nd, th).to(torch.complex128)

    def err(a):
        return float((ell @ torch.polar(torch.ones_like(nd), a * nd) - torch.polar(torch.ones_like(th), a * th)).abs().max())

    if err(a_hi) <= tol:
        return a_hi
    lo, hi = 0.0, a_hi
    for _ in range(40):
        m = (lo + hi) / 2
        lo, hi = (m, hi) if err(m) <= tol else (lo, m)
    return lo
