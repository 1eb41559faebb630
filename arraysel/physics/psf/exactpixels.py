"""The exact image values of one selection on chosen pixels, :class:`ExactPixels`: delay-and-sum
of its I/Q channels with the DAS plans of the grid blocks (made on demand, kept up to a memory
cap, their transmit distances kept for good) or of E (made once), compiled without gradient,
torch's ``das_apply`` with one.

:class:`ExactPixels` is a part of :class:`~arraysel.physics.psf.refinement.Refinement`
(``refinement.exact``), which settles loose blocks, near-ties and kernel windows with it; a
truncated view's refinement shares its caches. Its inputs (constructor arguments): ``model``
(its public interface), ``layout`` (E's rows, columns and shape) and ``certificates`` (the
channels' windows: ``window_offset``, ``window_samples``).
"""
from __future__ import annotations

import numpy as np
import torch

from arraysel.physics.beamform import das_apply
from arraysel.physics.psf.build import window_plans
from arraysel.physics.psf.certificate import RawChannels

__all__ = ["ExactPixels"]


def pixel_blocks(zi: torch.Tensor, xi: torch.Tensor, b: int, n_x: int) -> tuple[list, list, list]:
    """``(blocks, rows, order)`` of grid pixels (zi, xi): the blocks (``b`` x ``b`` pixels, ``n_x``
    grid columns) that hold them, each block's pixels as row-major indices within it, and the
    positions of those pixels in ``zi``."""
    blocks, rows, order = [], [], []
    qz, qx = zi // b, xi // b
    for z_, x_ in torch.unique(torch.stack([qz, qx], 1), dim=0).tolist():
        sel = torch.nonzero((qz == z_) & (qx == x_)).flatten()
        bw = min(b, n_x - x_ * b)
        blocks.append((z_, x_))
        rows.append((zi[sel] - z_ * b) * bw + (xi[sel] - x_ * b))
        order.append(sel)
    return blocks, rows, order


class ExactPixels:
    """Exact image values of one selection on grid blocks, pixels and kernel windows (see the
    module), with the caches of the DAS plans: ``blocks`` (block -> its plan), ``dtx`` (block ->
    its transmit distances) and E's plan."""

    def __init__(self, model, layout, certificates):
        self.model = model
        self.layout = layout
        self.certificates = certificates
        self.blocks: dict = {}  # block -> its DAS plan (:meth:`plans_for_blocks`)
        self.dtx: dict = {}  # block -> its transmit distances (:meth:`transmit_distances`)
        self._e_plans = None  # E's DAS plan (:meth:`e_plans`)

    #: memory (bytes) of the block DAS plans kept (one block: ntx x block^2 x Ne entries of index, weight and rotation)
    plan_cache_bytes = 256 * 2 ** 20

    @property
    def plan_index_dtype(self) -> torch.dtype:
        """Integer type of the block plans' sample indices (local to the channel windows): 16
        bits where the windows allow, so that the plan cache holds more blocks (256 elements:
        167 blocks in :attr:`plan_cache_bytes` instead of 117 with 64-bit indices)."""
        return torch.int16 if self.certificates.window_samples < 2 ** 15 else torch.int32

    @property
    def plan_cache_blocks(self) -> int:
        """Block DAS plans kept in memory (from :attr:`plan_cache_bytes`)."""
        model = self.model
        entry = self.plan_index_dtype.itemsize + model.dtype.itemsize + model.cdtype.itemsize
        per = len(model.transmits) * model.block ** 2 * model.n_elements * entry
        return max(16, self.plan_cache_bytes // per)

    def plans_for_blocks(self, blocks: list) -> list:
        """DAS plans of the pixels of the grid blocks ``blocks`` ((qz, qx) pairs), row-major,
        clipped to the grid: per block ``(i0, w, rot)`` stacked over the transmits, shapes
        (ntx, npix, Ne) (sample index, interpolation weight, complex rotation). Cached; the
        missing blocks are planned together (:func:`~arraysel.physics.psf.build.window_plans`)."""
        missing = list(dict.fromkeys(q for q in blocks if q not in self.blocks))
        made = {}
        if missing:
            model = self.model
            b = model.block
            zs, xs, sizes = [], [], []
            for qz, qx in missing:
                Z, X = torch.meshgrid(model.z_grid[qz * b:(qz + 1) * b], model.x_grid[qx * b:(qx + 1) * b],
                                      indexing="ij")
                zs.append(Z.reshape(-1))
                xs.append(X.reshape(-1))
                sizes.append(Z.numel())
            dtx = self.transmit_distances(missing, xs, zs)
            offset = self.certificates.window_offset
            per_tx = list(zip(*window_plans(self.model, offset, torch.cat(xs), torch.cat(zs), dtx)))
            stacked = (torch.stack(per_tx[0]).to(model.device, self.plan_index_dtype),
                       torch.stack(per_tx[1]).to(model.device, model.dtype),
                       torch.stack(per_tx[2]).to(model.device, model.cdtype))
            parts = [a.split(sizes, dim=1) for a in stacked]
            for i, q in enumerate(missing):
                made[q] = tuple(a[i].contiguous() for a in parts)
                if len(self.blocks) < self.plan_cache_blocks:
                    self.blocks[q] = made[q]
        return [self.blocks.get(q) or made[q] for q in blocks]

    def transmit_distances(self, blocks: list, xs: list, zs: list) -> torch.Tensor:
        """(ntx, Npix) transmit distances of the pixels (``xs``, ``zs``: one tensor per block) of
        ``blocks``, kept per block for good (7 transmits x 64 pixels a block: 8 MB for a 400 x
        400 grid): an evicted block plan is made again without them, which are most of its
        cost for a large aperture (each pixel's minimum over 4 points an element)."""
        from arraysel.physics.beamform import transmit_distance

        model = self.model
        s = model.setup
        known = self.dtx
        todo = [i for i, q in enumerate(blocks) if q not in known]
        if todo:
            x = torch.cat([xs[i] for i in todo])
            z = torch.cat([zs[i] for i in todo])
            d = torch.stack([transmit_distance(x, z, t.delays, s.probe, s.acq.c) for t in model.transmits])
            for i, part in zip(todo, d.split([xs[i].numel() for i in todo], dim=1)):
                known[blocks[i]] = part.clone()
        return torch.cat([known[q] for q in blocks], dim=1)

    def das(self, X: torch.Tensor, blocks: list, rows: list | None = None, step: int = 32) -> torch.Tensor:
        """Exact image values of one selection (I/Q channels X: (ntx, Ne, T) complex, or its
        :class:`RawChannels`) on the pixels of ``blocks`` ((qz, qx) pairs), or on the given pixel
        rows of each block's plan. Blocks are planned and summed ``step`` at a time
        (:attr:`Refinement.das_blocks <arraysel.physics.psf.refinement.Refinement.das_blocks>`),
        so a window's 256 blocks do not hold all their plans at once (2.3 MB a block for a
        256-element probe)."""
        if not isinstance(X, RawChannels) and not X.requires_grad and X.device.type == "cpu":
            # no gradient wanted: complex channels as raw ones (time order, receive weights applied)
            y = torch.view_as_real(X).permute(1, 3, 0, 2).contiguous().numpy()
            X = RawChannels(y, np.ones(y.shape[0], dtype=y.dtype), 1)
        blocks = [(int(qz), int(qx)) for qz, qx in blocks]
        if len(blocks) > step:
            return torch.cat([self.das(X, blocks[i:i + step], None if rows is None else rows[i:i + step], step)
                              for i in range(0, len(blocks), step)])
        plans = self.plans_for_blocks(blocks)
        if rows is not None:
            plans = [tuple(a[:, r] for a in pl) for pl, r in zip(plans, rows)]
        if isinstance(X, RawChannels):
            # the compiled sum, a block at a time (concatenating the blocks' plans copied more
            # than the sums read)
            return torch.cat([self.das_compiled(X, pl) for pl in plans])
        i0, wt, rot = (torch.cat([pl[j] for pl in plans], dim=1) if len(plans) > 1 else plans[0][j]
                       for j in range(3))
        img = 0
        for n in range(len(self.model.transmits)):
            img = img + das_apply(X[n], i0[n], wt[n], rot[n])
        return img

    def das_compiled(self, X: RawChannels, plan: tuple) -> torch.Tensor:
        """Exact image values of one selection (its raw channels) on the pixels of one block plan
        (stacked over the transmits) by the compiled sum over every transmit, which skips the
        entries outside the aperture."""
        i0, wt, rot = plan
        from arraysel.physics.pairkernels import das_stacked_raw

        out = das_stacked_raw(X.y, X.we, i0.contiguous().numpy(), wt.contiguous().numpy(),
                              torch.view_as_real(rot.contiguous()).numpy(), X.segment)
        return torch.complex(*torch.from_numpy(out).to(self.model.dtype).unbind(1))

    def pixels(self, X, zi: torch.Tensor, xi: torch.Tensor, step: int = 32) -> torch.Tensor:
        """Exact compound image values at grid pixels (zi, xi) of one selection from its I/Q
        channels ``X`` (ntx, Ne, T) (or its :class:`RawChannels`): delay-and-sum with the cached
        block plans, as the exact path."""
        blocks, rows, order = pixel_blocks(zi.cpu(), xi.cpu(), self.model.block, self.model.setup.n_x)
        vals = self.das(X, blocks, rows, step)
        out = torch.empty_like(vals)
        out[torch.cat(order).to(vals.device)] = vals
        return out

    def e_plans(self) -> list:
        """DAS plan of the pixels of E (row-major), per transmit ``(i0, wt, rot)`` numpy arrays
        ((Npix_E, Ne) sample index local to the channel windows, interpolation weight, and
        (Npix_E, Ne, 2) phase rotation), made on first use and kept."""
        plans = self._e_plans
        if plans is None:
            model = self.model
            Z, X = torch.meshgrid(model.z_grid[self.layout.rows], model.x_grid[self.layout.cols], indexing="ij")
            plans = [(i0.to(torch.int32).contiguous().numpy(), w.to(model.dtype).contiguous().numpy(),
                      torch.view_as_real(rot.to(model.cdtype)).contiguous().numpy())
                     for i0, w, rot in window_plans(model, self.certificates.window_offset, X.reshape(-1),
                                                    Z.reshape(-1))]
            self._e_plans = plans
        return plans


    def window(self, x, z0: int, x0: int, grad: bool, step: int = 32) -> torch.Tensor:
        """The exact image (window, window) of one selection (I/Q channels ``x`` (ntx, Ne, T))
        on the kernel window at grid offset (z0, x0). A window inside E reads the DAS plan of E
        (:meth:`e_plans`, made once): the compiled sum without gradient (``grad`` False), torch's
        ``das_apply`` on the same plan rows with one; a window outside E goes through the block
        plans (:meth:`pixels`)."""
        n = self.model.setup.window
        ar = torch.arange(n)
        zi = (z0 + ar)[:, None].expand(n, n).reshape(-1)
        xi = (x0 + ar)[None, :].expand(n, n).reshape(-1)
        rows, cols = self.layout.rows, self.layout.cols
        if not (rows.start <= z0 and z0 + n <= rows.stop and cols.start <= x0 and x0 + n <= cols.stop):
            return self.pixels(x, zi, xi, step).reshape(n, n)
        pix = (zi - rows.start) * self.layout.shape[1] + (xi - cols.start)
        if grad:
            img = 0
            for t, (i0, wt, rot) in enumerate(self.e_plans()):
                img = img + das_apply(x[t], torch.from_numpy(i0)[pix].long().to(x.device),
                                      torch.from_numpy(wt)[pix].to(x.device),
                                      torch.view_as_complex(torch.from_numpy(rot)[pix]).to(x.device))
            return img.reshape(n, n)
        from arraysel.physics.pairkernels import das_plan_rows

        v = torch.from_numpy(das_plan_rows(torch.view_as_real(x.contiguous()).numpy(), self.e_plans(), pix.numpy()))
        return torch.complex(v[:, 0], v[:, 1]).to(x.dtype).reshape(n, n)
