"""The fast 3-D point-spread function: transmit and receive factored in time, per pixel.

For one point scatterer, transmit ``n`` and receive element ``e``, the exact path
(:class:`~arraysel.physics.volume.psf.MatrixPSF`) beamforms the echo

    S_ne(f) = w_e RC_e(f) T_n(f),       T_n(f) = sum_j w_j G_nj(f)

(``T_n`` the field at the scatterer, linear in the selection ``w``; ``RC_e`` the element's
receive factor). Its I/Q signal is, to the accuracy checked below, ``conj(S)`` times the
demodulator's response ``L_n(f)`` at the sample's absolute index ``m``, as the tone
``exp(i beta_f m)``, ``beta_f = 2 pi (f - fc) / fs``; delay-and-sum reads it by linear
interpolation at ``x = xi_n(p) + eta_e(p)`` samples (transmit and receive distances times fs / c)
and rotates it by ``exp(2i pi fc x / fs)``. Linear interpolation of a tone is the tone times a
1-periodic function of ``x``, ``sum_q h_q(beta) exp(2i pi q x)`` (:func:`interpolation_harmonics`),
so the image of pixel ``p`` is

    img(p) = sum_n sum_e w_e sum_f sum_q conj(T_n RC_e) L_n h_q exp(i (kappa_f + 2 pi q) x_npe),

``kappa_f = 2 pi f / fs``. Three structures make it cheap for many selections:

* **transmit subspace**: ``conj(T_n)`` lies in the span of the rows of ``conj(G_n)``; a weighted
  SVD keeps ``r_n`` of them (``conj T_n ~ sum_g c_ng(w) Phi_ng(f)``, ``c_n = w @ C_n``);
* **receive delays per pixel**: ``conj(RC_e(f)) = A_e(f) exp(-i kappa_f eta_e(s))`` with ``A_e``
  smooth in f (a polynomial in f times a shared spectrum, :func:`_receive_amplitudes`), and
  ``delta_e(p) = eta_e(p) - eta_e(s)`` spans a short interval for each pixel, on which
  ``exp(i (kappa_f - kappa_c) delta)`` is interpolated at Chebyshev nodes ``delta_pm``; each pixel
  gets the fewest nodes its interval needs (near the scatterer the receive delays hardly differ from
  the scatterer's, so few), and pixels are grouped by that count (:attr:`MatrixFastPSF.sizes`
  ``pixels_by_nodes``);
* what is left per pixel is a receive sum ``gamma_pqmk(w) = sum_e w_e B_e,pqmk`` (one matrix
  product for a batch of selections) and a transmit sum ``sum_ng c_ng(w) Psi_ng,pqmk``.

So ``img(p) = sum_{q,m,k} gamma_pqmk(w) sum_{n,g} c_ng(w) Psi_ng,pqmk``: bilinear in ``w`` like the
exact image, differentiable, and the cost of a selection does not grow with the number of
transmits' frequencies or with the receive sum's length in time.

The build checks the two assumptions it rests on (the I/Q map's tone form on the samples the
planes read, and every read sample inside the record) and measures the truncations; then it
compares the fast planes with the exact path on check selections (full array, random subsets)
and records the worst relative error in :attr:`MatrixFastPSF.check` -- the certificate the
objective reads before it trusts the fast path (``docs/matrix.md``).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from arraysel.errors import ParameterError, SelectionError, check_number
from arraysel.physics.volume.nodes import chebyshev_nodes, interpolation_harmonics, lagrange, node_reach
from arraysel.physics.volume.psf import (MatrixPSF, check_element_weights, check_surfaces, plane_axes, split_planes,
                                         transmit_event_weights)
from arraysel.physics.volume.stored import STORAGES, ColumnSink, stored_product

__all__ = ["FastPathUnavailable", "FastSettings", "MatrixFastPSF", "STORAGES", "interpolation_harmonics",
           "fast_relative_error", "stored_product"]


class FastPathUnavailable(RuntimeError):
    """The fast path cannot represent this scene (the reason says why); use the exact path."""


def _transmit_rows(ranks, r_max: int):
    """The rows of the flattened (transmit, g) coefficients that the unpadded transmit tensor keeps
    (g < r_n of each transmit ``n``); None when no transmit is padded."""
    if all(r == r_max for r in ranks):
        return None
    return torch.cat([n * r_max + torch.arange(r) for n, r in enumerate(ranks)])


def fast_relative_error(fast: dict, exact: dict) -> torch.Tensor:
    """Per selection, the largest over planes of ``||fast - exact||^2 / ||exact||^2`` (B,)."""
    errs = [((fast[k] - exact[k]).abs() ** 2).flatten(1).sum(1) / (exact[k].abs() ** 2).flatten(1).sum(1)
            for k in exact]
    return torch.stack(errs).amax(0)


@dataclass(frozen=True)
class FastSettings:
    """Truncation tolerances of :class:`MatrixFastPSF` (relative, on the weighted spectra).

    tol: singular values / fit residuals / interpolation errors kept below this fraction;
    replicas: interpolation harmonics ``q = -replicas .. replicas`` kept (0: the ideal delay only);
    max_nodes: the most Chebyshev nodes a pixel may need (a larger need: the fast path is refused);
    check_tol: the largest relative plane error (squared norm ratio) accepted on the check
    selections; above it the fast path is refused (the objective uses the exact path).
    storage: ``"float32"`` keeps the receive matrix and the transmit tensor in single (or the
    evaluation's) precision; ``"float16"`` rounds them, each column scaled to a largest magnitude of
    1, to float16 (11 significant bits) at the build, before the check, so the check measures the
    model as stored: half the memory and cache; the products are still formed in the evaluation's
    precision, a block of columns at a time (:mod:`arraysel.physics.volume.stored`).
    """

    tol: float = 1e-5
    replicas: int = 0
    max_nodes: int = 48
    check_tol: float = 1e-4
    storage: str = "float32"

    def __post_init__(self):
        check_number("tol", self.tol, lo=0, lo_open=True, hi=1e-1)
        check_number("replicas", self.replicas, lo=0, hi=8, integer=True)
        check_number("max_nodes", self.max_nodes, lo=2, hi=512, integer=True)
        check_number("check_tol", self.check_tol, lo=0, lo_open=True, hi=1.0)
        if self.storage not in STORAGES:
            raise ParameterError(f"storage = {self.storage!r} is not allowed; choose one of {', '.join(STORAGES)}")


def _tone_response(t, s0: int, s1: int, fc: float, fs: float, tol: float) -> torch.Tensor:
    """``L_n(f)`` (F,) complex128 with ``iq[m] = sum_f conj(S_f) L_f exp(i beta_f m)`` on the
    samples ``[s0, s1)``; raises FastPathUnavailable when the map departs from that form by more
    than ``tol`` (relative, each tone weighted by the size of the echo's spectrum there)."""
    M = t.iq_map(slice(s0, s1)).to(torch.float64)
    F = M.shape[0] // 2
    T = M.shape[1] // 2
    re = torch.complex(M[:F, :T], M[:F, T:])
    im = torch.complex(M[F:, :T], M[F:, T:])
    anti = (re + 1j * im) / 2   # the part acting on conj(S)
    lin = (re - 1j * im) / 2    # the part acting on S (the demodulator's image, ~0)
    f = t.grid.f.to(torch.float64)
    beta = 2 * math.pi * (f - fc) / fs
    m = torch.arange(s0, s1, dtype=torch.float64)
    tone = torch.polar(torch.ones(F, T, dtype=torch.float64), beta[:, None] * m[None])
    L = (anti * tone.conj()).mean(1)
    wf = (t.rx_factor.abs().amax(0) * t.tx_field.abs().amax(0)).to(torch.float64)[:, None]
    resid = ((anti - L[:, None] * tone) * wf).norm() + (lin * wf).norm()
    size = (anti * wf).norm()
    if not bool(size > 0) or float(resid / size) > tol:
        raise FastPathUnavailable(f"the I/Q map is not a tone response on the samples read (relative "
                                  f"departure {float(resid / size):.2e} > {tol:.1e})")
    return L


def _receive_amplitudes(A: list[torch.Tensor], f: list[torch.Tensor], fc: float, weights: list[torch.Tensor],
                        tol: float, max_k: int = 8):
    """Fit ``A_e(f) = shape_n(f) sum_k a_ek ((f - fc) / fc)^k`` for every transmit's grid.

    A: per transmit (Ne, F_n) complex; weights: per transmit (F_n,) relevance. The shared shape is
    the element mean of A. Returns ``(a (Ne, K), basis list of (K, F_n))`` with the weighted
    residual <= tol, or raises FastPathUnavailable."""
    shapes = [a.mean(0) for a in A]
    for K in range(1, max_k + 1):
        rows, rhs = [], []
        for a, s, fr, w in zip(A, shapes, f, weights):
            nu = (fr - fc) / fc
            basis = torch.stack([s * nu ** k for k in range(K)])  # (K, F)
            rows.append((basis * w[None]).T)                      # (F, K)
            rhs.append((a * w[None]).T)                           # (F, Ne)
        Bm, R = torch.cat(rows), torch.cat(rhs)
        coef = torch.linalg.lstsq(Bm, R).solution                 # (K, Ne)
        resid = float((Bm @ coef - R).norm() / R.norm())
        if resid <= tol:
            bases = [torch.stack([s * ((fr - fc) / fc) ** k for k in range(K)]) for s, fr in zip(shapes, f)]
            return coef.T.contiguous(), bases
    raise FastPathUnavailable(f"the elements' receive responses are not smooth in frequency to {tol:.1e} "
                              f"with {max_k} terms (residual {resid:.2e})")


def _transmit_responses(ex: MatrixPSF, rx_pos: torch.Tensor, eta_s: torch.Tensor, fc: float, fs: float,
                        check_tol: float):
    """Per transmit of ``ex``: the demodulator's tone response ``L_n`` (F,), the frequency grid
    ``f``, the receive amplitudes ``A_n`` (Ne, F) (``conj(RC)`` with the scatterer's receive delay
    taken out), the relevance of each frequency (normalised to the largest over the transmits) and
    the transmit delays ``xi_n`` (P,) in samples. Raises :class:`FastPathUnavailable` when a pixel
    reads a sample outside the RF record."""
    L, fgrid, A, relevance, tx_pos = [], [], [], [], []
    for n, t in enumerate(ex.transmits):
        s0, s1 = ex._samples[n]
        xi = ex._tx_pos[n].to("cpu", torch.float64)                    # (P,)
        x = xi[:, None] + rx_pos
        if float(x.min()) < 0 or float(x.max()) > t.grid.n_time - 2:
            raise FastPathUnavailable(
                f"transmit {n}: some pixel reads a sample outside the RF record (samples {float(x.min()):.1f} "
                f"to {float(x.max()):.1f} read, record [0, {t.grid.n_time - 2}]); the exact path skips "
                "those reads, the fast path cannot: shrink the planes or use the exact path")
        Ln = _tone_response(t, s0, s1, fc, fs, 0.1 * math.sqrt(check_tol))
        f = t.grid.f.to(torch.float64)
        kf = 2 * math.pi * f / fs
        RC = t.rx_factor.to(torch.complex128)                            # (Ne, F)
        An = RC.conj() * torch.polar(torch.ones_like(eta_s[:, None] * kf), eta_s[:, None] * kf[None])
        L.append(Ln)
        fgrid.append(f)
        A.append(An)
        relevance.append(Ln.abs() * RC.abs().amax(0) * t.tx_field.abs().amax(0).to(torch.float64))
        tx_pos.append(xi)
    rel_max = max(float(r.max()) for r in relevance)
    return L, fgrid, A, [r / rel_max for r in relevance], tx_pos


def _transmit_subspaces(ex: MatrixPSF, L: list[torch.Tensor], tol: float):
    """Per transmit: ``C_n`` (Ne, r_n) and ``Phi_n`` (r_n, F), the weighted SVD of ``conj(G_n)``
    truncated at ``tol`` (``conj T_n ~ (w @ C_n) Phi_n``)."""
    C_list, Phi = [], []
    for n, t in enumerate(ex.transmits):
        G = t.tx_field.to(torch.complex128).conj()                       # (Ne, F)
        D = L[n].abs() * t.rx_factor.abs().amax(0).to(torch.float64)
        D = D / D.max()
        U, S, Vh = torch.linalg.svd(G * D[None], full_matrices=False)
        r = int((S > tol * S[0]).sum())
        safe = torch.where(D > 0, D, torch.ones_like(D))
        C_list.append(U[:, :r] * S[:r])                                  # (Ne, r)
        Phi.append(torch.where(D[None] > 0, Vh[:r] / safe[None], torch.zeros_like(Vh[:r])))  # (r, F)
    return C_list, Phi


def _node_groups(delta: torch.Tensor, fgrid, relevance, fs: float, kc: float, st: FastSettings, width: int):
    """Chebyshev nodes per pixel on ``[min_e delta, max_e delta]``: a pixel whose receive delays
    span a phase half-width ``a_p`` needs the fewest nodes that interpolate ``exp(i a_p t)`` on
    [-1, 1] to tol; pixels are grouped by that count (pixels near the scatterer need few).
    ``width``: columns per pixel and node (harmonics times amplitude terms). Returns the pixels'
    interval midpoints and half-widths (P,), the groups ``(nodes, pixels, column offset)`` and
    the number of columns."""
    tol = st.tol
    lo, hi = delta.amin(1), delta.amax(1)
    mid, half = (lo + hi) / 2, (hi - lo) / 2
    band = torch.cat([(2 * math.pi * f / fs - kc)[r > tol] for f, r in zip(fgrid, relevance)]).abs().max()
    a_pix = band * half                                                  # (P,) phase half-spans
    need = torch.full_like(a_pix, -1, dtype=torch.long)
    for n_nodes in range(4, st.max_nodes + 1, 2):
        left = need < 0
        if not bool(left.any()):
            break
        reach = node_reach(n_nodes, tol, float(a_pix[left].max()))
        need[left & (a_pix <= reach)] = n_nodes
    if bool((need < 0).any()):
        raise FastPathUnavailable(f"the receive delays of a pixel span too long a time for "
                                  f"{st.max_nodes} interpolation nodes (phase span {2 * float(a_pix.max()):.1f} rad)")
    groups = []                                                          # (nodes, pixels, column offset)
    off = 0
    for n_nodes in sorted(set(need.tolist())):
        idx = torch.nonzero(need == n_nodes).flatten()
        groups.append((n_nodes, idx, off))
        off += idx.numel() * n_nodes * width
    return mid, half, groups, off


def _receive_matrix(delta, rx_pos, mid, half, groups, a_ek, kc: float, orders, chunk: int, sink: ColumnSink):
    """The receive matrix ``B`` (Ne, columns) into ``sink``, each group's columns ordered (pixel, q,
    node, k), a block of ``chunk`` pixels at a time."""
    n_elements, K, Q = delta.shape[1], a_ek.shape[1], len(orders)
    for n_nodes, idx, off in groups:
        nodes = chebyshev_nodes(n_nodes)
        width = Q * n_nodes * K
        for p0 in range(0, idx.numel(), chunk):
            ii = idx[p0:p0 + chunk]
            dl = delta[ii]                                               # (p, Ne)
            hh = half[ii, None]
            tnorm = torch.where(hh > 0, (dl - mid[ii, None]) / torch.where(hh > 0, hh, torch.ones_like(hh)),
                                torch.zeros_like(dl))
            ell = lagrange(nodes.expand(dl.shape[0], n_nodes), tnorm)  # (p, Ne, S)
            ph = torch.polar(torch.ones_like(dl), kc * dl)               # (p, Ne)
            reps = torch.stack([torch.polar(torch.ones_like(dl), 2 * math.pi * q * rx_pos[ii]) for q in orders], 1)
            blk = ph[:, None, :, None] * reps[..., None] * ell[:, None].to(ph.dtype)  # (p, Q, Ne, S)
            blk = blk[..., None] * a_ek[None, None, :, None, :]           # (p, Q, Ne, S, K)
            sink.put(off + p0 * width, blk.permute(2, 0, 1, 3, 4).reshape(n_elements, -1))


def _transmit_weights(fgrid, Phi, L, rx_basis, fs: float, fc: float, tol: float, orders) -> list:
    """Per transmit ``(W, kf)``: the weights (r_n, Q, K, F') of its transmit sums over the
    frequencies F' where the echo has weight, and those frequencies' phase steps a sample."""
    out = []
    for n in range(len(fgrid)):
        f = fgrid[n]
        kf = 2 * math.pi * f / fs
        h = interpolation_harmonics(2 * math.pi * (f - fc) / fs, orders)  # (Q, F)
        W = (Phi[n] * L[n][None])[:, None, None, :] * h[None, :, None, :] * rx_basis[n][None, None]  # (r, Q, K, F)
        # frequencies where the echo has no weight add nothing (a thousandth of ``tol``): leave them out
        mag = W.abs().amax((0, 1, 2))
        keep = mag > 1e-3 * tol * mag.max()
        out.append((W[..., keep], kf[keep]))
    return out


def _transmit_tensor(weights, tx_pos, ranks, mid, half, groups, kc: float, orders, chunk: int, sink: ColumnSink):
    """The transmit tensor ``Psi`` (sum of the ranks, columns) into ``sink``: the rows g < r_n of
    each transmit ``n`` (``weights`` from :func:`_transmit_weights`), in the receive matrix's
    column order, a block of ``chunk`` pixels (all transmits) at a time."""
    Q, K = len(orders), weights[0][0].shape[2]
    first = [0]
    for r in ranks:
        first.append(first[-1] + r)
    for n_nodes, idx, off in groups:
        nodes = chebyshev_nodes(n_nodes)
        width = Q * n_nodes * K
        for p0 in range(0, idx.numel(), chunk):
            ii = idx[p0:p0 + chunk]
            dnode = mid[ii, None] + half[ii, None] * nodes[None]         # (p, S) delta_pm
            blk = torch.empty(first[-1], ii.numel() * width, dtype=sink.cdtype)
            for n, (W, kf) in enumerate(weights):
                xi = tx_pos[n]
                zeta = xi[ii, None] + dnode                              # (p, S)
                E = torch.polar(torch.ones_like(zeta[..., None] * kf), zeta[..., None] * kf)  # (p, S, F)
                pre = torch.stack([torch.polar(torch.ones_like(zeta), 2 * math.pi * q * xi[ii, None]
                                               - kc * dnode) for q in orders], 1)  # (p, Q, S)
                # sum_f W[g,q,k,f] E[p,s,f]  -> (g, p, q, s, k)
                v = torch.einsum("gqkf,psf->gpqsk", W, E) * pre[None, :, :, :, None]
                blk[first[n]:first[n + 1]] = v.reshape(ranks[n], -1).to(sink.cdtype)
            sink.put(off + p0 * width, blk)


class MatrixFastPSF:
    """The fast path of :class:`~arraysel.physics.volume.psf.MatrixPSF` (module docstring).

    Parameters: ``exact`` the exact model (any dtype: the build runs in float64 from its setup);
    ``settings`` (:class:`FastSettings`); ``dtype`` of the evaluation; ``check_masks`` (C, Ne)
    selections the build compares with the exact path (default: the full array and two random
    subsets of a quarter of the elements, seed 0).

    Raises :class:`FastPathUnavailable` when the scene breaks an assumption or the check fails.
    :attr:`check` records the measured errors; :attr:`sizes` the truncation ranks
    (``transmit_ranks``, ``nodes`` the most a pixel uses, ``pixels_by_nodes``, ``harmonics``,
    ``amplitude_terms``), ``pixels`` and the ``bytes`` of the evaluation tensors.
    """

    def __init__(self, exact: MatrixPSF, settings: FastSettings | None = None, dtype=torch.float32,
                 check_masks=None, pixel_chunk: int = 256):
        if dtype not in (torch.float32, torch.float64):
            raise ParameterError(f"dtype = {dtype} is not allowed; choose torch.float32 or torch.float64")
        if settings is not None and not isinstance(settings, FastSettings):
            raise ParameterError(f"settings must be a FastSettings, got {type(settings).__name__}")
        self.settings = settings or FastSettings()
        self.exact = exact
        self.setup = exact.setup
        self.coords = exact.coords
        self._shapes = dict(exact._shapes)
        chunk = check_number("pixel_chunk", pixel_chunk, lo=1, hi=1 << 20, integer=True)
        self.n_elements = exact.n_elements
        self.image_scale = exact.image_scale
        self.dtype = dtype
        self.cdtype = torch.complex64 if dtype == torch.float32 else torch.complex128
        self.device = exact.device
        self._build(int(chunk))
        self.check = self._check(check_masks)

    # ---------------------------------------------------------------- build
    def _build(self, chunk: int):
        s, st = self.setup, self.settings
        probe, acq = s.probe, s.acq
        fs, c, fc = acq.fs, acq.c, probe.fc
        ex = self.exact
        rx_pos = ex._rx_pos.to("cpu", torch.float64)                       # (P, Ne) eta_e(p), samples
        pos = torch.as_tensor(probe.element_positions(), dtype=torch.float64)
        sc = torch.tensor(s.scatterer, dtype=torch.float64)
        eta_s = (pos - sc).norm(dim=1) * (fs / c)                          # (Ne,) eta_e(s)
        delta = rx_pos - eta_s[None]                                       # (P, Ne)
        kc = 2 * math.pi * fc / fs
        orders = list(range(-st.replicas, st.replicas + 1))
        n_tx = len(ex.transmits)

        L, fgrid, A, relevance, tx_pos = _transmit_responses(ex, rx_pos, eta_s, fc, fs, st.check_tol)
        a_ek, rx_basis = _receive_amplitudes(A, fgrid, fc, relevance, st.tol)
        K = a_ek.shape[1]
        C_list, Phi = _transmit_subspaces(ex, L, st.tol)
        ranks = [int(cn.shape[1]) for cn in C_list]
        Q = len(orders)
        P = rx_pos.shape[0]
        mid, half, groups, n_cols = _node_groups(delta, fgrid, relevance, fs, kc, st, Q * K)
        # built a block of pixels at a time straight into their storage (float16: rounded block by block,
        # before the check, which then measures the model as stored)
        sink = ColumnSink(self.n_elements, n_cols, st.storage, self.cdtype, real=True)
        _receive_matrix(delta, rx_pos, mid, half, groups, a_ek, kc, orders, chunk, sink)
        self._B, self._B_scale = sink.result()
        del sink
        r_max = max(ranks)
        sink = ColumnSink(sum(ranks), n_cols, st.storage, self.cdtype, real=False)
        _transmit_tensor(_transmit_weights(fgrid, Phi, L, rx_basis, fs, fc, st.tol, orders), tx_pos, ranks, mid,
                         half, groups, kc, orders, chunk, sink)
        self._Psi, self._Psi_scale = sink.result()
        del sink
        order = torch.cat([idx for _, idx, _ in groups])
        #: (pixels in the groups' order, nodes a pixel, column offset) per group, and the inverse order
        self._groups = [(idx.numel(), Q * n_nodes * K, off) for n_nodes, idx, off in groups]
        self._unsort = torch.argsort(order)
        self._C = torch.zeros(n_tx, self.n_elements, r_max, dtype=self.cdtype)
        for n, cn in enumerate(C_list):
            self._C[n, :, :ranks[n]] = cn.to(self.cdtype)
        self._rows = _transmit_rows(ranks, r_max)
        self.sizes = {"transmit_ranks": ranks, "nodes": max(g[0] for g in groups),
                      "pixels_by_nodes": {g[0]: int(g[1].numel()) for g in groups}, "harmonics": Q, "amplitude_terms": K,
                      "pixels": P, "bytes": self._bytes()}
        if self.device.type != "cpu":
            self._to_device()

    def _to_device(self) -> None:
        for name in ("_B", "_Psi", "_C", "_unsort", "_rows", "_B_scale", "_Psi_scale"):
            t = getattr(self, name)
            if t is not None:
                setattr(self, name, t.to(self.device))

    def element_coefficients(self) -> torch.Tensor:
        """Each element's transmit coefficients (Ne, rows of the transmit tensor): the rows of
        ``C_n`` side by side, as :meth:`transmit_coefficients` of the unit selections."""
        c = self._C.permute(1, 0, 2).reshape(self.n_elements, -1)
        return c if self._rows is None else c.index_select(1, self._rows)

    def _bytes(self) -> int:
        return int(sum(t.numel() * t.element_size() for t in (self._B, self._Psi, self._C, self._B_scale,
                                                                self._Psi_scale) if t is not None))

    @property
    def storage(self) -> str:
        """The precision the receive matrix and the transmit tensor are held in (:data:`STORAGES`)."""
        return "float16" if self._B.dtype == torch.float16 else "float32"

    def receive_matrix(self, elements: torch.Tensor | None = None) -> torch.Tensor:
        """The receive matrix ``B`` (Ne, 2 columns; re, im interleaved), or its rows ``elements``, in
        the evaluation's precision (no copy when it is stored so)."""
        B = self._B if elements is None else self._B[elements]
        if self._B_scale is None:
            return B
        return B.to(self.dtype) * self._B_scale.to(self.dtype)

    # ---------------------------------------------------------------- evaluate
    def _receive_sums(self, r: torch.Tensor, base) -> torch.Tensor:
        """``r @ B`` (B, 2 columns); with ``base`` (Ne,) weights that each row of ``r`` differs from in
        a few elements (the moves of a local search), the base's sums (the latest base's kept) plus
        the rows of ``B`` of the elements that differ: a swap costs two rows of ``B``, not ``Ne``."""
        if base is None:
            return stored_product(r, self._B, self._B_scale)
        b = check_element_weights(base, self.n_elements, self.dtype, self.device)
        d = r - b
        rows, cols = d.nonzero(as_tuple=True)
        if rows.numel() > r.shape[0] * self.n_elements // 8:   # not a few moves: the full product
            return stored_product(r, self._B, self._B_scale)
        key = b.detach().cpu().numpy().tobytes()
        if getattr(self, "_base_sums", (None,))[0] != key:   # the latest base's sums, kept: a search asks again
            self._base_sums = (key, stored_product(b.detach()[None], self._B, self._B_scale)[0])
        out = self._base_sums[1].expand(r.shape[0], -1).clone()
        return out.index_add_(0, rows, d[rows, cols, None] * self.receive_matrix(cols))

    def transmit_coefficients(self, weights: torch.Tensor) -> torch.Tensor:
        """``c`` (B, rows of the transmit tensor): each transmit's field coefficients ``w @ C_n``,
        the rows g < r_n of each; ``weights`` (B, Ne) one apodization for every transmit, or
        (B, n_tx, Ne) one per transmit event."""
        w = weights.to(self.cdtype)
        if w.dim() == 2:
            c = torch.einsum("be,ner->bnr", w, self._C)
        else:
            c = torch.einsum("bne,ner->bnr", w, self._C)
        c = c.reshape(w.shape[0], -1)
        return c if self._rows is None else c.index_select(1, self._rows)

    def transmit_sums(self, c: torch.Tensor) -> torch.Tensor:
        """``z = c @ Psi`` (B, columns) complex from :meth:`transmit_coefficients`' ``c``."""
        return stored_product(c, self._Psi, self._Psi_scale)

    def image(self, weights, receive=None, base=None) -> torch.Tensor:
        """Compound image (B, Npix) on the planes' pixels (as :meth:`MatrixPSF.image`); with
        ``receive`` (B, Ne) separate receive weights (``weights`` the transmit apodization): the
        receive sum ``gamma`` of ``receive``, the transmit sum ``c`` of ``weights`` (bilinear).
        ``weights`` (B, n_tx, Ne): one transmit apodization per transmit event (``receive``
        required), each event's coefficients ``c_n`` from its own. ``base`` (Ne,): weights that each
        row of the receive weights differs from in a few elements (a local search's selection; its
        moves' receive sums are then formed from it, the same sums)."""
        n_tx = self._C.shape[0]
        w = transmit_event_weights(weights, n_tx, self.n_elements, self.dtype, self.device)
        if w.shape[1] > 1 and receive is None:
            raise SelectionError("per-transmit weights (B, n_tx, Ne) need the receive weights (receive=)")
        r = w[:, 0] if receive is None else check_element_weights(receive, self.n_elements, self.dtype, self.device)
        if r.shape != w[:, 0].shape:
            raise SelectionError(f"receive weights must have the transmit weights' shape {tuple(w[:, 0].shape)}, "
                                 f"got {tuple(r.shape)}")
        Bn = w.shape[0]
        gamma = torch.view_as_complex(self._receive_sums(r, base).reshape(Bn, -1, 2))   # (B, columns)
        # one transmit apodization for all transmits, or one per transmit event: each event's own
        z = self.transmit_sums(self.transmit_coefficients(w[:, 0] if w.shape[1] == 1 else w))  # (B, columns)
        prod = gamma * z
        # split, not slices: a slice's backward fills a full-size zero tensor per group
        parts = torch.split(prod, [n * width for n, width, _ in self._groups], dim=1)
        img = torch.cat([part.reshape(Bn, n, width).sum(-1) for part, (n, width, _) in zip(parts, self._groups)],
                        dim=1)                                               # (B, P) in the groups' order
        return img[:, self._unsort]

    def planes(self, weights, receive=None, base=None) -> dict[str, torch.Tensor]:
        """``{name: complex (B, H, W)}`` as :meth:`MatrixPSF.planes`; differentiable in ``weights``
        (and ``receive``, separate receive weights); ``base`` as :meth:`image`."""
        return split_planes(self.image(weights, receive=receive, base=base), self._shapes)

    # ---------------------------------------------------------------- check
    def state(self) -> dict[str, torch.Tensor]:
        """The tensors that :meth:`from_state` restores this model from (for the on-disk cache;
        stored in single precision, 1e-7 relative, far below the check's tolerance, or in the
        scaled float16 of :attr:`FastSettings.storage`, as checked, with their column scales). The
        transmit tensor holds the rows ``g < r_n`` of each transmit (``ranks``), without padding."""
        low = self.storage == "float16"
        out = {"B": self._B.cpu() if low else self._B.cpu().float(),
               "Psi": self._Psi.cpu() if low else self._Psi.cpu().to(torch.complex64),
               "C": self._C.cpu().to(torch.complex64), "unsort": self._unsort.cpu(),
               "groups": torch.tensor(self._groups, dtype=torch.int64).reshape(-1, 3),
               "image_scale": torch.tensor(float(self.image_scale)),
               "check_error": torch.tensor(float(self.check["max_relative_error"])),
               "ranks": torch.tensor(self.sizes["transmit_ranks"]), "nodes": torch.tensor(self.sizes["nodes"]),
               "harmonics": torch.tensor(self.sizes["harmonics"]),
               "amplitude_terms": torch.tensor(self.sizes["amplitude_terms"])}
        if low:
            out.update(B_scale=self._B_scale.cpu(), Psi_scale=self._Psi_scale.cpu())
        return out

    @classmethod
    def from_state(cls, setup, state: dict, settings: FastSettings | None = None, dtype=torch.float32,
                   device="cpu", coords: dict | None = None) -> "MatrixFastPSF":
        """A model restored from :meth:`state` for ``setup`` (no exact model is built: :attr:`exact`
        is None); ``coords``: the surfaces it was built on, when not the setup's planes (as
        :class:`MatrixPSF`'s ``coords``). Tensors stored in float16 stay so (read a block at a
        time). Raises ValueError when the tensors do not fit the setup."""
        self = cls.__new__(cls)
        self.settings = settings or FastSettings()
        self.exact = None
        self.setup = setup
        self.coords = plane_axes(setup) if coords is None else check_surfaces(coords)
        self._shapes = {k: tuple(v.shape[:2]) for k, v in self.coords.items()}
        self.n_elements = setup.probe.n_elements
        self.dtype = dtype
        self.cdtype = torch.complex64 if dtype == torch.float32 else torch.complex128
        self.device = torch.device(device)
        self.image_scale = float(state["image_scale"])
        self._groups = [tuple(int(v) for v in row) for row in state["groups"]]
        n_pix = sum(h * w for h, w in self._shapes.values())
        columns = sum(n * width for n, width, _ in self._groups)
        B, Psi, C, unsort = state["B"], state["Psi"], state["C"], state["unsort"]
        ranks = [int(r) for r in state["ranks"]]
        low = B.dtype == torch.float16
        self._B_scale, self._Psi_scale = (state.get("B_scale"), state.get("Psi_scale")) if low else (None, None)
        if (B.shape != (self.n_elements, 2 * columns) or Psi.shape[1] != (2 * columns if low else columns)
                or unsort.shape != (n_pix,) or (Psi.dtype == torch.float16) != low
                or sum(n for n, _, _ in self._groups) != n_pix
                or C.shape[:2] != (setup.n_tx, self.n_elements) or len(ranks) != C.shape[0]
                or max(ranks) != C.shape[2] or sum(ranks) != Psi.shape[0]
                or (low and (self._B_scale is None or self._Psi_scale is None
                             or self._B_scale.shape != (2 * columns,) or self._Psi_scale.shape != (columns,)))):
            raise ValueError("the stored fast-path tensors do not fit this scene")
        self._B = (B if low else B.to(dtype)).contiguous()
        self._Psi = (Psi if low else Psi.to(self.cdtype)).contiguous()
        self._C = C.to(self.cdtype).contiguous()
        self._rows = _transmit_rows(ranks, C.shape[2])
        self._unsort = unsort
        self._to_device()
        self.sizes = {"transmit_ranks": ranks, "nodes": int(state["nodes"]),
                      "harmonics": int(state["harmonics"]), "amplitude_terms": int(state["amplitude_terms"]),
                      "pixels": n_pix, "bytes": self._bytes()}
        self.check = {"max_relative_error": float(state["check_error"]), "tolerance": self.settings.check_tol,
                      "restored": True}
        return self

    def _check(self, masks) -> dict:
        ne = self.n_elements
        if masks is None:
            g = torch.Generator().manual_seed(0)
            k = max(1, ne // 4)
            rows = [torch.ones(ne)]
            for _ in range(2):
                m = torch.zeros(ne)
                m[torch.randperm(ne, generator=g)[:k]] = 1
                rows.append(m)
            masks = torch.stack(rows)
        masks = torch.as_tensor(np.asarray(masks), dtype=torch.float64) if not isinstance(masks, torch.Tensor) \
            else masks.to(torch.float64)
        with torch.no_grad():
            exact = {k: v.to(torch.complex128) for k, v in self.exact.planes(masks.to(self.exact.dtype)).items()}
            fast = {k: v.to(torch.complex128) for k, v in self.planes(masks).items()}
        err = fast_relative_error(fast, exact)
        worst = float(err.max())
        rec = {"masks": int(masks.shape[0]), "max_relative_error": worst,
               "per_mask": [float(e) for e in err], "tolerance": self.settings.check_tol}
        if not math.isfinite(worst) or worst > self.settings.check_tol:
            raise FastPathUnavailable(f"the fast path departs from the exact path by {worst:.2e} (relative "
                                      f"squared error) on its check selections, above {self.settings.check_tol:.1e}")
        return rec
