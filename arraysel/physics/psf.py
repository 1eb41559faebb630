"""Point-spread function (PSF) synthesis for batches of element selections.

The paper scene (SPEC §1): one point scatterer, ``n_tx`` plane-wave
transmits, RF -> I/Q -> delay-and-sum, the compound image summed coherently,
and the complex 128 x 128 window centred on the peak of its magnitude,
normalised to unit L2 norm, is the PSF kernel ``kappa``.

A selection enters as element weights ``m`` (``(B, Ne)``, 0/1 masks or soft
weights in [0, 1]) used both as TX apodization and as RX channel weights.
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
  Because the SPEC searches the peak over the whole grid, the fast path also
  precomputes, for 8 x 8 blocks of pixels outside ``E``, the samples each
  block reads from each channel: the envelopes of a selection's I/Q channels
  there bound ``|I|`` on the block (``_PairBasis``, certificates). A selection
  whose peak in ``E`` (less its error bound) beats every block bound, or whose
  loose blocks are settled exactly (strip pair images, their low-rank
  factors, or block-wise DAS), and whose window fits in ``E``, provably has
  its global peak there; a kernel whose error bound is too large is retried
  at the stored rank; any other selection is recomputed by the exact path on
  the whole grid. The result is therefore the SPEC's kernel, up to the stated
  error bound (5e-3 relative L2; the actual error is typically below 1e-3),
  for every selection.
"""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field, fields

import numpy as np
import torch

from arraysel.physics.beamform import das_apply, das_plan, iq_matrix
from arraysel.io.cache import cache_dir  # noqa: F401  (re-exported: the cache lives in arraysel.io.cache)
from arraysel.physics.delays import plane_wave_delays
from arraysel.errors import NumericalError, ParameterError, SelectionError, check_number
from arraysel.physics.probes import Acquisition, Probe, check_sampling
from arraysel.physics.simus import (SimOptions, element_responses, grid_for_points, probe_response, pulse_spectrum,
                    spectra_to_rf, spectra_to_rf_maps)

_log = logging.getLogger(__name__)


@dataclass(frozen=True, repr=False)
class PSFSetup:
    """Everything the PSF of a selection depends on (a scene's physics part).

    probe, acq: transducer and acquisition (fs, c, attenuation, pulse cycles).
    tilts: plane-wave tilts (radians); TX delays are the full array's.
    n_x, n_z: image grid size; pixel: grid pitch (m, default (c/fs)/4);
        ``x_i = (i - n_x//2 + x_offset) pixel``, ``z_i = (i + z_offset) pixel``
        (offsets in whole pixels; ``x_offset`` is left out of the repr when 0,
        so that the cache keys of unshifted grids do not change).
    scatterer: (x, z) in metres (default: the pixel (x = x_offset pixel,
        z = (n_z//2 + z_offset) pixel), i.e. column n_x//2, row n_z//2).
    window: PSF window side (pixels).
    fnumber: receive f-number (0 = full aperture).
    iq_bandwidth: bandwidth (%) of the I/Q low-pass (default: the probe's).
    options: simulator accuracy settings.
    """

    probe: Probe
    acq: Acquisition
    tilts: tuple = tuple(np.deg2rad(np.linspace(-10, 10, 7)))
    n_x: int = 400
    n_z: int = 400
    pixel: float | None = None
    z_offset: int = 0
    scatterer: tuple | None = None
    reflectivity: float = 1.0
    window: int = 128
    fnumber: float = 0.0
    iq_bandwidth: float | None = None
    options: SimOptions = field(default_factory=SimOptions)
    x_offset: int = 0

    def __repr__(self) -> str:
        parts = [f"{f.name}={getattr(self, f.name)!r}" for f in fields(self)
                 if not (f.name == "x_offset" and self.x_offset == 0)]
        return f"{type(self).__qualname__}({', '.join(parts)})"

    def __post_init__(self):
        check_sampling(self.probe, self.acq)
        check_number("x_offset", self.x_offset, lo=-10 ** 6, hi=10 ** 6, integer=True)
        check_number("n_x", self.n_x, lo=2, hi=8192, integer=True)
        check_number("n_z", self.n_z, lo=2, hi=8192, integer=True)
        check_number("window", self.window, lo=2, hi=min(self.n_x, self.n_z), integer=True)
        if self.pixel is not None:
            check_number("pixel", self.pixel, lo=0, lo_open=True, hi=1.0)
        if len(self.tilts) < 1:
            raise ParameterError("tilts: at least one transmit is needed")
        for t in self.tilts:
            check_number("tilt (rad)", t, lo=-math.pi / 2, hi=math.pi / 2, lo_open=True, hi_open=True)
        check_number("fnumber", self.fnumber, lo=0.0, hi=100.0)
        check_number("reflectivity", self.reflectivity, lo=0.0, lo_open=True)
        xs, zs = self.scatterer_position
        if zs <= 0:
            raise ParameterError(f"scatterer depth z = {zs!r} m must be > 0 (in front of the array)")

    @property
    def pitch(self) -> float:
        return self.pixel if self.pixel is not None else self.acq.c / self.acq.fs / 4

    @property
    def x(self) -> np.ndarray:
        return (np.arange(self.n_x) - self.n_x // 2 + self.x_offset) * self.pitch

    @property
    def z(self) -> np.ndarray:
        return (np.arange(self.n_z) + self.z_offset) * self.pitch

    @property
    def scatterer_position(self) -> tuple[float, float]:
        if self.scatterer is not None:
            return float(self.scatterer[0]), float(self.scatterer[1])
        return float(self.x_offset * self.pitch), float((self.n_z // 2 + self.z_offset) * self.pitch)

    @property
    def scatterer_pixel(self) -> tuple[int, int]:
        """(row, column) of the grid pixel nearest the scatterer (may lie outside the grid)."""
        xs, zs = self.scatterer_position
        return int(round(zs / self.pitch - self.z_offset)), int(round(xs / self.pitch - self.x_offset)) + self.n_x // 2

    @property
    def wavelength(self) -> float:
        return self.acq.c / self.probe.fc


@dataclass
class _Transmit:
    delays: np.ndarray        # (Ne,)
    grid: object              # FrequencyGrid
    G: torch.Tensor           # (Ne, F) TX contributions R_j e^{i w tau_j}
    RC: torch.Tensor          # (Ne, F) RX spectra factor C(f) R_e(f)
    IQ: torch.Tensor          # (2F, 2T) real: [Re S, Im S] @ IQ = [Re I/Q, Im I/Q] (spectra -> RF -> I/Q)


def _window_start(peak: torch.Tensor, size: int, n: int) -> torch.Tensor:
    return torch.clamp(peak - size // 2, 0, n - size)


class PSFModel:
    """Batched, differentiable PSF synthesis for one scene.

    Parameters
    ----------
    setup : :class:`PSFSetup`.
    dtype : real dtype of the computation (torch.float32 or torch.float64).
    device : torch device.
    margin : pixels added on each side of the window for the fast path's
        exact region ``E``; block : side (pixels) of the bound blocks.
    rank_tol : energy fraction the fast path's truncated SVD of the pair images on ``E`` may
        discard (``benchmarks/work_precision.py`` measures error and time against it). The
        stored basis keeps more (``_BUILD_RANK_TOL``); every kernel carries a rigorous error
        bound, and one whose bound exceeds ``kernel_tol`` of its norm is retried at the stored
        rank, then on the exact path, so this trades speed only against how often that happens.

    The precomputation itself always runs in float64.
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
        self._xg = torch.as_tensor(setup.x, dtype=torch.float64)
        self._zg = torch.as_tensor(setup.z, dtype=torch.float64)
        self._plans: dict = {}
        self._plan_elements = 0
        #: DAS plan entries (pixels x elements) kept in memory for the exact path
        self.plan_cache_elements = plan_cache_elements
        #: memory (bytes) the exact path may use (``ARRAYSEL_MEMORY_GIB``); its batches follow from it
        self.memory_limit = memory_limit_bytes()
        #: the exact path's baseline: interpreter, torch and the model (a constant: what else the
        #: process holds is not this scene's to budget)
        self.baseline_bytes = _BASELINE_BYTES
        #: memory other models of the same objective keep (their DAS plans), set by the objective
        self.other_bytes = 0
        self._check_exact_memory()
        self.fast = None
        if fast:
            need = self.basis_bytes()
            limit = _basis_limit_bytes()
            if need > limit:
                _log.warning("PSF fast path disabled: its precomputation would need %.1f GiB (> %.1f GiB, "
                             "set ARRAYSEL_BASIS_MAX_GIB to allow more); using the exact path",
                             need / 2 ** 30, limit / 2 ** 30)
            else:
                full = _load_or_build_basis(self)
                self.fast = full.truncated(full.rank_for(self.rank_tol))
        self._ref = None

    def basis_bytes(self) -> int:
        """Estimated peak memory (bytes) of building the fast path's basis (see
        :class:`_PairBasis`): the windowed pair I/Q signals, the pair images of E (all of them
        for small probes, row blocks and a sketch for larger ones), the strips' pair images
        when they are kept, and the stored tensors."""
        s = self.setup
        ne = self.n_elements
        ntx = len(s.tilts)
        pairs = ne * (ne + 1) // 2
        rows = min(s.n_z, s.window + 2 * self.margin)
        cols = min(s.n_x, s.window + 2 * self.margin)
        npix, npix2 = rows * cols, rows * (s.n_x - cols)
        size = torch.finfo(self.dtype).bits // 8
        T = self._window_estimate()
        X = ntx * ne * T * ne * 8
        A = 2 * ntx * ne * T * ne * size
        sketch = _PairBasis.sketch_columns
        if pairs <= sketch:
            work = pairs * 2 * npix * 8 * 2 + pairs * pairs * 8 * 3
            rank = pairs
        else:
            blk = max(ne, _PairBasis.build_rows * max(1, 20736 // max(1, npix)))
            work = pairs * sketch * 8 * 2 + sketch * 2 * npix * 8 * 2 + 3 * blk * 2 * npix * 8
            rank = sketch
        strips = size * pairs * 2 * npix2
        if strips > _STRIP_MAX_BYTES:
            strips = 0
        stored = size * (pairs * rank + rank * 2 * npix + pairs * 2 * 1024) + A + strips
        return int(X + work + stored + (strips // size) * 8)

    def _window_estimate(self) -> int:
        """Samples per channel window (:meth:`_PairBasis._sample_ranges`), estimated from the
        DAS plans of a subsampled grid (every 8th row and column and the grid's edges); computed
        once per model (the memory guard and the cache's size hint both ask)."""
        if getattr(self, "_window_samples", None) is None:
            self._window_samples = self._estimate_window()
        return self._window_samples

    def _estimate_window(self) -> int:
        s = self.setup
        zi = torch.unique(torch.cat([torch.arange(0, s.n_z, 8), torch.tensor([s.n_z - 1])]))
        xi = torch.unique(torch.cat([torch.arange(0, s.n_x, 8), torch.tensor([s.n_x - 1])]))
        Z, X = torch.meshgrid(self._zg[zi], self._xg[xi], indexing="ij")
        span = 2
        for t in self.transmits:
            p = das_plan(X, Z, t.delays, s.probe, s.acq.fs, s.acq.c, t.grid.n_time, fnumber=s.fnumber, fc=s.probe.fc)
            valid = p.rot.abs() > 0
            if bool(valid.any()):
                hi = torch.where(valid, p.i0, torch.full_like(p.i0, -1)).amax(0)
                lo = torch.where(valid, p.i0, torch.full_like(p.i0, 1 << 40)).amin(0)
                ok = hi >= lo
                if bool(ok.any()):
                    span = max(span, int((hi - lo)[ok].max()) + 2)
        return -(-(span + 8) // 4) * 4

    # ------------------------------------------------------------------ exact path: memory
    # The exact path's peak resident memory, in bytes, for a batch of ``batch`` masks (no autograd):
    #   baseline: interpreter, torch and the model (``baseline_bytes``, a constant)
    # + DAS plans kept: entries (pixel, element, transmit) x (i0 + w + rot), capped at a quarter
    #   of ``memory_limit``; in a several-point objective also its siblings' plans and tensors
    #   (``other_bytes``)
    # + building one plan chunk: ~12 float64 (pixels x Ne) temporaries
    # + per mask: I/Q of every transmit (n_tx x Ne x T complex), one transmit's spectra and RF on
    #   the way, the whole-grid image (row chunks, their concatenation, its magnitude)
    # + one DAS call: _DAS_TEMPS (B, pixels x Ne) complex temporaries (gathered samples, their
    #   index, differences, products), its pixels chosen to keep this near _DAS_BYTES;
    # all but the baseline times _HEAP_FACTOR, the heap growth (fragmentation, blocks glibc
    # keeps) measured on top of the live tensors by ``benchmarks/exact_memory.py``.
    # :meth:`exact_chunking` picks the batch so the total stays within ``memory_limit``.

    def _sizes(self):
        c = 8 if self.dtype == torch.float32 else 16
        T = max(t.grid.n_time for t in self.transmits)
        nfft = max(t.grid.n_fft for t in self.transmits)
        F = max(int(t.grid.f.numel()) for t in self.transmits)
        return c, T, nfft, F

    def _plan_rows(self) -> int:
        return max(1, (2 ** 21) // max(1, self.setup.n_x * self.n_elements))

    def plan_cache_bytes(self) -> int:
        """Memory (bytes) of the DAS plans the exact path keeps (whole grid, every transmit, capped)."""
        c = 8 if self.dtype == torch.float32 else 16
        return self._plan_cache_limit() * (8 + c // 2 + c)

    def _plan_cache_limit(self) -> int:
        """Plan entries kept: ``plan_cache_elements``, at most a quarter of ``memory_limit``, at most all."""
        s = self.setup
        c = 8 if self.dtype == torch.float32 else 16
        quarter = self.memory_limit // 4 // (8 + c // 2 + c)
        return int(min(self.plan_cache_elements, quarter, len(self.transmits) * s.n_z * s.n_x * self.n_elements))

    def model_bytes(self) -> int:
        """Memory (bytes) of the model's own tensors: per transmit the spectra -> I/Q map (2F x 2T
        in the model's dtype) and the spectra factors (Ne x F complex128 twice)."""
        return sum(int(t.IQ.numel()) * t.IQ.element_size() + 2 * int(t.G.numel()) * 16
                   for t in self.transmits)

    def _per_mask_bytes(self) -> int:
        s = self.setup
        c, T, nfft, F = self._sizes()
        ne = self.n_elements
        return len(self.transmits) * ne * T * c + 2 * ne * (F + nfft) * c + (2 * c + c // 2) * s.n_z * s.n_x

    def _das_pixels(self, batch: int) -> int:
        s = self.setup
        c = self._sizes()[0]
        want = _DAS_BYTES // max(1, _DAS_TEMPS * batch * self.n_elements * c)
        return int(min(s.n_z * s.n_x, max(s.n_x, want)))

    def exact_bytes(self, batch: int, pixels: int | None = None) -> int:
        """Estimated peak resident memory (bytes) of the process during an exact-path evaluation of
        ``batch`` masks with DAS calls of ``pixels`` pixels (default: :meth:`exact_chunking`'s)."""
        s = self.setup
        c = self._sizes()[0]
        if pixels is None:
            pixels = self._das_pixels(batch)
        build = 12 * self._plan_rows() * s.n_x * self.n_elements * 8
        das = _DAS_TEMPS * batch * pixels * self.n_elements * c
        work = self.plan_cache_bytes() + self.other_bytes + build + batch * self._per_mask_bytes() + das
        return int(self.baseline_bytes + _HEAP_FACTOR * work)

    def exact_chunking(self, batch: int | None = None) -> tuple[int, int]:
        """(masks per batch, pixels per DAS call) of the exact path within ``memory_limit``.

        With ``batch`` given, only the pixels per DAS call are chosen for it.
        """
        if batch is None:
            batch = _EXACT_MAX_BATCH
            while batch > 1 and self.exact_bytes(batch) > self.memory_limit:
                batch = max(1, min(batch - 1, int(batch * 0.85)))
        return batch, self._das_pixels(batch)
    def masks_per_batch(self) -> int:
        """Masks an evaluation should hand to :meth:`kernels` at once (bounded memory on the exact path)."""
        if self.fast is not None:
            return _EXACT_MAX_BATCH
        return self.exact_chunking()[0]

    def exact_seconds_per_mask(self, batch: int | None = None) -> float:
        """Estimated wall time (s) of one mask on the exact path (whole-grid image), at ``batch`` masks
        per call (default: :meth:`exact_chunking`'s).

        Calibrated once by timing one DAS plan chunk (build and apply) of this grid, so the
        estimate costs a fraction of a second and reflects the machine's current load.
        """
        import time

        if batch is None:
            batch = self.exact_chunking()[0]
        if getattr(self, "_calib", None) is None:
            s = self.setup
            rows = slice(0, min(s.n_z, self._plan_rows()))
            t = self.transmits[0]
            t0 = time.perf_counter()
            Z, X = torch.meshgrid(self._zg[rows], self._xg, indexing="ij")
            plan = das_plan(X, Z, t.delays, s.probe, s.acq.fs, s.acq.c, t.grid.n_time, fnumber=s.fnumber,
                            fc=s.probe.fc)
            plan.w, plan.rot = plan.w.to(self.device, self.dtype), plan.rot.to(self.device, self.cdtype)
            plan.i0 = plan.i0.to(self.device)
            t1 = time.perf_counter()
            iq = torch.ones(2, self.n_elements, t.grid.n_time, dtype=self.cdtype, device=self.device)
            das = []
            for _ in range(2):  # the first call pays for allocations
                t2 = time.perf_counter()
                das_apply(iq, plan.i0, plan.w, plan.rot)
                das.append((time.perf_counter() - t2) / 2)
            self._calib = ((t1 - t0) / (rows.stop * s.n_x), min(das) / (rows.stop * s.n_x))
        per_px_plan, per_px_das = self._calib
        s = self.setup
        pixels = len(self.transmits) * s.n_z * s.n_x
        total = pixels * self.n_elements
        cached = min(1.0, self._plan_cache_limit() / max(1, total))
        # DAS for every mask; plans that do not fit the cache are rebuilt on every call
        return pixels * (per_px_das + (1 - cached) * per_px_plan / max(1, batch))

    def _check_exact_memory(self) -> None:
        """Refuse, before any work, a scene whose exact path cannot fit ``memory_limit`` even one mask
        and one grid row at a time."""
        need = self.exact_bytes(1, pixels=self.setup.n_x)
        if need > self.memory_limit:
            s = self.setup
            raise ParameterError(
                f"this scene needs about {need / 2 ** 30:.1f} GiB for one mask on the exact PSF path (grid "
                f"{s.n_x} x {s.n_z} pixels, {self.n_elements} elements, {len(self.transmits)} transmits), more "
                f"than the memory cap of {self.memory_limit / 2 ** 30:.1f} GiB: reduce grid.n_x / grid.n_z "
                f"(or coarsen grid.pixel), or raise the cap with ARRAYSEL_MEMORY_GIB")

    # ------------------------------------------------------------------ exact path
    def _build_transmits(self):
        s = self.setup
        probe, acq = s.probe, s.acq
        xs, zs = s.scatterer_position
        xt = torch.tensor([xs], dtype=torch.float64)
        zt = torch.tensor([zs], dtype=torch.float64)
        delays_all = plane_wave_delays(probe, list(s.tilts), acq.c)
        self.transmits = []
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
            Q = iq_matrix(grid.n_time, acq.fs, probe.fc,
                          probe.bandwidth if s.iq_bandwidth is None else s.iq_bandwidth)
            parts.append((delays, grid, G, R * C[None, :], _spectra_to_iq_map(grid, Q)))
        # A deep, attenuated or weak echo can lie below float32's normal range at its physical
        # scale; G and RC are divided by their largest magnitude over all transmits (the kernel is
        # normalised, so only the unit changes): spectra, RF, I/Q and images are in units of
        # ``image_scale``.
        g_max = max(float(G.abs().max()) for _, _, G, _, _ in parts)
        rc_max = max(float(RC.abs().max()) for _, _, _, RC, _ in parts)
        if not (g_max > 0 and rc_max > 0 and math.isfinite(g_max) and math.isfinite(rc_max)):
            raise NumericalError(f"the echo of the scatterer is zero or not finite (|G| max {g_max:.3g}, "
                                 f"|RC| max {rc_max:.3g}): check depth, attenuation and reflectivity")
        #: physical value of one unit of :meth:`spectra`, :meth:`rf`, :meth:`iq` and :meth:`image`
        self.image_scale = g_max * rc_max
        for delays, grid, G, RC, IQ in parts:
            self.transmits.append(_Transmit(delays=delays, grid=grid, G=G / g_max, RC=RC / rc_max,
                                            IQ=IQ.to(self.device, self.dtype)))

    def _weights(self, weights) -> torch.Tensor:
        w = weights if isinstance(weights, torch.Tensor) else torch.as_tensor(np.asarray(weights))
        if w.dim() == 1:
            w = w[None]
        if w.dim() != 2 or w.shape[-1] != self.n_elements:
            raise SelectionError(f"weights must have shape (B, {self.n_elements}), got {tuple(w.shape)}")
        w = w.to(device=self.device, dtype=self.dtype)
        return w

    def spectra(self, weights, tx: int) -> torch.Tensor:
        """Received spectra (B, Ne, F) of transmit ``tx`` for weights (B, Ne), in units of ``image_scale``."""
        t = self.transmits[tx]
        w = self._weights(weights)
        G = t.G.to(self.device, self.cdtype)
        RC = t.RC.to(self.device, self.cdtype)
        field_ = w.to(self.cdtype) @ G  # (B, F): field at the scatterer
        return w.to(self.cdtype)[:, :, None] * RC[None] * field_[:, None, :]

    def rf(self, weights, tx: int) -> torch.Tensor:
        """RF signals (B, Ne, T) of transmit ``tx`` (element-major, time last), in units of ``image_scale``."""
        return spectra_to_rf(self.spectra(weights, tx), self.transmits[tx].grid)

    def iq(self, weights, tx: int) -> torch.Tensor:
        """I/Q signals (B, Ne, T) of transmit ``tx``: the I/Q demodulation of :meth:`rf`, computed
        from the spectra in one product with the composed linear map (:func:`_spectra_to_iq_map`).

        Composing the maps in float64 first matters in float32: a strongly attenuated echo has
        out-of-band (low-frequency) content orders of magnitude above the in-band part that forms
        the PSF; an RF record in float32 carries rounding noise at the level of the former across
        the whole band, which the I/Q filter would pass. Here each spectral bin enters with the
        weight the filter gives it, so rounding stays relative to what reaches the I/Q signal.
        """
        s = self.spectra(weights, tx)
        y = torch.cat([s.real, s.imag], dim=-1) @ self.transmits[tx].IQ
        t = y.shape[-1] // 2
        return torch.complex(y[..., :t], y[..., t:])

    def _plan(self, tx: int, rows: slice, cols: slice):
        """DAS plan of transmit ``tx`` on grid rows/cols; whole-grid plans are cached by row blocks."""
        key = (tx, rows.start, rows.stop, cols.start, cols.stop)
        plan = self._plans.get(key)
        if plan is None:
            s = self.setup
            Z, X = torch.meshgrid(self._zg[rows], self._xg[cols], indexing="ij")
            plan = das_plan(X, Z, self.transmits[tx].delays, s.probe, s.acq.fs, s.acq.c,
                            self.transmits[tx].grid.n_time, fnumber=s.fnumber, fc=s.probe.fc)
            plan.w = plan.w.to(self.device, self.dtype)
            plan.rot = plan.rot.to(self.device, self.cdtype)
            plan.i0 = plan.i0.to(self.device)
            size = plan.i0.numel()
            if self._plan_elements + size <= self._plan_cache_limit():
                self._plans[key] = plan
                self._plan_elements += size
        return plan

    def image(self, weights, rows: slice | None = None, cols: slice | None = None,
              rows_per_chunk: int | None = None) -> torch.Tensor:
        """Exact compound image (B, nz', nx') on grid rows/cols (default: whole grid).

        In units of :attr:`image_scale`; differentiable with respect to ``weights``.
        """
        rows = rows or slice(0, self.setup.n_z)
        cols = cols or slice(0, self.setup.n_x)
        w = self._weights(weights)
        iqs = [self.iq(w, n) for n in range(len(self.transmits))]
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

    def kernels_exact(self, weights) -> torch.Tensor:
        """SPEC kernels (B, window, window) from the exact whole-grid image, in batches of
        :meth:`exact_chunking`'s size (bounded memory whatever B)."""
        w = self._weights(weights)
        step = self.exact_chunking()[0]
        if w.shape[0] <= step:
            return window_and_normalise(self.image(w), self.setup.window)
        return torch.cat([window_and_normalise(self.image(w[i:i + step]), self.setup.window)
                          for i in range(0, w.shape[0], step)])

    # ------------------------------------------------------------------ fast path
    def kernels(self, weights, return_info: bool = False):
        """SPEC kernels (B, window, window) complex; differentiable w.r.t. weights.

        Uses the precomputed pair basis when the peak provably lies in its
        region, the exact path otherwise.
        """
        w = self._weights(weights)
        if self.fast is None:
            k = self.kernels_exact(w)
            return (k, torch.zeros(w.shape[0], dtype=torch.bool)) if return_info else k
        k, ok = self.fast.kernels(w)
        bad = torch.nonzero(~ok).flatten()
        if bad.numel():
            ke = self.kernels_exact(w[bad])
            k = k.clone() if not k.requires_grad else k
            k = k.index_put((bad,), ke.to(k.dtype)) if k.requires_grad else k.index_copy(0, bad, ke.to(k.dtype))
        return (k, ~ok) if return_info else k

    def reference_kernel(self) -> torch.Tensor:
        """The full-array kernel (window, window), cached."""
        if self._ref is None:
            with torch.no_grad():
                self._ref = self.kernels(torch.ones(1, self.n_elements))[0]
        return self._ref


#: resident memory of ``import arraysel`` and one model (measured: 0.28 GiB after the imports)
_BASELINE_BYTES = 450 * 2 ** 20
#: target size of one DAS call's temporaries, and how many (B, pixels x Ne) complex arrays they are
_DAS_BYTES = 128 * 2 ** 20
_DAS_TEMPS = 6
#: resident heap per byte of live tensors (measured by benchmarks/exact_memory.py)
_HEAP_FACTOR = 1.2
#: largest batch the exact path hands to DAS at once
_EXACT_MAX_BATCH = 256


def memory_limit_bytes() -> int:
    """Memory cap (bytes) of the exact PSF path: ``$ARRAYSEL_MEMORY_GIB``, default min(4 GiB, RAM / 4)."""
    import os

    raw = os.environ.get("ARRAYSEL_MEMORY_GIB")
    if raw is None:
        try:
            ram = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
        except (ValueError, OSError, AttributeError):  # not POSIX
            ram = 24 * 2 ** 30
        return int(min(4 * 2 ** 30, ram / 4))
    try:
        gib = float(raw)
    except ValueError:
        raise ParameterError(f"ARRAYSEL_MEMORY_GIB = {raw!r} must be a number of GiB (> 0)") from None
    check_number("ARRAYSEL_MEMORY_GIB", gib, lo=0, lo_open=True, hi=1e6)
    return int(gib * 2 ** 30)


def _basis_limit_bytes() -> int:
    import os

    raw = os.environ.get("ARRAYSEL_BASIS_MAX_GIB", "8")
    try:
        gib = float(raw)
    except ValueError:
        raise ParameterError(f"ARRAYSEL_BASIS_MAX_GIB = {raw!r} must be a number of GiB (> 0)") from None
    check_number("ARRAYSEL_BASIS_MAX_GIB", gib, lo=0, lo_open=True)
    return int(gib * 2 ** 30)


def _load_or_build_basis(model: "PSFModel") -> "_PairBasis":
    """Build the fast-path basis, or load it from the on-disk cache (:mod:`arraysel.io.cache`, keyed by
    the scene physics); the stored state is :meth:`_PairBasis.state`, a dict of named tensors."""
    from arraysel import __version__
    from arraysel.io import cache

    built = []

    def build() -> dict:
        built.append(_PairBasis(model, rank_tol=_BUILD_RANK_TOL))
        return built[0].state()

    need = model.basis_bytes()
    item = torch.finfo(model.dtype).bits // 8
    state = cache.load_or_build(
        "psf-basis", (__version__, _BASIS_VERSION, model.setup, str(model.dtype), model.margin, model.block,
                      _BUILD_RANK_TOL),
        build, what="the PSF fast-path basis",
        size_hint=int(0.55 * need * item / 4),  # stored tensors: about 0.55 of the float64 build peak per float32
        seconds_hint=need / 2e7 * 2 / max(1, torch.get_num_threads()))  # ~100 s for the paper scene on 2 cores
    return built[0] if built else _PairBasis.from_state(model, state)


_BASIS_VERSION = 10
#: largest memory of the strips' pair images (tier 2) kept by the fast path; above it they are
#: not built and loose blocks beside E are beamformed exactly
_STRIP_MAX_BYTES = 1 << 30
#: bound of the relative L2 error of a kernel from a sketched basis (probes with more than
#: about 68 elements), above which it is recomputed exactly: its bound carries the Frobenius
#: norm of what the sketch missed, so it is far looser than the actual error (measured on
#: L11-5v: bounds 1e-2 to 3e-2, actual errors about 5e-4 at the run-time rank); 5e-2
#: certifies SI-MSE <= 2.5e-3 (the exact Gram build of small probes certifies 5e-3)
_SKETCH_KERNEL_TOL = 5e-2
#: energy fraction the stored SVD of the pair images on E discards (runs truncate further)
_BUILD_RANK_TOL = 1e-7


class _BuildProgress:
    """Logs the steps of a basis build with their durations (``logging`` INFO)."""

    def __init__(self, model: "PSFModel", basis: "_PairBasis"):
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


def _spectra_to_iq_map(grid, Q: torch.Tensor) -> torch.Tensor:
    """Real (2F, 2T) float64 matrix ``M`` with ``[Re S, Im S] @ M = [Re IQ, Im IQ]``, where
    ``IQ = spectra_to_rf(S, grid) @ Q.T`` (the exact path's spectra -> RF -> I/Q), composed in float64."""
    a, b = spectra_to_rf_maps(grid)
    qt = Q.to(torch.complex128).T
    m = torch.cat([a.to(torch.complex128) @ qt, b.to(torch.complex128) @ qt], dim=0)  # (2F, T)
    return torch.cat([m.real, m.imag], dim=1)


def window_and_normalise(img: torch.Tensor, size: int, peak=None) -> torch.Tensor:
    """Cut the (size x size) window centred on the peak of |img| (clipped), L2-normalised.

    img: (B, nz, nx) complex. Raises NumericalError if an image is all zero.
    """
    B, nz, nx = img.shape
    mag = img.detach().abs().reshape(B, -1)
    if peak is None:
        peak = mag.argmax(dim=1)
    pz = peak // nx
    px = peak % nx
    z0 = _window_start(pz, size, nz)
    x0 = _window_start(px, size, nx)
    ar = torch.arange(size, device=img.device)
    zi = (z0[:, None] + ar[None])[:, :, None]
    xi = (x0[:, None] + ar[None])[:, None, :]
    bi = torch.arange(B, device=img.device)[:, None, None]
    win = img[bi, zi, xi]
    top = mag.gather(1, peak[:, None])[:, 0]
    if bool((top == 0).any()) or not bool(torch.isfinite(mag).all()):
        raise NumericalError("PSF image is all zero or not finite for some selection "
                             "(is the selection empty, or the scatterer outside the grid?)")
    return _unit_norm(win, top)


def _scale_complex(x: torch.Tensor, s: torch.Tensor) -> torch.Tensor:
    """``x / s`` (s real, one per batch item) through the real view: torch's complex division
    by a promoted real returns inf/NaN for a subnormal divisor."""
    return torch.view_as_complex(torch.view_as_real(x) / s.reshape(-1, *([1] * x.dim())))


def _unit_norm(win: torch.Tensor, top: torch.Tensor, with_norm: bool = False):
    """Windows (B, h, w) divided by their L2 norm; ``top`` (B,) > 0 is a detached scale
    (the peak magnitude) applied first, so squares of tiny or huge values cannot under/overflow.
    With ``with_norm`` also the (detached) norms themselves."""
    top = top.detach().to(win.real.dtype)
    win = _scale_complex(win, top)
    norm = torch.linalg.vector_norm(torch.view_as_real(win).reshape(win.shape[0], -1), dim=1)
    out = _scale_complex(win, torch.where(norm > 0, norm, torch.ones_like(norm)))
    return (out, norm.detach() * top) if with_norm else out


def _csr(crow, col, val, size):
    import warnings

    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*[Ss]parse.*")
        return torch.sparse_csr_tensor(crow, col, val, size=size, check_invariants=True)


def pair_index(ne: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Indices (e, j) with e <= j of the Ne(Ne+1)/2 element pairs."""
    e, j = torch.triu_indices(ne, ne)
    return e, j


def pair_products(w: torch.Tensor, e: torch.Tensor, j: torch.Tensor) -> torch.Tensor:
    """(B, P) products w_e w_j of the pairs (e <= j)."""
    return w[:, e] * w[:, j]


class _PairBasis:
    """Precomputed pair images and peak certificates of the fast path.

    Regions (grid rows ``rows`` = the window plus a margin around the scatterer):

    * tier 1, ``E``: the columns of the window plus the margin;
    * tier 2, the *strips*: the remaining columns of the same rows, so that
      E and the strips make the full-width band ``rows x all columns``.

    Images: ``I = c @ H`` with ``c`` the (B, P) pair products and ``H`` the
    (P, 2 Npix) real pair images ([re | im]); tier 1 is stored as a truncated
    SVD ``U @ V`` when that saves work (discarded energy <= ``rank_tol``).

    Certificates: for transmit n and receive element e the I/Q channel of a
    selection is ``X_ne(t) = m_e sum_j m_j A_nej(t)`` (A: pair I/Q signals).
    Linear interpolation and unit phase rotations cannot exceed the larger
    neighbouring sample, so on a block Q of pixels
    ``|I(p)| <= sum_{n,e} max_{t in [lo, hi]_neQ} |X_ne(t)|``, where
    ``[lo, hi]`` spans the samples the block's pixels read. The maxima come from
    aligned segments of :attr:`seg` samples: ``[lo, hi]`` lies inside segments
    ``lo // seg .. hi // seg``, and the envelope of every run of 1 .. M
    consecutive segments is formed once per batch (:meth:`envelopes`), so one
    sparse product sums the right run for every (block, transmit, element).
    Certificate 1 covers the blocks not inside E, certificate 2 the blocks not
    inside the band. A selection is done at tier 1 when its peak in E beats
    certificate 1 (and its window fits in E), or when the blocks whose bound
    reaches the peak are beamformed exactly and stay below it
    (:meth:`refine`); at tier 2 likewise on the band; otherwise the exact path
    recomputes it.
    """

    def __init__(self, model: PSFModel, rank_tol: float = _BUILD_RANK_TOL, _state: dict | None = None):
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
        self.e_idx, self.j_idx = pair_index(ne)
        outside1, outside2 = self._outside_blocks()
        self.blocks1 = torch.nonzero(outside1)  # (nQ1, 2): rows of S1 as (qz, qx)
        self.blocks2 = torch.nonzero(outside2)  # (nQ2, 2): rows of S2 as (qz, qx)
        self._strip_layout()
        self._block_plans: dict = {}
        self._row_energy = None
        #: the full-rank basis this one was truncated from (:meth:`truncated`): kernels whose
        #: error bound fails here are retried there before the exact path
        self.finer = None
        if _state is not None:
            self._set_state(_state)
            return
        self.strips = self._strip_bytes() <= _STRIP_MAX_BYTES
        if not self.strips:
            self._disable_strips()
        progress = _BuildProgress(model, self)
        lo, hi = self._sample_ranges()
        progress.step("sample ranges")
        X = self._windowed_pair_iq()
        progress.step("pair I/Q signals")
        plan1 = self._local_plan(self.rows, torch.arange(self.cols.start, self.cols.stop))
        self.core_pix = self._core_pixels()
        self.U, self.V, self.rank, self.rank_tail, rho, col1, self.Hc = self._compress(X, plan1, rank_tol,
                                                                                      progress)
        del plan1
        if self.npix2:
            H2 = self._dense_pair_images(X, self._local_plan(self.rows, self.strip_cols))
            col2 = float(_pixel_norms(H2).max())
            H2 = H2[:, self.h2_cols]
            self._strip_factors(H2)
            self.H2 = H2.to(model.device, model.dtype)
            del H2
            progress.step("strip pair images")
        else:
            col2 = 0.0
            self.H2 = torch.zeros(self.e_idx.numel(), 0, dtype=model.dtype, device=model.device)
            self._strip_factors(self.H2.double())
        #: [max residual pixel-column norm of U V, max pixel-column norm of H1, of H2,
        #:  bound of the largest discarded singular value of H1]
        self.err = torch.tensor([rho, col1, col2, self.sigma_next], dtype=torch.float64)
        self._build_certificates(X, lo, hi)
        if self.missed > 0:
            self.kernel_tol = _SKETCH_KERNEL_TOL
        progress.close()

    # ------------------------------------------------------------------ precomputation
    def _strip_layout(self):
        """Column order of ``H2``: block-major, so the pair images of one grid block of the strips
        are ``2 block^2`` adjacent columns ([re | im] of its pixels, row-major), followed by the
        pixels no whole block covers. Sets ``h2_cols`` (old [re | im] column of each new column),
        its inverse ``h2_inv`` and ``strip_block_col`` (nQ1,): the first column of each tier-1
        block in ``H2``, -1 where the block is not wholly inside the strips."""
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
        the scatterer, where the peak of a selection's image lies (its pair images, ``Hc``,
        settle near-ties at the peak without delay-and-sum)."""
        s = self.model.setup
        iz, ix = s.scatterer_pixel
        iz, ix = iz - self.rows.start, ix - self.cols.start
        h, w = self.shape
        zr = torch.arange(max(0, iz - self.core), min(h, iz + self.core))
        xr = torch.arange(max(0, ix - self.core), min(w, ix + self.core))
        return (zr[:, None] * w + xr[None, :]).reshape(-1)

    #: rank of the per-block factors of the strip pair images (:meth:`_strip_factors`)
    strip_rank = 16

    def _strip_factors(self, H2: torch.Tensor):
        """Rank-``strip_rank`` factors of the pair images of every whole strip block (block-major
        ``H2`` in float64): ``M_q = W S Z^T`` (SVD from the 2 b^2 x 2 b^2 Gram matrix) gives
        ``SF[q] = W_r S_r`` (P, r), ``SG[q] = Z_r^T`` (r, 2 b^2), ``SS[q] = S_r`` and ``Snext[q]``
        (a safe upper bound of ``S_{r+1}``). Then ``|c M_q - (c SF) SG|`` at a pixel is at most
        ``|c_perp| Snext`` with ``|c_perp|^2 = |c|^2 - |(c SF) / SS|^2``: a cheap, rigorous bound of
        a block's image that clears most loose blocks without reading its ``2 b^2`` columns."""
        model = self.model
        bb2 = 2 * model.block ** 2
        nw = int((self.strip_block_col >= 0).sum())
        r = min(self.strip_rank, bb2)
        P = H2.shape[0]
        if nw == 0:
            self.SF = torch.zeros(0, P, r, dtype=model.dtype, device=model.device)
            self.SG = torch.zeros(0, r, bb2, dtype=model.dtype, device=model.device)
            self.SS = torch.zeros(0, r, dtype=model.dtype, device=model.device)
            self.Snext = torch.zeros(0, dtype=torch.float64, device=model.device)
            return
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
        self.SF = torch.cat(SF).to(model.device, model.dtype)
        self.SG = torch.cat(SG).to(model.device, model.dtype)
        self.SS = torch.cat(SS).to(model.device, model.dtype)
        self.Snext = torch.cat(SN).to(model.device)

    # -- sample ranges and windowed pair I/Q -------------------------------------------------
    def _sample_ranges(self):
        """Samples read by the grid's pixels, block by block, from the block centres.

        The transmit distance (a minimum of 1-Lipschitz distances) and each receive distance
        are 1-Lipschitz in the pixel position, so over a block of half-diagonal ``r`` the
        sample position ``(d_TX + d_RX) fs / c`` of a pixel lies within ``2 r fs / c`` of the
        centre's: the ranges below contain every sample a pixel of the block reads (they may
        hold a sample or two more, which only loosens the bounds). Channels outside the
        f-number aperture are kept (a bound only grows).

        Returns ``lo``, ``hi`` (ntx, nbz, nbx, Ne): per block and (transmit, element) the
        first and last sample index a pixel may read (``hi < lo`` where none can), and sets
        ``off`` (ntx, Ne): the first sample of each channel's window, and ``T``: the window
        length (a multiple of :attr:`seg`). Every sample any grid pixel reads lies in
        ``[off, off + T - 1]``, so channels are kept, precomputed and enveloped on that window
        only (its length follows the grid, not the record)."""
        from arraysel.physics.beamform import transmit_distance

        model = self.model
        s = model.setup
        b = model.block
        nbz, nbx = -(-s.n_z // b), -(-s.n_x // b)
        p = s.pitch
        zc = float(model._zg[0]) + (torch.arange(nbz, dtype=torch.float64) * b + (b - 1) / 2) * p
        xc = float(model._xg[0]) + (torch.arange(nbx, dtype=torch.float64) * b + (b - 1) / 2) * p
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
        self.off = torch.where(read, first, torch.zeros_like(first))
        span = int(torch.where(read, last - first + 1, torch.ones_like(first)).max())
        self.T = -(-max(span, 2) // self.seg) * self.seg
        return lo, hi

    def _windowed_pair_iq(self) -> np.ndarray:
        """I/Q of every (rx e, tx j) pair on each channel's window: ``X[n, e, t, j]`` (ntx, Ne, T, Ne)
        complex64, sample ``off[n, e] + t`` of the record (zero past its end).

        The RF of a pair is the inverse FFT of ``RC_e(f) G_nj(f)``; the I/Q demodulation
        (mixing, zero-phase Butterworth low-pass, factor 2) is applied with SciPy's
        ``filtfilt`` along time, which is the same linear map as :func:`iq_matrix`."""
        import scipy.signal

        model = self.model
        s = model.setup
        ne = model.n_elements
        ntx = len(model.transmits)
        out = np.zeros((ntx, ne, self.T, ne), dtype=np.complex64)
        from arraysel.physics.beamform import iq_lowpass

        b_, a_ = iq_lowpass(s.acq.fs, s.probe.fc, s.probe.bandwidth if s.iq_bandwidth is None else s.iq_bandwidth)
        off = self.off.numpy()
        for n, t in enumerate(model.transmits):
            T = t.grid.n_time
            mix = np.exp(-2j * np.pi * s.probe.fc * np.arange(T) / s.acq.fs)
            step = max(1, 2 ** 24 // (ne * T))
            for e0 in range(0, ne, step):
                e1 = min(ne, e0 + step)
                spec = t.RC[e0:e1, None, :] * t.G[None, :, :]
                rf = spectra_to_rf(spec, t.grid).numpy()  # (ce, Ne, T)
                iq = 2 * scipy.signal.filtfilt(b_, a_, rf * mix, axis=-1)
                for e in range(e0, e1):
                    o = int(off[n, e])
                    k = max(0, min(self.T, T - o))
                    out[n, e, :k, :] = iq[e - e0, :, o:o + k].T
        return out

    def _local_plan(self, rows: slice, cols: torch.Tensor):
        """DAS plan of the pixels (rows x cols) for the pair-image kernel: (i0 local to the
        channel windows, weight, rotation re, im), each (ntx, Ne, Npix) numpy."""
        model = self.model
        s = model.setup
        Z, X = torch.meshgrid(model._zg[rows], model._xg[cols], indexing="ij")
        out = [[], [], [], []]
        for n, t in enumerate(model.transmits):
            p = das_plan(X, Z, t.delays, s.probe, s.acq.fs, s.acq.c, t.grid.n_time, fnumber=s.fnumber,
                         fc=s.probe.fc)
            i0 = torch.where(p.rot.abs() > 0, p.i0 - self.off[n][None, :], torch.zeros_like(p.i0))
            out[0].append(i0.T.to(torch.int32))
            out[1].append(p.w.T.to(torch.float32))
            out[2].append(p.rot.real.T.to(torch.float32))
            out[3].append(p.rot.imag.T.to(torch.float32))
        return tuple(np.ascontiguousarray(torch.stack(a).numpy()) for a in out)

    #: most pair rows the kernel fills at once (bounds the build's working memory)
    build_rows = 512

    def _pair_image_blocks(self, X: np.ndarray, plan: tuple):
        """Yield ``(r0, H)``: the symmetric pair images of rows ``r0 .. r0 + len(H)`` as a
        (rows, 2 Npix) float64 tensor [re | im]."""
        from arraysel.physics.pairkernels import pair_images, pair_row_blocks

        ne = self.model.n_elements
        npix = plan[0].shape[2]
        rows = max(ne, self.build_rows * max(1, 20736 // max(1, npix)))
        r0 = 0
        for e0, e1, nr in pair_row_blocks(ne, rows):
            out = torch.from_numpy(pair_images(X, plan, e0, e1))  # (Npix, nr, 2)
            yield r0, torch.cat([out[:, :, 0].T, out[:, :, 1].T], dim=1)
            r0 += nr

    def _dense_pair_images(self, X: np.ndarray, plan: tuple) -> torch.Tensor:
        """All symmetric pair images on the plan's pixels: (P, 2 Npix) float64 [re | im]."""
        return torch.cat([H for _, H in self._pair_image_blocks(X, plan)], dim=0)

    #: real columns of the randomised range sketch of the pair images on E (probes whose
    #: pair count exceeds it are compressed from the sketch; smaller ones exactly)
    sketch_columns = 2400

    def _compress(self, X: np.ndarray, plan: tuple, rank_tol: float, progress=None):
        """Truncated SVD ``H ~ U V`` of the pair images ``H`` (P, 2 Npix) on E, with ``U``
        orthonormal (P, r) and ``V = U^T H``.

        Small probes (P <= :attr:`sketch_columns`): ``H`` is formed and the P x P Gram matrix
        diagonalised (exact). Larger ones: two passes over row blocks of ``H`` that are never
        all held at once: a subsampled randomised Fourier sketch ``Y = H S`` (random signs,
        2-D FFT of each pair image, random frequencies) gives an orthonormal ``Q`` spanning
        the pairs' dominant subspace; the second pass forms ``B = Q^T H``, the pixels' column
        norms and the core columns; the SVD of ``B`` gives ``U = Q W``, ``V = W^T B``.

        Returns U (None when no compression pays), V, rank, discarded energy fraction, the
        largest residual pixel-column norm ``max_p |(I - U U^T) H_p|`` (exact, from
        ``|H_p|^2 - |V_p|^2``), the largest pixel-column norm and the core pair images ``Hc``.
        Sets ``sigma_next``: a rigorous bound of the spectral norm of ``(I - U U^T) H``
        (the next singular value of B plus the Frobenius norm of what the sketch missed).
        """
        model = self.model
        P = self.e_idx.numel()
        npix = self.npix
        core = torch.cat([self.core_pix, npix + self.core_pix])
        if P <= self.sketch_columns:
            H = self._dense_pair_images(X, plan)
            if progress is not None:
                progress.step("pair images on E")
            col = _pixel_norms(H)
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
                self.sigma_next = self.missed = 0.0
                return None, H.to(model.device, model.dtype), P, 0.0, 0.0, float(col.max()), Hc
            U = evecs[:, :rank]
            V = U.T @ H
            self.sigma_next = float(evals[rank].sqrt()) if rank < P else 0.0
            self.missed = 0.0
            rho = float((col ** 2 - _pixel_norms(V) ** 2).clamp(min=0).sqrt().max())
            return (U.to(model.device, model.dtype), V.to(model.device, model.dtype), rank,
                    float(tail[rank - 1] / total), rho, float(col.max()), Hc)
        h, w = self.shape
        L = min(self.sketch_columns, 2 * npix) // 2
        gen = torch.Generator().manual_seed(20261123)
        signs = torch.where(torch.rand(npix, generator=gen, dtype=torch.float64) < 0.5, -1.0, 1.0)
        freqs = torch.randperm(npix, generator=gen)[:L]
        Y = torch.empty(P, 2 * L, dtype=torch.float64)
        for r0, H in self._pair_image_blocks(X, plan):
            z = torch.complex(H[:, :npix], H[:, npix:]) * signs
            f = torch.fft.fft2(z.reshape(-1, h, w), norm="ortho").reshape(z.shape[0], npix)[:, freqs]
            Y[r0:r0 + H.shape[0], :L] = f.real
            Y[r0:r0 + H.shape[0], L:] = f.imag
        if progress is not None:
            progress.step("sketch of the pair images on E")
        Q = torch.linalg.qr(Y)[0]
        del Y
        B = torch.zeros(Q.shape[1], 2 * npix, dtype=torch.float64)
        col2 = torch.zeros(npix, dtype=torch.float64)
        Hc = torch.empty(P, core.numel(), dtype=torch.float64)
        for r0, H in self._pair_image_blocks(X, plan):
            r1 = r0 + H.shape[0]
            B.addmm_(Q[r0:r1].T, H)
            col2 += H[:, :npix].square().sum(0) + H[:, npix:].square().sum(0)
            Hc[r0:r1] = H[:, core]
        if progress is not None:
            progress.step("projection of the pair images on E")
        evals, W = torch.linalg.eigh(B @ B.T)
        evals = evals.flip(0).clamp(min=0)
        W = W.flip(1)
        total = float(col2.sum())
        missed = max(0.0, total - float(evals.sum()))
        tail = total - torch.cumsum(evals, 0)
        ok = torch.nonzero(tail <= rank_tol * total).flatten()
        rank = int(ok[0]) + 1 if ok.numel() else evals.numel()
        U = Q @ W[:, :rank]
        V = W[:, :rank].T @ B
        nxt = float(evals[rank].sqrt()) if rank < evals.numel() else 0.0
        #: Frobenius norm of what the sketch missed, ``|(I - Q Q^T) H|_F``: part of every
        #: spectral bound of a truncation of this basis (0 for the exact build)
        self.missed = math.sqrt(missed) * (1 + 1e-6)
        self.sigma_next = nxt * (1 + 1e-6) + self.missed
        rho = float((col2 - _pixel_norms(V) ** 2).clamp(min=0).sqrt().max())
        return (U.to(model.device, model.dtype), V.to(model.device, model.dtype), rank,
                float(tail[rank - 1] / total), rho, float(col2.max().sqrt()), Hc.to(model.device, model.dtype))

    def _strip_bytes(self) -> int:
        """Memory of the strips' pair images and block factors in the model's dtype."""
        P = self.e_idx.numel()
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

    #: samples per aligned envelope segment of the certificates
    seg = 4

    def _build_certificates(self, X: np.ndarray, lo: torch.Tensor, hi: torch.Tensor):
        model = self.model
        ne = model.n_elements
        T = self.T
        # A[j, (n, e, r, a)] = I/Q sample t = a seg + r of (rx e, tx j): the channel of receive e on
        # transmit n is m_e sum_j m_j A[j, (n, e, :, :)]; samples are stored segment-offset major
        # so that the envelopes reduce over contiguous slabs (:meth:`envelopes`)
        A = torch.from_numpy(X).permute(3, 0, 1, 2)  # (j, n, e, T)
        A = A.reshape(ne, A.shape[1], ne, T // self.seg, self.seg).transpose(-1, -2).reshape(ne, -1)
        self.A = torch.cat([A.real, A.imag], dim=1).to(model.device, model.dtype)
        off = self.off[:, None, None, :]
        read = hi >= lo
        lo = torch.where(read, lo - off, torch.full_like(lo, T))
        hi = torch.where(read, (hi - off).clamp(max=T - 1), torch.full_like(hi, -1))
        outside1, outside2 = self._outside_blocks()
        has_all = hi >= lo
        runs = torch.where(has_all, hi // self.seg - lo // self.seg + 1, torch.zeros_like(lo))
        #: longest run of consecutive segments a block reads
        self.L = max(1, int(runs.max()))
        self.S1 = self._block_matrix(lo, hi, outside1)
        self.S2 = self._block_matrix(lo, hi, outside2) if self.strips else \
            _csr(torch.zeros(1, dtype=torch.long), torch.zeros(0, dtype=torch.long),
                 torch.zeros(0, dtype=model.dtype), (0, self.S1.shape[1])).to(model.device)

    def _outside_blocks(self):
        """(nbz, nbx) bool masks of the blocks not inside E (tier 1) and not inside the band (tier 2)."""
        s = self.model.setup
        b = self.model.block
        bz = torch.arange(-(-s.n_z // b))
        bx = torch.arange(-(-s.n_x // b))
        in_rows = (bz * b >= self.rows.start) & ((bz + 1) * b <= self.rows.stop)
        in_cols = (bx * b >= self.cols.start) & ((bx + 1) * b <= self.cols.stop)
        outside1 = ~(in_rows[:, None] & in_cols[None, :])
        outside2 = ~(in_rows[:, None] & torch.ones(bx.numel(), dtype=torch.bool)[None, :])
        return outside1, outside2

    def _block_matrix(self, lo, hi, outside):
        """Sparse (nQ, ntx*Ne*M*nS) matrix summing, per block, the envelope of the run of
        segments that holds the block's samples (layout of :meth:`envelopes`)."""
        model = self.model
        ntx, _, _, ne = lo.shape
        M, nS, sg = self.L, self.T // self.seg, self.seg
        qz, qx = torch.nonzero(outside, as_tuple=True)
        nq = qz.numel()
        lo_q = lo[:, qz, qx]
        hi_q = hi[:, qz, qx]
        has = hi_q >= lo_q
        first = (lo_q // sg).clamp(0, nS - 1)
        run = (hi_q // sg - lo_q // sg).clamp(0, M - 1)
        n_ar = torch.arange(ntx)[:, None, None]
        e_ar = torch.arange(ne)[None, None, :]
        col = ((n_ar * ne + e_ar) * M + run) * nS + first
        q_ar = torch.arange(nq)[None, :, None].expand_as(col)
        rows_i = q_ar[has]
        cols_i = col[has]
        width = ntx * ne * M * nS
        order = torch.argsort(rows_i * width + cols_i)
        rows_i, cols_i = rows_i[order], cols_i[order]
        crow = torch.zeros(nq + 1, dtype=torch.long)
        crow[1:] = torch.cumsum(torch.bincount(rows_i, minlength=nq), 0)
        vals = torch.full((rows_i.numel(),), 1.0 + 1e-4, dtype=model.dtype)  # rounding safety margin
        return _csr(crow, cols_i, vals, (nq, width)).to(model.device)

    # ------------------------------------------------------------------ cache
    def state(self) -> dict:
        st = {"V": self.V.cpu(), "H2": self.H2.cpu(), "A": self.A.cpu(), "err": self.err,
              "Hc": self.Hc.cpu(), "core_pix": self.core_pix, "SF": self.SF.cpu(), "SG": self.SG.cpu(),
              "SS": self.SS.cpu(), "Snext": self.Snext.cpu(),
              "meta": torch.tensor([self.T, self.L, self.rank, self.seg, int(self.strips)]),
              "rank_tail": torch.tensor(self.rank_tail), "off": self.off.cpu(), "row_energy": self.row_energy,
              "missed": torch.tensor(self.missed, dtype=torch.float64)}
        if self.U is not None:
            st["U"] = self.U.cpu()
        for name in ("S1", "S2"):
            S = getattr(self, name)
            st[name + "_crow"], st[name + "_col"], st[name + "_val"] = (
                S.crow_indices().cpu(), S.col_indices().cpu(), S.values().cpu())
            st[name + "_shape"] = torch.tensor(list(S.shape))
        return st

    def _set_state(self, st: dict):
        dev, dt = self.model.device, self.model.dtype
        self.U = st["U"].to(dev, dt) if "U" in st else None
        self.V, self.H2, self.A, self.Hc, self.SF, self.SG, self.SS = (
            st[k].to(dev, dt) for k in ("V", "H2", "A", "Hc", "SF", "SG", "SS"))
        self.Snext = st["Snext"].double().to(dev)
        self.core_pix = st["core_pix"].long()
        self.T, self.L, self.rank, self.seg, strips = (int(v) for v in st["meta"])
        self.off = st["off"].long()
        self._row_energy = st["row_energy"].double()
        if not strips:
            self._disable_strips()
        self.rank_tail = float(st["rank_tail"])
        self.missed = float(st["missed"])
        if self.missed > 0:
            self.kernel_tol = _SKETCH_KERNEL_TOL
        self.err = st["err"].double()
        for name in ("S1", "S2"):
            shape = tuple(int(v) for v in st[name + "_shape"])
            setattr(self, name, _csr(st[name + "_crow"], st[name + "_col"], st[name + "_val"].to(dt),
                                     shape).to(dev))

    @classmethod
    def from_state(cls, model, state):
        return cls(model, _state=state)

    def truncated(self, rank: int) -> "_PairBasis":
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
        tail = self.V[r:].double()
        pix = (tail[:, :n] ** 2 + tail[:, n:] ** 2).sum(0)
        sig = self.row_energy[r:]
        err = self.err.clone()
        err[0] = math.sqrt(float(err[0]) ** 2 + float(pix.max())) * (1 + 1e-6)
        err[3] = max(float(sig[0].sqrt()) * (1 + 1e-6), float(err[3]) - self.missed) + self.missed
        total = float(self.row_energy.sum()) / max(1e-300, 1 - self.rank_tail)
        out.row_energy = self.row_energy[:r]
        out.U, out.V, out.rank, out.err = self.U[:, :r].contiguous(), self.V[:r].contiguous(), r, err
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
            # a sketched basis: once the next singular value is below a quarter of the sketch's
            # own term (:attr:`missed`) more rank costs time without tightening any bound
            small = torch.nonzero(sig2.sqrt() <= self.missed / 4).flatten()
            if small.numel():
                rank = min(rank, max(1, int(small[0])))
        return rank

    # ------------------------------------------------------------------ evaluation
    def _pairs(self, w):
        return pair_products(w, self.e_idx.to(w.device), self.j_idx.to(w.device))

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
            eps = resid * float(self.err[0]) + rnd
            win_err = resid * float(self.err[3]) + rnd * self.model.setup.window
        return img, eps, win_err

    def _rounding(self, c: torch.Tensor, cn2: torch.Tensor | None = None) -> torch.Tensor:
        """(B,) rounding allowance of one image pixel ``c @ H_p``: ``2 sqrt(P) u |c| max_p |H_p|``."""
        if cn2 is None:
            cn2 = (c ** 2).sum(1)
        u = torch.finfo(c.dtype).eps / 2
        return 2 * math.sqrt(c.shape[1]) * u * cn2.sqrt() * float(self.err[1:].max())

    def band_images(self, w: torch.Tensor, img_e: torch.Tensor | None = None) -> torch.Tensor:
        """Images on the full-width band (B, nzE, n_x) complex."""
        if img_e is None:
            img_e = self.images(w)
        B = w.shape[0]
        y = (self._pairs(w) @ self.H2)[:, self.h2_inv.to(w.device)]
        strips = torch.complex(y[:, : self.npix2], y[:, self.npix2:]).reshape(B, self.shape[0], -1)
        left = self.cols.start
        return torch.cat([strips[:, :, :left], img_e, strips[:, :, left:]], dim=2)

    def channels(self, w: torch.Tensor) -> torch.Tensor:
        """I/Q channel signals (B, ntx, Ne, T) complex of selections w: ``m_e sum_j m_j A_nej``."""
        ne = self.model.n_elements
        ntx = len(self.model.transmits)
        y = w @ self.A
        half = y.shape[1] // 2
        x = torch.complex(y[:, :half], y[:, half:]).reshape(w.shape[0], ntx, ne, self.seg, self.T // self.seg)
        x = x.transpose(-1, -2).reshape(w.shape[0], ntx, ne, self.T)
        return x * w.to(x.dtype)[:, None, :, None]

    def pair_iq(self) -> torch.Tensor:
        """The windowed pair I/Q signals (Ne tx j, ntx, Ne rx e, T) complex (sample t of the window
        of (n, e) is sample ``off[n, e] + t`` of the record)."""
        ne = self.model.n_elements
        half = self.A.shape[1] // 2
        a = torch.complex(self.A[:, :half], self.A[:, half:])
        a = a.reshape(ne, len(self.model.transmits), ne, self.seg, self.T // self.seg)
        return a.transpose(-1, -2).reshape(ne, len(self.model.transmits), ne, self.T)

    #: (transmit, element) channels per step of :meth:`envelopes` (keeps the products in cache)
    env_group = 8

    def envelopes(self, w: torch.Tensor) -> torch.Tensor:
        """Segment envelopes (ntx * Ne * M * nS, B) of the channels of selections w.

        Entry (n, e, m, a): ``max |X_ne(t)|`` over segments ``a .. a + m`` (``seg`` samples
        each; zeros past the end). The channel sums are formed :attr:`env_group` channels at a
        time and reduced to segment maxima at once, so they never reach main memory; then
        M - 1 running maxima on the segment array (``seg`` times smaller than the channels).
        """
        ne = self.model.n_elements
        ntx = len(self.model.transmits)
        B = w.shape[0]
        T = self.T
        nS = T // self.seg
        nch = ntx * ne
        half = self.A.shape[1] // 2
        a_re, a_im = self.A[:, :half].T, self.A[:, half:].T
        wt = w.T.contiguous()
        seg = w.new_empty(nch, nS, B)
        for g0 in range(0, nch, self.env_group):
            g1 = min(nch, g0 + self.env_group)
            yr = a_re[g0 * T: g1 * T] @ wt
            yi = a_im[g0 * T: g1 * T] @ wt
            sq = torch.addcmul(yi.square_(), yr, yr)
            torch.amax(sq.view(g1 - g0, self.seg, nS, B), dim=1, out=seg[g0:g1])
        seg.sqrt_()
        seg.view(ntx, ne, nS, B).mul_(w.abs().T[None, :, None, :])
        env = seg.new_empty(nch, self.L, nS, B)
        env[:, 0] = seg
        for m in range(1, self.L):
            env[:, m, nS - m:] = env[:, m - 1, nS - m:]
            torch.maximum(env[:, m - 1, : nS - m], seg[:, m:], out=env[:, m, : nS - m])
        return env.view(-1, B)

    def bound(self, w: torch.Tensor, tier: int = 1, per_block: bool = False, env=None) -> torch.Tensor:
        """(B,) upper bound of |I| on the blocks outside E (tier 1) or outside the band (tier 2);
        with ``per_block`` the (nQ, B) bounds of every block. ``env``: :meth:`envelopes` of w."""
        S = self.S1 if tier == 1 else self.S2
        B = w.shape[0]
        if S.shape[0] == 0:
            return torch.zeros((0, B) if per_block else B, dtype=w.dtype, device=w.device)
        if env is None:
            env = self.envelopes(w)
        bounds = torch.sparse.mm(S, env)  # (nQ, B)
        return bounds if per_block else bounds.amax(dim=0)

    #: at most this many blocks are beamformed exactly to settle a selection (else: exact path)
    refine_max_blocks = 256
    #: memory (bytes) of the block DAS plans kept (one block: ntx x block^2 x Ne entries of
    #: index, weight and rotation)
    plan_cache_bytes = 256 * 2 ** 20

    @property
    def plan_cache_blocks(self) -> int:
        """Block DAS plans kept in memory (from :attr:`plan_cache_bytes`)."""
        model = self.model
        per = len(model.transmits) * model.block ** 2 * model.n_elements * (8 + 4 + 8)
        return max(16, self.plan_cache_bytes // per)

    def _plans_for_blocks(self, blocks: list) -> list:
        """DAS plans (per block: one (i0, w, rot) per transmit) of the pixels of the grid blocks
        ``blocks`` ((qz, qx) pairs), row-major, clipped to the grid. Cached; the missing blocks are
        planned together (one :func:`das_plan` call per transmit)."""
        missing = list(dict.fromkeys(q for q in blocks if q not in self._block_plans))
        made = {}
        if missing:
            model = self.model
            s = model.setup
            b = model.block
            zs, xs, sizes = [], [], []
            for qz, qx in missing:
                Z, X = torch.meshgrid(model._zg[qz * b:(qz + 1) * b], model._xg[qx * b:(qx + 1) * b],
                                      indexing="ij")
                zs.append(Z.reshape(-1))
                xs.append(X.reshape(-1))
                sizes.append(Z.numel())
            Z, X = torch.cat(zs), torch.cat(xs)
            per_tx = []
            for n, t in enumerate(model.transmits):
                p = das_plan(X, Z, t.delays, s.probe, s.acq.fs, s.acq.c, t.grid.n_time, fnumber=s.fnumber,
                             fc=s.probe.fc)
                # sample indices local to the channel windows (see _sample_ranges)
                i0 = torch.where(p.rot.abs() > 0, p.i0 - self.off[n][None, :], torch.zeros_like(p.i0))
                per_tx.append((i0.to(model.device).split(sizes), p.w.to(model.device, model.dtype).split(sizes),
                               p.rot.to(model.device, model.cdtype).split(sizes)))
            for i, q in enumerate(missing):
                made[q] = [(i0[i], wt[i], rot[i]) for i0, wt, rot in per_tx]
                if len(self._block_plans) < self.plan_cache_blocks:
                    self._block_plans[q] = made[q]
        return [self._block_plans.get(q) or made[q] for q in blocks]

    def _das(self, X: torch.Tensor, blocks: list, rows: list | None = None) -> torch.Tensor:
        """Exact image values of one selection (I/Q channels X: (ntx, Ne, T)) on the pixels of
        ``blocks`` ((qz, qx) pairs), or on the given pixel rows of each block's plan."""
        plans = self._plans_for_blocks([(int(qz), int(qx)) for qz, qx in blocks])
        img = 0
        for n in range(len(self.model.transmits)):
            parts = [tuple(a[r] for a in pl[n]) if rows is not None else pl[n] for pl, r in
                     zip(plans, rows if rows is not None else [None] * len(plans))]
            i0, wt, rot = (torch.cat([pt[j] for pt in parts]) for j in range(3))
            img = img + das_apply(X[n], i0, wt, rot)
        return img

    def strip_bounds(self, c: torch.Tensor, slots: torch.Tensor, slack: torch.Tensor | None = None) -> torch.Tensor:
        """(n, B) float64 upper bounds of ``max |I|`` on the whole strip blocks ``slots`` (their
        order in ``H2``) for pair products ``c`` (B, P), from the rank-r factors
        (:meth:`_strip_factors`): ``|(c SF) SG| + |c_perp| S_{r+1}`` plus rounding allowances."""
        if slack is None:
            slack = self._rounding(c)
        bb = self.model.block ** 2
        sl = slots.to(c.device)
        cf = torch.matmul(c[None], self.SF[sl])                                  # (n, B, r)
        v = torch.matmul(cf, self.SG[sl]).view(sl.numel(), c.shape[0], 2, bb)
        peak = torch.addcmul(v[:, :, 1].square(), v[:, :, 0], v[:, :, 0]).amax(-1).sqrt()
        cw2 = (cf / self.SS[sl][:, None, :]).square().sum(-1).double()
        cn2 = (c.double() ** 2).sum(1)[None]
        # |c_perp|, widened for the rounding of |c W_r|^2 (float32)
        cperp = ((cn2 - cw2).clamp(min=0) + 1e-6 * cn2).sqrt()
        # rounding of the two float32 products: 2 sqrt(P) u |c| S_1, on top of H2's own
        rnd = 2 * math.sqrt(c.shape[1]) * torch.finfo(c.dtype).eps * cn2.sqrt() * self.SS[sl][:, :1].double()
        return peak.double() * (1 + 1e-4) + cperp * self.Snext[sl][:, None] + rnd + 2 * slack.double()

    def refine(self, w: torch.Tensor, threshold: torch.Tensor, env=None, tier: int = 2) -> torch.Tensor:
        """Settle selections whose certificate failed: (B,) True where the exact image on every
        block (outside E for tier 1, outside the band for tier 2) whose bound reaches
        ``threshold`` (the peak less its error bound) stays below it.

        Blocks wholly inside the strips (tier 1) take their values from the precomputed strip
        pair images, one small product per block for all selections at once (block-major
        columns of ``H2``); other blocks are delay-and-summed from the selection's I/Q channels
        (:meth:`channels`). Either way a selection with a few loose blocks costs far less than
        a whole-grid exact image.
        """
        B = w.shape[0]
        out = torch.zeros(B, dtype=torch.bool)
        S = self.S1 if tier == 1 else self.S2
        if S.shape[0] == 0 or B == 0:
            return out
        blocks = self.blocks1 if tier == 1 else self.blocks2
        w = w.detach()
        clear = self.bound(w, tier, per_block=True, env=env) < threshold[None]  # (nQ, B)
        strip = torch.zeros(S.shape[0], dtype=torch.bool)
        if tier == 1 and self.npix2:
            # blocks wholly inside the strips: their pair images are precomputed (exact to rounding)
            col0 = self.strip_block_col
            strip = col0 >= 0
            todo = torch.nonzero(strip & ~clear.all(1).cpu()).flatten()
            c = self._pairs(w)
            slack = self._rounding(c)
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
                # runs of blocks adjacent in H2 (gaps of up to 2 blocks are computed too)
                slot = col0[todo] // (2 * bb)
                cut = torch.nonzero(slot[1:] - slot[:-1] > 3).flatten() + 1
                for run in torch.tensor_split(todo, cut.tolist()):
                    first, last = int(col0[run[0]]), int(col0[run[-1]]) + 2 * bb
                    v = (c @ self.H2[:, first:last]).view(B, -1, 2, bb)
                    peak2 = torch.addcmul(v[:, :, 1].square(), v[:, :, 0], v[:, :, 0]).amax(2)  # (B, blocks)
                    at = (col0[run] - first) // (2 * bb)
                    clear[run] |= (peak2[:, at.to(peak2.device)] < limit[:, None]).T
        clear = clear.cpu()
        X = None
        for i in range(B):
            left = torch.nonzero(~clear[:, i]).flatten()
            if not left.numel():
                out[i] = True
                continue
            if bool(strip[left].any()) or left.numel() > self.refine_max_blocks:
                continue  # a strip block reaches the peak, or too many blocks to beamform
            if X is None:
                X = self.channels(w)
            img = self._das(X[i], [tuple(int(v) for v in blocks[q]) for q in left.tolist()])
            out[i] = bool(img.abs().max() * (1 + 1e-4) < threshold[i])
        return out

    @staticmethod
    def _cut(img, z0, x0, size):
        B = img.shape[0]
        ar = torch.arange(size, device=img.device)
        zi = (z0[:, None] + ar[None])[:, :, None]
        xi = (x0[:, None] + ar[None])[:, None, :]
        bi = torch.arange(B, device=img.device)[:, None, None]
        win = img[bi, zi, xi]
        top = win.detach().abs().reshape(B, -1).amax(dim=1)
        return _unit_norm(win, torch.where(top > 0, top, torch.ones_like(top)), with_norm=True)

    #: at most this many pixels tied with the peak (within the error bound) are settled exactly
    max_ties = 256
    #: largest bound of the relative L2 error of a fast-path kernel window (else: exact path);
    #: a sketched basis (large probes) carries the sketch's term in every bound and uses
    #: :data:`_SKETCH_KERNEL_TOL` instead
    kernel_tol = 5e-3

    def _exact_pixels(self, X: torch.Tensor, zi: torch.Tensor, xi: torch.Tensor) -> torch.Tensor:
        """Exact compound image values at grid pixels (zi, xi) of one selection from its I/Q
        channels ``X`` (ntx, Ne, T) (delay-and-sum with the cached block plans, as the exact path)."""
        s = self.model.setup
        b = self.model.block
        zi, xi = zi.cpu(), xi.cpu()
        blocks, rows, order = [], [], []
        qz, qx = zi // b, xi // b
        for z_, x_ in torch.unique(torch.stack([qz, qx], 1), dim=0).tolist():
            sel = torch.nonzero((qz == z_) & (qx == x_)).flatten()
            bw = min(b, s.n_x - x_ * b)
            blocks.append((z_, x_))
            rows.append((zi[sel] - z_ * b) * bw + (xi[sel] - x_ * b))
            order.append(sel)
        vals = self._das(X, blocks, rows)
        out = torch.empty_like(vals)
        out[torch.cat(order).to(vals.device)] = vals
        return out

    def _locate(self, img: torch.Tensor, eps: torch.Tensor, w: torch.Tensor, row0: int, col0: int):
        """Peak pixel of the exact image, from an approximation ``img`` (B, h, wd) at grid offset
        (row0, col0) whose |.| error is at most ``eps`` (B,).

        Every pixel within 2 eps of the approximate peak may be the exact peak: those are
        evaluated exactly (:meth:`_exact_pixels`) and the largest wins (the first in row-major
        order, as ``argmax`` on the exact image). Returns the peak's grid row and column, a lower
        bound ``thr`` of the exact peak value and a flag (False: more than :attr:`max_ties` ties,
        or an all-zero image).
        """
        B, h, wd = img.shape
        with torch.no_grad():
            mag = img.detach().abs().reshape(B, -1)
            val, arg = mag.max(dim=1)
            cand = mag >= (val - 2 * eps)[:, None]
            n = cand.sum(dim=1)
            ok = (val > 0) & (n <= self.max_ties)
            amb = torch.nonzero(ok & (n > 1)).flatten()
            if amb.numel():
                arg = arg.clone()
                if (h, wd) == self.shape and (row0, col0) == (self.rows.start, self.cols.start):
                    amb = self._settle_in_core(cand, amb, arg, w)
            if amb.numel():
                X = self.channels(w[amb].detach())
                for i, b in enumerate(amb.tolist()):
                    idx = torch.nonzero(cand[b]).flatten()
                    v = self._exact_pixels(X[i], idx // wd + row0, idx % wd + col0).abs()
                    arg[b] = idx[int(torch.argmax(v))]
        return arg // wd + row0, arg % wd + col0, val - eps, ok

    def _settle_in_core(self, cand: torch.Tensor, amb: torch.Tensor, arg: torch.Tensor, w: torch.Tensor):
        """Settle the near-ties ``cand`` (B, npix) on E of the selections ``amb`` whose candidates
        all lie in the core, from the core's exact pair images (one product for all of them);
        writes their peak index into ``arg`` and returns the selections left (candidates
        outside the core)."""
        pos = getattr(self, "_core_pos", None)
        if pos is None or pos.device != cand.device:
            pos = torch.full((self.npix,), -1, dtype=torch.long)
            pos[self.core_pix] = torch.arange(self.core_pix.numel())
            pos = self._core_pos = pos.to(cand.device)
        ca = cand[amb]
        inside = ~(ca & (pos < 0)[None]).any(1)
        sel = amb[inside]
        if sel.numel():
            union = torch.nonzero(ca[inside].any(0)).flatten()
            cols = pos[union]
            nc = self.Hc.shape[1] // 2
            v = self._pairs(w[sel].detach()) @ self.Hc[:, torch.cat([cols, cols + nc])]
            nu = union.numel()
            mag2 = torch.addcmul(v[:, nu:].square(), v[:, :nu], v[:, :nu])
            mag2 = torch.where(ca[inside][:, union], mag2, torch.full_like(mag2, -1.0))
            arg[sel] = union[mag2.argmax(dim=1)]
        return amb[~inside]

    def _windows(self, pz, px, rows, cols):
        s = self.model.setup
        z0 = _window_start(pz, s.window, s.n_z)
        x0 = _window_start(px, s.window, s.n_x)
        fits = (z0 >= rows.start) & (z0 + s.window <= rows.stop) & (x0 >= cols.start) & \
               (x0 + s.window <= cols.stop)
        return z0, x0, fits

    def kernels(self, w: torch.Tensor):
        """Kernels (B, win, win) and a (B,) bool tensor: True where certified (else recompute).

        Certified: the exact peak is located (pixels tied with the approximate peak within the
        error bound are evaluated exactly), its window fits in the region, and the lower bound of
        the peak beats the bound of |I| outside the region (tier 1: E; tier 2: the band, whose
        loose blocks are then beamformed exactly, :meth:`refine`).
        """
        s = self.model.setup
        with torch.no_grad():
            wd = w.detach()
            env = self.envelopes(wd)
        img, eps, win_err = self.images(w, with_error=True)
        pz, px, thr, ok = self._locate(img, eps, w, self.rows.start, self.cols.start)
        z0, x0, fits = self._windows(pz, px, self.rows, self.cols)
        with torch.no_grad():
            ok = ok & fits
            passed = ok & (self.bound(wd, 1, env=env) < thr)
            retry = torch.nonzero(ok & ~passed).flatten()
            if retry.numel():
                passed[retry] = self.refine(wd[retry], thr[retry], env=env[:, retry], tier=1).to(passed.device)
            ok = passed
        z0e = torch.where(ok, z0 - self.rows.start, torch.zeros_like(z0))
        x0e = torch.where(ok, x0 - self.cols.start, torch.zeros_like(x0))
        out, norm = self._cut(img, z0e, x0e, s.window)
        ok = ok & (win_err <= self.kernel_tol * norm)
        todo = torch.nonzero(~ok).flatten()
        if todo.numel() and self.npix2:
            w2 = w[todo]
            band = self.band_images(w2, img[todo])
            pz2, px2, thr2, ok2 = self._locate(band, eps[todo], w2, self.rows.start, 0)
            z02, x02, fits2 = self._windows(pz2, px2, self.rows, slice(0, s.n_x))
            with torch.no_grad():
                ok2 = ok2 & fits2
                env2 = env[:, todo]
                passed = ok2 & (self.bound(wd[todo], 2, env=env2) < thr2)
                retry = torch.nonzero(ok2 & ~passed).flatten()
                if retry.numel():
                    passed[retry] = self.refine(wd[todo][retry], thr2[retry], env=env2[:, retry]).to(passed.device)
            z0b = torch.where(passed, z02 - self.rows.start, torch.zeros_like(z02))
            k2, norm2 = self._cut(band, z0b, torch.where(passed, x02, torch.zeros_like(x02)), s.window)
            passed = passed & (win_err[todo] <= self.kernel_tol * norm2)
            sel = torch.nonzero(passed).flatten()
            if sel.numel():
                out = out.index_put((todo[sel],), k2[sel])
                ok = ok.clone()
                ok[todo[sel]] = True
        todo = torch.nonzero(~ok).flatten()
        if todo.numel() and self.finer is not None:
            # a tighter error bound (the full stored rank) settles most of the rest
            k3, ok3 = self.finer.kernels(w[todo])
            sel = torch.nonzero(ok3.to(todo.device)).flatten()
            if sel.numel():
                out = out.index_put((todo[sel],), k3[sel])
                ok = ok.clone()
                ok[todo[sel]] = True
        return out, ok.cpu()


def _pixel_norms(H: torch.Tensor) -> torch.Tensor:
    """Norm over pairs of each pixel's complex column of a (P, 2 Npix) [re | im] matrix: (Npix,)."""
    n = H.shape[1] // 2
    return ((H[:, :n] ** 2).sum(0) + (H[:, n:] ** 2).sum(0)).sqrt()


def _pair_position(e: int, j: int, ne: int) -> int:
    """Row of pair (e <= j) in the order of :func:`pair_index` (row-major upper triangle)."""
    return e * ne - e * (e - 1) // 2 + (j - e)
