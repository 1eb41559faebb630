"""The reductions every PSF metric is made of, 1-D kernels and 3-D plane sets alike: safe divisions
and square roots, dot products and norms on the CPU's BLAS, the detached scale that keeps float32
squares in range, the peak of ``|kappa|^2`` and the masked quantile of ``L_SLR_q``.

:mod:`arraysel.objective.metrics` (kernels on a pixel grid), :mod:`arraysel.objective.metrics3d`
(plane sets with pixel positions) and :mod:`arraysel.objective.columns3d` import them from here, the
one definition of each. Every function is differentiable where it is smooth and gives finite
sub-gradients elsewhere (never NaN).
"""
from __future__ import annotations

import math

import torch
from torch import Tensor

__all__ = ["BOUNDARY_RTOL", "broadcast_shapes", "safe_div", "detached_scale", "divide_by_scale", "use_matmul",
           "inner", "rowdot", "sqnorm", "promote", "scaled_abs2", "peak_index", "safe_sqrt", "masked_quantile"]

#: relative tolerance on r**2 for the inclusive region boundaries (a pixel exactly on a boundary is
#: inside whatever the rounding of the pitch and the wavelength)
BOUNDARY_RTOL = 1e-9


def broadcast_shapes(*shapes) -> torch.Size:
    """``torch.broadcast_shapes`` without its first-call import of torch's symbolic-shape machinery
    (sympy: about a second of a cold start); raises RuntimeError when the shapes do not broadcast."""
    import numpy as np

    try:
        return torch.Size(np.broadcast_shapes(*(tuple(s) for s in shapes)))
    except ValueError as exc:
        raise RuntimeError(str(exc)) from None


def safe_div(num: Tensor, den: Tensor) -> Tensor:
    """num / den where den != 0, 0 elsewhere; finite gradient in both cases."""
    nz = den != 0
    return torch.where(nz, num / torch.where(nz, den, torch.ones_like(den)), torch.zeros_like(num))


def detached_scale(x: Tensor) -> Tensor:
    """max(|Re|, |Im|) over the last two axes, detached; 1 where the kernel is zero."""
    x = x.detach()
    s = (torch.view_as_real(x).abs().amax(dim=(-3, -2, -1)) if x.is_complex()
         else x.abs().amax(dim=(-2, -1)))
    return torch.where(s > 0, s, torch.ones_like(s))


def divide_by_scale(x: Tensor, s: Tensor) -> Tensor:
    """``x / s[..., None, None]`` for a real ``s > 0`` of shape ``x.shape[:-2]``.

    A complex ``x`` is divided through its real view: torch promotes a real
    divisor to complex, and its complex division returns inf/NaN for a
    subnormal divisor (e.g. a float32 kernel whose largest entry is 1e-44).
    """
    if x.is_complex():
        return torch.view_as_complex(torch.view_as_real(x.resolve_conj()) / s[..., None, None, None])
    return x / s[..., None, None]


def use_matmul(x: Tensor) -> bool:
    """Whether to reduce dot products with matmul (BLAS) rather than multiply-and-sum.

    Only on CPU, where it is several times faster. On accelerators the
    elementwise form is as fast (memory bound) and is never subject to
    reduced-precision matmul modes (TF32 under
    ``torch.set_float32_matmul_precision('high')``).
    """
    return x.device.type == "cpu"


def inner(u: Tensor, v: Tensor) -> Tensor:
    """<u, v> = sum(conj(u) v) over the last two axes, leading axes broadcast."""
    uf, vf = u.flatten(-2), v.flatten(-2)
    if not use_matmul(uf):
        return (uf.conj() * vf).sum(-1)
    if not (u.is_complex() or v.is_complex()):
        return torch.matmul(uf.unsqueeze(-2), vf.unsqueeze(-1))[..., 0, 0]
    # conj(sum(u conj(v))) with conj(v) materialised: in torch 2.x a matmul
    # with a lazily conjugated operand takes a much slower path.
    return torch.matmul(uf.unsqueeze(-2), vf.conj().resolve_conj().unsqueeze(-1))[..., 0, 0].conj()


def rowdot(x: Tensor, y: Tensor) -> Tensor:
    """sum(x * y, -1) for real tensors of the same shape."""
    if not use_matmul(x):
        return (x * y).sum(-1)
    return torch.matmul(x.unsqueeze(-2), y.unsqueeze(-1))[..., 0, 0]


def sqnorm(u: Tensor) -> Tensor:
    """||u||^2 over the last two axes (real), smooth everywhere."""
    x = torch.view_as_real(u).flatten(-3) if u.is_complex() else u.flatten(-2)
    return rowdot(x, x)


def promote(a: Tensor, b: Tensor) -> tuple[Tensor, Tensor]:
    dt = torch.promote_types(a.dtype, b.dtype)
    return a.to(dt), b.to(dt)


def scaled_abs2(kappa: Tensor) -> Tensor:
    """|kappa / s|^2 flattened to (B, H*W), s = detached max(|Re|, |Im|) of each kernel.

    The scale keeps the squares in range in float32 whatever the kernels'
    units; every lobe ratio is scale invariant, so no gradient is lost.
    """
    b = kappa.shape[0]
    xr = torch.view_as_real(kappa) if kappa.is_complex() else kappa[..., None]
    xr = xr.reshape(b, -1, xr.shape[-1])
    return (xr / detached_scale(kappa)[:, None, None]).square().sum(-1)


def peak_index(k2: Tensor) -> Tensor:
    """Argmax of ``k2`` of shape (B, N) (first on ties): (B,) long, no gradient."""
    return torch.argmax(k2.detach(), dim=-1)


def safe_sqrt(x: Tensor) -> Tensor:
    """sqrt(x) for x > 0, 0 elsewhere; gradient 0 (not inf/NaN) at x <= 0."""
    pos = x > 0
    return torch.where(pos, torch.sqrt(torch.where(pos, x, torch.ones_like(x))), torch.zeros_like(x))


def masked_quantile(x: Tensor, mask: Tensor, q: float, transform=None) -> Tensor:
    """Per-row quantile (linear interpolation, as torch.quantile) over ``mask``.

    ``x`` (B, N) with ``x >= 0``; ``mask`` (B, N) of 0/1 in ``x``'s dtype.
    Returns the q-quantile of ``transform(x)`` (an increasing function,
    applied only to the two order statistics needed). Rows with an empty mask
    give 0. One ``topk`` over the batch: only the ~(1 - q) N largest values
    are needed, not a sort.
    """
    b, n_all = x.shape
    n = mask.sum(-1).round().long()                     # (B,) count of masked pixels
    n_eff = n.clamp_min(1)
    k = min(n_all, int(math.ceil((1.0 - q) * (n_all - 1))) + 2)
    vals = torch.addcmul(mask - 1, x, mask)             # x inside, sentinel -1 outside
    top = torch.topk(vals, k, dim=-1, largest=True, sorted=True).values  # descending
    rank_dt = torch.float32 if x.device.type == "mps" else torch.float64
    pos = q * (n_eff - 1).to(rank_dt)                   # ascending rank, as torch.quantile
    lo = torch.floor(pos)
    hi = torch.ceil(pos)
    frac = (pos - lo).to(x.dtype)
    d_lo = (n_eff - 1 - lo.long()).clamp(0, k - 1)       # ascending rank -> descending index
    d_hi = (n_eff - 1 - hi.long()).clamp(0, k - 1)
    v_lo = top.gather(-1, d_lo[:, None]).squeeze(-1)
    v_hi = top.gather(-1, d_hi[:, None]).squeeze(-1)
    if transform is not None:
        v_lo, v_hi = transform(v_lo), transform(v_hi)
    res = v_lo + frac * (v_hi - v_lo)
    return torch.where(n > 0, res, torch.zeros_like(res))
