"""The fast path's pair basis: its regions, the stored tensors and their serialisation, the
truncation to a run-time rank, and the images of a batch of selections on E and the band.

See :mod:`arraysel.physics.psf.operator` for the method; the build steps are in
:mod:`~arraysel.physics.psf.build`, the peak certificates in
:mod:`~arraysel.physics.psf.certificate`, the certified kernels and their refinement in
:mod:`~arraysel.physics.psf.refinement`, the disk cache in :mod:`~arraysel.physics.psf.store`.
"""
from __future__ import annotations

import logging
import math
from typing import NamedTuple

import torch

from arraysel.errors import check_number
from arraysel.physics.psf.build import BasisBuild, combined_tail, pixel_norms
from arraysel.physics.psf.certificate import Certificates, sparse_csr
from arraysel.physics.psf.refinement import Refinement

_log = logging.getLogger(__name__)

#: energy fraction the stored SVD of the pair images on E discards (runs truncate further)
BUILD_RANK_TOL = 1e-7


def pair_index(ne: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Indices (e, j) with e <= j of the Ne(Ne+1)/2 element pairs."""
    e, j = torch.triu_indices(ne, ne)
    return e, j


def pair_products(w: torch.Tensor, e: torch.Tensor, j: torch.Tensor) -> torch.Tensor:
    """(B, P) products w_e w_j of the pairs (e <= j)."""
    return w[:, e] * w[:, j]


class ErrorConstants(NamedTuple):
    """The constants of a basis's rigorous error bounds (all >= 0)."""

    #: largest residual pixel-column norm of the truncated SVD on E, ``max_p |(I - U U^T) H_p|``
    pixel_residual: float
    #: largest pixel-column norm of the pair images on E
    column_e: float
    #: largest pixel-column norm of the strips' pair images
    column_strips: float
    #: bound of the spectral norm of ``(I - U U^T) H`` (the largest discarded singular value)
    spectral_tail: float


class BuildProgress:
    """Logs the steps of a basis build with their durations (``logging`` INFO)."""

    def __init__(self, model, basis: "PairBasis"):
        import time

        self._time = time.perf_counter
        self.t0 = self.t = self._time()
        _log.info("building the PSF fast-path basis: %d elements, %d transmits, E %d x %d pixels%s",
                  model.n_elements, len(model.transmits), basis.shape[0], basis.shape[1],
                  "" if basis.strips else " (no strips: loose blocks beside E are beamformed exactly)")

    def step(self, what: str):
        now = self._time()
        _log.info("  %s: %.1f s", what, now - self.t)
        self.t = now

    def close(self):
        _log.info("basis built in %.1f s", self._time() - self.t0)


class PairBasis(BasisBuild, Certificates, Refinement):
    """Precomputed pair images and peak certificates of the fast path.

    Regions (grid rows ``rows`` = the window plus a margin around the scatterer):

    * tier 1, ``E``: the columns of the window plus the margin;
    * tier 2, the *strips*: the remaining columns of the same rows, so that
      E and the strips make the full-width band ``rows x all columns``.

    Images: ``I = c @ H`` with ``c`` the (B, P) pair products and ``H`` the
    (P, 2 Npix) real pair images ([re | im]); tier 1 is stored as a truncated
    SVD ``U @ V`` when that saves work (discarded energy <= ``rank_tol``).

    Certificates (:mod:`~arraysel.physics.psf.certificate`): the envelopes of a selection's I/Q
    channels bound ``|I|`` on every grid block outside E (tier 1, ``block_envelopes_e``) or outside
    the band (tier 2, ``block_envelopes_band``). A selection is done at tier 1 when its peak in E
    beats the tier-1 bound (and its window fits in E), or when the blocks whose bound reaches the
    peak are settled exactly and stay below it (:meth:`refine`); at tier 2 likewise on the band;
    otherwise the exact path recomputes it.

    Stored tensors (model dtype unless noted): ``U``, ``V`` (the truncated SVD on E);
    ``strip_images`` (P, 2 Npix2) the strips' pair images in block-major column order;
    ``strip_left``, ``strip_right``, ``strip_sigma``, ``strip_sigma_next`` their per-block
    rank-``strip_rank`` factors; ``core_images`` the core's exact pair images;
    ``pair_channels`` (Ne, Ne 2 ntx T) the windowed pair I/Q signals (receive element, real and
    imaginary part, transmit, then samples segment-offset major);
    ``window_offset`` (ntx, Ne) the first record sample of each channel's window of
    ``window_samples`` samples; ``max_run`` the longest run of segments a block reads;
    ``error`` the :class:`ErrorConstants`.

    From the model it reads only the interface :class:`~arraysel.physics.psf.operator.PSFModel`
    states (``setup``, ``n_elements``, ``transmits``, ``x_grid``, ``z_grid``, ``margin``,
    ``block``, ``dtype``, ``cdtype``, ``device``).
    """

    #: largest memory of the strips' pair images (tier 2) kept; above it they are not built and
    #: loose blocks beside E are beamformed exactly
    strip_max_bytes = 1 << 30
    #: bound of the relative L2 error of a kernel from a sketched basis (probes with more than
    #: about 68 elements), above which it is recomputed exactly: its bound carries a bound of
    #: what the sketch missed, so it is looser than the actual error (random masks at the
    #: run-time rank: L11-5v bounds 4e-3 to 1e-2, a 256-element probe 1e-2 to 3.4e-2; actual
    #: errors about 5e-4); 5e-2 certifies SI-MSE <= 2.5e-3 (the exact Gram build of small
    #: probes certifies 5e-3)
    sketch_kernel_tol = 5e-2

    def __init__(self, model, rank_tol: float = BUILD_RANK_TOL, _state: dict | None = None):
        s = model.setup
        self.model = model
        ne = model.n_elements
        win = s.window
        m = model.margin
        iz, ix = s.scatterer_pixel
        half = win // 2
        z_lo = max(0, min(iz - half - m, s.n_z - win - 2 * m))
        x_lo = max(0, min(ix - half - m, s.n_x - win - 2 * m))
        self.rows = slice(z_lo, min(s.n_z, z_lo + win + 2 * m))
        self.cols = slice(x_lo, min(s.n_x, x_lo + win + 2 * m))
        self.shape = (self.rows.stop - self.rows.start, self.cols.stop - self.cols.start)
        self.npix = self.shape[0] * self.shape[1]
        self.strip_cols = torch.cat([torch.arange(0, self.cols.start), torch.arange(self.cols.stop, s.n_x)])
        self.npix2 = self.shape[0] * self.strip_cols.numel()
        self.pairs_e, self.pairs_j = pair_index(ne)
        outside1, outside2 = self._outside_blocks()
        self.blocks1 = torch.nonzero(outside1)  # (nQ1, 2): the tier-1 blocks (rows of block_envelopes_e) as (qz, qx)
        self.blocks2 = torch.nonzero(outside2)  # (nQ2, 2): the tier-2 blocks (rows of block_envelopes_band)
        self._strip_layout()
        self._block_plans: dict = {}
        self._e_plan_holder: dict = {}  # E's DAS plan (Refinement._e_plans), shared with truncated views
        self._block_dtx: dict = {}  # blocks' transmit distances (Refinement._block_transmit_distances)
        self._block_index: dict = {}  # per tier, the blocks' envelope entries (Certificates._bound_index)
        #: kernels that reached each costly step since the basis was made (shared with truncated
        #: views): ``"finer"`` (the stored rank's tighter bound), ``"exact_windows"`` (their
        #: window delay-and-summed exactly)
        self.settled = {"finer": 0, "exact_windows": 0}
        self._row_energy = None
        #: the full-rank basis this one was truncated from (:meth:`truncated`): kernels whose
        #: error bound fails here are retried there before the exact path
        self.finer = None
        if _state is not None:
            self._set_state(_state)
            return
        self.strips = self._strip_bytes() <= self.strip_max_bytes
        if not self.strips:
            self._disable_strips()
        progress = BuildProgress(model, self)
        lo, hi = self._sample_ranges()
        progress.step("sample ranges")
        X = self._windowed_pair_iq()
        progress.step("pair I/Q signals")
        plan1 = self._local_plan(self.rows, torch.arange(self.cols.start, self.cols.stop))
        self.core_pix = self._core_pixels()
        svd = self._compress(X, plan1, rank_tol, progress)
        del plan1
        self.U, self.V, self.rank, self.rank_tail = svd.U, svd.V, svd.rank, svd.rank_tail
        self.core_images, self.missed = svd.core_images, svd.missed
        if self.npix2:
            H2 = self._dense_pair_images(X, self._local_plan(self.rows, self.strip_cols))
            col2 = float(pixel_norms(H2).max())
            H2 = H2[:, self.h2_cols]
            self._strip_factors(H2)
            self.strip_images = H2.to(model.device, model.dtype)
            del H2
            progress.step("strip pair images")
        else:
            col2 = 0.0
            self.strip_images = torch.zeros(self.pairs_e.numel(), 0, dtype=model.dtype, device=model.device)
            self._strip_factors(self.strip_images.double())
        self.error = ErrorConstants(pixel_residual=svd.pixel_residual, column_e=svd.column_norm,
                                    column_strips=col2, spectral_tail=svd.spectral_tail)
        self._build_certificates(X, lo, hi)
        if self.missed > 0:
            self.kernel_tol = self.sketch_kernel_tol
        progress.close()

    # ------------------------------------------------------------------ precomputation
    def _strip_layout(self):
        """Column order of ``strip_images`` (``H2``): block-major, so the pair images of one grid block of the strips
        are ``2 block^2`` adjacent columns ([re | im] of its pixels, row-major), followed by the
        pixels no whole block covers. Sets ``h2_cols`` (old [re | im] column of each new column),
        its inverse ``h2_inv`` and ``strip_block_col`` (nQ1,): the first column of each tier-1
        block in ``strip_images``, -1 where the block is not wholly inside the strips."""
        s = self.model.setup
        b = self.model.block
        nstrip = self.strip_cols.numel()
        qz, qx = self.blocks1[:, 0], self.blocks1[:, 1]
        in_rows = (qz * b >= self.rows.start) & ((qz + 1) * b <= self.rows.stop)
        in_grid = (qx + 1) * b <= s.n_x
        in_strip = ((qx + 1) * b <= self.cols.start) | (qx * b >= self.cols.stop)
        whole = torch.nonzero(in_rows & in_grid & in_strip).flatten()
        ar = torch.arange(b)
        z = qz[whole, None, None] * b + ar[None, :, None] - self.rows.start  # (nW, b, 1)
        x = qx[whole, None, None] * b + ar[None, None, :]
        j = torch.where(x < self.cols.start, x, x - (self.cols.stop - self.cols.start))
        pix = (z * nstrip + j).reshape(whole.numel(), b * b)  # strip pixels of each whole block
        covered = torch.zeros(self.npix2, dtype=torch.bool)
        covered[pix.reshape(-1)] = True
        rest = torch.nonzero(~covered).flatten()
        self.h2_cols = torch.cat([torch.cat([pix, pix + self.npix2], dim=1).reshape(-1), rest, rest + self.npix2])
        self.h2_inv = torch.argsort(self.h2_cols)
        self.strip_block_col = torch.full((self.blocks1.shape[0],), -1, dtype=torch.long)
        self.strip_block_col[whole] = torch.arange(whole.numel()) * 2 * b * b

    #: half side (pixels) of the core around the scatterer whose exact pair images are kept
    core = 16

    def _core_pixels(self) -> torch.Tensor:
        """Row-major E-pixel indices of the core: the (2 core) x (2 core) pixels of E centred on
        the scatterer, where the peak of a selection's image lies (its pair images, ``core_images``,
        settle near-ties at the peak without delay-and-sum)."""
        s = self.model.setup
        iz, ix = s.scatterer_pixel
        iz, ix = iz - self.rows.start, ix - self.cols.start
        h, w = self.shape
        zr = torch.arange(max(0, iz - self.core), min(h, iz + self.core))
        xr = torch.arange(max(0, ix - self.core), min(w, ix + self.core))
        return (zr[:, None] * w + xr[None, :]).reshape(-1)

    def _strip_bytes(self) -> int:
        """Memory of the strips' pair images and block factors in the model's dtype."""
        P = self.pairs_e.numel()
        size = torch.finfo(self.model.dtype).bits // 8
        nw = int((self.strip_block_col >= 0).sum())
        return size * P * (2 * self.npix2 + nw * self.strip_rank)

    def _disable_strips(self):
        """Drop tier 2 (the strips' pair images): loose blocks outside E are beamformed exactly."""
        self.strips = False
        self.npix2 = 0
        self.strip_cols = torch.zeros(0, dtype=torch.long)
        self.h2_cols = torch.zeros(0, dtype=torch.long)
        self.h2_inv = torch.zeros(0, dtype=torch.long)
        self.strip_block_col = torch.full_like(self.strip_block_col, -1)

    # ------------------------------------------------------------------ cache
    #: stored key -> attribute of the dense tensors kept in the model's dtype (the keys are the
    #: serialised format: keep them, or bump :data:`~arraysel.physics.psf.store.BASIS_VERSION`)
    _DENSE = {"V": "V", "H2": "strip_images", "A": "pair_channels", "Hc": "core_images", "SF": "strip_left",
              "SG": "strip_right", "SS": "strip_sigma"}
    #: stored key prefix -> attribute of the sparse block matrices
    _SPARSE = {"S1": "block_envelopes_e", "S2": "block_envelopes_band"}

    def state(self) -> dict:
        """The stored tensors by name (see :attr:`_DENSE` and :attr:`_SPARSE`)."""
        st = {key: getattr(self, attr).cpu() for key, attr in self._DENSE.items()}
        st.update({"err": torch.tensor(list(self.error), dtype=torch.float64), "core_pix": self.core_pix,
                   "Snext": self.strip_sigma_next.cpu(),
                   "meta": torch.tensor([self.window_samples, self.max_run, self.rank, self.segment,
                                         int(self.strips)]),
                   "rank_tail": torch.tensor(self.rank_tail), "off": self.window_offset.cpu(),
                   "row_energy": self.row_energy, "missed": torch.tensor(self.missed, dtype=torch.float64)})
        if self.U is not None:
            st["U"] = self.U.cpu()
        for key, attr in self._SPARSE.items():
            S = getattr(self, attr)
            st[key + "_crow"], st[key + "_col"], st[key + "_val"] = (
                S.crow_indices().cpu(), S.col_indices().cpu(), S.values().cpu())
            st[key + "_shape"] = torch.tensor(list(S.shape))
        return st

    def _set_state(self, st: dict):
        dev, dt = self.model.device, self.model.dtype
        self.U = st["U"].to(dev, dt) if "U" in st else None
        for key, attr in self._DENSE.items():
            setattr(self, attr, st[key].to(dev, dt))
        self.strip_sigma_next = st["Snext"].double().to(dev)
        self.core_pix = st["core_pix"].long()
        self.window_samples, self.max_run, self.rank, self.segment, strips = (int(v) for v in st["meta"])
        self.window_offset = st["off"].long()
        self._row_energy = st["row_energy"].double()
        self.strips = bool(strips)
        if not strips:
            self._disable_strips()
        self.rank_tail = float(st["rank_tail"])
        self.missed = float(st["missed"])
        if self.missed > 0:
            self.kernel_tol = self.sketch_kernel_tol
        self.error = ErrorConstants(*(float(v) for v in st["err"].double()))
        for key, attr in self._SPARSE.items():
            shape = tuple(int(v) for v in st[key + "_shape"])
            setattr(self, attr, sparse_csr(st[key + "_crow"], st[key + "_col"], st[key + "_val"].to(dt),
                                           shape).to(dev))

    @classmethod
    def from_state(cls, model, state):
        return cls(model, _state=state)

    def truncated(self, rank: int) -> "PairBasis":
        """A view of this basis keeping the first ``rank`` singular vectors of the pair images on
        E, with its error constants widened to stay rigorous: the residual pixel-column norm
        grows by the dropped rows of V (``rho^2 + max_p sum_{i >= rank} |V_ip|^2``) and the
        largest discarded singular value becomes ``|V_rank|``."""
        import copy

        out = copy.copy(self)
        r = int(check_number("rank", rank, lo=1, integer=True))
        if self.U is None or r >= self.rank:
            return out
        n = self.npix
        # sum of the dropped rows' squares per pixel, a few rows at a time (the rows of V beyond
        # the run-time rank are most of V: held at once in float64 they doubled the resident
        # memory of a 128-element probe's cold start)
        pix = torch.zeros(n, dtype=torch.float64, device=self.V.device)
        for i0 in range(r, self.V.shape[0], 64):
            tail = self.V[i0:i0 + 64].double()
            pix += tail[:, :n].square().sum(0) + tail[:, n:].square().sum(0)
        sig = self.row_energy[r:]
        err = self.error._replace(
            pixel_residual=math.sqrt(self.error.pixel_residual ** 2 + float(pix.max())) * (1 + 1e-6),
            spectral_tail=max(combined_tail(float(sig[0].sqrt()), self.missed), self.error.spectral_tail))
        total = float(self.row_energy.sum()) / max(1e-300, 1 - self.rank_tail)
        out.row_energy = self.row_energy[:r]
        out.U, out.V, out.rank, out.error = self.U[:, :r].contiguous(), self.V[:r].contiguous(), r, err
        out.rank_tail = self.rank_tail + float(sig.sum()) / total
        out.finer = self
        return out

    @property
    def row_energy(self) -> torch.Tensor:
        """(rank,) float64 squared singular values ``|V_i|^2`` (V's rows are orthogonal), computed
        once at build time and stored with the basis (a cold start does not read all of V)."""
        if self._row_energy is None:
            self._row_energy = (self.V.double() ** 2).sum(1) if self.U is not None else \
                torch.zeros(0, dtype=torch.float64)
        return self._row_energy

    @row_energy.setter
    def row_energy(self, value: torch.Tensor):
        self._row_energy = value

    def rank_for(self, rank_tol: float) -> int:
        """Smallest rank whose discarded energy fraction is at most ``rank_tol`` (at most the
        stored rank)."""
        if self.U is None:
            return self.rank
        sig2 = self.row_energy
        total = float(sig2.sum()) / max(1e-300, 1 - self.rank_tail)
        tail = total - torch.cumsum(sig2, 0)
        ok = torch.nonzero(tail <= rank_tol * total).flatten()
        rank = int(ok[0]) + 1 if ok.numel() else self.rank
        if self.missed > 0:
            # a sketched basis: once the next singular value is below the sketch's own term
            # (:attr:`missed`) the window bound is within sqrt(2) of its floor
            # (:func:`~arraysel.physics.psf.build.combined_tail`) and more rank costs time
            # for little tightening
            small = torch.nonzero(sig2.sqrt() <= self.missed).flatten()
            if small.numel():
                rank = min(rank, max(1, int(small[0])))
        return rank

    def bytes_per_selection(self) -> int:
        """Memory (bytes) that one more selection adds to a batch of :meth:`kernels`: its
        envelopes (every run of segments of every channel), its image on E and that image's
        complex copy, its per-block bounds (float64 sums and their cast) and its kernel window
        twice (the cut window and the metrics' copy)."""
        m = self.model
        item = m.dtype.itemsize
        env = len(m.transmits) * m.n_elements * self.max_run * (self.window_samples // self.segment) * item
        images = 2 * 2 * self.npix * item
        bounds = self.block_envelopes_e.shape[0] * (8 + item)
        kernels = 2 * 2 * m.setup.window ** 2 * item
        return env + images + bounds + kernels

    # ------------------------------------------------------------------ evaluation
    def _pairs(self, w):
        return pair_products(w, self.pairs_e.to(w.device), self.pairs_j.to(w.device))

    def images(self, w: torch.Tensor, with_error: bool = False):
        """Images on region E, (B, nzE, nxE) complex [and two (B,) error bounds].

        The error bounds cover the SVD truncation and rounding. Per pixel,
        ``|c (I - U U^T) H_p| <= |c - (c U) U^T| rho`` with ``rho`` the largest residual
        pixel-column norm; on any set of pixels (the kernel window) in L2,
        ``<= |c - (c U) U^T| sigma_{r+1}`` (both rigorous). The rounding allowance is
        ``2 sqrt(P) u |c| max_p |H_p|`` per pixel (u: the unit roundoff of the dtype), times
        the window side in L2.
        """
        c = self._pairs(w)
        if self.U is not None:
            cu = c @ self.U
            y = cu @ self.V
        else:
            y = c @ self.V
        img = torch.complex(y[:, : self.npix], y[:, self.npix:]).reshape(w.shape[0], *self.shape)
        if not with_error:
            return img
        with torch.no_grad():
            cn2 = (c.detach() ** 2).sum(1)
            resid = (cn2 - (cu.detach() ** 2).sum(1)).clamp(min=0).sqrt() if self.U is not None else 0 * cn2
            rnd = self._rounding(c.detach(), cn2)
            eps = resid * self.error.pixel_residual + rnd
            win_err = resid * self.error.spectral_tail + rnd * self.model.setup.window
        return img, eps, win_err

    def _rounding(self, c: torch.Tensor, cn2: torch.Tensor | None = None) -> torch.Tensor:
        """(B,) rounding allowance of one image pixel ``c @ H_p``: ``2 sqrt(P) u |c| max_p |H_p|``."""
        if cn2 is None:
            cn2 = (c ** 2).sum(1)
        u = torch.finfo(c.dtype).eps / 2
        return 2 * math.sqrt(c.shape[1]) * u * cn2.sqrt() * max(self.error.column_e, self.error.column_strips)

    def band_images(self, w: torch.Tensor, img_e: torch.Tensor | None = None) -> torch.Tensor:
        """Images on the full-width band (B, nzE, n_x) complex."""
        if img_e is None:
            img_e = self.images(w)
        B = w.shape[0]
        y = (self._pairs(w) @ self.strip_images)[:, self.h2_inv.to(w.device)]
        strips = torch.complex(y[:, : self.npix2], y[:, self.npix2:]).reshape(B, self.shape[0], -1)
        left = self.cols.start
        return torch.cat([strips[:, :, :left], img_e, strips[:, :, left:]], dim=2)

    def channels(self, w: torch.Tensor) -> torch.Tensor:
        """I/Q channel signals (B, ntx, Ne, T) complex of selections w: ``m_e sum_j m_j A_nej``."""
        x = self._complex_channels(w @ self.pair_channels, w.shape[0]).transpose(1, 2)
        return x * w.to(x.dtype)[:, None, :, None]

    def _complex_channels(self, y: torch.Tensor, n: int) -> torch.Tensor:
        """(n, Ne, ntx, T) complex, samples in time order, from rows of ``pair_channels``' layout
        (n, Ne * 2 * ntx * T)."""
        ne, sg = self.model.n_elements, self.segment
        y = y.view(n, ne, 2, len(self.model.transmits), sg, self.window_samples // sg)
        x = torch.complex(y[:, :, 0], y[:, :, 1])
        return x.transpose(-1, -2).reshape(n, ne, len(self.model.transmits), self.window_samples)

    def pair_iq(self) -> torch.Tensor:
        """The windowed pair I/Q signals (Ne tx j, ntx, Ne rx e, T) complex (sample t of the window
        of (n, e) is sample ``off[n, e] + t`` of the record)."""
        return self._complex_channels(self.pair_channels, self.model.n_elements).transpose(1, 2)
