"""The fast path's pair basis, :class:`PairBasis`: its entry points (:meth:`PairBasis.build`,
:meth:`PairBasis.from_state`), the truncation to a run-time rank, and the images of a batch of
selections on E and the band.

It is built from parts, each an object in its own module made from explicit inputs (see
:mod:`arraysel.physics.psf.operator` for the method); ``PairBasis`` inherits from none of them:

* the **layout** (:class:`~arraysel.physics.psf.layout.BasisLayout`, ``basis.layout``): regions,
  pairs, blocks and the strips' column order, from the grid alone;
* the **build** (:class:`~arraysel.physics.psf.build.BasisBuilder`, used by :meth:`PairBasis.build`
  only): sample ranges, windowed pair I/Q, pair images, their compression and the strips'
  factors, each step returning what it makes;
* the **state** (:mod:`~arraysel.physics.psf.state`): the stored tensors, their error constants
  and their serialisation (the disk cache is :mod:`~arraysel.physics.psf.store`);
* the **certificates** (:class:`~arraysel.physics.psf.certificate.Certificates`,
  ``basis.certificates``): the pair I/Q signals on their windows, envelopes and block bounds;
* the **refinement** (:class:`~arraysel.physics.psf.refinement.Refinement`, ``basis.refinement``):
  the certified kernels (:meth:`PairBasis.kernels` runs them), peak location, ties and loose
  blocks; it reads the basis's images and stored tensors and the certificates.

The images of a selection's neighbours from the pair-image rows a local search keeps
(:meth:`PairBasis.swap_images`, :meth:`PairBasis.pair_rows`) are functions of the basis in
:mod:`~arraysel.physics.psf.neighbourimages`, which the methods of the same names call.
"""
from __future__ import annotations

import logging
import math

import numpy as np
import torch

from arraysel.errors import check_number
from arraysel.physics.psf.build import BasisBuilder, combined_tail, pixel_norms
from arraysel.physics.psf.certificate import Certificates
from arraysel.physics.psf import neighbourimages
from arraysel.physics.psf.layout import LAYOUT_FIELDS, BasisLayout, pair_index
from arraysel.physics.psf.refinement import Refinement
from arraysel.physics.psf.state import ErrorConstants, basis_state, restore_state
from arraysel.physics.psf.swapbase import form_base

__all__ = ["PairBasis", "BUILD_RANK_TOL", "ErrorConstants", "pair_index", "pair_products"]

_log = logging.getLogger(__name__)

#: energy fraction the stored SVD of the pair images on E discards (runs truncate further)
BUILD_RANK_TOL = 1e-7


def pair_products(w: torch.Tensor, e: torch.Tensor, j: torch.Tensor) -> torch.Tensor:
    """(B, P) products w_e w_j of the pairs (e <= j)."""
    return w[:, e] * w[:, j]


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


def _layout_attribute(name: str) -> property:
    return property(lambda self: getattr(self.layout, name), doc=f"``layout.{name}`` (:class:`BasisLayout`)")


class PairBasis:
    """Precomputed pair images and peak certificates of the fast path.

    Make one with :meth:`build` (from the model's physics) or :meth:`from_state` (from the stored
    tensors, :meth:`state`); :class:`~arraysel.physics.psf.store` does one or the other through
    the cache.

    Regions: ``layout`` (:class:`~arraysel.physics.psf.layout.BasisLayout`; its fields
    ``rows``, ``cols``, ``shape``, ``npix``, ``strip_cols``, ``npix2``, ``pairs_e``, ``pairs_j``,
    ``blocks1``, ``blocks2``, ``h2_cols``, ``h2_inv``, ``strip_block_col``, ``core_pix``,
    ``strips`` read as attributes of the basis): tier 1, ``E``, the window plus a margin
    around the scatterer; tier 2, the *strips*, the rest of the same rows.

    Images: ``I = c @ H`` with ``c`` the (B, P) pair products and ``H`` the
    (P, 2 Npix) real pair images ([re | im]); tier 1 is stored as a truncated
    SVD ``U @ V`` when that saves work (discarded energy <= ``rank_tol``).

    Certificates (``certificates``, :mod:`~arraysel.physics.psf.certificate`): the envelopes of
    a selection's I/Q channels bound ``|I|`` on every grid block outside E (tier 1,
    ``certificates.block_envelopes_e``) or outside the band (tier 2,
    ``certificates.block_envelopes_band``). A selection is done at tier 1 when its peak in E
    beats the tier-1 bound (and its window fits in E), or when the blocks whose bound reaches the
    peak are settled exactly and stay below it (``refinement.refine``,
    :mod:`~arraysel.physics.psf.refinement`); at tier 2 likewise on the band; otherwise the exact
    path recomputes it.

    Stored tensors: :mod:`~arraysel.physics.psf.state`.

    From the model it reads only the interface :class:`~arraysel.physics.psf.operator.PSFModel`
    states (``setup``, ``n_elements``, ``transmits``, ``x_grid``, ``z_grid``, ``margin``,
    ``block``, ``dtype``, ``cdtype``, ``device``).
    """

    #: largest memory of the strips' pair images (tier 2) kept; above it they are not built and
    #: loose blocks beside E are beamformed exactly
    strip_max_bytes = 1 << 30
    #: bound of the relative L2 error of a kernel from a sketched basis (probes with more than
    #: about 68 elements), above which it is recomputed exactly: its bound carries a bound of
    #: what the sketch missed, so it is looser than the actual error (``docs/performance.md``
    #: gives the bounds and errors measured); 5e-2 certifies SI-MSE <= 2.5e-3 (the exact Gram
    #: build of small probes certifies 5e-3)
    sketch_kernel_tol = 5e-2
    #: half side (pixels) of the core around the scatterer whose exact pair images are kept
    core = 16

    def __init__(self, model, layout: BasisLayout | None = None):
        """A basis of ``model`` on ``layout`` (default :meth:`BasisLayout.of
        <arraysel.physics.psf.layout.BasisLayout.of>`) holding no tensors and no parts yet:
        :meth:`build` and :meth:`from_state` fill it."""
        self.model = model
        self.layout = layout if layout is not None else BasisLayout.of(model, self.core)
        #: the peak certificates (:class:`~arraysel.physics.psf.certificate.Certificates`)
        self.certificates: Certificates | None = None
        #: the certified kernels (:class:`~arraysel.physics.psf.refinement.Refinement`)
        self.refinement: Refinement | None = None
        self._row_energy = None
        #: the full-rank basis this one was truncated from (:meth:`truncated`): kernels whose
        #: error bound fails here are retried there before the exact path
        self.finer = None

    def _attach_refinement(self, shared: Refinement | None = None):
        """Make :attr:`refinement` on this basis's images and certificates, with the kernel
        tolerance of its build (:attr:`sketch_kernel_tol` for a sketched one); ``shared``: the
        refinement of the basis this view comes from, whose caches and counts it shares (the
        view's certificates are then a :meth:`~arraysel.physics.psf.certificate.Certificates.view`
        of that basis's)."""
        tol = self.sketch_kernel_tol if self.missed > 0 else None
        if shared is not None:
            tol = shared.kernel_tol
            self.certificates = self.certificates.view()
        self.refinement = Refinement(self, self.certificates, kernel_tol=tol, shared=shared)

    @classmethod
    def build(cls, model, rank_tol: float = BUILD_RANK_TOL) -> "PairBasis":
        """Build ``model``'s basis: the layout, the strips kept when they fit
        :attr:`strip_max_bytes`, the sample ranges, the windowed pair I/Q signals, the pair images
        of E compressed to ``rank_tol``, the strips' pair images and factors, the error constants
        and the certificates (logged step by step at INFO)."""
        self = cls(model)
        if self.layout.strip_bytes(torch.finfo(model.dtype).bits // 8, BasisBuilder.strip_rank) > \
                self.strip_max_bytes:
            self.layout = self.layout.without_strips()
        progress = BuildProgress(model, self)
        builder = BasisBuilder(model, self.layout, Certificates.segment)
        lo, hi = builder.sample_ranges()
        progress.step("sample ranges")
        X = builder.windowed_pair_iq()
        progress.step("pair I/Q signals")
        plan1 = builder.local_plan(self.rows, torch.arange(self.cols.start, self.cols.stop))
        svd = builder.compress(X, plan1, rank_tol, progress)
        del plan1
        self.U, self.V, self.rank, self.rank_tail = svd.U, svd.V, svd.rank, svd.rank_tail
        self.core_images, self.missed = svd.core_images, svd.missed
        if self.npix2:
            H2 = builder.dense_pair_images(X, builder.local_plan(self.rows, self.strip_cols))
            col2 = float(pixel_norms(H2).max())
            H2 = H2[:, self.h2_cols]
            factors = builder.strip_factors(H2)
            self.strip_images = H2.to(model.device, model.dtype)
            del H2
            progress.step("strip pair images")
        else:
            col2 = 0.0
            self.strip_images = torch.zeros(self.pairs_e.numel(), 0, dtype=model.dtype, device=model.device)
            factors = builder.strip_factors(self.strip_images.double())
        self.strip_left, self.strip_right, self.strip_sigma, self.strip_sigma_next = factors
        self.error = ErrorConstants(pixel_residual=svd.pixel_residual, column_e=svd.column_norm,
                                    column_strips=col2, spectral_tail=svd.spectral_tail)
        self.certificates = Certificates.build(model, self.layout, X, lo, hi, builder.window_offset,
                                               builder.window_samples)
        self._attach_refinement()
        progress.close()
        return self

    @classmethod
    def from_state(cls, model, state: dict) -> "PairBasis":
        """``model``'s basis from its stored tensors (:meth:`state`)."""
        self = cls(model)
        restore_state(self, state)
        self._attach_refinement()
        return self

    def state(self) -> dict:
        """The stored tensors by name (:func:`arraysel.physics.psf.state.basis_state`)."""
        return basis_state(self)

    def truncated(self, rank: int) -> "PairBasis":
        """A view of this basis keeping the first ``rank`` singular vectors of the pair images on
        E, with its error constants widened to stay rigorous: the residual pixel-column norm
        grows by the dropped rows of V (``rho^2 + max_p sum_{i >= rank} |V_ip|^2``) and the
        largest discarded singular value becomes ``|V_rank|``."""
        import copy

        out = copy.copy(self)
        r = int(check_number("rank", rank, lo=1, integer=True))
        if self.U is None or r >= self.rank:
            out._attach_refinement(shared=self.refinement)
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
        out.__dict__.pop("_swap_rows", None)  # rows of U V at the stored rank: not this view's
        out.rank_tail = self.rank_tail + float(sig.sum()) / total
        out.finer = self
        out._attach_refinement(shared=self.refinement)
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
        m, cert = self.model, self.certificates
        item = m.dtype.itemsize
        env = len(m.transmits) * m.n_elements * cert.max_run * (cert.window_samples // cert.segment) * item
        images = 2 * 2 * self.npix * item
        bounds = self.certificates.block_envelopes_e.shape[0] * (8 + item)
        kernels = 2 * 2 * m.setup.window ** 2 * item
        return env + images + bounds + kernels

    def kernels(self, w: torch.Tensor, env: torch.Tensor | None = None, images: tuple | None = None):
        """Kernels (B, win, win) of selections ``w`` and a (B,) bool tensor, True where certified
        (else the caller recomputes them): :meth:`Refinement.kernels
        <arraysel.physics.psf.refinement.Refinement.kernels>`. ``env``: the envelopes of ``w``
        (:meth:`Certificates.envelopes <arraysel.physics.psf.certificate.Certificates.envelopes>`
        or, for one-swap neighbours, ``swap_envelopes``), ``images``: its images on E with their
        error bounds (:meth:`images` with ``with_error``, or :meth:`swap_images`), when the caller
        has them."""
        return self.refinement.kernels(w, env=env, images=images)

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
        return (img, *self._image_errors(c, cu if self.U is not None else None))

    def _image_errors(self, c: torch.Tensor, cu: torch.Tensor | None) -> tuple[torch.Tensor, torch.Tensor]:
        """(B,) per-pixel and window error bounds of the images of pair products ``c`` whose
        coefficients are ``cu = c @ U`` (None without compression): see :meth:`images`."""
        with torch.no_grad():
            cn2 = (c.detach() ** 2).sum(1)
            resid = (cn2 - (cu.detach() ** 2).sum(1)).clamp(min=0).sqrt() if cu is not None else 0 * cn2
            rnd = self._rounding(c.detach(), cn2)
            eps = resid * self.error.pixel_residual + rnd
            win_err = resid * self.error.spectral_tail + rnd * self.model.setup.window
        return eps, win_err

    #: largest memory (bytes) of the pair images on E (rows of ``U V``) that :meth:`swap_images`
    #: keeps from one neighbourhood to the next (all P rows: 0.35 GB in float32 on the paper
    #: scene, 1.4 GB for 128 elements), and never more than the memory cap
    #: ``ARRAYSEL_MEMORY_GIB`` (:func:`~arraysel.physics.psf.settings.memory_limit_bytes`); beyond
    #: it the rows a neighbourhood needs are formed and dropped
    swap_rows_max_bytes = 3 << 29

    def swap_rows_cap(self) -> int:
        """Bytes of pair-image rows :meth:`pair_rows` may keep: :attr:`swap_rows_max_bytes`, at
        most the memory cap ``ARRAYSEL_MEMORY_GIB``."""
        from arraysel.physics.psf.settings import memory_limit_bytes

        return min(int(self.swap_rows_max_bytes), memory_limit_bytes())

    def bytes_of_pair_rows(self) -> int:
        """Bytes of all pair-image rows on E (what :meth:`fill_pair_rows` keeps)."""
        return int(self.pairs_e.numel() * self.V.shape[1] * self.V.element_size())

    #: moves a neighbourhood base is carried by row updates (:meth:`swap_images`) before it is
    #: formed afresh from the basis
    swap_base_refresh = 64

    #: the most elements a selection may differ by from the last base for :meth:`swap_base` to
    #: update that base by rows instead of forming it afresh (2 m column gathers of the pair rows
    #: against the product of the selection's coefficients: docs/performance.md, tuning constants)
    swap_base_moved_max = 8

    #: bytes the neighbourhood bases of :meth:`swap_base` may keep: the images and element rows
    #: of the latest selections (float64, ``16 (Ne + 1) Npix`` bytes each: 43 MB on a 128-element
    #: scene, 22 MB on the paper scene), so that descents taking turns (a search's race) each find
    #: their own base instead of forming it afresh at every turn; at least one is kept, and at
    #: most a quarter of the memory cap ``ARRAYSEL_MEMORY_GIB``
    swap_base_max_bytes = 3 << 28

    def swap_base(self, mask: torch.Tensor, bases=None):
        """``(y, G)`` of the 0/1 selection ``mask``, float64: its image on E (1, 2 Npix) and the
        rows ``G_e = sum_{j in mask} H_ej`` (Ne, 2 Npix): from ``bases``, the bases of the latest
        selections that the caller (a search's objective) keeps
        (:class:`arraysel.objective.swapbases.SwapBases`: kept, carried by rows from a kept one
        that a move of at most :attr:`swap_base_moved_max` elements reaches, for at most
        :attr:`swap_base_refresh` elements moved in a row, or formed afresh), else formed afresh
        (:func:`~arraysel.physics.psf.swapbase.form_base`)."""
        if bases is None:
            return form_base(self, mask.cpu() != 0)
        return bases.base(self, mask)

    #: the cost of summing one pair-image row into a neighbour's image, in columns of the product
    #: ``(c U) V`` (docs/performance.md, tuning constants): :meth:`swap_images` sums rows while a
    #: neighbour's ``2 m (m + 1)`` of them cost less than the product, and forms the product beyond
    move_row_cost = 20

    # the neighbours' images and the pair-image rows: arraysel.physics.psf.neighbourimages
    def pair_lookup(self) -> torch.Tensor:
        """(Ne, Ne) long: the index of pair (e, j) (either order) among :attr:`pairs_e`,
        :attr:`pairs_j` (:func:`~arraysel.physics.psf.neighbourimages.pair_lookup`)."""
        return neighbourimages.pair_lookup(self)

    def pair_rows(self, pairs: torch.Tensor) -> torch.Tensor:
        """(n, 2 Npix) pair images on E ([re | im]) of the pairs ``pairs`` (long (n,)), kept while
        they fit :meth:`swap_rows_cap` (:func:`~arraysel.physics.psf.neighbourimages.pair_rows`)."""
        return neighbourimages.pair_rows(self, pairs)

    def fill_pair_rows(self, block: int = 256) -> bool:
        """Form now every pair-image row :meth:`pair_rows` keeps; whether all are kept
        (:func:`~arraysel.physics.psf.neighbourimages.fill_pair_rows`)."""
        return neighbourimages.fill_pair_rows(self, block)

    def _all_rows(self):
        """Every pair-image row on E as one numpy array (P, 2 Npix) when all are at hand, else
        None (:func:`~arraysel.physics.psf.neighbourimages.all_rows`)."""
        return neighbourimages.all_rows(self)

    def _move_terms(self, a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The pair-image rows moves add to an image (:func:`~arraysel.physics.psf.neighbourimages.move_terms`)."""
        return neighbourimages.move_terms(self, a, b)

    def swap_images(self, mask: torch.Tensor, out: torch.Tensor, into: torch.Tensor, w: torch.Tensor, bases=None):
        """:meth:`images` ``(w, with_error=True)`` of the neighbours ``w`` of the selection ``mask``
        that switch ``out`` off and ``into`` on (:func:`~arraysel.physics.psf.neighbourimages.swap_images`)."""
        return neighbourimages.swap_images(self, mask, out, into, w, bases)

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
        x = self._complex_channels(w @ self.certificates.pair_channels, w.shape[0]).transpose(1, 2)
        return x * w.to(x.dtype)[:, None, :, None]

    def _complex_channels(self, y: torch.Tensor, n: int) -> torch.Tensor:
        """(n, Ne, ntx, T) complex, samples in time order, from rows of ``pair_channels``' layout
        (n, Ne * 2 * ntx * T)."""
        ne, sg, T = self.model.n_elements, self.certificates.segment, self.certificates.window_samples
        y = y.view(n, ne, 2, len(self.model.transmits), sg, T // sg)
        x = torch.complex(y[:, :, 0], y[:, :, 1])
        return x.transpose(-1, -2).reshape(n, ne, len(self.model.transmits), T)

    def pair_iq(self) -> torch.Tensor:
        """The windowed pair I/Q signals (Ne tx j, ntx, Ne rx e, T) complex (sample t of the window
        of (n, e) is sample ``off[n, e] + t`` of the record)."""
        return self._complex_channels(self.certificates.pair_channels, self.model.n_elements).transpose(1, 2)


# the layout's fields read as the basis's own attributes (``basis.rows`` for ``basis.layout.rows``)
for _name in LAYOUT_FIELDS:
    setattr(PairBasis, _name, _layout_attribute(_name))
del _name
