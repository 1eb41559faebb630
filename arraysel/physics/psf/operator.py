"""Point-spread function (PSF) synthesis for batches of element selections.

The paper scene (``docs/paper-scene.md``): one point scatterer, ``n_tx`` plane-wave
transmits, RF -> I/Q -> delay-and-sum, the compound image summed coherently,
and the complex 128 x 128 window centred on the peak of its magnitude,
normalised to unit L2 norm, is the PSF kernel ``kappa``.

A selection enters as element weights ``m`` (``(B, Ne)``, 0/1 masks or soft
weights in [0, 1]) used both as TX apodization and as RX channel weights. The exact
path also takes separate receive weights ``r`` (``receive=``; ``m`` is then the TX
apodization alone): the image is bilinear, ``I(p) = sum_{e, j} m_j r_e G_ej(p)``
with ``G_ej`` the image of the echo sent by ``j`` and received by ``e``; ``r = m``
is the shared selection, the same computation. The pair basis of the fast path
holds ``H_ej = G_ej + G_je``, which is enough only for ``r = m``, so a separate
receive aperture is evaluated on the exact path.
For one scatterer the echo received by element ``e`` is a superposition of
the contributions transmitted by every element ``j``, and every later step
(inverse FFT, demodulation, DAS, compounding) is linear, so the compound
image is a quadratic form of the weights::

    I(p) = sum_{e, j} m_e m_j H_ej(p)

:class:`PSFModel` offers two ways to evaluate it:

* the *exact path* (:meth:`PSFModel.image`) runs the simulator -> RF -> I/Q
  -> DAS pipeline for each selection, on any set of pixels (the whole grid by
  default), chunked over pixels to bound memory;
* the *fast path* (:meth:`PSFModel.kernels`) precomputes the pair images
  ``H_ej`` on a region ``E`` around the scatterer (the PSF window plus a
  margin), so that the image of a batch of selections is one matrix product
  of the pair products ``m_e m_j`` with ``H`` (a truncated SVD ``U V`` of it,
  with a rigorous bound of the truncation error of every pixel and window).
  Because the kernel's peak is searched for over the whole grid, the fast path also
  precomputes, for 8 x 8 blocks of pixels outside ``E``, the samples each
  block reads from each channel: the envelopes of a selection's I/Q channels
  there bound ``|I|`` on the block (``PairBasis``, certificates). A selection
  whose peak in ``E`` (less its error bound) beats every block bound, or whose
  loose blocks are settled exactly (strip pair images, their low-rank
  factors, or block-wise DAS), and whose window fits in ``E``, provably has
  its global peak there; a kernel whose error bound is too large is retried
  at the stored rank; any other selection is recomputed by the exact path on
  the whole grid. The result is therefore the scene's kernel, up to the stated
  error bound (5e-3 relative L2; the actual error is typically below 1e-3),
  for every selection.
"""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np
import torch

from arraysel.errors import NumericalError, ParameterError, SelectionError, check_number
from arraysel.physics.beamform import das_apply, das_plan, iq_matrix
from arraysel.physics.delays import plane_wave_delays
from arraysel.physics.psf.basis import PairBasis
from arraysel.physics.psf import sizing
from arraysel.physics.psf.settings import basis_limit_bytes, memory_limit_bytes
from arraysel.physics.psf.setup import PSFSetup
from arraysel.physics.psf.store import load_or_build_basis, stored_window_estimate
from arraysel.physics.psf.window import window_and_normalise
from arraysel.physics.simus import (element_responses, grid_for_points, probe_response, pulse_spectrum,
                                    spectra_to_rf, spectra_to_rf_maps)

_log = logging.getLogger(__name__)


@dataclass
class Transmit:
    """One plane-wave transmit of a :class:`PSFModel` (spectra in units of ``image_scale``)."""

    delays: np.ndarray          #: (Ne,) transmit delays (s)
    grid: object                #: the simulator's FrequencyGrid
    tx_field: torch.Tensor      #: (Ne, F) field at the scatterer from each transmitting element, R_j e^{i w tau_j}
    rx_factor: torch.Tensor     #: (Ne, F) receive factor C(f) R_e(f) of each receiving element
    iq_band: tuple              #: (fs, fc, bandwidth %) of the I/Q demodulation

    def iq_map(self, samples: slice = slice(None)) -> torch.Tensor:
        """Real (2F, 2T) float64 matrix ``M`` with ``[Re S, Im S] @ M = [Re IQ, Im IQ]``, where
        ``IQ = spectra_to_rf(S, grid) @ iq_matrix.T``: the exact path's spectra -> RF -> I/Q,
        composed in float64 (see :meth:`PSFModel.iq`). Only the I/Q ``samples`` wanted, if given
        (T their number)."""
        a, b = spectra_to_rf_maps(self.grid)
        # formed here only: the exact path keeps the map
        qt = iq_matrix(self.grid.n_time, *self.iq_band, rows=samples).T
        m = torch.cat([a.to(torch.complex128) @ qt, b.to(torch.complex128) @ qt], dim=0)  # (2F, T)
        return torch.cat([m.real, m.imag], dim=1)


def normalised_transmits(parts) -> tuple[float, list[Transmit]]:
    """The transmits of ``parts`` (``(delays, grid, G, RC, iq_band)`` each: ``G`` the transmit
    field and ``RC`` the receive factor at the scatterer, ``(Ne, F)`` complex) with ``G`` and
    ``RC`` divided by their largest magnitude over all transmits, and the physical value of one
    unit of what they produce (``image_scale``). A deep, attenuated or weak echo can lie below
    float32's normal range at its physical scale; the kernels are normalised, so only the unit
    changes. Raises :class:`NumericalError` when the echo is zero or not finite."""
    g_max = max(float(G.abs().max()) for _, _, G, _, _ in parts)
    rc_max = max(float(RC.abs().max()) for _, _, _, RC, _ in parts)
    if not (g_max > 0 and rc_max > 0 and math.isfinite(g_max) and math.isfinite(rc_max)):
        raise NumericalError(f"the echo of the scatterer is zero or not finite (|G| max {g_max:.3g}, "
                             f"|RC| max {rc_max:.3g}): check depth, attenuation and reflectivity")
    return g_max * rc_max, [Transmit(delays=d, grid=g, tx_field=G / g_max, rx_factor=RC / rc_max, iq_band=b)
                            for d, g, G, RC, b in parts]



class PSFModel:
    """Batched, differentiable PSF synthesis for one scene.

    Parameters
    ----------
    setup : :class:`PSFSetup`.
    dtype : real dtype of the computation (torch.float32 or torch.float64).
    device : torch device.
    margin : pixels added on each side of the window for the fast path's
        exact region ``E``; block : side (pixels) of the bound blocks.
    fast : build (or load) the fast path's pair basis; False: the exact path only.
    plan_cache_elements : DAS plan entries (pixels x elements) the exact path keeps.
    rank_tol : energy fraction the fast path's truncated SVD of the pair images on ``E`` may
        discard (``benchmarks/work_precision.py`` measures error and time against it). The
        stored basis keeps more (``BUILD_RANK_TOL`` of :mod:`~arraysel.physics.psf.basis`);
        every kernel carries a rigorous error bound, and one whose bound exceeds ``kernel_tol``
        of its norm is retried at the stored rank, then on the exact path, so this trades speed
        only against how often that happens.

    The precomputation itself always runs in float64.

    Attributes used by the pair basis (its whole view of the model): ``setup``,
    ``n_elements``, ``transmits`` (:class:`Transmit` records), ``x_grid``, ``z_grid`` (float64
    pixel coordinates), ``margin``, ``block``, ``dtype``, ``cdtype``, ``device``.
    """

    def __init__(self, setup: PSFSetup, dtype=torch.float32, device="cpu", margin: int = 8, block: int = 8,
                 fast: bool = True, plan_cache_elements: int = 80_000_000, rank_tol: float = 1e-6):
        if dtype not in (torch.float32, torch.float64):
            raise ParameterError(f"dtype = {dtype} is not allowed; choose torch.float32 or torch.float64")
        self.setup = setup
        self.dtype = dtype
        self.cdtype = torch.complex64 if dtype == torch.float32 else torch.complex128
        self.device = torch.device(device)
        self.n_elements = setup.probe.n_elements
        self.margin = int(check_number("margin", margin, lo=0, hi=4096, integer=True))
        self.block = int(check_number("block", block, lo=1, hi=4096, integer=True))
        self.rank_tol = float(check_number("rank_tol", rank_tol, lo=0, hi=1, lo_open=True, hi_open=True))
        self._build_transmits()
        self.x_grid = torch.as_tensor(setup.x, dtype=torch.float64)
        self.z_grid = torch.as_tensor(setup.z, dtype=torch.float64)
        self._plans: dict = {}
        self._iq_maps: dict = {}  # transmit -> its spectra -> I/Q map in the model's dtype (exact path)
        self._plan_elements = 0
        #: DAS plan entries (pixels x elements) kept in memory for the exact path
        self.plan_cache_elements = plan_cache_elements
        #: memory (bytes) the exact path may use (``ARRAYSEL_MEMORY_GIB``); its batches follow from it
        self.memory_limit = memory_limit_bytes()
        #: the exact path's baseline: interpreter, torch and the model (a constant: what else the
        #: process holds is not this scene's to budget)
        self.baseline_bytes = sizing._BASELINE_BYTES
        #: memory other models of the same objective keep (their DAS plans), set by the objective
        self.other_bytes = 0
        sizing.check_exact_memory(self)
        #: the certified fast path (a :class:`~arraysel.physics.psf.basis.PairBasis` truncated to
        #: ``rank_tol``), or None when it is off or over its memory cap
        self.basis: PairBasis | None = None
        if fast:
            # a cached basis carries the window estimate of the memory guard (the same number,
            # without computing the plans it comes from)
            self._window_samples = stored_window_estimate(self)
            need = self.basis_bytes()
            limit = basis_limit_bytes()
            if need > limit:
                _log.warning("PSF fast path disabled: its precomputation would need %.1f GiB (> %.1f GiB, "
                             "set ARRAYSEL_BASIS_MAX_GIB to allow more); using the exact path",
                             need / 2 ** 30, limit / 2 ** 30)
            else:
                full = load_or_build_basis(self)
                self.basis = full.truncated(full.rank_for(self.rank_tol))
        self._ref = None

    # ------------------------------------------------------------------ sizing
    # the memory and time sizing lives in arraysel.physics.psf.sizing; these are its entry points
    def basis_bytes(self) -> int:
        """Estimated peak memory (bytes) of building the fast path's basis (:func:`sizing.basis_bytes
        <arraysel.physics.psf.sizing.basis_bytes>`)."""
        return sizing.basis_bytes(self)

    def basis_stored_bytes(self) -> int:
        """Upper estimate (bytes) of the stored basis (:func:`~arraysel.physics.psf.sizing.basis_stored_bytes`)."""
        return sizing.basis_stored_bytes(self)

    def basis_build_seconds(self) -> float:
        """Estimated wall time (s) of building the basis (:func:`~arraysel.physics.psf.sizing.basis_build_seconds`)."""
        return sizing.basis_build_seconds(self)

    def window_estimate(self) -> int:
        """Samples per channel window, estimated once (:func:`~arraysel.physics.psf.sizing.window_estimate`)."""
        return sizing.window_estimate(self)

    def _estimate_window(self) -> int:
        return sizing.estimate_window(self)

    def plan_cache_bytes(self) -> int:
        """Memory (bytes) of the DAS plans the exact path keeps (:func:`~arraysel.physics.psf.sizing.plan_cache_bytes`)."""
        return sizing.plan_cache_bytes(self)

    def plan_cache_limit(self) -> int:
        """DAS plan entries the exact path keeps (:func:`~arraysel.physics.psf.sizing.plan_cache_limit`)."""
        return sizing.plan_cache_limit(self)

    def model_bytes(self) -> int:
        """Memory (bytes) of the model's own tensors (:func:`~arraysel.physics.psf.sizing.model_bytes`)."""
        return sizing.model_bytes(self)

    def exact_bytes(self, batch: int, pixels: int | None = None) -> int:
        """Peak resident memory (bytes) of an exact-path batch (:func:`~arraysel.physics.psf.sizing.exact_bytes`)."""
        return sizing.exact_bytes(self, batch, pixels)

    def exact_chunking(self, batch: int | None = None) -> tuple[int, int]:
        """(masks per batch, pixels per DAS call) of the exact path (:func:`~arraysel.physics.psf.sizing.exact_chunking`)."""
        return sizing.exact_chunking(self, batch)

    #: memory (bytes) of the per-selection tensors of one fast-path batch (:meth:`masks_per_batch`)
    fast_batch_bytes = 256 << 20

    def masks_per_batch(self) -> int:
        """Masks an evaluation should hand to :meth:`kernels` at once (:func:`~arraysel.physics.psf.sizing.masks_per_batch`)."""
        return sizing.masks_per_batch(self)

    def exact_seconds_per_mask(self, batch: int | None = None) -> float:
        """Estimated wall time (s) of one mask on the exact path (:func:`~arraysel.physics.psf.sizing.exact_seconds_per_mask`)."""
        return sizing.exact_seconds_per_mask(self, batch)

    # ------------------------------------------------------------------ exact path
    def _build_transmits(self):
        s = self.setup
        probe, acq = s.probe, s.acq
        xs, zs = s.scatterer_position
        xt = torch.tensor([xs], dtype=torch.float64)
        zt = torch.tensor([zs], dtype=torch.float64)
        delays_all = plane_wave_delays(probe, list(s.tilts), acq.c)
        parts = []
        for delays in delays_all:
            grid = grid_for_points(xt, zt, delays, probe, acq, s.options)
            f = grid.f
            R = element_responses(xt, zt, f, probe, acq.c, acq.attenuation, s.options)[0]  # (Ne, F)
            w = 2 * math.pi * f
            tau = torch.as_tensor(delays, dtype=torch.float64)
            G = R * torch.polar(torch.ones_like(tau[:, None] * w), tau[:, None] * w)
            H = probe_response(f, probe.fc, probe.bandwidth)
            P = pulse_spectrum(f, probe.fc, acq.tx_cycles)
            C = P * H * H * (grid.df * probe.width * s.reflectivity)
            band = (acq.fs, probe.fc, probe.bandwidth if s.iq_bandwidth is None else s.iq_bandwidth)
            parts.append((delays, grid, G, R * C[None, :], band))
        # spectra, RF, I/Q and images are in units of ``image_scale`` (see normalised_transmits)
        #: physical value of one unit of :meth:`spectra`, :meth:`rf`, :meth:`iq` and :meth:`image`
        self.image_scale, self.transmits = normalised_transmits(parts)

    def _weights(self, weights) -> torch.Tensor:
        w = weights if isinstance(weights, torch.Tensor) else torch.as_tensor(np.asarray(weights))
        if w.dim() == 1:
            w = w[None]
        if w.dim() != 2 or w.shape[-1] != self.n_elements:
            raise SelectionError(f"weights must have shape (B, {self.n_elements}), got {tuple(w.shape)}")
        w = w.to(device=self.device, dtype=self.dtype)
        return w

    def _receive(self, w: torch.Tensor, receive) -> torch.Tensor:
        return receive_weights(w, receive, self._weights)

    def spectra(self, weights, tx: int, receive=None) -> torch.Tensor:
        """Received spectra (B, Ne, F) of transmit ``tx`` for weights (B, Ne), in units of ``image_scale``;
        ``weights`` are the TX apodization and the RX channel weights, or the TX apodization
        alone when ``receive`` (B, Ne) gives the RX channel weights."""
        t = self.transmits[tx]
        w = self._weights(weights)
        r = self._receive(w, receive)
        G = t.tx_field.to(self.device, self.cdtype)
        RC = t.rx_factor.to(self.device, self.cdtype)
        field_ = w.to(self.cdtype) @ G  # (B, F): field at the scatterer
        return r.to(self.cdtype)[:, :, None] * RC[None] * field_[:, None, :]

    def rf(self, weights, tx: int, receive=None) -> torch.Tensor:
        """RF signals (B, Ne, T) of transmit ``tx`` (element-major, time last), in units of ``image_scale``."""
        return spectra_to_rf(self.spectra(weights, tx, receive), self.transmits[tx].grid)

    def iq(self, weights, tx: int, receive=None) -> torch.Tensor:
        """I/Q signals (B, Ne, T) of transmit ``tx``: the I/Q demodulation of :meth:`rf`, computed
        from the spectra in one product with the composed linear map (:meth:`Transmit.iq_map`,
        formed on first use and kept in the model's dtype).

        Composing the maps in float64 first matters in float32: a strongly attenuated echo has
        out-of-band (low-frequency) content orders of magnitude above the in-band part that forms
        the PSF; an RF record in float32 carries rounding noise at the level of the former across
        the whole band, which the I/Q filter would pass. Here each spectral bin enters with the
        weight the filter gives it, so rounding stays relative to what reaches the I/Q signal.
        """
        if tx not in self._iq_maps:
            self._iq_maps[tx] = self.transmits[tx].iq_map().to(self.device, self.dtype)
        s = self.spectra(weights, tx, receive)
        y = torch.cat([s.real, s.imag], dim=-1) @ self._iq_maps[tx]
        t = y.shape[-1] // 2
        return torch.complex(y[..., :t], y[..., t:])

    def _plan(self, tx: int, rows: slice, cols: slice):
        """DAS plan of transmit ``tx`` on grid rows/cols; whole-grid plans are cached by row blocks."""
        key = (tx, rows.start, rows.stop, cols.start, cols.stop)
        plan = self._plans.get(key)
        if plan is None:
            s = self.setup
            Z, X = torch.meshgrid(self.z_grid[rows], self.x_grid[cols], indexing="ij")
            plan = das_plan(X, Z, self.transmits[tx].delays, s.probe, s.acq.fs, s.acq.c,
                            self.transmits[tx].grid.n_time, fnumber=s.fnumber, fc=s.probe.fc)
            plan.w = plan.w.to(self.device, self.dtype)
            plan.rot = plan.rot.to(self.device, self.cdtype)
            plan.i0 = plan.i0.to(self.device)
            size = plan.i0.numel()
            if self._plan_elements + size <= self.plan_cache_limit():
                self._plans[key] = plan
                self._plan_elements += size
        return plan

    def image(self, weights, rows: slice | None = None, cols: slice | None = None,
              rows_per_chunk: int | None = None, receive=None) -> torch.Tensor:
        """Exact compound image (B, nz', nx') on grid rows/cols (default: whole grid).

        In units of :attr:`image_scale`; differentiable with respect to ``weights`` (and
        ``receive``: separate RX channel weights (B, Ne), ``weights`` then the TX apodization).
        """
        rows = rows or slice(0, self.setup.n_z)
        cols = cols or slice(0, self.setup.n_x)
        w = self._weights(weights)
        r = self._receive(w, receive)
        iqs = [self.iq(w, n, None if receive is None else r) for n in range(len(self.transmits))]
        nz = rows.stop - rows.start
        nx = cols.stop - cols.start
        if rows_per_chunk is None:
            rows_per_chunk = max(1, (2 ** 21) // max(1, nx * self.n_elements))
        # DAS of a plan chunk in pixel sub-chunks, so that the (B, pixels x Ne) temporaries fit
        sub = self.exact_chunking(int(w.shape[0]))[1]
        out = []
        for r0 in range(rows.start, rows.stop, rows_per_chunk):
            r = slice(r0, min(rows.stop, r0 + rows_per_chunk))
            acc = 0
            for n, iq in enumerate(iqs):
                p = self._plan(n, r, cols)
                npix = p.i0.shape[0]
                if npix <= sub:
                    acc = acc + das_apply(iq, p.i0, p.w, p.rot)
                else:
                    acc = acc + torch.cat([das_apply(iq, p.i0[j:j + sub], p.w[j:j + sub], p.rot[j:j + sub])
                                           for j in range(0, npix, sub)], dim=-1)
            out.append(acc.reshape(w.shape[0], r.stop - r.start, nx))
        return torch.cat(out, dim=1) if len(out) > 1 else out[0].reshape(w.shape[0], nz, nx)

    def kernels_exact(self, weights, receive=None) -> torch.Tensor:
        """PSF kernels (B, window, window) from the exact whole-grid image, in batches of
        :meth:`exact_chunking`'s size (bounded memory whatever B); ``receive``: separate RX
        channel weights (B, Ne), ``weights`` then the TX apodization."""
        w = self._weights(weights)
        r = None if receive is None else self._receive(w, receive)
        step = self.exact_chunking()[0]
        if w.shape[0] <= step:
            return window_and_normalise(self.image(w, receive=r), self.setup.window)
        return torch.cat([window_and_normalise(self.image(w[i:i + step], receive=None if r is None else
                                                          r[i:i + step]), self.setup.window)
                          for i in range(0, w.shape[0], step)])

    # ------------------------------------------------------------------ fast path
    def kernels(self, weights, return_info: bool = False, receive=None):
        """PSF kernels (B, window, window) complex; differentiable w.r.t. weights.

        Uses the precomputed pair basis when the peak provably lies in its
        region, the exact path otherwise. With ``receive`` (separate RX channel weights (B, Ne),
        ``weights`` then the TX apodization) the exact path (the pair basis is symmetric in
        transmit and receive).
        """
        w = self._weights(weights)
        if receive is not None:
            k = self.kernels_exact(w, receive=receive)
            return (k, torch.ones(w.shape[0], dtype=torch.bool)) if return_info else k
        if self.basis is None:
            k = self.kernels_exact(w)
            return (k, torch.zeros(w.shape[0], dtype=torch.bool)) if return_info else k
        return self._fast_or_exact(w, return_info)

    def _fast_or_exact(self, w: torch.Tensor, return_info: bool, **basis_inputs):
        """The basis's kernels of weights ``w``, those it does not settle from the exact path;
        ``basis_inputs`` (``env``, ``images``) go to :meth:`PairBasis.kernels`."""
        k, ok = self.basis.kernels(w, **basis_inputs)
        bad = torch.nonzero(~ok).flatten()
        if bad.numel():
            ke = self.kernels_exact(w[bad])
            k = k.clone() if not k.requires_grad else k
            k = k.index_put((bad,), ke.to(k.dtype)) if k.requires_grad else k.index_copy(0, bad, ke.to(k.dtype))
        return (k, ~ok) if return_info else k

    def swap_kernels(self, mask, out, into, return_info: bool = False, bases=None):
        """:meth:`kernels` (no gradient) of the neighbours of the 0/1 selection ``mask`` (Ne,) that
        switch the elements ``out[b]`` off and ``into[b]`` on (int (B,): one-swap neighbours, or
        (B, m): m elements each, ``-1`` for none). The same kernels, to rounding: on the CPU the certificates'
        envelopes of the neighbours are corrected from the selection's channel sums
        (:meth:`~arraysel.physics.psf.certificate.Certificates.swap_envelopes`) instead of being
        summed afresh, and their images on E from the selection's image and pair-image rows
        (:meth:`~arraysel.physics.psf.basis.PairBasis.swap_images`) instead of the product of
        every neighbour; everything after them (peaks, refinement, the exact path for a neighbour
        the certificates do not settle) is what :meth:`kernels` does. ``bases``: the selection
        bases the caller keeps (:meth:`~arraysel.physics.psf.basis.PairBasis.swap_base`)."""
        m = self._weights(mask)[0]
        a = torch.as_tensor(np.asarray(out, dtype=np.int64))
        b = torch.as_tensor(np.asarray(into, dtype=np.int64))
        a, b = (a.reshape(-1, 1) if a.ndim < 2 else a), (b.reshape(-1, 1) if b.ndim < 2 else b)
        w = m.repeat(a.shape[0], 1)
        for idx, val in ((a, 0), (b, 1)):
            r, c = torch.nonzero(idx >= 0, as_tuple=True)
            w[r.to(w.device), idx[r, c].to(w.device)] = val
        with torch.no_grad():
            if self.basis is None or not a.shape[0] or not self.basis.certificates.swaps_compiled(m):
                return self.kernels(w, return_info=return_info)
            return self._fast_or_exact(w, return_info, env=self.basis.certificates.swap_envelopes(m, a, b),
                                       images=self.basis.swap_images(m, a, b, w, bases))

    def reference_kernel(self) -> torch.Tensor:
        """The full-array kernel (window, window), cached."""
        if self._ref is None:
            with torch.no_grad():
                self._ref = self.kernels(torch.ones(1, self.n_elements))[0]
        return self._ref


def receive_weights(w: torch.Tensor, receive, check) -> torch.Tensor:
    """The receive weights of a batch whose transmit weights are ``w``: ``w`` itself (one shared
    aperture) when ``receive`` is None, else ``receive`` checked by ``check`` and of ``w``'s shape."""
    if receive is None:
        return w
    r = check(receive)
    if r.shape != w.shape:
        raise SelectionError(f"receive weights must have the transmit weights' shape {tuple(w.shape)}, "
                             f"got {tuple(r.shape)}")
    return r
