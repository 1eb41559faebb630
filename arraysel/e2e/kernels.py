"""The PSF kernel as the image model of end-to-end training sees it: cropped or padded to the scene
size (:func:`fit_kernel`) or sub-sampled to a coarser scene grid (:func:`decimate_kernel`)."""
from __future__ import annotations

import torch

from arraysel.errors import ParameterError, check_number

__all__ = ["fit_kernel", "decimate_kernel"]


def fit_kernel(kappa: torch.Tensor, n: int) -> torch.Tensor:
    """Crop (or zero-pad) an ``(h, h)`` kernel to ``(n, n)`` keeping its centre pixel.

    Pixel ``(h // 2, h // 2)`` of ``kappa`` becomes pixel ``(n // 2, n // 2)``
    of the result (the zero shift of :class:`~arraysel.e2e.recon.ConvolutionOperator`);
    differentiable.
    """
    h = kappa.shape[-1]
    if h == n:
        return kappa
    if h > n:
        s = h // 2 - n // 2
        return kappa[..., s:s + n, s:s + n]
    s = n // 2 - h // 2
    return torch.nn.functional.pad(kappa, (s, n - h - s, s, n - h - s))


def decimate_kernel(kappa: torch.Tensor, stride: int) -> torch.Tensor:
    """Every ``stride``-th pixel of an ``(h, h)`` kernel, keeping its centre pixel, unit L2 norm.

    Pixel ``(h // 2, h // 2)`` of ``kappa`` becomes pixel ``(h // 2 // stride, ...)``,
    the centre pixel of the result when ``h`` is a multiple of ``stride``
    (``h = 128, stride = 2``: 64 x 64 at twice the pitch). Plain sub-sampling,
    no filter: it is exact when the kernel's spectrum lies inside the coarser
    grid's Nyquist band (the paper scene's beamformed I/Q PSF: 5e-4 of the
    energy of the uniform selection's kernel lies outside it for ``stride = 2``,
    14 % for ``stride = 4``). The result is rescaled to unit L2 norm like the
    objective's kernels. Differentiable; ``stride = 1`` returns ``kappa``.
    """
    stride = check_number("kernel_stride", stride, lo=1, integer=True)
    if stride == 1:
        return kappa
    h = kappa.shape[-1]
    if h % stride:
        raise ParameterError(f"kernel_stride ({stride}) must divide the kernel size ({h})")
    c = h // 2
    sub = kappa[..., c % stride::stride, c % stride::stride]
    norm = (sub.real ** 2 + sub.imag ** 2).sum((-2, -1), keepdim=True).sqrt() if sub.is_complex() \
        else sub.pow(2).sum((-2, -1), keepdim=True).sqrt()
    return sub / norm.clamp_min(torch.finfo(norm.dtype).tiny)
