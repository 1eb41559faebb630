"""Tensors held in a lower precision than the evaluation's, and products with them.

The fast path's two large tensors (:class:`~arraysel.physics.volume.fast.MatrixFastPSF`'s receive
matrix and transmit tensor) may be stored in float16 (:attr:`FastSettings.storage
<arraysel.physics.volume.fast.FastSettings>`): half the memory and cache of float32. Each stored
column is scaled to a largest magnitude of 1 (its scale kept in float32), so nothing overflows and
every entry keeps float16's 11 significant bits relative to its column. The products with them are
formed in the evaluation's precision, a block of :data:`STORED_BLOCK` columns converted into one
buffer at a time and the product's columns scaled once, so the stored tensor is never held whole
in float32 and the only rounding is that of the stored entries (measured by the fast path's check).
"""
from __future__ import annotations

import torch

__all__ = ["STORAGES", "STORED_BLOCK", "ColumnSink", "store", "stored_product"]

#: the precisions :class:`~arraysel.physics.volume.fast.FastSettings` may store the large tensors in
STORAGES = ("float32", "float16")
#: columns of a stored tensor converted to the evaluation's precision at a time
STORED_BLOCK = 1024


def store(x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``(data, scale)``: a tensor (R, C) as float16 columns scaled to a largest magnitude of 1, and
    the float32 scales (C,) that restore it (``data * scale``); an all-zero column has scale 1. A
    complex tensor is stored as its real view, (re, im) pairs of columns (R, 2 C), both parts of a
    column under its one scale."""
    real = torch.view_as_real(x) if x.is_complex() else x[..., None]            # (R, C, 1 or 2)
    top = real.abs().amax((0, 2))
    scale = torch.where(top > 0, top, torch.ones_like(top))
    return (real / scale[:, None]).reshape(x.shape[0], -1).to(torch.float16), scale.to(torch.float32)


class ColumnSink:
    """A complex tensor (R, C) written a block of whole columns at a time and held as it will be
    used, never whole in ``cdtype``: ``real`` True, as its real view (R, 2 C), (re, im) pairs of
    columns, else complex; with ``storage`` "float16", each block stored at once (:func:`store`,
    which scales each column, real or complex, on its own: storing by blocks gives what storing the
    whole tensor would). :meth:`put` the columns ``c0:c0 + w`` (all R rows, any complex dtype,
    cast to ``cdtype`` first); :meth:`result` ``(data, scale or None)``."""

    def __init__(self, rows: int, cols: int, storage: str, cdtype, real: bool):
        if storage not in STORAGES:
            raise ValueError(f"storage = {storage!r} is not allowed; choose one of {', '.join(STORAGES)}")
        self.half, self.real, self.cdtype = storage == "float16", bool(real), cdtype
        rdtype = torch.float32 if cdtype == torch.complex64 else torch.float64
        if self.half:
            self.data = torch.zeros(rows, 2 * cols, dtype=torch.float16)
            self.scale = torch.ones(2 * cols if self.real else cols, dtype=torch.float32)
        else:
            self.data = torch.zeros(rows, 2 * cols, dtype=rdtype) if self.real else torch.zeros(rows, cols, dtype=cdtype)
            self.scale = None

    def put(self, c0: int, block: torch.Tensor) -> None:
        w = block.shape[1]
        x = block.to(self.cdtype)
        if self.real:
            x = torch.view_as_real(x).reshape(x.shape[0], -1)
        if not self.half:
            if self.real:
                self.data[:, 2 * c0:2 * (c0 + w)] = x
            else:
                self.data[:, c0:c0 + w] = x
            return
        data, scale = store(x)
        self.data[:, 2 * c0:2 * (c0 + w)] = data
        per = 2 if self.real else 1
        self.scale[per * c0:per * (c0 + w)] = scale

    def result(self) -> tuple[torch.Tensor, torch.Tensor | None]:
        return self.data, self.scale


def _blocks(stored: torch.Tensor, n: int, dtype):
    """``(a, b, block)`` for each :data:`STORED_BLOCK` of the ``n`` columns of ``stored``: columns
    ``a:b`` in ``dtype``, unscaled, converted into one buffer (a complex ``dtype`` reads the stored
    (re, im) pairs of columns; the last, narrower block is a new tensor)."""
    cplx = dtype.is_complex
    real = (torch.float32 if dtype == torch.complex64 else torch.float64) if cplx else dtype
    per = 2 if cplx else 1
    buf = torch.empty(stored.shape[0], per * min(n, STORED_BLOCK), dtype=real, device=stored.device)
    for a in range(0, n, STORED_BLOCK):
        b = min(n, a + STORED_BLOCK)
        src = stored[:, per * a:per * b]
        blk = buf.copy_(src) if src.shape[1] == buf.shape[1] else src.to(real)
        yield a, b, (torch.view_as_complex(blk.reshape(stored.shape[0], b - a, 2)) if cplx else blk)


class _StoredProduct(torch.autograd.Function):
    """``x @ S`` for ``S`` held in float16 with column scales: ``S`` converted to ``x``'s precision
    :data:`STORED_BLOCK` columns at a time into one buffer (never whole), the product formed in
    ``x``'s and scaled once at the end."""

    @staticmethod
    def forward(ctx, x, stored, scale):
        n = stored.shape[1] // 2 if x.is_complex() else stored.shape[1]
        out = torch.empty(x.shape[0], n, dtype=x.dtype, device=x.device)
        for a, b, blk in _blocks(stored, n, x.dtype):
            out[:, a:b] = x @ blk
        if scale is not None:
            out.mul_(scale.to(x.real.dtype))
        ctx.save_for_backward(stored, scale)
        ctx.n, ctx.dtype = n, x.dtype
        return out

    @staticmethod
    def backward(ctx, grad):
        stored, scale = ctx.saved_tensors
        if scale is not None:
            grad = grad * scale.to(grad.real.dtype)
        gx = torch.zeros(grad.shape[0], stored.shape[0], dtype=ctx.dtype, device=grad.device)
        for a, b, blk in _blocks(stored, ctx.n, ctx.dtype):
            gx += grad[:, a:b] @ blk.mH
        return gx, None, None


def stored_product(x: torch.Tensor, stored: torch.Tensor, scale: torch.Tensor | None = None) -> torch.Tensor:
    """``x @ stored`` (differentiable in ``x``); a float16 ``stored`` (with its column ``scale``
    from :func:`store`; a complex ``x``: its (re, im) pairs of columns) is read a block of columns
    at a time in ``x``'s precision."""
    if stored.dtype != torch.float16:
        return x @ stored
    return _StoredProduct.apply(x, stored, scale)
