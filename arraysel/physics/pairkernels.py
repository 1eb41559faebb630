"""Compiled kernel of the fast path's precomputation: symmetric pair images.

For one scatterer the image of a selection ``m`` is ``I(p) = sum_{e<=j} m_e m_j H_ej(p)``
with the symmetric pair image ``H_ej = D_ej + D_je`` (``e < j``), ``H_ee = D_ee``, where
``D_ej(p) = sum_n rot_nep * lerp(X_nej, t_nep)`` is the delay-and-sum, over the
transmits ``n``, of the I/Q signal ``X_nej`` received by element ``e`` when element ``j``
transmits. :func:`pair_images` evaluates ``H`` for the pairs whose first element lies in
``[e0, e1)``, on any set of pixels, directly from the I/Q signals and the DAS plans: a
pixel reads two adjacent samples of a row of ``X`` per (transmit, element), so the
work is ``ntx * Ne^2 * Npix`` complex multiply-adds and no pair image is ever held
for all pixels at once unless the caller asks for it.

The loops are compiled with numba (parallel over pixels). Everything here works on
numpy arrays; the callers convert. The compiled code is cached on disk (``cache=True``: next to
this file, or in numba's user-wide cache folder when the package folder is read-only, or in
``NUMBA_CACHE_DIR``), so only the first process on a machine pays the compilation, about a
second per argument signature; later processes load it (a cold ``arraysel evaluate`` that
settles a loose block or an exact window needs the delay-and-sum kernel).
"""
from __future__ import annotations

import numba
import numpy as np


@numba.njit(inline="always", cache=True)
def _lerp_rotate_add(out, p, row, a, b, w, cr, ci):
    """``out[p, row] += (cr + i ci) * (a + (b - a) w)`` on the [re, im] pair of ``out``."""
    vr = a.real + (b.real - a.real) * w
    vi = a.imag + (b.imag - a.imag) * w
    out[p, row, 0] += cr * vr - ci * vi
    out[p, row, 1] += cr * vi + ci * vr


@numba.njit(parallel=True, cache=True, nogil=True)
def _pair_images_kernel(X, i0, wt, rr, ri, e0, e1, out):
    """Accumulate the symmetric pair images of rows (e in [e0, e1), j >= e) into ``out``.

    X: (ntx, Ne, T, Ne) complex64, ``X[n, e, t, j]`` the I/Q sample ``t`` of (rx e, tx j);
    i0: (ntx, Ne, Npix) int32 first sample read by pixel p for rx e (local to ``X``);
    wt: (ntx, Ne, Npix) float32 linear-interpolation weight of the second sample;
    rr, ri: (ntx, Ne, Npix) float32 real and imaginary part of the phase rotation
    (0 where the sample is outside the record or the element outside the aperture);
    out: (Npix, nrows, 2) float64, rows in upper-triangle order of (e, j).
    """
    ntx = X.shape[0]
    ne = X.shape[1]
    npix = i0.shape[2]
    for p in numba.prange(npix):
        for n in range(ntx):
            # D_ej, e in the block (receive), every j >= e (transmit)
            row = 0
            for e in range(e0, e1):
                cr = rr[n, e, p]
                ci = ri[n, e, p]
                if cr != 0.0 or ci != 0.0:
                    i = i0[n, e, p]
                    w = wt[n, e, p]
                    for j in range(e, ne):
                        _lerp_rotate_add(out, p, row + j - e, X[n, e, i, j], X[n, e, i + 1, j], w, cr, ci)
                row += ne - e
            # D_je, j > e (receive), e in the block (transmit)
            for j in range(e0 + 1, ne):
                cr = rr[n, j, p]
                ci = ri[n, j, p]
                if cr == 0.0 and ci == 0.0:
                    continue
                i = i0[n, j, p]
                w = wt[n, j, p]
                row = 0
                for e in range(e0, min(e1, j)):
                    _lerp_rotate_add(out, p, row + j - e, X[n, j, i, e], X[n, j, i + 1, e], w, cr, ci)
                    row += ne - e


def pair_row_blocks(n_elements: int, max_rows: int) -> list[tuple[int, int, int]]:
    """Split the upper-triangle pair rows into blocks of whole first elements:
    ``(e0, e1, rows)`` with at most ``max_rows`` rows each (at least one element)."""
    blocks = []
    e0 = 0
    while e0 < n_elements:
        e1, rows = e0, 0
        while e1 < n_elements and (rows + (n_elements - e1) <= max_rows or e1 == e0):
            rows += n_elements - e1
            e1 += 1
        blocks.append((e0, e1, rows))
        e0 = e1
    return blocks


def pair_images(X: np.ndarray, plan: tuple, e0: int, e1: int) -> np.ndarray:
    """Symmetric pair images (Npix, nrows, 2) float64 of the rows (e in [e0, e1), j >= e).

    ``plan`` = (i0, wt, rr, ri) as documented in :func:`_pair_images_kernel`.
    """
    i0, wt, rr, ri = plan
    ne = X.shape[1]
    rows = sum(ne - e for e in range(e0, e1))
    out = np.zeros((i0.shape[2], rows, 2), dtype=np.float64)
    _pair_images_kernel(X, i0, wt, rr, ri, int(e0), int(e1), out)
    return out


@numba.njit(parallel=True, cache=True, nogil=True)
def _das_rows_kernel(x, pix, i0, wt, rot, out):
    """``out[k] += sum_e rot[p, e] lerp(x[e], i0[p, e], wt[p, e])`` for plan row ``p = pix[k]``,
    over the entries with a non-zero rotation (the others are outside the aperture or the
    record).

    x: (Ne, T, 2) float [re, im] I/Q of one transmit; pix: (K,) int64; i0: (Npix, Ne) int;
    wt: (Npix, Ne) float; rot: (Npix, Ne, 2) float; out: (K, 2) float64.
    """
    ne = i0.shape[1]
    for k in numba.prange(pix.shape[0]):
        p = pix[k]
        sr = 0.0
        si = 0.0
        for e in range(ne):
            cr = rot[p, e, 0]
            ci = rot[p, e, 1]
            if cr != 0.0 or ci != 0.0:
                i = i0[p, e]
                w = wt[p, e]
                ar = x[e, i, 0]
                ai = x[e, i, 1]
                vr = ar + (x[e, i + 1, 0] - ar) * w
                vi = ai + (x[e, i + 1, 1] - ai) * w
                sr += cr * vr - ci * vi
                si += cr * vi + ci * vr
        out[k, 0] += sr
        out[k, 1] += si


def das_plan_rows(x: np.ndarray, plans, pix: np.ndarray) -> np.ndarray:
    """Delay-and-sum of one selection's I/Q channels on the rows ``pix`` (int64) of the plans
    (the same sum as :func:`arraysel.physics.beamform.das_apply`, skipping the entries outside
    the aperture). x: (ntx, Ne, T, 2) float [re, im]; plans: per transmit ``(i0, wt, rot)`` numpy
    arrays of shapes (Npix, Ne), (Npix, Ne), (Npix, Ne, 2). Returns (len(pix), 2) float64."""
    out = np.zeros((pix.shape[0], 2), dtype=np.float64)
    for n, (i0, wt, rot) in enumerate(plans):
        _das_rows_kernel(x[n], pix, i0, wt, rot, out)
    return out


@numba.njit(parallel=True, cache=True, nogil=True)
def _das_stacked_raw_kernel(y, we, i0, wt, rot, sg, out):
    """``out[p] = sum_{n, e} rot[n, p, e] we[e] lerp(y[:, n, e], i0[n, p, e], wt[n, p, e])`` over the
    entries with a non-zero rotation and weight. y: (2, ntx, Ne, T) [re, im], sample t of channel
    (n, e) at ``(t % sg) (T // sg) + t // sg``; i0, wt: (ntx, Npix, Ne); rot: (ntx, Npix, Ne, 2);
    out: (Npix, 2) float64."""
    ntx = i0.shape[0]
    ne = i0.shape[2]
    ns = y.shape[3] // sg
    for p in numba.prange(i0.shape[1]):
        sr = 0.0
        si = 0.0
        for n in range(ntx):
            for e in range(ne):
                f = we[e]
                cr = rot[n, p, e, 0]
                ci = rot[n, p, e, 1]
                if f != 0.0 and (cr != 0.0 or ci != 0.0):
                    i = i0[n, p, e]
                    w = wt[n, p, e]
                    ia = (i % sg) * ns + i // sg
                    ib = ((i + 1) % sg) * ns + (i + 1) // sg
                    ar = y[0, n, e, ia]
                    ai = y[1, n, e, ia]
                    vr = (ar + (y[0, n, e, ib] - ar) * w) * f
                    vi = (ai + (y[1, n, e, ib] - ai) * w) * f
                    sr += cr * vr - ci * vi
                    si += cr * vi + ci * vr
        out[p, 0] = sr
        out[p, 1] = si


def das_stacked_raw(y: np.ndarray, we: np.ndarray, i0: np.ndarray, wt: np.ndarray, rot: np.ndarray,
                    segment: int) -> np.ndarray:
    """Delay-and-sum of one selection's I/Q channels with block plans stacked over the transmits,
    in one compiled call (the certificates' refinement: a call covers a few blocks, where one call
    and plan concatenation per transmit cost as much as the sums). y (2, ntx, Ne, T) [re, im]
    with each channel's samples in segment-offset-major order (``segment`` samples a segment;
    1: time order), weighted by ``we`` (Ne,) inside the sum (the certificate product's raw
    channels, :class:`arraysel.physics.psf.refinement.RawChannels`); i0, wt (ntx, Npix, Ne); rot
    (ntx, Npix, Ne, 2). Returns (Npix, 2) float64 [re, im]."""
    out = np.empty((i0.shape[1], 2), dtype=np.float64)
    _das_stacked_raw_kernel(y, we, i0, wt, rot, int(segment), out)
    return out
