"""Settling the selections the certificates alone do not: the certified kernel evaluation of the
fast path, the peak located among near-ties (settled from the core's exact pair images or by
delay-and-sum at the tied pixels), and loose blocks cleared by the strips' low-rank factors,
their exact pair images, or block-wise delay-and-sum.

:class:`Refinement` is a part of :class:`~arraysel.physics.psf.basis.PairBasis`
(``basis.refinement``); :meth:`PairBasis.kernels <arraysel.physics.psf.basis.PairBasis.kernels>`
runs its :meth:`Refinement.kernels`. Its inputs (constructor arguments):

* ``basis``, of which it reads this interface only: ``model`` (its public interface),
  ``layout``, the images (:meth:`~arraysel.physics.psf.basis.PairBasis.images`, ``band_images``,
  ``channels``, the pair products ``_pairs`` and the rounding allowance ``_rounding``), the
  stored ``strip_images``, ``strip_left``, ``strip_right``, ``strip_sigma``,
  ``strip_sigma_next`` and ``core_images``, and ``finer`` (the full-rank basis a truncated one
  retries on);
* ``certificates``, the basis's :class:`~arraysel.physics.psf.certificate.Certificates` (block
  bounds, envelopes, the pair channels and their windows);
* ``kernel_tol`` (default :attr:`Refinement.kernel_tol`);
* ``shared``: another basis's refinement whose caches and counts this one shares (a truncated
  view and the basis it comes from).

It owns ``kernel_tol``, the counts ``settled`` (kernels that reached each costly step since
the basis was made: ``"finer"``, the stored rank's tighter bound, and ``"exact_windows"``, their
window delay-and-summed exactly), ``exact`` (the
:class:`~arraysel.physics.psf.exactpixels.ExactPixels` that delay-and-sum a selection on chosen
pixels, with the caches of the block DAS plans and transmit distances and E's DAS plan), the
core's pixel positions and ``hot``, the
:class:`~arraysel.physics.psf.hotblocks.HotBlocks` that settle the blocks left loose again and
again from their pair matrices.
"""
from __future__ import annotations

import contextlib
import math

import torch

from arraysel.physics import compiled
from arraysel.physics.psf.certificate import RawChannels, largest_bound
from arraysel.physics.psf.exactpixels import ExactPixels
from arraysel.physics.psf.hotblocks import HotBlocks
from arraysel.physics.psf.window import cut_windows, window_start


def _runs(slots: torch.Tensor, most: int = 32) -> list[tuple[int, int]] | None:
    """``[(a, b), ...]``: the runs of consecutive values ``a .. b - 1`` of increasing ``slots``
    (None when they are not increasing or form more than ``most`` runs)."""
    s = slots.cpu()
    if s.numel() == 0 or not bool((s[1:] > s[:-1]).all()):
        return None
    cut = (torch.nonzero(s[1:] - s[:-1] != 1).flatten() + 1).tolist()
    if len(cut) >= most:
        return None
    starts = [0] + cut
    ends = cut + [s.numel()]
    return [(int(s[i]), int(s[j - 1]) + 1) for i, j in zip(starts, ends)]


def _windows(setup, pz, px, rows, cols):
    """Grid offsets (z0, x0) of the kernel windows of peaks (pz, px) and whether each fits in the
    region (rows, cols)."""
    z0 = window_start(pz, setup.window, setup.n_z)
    x0 = window_start(px, setup.window, setup.n_x)
    fits = (z0 >= rows.start) & (z0 + setup.window <= rows.stop) & (x0 >= cols.start) & \
        (x0 + setup.window <= cols.stop)
    return z0, x0, fits


def _envelope_scratch(pool: list, certificates, wd: torch.Tensor) -> torch.Tensor | None:
    """The memory the envelopes of a batch ``wd`` are written in (:func:`_batch_envelopes`): the
    last batch's, when it is large enough, taken from ``pool`` (a second thread finds it empty
    and gets memory of its own), else new; None (the envelopes' own memory) for a batch smaller
    than :data:`~arraysel.physics.compiled.MIN_BATCH` or off the CPU. The envelopes of a
    128-element scene's batch are about 150 MB: memory mapped afresh for every batch cost about
    0.3 CPU ms a mask in page faults."""
    if wd.shape[0] < compiled.MIN_BATCH or wd.device.type != "cpu":
        return None
    need = certificates.envelope_size(wd.shape[0])
    buf = pool.pop() if pool else None
    if buf is None or buf.numel() < need or buf.dtype != wd.dtype:
        buf = torch.empty(need, dtype=wd.dtype)
    return buf


@contextlib.contextmanager
def _batch_envelopes(refinement: "Refinement", wd: torch.Tensor, env: torch.Tensor | None):
    """``env``, or the envelopes of ``wd`` (no gradient) in memory of
    :func:`_envelope_scratch`, which goes back to ``refinement._env_pool`` on exit."""
    if env is not None:
        yield env
        return
    scratch = _envelope_scratch(refinement._env_pool, refinement.certificates, wd)
    try:
        with torch.no_grad():
            env = refinement.certificates.envelopes(wd, out=scratch)
        yield env
    finally:
        if scratch is not None and not refinement._env_pool:
            refinement._env_pool.append(scratch)


class Refinement:
    """Peak location, refinement and the certified kernels of a
    :class:`~arraysel.physics.psf.basis.PairBasis` (``basis.refinement``; its inputs and what it
    owns: see the module)."""

    def __init__(self, basis, certificates, kernel_tol: float | None = None, shared: "Refinement | None" = None):
        self.basis = basis
        self.model = basis.model
        self.layout = basis.layout
        self.certificates = certificates
        self.kernel_tol = self.kernel_tol if kernel_tol is None else float(kernel_tol)
        if shared is None:
            #: the exact values on chosen pixels and the DAS plans' caches (:class:`ExactPixels`)
            self.exact = ExactPixels(self.model, self.layout, certificates)
            self.settled = {"finer": 0, "exact_windows": 0}  #: kernels that reached each costly step
            self.hot = HotBlocks(self.model, certificates, self.exact.plans_for_blocks)
        else:
            self.exact, self.settled, self.hot = shared.exact, shared.settled, shared.hot
        self._plans_for_blocks = self.exact.plans_for_blocks  # block DAS plans, cached
        self._block_plans, self._block_dtx = self.exact.blocks, self.exact.dtx  # the plan caches
        self._core_pos = None  # E pixel -> its column among the core's (:meth:`_settle_in_core`)
        self._env_pool: list = []  # the memory of the last batch's envelopes (:func:`_envelope_scratch`)

    #: at most this many pixels tied with the peak (within the error bound) are settled exactly
    max_ties = 256

    #: largest bound of the relative L2 error of a fast-path kernel window (else: exact path);
    #: a sketched basis (large probes) carries the sketch's term in every bound and uses
    #: :attr:`~arraysel.physics.psf.basis.PairBasis.sketch_kernel_tol` instead
    kernel_tol = 5e-3

    #: at most this many blocks are beamformed exactly to settle a selection (else: exact path)
    refine_max_blocks = 1024

    #: grid blocks planned and delay-and-summed at once by :meth:`_das`
    das_blocks = 32

    def _das(self, X: torch.Tensor, blocks: list, rows: list | None = None) -> torch.Tensor:
        """Exact image values of one selection (I/Q channels X: (ntx, Ne, T) complex, or its
        :class:`RawChannels`) on the pixels of ``blocks`` ((qz, qx) pairs), or on the given pixel
        rows of each block's plan, :attr:`das_blocks` blocks at a time
        (:meth:`ExactPixels.das <arraysel.physics.psf.exactpixels.ExactPixels.das>`)."""
        return self.exact.das(X, blocks, rows, self.das_blocks)

    def strip_bounds(self, c: torch.Tensor, slots: torch.Tensor, slack: torch.Tensor | None = None) -> torch.Tensor:
        """(n, B) float64 upper bounds of ``max |I|`` on the whole strip blocks ``slots`` (their
        order in ``strip_images``) for pair products ``c`` (B, P), from the rank-r factors
        (:meth:`_strip_factors`): ``|(c SF) SG| + |c_perp| S_{r+1}`` plus rounding allowances."""
        if slack is None:
            slack = self.basis._rounding(c)
        bb = self.model.block ** 2
        sl = slots.to(c.device)
        runs = _runs(slots)
        if runs is None:
            cf = torch.matmul(c[None], self.basis.strip_left[sl])                              # (n, B, r)
            v = torch.matmul(cf, self.basis.strip_right[sl])
        else:
            # the factors of each run of consecutive slots read in place: gathering them copied
            # (n, P, r) floats, more than the products read; each run costs a little more, hence
            # at most 32 of them (``docs/performance.md``, "Tuning constants")
            cfs = [torch.matmul(c[None], self.basis.strip_left[a:b]) for a, b in runs]
            cf = torch.cat(cfs)
            v = torch.cat([torch.matmul(f, self.basis.strip_right[a:b]) for f, (a, b) in zip(cfs, runs)])
        v = v.view(sl.numel(), c.shape[0], 2, bb)
        peak = torch.addcmul(v[:, :, 1].square(), v[:, :, 0], v[:, :, 0]).amax(-1).sqrt()
        cw2 = (cf / self.basis.strip_sigma[sl][:, None, :]).square().sum(-1).double()
        cn2 = (c.double() ** 2).sum(1)[None]
        # |c_perp|, widened for the rounding of |c W_r|^2 (float32)
        cperp = ((cn2 - cw2).clamp(min=0) + 1e-6 * cn2).sqrt()
        # rounding of the two float32 products: 2 sqrt(P) u |c| S_1, on top of strip_images' own
        sigma = self.basis.strip_sigma[sl]
        rnd = 2 * math.sqrt(c.shape[1]) * torch.finfo(c.dtype).eps * cn2.sqrt() * sigma[:, :1].double()
        return peak.double() * (1 + 1e-4) + cperp * self.basis.strip_sigma_next[sl][:, None] + rnd + 2 * slack.double()

    def refine(self, w: torch.Tensor, threshold: torch.Tensor, env=None, tier: int = 2,
               bounds: torch.Tensor | None = None) -> torch.Tensor:
        """Settle selections whose certificate failed: (B,) True where the exact image on every
        block (outside E for tier 1, outside the band for tier 2) whose bound reaches
        ``threshold`` (the peak less its error bound) stays below it.

        Blocks wholly inside the strips (tier 1) take their values from the precomputed strip
        pair images, one small product per block for all selections at once (block-major
        columns of ``strip_images``); other blocks are delay-and-summed from the selection's I/Q
        channels (``basis.channels``). Either way a selection with a few loose blocks costs far
        less than a whole-grid exact image. ``env``: the envelopes of w; ``bounds``: its
        per-block bounds (``certificates.bound`` with ``per_block``), when the caller has them.
        """
        B = w.shape[0]
        out = torch.zeros(B, dtype=torch.bool)
        S = self.certificates.block_envelopes_e if tier == 1 else self.certificates.block_envelopes_band
        if S.shape[0] == 0 or B == 0:
            return out
        blocks = self.layout.blocks1 if tier == 1 else self.layout.blocks2
        w = w.detach()
        if bounds is None:
            bounds = self.certificates.bound(w, tier, per_block=True, env=env)
        clear = bounds < threshold[None]  # (nQ, B)
        strip = torch.zeros(S.shape[0], dtype=torch.bool)
        if tier == 1 and self.layout.npix2:
            # blocks wholly inside the strips: their pair images are precomputed (exact to rounding)
            col0 = self.layout.strip_block_col
            strip = col0 >= 0
            todo = torch.nonzero(strip & ~clear.all(1).cpu()).flatten()
            c = self.basis._pairs(w)
            slack = self.basis._rounding(c)
            bb = self.model.block ** 2
            if todo.numel():
                # first the rank-r factors: their bound below the threshold clears a block
                slot = col0[todo] // (2 * bb)
                for part in torch.split(torch.arange(todo.numel()), 256):
                    bound = self.strip_bounds(c, slot[part], slack)
                    clear[todo[part]] |= (bound * (1 + 1e-4) < threshold.double()[None]).to(clear.device)
                todo = todo[~clear[todo].all(1).cpu()]
            if todo.numel():
                limit = (threshold / (1 + 1e-4) - slack).square()
                # runs of blocks adjacent in strip_images (gaps of up to 2 blocks are computed too)
                slot = col0[todo] // (2 * bb)
                cut = torch.nonzero(slot[1:] - slot[:-1] > 3).flatten() + 1
                for run in torch.tensor_split(todo, cut.tolist()):
                    first, last = int(col0[run[0]]), int(col0[run[-1]]) + 2 * bb
                    v = (c @ self.basis.strip_images[:, first:last]).view(B, -1, 2, bb)
                    peak2 = torch.addcmul(v[:, :, 1].square(), v[:, :, 0], v[:, :, 0]).amax(2)  # (B, blocks)
                    at = (col0[run] - first) // (2 * bb)
                    clear[run] |= (peak2[:, at.to(peak2.device)] < limit[:, None]).T
        clear = clear.cpu()
        loose = {}  # selection -> its blocks to beamform
        for i in range(B):
            left = torch.nonzero(~clear[:, i]).flatten()
            if not left.numel():
                out[i] = True
            elif not bool(strip[left].any()) and left.numel() <= self.refine_max_blocks:
                loose[i] = left
            # else: a strip block reaches the peak, or too many blocks to beamform
        out[torch.tensor(self.hot.settle(w, loose, blocks, threshold), dtype=torch.long)] = True  # hot ones first
        for i, x in self._grouped_channels(w, list(loose), raw=True):
            img = self._das(x, [tuple(int(v) for v in blocks[q]) for q in loose[i].tolist()])
            out[i] = bool(img.abs().max() * (1 + 1e-4) < threshold[i])
        return out

    def _grouped_channels(self, w: torch.Tensor, index: list, raw: bool = False):
        """Yield ``(i, X)`` for each selection ``w[i]``, ``i`` in ``index`` (in order), with its
        I/Q channels X (ntx, Ne, T), formed :attr:`channel_group` selections at a time: one
        product with every pair channel per group (a whole batch's channels of a 256-element
        probe are about 1 GB). With ``raw`` (for :meth:`_das` only), on the CPU and without
        gradient, X is the product's :class:`RawChannels`, formed for the receive elements the
        group uses only (:meth:`_receive_products`; a group of one selection: its own). Per
        receive element's selections would cost more: a group's product is bound by reading
        ``pair_channels``, which the whole product reads once."""
        raw = raw and self.raw_channels and w.device.type == "cpu" and not w.requires_grad
        moved = self.certificates.moved_channels(w, index) if raw else None
        if moved is not None:  # neighbours of the selection being searched (Certificates.moved_channels)
            yield from moved
            return
        ne, ntx = self.model.n_elements, len(self.model.transmits)
        for g in range(0, len(index), self.channel_group):
            part = index[g:g + self.channel_group]
            wg = w[torch.tensor(part, dtype=torch.long, device=w.device)]
            if not raw:
                yield from zip(part, self.basis.channels(wg))
                continue
            shape = (len(part), ne, 2, ntx, self.certificates.window_samples)
            if bool((wg != 0).any(0).all()):
                y = (wg @ self.certificates.pair_channels).view(shape)  # every receive element is used
            else:
                y = torch.empty(shape, dtype=wg.dtype)
                for e0, e1, _, ys in self.certificates._receive_products(wg, subsets=False):
                    y[:, e0:e1] = ys
            y = y.numpy()
            we = wg.numpy().astype(y.dtype)
            yield from ((i, RawChannels(y[k], we[k], self.certificates.segment)) for k, i in enumerate(part))

    def _locate(self, img: torch.Tensor, eps: torch.Tensor, w: torch.Tensor, row0: int, col0: int):
        """Peak pixel of the exact image, from an approximation ``img`` (B, h, wd) at grid offset
        (row0, col0) whose |.| error is at most ``eps`` (B,).

        Every pixel within 2 eps of the approximate peak may be the exact peak: those are
        evaluated exactly (:meth:`ExactPixels.pixels
        <arraysel.physics.psf.exactpixels.ExactPixels.pixels>`) and the largest wins (the first in row-major
        order, as ``argmax`` on the exact image). Returns the peak's grid row and column, a lower
        bound ``thr`` of the exact peak value and a flag (False: more than :attr:`max_ties` ties,
        or an all-zero image).
        """
        B, h, wd = img.shape
        with torch.no_grad():
            if B >= compiled.MIN_BATCH and img.device.type == "cpu" and img.dtype in (torch.complex64,
                                                                                      torch.complex128):
                # one compiled read of each image (a batch of at least MIN_BATCH)
                from arraysel.physics.peakkernels import peak_stats

                two_eps = 2 * eps.detach().cpu().double()
                val, arg, n, cand = (torch.from_numpy(a) for a in peak_stats(
                    torch.view_as_real(img.detach().resolve_conj()).reshape(B, -1, 2).numpy(), two_eps.numpy()))
            else:
                mag = img.detach().abs().reshape(B, -1)
                val, arg = mag.max(dim=1)
                cand = mag >= (val - 2 * eps)[:, None]
                n = cand.sum(dim=1)
            ok = (val > 0) & (n <= self.max_ties)
            amb = torch.nonzero(ok & (n > 1)).flatten()
            if amb.numel():
                arg = arg.clone()
                if (h, wd) == self.layout.shape and (row0, col0) == (self.layout.rows.start, self.layout.cols.start):
                    amb = self._settle_in_core(cand, amb, arg, w)
            for b, x in self._grouped_channels(w.detach(), amb.tolist(), raw=True):
                idx = torch.nonzero(cand[b]).flatten()
                v = self.exact.pixels(x, idx // wd + row0, idx % wd + col0, self.das_blocks).abs()
                arg[b] = idx[int(torch.argmax(v))]
        return arg // wd + row0, arg % wd + col0, val - eps, ok

    def _settle_in_core(self, cand: torch.Tensor, amb: torch.Tensor, arg: torch.Tensor, w: torch.Tensor):
        """Settle the near-ties ``cand`` (B, npix) on E of the selections ``amb`` whose candidates
        all lie in the core, from the core's exact pair images (one product for all of them);
        writes their peak index into ``arg`` and returns the selections left (candidates
        outside the core)."""
        pos = self._core_pos
        if pos is None or pos.device != cand.device:
            pos = torch.full((self.layout.npix,), -1, dtype=torch.long)
            pos[self.layout.core_pix] = torch.arange(self.layout.core_pix.numel())
            pos = self._core_pos = pos.to(cand.device)
        ca = cand[amb]
        inside = ~(ca & (pos < 0)[None]).any(1)
        sel = amb[inside]
        if sel.numel():
            union = torch.nonzero(ca[inside].any(0)).flatten()
            cols = pos[union]
            nc = self.basis.core_images.shape[1] // 2
            v = self.basis._pairs(w[sel].detach()) @ self.basis.core_images[:, torch.cat([cols, cols + nc])]
            nu = union.numel()
            mag2 = torch.addcmul(v[:, nu:].square(), v[:, :nu], v[:, :nu])
            mag2 = torch.where(ca[inside][:, union], mag2, torch.full_like(mag2, -1.0))
            arg[sel] = union[mag2.argmax(dim=1)]
        return amb[~inside]

    def kernels(self, w: torch.Tensor, env: torch.Tensor | None = None, images: tuple | None = None,
                tier_one: bool = False):
        """Kernels (B, win, win) and a (B,) bool tensor: True where certified (else recompute).
        ``env``: the envelopes of ``w`` (``certificates.envelopes``), ``images``: its images on E
        with their error bounds (``basis.images`` with ``with_error``), when the caller has them
        (one-swap neighbours: ``certificates.swap_envelopes``, ``basis.swap_images``).
        ``tier_one``: return after tier 1 (True then marks the kernels that are windows of
        ``images``, which :mod:`arraysel.objective.pair_model` differentiates).

        Certified: the exact peak is located (pixels tied with the approximate peak within the
        error bound are evaluated exactly), its window fits in the region, and the lower bound of
        the peak beats the bound of |I| outside the region (tier 1: E; tier 2: the band, whose
        loose blocks are then beamformed exactly, :meth:`refine`); in steps, :meth:`_tier_one`
        to :meth:`_exact_rest`."""
        wd = w.detach()
        with _batch_envelopes(self, wd, env) as env:  # not read past tier 2
            img, eps, win_err = self.basis.images(w, with_error=True) if images is None else images
            out, ok, peaks = self._tier_one(w, wd, env, img, eps, win_err)
            if tier_one:
                return out, ok.cpu()
            out, ok = self._tier_two(w, wd, env, img, eps, win_err, out, ok, peaks)
        if self.basis.finer is not None:
            out, ok = self._finer_windows(w, out, ok, peaks)
        out, ok = self._finer_kernels(w, out, ok, peaks)
        return self._exact_rest(w, out, ok, peaks)

    def _tier_one(self, w, wd, env, img, eps, win_err):
        """Tier 1 of :meth:`kernels`: ``(out, ok, peaks)``, the windows of ``img`` whose peak the
        bound outside E certifies (:meth:`refine` retrying those the largest bound does not) and
        whose window fits in E within :attr:`kernel_tol`, and ``peaks`` = ``(located, win_z,
        win_x)``: the selections whose peak is certified and their windows' grid offsets (-1
        elsewhere), whether or not the window fits in E (tier 2 adds its own)."""
        s = self.model.setup
        pz, px, thr, ok = self._locate(img, eps, w, self.layout.rows.start, self.layout.cols.start)
        z0, x0, fits = _windows(s, pz, px, self.layout.rows, self.layout.cols)
        with torch.no_grad():
            # the per-block bounds serve the peaks that the largest of them does not certify too
            # (forming them again for those selections, from a copy of their envelopes' columns,
            # cost more than the first time)
            bounds = self.certificates.bound(wd, 1, per_block=True, env=env)
            passed = ok & (largest_bound(bounds) < thr)
            retry = torch.nonzero(ok & ~passed).flatten()
            if retry.numel():
                passed[retry] = self.refine(wd[retry], thr[retry], tier=1, bounds=bounds[:, retry]).to(passed.device)
            # the window of every selection whose peak is certified (tier 1 here, tier 2 below),
            # whether or not the window fits in E
            located, win_z, win_x = passed.clone(), torch.where(passed, z0, -1), torch.where(passed, x0, -1)
            ok = passed & fits
        z0e = torch.where(ok, z0 - self.layout.rows.start, torch.zeros_like(z0))
        x0e = torch.where(ok, x0 - self.layout.cols.start, torch.zeros_like(x0))
        out, norm = cut_windows(img, z0e, x0e, s.window)
        ok = ok & (win_err <= self.kernel_tol * norm)
        return out, ok, (located, win_z, win_x)

    def _tier_two(self, w, wd, env, img, eps, win_err, out, ok, peaks):
        """Tier 2 (the band) of :meth:`kernels` for the selections whose peak tier 1 could not
        certify; writes the peaks it certifies into ``peaks``. A certified peak whose window
        leaves E or whose error bound is too loose gets an exact window later (cheaper than the
        band's product, which reads every strip pair image, and exact)."""
        s = self.model.setup
        located, win_z, win_x = peaks
        todo = torch.nonzero(~ok & ~located).flatten()
        if not (todo.numel() and self.layout.npix2):
            return out, ok
        w2 = w[todo]
        band = self.basis.band_images(w2, img[todo])
        pz2, px2, thr2, ok2 = self._locate(band, eps[todo], w2, self.layout.rows.start, 0)
        z02, x02, fits2 = _windows(s, pz2, px2, self.layout.rows, slice(0, s.n_x))
        with torch.no_grad():
            ok2 = ok2 & fits2
            bounds = self.certificates.bound(wd[todo], 2, per_block=True, env=env[:, todo])
            passed = ok2 & (largest_bound(bounds) < thr2)
            retry = torch.nonzero(ok2 & ~passed).flatten()
            if retry.numel():
                passed[retry] = self.refine(wd[todo][retry], thr2[retry], bounds=bounds[:, retry]).to(passed.device)
        with torch.no_grad():
            sel = torch.nonzero(passed).flatten()
            located[todo[sel]] = True
            win_z[todo[sel]], win_x[todo[sel]] = z02[sel], x02[sel]
        z0b = torch.where(passed, z02 - self.layout.rows.start, torch.zeros_like(z02))
        k2, norm2 = cut_windows(band, z0b, torch.where(passed, x02, torch.zeros_like(x02)), s.window)
        passed = passed & (win_err[todo] <= self.kernel_tol * norm2)
        sel = torch.nonzero(passed).flatten()
        if sel.numel():
            out = out.index_put((todo[sel],), k2[sel])
            ok = ok.clone()
            ok[todo[sel]] = True
        return out, ok

    def _finer_windows(self, w, out, ok, peaks):
        """Located, only the error bound too loose: the full stored rank's tighter bound
        (``basis.finer``), on the certified window (when it lies in E)."""
        located, win_z, win_x = peaks
        n, rows, cols = self.model.setup.window, self.layout.rows, self.layout.cols
        inside = ~ok & located & (win_z >= rows.start) & (win_z + n <= rows.stop) & \
            (win_x >= cols.start) & (win_x + n <= cols.stop)
        todo = torch.nonzero(inside).flatten()
        if todo.numel():
            img_f, _, werr_f = self.basis.finer.images(w[todo], with_error=True)
            k_f, norm_f = cut_windows(img_f, win_z[todo] - rows.start, win_x[todo] - cols.start, n)
            sel = torch.nonzero(werr_f <= self.kernel_tol * norm_f).flatten()
            self.settled["finer"] += todo.numel()
            if sel.numel():
                out = out.index_put((todo[sel],), k_f[sel].to(out.dtype))
                ok = ok.clone()
                ok[todo[sel]] = True
        return out, ok

    def _finer_kernels(self, w, out, ok, peaks):
        """Not located: a tighter error bound (the full stored rank, ``basis.finer``) settles
        most of the rest."""
        located = peaks[0]
        todo = torch.nonzero(~ok & ~located).flatten()
        if todo.numel() and self.basis.finer is not None:
            k3, ok3 = self.basis.finer.kernels(w[todo])
            sel = torch.nonzero(ok3.to(todo.device)).flatten()
            self.settled["finer"] += todo.numel()
            if sel.numel():
                out = out.index_put((todo[sel],), k3[sel])
                ok = ok.clone()
                ok[todo[sel]] = True
        return out, ok

    def _exact_rest(self, w, out, ok, peaks):
        """The peak and its window are certified and only the image's error bound is too loose:
        the window itself is delay-and-summed exactly from the selection's channels (at most
        :attr:`exact_windows_max` of them). Returns :meth:`kernels`' result."""
        located, win_z, win_x = peaks
        todo = torch.nonzero(~ok & located).flatten()
        if todo.numel() and todo.numel() <= self.exact_windows_max:
            out = out.index_put((todo,), self._exact_windows(w[todo], win_z[todo], win_x[todo]).to(out.dtype))
            self.settled["exact_windows"] += todo.numel()
            ok = ok.clone()
            ok[todo] = True
        return out, ok.cpu()

    #: most selections of one batch whose windows are beamformed exactly (:meth:`_exact_windows`);
    #: each costs a window's delay-and-sum, a fraction of the whole-grid exact path's
    exact_windows_max = 4096
    #: block delay-and-sums without gradient read :class:`RawChannels` (False: the complex channels
    #: of ``basis.channels``, the same values; ``benchmarks/bench_certificate.py`` compares the two)
    raw_channels = True
    #: memory (bytes) of the channels of the selections formed at once (:meth:`_grouped_channels`, for
    #: :meth:`_exact_windows`, :meth:`refine` and :meth:`_locate`): each group reads all of ``pair_channels``,
    #: so larger groups cost less per selection (``docs/performance.md``, "Tuning constants")
    channel_group_bytes = 192 << 20

    @property
    def channel_group(self) -> int:
        """Selections whose channels are formed at once (from :attr:`channel_group_bytes`)."""
        per = 2 * len(self.model.transmits) * self.model.n_elements * self.certificates.window_samples * \
            (torch.finfo(self.model.dtype).bits // 8)
        return max(1, self.channel_group_bytes // per)

    def _exact_windows(self, w: torch.Tensor, z0: torch.Tensor, x0: torch.Tensor) -> torch.Tensor:
        """Kernels (B, window, window) of selections ``w`` from the exact image on their windows at
        grid offsets (z0, x0) (delay-and-sum of their I/Q channels, as the exact path;
        differentiable, :meth:`ExactPixels.window <arraysel.physics.psf.exactpixels.ExactPixels.window>`),
        normalised as :func:`cut_windows` does."""
        n = self.model.setup.window
        grad = w.requires_grad or w.device.type != "cpu"
        wins = [self.exact.window(x, int(z0[i]), int(x0[i]), grad, self.das_blocks)
                for i, x in self._grouped_channels(w, list(range(w.shape[0])))]
        win = torch.stack(wins)
        zero = torch.zeros(w.shape[0], dtype=torch.long)
        return cut_windows(win, zero, zero, n)[0]
