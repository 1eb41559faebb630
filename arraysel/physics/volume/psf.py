"""The exact 3-D point-spread function of a matrix probe, on three planes through the scatterer.

For one point scatterer and a set of transmits (full-array delays, :mod:`.delays`), a selection
enters as element weights ``m`` (B, Ne) used as TX apodization and RX channel weights (an
inactive element: weight 0, its delay kept). Each transmit is simulated (SIMUS3, :mod:`.simus`),
demodulated (the 1-D ``rf2iq`` map, :class:`~arraysel.physics.psf.operator.Transmit`), beamformed
with delay-and-sum (:mod:`.beamform`) and the images are summed coherently.

The image is sampled on three planes through the scatterer ``(xs, ys, zs)`` (``docs/matrix.md``):

* ``"xy"``: the C-plane z = zs, rows along y, columns along x;
* ``"xz"``: the plane y = ys, rows along z, columns along x;
* ``"yz"``: the plane x = xs, rows along z, columns along y.

An axis of half-size ``h`` has ``n = max(1, round(2 h / pixel))`` pixels at
``centre + (i - n // 2) pixel``, so the scatterer sits on pixel ``n // 2`` of each axis and the
three planes share the pixel through it. :meth:`MatrixPSF.planes` returns
``dict[name, complex Tensor (B, H, W)]``, :attr:`MatrixPSF.coords` ``dict[name, Tensor (H, W, 3)]``
(x, y, z in metres). The values are the compounded DAS sums in units of ``image_scale`` (not
normalised per selection); :func:`peak_normalise` divides a selection's three planes by their
joint peak magnitude.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import torch

from arraysel.errors import NumericalError, ParameterError, SelectionError, check_number
from arraysel.physics.beamform import das_apply
from arraysel.physics.probes import MATRIX_PLANES, Acquisition, MatrixProbe, PlanarProbe, check_sampling
from arraysel.physics.psf.operator import normalised_transmits, receive_weights
from arraysel.physics.psf.window import scale_complex
from arraysel.physics.simus import SimOptions, probe_response, pulse_spectrum
from arraysel.physics.volume.beamform import receive_distance3, transmit_distance3
from arraysel.physics.volume.simus import element_responses3, grid_for_points3

__all__ = ["PLANES", "MatrixPSFSetup", "MatrixPSF", "plane_axes", "peak_normalise", "check_element_weights"]

#: a batch on the CPU whose delay-and-sum reads at least this many (pixel, element, transmit)
#: entries goes to the compiled kernels (:mod:`.kernels`, with their adjoint for the gradient):
#: below it, loading the compiled code costs more than torch's passes
COMPILED_MIN_ENTRIES = 1 << 21


class _CompiledDAS(torch.autograd.Function):
    """The delay-and-sum of :meth:`MatrixPSF.image` by the compiled kernels: forward
    :func:`~arraysel.physics.volume.kernels.das3`, backward its adjoint; memory O(I/Q), not
    O(pixels x elements) as torch's graph would keep."""

    @staticmethod
    def forward(ctx, iq, geo):
        from arraysel.physics.volume.kernels import das3

        rows, tx_pos, rx_pos_t, tx_rot, rx_rot_t, s0, n_time = geo
        out = np.zeros((rx_pos_t.shape[1], iq.shape[-1]), dtype=tx_rot.dtype)
        das3(iq.detach().resolve_conj().numpy(), rows, tx_pos, rx_pos_t, tx_rot, rx_rot_t, s0, n_time, out)
        ctx.geo = geo
        ctx.iq_shape = tuple(iq.shape)
        return torch.from_numpy(out)

    @staticmethod
    def backward(ctx, grad):
        from arraysel.physics.volume.kernels import das3_adjoint

        rows, tx_pos, rx_pos_t, tx_rot, rx_rot_t, s0, n_time = ctx.geo
        giq = np.zeros(ctx.iq_shape, dtype=tx_rot.dtype)
        das3_adjoint(np.ascontiguousarray(grad.resolve_conj().numpy()), rows, tx_pos, rx_pos_t, tx_rot, rx_rot_t,
                     s0, n_time, giq)
        return torch.from_numpy(giq), None

#: the planes, in this order: the C-plane at the scatterer's depth, then the xz and yz planes
PLANES = MATRIX_PLANES


def _axis(name: str, half: float, pixel: float) -> int:
    return max(1, int(round(2 * half / pixel)))


@dataclass(frozen=True, eq=False)
class MatrixPSFSetup:
    """Everything the 3-D PSF of a selection depends on.

    probe, acq: the matrix probe and the acquisition (fs, c, attenuation, pulse cycles).
    delays: (n_tx, Ne) full-array transmit delays (s, finite; e.g. ``diverging_delays3``).
    scatterer: (x, y, z) in metres, z > 0.
    half_x, half_y, half_z: half-sizes (m, > 0) of the planes along each axis.
    pixel: pixel pitch of every plane (m, > 0).
    planes: names of the planes to compute (a subset of :data:`PLANES`).
    reflectivity, iq_bandwidth (%, default the probe's), options: as in 1-D.
    """

    probe: MatrixProbe
    acq: Acquisition
    delays: np.ndarray
    scatterer: tuple
    half_x: float
    half_y: float
    half_z: float
    pixel: float
    planes: tuple = PLANES
    reflectivity: float = 1.0
    iq_bandwidth: float | None = None
    options: SimOptions = field(default_factory=SimOptions)

    def __post_init__(self):
        if not isinstance(self.probe, (MatrixProbe, PlanarProbe)):
            raise ParameterError(f"probe must be a MatrixProbe or a PlanarProbe (a 3-D PSF needs a 2-D array), got "
                                 f"{type(self.probe).__name__}")
        check_sampling(self.probe, self.acq)
        d = np.asarray(self.delays, dtype=np.float64)
        if d.ndim == 1:
            d = d[None]
        if d.ndim != 2 or d.shape[1] != self.probe.n_elements or d.shape[0] < 1:
            raise ParameterError(f"delays must have shape (n_tx, {self.probe.n_elements}), got {d.shape}")
        if not np.isfinite(d).all():
            raise ParameterError("delays must be finite (an inactive element keeps its delay and gets weight 0)")
        object.__setattr__(self, "delays", d)
        if len(self.scatterer) != 3:
            raise ParameterError(f"scatterer must be (x, y, z) in metres, got {self.scatterer!r}")
        xs, ys, zs = (float(v) for v in self.scatterer)
        check_number("scatterer x (m)", xs, lo=-1, hi=1)
        check_number("scatterer y (m)", ys, lo=-1, hi=1)
        check_number("scatterer z (m)", zs, lo=0, lo_open=True, hi=2)
        object.__setattr__(self, "scatterer", (xs, ys, zs))
        pixel = check_number("pixel", self.pixel, lo=0, lo_open=True, hi=0.1)
        for key in ("half_x", "half_y", "half_z"):
            check_number(key, getattr(self, key), lo=0, lo_open=True, hi=0.5)
            n = _axis(key, getattr(self, key), pixel)
            if n > 4096:
                raise ParameterError(f"{key} = {getattr(self, key)!r} m is {n} pixels of {pixel!r} m; allowed: "
                                     "at most 4096 pixels an axis")
        nz = _axis("half_z", self.half_z, pixel)
        top = zs - (nz // 2) * pixel
        if top <= 0:
            raise ParameterError(f"half_z = {self.half_z!r} m reaches above the array: the planes' first row lies "
                                 f"at z = {top!r} m (need z > 0; scatterer depth {zs!r} m)")
        planes = tuple(self.planes)
        bad = [p for p in planes if p not in PLANES]
        if bad or not planes or len(set(planes)) != len(planes):
            raise ParameterError(f"planes = {self.planes!r}: allowed a non-empty subset of {PLANES}")
        object.__setattr__(self, "planes", planes)
        check_number("reflectivity", self.reflectivity, lo=0, lo_open=True)

    @property
    def n_tx(self) -> int:
        return int(self.delays.shape[0])


def plane_axes(setup: MatrixPSFSetup) -> dict[str, torch.Tensor]:
    """Pixel coordinates (float64, H, W, 3) of each plane of ``setup`` (see the module docstring)."""
    xs, ys, zs = setup.scatterer
    p = setup.pixel

    def ax(c, half):
        n = _axis("", half, p)
        return torch.as_tensor(c + (np.arange(n) - n // 2) * p, dtype=torch.float64)

    x, y, z = ax(xs, setup.half_x), ax(ys, setup.half_y), ax(zs, setup.half_z)
    out = {}
    for name in setup.planes:
        if name == "xy":
            Y, X = torch.meshgrid(y, x, indexing="ij")
            out[name] = torch.stack([X, Y, torch.full_like(X, zs)], dim=-1)
        elif name == "xz":
            Z, X = torch.meshgrid(z, x, indexing="ij")
            out[name] = torch.stack([X, torch.full_like(X, ys), Z], dim=-1)
        else:
            Z, Y = torch.meshgrid(z, y, indexing="ij")
            out[name] = torch.stack([torch.full_like(Y, xs), Y, Z], dim=-1)
    return out


def check_surfaces(coords) -> dict[str, torch.Tensor]:
    """``coords`` ``{name: (H, W, 3)}`` as float64 tensors, checked: a non-empty dict of finite
    positions in metres below the array (z > 0), at least 1 x 1 pixels each."""
    if not isinstance(coords, dict) or not coords:
        raise ParameterError("coords must be a non-empty dict {name: array (H, W, 3)} of positions in metres")
    out = {}
    for name, c in coords.items():
        t = torch.as_tensor(np.asarray(c.detach().cpu() if isinstance(c, torch.Tensor) else c, dtype=np.float64))
        if t.dim() != 3 or t.shape[-1] != 3 or t.shape[0] < 1 or t.shape[1] < 1:
            raise ParameterError(f"coords[{name!r}] must have shape (H, W, 3), got {tuple(t.shape)}")
        if not bool(torch.isfinite(t).all()) or not bool((t[..., 2] > 0).all()):
            raise ParameterError(f"coords[{name!r}] must be finite positions below the array (z > 0, metres)")
        out[str(name)] = t
    return out


def split_planes(img: torch.Tensor, shapes: dict[str, tuple[int, int]]) -> dict[str, torch.Tensor]:
    """The planes ``{name: (B, H, W)}`` of an image (B, Npix) whose pixels are the planes'
    pixels concatenated in ``shapes`` order (``{name: (H, W)}``)."""
    out, k = {}, 0
    for name, (h, w) in shapes.items():
        out[name] = img[:, k:k + h * w].reshape(-1, h, w)
        k += h * w
    return out


def check_element_weights(weights, n_elements: int, dtype, device) -> torch.Tensor:
    """Element weights as a (B, Ne) tensor of ``dtype`` on ``device``; SelectionError for another
    shape or a value that is not finite."""
    w = weights if isinstance(weights, torch.Tensor) else torch.as_tensor(np.asarray(weights, dtype=np.float64))
    if w.dim() == 1:
        w = w[None]
    if w.dim() != 2 or w.shape[-1] != n_elements:
        raise SelectionError(f"weights must have shape (B, {n_elements}) (element iy * nx + ix), "
                             f"got {tuple(w.shape)}")
    if not bool(torch.isfinite(w.detach()).all()):
        raise SelectionError("weights must be finite")
    return w.to(device=device, dtype=dtype)


def transmit_event_weights(weights, n_tx: int, n_elements: int, dtype, device) -> torch.Tensor:
    """Transmit apodizations, one per transmit event: ``(B, n_tx, Ne)`` as given, or ``(B, Ne)``
    (one aperture for every event) as a ``(B, 1, Ne)`` view; SelectionError for another shape or
    a value that is not finite."""
    if isinstance(weights, torch.Tensor) and weights.dim() == 3 or not isinstance(weights, torch.Tensor) \
            and np.ndim(weights) == 3:
        w = weights if isinstance(weights, torch.Tensor) else torch.as_tensor(np.asarray(weights, dtype=np.float64))
        if w.shape[1:] != (n_tx, n_elements):
            raise SelectionError(f"per-transmit weights must have shape (B, {n_tx}, {n_elements}) (one transmit "
                                 f"apodization per transmit event), got {tuple(w.shape)}")
        if not bool(torch.isfinite(w.detach()).all()):
            raise SelectionError("weights must be finite")
        return w.to(device=device, dtype=dtype)
    return check_element_weights(weights, n_elements, dtype, device)[:, None]


def peak_normalise(planes: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """Each selection's planes divided by their joint peak magnitude (the largest ``|value|`` over
    all its planes; detached), so that the peak is 1. Raises NumericalError for an all-zero one."""
    peak = torch.stack([v.detach().abs().flatten(1).amax(1) for v in planes.values()]).amax(0)
    if bool((peak == 0).any()) or not bool(torch.isfinite(peak).all()):
        raise NumericalError("a 3-D PSF is all zero or not finite (is the selection empty?)")
    return {k: scale_complex(v, peak.to(v.real.dtype)) for k, v in planes.items()}


class MatrixPSF:
    """The exact 3-D PSF on three planes, batched over selections and differentiable in the weights.

    Parameters: setup (:class:`MatrixPSFSetup`); dtype torch.float32 or torch.float64 (the
    precomputation runs in float64); device; ``pixel_chunk`` pixels per DAS call; ``coords``:
    any set of surfaces ``{name: (H, W, 3)}`` (metres, z > 0) to image instead of the setup's
    planes (e.g. :func:`~arraysel.physics.beampattern.sphere_surface`, a surface sampled in angle
    at the scatterer's range); :meth:`planes` then returns those surfaces.
    """

    def __init__(self, setup: MatrixPSFSetup, dtype=torch.float32, device="cpu", pixel_chunk: int = 512,
                 coords: dict | None = None):
        if dtype not in (torch.float32, torch.float64):
            raise ParameterError(f"dtype = {dtype} is not allowed; choose torch.float32 or torch.float64")
        self.setup = setup
        self.dtype = dtype
        self.cdtype = torch.complex64 if dtype == torch.float32 else torch.complex128
        self.device = torch.device(device)
        self.n_elements = setup.probe.n_elements
        self.pixel_chunk = int(check_number("pixel_chunk", pixel_chunk, lo=1, hi=1 << 20, integer=True))
        #: pixel coordinates of each plane, float64 (H, W, 3) metres
        self.coords = plane_axes(setup) if coords is None else check_surfaces(coords)
        self._shapes = {k: tuple(v.shape[:2]) for k, v in self.coords.items()}
        pts = torch.cat([v.reshape(-1, 3) for v in self.coords.values()])
        self._build_transmits()
        s = setup
        fs, c, fc = s.acq.fs, s.acq.c, s.probe.fc
        drx = receive_distance3(pts, s.probe)  # (Npix, Ne) float64
        #: receive sample positions |p - r_e| fs / c (float64, on the device) and phase rotations
        self._rx_pos = (drx * (fs / c)).to(self.device)
        self._rx_rot = torch.polar(torch.ones_like(drx), 2 * math.pi * fc / c * drx).to(self.device, self.cdtype)
        self._tx_pos, self._tx_rot, self._samples, self._maps = [], [], [], []
        rmin = self._rx_pos.amin(1).cpu()
        rmax = self._rx_pos.amax(1).cpu()
        for t in self.transmits:
            dtx = transmit_distance3(pts, t.delays, s.probe, c)
            tp = dtx * (fs / c)
            n_t = t.grid.n_time
            lo = float((tp + rmin).min())
            hi = float((tp + rmax).max())
            s0 = int(min(max(0, math.floor(lo)), n_t - 2))
            s1 = int(max(min(n_t - 2, math.floor(hi)) + 2, s0 + 2))
            self._tx_pos.append(tp.to(self.device))
            rot = torch.polar(torch.ones_like(dtx), 2 * math.pi * fc / c * dtx)
            self._tx_rot.append(rot.to(self.device, self.cdtype))
            self._samples.append((s0, s1))
            self._maps.append(t.iq_map(slice(s0, s1)).to(self.device, self.dtype))
        self._rx_pos_t = self._rx_rot_t = None
        if self.device.type == "cpu":  # the compiled path's copies, (n_tx, Npix)
            self._tx_pos_np = torch.stack(self._tx_pos).numpy()
            self._tx_rot_np = torch.stack(self._tx_rot).numpy()

    def _build_transmits(self):
        s = self.setup
        probe, acq = s.probe, s.acq
        pt = torch.tensor([s.scatterer], dtype=torch.float64)
        parts = []
        for delays in s.delays:
            grid = grid_for_points3(pt, delays, probe, acq, s.options)
            f = grid.f
            R = element_responses3(pt, f, probe, acq.c, acq.attenuation, s.options)[0]  # (Ne, F)
            w = 2 * math.pi * f
            tau = torch.as_tensor(delays, dtype=torch.float64)
            G = R * torch.polar(torch.ones_like(tau[:, None] * w), tau[:, None] * w)
            H = probe_response(f, probe.fc, probe.bandwidth)
            C = pulse_spectrum(f, probe.fc, acq.tx_cycles) * H * H * s.reflectivity
            band = (acq.fs, probe.fc, probe.bandwidth if s.iq_bandwidth is None else s.iq_bandwidth)
            parts.append((delays, grid, G, R * C[None, :], band))
        #: physical value (SIMUS3's RF amplitude) of one unit of :meth:`iq` and :meth:`planes`
        self.image_scale, self.transmits = normalised_transmits(parts)

    # ------------------------------------------------------------------ pieces
    def _weights(self, weights) -> torch.Tensor:
        return check_element_weights(weights, self.n_elements, self.dtype, self.device)

    def _apertures(self, weights, receive) -> tuple[torch.Tensor, torch.Tensor]:
        """``(transmit (B, n_tx or 1, Ne), receive (B, Ne))`` of :meth:`image`'s arguments."""
        w = transmit_event_weights(weights, len(self.transmits), self.n_elements, self.dtype, self.device)
        if w.shape[1] > 1 and receive is None:
            raise SelectionError("per-transmit weights (B, n_tx, Ne) need the receive weights (receive=)")
        return w, (w[:, 0] if receive is None else receive_weights(w[:, 0], receive, self._weights))

    def iq(self, weights, tx: int, elements: torch.Tensor | None = None, receive=None) -> torch.Tensor:
        """I/Q signals (B, n, T) of transmit ``tx`` for the receive ``elements`` (default all),
        on the samples the planes read (``_samples[tx]``), in units of ``image_scale``;
        ``receive`` (B, Ne): separate RX channel weights (``weights`` then the TX apodization,
        (B, Ne) or (B, n_tx, Ne): one per transmit event)."""
        t = self.transmits[tx]
        w, r = self._apertures(weights, receive)
        w = w[:, tx if w.shape[1] > 1 else 0]
        G = t.tx_field.to(self.device, self.cdtype)
        RC = t.rx_factor.to(self.device, self.cdtype)
        field_ = w.to(self.cdtype) @ G  # (B, F): the field at the scatterer
        if elements is not None:
            RC, wr = RC[elements], r[:, elements]
        else:
            wr = r
        spectra = wr.to(self.cdtype)[:, :, None] * RC[None] * field_[:, None, :]
        y = torch.cat([spectra.real, spectra.imag], dim=-1) @ self._maps[tx]
        n = y.shape[-1] // 2
        return torch.complex(y[..., :n], y[..., n:])

    def image(self, weights, receive=None) -> torch.Tensor:
        """Compound image (B, Npix) on the planes' pixels, concatenated in :attr:`coords` order;
        ``receive`` (B, Ne): separate RX channel weights (``weights`` then the TX apodization;
        None: the same weights transmit and receive). ``weights`` (B, n_tx, Ne): a transmit
        apodization per transmit event (per-transmit apertures; ``receive`` required)."""
        w, r = self._apertures(weights, receive)
        if w.shape[1] == 1:
            w = w[:, 0]
        elements = None
        if not (w.requires_grad or r.requires_grad):
            support = (r != 0)
            if w.shape[0] > 1 and int(support.any(0).sum()) > 1.5 * int(support.sum(1).max()):
                # sparse selections with different supports: each one's own elements are fewer
                # reads than their union for all (a selection's zero weights receive nothing)
                return torch.cat([self.image(w[i:i + 1], None if receive is None else r[i:i + 1])
                                  for i in range(w.shape[0])])
            used = torch.nonzero(support.any(0)).flatten()
            if used.numel() == 0:
                raise SelectionError("every selection is empty (all weights zero)")
            if used.numel() < self.n_elements:
                elements = used  # an element of weight 0 everywhere receives nothing
        iqs = [self.iq(w, n, elements, None if receive is None else r) for n in range(len(self.transmits))]
        npix, ne = self._rx_pos.shape[0], (self.n_elements if elements is None else elements.numel())
        if self.device.type == "cpu" and npix * ne * len(iqs) >= COMPILED_MIN_ENTRIES:
            return self._image_compiled(iqs, elements)
        rx_pos = self._rx_pos if elements is None else self._rx_pos[:, elements]
        rx_rot = self._rx_rot if elements is None else self._rx_rot[:, elements]
        out = []
        for p0 in range(0, npix, self.pixel_chunk):
            sl = slice(p0, min(npix, p0 + self.pixel_chunk))
            acc = 0
            for n, t in enumerate(self.transmits):
                s0 = self._samples[n][0]
                pos = self._tx_pos[n][sl, None] + rx_pos[sl]
                valid = (pos >= 0) & (pos <= t.grid.n_time - 2)
                pos = torch.where(valid, pos - s0, torch.zeros_like(pos))
                i0 = torch.floor(pos)
                rot = self._tx_rot[n][sl, None] * rx_rot[sl] * valid.to(self.dtype)
                acc = acc + das_apply(iqs[n], i0.to(torch.long), (pos - i0).to(self.dtype), rot)
            out.append(acc)
        return torch.cat(out, dim=1) if len(out) > 1 else out[0]

    def _image_compiled(self, iqs, elements) -> torch.Tensor:
        T = max(int(q.shape[-1]) for q in iqs)
        # (n_tx, E, T, B): the batch innermost; padding samples are never read
        iq = torch.stack([torch.nn.functional.pad(q, (0, T - q.shape[-1])) for q in iqs]).permute(0, 2, 3, 1)
        if self._rx_pos_t is None:  # (E, P) copies, made on first use
            self._rx_pos_t = self._rx_pos.T.contiguous().numpy()
            self._rx_rot_t = self._rx_rot.T.contiguous().numpy()
        rows = np.arange(self.n_elements) if elements is None else elements.numpy()
        geo = (rows.astype(np.int64), self._tx_pos_np, self._rx_pos_t, self._tx_rot_np, self._rx_rot_t,
               np.array([s[0] for s in self._samples], dtype=np.int64),
               np.array([t.grid.n_time for t in self.transmits], dtype=np.int64))
        return _CompiledDAS.apply(iq.contiguous(), geo).T

    def planes(self, weights, receive=None) -> dict[str, torch.Tensor]:
        """The compound image on each plane: ``{name: complex (B, H, W)}`` (:attr:`coords` order
        and pixels), in units of ``image_scale``; differentiable in ``weights`` (and ``receive``:
        separate RX channel weights, :meth:`image`)."""
        return split_planes(self.image(weights, receive), self._shapes)
