"""The metrics of :func:`~arraysel.objective.metrics3d.psf3d_metrics` for many images held pixel-major.

A neighbourhood of a 3-D scene (:mod:`arraysel.objective.matrix_neighbours`) produces its images
either as columns (real and imaginary parts ``(P, M)``, one column per neighbour, the rows the
pixels of every plane: :meth:`ColumnMetrics.__call__`) or, for a block of swaps, as ``|img|^2``
with one row per neighbour and its sums against the reference (:meth:`ColumnMetrics.from_power`).
Neither is reshaped into the ``(M, H, W)`` planes :func:`psf3d_metrics` takes: the pixels'
positions are held in the images' pixel order; the peaks, the region sums and the side-lobe
quantile's order statistics come from compiled passes along each neighbour's row
(:mod:`arraysel.objective.column_kernels`). The definitions are those of
:mod:`arraysel.objective.metrics3d` (the same regions around each image's own peak, the same
quantile, the same main-lobe widths through the C-plane's own peak), so the values are the same to
rounding (``tests/test_matrix_neighbours.py``). CPU tensors. No gradient.
"""
from __future__ import annotations

import math

import numpy as np
import torch

from arraysel.objective.metrics import METRIC_NAMES
from arraysel.objective.reductions import BOUNDARY_RTOL, safe_div as _safe_div
from arraysel.objective.metrics3d import (C_PLANE, MERIT_NAMES, PSL_FLOOR_DB, SIX_DB, c_plane_axes, level_crossing,
                                          region_radii, plane_set)

__all__ = ["ColumnMetrics"]


def _sqrt0(x: torch.Tensor) -> torch.Tensor:
    return torch.sqrt(torch.clamp(x, min=0))


class ColumnMetrics:
    """Every metric of a 3-D objective (``METRIC_NAMES`` and ``MERIT_NAMES``) of images given as
    columns. ``coords``: the objective's plane coordinates ``{name: (H, W, 3)}``; ``reference``:
    the full array's planes ``{name: (1, H, W)}``; ``rows``: for each row of the columns, the
    pixel (in the planes' order, plane after plane, row-major) it holds; ``wavelength``,
    ``r_main``, ``r_guard``, ``quantile`` as :func:`psf3d_metrics`."""

    def __init__(self, coords, reference, rows: torch.Tensor, *, wavelength: float, r_main: float,
                 r_guard: float, quantile: float, dtype=torch.float32):
        ps = plane_set({k: v for k, v in reference.items()}, coords)
        self.names = ps.names
        self.rows = rows                                   # row r holds pixel rows[r]
        self.n = n = int(rows.numel())
        self.unsort = torch.empty_like(rows)
        self.unsort[rows] = torch.arange(n)                # pixel i sits in row unsort[i]
        self.coords = ps.coords[rows]                      # (N, 3) float64, in row order
        self.rm, self.rg = region_radii(wavelength, r_main, r_guard)
        self.q = float(quantile)
        self.dtype = dtype
        ref = ps.flat[0].to(torch.complex128)[rows]        # the reference, in row order
        self.ref_r, self.ref_i = ref.real.to(dtype), ref.imag.to(dtype)
        self.rr = float((ref.abs() ** 2).sum())
        self.top = min(n, int(math.ceil((1.0 - self.q) * (n - 1))) + 2)
        self.c_off = ps.offsets.get(C_PLANE)
        if self.c_off is not None:
            self.c_shape = ps.shapes[C_PLANE]
            c = np.asarray(coords[C_PLANE], dtype=np.float64)
            self.c_coords = c
            self.c_axes = c_plane_axes(C_PLANE, c)

    def __call__(self, re: torch.Tensor, im: torch.Tensor) -> dict[str, np.ndarray]:
        """``{name: float64 (M,)}`` of the images ``re + i im`` (each ``(P, M)``, rows as ``rows``)."""
        k2 = (re * re).addcmul_(im, im)                                    # |kappa|^2 (P, M)
        kr_re = self.ref_r @ re + self.ref_i @ im
        kr_im = self.ref_i @ re - self.ref_r @ im
        k2 = k2.T.contiguous()                                             # (M, N), in row order
        return self.from_power(k2, k2.sum(1).double(), kr_re.double(), kr_im.double())

    def from_power(self, k2: torch.Tensor, kk: torch.Tensor, kr_re: torch.Tensor,
                   kr_im: torch.Tensor) -> dict[str, np.ndarray]:
        """``{name: float64 (M,)}`` of images given by their ``|kappa|^2`` ``k2`` (M, N) (rows as
        ``rows``), ``<k, k>`` ``kk`` and ``<k, r>`` (``kr_re + i kr_im``) against the reference
        (each float64 (M,))."""
        out: dict[str, torch.Tensor] = {}
        tiny = torch.finfo(k2.dtype).tiny
        fit = _safe_div(kr_re ** 2 + kr_im ** 2, torch.where(kk > tiny, kk, torch.zeros_like(kk)))
        out["L_PSF"] = torch.clamp((self.rr - fit) / self.rr, min=0.0) if self.rr > 0 else torch.zeros_like(kk)
        peak_val, peak, c_peak = self._peaks(k2)
        lobe = {k: torch.empty(k2.shape[0], dtype=torch.float64) for k in
                ("L_contrast", "L_SLR_q", "L_SLR_i", "PSL_dB")}
        uniq, inv = torch.unique(self.coords[peak], dim=0, return_inverse=True)
        k2n = np.ascontiguousarray(k2.numpy())
        for u in range(uniq.shape[0]):
            rows = torch.nonzero(inv == u).flatten()
            for k, v in self._lobes(k2n, rows.numpy(), peak_val.index_select(0, rows), uniq[u]).items():
                lobe[k][rows] = v
        out.update(lobe)
        out["L_SLR"] = 0.5 * (out["L_SLR_q"] + out["L_SLR_i"])
        out["Mean"] = 0.25 * (out["L_PSF"] + out["L_contrast"] + out["L_SLR_q"] + out["L_SLR_i"])
        res = {k: out[k].double().numpy() for k in (*METRIC_NAMES, "PSL_dB")}
        res.update(self._widths(k2, c_peak))
        return {k: res[k] for k in (*METRIC_NAMES, *MERIT_NAMES)}

    def _lobes(self, k2: np.ndarray, rows: np.ndarray, peak: torch.Tensor,
               position: torch.Tensor) -> dict[str, torch.Tensor]:
        """The lobe terms of the items ``k2[rows]`` (``k2`` (M, N)) whose peaks (values ``peak``)
        lie at ``position``: the region sums and the side's largest values in one compiled pass
        (:func:`~arraysel.objective.column_kernels.lobe_sums`)."""
        from arraysel.objective.column_kernels import lobe_sums

        d2 = (self.coords - position[None]).square().sum(-1)
        main = d2 <= self.rm * self.rm * (1 + BOUNDARY_RTOL)
        side = d2 >= self.rg * self.rg * (1 - BOUNDARY_RTOL)
        n_main, n_side = int(main.sum()), int(side.sum())
        k = min(self.top, n_side)
        s_main, s_side = np.empty(rows.size), np.empty(rows.size)
        top = np.empty((rows.size, max(k, 1)))
        side_idx = torch.nonzero(side).flatten().numpy()
        rows = np.ascontiguousarray(rows, dtype=np.int64)
        # the heap starts from the side pixels largest in the first image (its neighbours' alike)
        seeds = side_idx[np.argsort(-k2[rows[0], side_idx], kind="stable")[:k]] if rows.size else side_idx[:k]
        free = side.numpy().astype(k2.dtype)
        free[seeds] = 0
        lobe_sums(k2, rows, main.double().numpy(), side.double().numpy(), np.ascontiguousarray(seeds, dtype=np.int64),
                  free, k, s_main, s_side, top)
        s_main, s_side, top = torch.from_numpy(s_main), torch.from_numpy(s_side), torch.from_numpy(top)
        res = {"L_SLR_i": _safe_div(s_side, s_main),
               "L_contrast": _safe_div(s_side / max(n_side, 1), s_main / max(n_main, 1))}
        peak = peak.double()
        if n_side == 0:
            res["L_SLR_q"] = torch.zeros_like(peak)
            res["PSL_dB"] = torch.full_like(peak, PSL_FLOOR_DB)
            return res
        pos = self.q * (n_side - 1)
        lo, hi = math.floor(pos), math.ceil(pos)
        v_lo = _sqrt0(top[:, min(max(n_side - 1 - lo, 0), k - 1)])
        v_hi = _sqrt0(top[:, min(max(n_side - 1 - hi, 0), k - 1)])
        res["L_SLR_q"] = _safe_div(v_lo + (pos - lo) * (v_hi - v_lo), _sqrt0(peak))
        ratio = _safe_div(top[:, 0], peak)
        res["PSL_dB"] = 10.0 * torch.log10(torch.clamp(ratio, min=10.0 ** (PSL_FLOOR_DB / 10.0)))
        return res

    def _peaks(self, k2: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """``(peak value, peak row, C-plane peak)`` of the items ``k2`` (M, N): the largest value and
        its first row (as ``torch.max``), and the first pixel of the C-plane (its flat index in the
        plane) holding the plane's largest value; one compiled pass
        (:func:`~arraysel.objective.column_kernels.peaks`)."""
        from arraysel.objective.column_kernels import peaks

        m = k2.shape[0]
        pv = torch.empty(m, dtype=k2.dtype)
        pk, cpk = torch.empty(m, dtype=torch.long), torch.zeros(m, dtype=torch.long)
        if self.c_off is None:
            crows = np.empty(0, dtype=np.int64)
        else:
            h, w = self.c_shape
            crows = self.unsort[self.c_off:self.c_off + h * w].numpy()         # C-plane pixel -> row
        peaks(np.ascontiguousarray(k2.numpy()), np.ascontiguousarray(crows, dtype=np.int64), pv.numpy(),
              pk.numpy(), cpk.numpy())
        return pv, pk, cpk

    def _widths(self, k2: torch.Tensor, flat_peak: torch.Tensor) -> dict[str, np.ndarray]:
        """The -6 dB widths along x and y of the C-plane through its own peak (its flat index in the
        plane ``flat_peak``; as :func:`~arraysel.objective.metrics3d.main_lobe_widths`) of the
        items ``k2`` (M, N)."""
        m = k2.shape[0]
        if self.c_off is None:
            return {"width_x_6dB": np.full(m, np.inf), "width_y_6dB": np.full(m, np.inf)}
        h, w = self.c_shape
        o = self.c_off
        at = self.unsort                                                   # pixel -> row
        i0, j0 = flat_peak // w, flat_peak % w
        c = self.c_coords
        out = {}
        for letter, comp in (("x", 0), ("y", 1)):
            if self.c_axes[letter] == 1:       # along the row i0
                idx = o + i0[:, None] * w + torch.arange(w)[None, :]
                s = c[i0.numpy(), :, comp]
            else:
                idx = o + torch.arange(h)[None, :] * w + j0[:, None]
                s = c[:, j0.numpy(), comp].T
            a = _sqrt0(torch.gather(k2, 1, at[idx])).double().numpy()        # (M, n)
            jp = np.argmax(a, axis=1)
            pk = a[np.arange(m), jp]
            thr = SIX_DB * pk
            width = np.abs(level_crossing(s, a, jp, thr, +1) - level_crossing(s, a, jp, thr, -1))
            out[f"width_{letter}_6dB"] = np.where(np.isfinite(width) & (pk > 0), width, np.inf)
        return out
