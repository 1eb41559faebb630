"""The two-way broadband beam pattern of a planar array in direction cosines (u, v): a cheap,
differentiable stand-in for the point-spread functions of a steered sector.

A planar array with transmit weights ``a`` and receive weights ``b`` (elements at ``(x_e, y_e)``),
steered to the direction ``(u0, v0) = (sin theta_x, sin theta_y)`` at frequency ``f``
(``k = 2 pi f / c``), answers a far-field point in the direction ``(u, v)`` with

    P_f(du, dv) = T_f(du, dv) R_f(du, dv),   T_f = sum_e a_e exp(i k (x_e du + y_e dv)),  R_f likewise,

``du = u - u0``, ``dv = v - v0``: the pattern of a steered beam is the array factor shifted, so
**one** pattern over the shifts ``(du, dv)`` holds every beam of the sector. A beam steered to ``s``
sees the directions ``s + (du, dv)``; the shifts a designer cares about are those that some beam of
the sector sees inside the ``region``:

* ``"sector"`` (default): points and pixels inside the sector, as a scene that images points of
  the sector on regions covering it: ``|du| <= 2 sin theta_x,max``;
* ``"visible"``: anything in the visible half-space ``u^2 + v^2 <= 1``: the unit disk swept over
  the sector, ``|du| <= 1 + sin theta_x,max``. There the grating lobes of the probe's own
  lattice appear for every selection once ``lambda / pitch < 1 + sin theta`` (MATRIX-32x32:
  ``lambda / 0.3 mm`` is 1.28 at 4 MHz, so beyond about 16 degrees of steering at the top of
  the band): a level no selection changes.

**Pixel view and beam view.** The image of a point at ``s`` over pixels is ``E(s)^2 T R`` (``E``
the element's far-field factor): relative to its peak the element factor cancels, and the
pattern alone is the point's PSF (the default, ``element=None``). A beam steered to ``s`` answering
scatterers at ``s + d`` weights each by ``E(s + d)^2 / E(s)^2`` (``element=(width, height,
baffle)``; :func:`steering_weights`).

:attr:`BeamPattern.coverage` is the fraction of the sector's beams (steerings uniform in ``(u0,
v0)`` over ``[-sin theta_x,max, sin theta_x,max] x [-sin theta_y,max, sin theta_y,max]``) that
see each shift: 1 near the origin, falling to 0 at the region's edge. A sum over shifts weighted
by it is the mean over the sector's beams; a maximum over the shifts it covers is the worst beam.

**Broadband.** The pulse-echo spectrum ``S(f)`` (SIMUS's windowed-sine pulse times the squared
transducer response, :func:`pulse_echo_spectrum`) weights the frequencies:

* ``combine="energy"`` (default): ``I = sum_i w_i |P_{f_i}|^2``, the energy of the pulse-echo
  response over time in each direction (Parseval), at ``n_freq`` nodes ``f_i``, the midpoints of
  equal shares of ``|S|^2`` (the quantiles ``(i - 1/2) / n_freq``), ``w_i = 1 / n_freq``: a power
  pattern;
* ``combine="coherent"``: ``P = sum_i w_i P_{f_i}``, the complex envelope at the beam's own range
  (the value a delay-and-sum image holds there), at ``n_freq`` uniform midpoints of the band where
  ``|S| >= 1 %`` of its peak, ``w_i ~ S(f_i)``, ``sum w_i = 1``: an amplitude pattern. The side lobes
  far from the axis arrive late, so this needs many more frequencies than the energy.

``S`` is ``i`` times a real function for SIMUS's pulse, so both patterns are symmetric,
``|P(-du, -dv)| = |P(du, dv)|``: only the half ``dv >= 0`` is computed.

**Sampling.** The shifts are sampled on a grid of steps ``lambda_top / (2 D oversample)`` in each
direction (``lambda_top`` the wavelength of the highest node, ``D`` the array's extent along that
axis), the Nyquist step of the two-way pattern at that frequency, rounded so that the grid ends
on the region's edge, with ``(0, 0)`` on the centre sample.

**Two paths.** Elements on a rectangular lattice (every :class:`MatrixProbe`; imported layouts
with missing elements after :func:`lattice_of`) use the separable transform
``T_f = E_y(f) A E_x(f)^T`` of the weight grid ``A`` (ny, nx), in real arithmetic, with the
lattice's symmetry folded in (each cosine and sine matrix has half the columns); elements
anywhere on the plane use the explicit sum (about ``Ne / 16`` times slower on MATRIX-32x32).
The energy combination runs in compiled kernels on the CPU for batches of at least
:data:`~arraysel.physics.compiled.MIN_BATCH` (:mod:`arraysel.physics.beamkernels`).
"""
from __future__ import annotations

import math

import numpy as np
import torch

from arraysel.errors import ParameterError, SelectionError, check_choice, check_number
from arraysel.physics.beamgeometry import (COMBINE, REGIONS, band_nodes, direction_cosines, element_factor,
                                           grating_lobe_directions, grating_lobe_segments, lattice_of,
                                           lattice_periods, pulse_echo_spectrum, sector_sines, sphere_surface,
                                           steering_coverage, steering_weights)
from arraysel.physics.compiled import MIN_BATCH
from arraysel.physics.probes import Acquisition, MatrixProbe, PlanarProbe, check_sound_speed

__all__ = ["BeamPattern", "COMBINE", "REGIONS", "pulse_echo_spectrum", "band_nodes", "steering_coverage",
           "element_factor", "steering_weights", "grating_lobe_directions", "grating_lobe_segments",
           "lattice_periods", "lattice_of", "direction_cosines", "sphere_surface"]


class _EnergyCombine(torch.autograd.Function):
    """``sum_f w_f |T_f|^2 |R_f|^2`` (R = T when not given) of (F, V, X) real and imaginary parts,
    by the compiled kernels of :mod:`arraysel.physics.beamkernels` (CPU), forward and backward."""

    @staticmethod
    def forward(ctx, w, tre, tim, rre=None, rim=None):
        from arraysel.physics import beamkernels as K

        arrs = [v.detach().numpy() for v in (tre, tim) + (() if rre is None else (rre, rim))]
        out = np.empty(tre.shape[1:], dtype=arrs[0].dtype)
        wn = w.detach().numpy()
        K.energy_shared(*arrs, wn, out) if rre is None else K.energy_pair(*arrs, wn, out)
        ctx.save_for_backward(w, tre, tim, *(() if rre is None else (rre, rim)))
        return torch.from_numpy(out)

    @staticmethod
    def backward(ctx, g):
        from arraysel.physics import beamkernels as K

        w, *ts = ctx.saved_tensors
        arrs = [v.detach().numpy() for v in ts]
        grads = [np.empty(arrs[0].shape, dtype=arrs[0].dtype) for _ in arrs]
        gn = np.ascontiguousarray(g.detach().numpy())
        if len(arrs) == 2:
            K.energy_shared_grad(*arrs, w.detach().numpy(), gn, *grads)
            return None, torch.from_numpy(grads[0]), torch.from_numpy(grads[1]), None, None
        K.energy_pair_grad(*arrs, w.detach().numpy(), gn, *grads)
        return (None,) + tuple(torch.from_numpy(v) for v in grads)


def _check_element(element):
    if element is None:
        return None
    try:
        w, h, baffle = element
    except (TypeError, ValueError):
        raise ParameterError(f"element must be (width, height, baffle) or None, got {element!r}") from None
    w = check_number("element width", w, lo=0, lo_open=True)
    h = check_number("element height", h, lo=0, lo_open=True)
    if not (baffle in ("soft", "rigid") or (isinstance(baffle, (int, float)) and baffle > 0)):
        raise ParameterError(f"element baffle = {baffle!r}: use 'soft', 'rigid' or a positive number")
    return (w, h, baffle)


def _fold(x: torch.Tensor, dim: int) -> tuple[torch.Tensor, torch.Tensor]:
    """``(x[j] + x[n-1-j], x[j] - x[n-1-j])`` for ``j < ceil(n / 2)`` along ``dim`` (the middle of
    an odd axis counted twice in the first, zero in the second)."""
    h = (x.shape[dim] + 1) // 2
    a, b = x.narrow(dim, 0, h), x.flip(dim).narrow(dim, 0, h)
    return a + b, a - b


def _half_axis(n: int, pitch: float) -> tuple[np.ndarray, float]:
    """Positions of the first ceil(n/2) nodes of a centred axis and the weight of the middle one."""
    x = (np.arange((n + 1) // 2) - (n - 1) / 2) * (pitch if math.isfinite(pitch) else 0.0)
    return x, (0.5 if n % 2 else 1.0)


class BeamPattern:
    """The two-way broadband beam pattern of a planar array over the shifts of a steered sector.

    Parameters
    ----------
    positions : a :class:`MatrixProbe`, or element centres (Ne, 2 or 3) in metres on a plane
        z = const (any layout: on a rectangular lattice, possibly with empty nodes, they take the
        separable path, else the explicit sum)
    fc, bandwidth, tx_cycles : the pulse (Hz, % pulse-echo -6 dB bandwidth, cycles), as in SIMUS
    c : speed of sound (m/s)
    sector_deg : ``(theta_x, theta_y)``, the largest steering angles in degrees, each in [0, 89]
    region : ``"sector"`` or ``"visible"`` (the module docstring)
    n_freq : frequencies of the broadband combination, 1..512
    oversample : the grid's step is the two-way Nyquist step divided by this, in [0.25, 16]
    combine : ``"energy"`` (a power pattern) or ``"coherent"`` (a complex amplitude pattern)
    element : ``(width, height, baffle)`` of the rectangular elements (metres; baffle as in
        :class:`MatrixProbe`), whose two-way factor at ``fc`` weights each beam's view of the
        pattern (the beam view, :func:`steering_weights`); None (default): the pixel view
    n_steer : steerings an axis over which those weights are averaged
    step : the grid's steps ``(du, dv)`` (or one for both) before rounding to the region's edge;
        None: the two-way Nyquist steps divided by ``oversample`` (two patterns of the same
        region and steps share their grid)
    chunk : selections transformed at once (memory ~ chunk * n_freq * pixels)
    dtype, device : torch.float32 or torch.float64; any device

    :meth:`pattern` ``(tx, rx=None) -> (B, Hv, Hu)``; :attr:`coords` ``(Hv, Hu, 3)`` holds
    ``(du, dv, 0)`` of every sample, :attr:`coverage` ``(Hv, Hu)`` the share of the sector's beams
    that see it (0 outside the region), :attr:`mean_weight` and :attr:`peak_weight` the mean and
    the largest over the beams of what each sees relative to its own peak (with the element
    factor; without, the coverage and 1 inside the region).
    """

    def __init__(self, positions, *, fc: float, bandwidth: float, c: float = 1540.0, tx_cycles: float = 1.0,
                 sector_deg=(30.0, 30.0), region: str = "sector", n_freq: int = 8, oversample: float = 1.0,
                 combine: str = "energy", element=None, n_steer: int = 33, step=None, chunk: int = 16,
                 dtype=torch.float32, device="cpu"):
        if dtype not in (torch.float32, torch.float64):
            raise ParameterError(f"dtype = {dtype} is not allowed; choose torch.float32 or torch.float64")
        self.dtype, self.device = dtype, torch.device(device)
        self.combine = check_choice("combine", combine, COMBINE)
        self.region = check_choice("region", region, REGIONS)
        self.c = check_sound_speed(c)
        self.chunk = check_number("chunk", chunk, lo=1, hi=1 << 16, integer=True)
        oversample = check_number("oversample", oversample, lo=0.25, hi=16)
        self._layout(positions)
        f, w = band_nodes(fc, check_number("bandwidth", bandwidth, lo=0, lo_open=True, hi=200, hi_open=True),
                          n_freq, combine, check_number("tx_cycles", tx_cycles, lo=0, lo_open=True))
        #: the frequencies (Hz) and weights of the broadband combination, float64 (F,)
        self.frequencies, self.freq_weights = f, w
        self.wavelengths = self.c / f
        self.sines = sector_sines(sector_deg)
        if region == "sector" and min(self.sines) <= 0:
            raise ParameterError(f"sector_deg = {sector_deg!r}: region 'sector' needs both angles > 0")
        self.extent = tuple((1.0 + s) if region == "visible" else 2.0 * s for s in self.sines)
        self.du, self.dv = self._grid(float(self.wavelengths.min()), oversample, step)
        self.coverage = steering_coverage(self.du, self.dv, *self.sines, region).to(self.device)
        self.element = _check_element(element)
        ef = None
        if self.element is not None:
            lam_c = self.c / float(fc)
            ef = lambda u, v: element_factor(u, v, *self.element, lam_c)  # noqa: E731
        mean, top = steering_weights(self.du, self.dv, *self.sines, region, ef, n_steer)
        self.mean_weight, self.peak_weight = mean.to(self.device), top.to(self.device)
        V, U = torch.meshgrid(self.dv, self.du, indexing="ij")
        self.coords = torch.stack([U, V, torch.zeros_like(U)], dim=-1)
        k = 2 * math.pi * f / self.c
        self._w = w.to(self.device, dtype)
        self._gl_cache: dict = {}
        self._build_grid(k) if self.path == "grid" else self._build_direct(k)

    @classmethod
    def from_probe(cls, probe: MatrixProbe, acq: Acquisition | None = None, *, element_factor: bool = False,
                   **kw) -> "BeamPattern":
        """The pattern of a matrix probe: its fc and bandwidth, ``acq``'s c and tx_cycles, and with
        ``element_factor`` its elements' size and baffle (the beam view)."""
        if not isinstance(probe, (MatrixProbe, PlanarProbe)):
            raise ParameterError(f"probe must be a MatrixProbe or a PlanarProbe, got {type(probe).__name__}")
        if acq is not None:
            kw = {"c": acq.c, "tx_cycles": acq.tx_cycles, **kw}
        if element_factor:
            kw.setdefault("element", (probe.width, probe.height, probe.baffle))
        layout = probe if isinstance(probe, MatrixProbe) else probe.element_positions()
        return cls(layout, fc=probe.fc, bandwidth=probe.bandwidth, **kw)

    # ------------------------------------------------------------------ setup
    def _layout(self, positions) -> None:
        if isinstance(positions, MatrixProbe):
            p = positions.element_positions()
            lat = (positions.nx, positions.ny, positions.pitch_x, positions.pitch_y, (0.0, 0.0),
                   positions.cells)   # each element's node: blank rows and columns stay empty
        else:
            p = np.asarray(positions, dtype=np.float64)
            if p.ndim != 2 or p.shape[1] not in (2, 3) or p.shape[0] < 1 or not np.isfinite(p).all():
                raise ParameterError(f"positions must be finite element centres (Ne, 2 or 3) in metres, got "
                                     f"shape {p.shape}")
            if p.shape[1] == 3 and np.ptp(p[:, 2]) > 1e-9 * max(1e-3, np.ptp(p[:, :2])):
                raise ParameterError("positions: the elements must lie on one plane z = const")
            lat = lattice_of(p)
        self.n_elements = int(p.shape[0])
        self.positions = torch.as_tensor(p[:, :2].copy())
        self.aperture = tuple(float(np.ptp(p[:, i])) for i in (0, 1))
        self.path = "grid" if lat is not None else "direct"
        self.lattice = lat

    def _grid(self, lam_top: float, oversample: float, step) -> tuple[torch.Tensor, torch.Tensor]:
        if step is not None:
            steps = [step, step] if np.ndim(step) == 0 else list(step)
            if len(steps) != 2:
                raise ParameterError(f"step must be one number or (du, dv), got {step!r}")
            steps = [check_number("step", v, lo=1e-6, hi=2) for v in steps]
        else:
            steps = [lam_top / (2 * d * oversample) if d > 0 else None for d in self.aperture]
            if steps[0] is None and steps[1] is None:
                steps = [0.05 / oversample] * 2
            steps = [s if s is not None else steps[1 - i] for i, s in enumerate(steps)]
        axes = []
        for e, s in zip(self.extent, steps):
            m = max(1, int(math.ceil(e / s - 1e-9)))
            if 2 * m + 1 > 8193:
                raise ParameterError(f"the pattern would need {2 * m + 1} samples an axis (at most 8193): lower "
                                     "oversample or n_freq's top frequency, or narrow the sector")
            axes.append(torch.arange(-m, m + 1, dtype=torch.float64) * (e / m))
        return axes[0], axes[1]

    def _build_grid(self, k: torch.Tensor) -> None:
        nx, ny, px, py, centre, index = self.lattice
        opt = dict(device=self.device, dtype=self.dtype)
        mv = (self.dv.numel() - 1) // 2
        dvh = self.dv[mv:]
        xh, midx = _half_axis(nx, px)
        yh, midy = _half_axis(ny, py)
        phx = k[:, None, None] * torch.as_tensor(xh)[None, :, None] * self.du[None, None, :]   # (F, hx, Hu)
        cx, sx = torch.cos(phx), torch.sin(phx)
        cx[:, -1, :] *= midx
        self._csx = torch.stack([cx, sx], 1).to(**opt)                  # (F, 2, hx, Hu)
        self._scx = torch.stack([sx, cx], 1).to(**opt)
        phy = k[:, None, None] * dvh[None, :, None] * torch.as_tensor(yh)[None, None, :]        # (F, Hvh, hy)
        cy, sy = torch.cos(phy), torch.sin(phy)
        cy[..., -1] *= midy
        self._wre = torch.cat([cy, -sy], -1).to(**opt)
        self._wim = torch.cat([cy, sy], -1).to(**opt)
        self._index = None if np.array_equal(index, np.arange(nx * ny)) else torch.as_tensor(index, device=self.device)
        self._shift = None
        if self.combine == "coherent" and (centre[0] != 0 or centre[1] != 0):
            ph = k[:, None, None] * (centre[0] * self.du[None, None, :] + centre[1] * dvh[None, :, None])
            self._shift = (torch.cos(ph)[:, :, None].to(**opt), torch.sin(ph)[:, :, None].to(**opt))

    def _build_direct(self, k: torch.Tensor) -> None:
        opt = dict(device=self.device, dtype=self.dtype)
        mv = (self.dv.numel() - 1) // 2
        x, y = self.positions[:, 0], self.positions[:, 1]
        phx = k[:, None, None] * x[None, :, None] * self.du[None, None, :]              # (F, Ne, Hu)
        phy = k[:, None, None] * y[None, :, None] * self.dv[mv:][None, None, :]         # (F, Ne, Hvh)
        self._ex = (torch.cos(phx).to(**opt), torch.sin(phx).to(**opt))
        self._ey = (torch.cos(phy).to(**opt), torch.sin(phy).to(**opt))

    # ------------------------------------------------------------------ transforms
    def _transform_grid(self, a: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Re and Im of ``T_f`` on the half grid, (F, Hvh, b * Hu), of weights ``a`` (b, Ne).

        The weight grid is folded in y and x first (``A[j] +- A[n-1-j]``): the even-even and
        odd-odd parts meet the x cosines and sines, then ``[Cy, -Sy]`` gives Re T; the even-odd and
        odd-even parts meet the sines and cosines, then ``[Cy, Sy]`` gives Im T."""
        nx, ny = self.lattice[0], self.lattice[1]
        b = a.shape[0]
        if self._index is not None:
            a = a.new_zeros(b, nx * ny).index_copy(1, self._index, a)
        ye, yo = _fold(a.reshape(b, ny, nx).transpose(0, 1), 0)                # (hy, b, nx)
        ee, eo = _fold(ye, 2)
        oe, oo = _fold(yo, 2)                                                  # (hy, b, hx)
        hy, hx = ee.shape[0], ee.shape[2]
        F, Hu = self.frequencies.numel(), self.du.numel()
        p = torch.matmul(torch.stack([ee, oo]).reshape(1, 2, hy * b, hx), self._csx)   # (F, 2, hy b, Hu)
        q = torch.matmul(torch.stack([eo, oe]).reshape(1, 2, hy * b, hx), self._scx)
        re = torch.bmm(self._wre, p.reshape(F, 2 * hy, b * Hu))
        im = torch.bmm(self._wim, q.reshape(F, 2 * hy, b * Hu))
        if self._shift is not None:
            c, s = self._shift
            c, s = c.expand(-1, -1, b, -1).reshape(re.shape), s.expand(-1, -1, b, -1).reshape(re.shape)
            re, im = re * c - im * s, re * s + im * c
        return re, im

    def _transform_direct(self, a: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        (exr, exi), (eyr, eyi) = self._ex, self._ey
        yr = a[None, :, :, None] * eyr[:, None]                  # (F, b, Ne, Hvh)
        yi = a[None, :, :, None] * eyi[:, None]
        yr, yi = yr.transpose(-1, -2), yi.transpose(-1, -2)      # (F, b, Hvh, Ne)
        re = yr @ exr[:, None] - yi @ exi[:, None]               # (F, b, Hvh, Hu)
        im = yr @ exi[:, None] + yi @ exr[:, None]
        f, b, hv, hu = re.shape
        return (re.transpose(1, 2).reshape(f, hv, b * hu), im.transpose(1, 2).reshape(f, hv, b * hu))

    def _combine(self, t, r, b: int) -> torch.Tensor:
        """The half pattern (b, Hvh, Hu) of the transforms ``t`` and ``r`` (None: shared), each a
        pair of (F, Hvh, b * Hu) tensors."""
        tre, tim = t
        f, hv, x = tre.shape
        if self.combine == "energy":
            if self.device.type == "cpu" and b >= MIN_BATCH:
                out = _EnergyCombine.apply(self._w, tre, tim, *(() if r is None else r))
            else:
                pt = torch.addcmul(tre * tre, tim, tim)
                prod = pt * pt if r is None else pt * torch.addcmul(r[0] * r[0], r[1], r[1])
                out = (self._w[None] @ prod.reshape(f, -1)).reshape(hv, x)
            return out.reshape(hv, b, -1).permute(1, 0, 2)
        rre, rim = t if r is None else r
        pre = torch.addcmul(tre * rre, tim, rim, value=-1.0)
        pim = torch.addcmul(tre * rim, tim, rre)
        pre = (self._w[None] @ pre.reshape(f, -1)).reshape(hv, b, -1).permute(1, 0, 2)
        pim = (self._w[None] @ pim.reshape(f, -1)).reshape(hv, b, -1).permute(1, 0, 2)
        return torch.complex(pre, pim)

    # ------------------------------------------------------------------ the pattern
    def _weights(self, w, name: str) -> torch.Tensor:
        t = w if isinstance(w, torch.Tensor) else torch.as_tensor(np.asarray(w, dtype=np.float64))
        if t.dim() == 1:
            t = t[None]
        if t.dim() != 2 or t.shape[-1] != self.n_elements:
            raise SelectionError(f"{name} must have shape (B, {self.n_elements}), got {tuple(t.shape)}")
        if t.is_complex() or not bool(torch.isfinite(t.detach()).all()):
            raise SelectionError(f"{name} must be real and finite")
        return t.to(device=self.device, dtype=self.dtype)

    def pattern(self, tx, rx=None) -> torch.Tensor:
        """The pattern (B, Hv, Hu) of transmit weights ``tx`` (B, Ne) and receive weights ``rx``
        (same shape; None: ``rx = tx``) on the grid of :attr:`coords`: real power
        (``"energy"``) or complex amplitude (``"coherent"``), in units of the weights' sums (a
        single element of weight 1 gives 1 everywhere). Differentiable in both weights."""
        a = self._weights(tx, "tx")
        b = None if rx is None else self._weights(rx, "rx")
        if b is not None and b.shape != a.shape:
            raise SelectionError(f"rx has shape {tuple(b.shape)}; it must match tx's {tuple(a.shape)}")
        transform = self._transform_grid if self.path == "grid" else self._transform_direct
        out = []
        for i in range(0, a.shape[0], self.chunk):
            n = min(self.chunk, a.shape[0] - i)
            if b is None:
                out.append(self._combine(transform(a[i:i + n]), None, n))
            else:                                   # one transform of both
                re, im = transform(torch.cat([a[i:i + n], b[i:i + n]]))
                h = re.shape[-1] // 2
                out.append(self._combine((re[..., :h], im[..., :h]), (re[..., h:], im[..., h:]), n))
        half = torch.cat(out) if len(out) > 1 else out[0]
        low = half[:, 1:].flip(1, 2)
        return torch.cat([low.conj() if low.is_complex() else low, half], dim=1)

    def grating_directions(self, tx, rx=None) -> list[torch.Tensor]:
        """For each selection, the segments (G, 2, 2) (float64, :func:`grating_lobe_segments`)
        along which the lattice of its transmit elements, and that of its receive elements
        (:func:`lattice_periods`), put grating lobes over the band of the nodes' wavelengths,
        within the pattern's grid. Needs a lattice layout (else every entry is empty). Selections
        of the same lattices get the same tensor object, on every call."""
        a = self._weights(tx, "tx")
        if self.path != "grid":
            return [torch.zeros(0, 2, 2, dtype=torch.float64) for _ in range(a.shape[0])]
        nx, ny, px, py, _, index = self.lattice
        index = torch.as_tensor(index)

        def nodes(w):
            return w.detach().cpu().new_zeros(w.shape[0], nx * ny).index_copy(1, index, w.detach().cpu())

        lat = [lattice_periods(nodes(a), nx, ny)]
        if rx is not None:
            lat.append(lattice_periods(nodes(self._weights(rx, "rx")), nx, ny))
        band = (float(self.wavelengths.min()), float(self.wavelengths.max()))
        bounds = (-self.extent[0], self.extent[0], -self.extent[1], self.extent[1])
        cache = self._gl_cache
        out = []
        for i in range(a.shape[0]):
            key = tuple(sorted({tuple(int(v) for v in L[i]) for L in lat}))
            if key not in cache:
                parts = [grating_lobe_segments(mx * px if mx else math.inf, my * py if my else math.inf, band,
                                               bounds=bounds) for mx, my in key if mx or my]
                cache[key] = torch.cat(parts) if parts else torch.zeros(0, 2, 2, dtype=torch.float64)
            out.append(cache[key])
        return out
