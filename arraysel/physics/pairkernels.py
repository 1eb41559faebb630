"""Compiled kernels of the fast path: symmetric pair images and their sparse sketch (the
precomputation), the delay-and-sum of one selection's channels on chosen pixels (the
certificates' refinement) and the sums of envelope entries that bound each grid block (the
certificates' block bounds). The kernels on a few selections' channels and on images (their
peaks, the peak search and the window cut) are in :mod:`arraysel.physics.peakkernels`, whose
public names are importable from here too.

For one scatterer the image of a selection ``m`` is ``I(p) = sum_{e<=j} m_e m_j H_ej(p)``
with the symmetric pair image ``H_ej = D_ej + D_je`` (``e < j``), ``H_ee = D_ee``, where
``D_ej(p) = sum_n rot_nep * lerp(X_nej, t_nep)`` is the delay-and-sum, over the
transmits ``n``, of the I/Q signal ``X_nej`` received by element ``e`` when element ``j``
transmits. :func:`pair_images` evaluates every ``H`` on a set of pixels directly from the I/Q
signals and the DAS plans: a pixel reads two adjacent samples of a row of ``X`` per
(transmit, receive element), and each such row holds the samples of every transmitting element,
so the pixel's ``Ne x Ne`` matrix ``D`` is accumulated a receive row at a time over contiguous
memory (``ntx * Ne^2`` complex multiply-adds a pixel), for a group of adjacent pixels at once,
and symmetrised once.

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

from arraysel.io.numba_cache import ensure_cache_dir
# re-exported from their own module: the peaks of a few selections' channels, row sums, moved
# rows, the peak search and the window cut
from arraysel.physics.peakkernels import (  # noqa: F401
    channel_peaks_into, cut_windows_compiled, move_rows, peak_stats, receive_major, row_sums, swap_channels,
    swap_peaks_into)

ensure_cache_dir(__file__)  # a place numba can cache the kernels in, also for a user who cannot write here

#: side of the square blocks of a pixel's matrix ``D`` read together when it is symmetrised
#: (``D_ej + D_je`` reads ``D`` by columns; blocks keep those reads in the first-level cache)
_SYM_BLOCK = 16

#: pixels whose matrices ``D`` are accumulated together, receive row by receive row: adjacent
#: pixels read nearly the same samples, so each row of ``X`` is read from memory once for them
#: all (the kernel is bound by those reads: 1.3 to 1.7 times faster than pixel by pixel)
_PIXEL_GROUP = 16


@numba.njit(parallel=True, cache=True, nogil=True)
def _pair_images_kernel(X, i0, wt, rr, ri, nchunk, group, out):
    """Symmetric pair images of every pair on the plan's pixels.

    X: (ntx, Ne, T, 2, Ne) float32, ``X[n, e, t, 0 | 1, j]`` the real | imaginary part of I/Q
    sample ``t`` of (rx e, tx j); i0: (ntx, Ne, Npix) int32 first sample read by pixel p for
    rx e (local to ``X``); wt: (ntx, Ne, Npix) float32 linear-interpolation weight of the
    second sample; rr, ri: (ntx, Ne, Npix) float32 real and imaginary part of the phase
    rotation (0 where the sample is outside the record or the element outside the aperture);
    nchunk: pixel chunks run in parallel; group: pixels accumulated together
    (:data:`_PIXEL_GROUP`); out: (2, Npix, P) float64 [re, im], pairs in upper-triangle order
    of (e, j), e <= j.
    """
    ntx = X.shape[0]
    ne = X.shape[1]
    npix = i0.shape[2]
    for c in numba.prange(nchunk):
        D = np.empty((group, ne, 2, ne))  # the group's D[q, e, re | im, j]
        pa = c * npix // nchunk
        pb = (c + 1) * npix // nchunk
        for g0 in range(pa, pb, group):
            ng = min(group, pb - g0)
            for e in range(ne):
                for q in range(ng):
                    D[q, e, 0, :] = 0.0
                    D[q, e, 1, :] = 0.0
                for n in range(ntx):
                    for q in range(ng):
                        p = g0 + q
                        cr = np.float64(rr[n, e, p])
                        ci = np.float64(ri[n, e, p])
                        if cr == 0.0 and ci == 0.0:
                            continue
                        w = np.float64(wt[n, e, p])
                        # lerp then rotate = rot (1 - w) x[i] + rot w x[i + 1]
                        ar, ai = cr * (1.0 - w), ci * (1.0 - w)
                        br, bi = cr * w, ci * w
                        i = i0[n, e, p]
                        xr, xi = X[n, e, i, 0], X[n, e, i, 1]
                        yr, yi = X[n, e, i + 1, 0], X[n, e, i + 1, 1]
                        dr = D[q, e, 0]
                        di = D[q, e, 1]
                        for j in range(ne):
                            dr[j] += ar * xr[j] - ai * xi[j] + br * yr[j] - bi * yi[j]
                            di[j] += ar * xi[j] + ai * xr[j] + br * yi[j] + bi * yr[j]
            for q in range(ng):
                p = g0 + q
                for eb in range(0, ne, _SYM_BLOCK):
                    for jb in range(eb, ne, _SYM_BLOCK):
                        for e in range(eb, min(eb + _SYM_BLOCK, ne)):
                            row = e * ne - (e * (e - 1)) // 2 - e  # pair (e, j) is row + j
                            for j in range(max(jb, e + 1), min(jb + _SYM_BLOCK, ne)):
                                out[0, p, row + j] = D[q, e, 0, j] + D[q, j, 0, e]
                                out[1, p, row + j] = D[q, e, 1, j] + D[q, j, 1, e]
                            if jb <= e:
                                out[0, p, row + e] = D[q, e, 0, e]
                                out[1, p, row + e] = D[q, e, 1, e]


def pair_images(X: np.ndarray, plan: tuple, buffer: np.ndarray | None = None) -> np.ndarray:
    """Symmetric pair images (2, Npix, P) float64 [re, im] of every pair (upper-triangle order)
    on the plan's pixels. ``X`` and ``plan`` = (i0, wt, rr, ri) as documented in
    :func:`_pair_images_kernel`. ``buffer``: a float64 array to write them into when it holds
    ``2 Npix P`` entries (a caller calling many times reuses its memory instead of having fresh
    pages mapped for each call); a fresh array otherwise."""
    i0, wt, rr, ri = plan
    ne = X.shape[1]
    npix = i0.shape[2]
    shape = (2, npix, ne * (ne + 1) // 2)
    if buffer is None or buffer.size < shape[0] * shape[1] * shape[2]:
        out = np.empty(shape, dtype=np.float64)
    else:
        out = buffer.reshape(-1)[:shape[0] * shape[1] * shape[2]].reshape(shape)
    nchunk = max(1, min(-(-npix // _PIXEL_GROUP), 4 * numba.get_num_threads()))
    _pair_images_kernel(X, i0, wt, rr, ri, nchunk, _PIXEL_GROUP, out)
    return out


@numba.njit(parallel=True, cache=True, nogil=True)
def _sparse_sketch_kernel(Yt, Ht, hit, sign, width):
    """``Yt[hit[r, k], q] += sign[r, k] Ht[r, q]`` for every row r and k, parallel over chunks
    of ``width`` columns q (the inner loop runs over a slice from 0, which the compiler
    vectorises)."""
    ncol = Ht.shape[1]
    nchunk = -(-ncol // width)
    for c in numba.prange(nchunk):
        q0 = c * width
        n = min(ncol, q0 + width) - q0
        for r in range(Ht.shape[0]):
            h = Ht[r, q0:q0 + n]
            for k in range(hit.shape[1]):
                y = Yt[hit[r, k], q0:q0 + n]
                s = sign[r, k]
                for q in range(n):
                    y[q] += s * h[q]


def sparse_sketch_add(Yt: np.ndarray, Ht: np.ndarray, hit: np.ndarray, sign: np.ndarray) -> None:
    """Add ``S^T Ht`` to ``Yt`` (L, n) in place, for the sparse sketching matrix ``S`` (rows of
    ``Ht``, L) whose row r holds ``sign[r, k]`` in column ``hit[r, k]`` (duplicates add up).
    Yt: (L, n) float32 or float64; Ht: (rows, n) float64; hit: (rows, zeta) int64; sign: (rows,
    zeta) float64."""
    _sparse_sketch_kernel(Yt, Ht, hit, sign, 1024)


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


@numba.njit(cache=True, nogil=True, inline="always")
def _segment_lerp(y, e, n, i, w, shift, ns, last):
    """``(re, im)`` of raw channel ``y[e]`` ((2, ntx, T), samples in segment-offset-major order,
    ``2 ** shift`` a segment, ``ns`` segments) for transmit ``n`` at sample ``i + w`` (linear
    interpolation between samples ``i`` and ``i + 1``): sample t is stored at ``(t % sg) ns + t //
    sg`` with ``sg = 2 ** shift`` (shifts and masks: an integer division per entry cost as much as
    the rest of the sum)."""
    r = i & last
    ia = r * ns + (i >> shift)
    ib = ia + ns if r != last else (i >> shift) + 1
    ar = y[e, 0, n, ia]
    ai = y[e, 1, n, ia]
    return ar + (y[e, 0, n, ib] - ar) * w, ai + (y[e, 1, n, ib] - ai) * w


def _segment_shift(segment: int, samples: int) -> int:
    """``log2(segment)`` for the compiled sums over raw channels of ``samples`` samples; a
    ``ValueError`` unless ``segment`` is a power of two dividing them."""
    shift = int(segment).bit_length() - 1
    if segment < 1 or 1 << shift != segment or samples % segment:
        raise ValueError(f"segment: a power of two dividing the {samples} samples, got {segment}")
    return shift


@numba.njit(parallel=True, cache=True, nogil=True)
def _das_stacked_raw_kernel(y, we, i0, wt, rot, shift, out):
    """``out[p] = sum_{n, e} rot[n, p, e] we[e] lerp(y[e, :, n], i0[n, p, e], wt[n, p, e])`` over
    the entries with a non-zero rotation and weight (the channels of a zero weight are not read).
    y: (Ne, 2, ntx, T) [re, im], samples in segment-offset-major order (:func:`_segment_lerp`,
    ``2 ** shift`` a segment); i0, wt: (ntx, Npix, Ne); rot: (ntx, Npix, Ne, 2); out: (Npix, 2)
    float64."""
    ntx = i0.shape[0]
    ne = i0.shape[2]
    ns = y.shape[3] >> shift
    last = (1 << shift) - 1
    for p in numba.prange(i0.shape[1]):
        sr = 0.0
        si = 0.0
        for n in range(ntx):
            for e in range(ne):
                f = we[e]
                cr = rot[n, p, e, 0]
                ci = rot[n, p, e, 1]
                if f != 0.0 and (cr != 0.0 or ci != 0.0):
                    vr, vi = _segment_lerp(y, e, n, np.int64(i0[n, p, e]), wt[n, p, e], shift, ns, last)
                    vr = vr * f
                    vi = vi * f
                    sr += cr * vr - ci * vi
                    si += cr * vi + ci * vr
        out[p, 0] = sr
        out[p, 1] = si


def das_stacked_raw(y: np.ndarray, we: np.ndarray, i0: np.ndarray, wt: np.ndarray, rot: np.ndarray,
                    segment: int) -> np.ndarray:
    """Delay-and-sum of one selection's I/Q channels with block plans stacked over the transmits,
    in one compiled call (the certificates' refinement: a call covers a few blocks, where one call
    and plan concatenation per transmit cost as much as the sums). y (Ne, 2, ntx, T) [re, im]
    with each channel's samples in segment-offset-major order (``segment`` samples a segment;
    1: time order), weighted by ``we`` (Ne,) inside the sum (the certificate product's raw
    channels, :class:`arraysel.physics.psf.refinement.RawChannels`); i0, wt (ntx, Npix, Ne); rot
    (ntx, Npix, Ne, 2). Returns (Npix, 2) float64 [re, im]."""
    out = np.empty((i0.shape[1], 2), dtype=np.float64)
    _das_stacked_raw_kernel(y, we, i0, wt, rot, _segment_shift(segment, y.shape[3]), out)
    return out


@numba.njit(parallel=True, cache=True, nogil=True)
def _block_pair_images_kernel(y, i0, wt, rot, shift, out):
    """``out[j, e, p] = sum_n rot[n, p, e] lerp(y[j, e, :, n], i0[n, p, e], wt[n, p, e])``: the
    delay-and-sum on a block's pixels of the I/Q signal received by element ``e`` when element
    ``j`` transmits, for every (j, e). y: (Ne, Ne, 2, ntx, T) [re, im] (``pair_channels``, tx
    rows, samples as :func:`_segment_lerp` reads them); i0, wt: (ntx, Npix, Ne); rot: (ntx, Npix,
    Ne, 2); out: (Ne, Ne, Npix, 2) float64."""
    nj = y.shape[0]
    ne = y.shape[1]
    ntx = i0.shape[0]
    npix = i0.shape[1]
    ns = y.shape[4] >> shift
    last = (1 << shift) - 1
    for j in numba.prange(nj):
        yj = y[j]
        for e in range(ne):
            for p in range(npix):
                sr = 0.0
                si = 0.0
                for n in range(ntx):
                    cr = rot[n, p, e, 0]
                    ci = rot[n, p, e, 1]
                    if cr != 0.0 or ci != 0.0:
                        vr, vi = _segment_lerp(yj, e, n, np.int64(i0[n, p, e]), wt[n, p, e], shift, ns, last)
                        sr += cr * vr - ci * vi
                        si += cr * vi + ci * vr
                out[j, e, p, 0] = sr
                out[j, e, p, 1] = si


def block_pair_matrix(y: np.ndarray, i0: np.ndarray, wt: np.ndarray, rot: np.ndarray, segment: int) -> np.ndarray:
    """The symmetric pair matrix ``G = (D + D^T) / 2`` of one block's pixels, (Ne, Ne, 2 Npix)
    float64 with [re | im] last-axis halves, so that a selection's image on the block is
    ``I(w) = sum_{e, j} w_e w_j G[e, j]`` (``D[j, e]``: :func:`_block_pair_images_kernel`), from
    the stored pair channels ``y`` (Ne, Ne, 2, ntx, T) and the block's plan (i0, wt: (ntx,
    Npix, Ne); rot: (ntx, Npix, Ne, 2)). The refinement's hot blocks
    (:class:`arraysel.physics.psf.hotblocks.HotBlocks`) settle selections from it
    instead of delay-and-summing each one's channels."""
    ne, npix = y.shape[0], i0.shape[1]
    D = np.empty((ne, ne, npix, 2), dtype=np.float64)
    _block_pair_images_kernel(y, i0, wt, rot, _segment_shift(segment, y.shape[4]), D)
    S = (D + D.transpose(1, 0, 2, 3)) * 0.5
    return np.ascontiguousarray(np.concatenate([S[..., 0], S[..., 1]], axis=2))


@numba.njit(cache=True, nogil=True)
def _moved_block_values_kernel(G, g, base, idx, val, out):
    """``out[r] = base + 2 sum_a val[r, a] g[idx[r, a]] + sum_{a, b} val[r, a] val[r, b]
    G[idx[r, a], idx[r, b]]`` over the entries ``idx >= 0`` of each row (the rest is padding)."""
    nr, nl = idx.shape
    n2 = g.shape[1]
    for r in range(nr):
        for p in range(n2):
            out[r, p] = base[p]
        for a in range(nl):
            x = idx[r, a]
            if x < 0:
                break
            va = val[r, a]
            for p in range(n2):
                out[r, p] += 2.0 * va * g[x, p]
            for b in range(nl):
                z = idx[r, b]
                if z < 0:
                    break
                vab = va * val[r, b]
                for p in range(n2):
                    out[r, p] += vab * G[x, z, p]


def moved_block_values(G: np.ndarray, g: np.ndarray, base: np.ndarray, idx: np.ndarray, val: np.ndarray) -> np.ndarray:
    """Images (R, 2 Npix) float64 on one block of selections ``w = s + d`` that differ from a
    reference selection ``s`` by ``d`` (row r: ``d[idx[r, a]] = val[r, a]``, ``idx`` padded with
    -1), from the block's pair matrix ``G`` (:func:`block_pair_matrix`), ``g = G s`` (Ne, 2 Npix)
    and ``base = s^T G s``: ``I(s + d) = I(s) + 2 d^T G s + d^T G d``, ``|d|^2`` rows of ``G``
    read a selection instead of all ``Ne^2``."""
    out = np.empty((idx.shape[0], g.shape[1]), dtype=np.float64)
    _moved_block_values_kernel(G, g, base, idx, val, out)
    return out


#: channels whose envelope entries are summed in the envelopes' precision before the sum moves
#: to float64 in :func:`block_bound_sums` (float32: relative error at most 31 u < 2e-6, well
#: inside the bounds' 1e-4 margin; twice the speed of float64 throughout)
_BOUND_PARTIAL = 32


@numba.njit(parallel=True, cache=True, nogil=True)
def _block_bound_sums_kernel(env, index, chans, group, partial, out):
    """``out[q, b] = sum_{c in chans} env[c, index[c, q], b]`` over ``index[c, q] >= 0``: partial
    sums over ``partial`` channels in env's precision, their total in float64. env: (nch, L, B)
    float; index: (nch, nQ) int32; out: (nQ, B) float64. Parallel over groups of ``group``
    consecutive blocks, channel by channel inside a group: neighbouring blocks read
    neighbouring rows of a channel's envelopes, which stay in cache for the group (a block at a
    time, or every block channel by channel, reads them from memory again)."""
    nq = index.shape[1]
    B = env.shape[2]
    nc = chans.shape[0]
    for g in numba.prange((nq + group - 1) // group):
        q0 = g * group
        q1 = min(nq, q0 + group)
        acc = np.zeros((q1 - q0, B), np.float64)
        part = np.zeros((q1 - q0, B), env.dtype)
        for c0 in range(0, nc, partial):
            for ci in range(c0, min(nc, c0 + partial)):
                ch = chans[ci]
                for q in range(q0, q1):
                    k = index[ch, q]
                    if k >= 0:
                        for b in range(B):
                            part[q - q0, b] += env[ch, k, b]
            for q in range(q1 - q0):
                for b in range(B):
                    acc[q, b] += part[q, b]
                    part[q, b] = 0.0
        for q in range(q0, q1):
            for b in range(B):
                out[q, b] = acc[q - q0, b]


def block_bound_sums(env: np.ndarray, index: np.ndarray, chans: np.ndarray, group: int = 64) -> np.ndarray:
    """Sums, per grid block ``q`` and selection ``b``, of the envelope entries the blocks read:
    ``sum_c env[c, index[c, q], b]`` over the channels ``chans`` (int64; the others are zero)
    and the entries with ``index[c, q] >= 0`` (the certificates' block bounds, what the sparse
    product with ``block_envelopes_*`` gives; float64 totals of float32 partial sums). env:
    (nch, L, B) float; index: (nch, nQ) int32. Returns (nQ, B) float64."""
    out = np.empty((index.shape[1], env.shape[2]), dtype=np.float64)
    _block_bound_sums_kernel(env, index, chans, max(1, int(group)), _BOUND_PARTIAL, out)
    return out

