"""Building the fast path's pair basis: the samples each block reads, the windowed pair I/Q
signals, the pair images and their compression (exact Gram or randomised sketch), and the
low-rank factors of the strip blocks.

:class:`BasisBuilder` is the build part of :class:`~arraysel.physics.psf.basis.PairBasis`: an
object made from its inputs alone (the model, the layout and the envelope segment) whose steps
return what they make (sample ranges, pair I/Q, a :class:`Compression`, :class:`StripFactors`)
for :meth:`PairBasis.build <arraysel.physics.psf.basis.PairBasis.build>` to keep. It reads from
the model only its public interface (``setup``, ``n_elements``, ``transmits``, ``x_grid``,
``z_grid``, ``block``, ``dtype``, ``device``) and from the layout ``rows``, ``cols``, ``shape``,
``npix``, ``pairs_e``, ``core_pix`` and ``strip_block_col``. :func:`window_plans` (the DAS plans
local to the channel windows) serves the refinement too.
"""
from __future__ import annotations

import logging
import math
import time
from typing import NamedTuple

import numpy as np
import torch

from arraysel.physics.beamform import das_plan

_log = logging.getLogger(__name__)


def pixel_norms(H: torch.Tensor) -> torch.Tensor:
    """Norm over pairs of each pixel's complex column of a (P, 2 Npix) [re | im] matrix: (Npix,)."""
    n = H.shape[1] // 2
    return ((H[:, :n] ** 2).sum(0) + (H[:, n:] ** 2).sum(0)).sqrt()


def combined_tail(sigma_next: float, missed: float) -> float:
    """Bound of the spectral norm of ``(I - U U^T) H`` for ``U = Q W_r``: the residual of a
    selection ``r = (I - Q Q^T) c + Q (I - W_r W_r^T) Q^T c`` splits into two orthogonal parts,
    one seen by what the sketch missed (``|(I - Q Q^T) H|_2 <= missed``), one by the next
    singular value of ``Q^T H``; by Cauchy-Schwarz the error ``|r^T H|`` is at most
    ``|r| sqrt(sigma_next^2 + missed^2)``."""
    return math.hypot(sigma_next, missed) * (1 + 1e-6)


def _tile_pixels(shape: tuple[int, int], tile: int) -> list[torch.Tensor]:
    """Pixel indices (row-major in an image of ``shape`` (h, w)) of each ``tile`` x ``tile``
    tile, tiles in row-major order (those cut by the edge hold fewer pixels)."""
    h, w = shape
    idx = torch.arange(h * w).reshape(h, w)
    return [idx[z:z + tile, x:x + tile].flatten() for z in range(0, h, tile) for x in range(0, w, tile)]


def _tile_rows(G: torch.Tensor, npix: int) -> torch.Tensor:
    """The [re | im] columns of the pixels ``G`` in a (., 2 npix) [re | im] matrix."""
    return torch.cat([G, npix + G])


def _row_gram(A: torch.Tensor) -> torch.Tensor:
    """``A A^T`` of a float64 (m, n) tensor, by a symmetric rank-k update (half the work of a
    product: BLAS ``dsyrk``, on ``A`` read in whichever memory order it is stored)."""
    from scipy.linalg.blas import dsyrk

    if A.T.is_contiguous():  # column-major already (a transposed view): no copy
        upper = dsyrk(1.0, A.T.numpy().T, trans=0)
    else:
        upper = dsyrk(1.0, A.contiguous().numpy().T, trans=1)
    upper = torch.from_numpy(upper)  # only the upper triangle is formed
    return upper + upper.triu(1).T


def _padded_gram(Ht: torch.Tensor, size: int) -> torch.Tensor:
    """``Ht Ht^T`` (a group's Gram matrix from its columns given as rows) in the top-left corner
    of a (size, size) zero matrix: zero rows and columns change neither eigenvalues nor trace."""
    g = _row_gram(Ht)
    return torch.nn.functional.pad(g, (0, size - g.shape[0], 0, size - g.shape[0]))


def _tile_grams(H: torch.Tensor, shape: tuple[int, int], tile: int) -> torch.Tensor:
    """(ntiles, 2 tile^2, 2 tile^2) Gram matrices ``H_G^T H_G`` of the float64 rows ``H``
    (rows, 2 h w) [re | im] of images of ``shape`` (h, w), one per ``tile`` x ``tile`` tile of
    pixels G (:func:`_tile_pixels`): its real then imaginary columns, zero-padded."""
    npix = shape[0] * shape[1]
    Ht = H.T
    return torch.stack([_padded_gram(Ht[_tile_rows(G, npix)], 2 * tile * tile) for G in _tile_pixels(shape, tile)])


def _missed_spectral(grams: torch.Tensor, grams_b: torch.Tensor, pairs: int, sketch: int) -> float:
    """Rigorous bound of ``|R|_2``, ``R = (I - Q Q^T) H`` the part of the pair images a sketch
    ``Q`` missed, from the Gram matrices of pixel groups G (a partition of the columns):
    ``R R^T = sum_G R_G R_G^T`` gives ``|R|_2^2 <= sum_G lambda_max(R_G^T R_G)`` with
    ``R_G^T R_G = H_G^T H_G - B_G^T B_G`` (``B = Q^T H``). Each group's rounding (the two
    float64 Gram sums over ``pairs`` and ``sketch`` terms, Q's departure from orthonormality,
    the eigensolver) is covered by ``1e-12 + 2 (pairs + sketch) u`` times its trace. Far tighter
    than the Frobenius norm when the missed part spreads over many directions of each group."""
    u = torch.finfo(torch.float64).eps
    diff = grams - grams_b
    diff = (diff + diff.transpose(1, 2)) / 2
    lam = torch.linalg.eigvalsh(diff)[:, -1]
    trace = grams.diagonal(dim1=1, dim2=2).sum(-1)
    slack = (1e-12 + 2 * (pairs + sketch) * u) * trace
    return math.sqrt(float((lam + slack).clamp(min=0).sum())) * (1 + 1e-6)


def _sketch(tile_images, npix: int, P: int, columns: int) -> torch.Tensor:
    """``Y^T`` (L, P) float64: the sparse sign sketch ``Y = H S`` of the pair images (P pairs,
    ``npix`` pixels of E), ``L`` = ``columns`` (at most ``2 npix``) columns, read a tile at a time
    from ``tile_images()`` (:meth:`BasisBuilder._tile_images`)."""
    from arraysel.physics.pairkernels import sparse_sketch_add

    # sparse sign sketch: each real column of H adds, with a random sign, to ``zeta``
    # random columns of the sketch (a sparse random embedding, applied a tile of pixels at
    # a time in ``zeta P`` adds a column; on the built-in probes it misses as little as the
    # earlier randomised Fourier sketch, and what it misses is bounded exactly below)
    L = min(columns, 2 * npix)
    zeta = min(8, L)
    gen = torch.Generator().manual_seed(20261124)
    hit = torch.randint(L, (2 * npix, zeta), generator=gen)
    sign = torch.where(torch.rand(2 * npix, zeta, generator=gen, dtype=torch.float64) < 0.5, -1.0, 1.0)
    sign /= math.sqrt(zeta)
    # the sketch only has to span the dominant subspace (what it misses is measured exactly
    # below), so it is accumulated in float32
    Yt = torch.zeros(L, P, dtype=torch.float32)
    for G, Ht in tile_images():
        rows = _tile_rows(G, npix)
        sparse_sketch_add(Yt.numpy(), Ht.contiguous().numpy(), hit[rows].numpy(), sign[rows].numpy())
    return Yt.double()


def _project(Q: torch.Tensor, tile_images, tiles, core: torch.Tensor, npix: int, P: int, tile: int):
    """The second pass over the pair images' tiles (``tile``-sided, P pairs, ``npix`` pixels of
    E): ``B^T = H^T Q`` (2 Npix, L), the pixels' squared column norms (Npix,), the ``core``
    columns of ``H`` (P, 2 ncore), the tiles' Gram matrices and the seconds spent on them."""
    Bt = torch.zeros(2 * npix, Q.shape[1], dtype=torch.float64)  # B^T = H^T Q
    col2 = torch.zeros(npix, dtype=torch.float64)
    Hc = torch.empty(P, core.numel(), dtype=torch.float64)
    in_core = torch.full((2 * npix,), -1, dtype=torch.long)
    in_core[core] = torch.arange(core.numel())
    m = 2 * tile * tile
    grams = torch.zeros(len(tiles), m, m, dtype=torch.float64)
    gram_s = 0.0
    prod = torch.empty(2 * max(G.numel() for G in tiles), Q.shape[1], dtype=torch.float64)
    for t, (G, Ht) in enumerate(tile_images()):
        rows = _tile_rows(G, npix)
        Bt[rows] = torch.matmul(Ht, Q, out=prod[:Ht.shape[0]])
        at = in_core[rows]
        Hc[:, at[at >= 0]] = Ht[at >= 0].T
        t0 = time.perf_counter()
        grams[t] = _padded_gram(Ht, m)
        gram_s += time.perf_counter() - t0
        # the pixels' squared column norms: the Gram matrix's diagonal
        g = G.numel()
        d = grams[t].diagonal()
        col2[G] = d[:g] + d[g:2 * g]
    return Bt, col2, Hc, grams, gram_s


def window_plans(model, window_offset: torch.Tensor, X: torch.Tensor, Z: torch.Tensor,
                 dtx: torch.Tensor | None = None):
    """Yield, transmit by transmit (so that callers converting them hold one float64 plan at a
    time), the DAS plan ``(i0, w, rot)`` ((Npix, Ne) each, float64) of ``model``'s pixels at (X,
    Z) with sample indices local to the channel windows starting at ``window_offset`` (ntx, Ne)
    (:meth:`BasisBuilder.sample_ranges`; 0 where the rotation is 0: outside the aperture or the
    record). ``dtx`` (ntx, Npix): the pixels' transmit distances, if known."""
    s = model.setup
    for n, t in enumerate(model.transmits):
        p = das_plan(X, Z, t.delays, s.probe, s.acq.fs, s.acq.c, t.grid.n_time, fnumber=s.fnumber,
                     fc=s.probe.fc, dtx=None if dtx is None else dtx[n])
        i0 = torch.where(p.rot.abs() > 0, p.i0 - window_offset[n][None, :], torch.zeros_like(p.i0))
        yield i0, p.w, p.rot


class Compression(NamedTuple):
    """The truncated SVD ``H ~ U V`` of the pair images ``H`` (P, 2 Npix) on E (:meth:`BasisBuilder.compress`)."""

    #: (P, rank) orthonormal, or None when no compression pays (then ``V`` is ``H`` itself)
    U: torch.Tensor | None
    #: (rank, 2 Npix) ``U^T H`` (or ``H``)
    V: torch.Tensor
    rank: int
    #: energy fraction of ``H`` the truncation discards
    rank_tail: float
    #: largest residual pixel-column norm ``max_p |(I - U U^T) H_p|`` (exact, from ``|H_p|^2 - |V_p|^2``)
    pixel_residual: float
    #: largest pixel-column norm of ``H``
    column_norm: float
    #: rigorous bound of the spectral norm of ``(I - U U^T) H`` (the next singular value,
    #: combined with what a sketch missed by :func:`combined_tail`)
    spectral_tail: float
    #: bound of the spectral norm of what the sketch missed, ``|(I - Q Q^T) H|_2`` (the smaller
    #: of its Frobenius norm and the pixel-group bound of :func:`_missed_spectral`; 0 for the
    #: exact build)
    missed: float
    #: (P, 2 ncore) the pair images of the core pixels ([re | im])
    core_images: torch.Tensor


class StripFactors(NamedTuple):
    """Per-block rank-``strip_rank`` factors of the strips' pair images (:meth:`BasisBuilder.strip_factors`)."""

    #: (nw, P, r) ``W_r S_r`` of each whole strip block
    left: torch.Tensor
    #: (nw, r, 2 b^2) ``Z_r^T``
    right: torch.Tensor
    #: (nw, r) ``S_r``
    sigma: torch.Tensor
    #: (nw,) float64, a safe upper bound of ``S_{r+1}``
    sigma_next: torch.Tensor


class BasisBuilder:
    """The precomputation steps of a :class:`~arraysel.physics.psf.basis.PairBasis` (see the
    module), for ``model`` on ``layout``; :meth:`PairBasis.build
    <arraysel.physics.psf.basis.PairBasis.build>` runs them in order and keeps what they return.

    It owns only the channel windows it finds (:meth:`sample_ranges`: ``window_offset``,
    ``window_samples``), which the later steps read; ``segment`` is the certificates' envelope
    segment, a divisor of the window length.
    """

    #: rank of the per-block factors of the strip pair images (:meth:`strip_factors`)
    strip_rank = 16

    def __init__(self, model, layout, segment: int):
        self.model = model
        self.layout = layout
        self.segment = int(segment)
        #: (ntx, Ne) first record sample of each channel's window, and the windows' length
        #: (:meth:`sample_ranges`)
        self.window_offset: torch.Tensor | None = None
        self.window_samples: int | None = None

    def strip_factors(self, H2: torch.Tensor) -> StripFactors:
        """Rank-``strip_rank`` factors of the pair images of every whole strip block (block-major
        ``H2`` in float64): ``M_q = W S Z^T`` (SVD from the 2 b^2 x 2 b^2 Gram matrix) gives
        ``SF[q] = W_r S_r`` (P, r), ``SG[q] = Z_r^T`` (r, 2 b^2), ``SS[q] = S_r`` and ``Snext[q]``
        (a safe upper bound of ``S_{r+1}``). Then ``|c M_q - (c SF) SG|`` at a pixel is at most
        ``|c_perp| Snext`` with ``|c_perp|^2 = |c|^2 - |(c SF) / SS|^2``: a cheap, rigorous bound of
        a block's image that clears most loose blocks without reading its ``2 b^2`` columns."""
        model = self.model
        bb2 = 2 * model.block ** 2
        nw = int((self.layout.strip_block_col >= 0).sum())
        r = min(self.strip_rank, bb2)
        P = H2.shape[0]
        if nw == 0:
            return StripFactors(left=torch.zeros(0, P, r, dtype=model.dtype, device=model.device),
                                right=torch.zeros(0, r, bb2, dtype=model.dtype, device=model.device),
                                sigma=torch.zeros(0, r, dtype=model.dtype, device=model.device),
                                sigma_next=torch.zeros(0, dtype=torch.float64, device=model.device))
        SF, SG, SS, SN = [], [], [], []
        for q0 in range(0, nw, 64):
            q1 = min(nw, q0 + 64)
            M = H2[:, q0 * bb2:q1 * bb2].reshape(P, q1 - q0, bb2).permute(1, 0, 2)  # (n, P, 2b^2)
            gram = M.transpose(1, 2) @ M
            evals, evecs = torch.linalg.eigh(gram)
            evals, evecs = evals.flip(-1).clamp(min=0), evecs.flip(-1)
            sig = evals.sqrt()
            Z = evecs[:, :, :r]
            SF.append(M @ Z)                                   # W_r S_r
            SG.append(Z.transpose(1, 2))
            SS.append(sig[:, :r])
            # eigenvalues of the Gram matrix are accurate to ~eps * sigma_1^2
            tail = sig[:, r] if r < bb2 else torch.zeros_like(sig[:, 0])
            SN.append((tail * (1 + 1e-6) + 1e-7 * sig[:, 0]))
        return StripFactors(left=torch.cat(SF).to(model.device, model.dtype),
                            right=torch.cat(SG).to(model.device, model.dtype),
                            sigma=torch.cat(SS).to(model.device, model.dtype),
                            sigma_next=torch.cat(SN).to(model.device))

    # -- sample ranges and windowed pair I/Q -------------------------------------------------
    def sample_ranges(self):
        """Samples read by the grid's pixels, block by block, from the block centres.

        The transmit distance (a minimum of 1-Lipschitz distances) and each receive distance
        are 1-Lipschitz in the pixel position, so over a block of half-diagonal ``r`` the
        sample position ``(d_TX + d_RX) fs / c`` of a pixel lies within ``2 r fs / c`` of the
        centre's: the ranges below contain every sample a pixel of the block reads (they may
        hold a sample or two more, which only loosens the bounds). Channels outside the
        f-number aperture are kept (a bound only grows).

        Returns ``lo``, ``hi`` (ntx, nbz, nbx, Ne): per block and (transmit, element) the
        first and last sample index a pixel may read (``hi < lo`` where none can), and sets
        ``window_offset`` (ntx, Ne): the first sample of each channel's window, and
        ``window_samples``: the window length (a multiple of :attr:`segment`). Every sample any grid pixel reads lies in
        ``[window_offset, window_offset + window_samples - 1]``, so channels are kept, precomputed and enveloped on that window
        only (its length follows the grid, not the record)."""
        from arraysel.physics.beamform import transmit_distance

        model = self.model
        s = model.setup
        b = model.block
        nbz, nbx = -(-s.n_z // b), -(-s.n_x // b)
        p = s.pitch
        zc = float(model.z_grid[0]) + (torch.arange(nbz, dtype=torch.float64) * b + (b - 1) / 2) * p
        xc = float(model.x_grid[0]) + (torch.arange(nbx, dtype=torch.float64) * b + (b - 1) / 2) * p
        Z, X = torch.meshgrid(zc, xc, indexing="ij")
        r = math.sqrt(2) * (b - 1) / 2 * p
        xe, ze, _, _ = s.probe.element_positions()
        drx = torch.sqrt((X[..., None] - torch.as_tensor(xe)) ** 2 + (Z[..., None] - torch.as_tensor(ze)) ** 2)
        slack = 2 * r * s.acq.fs / s.acq.c + 1e-9
        los, his = [], []
        for t in model.transmits:
            dtx = transmit_distance(X, Z, t.delays, s.probe, s.acq.c)
            pos = (dtx[..., None] + drx) / s.acq.c * s.acq.fs
            lo = torch.floor(pos - slack).clamp(min=0)
            hi = torch.floor(pos + slack) + 1
            n_t = t.grid.n_time
            can = (pos + slack >= 0) & (pos - slack <= n_t - 2)
            hi = hi.clamp(max=n_t - 1)
            los.append(torch.where(can, lo, torch.full_like(lo, 1 << 40)).long())
            his.append(torch.where(can, hi, torch.full_like(hi, -1)).long())
        lo, hi = torch.stack(los), torch.stack(his)  # (ntx, nbz, nbx, Ne)
        first = lo.amin(dim=(1, 2))
        last = hi.amax(dim=(1, 2))
        read = last >= first
        self.window_offset = torch.where(read, first, torch.zeros_like(first))
        span = int(torch.where(read, last - first + 1, torch.ones_like(first)).max())
        self.window_samples = -(-max(span, 2) // self.segment) * self.segment
        return lo, hi

    def windowed_pair_iq(self) -> np.ndarray:
        """I/Q of every (rx e, tx j) pair on each channel's window: ``X[n, e, t, 0 | 1, j]``
        (ntx, Ne, T, 2, Ne) float32, the real | imaginary part of sample ``off[n, e] + t`` of the
        record (zero past its end).

        The RF spectrum of a pair is the product ``RC_e(f) G_nj(f)``, and its I/Q signal (inverse
        FFT, mixing, zero-phase Butterworth low-pass, factor 2) is one linear map of it, the exact
        path's own composed spectra -> I/Q map (:meth:`Transmit.iq_map`, float64). Applying it
        to the window's samples only, receive elements in groups (one batched product each),
        costs ``Ne^2 F T_window`` per transmit instead of a filter over the whole record for
        each of the ``Ne^2`` pairs."""
        model = self.model
        ne = model.n_elements
        ntx = len(model.transmits)
        Tw = self.window_samples
        out = np.zeros((ntx, ne, Tw, 2, ne), dtype=np.float32)
        ar = torch.arange(Tw)
        for n, t in enumerate(model.transmits):
            # the record's samples some channel's window reads: [lo, lo + T)
            lo = int(self.window_offset[n].min())
            T = max(1, min(t.grid.n_time, int(self.window_offset[n].max()) + Tw) - lo)
            # the products run in the model's dtype (float64 for a float64 model)
            M = t.iq_map(slice(lo, lo + T)).to(model.dtype)  # (2F, 2T)
            F = M.shape[0] // 2
            # zero column at index 2T: samples past the end of the record
            M = torch.cat([M, M.new_zeros(2 * F, 1)], dim=1)
            Mt = M.T.contiguous()                            # (2T + 1, 2F)
            tx = t.tx_field.to(model.cdtype)                 # (Ne, F), transmit j
            rx = t.rx_factor.to(model.cdtype)                # (Ne, F), receive e
            step = max(1, 2 ** 22 // (ne * F))
            for e0 in range(0, ne, step):
                e1 = min(ne, e0 + step)
                s_ = rx[e0:e1, None, :] * tx[None, :, :]     # (ce, Ne, F)
                lhs = torch.cat([s_.real, s_.imag], dim=2)   # (ce, Ne, 2F)
                idx = self.window_offset[n, e0:e1, None] - lo + ar[None, :]  # (ce, Tw)
                idx = torch.where(idx < T, idx, torch.full_like(idx, 2 * T))
                cols = torch.cat([idx, torch.where(idx < T, idx + T, idx)], dim=1)  # (ce, 2 Tw)
                rhs = Mt[cols]                               # (ce, 2 Tw, 2F)
                # transposed product, so that each (sample, re | im) row holds every j
                y = torch.bmm(rhs, lhs.transpose(1, 2))      # (ce, 2 Tw, Ne)
                y = y.reshape(e1 - e0, 2, Tw, ne).transpose(1, 2)  # (ce, Tw, 2, Ne)
                out[n, e0:e1] = y.to(torch.float32).numpy()
        return out

    def local_plan(self, rows: slice, cols: torch.Tensor):
        """DAS plan of the pixels (rows x cols) for the pair-image kernel: (i0 local to the
        channel windows, weight, rotation re, im), each (ntx, Ne, Npix) numpy."""
        model = self.model
        Z, X = torch.meshgrid(model.z_grid[rows], model.x_grid[cols], indexing="ij")
        out = [[], [], [], []]
        for i0, w, rot in window_plans(model, self.window_offset, X, Z):
            out[0].append(i0.T.to(torch.int32))
            out[1].append(w.T.to(torch.float32))
            out[2].append(rot.real.T.to(torch.float32))
            out[3].append(rot.imag.T.to(torch.float32))
        return tuple(np.ascontiguousarray(torch.stack(a).numpy()) for a in out)

    #: memory (bytes) of the kernel's output for one call (a group of pixels with every pair)
    build_tile_bytes = 256 << 20

    def pair_image_tiles(self, X: np.ndarray, plan: tuple, tiles):
        """Yield ``(G, Ht)`` for each pixel-index tensor ``G`` of ``tiles`` (indices into the
        plan's pixels): ``Ht`` (2 |G|, P) float64, the symmetric pair images of every pair on
        those pixels, real rows then imaginary rows (the pixels' [re | im] columns of the pair
        images, transposed). Consecutive tiles share a kernel call up to
        :attr:`build_tile_bytes` of output. The kernel's output and the tiles are written into
        buffers reused from tile to tile (each ``Ht`` is overwritten by the next): fresh
        hundred-megabyte arrays for every tile had the kernel map and zero 33 GB of pages in a
        256-element build."""
        from arraysel.physics.pairkernels import pair_images

        P = self.layout.pairs_e.numel()
        per_call = max(1, self.build_tile_bytes // (P * 16))
        tiles = list(tiles)
        largest = max(G.numel() for G in tiles)
        # a group holds up to per_call pixels, or one tile larger than that
        buffer = np.empty(2 * max(largest, min(per_call, sum(G.numel() for G in tiles))) * P, dtype=np.float64)
        tile_buf = []  # made when a call holds several tiles

        def run(group):
            pix = torch.cat(group).numpy()
            v = torch.from_numpy(pair_images(X, tuple(np.ascontiguousarray(a[:, :, pix]) for a in plan),
                                             buffer))
            at = 0
            for G in group:
                g = G.numel()
                if len(group) == 1:
                    yield G, v.view(2 * g, P)
                else:
                    if not tile_buf:
                        tile_buf.append(torch.empty(2 * largest * P, dtype=torch.float64))
                    Ht = tile_buf[0][:2 * g * P].view(2 * g, P)
                    Ht.view(2, g, P).copy_(v[:, at:at + g])
                    yield G, Ht
                at += g

        group, n = [], 0
        for G in tiles:
            if group and n + G.numel() > per_call:
                yield from run(group)
                group, n = [], 0
            group.append(G)
            n += G.numel()
        if group:
            yield from run(group)

    def dense_pair_images(self, X: np.ndarray, plan: tuple, dtype=torch.float64,
                           transposed: bool = False) -> torch.Tensor:
        """All symmetric pair images on the plan's pixels: (P, 2 Npix) [re | im] in ``dtype``,
        or its transpose (2 Npix, P), stored row-major, if ``transposed``."""
        P = self.layout.pairs_e.numel()
        npix = plan[0].shape[2]
        out = torch.empty(2 * npix, P, dtype=dtype) if transposed else torch.empty(P, 2 * npix, dtype=dtype)
        per_call = max(1, self.build_tile_bytes // (P * 16))
        for G, Ht in self.pair_image_tiles(X, plan, torch.arange(npix).split(per_call)):
            p0, p1 = int(G[0]), int(G[-1]) + 1
            if transposed:
                out[p0:p1] = Ht[:p1 - p0]
                out[npix + p0:npix + p1] = Ht[p1 - p0:]
            else:
                out[:, p0:p1] = Ht[:p1 - p0].T
                out[:, npix + p0:npix + p1] = Ht[p1 - p0:].T
        return out

    #: side (pixels) of the tiles of E whose residual Gram matrices bound what a sketch missed
    #: (:func:`_missed_spectral`): larger tiles give a tighter bound at a cost growing as the side
    #: squared (``P (2 side^2)^2`` per tile)
    missed_tile = 16

    #: real columns of the randomised range sketch of the pair images on E (probes whose
    #: pair count exceeds it are compressed from the sketch; smaller ones exactly)
    sketch_columns = 2400

    #: largest memory (bytes) of the pair images on E kept, in the model's dtype, between the
    #: sketch's two passes; below it the second pass reads them instead of delay-and-summing
    #: them again (a 128-element probe in float32: 1.4 GB, a fifth of the build's time), above
    #: it they are recomputed
    keep_images_max_bytes = 2 << 30

    @classmethod
    def keeps_images(cls, pairs: int, npix: int, dtype: torch.dtype) -> bool:
        """Whether a sketched build keeps the pair images of ``pairs`` pairs on ``npix`` pixels
        of E, in ``dtype``, for its second pass (:attr:`keep_images_max_bytes`)."""
        return pairs * 2 * npix * (torch.finfo(dtype).bits // 8) <= cls.keep_images_max_bytes

    def compress(self, X: np.ndarray, plan: tuple, rank_tol: float, progress=None) -> Compression:
        """Truncated SVD ``H ~ U V`` of the pair images ``H`` (P, 2 Npix) on E, with ``U``
        orthonormal (P, r) and ``V = U^T H``.

        Small probes (P <= :attr:`sketch_columns`): ``H`` is formed and the P x P Gram matrix
        diagonalised (exact, :meth:`_compress_exact`). Larger ones (:meth:`_compress_sketched`):
        two passes over :attr:`missed_tile`-sided tiles of pixels of ``H``, which is held whole
        only in the model's dtype and only up to :attr:`keep_images_max_bytes` (else the second
        pass computes the tiles again): a sparse sign sketch ``Y = H S`` gives an orthonormal
        ``Q`` spanning the pairs' dominant subspace; the second pass forms ``B = Q^T H``, the
        pixels' column norms, the core columns and the tiles' Gram matrices (what ``Q`` missed,
        :func:`_missed_spectral`); the SVD of ``B`` gives ``U = Q W``, ``V = W^T B``.

        Returns a :class:`Compression` record.
        """
        core = torch.cat([self.layout.core_pix, self.layout.npix + self.layout.core_pix])
        if self.layout.pairs_e.numel() <= self.sketch_columns:
            return self._compress_exact(X, plan, rank_tol, core, progress)
        return self._compress_sketched(X, plan, rank_tol, core, progress)

    def _compress_exact(self, X: np.ndarray, plan: tuple, rank_tol: float, core: torch.Tensor,
                        progress) -> Compression:
        """:meth:`compress` of a small probe: ``H`` formed whole and its Gram matrix diagonalised."""
        model = self.model
        P = self.layout.pairs_e.numel()
        H = self.dense_pair_images(X, plan)
        if progress is not None:
            progress.step("pair images on E")
        col = pixel_norms(H)
        Hc = H[:, core].to(model.device, model.dtype)
        gram = H @ H.T
        evals, evecs = torch.linalg.eigh(gram)
        evals = evals.flip(0).clamp(min=0)
        evecs = evecs.flip(1)
        total = float(evals.sum())
        tail = total - torch.cumsum(evals, 0)
        rank = int(torch.nonzero(tail <= rank_tol * total).flatten()[0]) + 1
        # U @ V costs P*R + R*N per selection against P*N for H itself
        if rank * (P + H.shape[1]) >= 0.9 * P * H.shape[1]:
            return Compression(U=None, V=H.to(model.device, model.dtype), rank=P, rank_tail=0.0,
                               pixel_residual=0.0, column_norm=float(col.max()), spectral_tail=0.0,
                               missed=0.0, core_images=Hc)
        U = evecs[:, :rank]
        V = U.T @ H
        rho = float((col ** 2 - pixel_norms(V) ** 2).clamp(min=0).sqrt().max())
        return Compression(U=U.to(model.device, model.dtype), V=V.to(model.device, model.dtype), rank=rank,
                           rank_tail=float(tail[rank - 1] / total), pixel_residual=rho,
                           column_norm=float(col.max()),
                           spectral_tail=float(evals[rank].sqrt()) if rank < P else 0.0,
                           missed=0.0, core_images=Hc)

    def _tile_images(self, X: np.ndarray, plan: tuple, tiles, kept: torch.Tensor | None):
        """Yield ``(G, Ht)``: the tiles' pair images, float64, columns as rows
        (:meth:`pair_image_tiles`), from the images ``kept`` (P columns, the model's dtype) when
        there are some, each written over the previous one (reused buffers: no fresh pages for
        each tile); else delay-and-summed again, a tile at a time."""
        if kept is None:
            yield from self.pair_image_tiles(X, plan, tiles)
            return
        npix, P = self.layout.npix, self.layout.pairs_e.numel()
        rows_max = 2 * max(G.numel() for G in tiles)
        b32 = torch.empty(rows_max, P, dtype=kept.dtype)
        b64 = torch.empty(rows_max, P, dtype=torch.float64)
        for G in tiles:
            n = 2 * G.numel()
            torch.index_select(kept, 0, _tile_rows(G, npix), out=b32[:n])
            yield G, b64[:n].copy_(b32[:n])

    def _compress_sketched(self, X: np.ndarray, plan: tuple, rank_tol: float, core: torch.Tensor,
                           progress) -> Compression:
        """:meth:`compress` of a large probe: a sketch, a projection onto it, and the SVD of that."""
        model = self.model
        P = self.layout.pairs_e.numel()
        npix = self.layout.npix
        tiles = _tile_pixels(self.layout.shape, self.missed_tile)
        # both passes read the pair images kept in the model's dtype when they fit (the column
        # norms and the basis then describe those rounded images, which differ from the float64
        # ones by less than the rounding allowance of an evaluation); else each pass
        # delay-and-sums them again, a tile at a time
        kept = self.dense_pair_images(X, plan, model.dtype, transposed=True) \
            if self.keeps_images(P, npix, model.dtype) else None

        def tile_images():
            return self._tile_images(X, plan, tiles, kept)

        Yt = _sketch(tile_images, npix, P, self.sketch_columns)
        if progress is not None:
            progress.step("sketch of the pair images on E")
        Q = torch.linalg.qr(Yt.T)[0]
        del Yt
        Bt, col2, Hc, grams, gram_s = _project(Q, tile_images, tiles, core, npix, P, self.missed_tile)
        del kept, tile_images
        if progress is not None:
            progress.step(f"projection of the pair images on E (of which the tiles' Gram matrices {gram_s:.1f} s)")
        B = Bt.T
        evals, W = torch.linalg.eigh(_row_gram(B))
        evals = evals.flip(0).clamp(min=0)
        W = W.flip(1)
        total = float(col2.sum())
        missed = max(0.0, total - float(evals.sum()))
        frob = math.sqrt(missed) * (1 + 1e-6)
        tile = self.missed_tile
        missed = min(frob, _missed_spectral(grams, _tile_grams(B, self.layout.shape, tile), P, Q.shape[1]))
        _log.info("  what the sketch missed: spectral norm <= %.3g (Frobenius %.3g) of |H|_F %.3g",
                  missed, frob, math.sqrt(total))
        tail = total - torch.cumsum(evals, 0)
        ok = torch.nonzero(tail <= rank_tol * total).flatten()
        rank = int(ok[0]) + 1 if ok.numel() else evals.numel()
        U = Q @ W[:, :rank]
        V = W[:, :rank].T @ B
        nxt = float(evals[rank].sqrt()) if rank < evals.numel() else 0.0
        rho = float((col2 - pixel_norms(V) ** 2).clamp(min=0).sqrt().max())
        return Compression(U=U.to(model.device, model.dtype), V=V.to(model.device, model.dtype), rank=rank,
                           rank_tail=float(tail[rank - 1] / total), pixel_residual=rho,
                           column_norm=float(col2.max().sqrt()), spectral_tail=combined_tail(nxt, missed),
                           missed=missed, core_images=Hc.to(model.device, model.dtype))

