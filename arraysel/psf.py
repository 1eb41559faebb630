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
  of the pair products ``m_e m_j`` with ``H``. Because the SPEC searches the
  peak over the whole grid, the fast path also precomputes, for blocks of
  pixels outside ``E``, an upper bound ``U_Q,ej >= max_{p in Q} |H_ej(p)|``
  from the I/Q envelopes; ``sum |m_e m_j| U_Q,ej`` bounds ``|I|`` on block Q.
  A selection whose peak in ``E`` beats every block bound (and whose window
  fits in ``E``) provably has its global peak in ``E``; any other selection
  is recomputed by the exact path on the whole grid. The result is therefore
  the SPEC's kernel, up to floating-point rounding, for every selection.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import torch

from .beamform import das_apply, das_plan, iq_matrix
from .delays import plane_wave_delays
from .errors import NumericalError, ParameterError, SelectionError, check_number
from .probes import Acquisition, Probe, check_sampling
from .simus import (SimOptions, element_responses, grid_for_points, probe_response, pulse_spectrum,
                    spectra_to_rf)


@dataclass(frozen=True)
class PSFSetup:
    """Everything the PSF of a selection depends on (a scene's physics part).

    probe, acq: transducer and acquisition (fs, c, attenuation, pulse cycles).
    tilts: plane-wave tilts (radians); TX delays are the full array's.
    n_x, n_z: image grid size; pixel: grid pitch (m, default (c/fs)/4);
        ``x_i = (i - n_x//2) pixel``, ``z_i = (i + z_offset) pixel``.
    scatterer: (x, z) in metres (default: the pixel (x=0, z=(n_z//2) pixel)).
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

    def __post_init__(self):
        check_sampling(self.probe, self.acq)
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
        return (np.arange(self.n_x) - self.n_x // 2) * self.pitch

    @property
    def z(self) -> np.ndarray:
        return (np.arange(self.n_z) + self.z_offset) * self.pitch

    @property
    def scatterer_position(self) -> tuple[float, float]:
        if self.scatterer is not None:
            return float(self.scatterer[0]), float(self.scatterer[1])
        return 0.0, float((self.n_z // 2 + self.z_offset) * self.pitch)

    @property
    def wavelength(self) -> float:
        return self.acq.c / self.probe.fc


@dataclass
class _Transmit:
    delays: np.ndarray        # (Ne,)
    grid: object              # FrequencyGrid
    G: torch.Tensor           # (Ne, F) TX contributions R_j e^{i w tau_j}
    RC: torch.Tensor          # (Ne, F) RX spectra factor C(f) R_e(f)
    Q: torch.Tensor           # (T, T) I/Q matrix


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

    The precomputation itself always runs in float64.
    """

    def __init__(self, setup: PSFSetup, dtype=torch.float32, device="cpu", margin: int = 8, block: int = 8,
                 fast: bool = True, plan_cache_elements: int = 80_000_000):
        if dtype not in (torch.float32, torch.float64):
            raise ParameterError(f"dtype = {dtype} is not allowed; choose torch.float32 or torch.float64")
        self.setup = setup
        self.dtype = dtype
        self.cdtype = torch.complex64 if dtype == torch.float32 else torch.complex128
        self.device = torch.device(device)
        self.n_elements = setup.probe.n_elements
        self.margin = int(check_number("margin", margin, lo=0, hi=4096, integer=True))
        self.block = int(check_number("block", block, lo=1, hi=4096, integer=True))
        self._build_transmits()
        self._xg = torch.as_tensor(setup.x, dtype=torch.float64)
        self._zg = torch.as_tensor(setup.z, dtype=torch.float64)
        self._plans: dict = {}
        self._plan_elements = 0
        #: DAS plan entries (pixels x elements) kept in memory for the exact path
        self.plan_cache_elements = plan_cache_elements
        self.fast = None
        if fast:
            self.fast = _load_or_build_basis(self)
        self._ref = None

    # ------------------------------------------------------------------ exact path
    def _build_transmits(self):
        s = self.setup
        probe, acq = s.probe, s.acq
        xs, zs = s.scatterer_position
        xt = torch.tensor([xs], dtype=torch.float64)
        zt = torch.tensor([zs], dtype=torch.float64)
        delays_all = plane_wave_delays(probe, list(s.tilts), acq.c)
        self.transmits = []
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
            self.transmits.append(_Transmit(delays=delays, grid=grid, G=G, RC=R * C[None, :], Q=Q))

    def _weights(self, weights) -> torch.Tensor:
        w = weights if isinstance(weights, torch.Tensor) else torch.as_tensor(np.asarray(weights))
        if w.dim() == 1:
            w = w[None]
        if w.dim() != 2 or w.shape[-1] != self.n_elements:
            raise SelectionError(f"weights must have shape (B, {self.n_elements}), got {tuple(w.shape)}")
        w = w.to(device=self.device, dtype=self.dtype)
        return w

    def spectra(self, weights, tx: int) -> torch.Tensor:
        """Received spectra (B, Ne, F) of transmit ``tx`` for weights (B, Ne)."""
        t = self.transmits[tx]
        w = self._weights(weights)
        G = t.G.to(self.device, self.cdtype)
        RC = t.RC.to(self.device, self.cdtype)
        field_ = w.to(self.cdtype) @ G  # (B, F): field at the scatterer
        return w.to(self.cdtype)[:, :, None] * RC[None] * field_[:, None, :]

    def rf(self, weights, tx: int) -> torch.Tensor:
        """RF signals (B, Ne, T) of transmit ``tx`` (element-major, time last)."""
        return spectra_to_rf(self.spectra(weights, tx), self.transmits[tx].grid)

    def iq(self, weights, tx: int) -> torch.Tensor:
        """I/Q signals (B, Ne, T) of transmit ``tx``."""
        rf = self.rf(weights, tx)
        Q = self.transmits[tx].Q.to(self.device, self.cdtype)
        return rf.to(self.cdtype) @ Q.T

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
            if self._plan_elements + size <= self.plan_cache_elements:
                self._plans[key] = plan
                self._plan_elements += size
        return plan

    def image(self, weights, rows: slice | None = None, cols: slice | None = None,
              rows_per_chunk: int | None = None) -> torch.Tensor:
        """Exact compound image (B, nz', nx') on grid rows/cols (default: whole grid).

        Differentiable with respect to ``weights``.
        """
        rows = rows or slice(0, self.setup.n_z)
        cols = cols or slice(0, self.setup.n_x)
        w = self._weights(weights)
        iqs = [self.iq(w, n) for n in range(len(self.transmits))]
        nz = rows.stop - rows.start
        nx = cols.stop - cols.start
        if rows_per_chunk is None:
            rows_per_chunk = max(1, (2 ** 21) // max(1, nx * self.n_elements))
        out = []
        for r0 in range(rows.start, rows.stop, rows_per_chunk):
            r = slice(r0, min(rows.stop, r0 + rows_per_chunk))
            acc = 0
            for n, iq in enumerate(iqs):
                p = self._plan(n, r, cols)
                acc = acc + das_apply(iq, p.i0, p.w, p.rot)
            out.append(acc.reshape(w.shape[0], r.stop - r.start, nx))
        return torch.cat(out, dim=1) if len(out) > 1 else out[0].reshape(w.shape[0], nz, nx)

    def kernels_exact(self, weights) -> torch.Tensor:
        """SPEC kernels (B, window, window) from the exact whole-grid image."""
        img = self.image(weights)
        return window_and_normalise(img, self.setup.window)

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


def cache_dir() -> str | None:
    """Folder of the precomputation cache: ``$ARRAYSEL_CACHE`` ('off' disables), else ~/.cache/arraysel."""
    import os

    path = os.environ.get("ARRAYSEL_CACHE")
    if path is not None and path.strip().lower() in ("", "0", "off", "none"):
        return None
    return path or os.path.join(os.path.expanduser("~"), ".cache", "arraysel")


_BASIS_FIELDS = ("U", "V", "A", "S_crow", "S_col", "S_val")


def _load_or_build_basis(model: "PSFModel") -> "_PairBasis":
    """Build the fast-path basis, or load it from the on-disk cache (keyed by the scene physics)."""
    import hashlib
    import os
    import tempfile

    from . import __version__

    key = hashlib.sha256(repr((__version__, _BASIS_VERSION, model.setup, str(model.dtype), model.margin,
                               model.block)).encode()).hexdigest()[:24]
    folder = cache_dir()
    path = os.path.join(folder, f"psf-basis-{key}.pt") if folder else None
    if path and os.path.exists(path):
        try:
            state = torch.load(path, map_location=model.device, weights_only=True)
            return _PairBasis.from_state(model, state)
        except Exception:  # a corrupt or stale cache entry is rebuilt
            pass
    basis = _PairBasis(model)
    if path:
        try:
            os.makedirs(folder, exist_ok=True)
            fd, tmp = tempfile.mkstemp(dir=folder, suffix=".tmp")
            os.close(fd)
            torch.save(basis.state(), tmp)
            os.replace(tmp, path)
        except OSError:
            pass
    return basis


_BASIS_VERSION = 1


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
    norm = torch.linalg.vector_norm(win.reshape(B, -1), dim=1)
    if bool((norm.detach() == 0).any()) or not bool(torch.isfinite(norm.detach()).all()):
        raise NumericalError("PSF image is all zero or not finite for some selection "
                             "(is the selection empty, or the scatterer outside the grid?)")
    return win / norm[:, None, None].to(win.dtype)


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
    """Precomputed pair images on the exact region E and the peak certificate outside it.

    Image on E: ``I_E = c @ H`` with ``c`` the (B, P) pair products and ``H``
    the (P, 2 Npix) real pair images, stored compressed as ``U @ V`` (a
    truncated SVD whose discarded energy is below ``rank_tol`` of the total).

    Certificate: for transmit n and receive element e the I/Q channel of a
    selection is ``X_ne(t) = m_e sum_j m_j A_nej(t)`` (A: pair I/Q signals).
    Linear interpolation and unit phase rotations cannot exceed the larger
    neighbouring sample, so on a block Q of pixels outside E
    ``|I(p)| <= sum_{n,e} max_{t in [lo, hi]_{neQ}} |X_ne(t)|``, where
    ``[lo, hi]`` spans the samples the block's pixels read. ``lo``/``hi`` are
    precomputed; per selection the bound costs one small matrix product, a
    sliding maximum and a sparse sum.
    """

    def __init__(self, model: PSFModel, rank_tol: float = 1e-7, _state: dict | None = None):
        s = model.setup
        self.model = model
        ne = model.n_elements
        win = s.window
        m = model.margin
        xs, zs = s.scatterer_position
        iz = int(round(zs / s.pitch - s.z_offset))
        ix = int(round(xs / s.pitch + s.n_x // 2))
        half = win // 2
        z_lo = max(0, min(iz - half - m, s.n_z - win - 2 * m))
        x_lo = max(0, min(ix - half - m, s.n_x - win - 2 * m))
        self.rows = slice(z_lo, min(s.n_z, z_lo + win + 2 * m))
        self.cols = slice(x_lo, min(s.n_x, x_lo + win + 2 * m))
        self.shape = (self.rows.stop - self.rows.start, self.cols.stop - self.cols.start)
        self.npix = self.shape[0] * self.shape[1]
        self.e_idx, self.j_idx = pair_index(ne)
        if _state is not None:
            self._set_state(_state)
            return
        pair_iq = [self._pair_iq(n) for n in range(len(model.transmits))]
        self._build_images(pair_iq, rank_tol)
        self._build_certificate(pair_iq)

    def _pair_iq(self, n: int) -> torch.Tensor:
        """I/Q of every (rx e, tx j) pair for transmit n: (Ne, Ne, T) complex128."""
        t = self.model.transmits[n]
        spec = t.RC[:, None, :] * t.G[None, :, :]  # (e, j, F)
        rf = spectra_to_rf(spec, t.grid)
        return rf.to(torch.complex128) @ t.Q.T

    def _build_images(self, pair_iq, rank_tol):
        model = self.model
        s = model.setup
        ne = model.n_elements
        Z, X = torch.meshgrid(model._zg[self.rows], model._xg[self.cols], indexing="ij")
        npix = self.npix
        Hfull = torch.zeros(ne, ne, npix, dtype=torch.complex128)
        for n, t in enumerate(model.transmits):
            iq = pair_iq[n]
            plan = das_plan(X, Z, t.delays, s.probe, s.acq.fs, s.acq.c, t.grid.n_time,
                            fnumber=s.fnumber, fc=s.probe.fc)
            T = iq.shape[-1]
            step = max(1, 2 ** 23 // (ne * npix))
            for e0 in range(0, ne, step):
                e1 = min(ne, e0 + step)
                idx = plan.i0[:, e0:e1].T[:, None, :].expand(-1, ne, -1)
                wt = plan.w[:, e0:e1].T[:, None, :]
                rot = plan.rot[:, e0:e1].T[:, None, :]
                src = iq[e0:e1]
                a = torch.gather(src, 2, idx)
                b = torch.gather(src, 2, (idx + 1).clamp(max=T - 1))
                Hfull[e0:e1] += (a + (b - a) * wt) * rot
        e, j = self.e_idx, self.j_idx
        Hs = Hfull[e, j] + torch.where((e != j)[:, None], Hfull[j, e], torch.zeros_like(Hfull[e, j]))
        del Hfull
        H = torch.cat([Hs.real, Hs.imag], dim=1)  # (P, 2 Npix) float64
        del Hs
        # truncated SVD through the (P x P) Gram matrix
        gram = H @ H.T
        evals, evecs = torch.linalg.eigh(gram)
        evals = evals.flip(0).clamp(min=0)
        evecs = evecs.flip(1)
        tail = evals.sum() - torch.cumsum(evals, 0)
        rank = int(torch.nonzero(tail <= rank_tol * evals.sum()).flatten()[0]) + 1
        U = evecs[:, :rank]
        V = U.T @ H  # (R, 2 Npix)
        self.rank = rank
        self.rank_tail = float(tail[rank - 1] / evals.sum())
        self.U = U.to(model.device, model.dtype)
        self.V = V.to(model.device, model.dtype)

    def _build_certificate(self, pair_iq):
        model = self.model
        s = model.setup
        ne = model.n_elements
        ntx = len(model.transmits)
        b = model.block
        T = max(x.shape[-1] for x in pair_iq)
        # A: (Ne_j, ntx * Ne_e * T) complex -> real [re | im]
        A = torch.zeros(ne, ntx, ne, T, dtype=torch.complex128)
        for n, iq in enumerate(pair_iq):
            A[:, n, :, : iq.shape[-1]] = iq.permute(1, 0, 2)
        A = A.reshape(ne, -1)
        self.T = T
        self.A = torch.cat([A.real, A.imag], dim=1).to(model.device, model.dtype)
        nbz = -(-s.n_z // b)
        nbx = -(-s.n_x // b)
        bz = torch.arange(nbz)
        bx = torch.arange(nbx)
        inside_z = (bz * b >= self.rows.start) & ((bz + 1) * b <= self.rows.stop)
        inside_x = (bx * b >= self.cols.start) & ((bx + 1) * b <= self.cols.stop)
        outside = ~(inside_z[:, None] & inside_x[None, :])  # (nbz, nbx)
        lo = torch.full((ntx, nbz, nbx, ne), T, dtype=torch.long)
        hi = torch.full((ntx, nbz, nbx, ne), -1, dtype=torch.long)
        rows_per = max(b, (2 ** 21 // (s.n_x * ne)) // b * b)
        for n, t in enumerate(model.transmits):
            for r0 in range(0, s.n_z, rows_per):
                rows = slice(r0, min(s.n_z, r0 + rows_per))
                nr = rows.stop - rows.start
                Z, X = torch.meshgrid(model._zg[rows], model._xg, indexing="ij")
                plan = das_plan(X, Z, t.delays, s.probe, s.acq.fs, s.acq.c, t.grid.n_time,
                                fnumber=s.fnumber, fc=s.probe.fc)
                valid = (plan.rot.abs() > 0).reshape(nr, s.n_x, ne)
                i0 = plan.i0.reshape(nr, s.n_x, ne)
                lo_p = torch.where(valid, i0, torch.full_like(i0, T))
                hi_p = torch.where(valid, i0 + 1, torch.full_like(i0, -1))
                padz = -(-nr // b) * b - nr
                padx = nbx * b - s.n_x
                lo_p = torch.nn.functional.pad(lo_p, (0, 0, 0, padx, 0, padz), value=T)
                hi_p = torch.nn.functional.pad(hi_p, (0, 0, 0, padx, 0, padz), value=-1)
                q0 = r0 // b
                nq = lo_p.shape[0] // b
                lo_b = lo_p.reshape(nq, b, nbx, b, ne).amin(dim=(1, 3))
                hi_b = hi_p.reshape(nq, b, nbx, b, ne).amax(dim=(1, 3))
                lo[n, q0:q0 + nq] = torch.minimum(lo[n, q0:q0 + nq], lo_b)
                hi[n, q0:q0 + nq] = torch.maximum(hi[n, q0:q0 + nq], hi_b)
        qz, qx = torch.nonzero(outside, as_tuple=True)
        lo = lo[:, qz, qx]  # (ntx, nQ, Ne)
        hi = hi[:, qz, qx]
        has = hi >= lo
        length = torch.where(has, hi - lo + 1, torch.zeros_like(lo))
        self.L = max(1, int(length.max()))
        nq = qz.numel()
        self.n_blocks = nq
        # column index of (n, e, lo) in the flattened sliding-max envelope (ntx, Ne, T)
        n_ar = torch.arange(ntx)[:, None, None]
        e_ar = torch.arange(ne)[None, None, :]
        col = (n_ar * ne + e_ar) * T + lo.clamp(0, T - 1)
        q_ar = torch.arange(nq)[None, :, None].expand_as(col)
        sel = has
        rows_i = q_ar[sel]
        cols_i = col[sel]
        order = torch.argsort(rows_i * (ntx * ne * T) + cols_i)
        rows_i, cols_i = rows_i[order], cols_i[order]
        crow = torch.zeros(nq + 1, dtype=torch.long)
        crow[1:] = torch.cumsum(torch.bincount(rows_i, minlength=nq), 0)
        vals = torch.full((rows_i.numel(),), 1.0 + 1e-4, dtype=model.dtype)  # rounding safety margin
        self.S = _csr(crow, cols_i, vals, (nq, ntx * ne * T)).to(model.device)

    def state(self) -> dict:
        S = self.S
        return {"U": self.U.cpu(), "V": self.V.cpu(), "A": self.A.cpu(), "S_crow": S.crow_indices().cpu(),
                "S_col": S.col_indices().cpu(), "S_val": S.values().cpu(),
                "meta": torch.tensor([self.T, self.L, self.rank, S.shape[0], S.shape[1]]),
                "rank_tail": torch.tensor(self.rank_tail)}

    def _set_state(self, st: dict):
        dev, dt = self.model.device, self.model.dtype
        self.U, self.V, self.A = (st[k].to(dev, dt) for k in ("U", "V", "A"))
        self.T, self.L, self.rank, nq, ncol = (int(v) for v in st["meta"])
        self.rank_tail = float(st["rank_tail"])
        self.n_blocks = nq
        self.S = _csr(st["S_crow"], st["S_col"], st["S_val"].to(dt), (nq, ncol)).to(dev)

    @classmethod
    def from_state(cls, model, state):
        return cls(model, _state=state)

    def images(self, w: torch.Tensor) -> torch.Tensor:
        """Images on region E, (B, nzE, nxE) complex."""
        c = pair_products(w, self.e_idx.to(w.device), self.j_idx.to(w.device))
        y = (c @ self.U) @ self.V
        img = torch.complex(y[:, : self.npix], y[:, self.npix:])
        return img.reshape(w.shape[0], *self.shape)

    def bound(self, w: torch.Tensor) -> torch.Tensor:
        """(B,) upper bound of |I| on the blocks outside region E."""
        B = w.shape[0]
        if self.n_blocks == 0:
            return torch.zeros(B, dtype=w.dtype, device=w.device)
        ne = self.model.n_elements
        ntx = len(self.model.transmits)
        y = w @ self.A  # (B, 2 * ntx * Ne * T)
        half = y.shape[1] // 2
        env = torch.sqrt(y[:, :half] ** 2 + y[:, half:] ** 2).reshape(B, ntx, ne, self.T)
        env = env * w.abs()[:, None, :, None]
        if self.L > 1:
            env = torch.nn.functional.pad(env.reshape(B * ntx * ne, 1, self.T), (0, self.L - 1))
            env = torch.nn.functional.max_pool1d(env, self.L, stride=1)
        env = env.reshape(B, -1)
        bounds = torch.sparse.mm(self.S, env.T.contiguous())  # (nQ, B)
        return bounds.amax(dim=0)

    def kernels(self, w: torch.Tensor):
        s = self.model.setup
        img = self.images(w)
        B = w.shape[0]
        nzE, nxE = self.shape
        mag = img.detach().abs().reshape(B, -1)
        val, arg = mag.max(dim=1)
        with torch.no_grad():
            bnd = self.bound(w.detach())
        pz = arg // nxE + self.rows.start
        px = arg % nxE + self.cols.start
        z0 = _window_start(pz, s.window, s.n_z)
        x0 = _window_start(px, s.window, s.n_x)
        fits = (z0 >= self.rows.start) & (z0 + s.window <= self.rows.stop) & \
               (x0 >= self.cols.start) & (x0 + s.window <= self.cols.stop)
        ok = fits & (bnd < val) & (val > 0)
        z0e = torch.where(ok, z0 - self.rows.start, torch.zeros_like(z0))
        x0e = torch.where(ok, x0 - self.cols.start, torch.zeros_like(x0))
        ar = torch.arange(s.window, device=w.device)
        zi = (z0e[:, None] + ar[None])[:, :, None]
        xi = (x0e[:, None] + ar[None])[:, None, :]
        bi = torch.arange(B, device=w.device)[:, None, None]
        win = img[bi, zi, xi]
        norm = torch.linalg.vector_norm(win.reshape(B, -1), dim=1)
        safe = torch.where(norm > 0, norm, torch.ones_like(norm))
        return win / safe[:, None, None].to(win.dtype), ok.cpu()
