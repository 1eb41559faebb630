"""Compiled kernels on a few selections' receive channels and on images: the segment peaks of
the channels formed from the rows of ``pair_channels`` a selection uses, and of its swap
neighbours from its held channel sums (the certificates' envelopes), the row sums and moved rows
those use, and, for batches without gradient, the peak search on E and the cut and normalisation
of the kernels' windows.

Split from :mod:`arraysel.physics.pairkernels` (the pair images, the sketch, the delay-and-sum
on chosen pixels and the block bounds), which re-exports every public name here. Compiled with
numba and cached on disk the same way (``cache=True``).
"""
from __future__ import annotations

import numba
import numpy as np

from arraysel.io.numba_cache import ensure_cache_dir

ensure_cache_dir(__file__)  # a place numba can cache the kernels in, also for a user who cannot write here

@numba.njit(cache=True, nogil=True, inline="always")
def _nan_max(m, v):
    """The larger of ``m`` and ``v``, NaN when either is (torch's ``maximum``); ``m`` on a tie."""
    return v if (v > m or v != v) else m


@numba.njit(cache=True, nogil=True, inline="always")
def _segment_peaks(acc, mx, ntx, seg, ns, half, scale, env, ne, e, b):
    """``env[n * ne + e, 0, a, b] = scale max_r |acc|`` over the samples ``r`` of segment ``a`` of
    transmit ``n``, for one channel ``acc`` ([re | im] halves, segment-offset-major samples; a
    NaN sample makes its segment's peak NaN); ``mx`` (ns,) is scratch."""
    for n in range(ntx):
        for a in range(ns):
            mx[a] = 0.0
        for r in range(seg):
            o = (n * seg + r) * ns
            for a in range(ns):
                mx[a] = _nan_max(mx[a], acc[o + a] * acc[o + a] + acc[half + o + a] * acc[half + o + a])
        for a in range(ns):
            env[n * ne + e, 0, a, b] = np.sqrt(mx[a]) * scale


def receive_major(used: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(sel_b, sel_e)`` (int64 each): the pairs (selection ``b``, receive element ``e``) with
    ``used[b, e]`` (B, Ne) nonzero, receive element by receive element (selections in order within
    each), the order in which the per-channel peak kernels (:func:`channel_peaks_into`,
    :func:`swap_peaks_into`) visit them: the selections of one receive
    element read the same row of the held channel sums and many of the same blocks of
    ``pair_channels``, which then stay in cache from one selection to the next; selection by
    selection, each is read from memory again for every selection (a neighbourhood's peaks 1.6
    to 1.9 times slower on the built-in scenes: ``benchmarks/bench_channel_order.py``). The
    values do not depend on the order. (:func:`swap_channels`, whose time goes to writing whole
    channels, keeps the selections' order: the two orders time the same.)"""
    sel_e, sel_b = np.nonzero(np.asarray(used).T)
    return sel_b.astype(np.int64), sel_e.astype(np.int64)


@numba.njit(parallel=True, cache=True, nogil=True)
def _channel_peaks_kernel(A, w, sel_b, sel_e, ntx, env):
    """``env[n * Ne + e, 0, a, b] = |w[b, e]| max_r |sum_j w[b, j] A[j, e, :, n, r, a]|`` for the
    pairs ``(b, e) = (sel_b[q], sel_e[q])``: the segment peaks of one receive channel of one
    selection, from the rows j of ``pair_channels`` that the selection uses. A: (Ne, Ne * 2 *
    ntx * T) float, ``pair_channels`` (columns of receive e: part [re, im], transmit n, segment
    offset r, segment a; T = segment * nS); w: (B, Ne) float; env: (ntx * Ne, M, nS, B). The
    channel is summed in float64 in a buffer that stays in cache; a NaN stays NaN (as torch's
    maximum keeps it). Parallel over the pairs."""
    ne = w.shape[1]
    ns = env.shape[2]
    half = A.shape[1] // (2 * ne)
    seg = half // (ntx * ns)
    for q in numba.prange(sel_b.shape[0]):
        b = sel_b[q]
        e = sel_e[q]
        base = e * 2 * half
        acc = np.empty(2 * half)
        mx = np.empty(ns)
        for c in range(2 * half):
            acc[c] = 0.0
        for j in range(ne):
            wj = np.float64(w[b, j])
            if wj != 0.0:
                row = A[j, base:base + 2 * half]  # a contiguous view: the loop vectorises (10x)
                for c in range(2 * half):
                    acc[c] += wj * row[c]
        _segment_peaks(acc, mx, ntx, seg, ns, half, abs(np.float64(w[b, e])), env, ne, e, b)


def channel_peaks_into(A: np.ndarray, w: np.ndarray, env: np.ndarray) -> None:
    """Write the segment peaks ``|X_ne|`` of the receive channels of selections ``w`` (B, Ne),
    formed from ``pair_channels`` A, into the first run of the envelopes ``env`` (ntx * Ne, M,
    nS, B) (:meth:`Certificates.envelopes` for a few selections: each channel reads only the rows
    of the elements its selection uses, k^2 of the Ne^2 blocks, where the product
    ``w @ pair_channels`` reads Ne of them per receive element); entries of receive elements a
    selection does not use are left as they are (zero)."""
    sel_b, sel_e = receive_major(w)
    _channel_peaks_kernel(A, w, sel_b, sel_e, env.shape[0] // w.shape[1], env)


@numba.njit(cache=True, nogil=True, inline="always")
def _fma_square(re, im):
    """``re^2 + im^2`` of float32 samples as torch's ``square`` then ``addcmul`` round it: ``im^2``
    rounded to float32, then ``re^2`` added in one rounding (a fused multiply-add), here summed in
    float64 (where ``re^2`` is exact) and rounded to float32."""
    t = im * im
    return np.float32(np.float64(re) * np.float64(re) + np.float64(t))


@numba.njit(parallel=True, cache=True, nogil=True)
def _product_peaks_kernel(y, rows, e0, w, env):
    """``env[n * Ne + e, 0, a, rows[i]] = |w[rows[i], e]| max_r |y[i, e - e0, :, n, r nS + a]|``:
    the segment peaks of the receive products ``y`` (B', g, 2, ntx, T) float32 of the selections
    ``rows`` (B',) int64 on the receive elements ``e0 .. e0 + g - 1`` (segment-offset-major
    samples), in y's precision as torch's square, fused sum, maximum, root and product give them; a NaN
    sample makes its segment's peak NaN. w: (B, Ne) float32; env: (ntx * Ne, M, nS, B) float32. Parallel over
    the selections."""
    g = y.shape[1]
    ntx = y.shape[3]
    ne = w.shape[1]
    ns = env.shape[2]
    seg = y.shape[4] // ns
    for i in numba.prange(y.shape[0]):
        b = rows[i]
        mx = np.empty(ns, dtype=y.dtype)
        for k in range(g):
            e = e0 + k
            scale = abs(w[b, e])
            for n in range(ntx):
                re = y[i, k, 0, n]
                im = y[i, k, 1, n]
                for a in range(ns):
                    mx[a] = _fma_square(re[a], im[a])
                for r in range(1, seg):
                    o = r * ns
                    for a in range(ns):
                        mx[a] = _nan_max(mx[a], _fma_square(re[o + a], im[o + a]))
                for a in range(ns):
                    env[n * ne + e, 0, a, b] = np.sqrt(mx[a]) * scale


def product_peaks_into(y: np.ndarray, rows: np.ndarray, e0: int, w: np.ndarray, env: np.ndarray) -> None:
    """Write the segment peaks of one receive product of :meth:`Certificates._receive_products
    <arraysel.physics.psf.certificate.Certificates._receive_products>` (``y`` (B', g, 2, ntx, T)
    of the selections ``rows`` of ``w`` (B, Ne) on the receive elements from ``e0``) into the
    first run of the envelopes ``env`` (ntx * Ne, M, nS, B): one read of the product, where
    torch's square, sum, maximum, root, product and scatter take six passes."""
    _product_peaks_kernel(y, np.ascontiguousarray(rows, dtype=np.int64), int(e0), w, env)


@numba.njit(parallel=True, cache=True, nogil=True)
def _segment_runs_kernel(env):
    """Runs 2 .. M of the envelopes ``env`` (nch, M, nS, B) from their first run:
    ``env[c, m, a] = max(env[c, m - 1, a], env[c, 0, a + m])`` (``env[c, m - 1, a]`` past the
    end), NaN where either is NaN (torch's ``maximum``). Parallel over the channels."""
    M = env.shape[1]
    ns = env.shape[2]
    B = env.shape[3]
    for c in numba.prange(env.shape[0]):
        for m in range(1, M):
            for a in range(ns):
                prev = env[c, m - 1, a]
                out = env[c, m, a]
                if a + m < ns:
                    nxt = env[c, 0, a + m]
                    for b in range(B):
                        out[b] = _nan_max(prev[b], nxt[b])
                else:
                    for b in range(B):
                        out[b] = prev[b]


def segment_runs(env: np.ndarray) -> None:
    """Fill runs 2 .. M of the envelopes ``env`` (nch, M, nS, B), C-contiguous, in place from
    their first run (:meth:`Certificates._segment_runs
    <arraysel.physics.psf.certificate.Certificates._segment_runs>` in one pass over each channel)."""
    _segment_runs_kernel(env)


@numba.njit(parallel=True, cache=True, nogil=True)
def _row_sums_kernel(A, rows, step, out):
    """``out[c] = sum_{j in rows} A[j, c]`` in float64, parallel over chunks of ``step`` columns
    (each chunk's sums stay in cache while the rows are read)."""
    n = A.shape[1]
    for g in numba.prange((n + step - 1) // step):
        c0 = g * step
        c1 = min(n, c0 + step)
        for c in range(c0, c1):
            out[c] = 0.0
        for j in rows:
            row = A[j, c0:c1]
            for c in range(c1 - c0):
                out[c0 + c] += np.float64(row[c])


def row_sums(A: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """(A.shape[1],) float64 sums of the rows ``rows`` of A (2-D float): a selection's channel
    products ``sum_{j in mask} A_j`` of ``pair_channels`` (:func:`swap_peaks_into`)."""
    out = np.empty(A.shape[1], dtype=np.float64)
    _row_sums_kernel(A, np.ascontiguousarray(rows, dtype=np.int64), 4096, out)
    return out


@numba.njit(parallel=True, cache=True, nogil=True)
def _move_rows_kernel(H, y, G, out, into, pidx, psign, step, res):
    """``res[b] = y - sum_i G[out[b, i]] + sum_i G[into[b, i]] + sum_t psign[b, t] H[pidx[b, t]]``
    (entries ``-1`` of out and into, and terms of sign 0, left out), summed in float64 over chunks
    of ``step`` columns (the chunk's sums stay in cache while the rows are read) and written in
    ``res``'s dtype; parallel over the rows b. H: (P, C) float; y: (C,) float64; G: (Ne, C)
    float64; out, into: (B, m) int64; pidx: (B, T) int64; psign: (B, T) float64; res: (B, C)."""
    B = out.shape[0]
    C = y.shape[0]
    m = out.shape[1]
    nchunk = (C + step - 1) // step
    for q in numba.prange(B * nchunk):
        b = q // nchunk
        c0 = (q % nchunk) * step
        c1 = min(C, c0 + step)
        acc = y[c0:c1].copy()
        for i in range(m):
            if out[b, i] < 0:
                continue
            ga = G[out[b, i], c0:c1]
            gb = G[into[b, i], c0:c1]
            for c in range(c1 - c0):
                acc[c] += gb[c] - ga[c]
        for t in range(pidx.shape[1]):
            sg = psign[b, t]
            if sg == 0.0:
                continue
            row = H[pidx[b, t], c0:c1]
            for c in range(c1 - c0):
                acc[c] += sg * np.float64(row[c])
        for c in range(c1 - c0):
            res[b, c0 + c] = acc[c]


def move_rows(H: np.ndarray, y: np.ndarray, G: np.ndarray, out: np.ndarray, into: np.ndarray, pidx: np.ndarray,
              psign: np.ndarray, dtype=None) -> np.ndarray:
    """(B, C) rows, in ``dtype`` (default ``H``'s), ``y - sum_i G[out[b, i]] + sum_i G[into[b, i]]
    + sum_t psign[b, t] H[pidx[b, t]]`` summed in float64 (entries ``-1`` of out and into, and
    terms of sign 0, left out): the images of a selection's neighbours from its image ``y``
    (C,), its element rows ``G`` (Ne, C) and pair-image rows ``H`` (P, C)
    (:meth:`PairBasis.swap_images <arraysel.physics.psf.basis.PairBasis.swap_images>`); one pass
    over each row read, where numpy's gathers and mixed-precision sums take three."""
    B = out.shape[0]
    res = np.empty((B, y.shape[0]), dtype=H.dtype if dtype is None else dtype)
    _move_rows_kernel(H, np.ascontiguousarray(y, dtype=np.float64), G, np.ascontiguousarray(out, dtype=np.int64),
                      np.ascontiguousarray(into, dtype=np.int64), np.ascontiguousarray(pidx, dtype=np.int64),
                      np.ascontiguousarray(np.broadcast_to(psign, pidx.shape), dtype=np.float64), 2048, res)
    return res


@numba.njit(parallel=True, cache=True, nogil=True)
def _swap_peaks_kernel(A, Y, out, into, sel_b, sel_e, ntx, env):
    """``env[n * Ne + e, 0, a, b] = max_r |Y[e] - sum_i A[out[b, i], e] + sum_i A[into[b, i], e]|``
    (over the samples ``r`` of segment ``a`` of transmit ``n``) for the pairs ``(b, e) =
    (sel_b[q], sel_e[q])``: the segment peaks of receive channel e of the neighbour b of a 0/1
    selection that swaps the m elements ``out[b]`` for the m elements ``into[b]`` (out, into:
    (B, m), ``-1`` for none), from the selection's channel sums over every receive element ``Y`` (Ne, 2 ntx T)
    float64, ``Y[e] = sum_{j in mask} A[j, e]``. A: ``pair_channels`` (as
    :func:`_channel_peaks_kernel`); env: (ntx * Ne, M, nS, B). Each channel is corrected in
    float64 in a buffer that stays in cache (2 m + 1 rows read where summing it afresh reads k);
    parallel over the pairs."""
    ne = Y.shape[0]
    ns = env.shape[2]
    half = Y.shape[1] // 2
    seg = half // (ntx * ns)
    m = out.shape[1]
    for q in numba.prange(sel_b.shape[0]):
        b = sel_b[q]
        e = sel_e[q]
        base = e * 2 * half
        acc = np.empty(2 * half)
        mx = np.empty(ns)
        rowy = Y[e]
        for c in range(2 * half):
            acc[c] = rowy[c]
        for i in range(m):
            if out[b, i] < 0:
                continue
            rowa = A[out[b, i], base:base + 2 * half]
            for c in range(2 * half):
                acc[c] -= np.float64(rowa[c])
        for i in range(m):
            if into[b, i] < 0:
                continue
            rowb = A[into[b, i], base:base + 2 * half]
            for c in range(2 * half):
                acc[c] += np.float64(rowb[c])
        _segment_peaks(acc, mx, ntx, seg, ns, half, 1.0, env, ne, e, b)


@numba.njit(parallel=True, cache=True, nogil=True)
def _swap_channels_kernel(A, Y, out, into, sel_b, sel_e, res):
    """``res[b, e] = Y[e] - sum_i A[out[b, i], e] + sum_i A[into[b, i], e]`` (entries ``-1`` left
    out; summed in float64, written in res's dtype) for the pairs ``(b, e) = (sel_b[q],
    sel_e[q])``: receive channel e of the neighbour b of a selection whose channel sums are Y (the
    layouts of :func:`_swap_peaks_kernel`; res: (B, Ne, 2 ntx T)). Sample by sample: one pass over
    the output, where :func:`_swap_peaks_kernel` adds row by row into a buffer it reduces next.
    Parallel over the pairs."""
    width = Y.shape[1]
    m = out.shape[1]
    for q in numba.prange(sel_b.shape[0]):
        b = sel_b[q]
        e = sel_e[q]
        base = e * width
        rowy = Y[e]
        dst = res[b, e]
        for c in range(width):
            v = rowy[c]
            for i in range(m):
                if out[b, i] >= 0:
                    v -= np.float64(A[out[b, i], base + c])
                if into[b, i] >= 0:
                    v += np.float64(A[into[b, i], base + c])
            dst[c] = v


def swap_channels(A: np.ndarray, Y: np.ndarray, out: np.ndarray, into: np.ndarray, on: np.ndarray) -> np.ndarray:
    """(B, Ne, 2 ntx T) receive channels, in ``A``'s dtype and its samples' order, of the selections
    that switch the elements ``out[b]`` off and ``into[b]`` on ((B, m) int, ``-1`` for none) in a
    selection whose channel sums over every receive element are ``Y`` (Ne, 2 ntx T) float64
    (:func:`swap_peaks_into`), formed on the receive elements each uses (``on`` (B, Ne) bool)
    only: ``2 m + 1`` rows read a channel where the product with ``pair_channels`` reads k. The
    entries of the other receive elements are undefined."""
    on = np.asarray(on, dtype=bool)
    res = np.empty((on.shape[0],) + Y.shape, dtype=A.dtype)
    sel_b, sel_e = (v.astype(np.int64) for v in np.nonzero(on))  # by selection: the writes stay in order
    _swap_channels_kernel(A, Y, np.ascontiguousarray(out, dtype=np.int64), np.ascontiguousarray(into, dtype=np.int64),
                          sel_b, sel_e, res)
    return res


def swap_peaks_into(A: np.ndarray, Y: np.ndarray, mask: np.ndarray, out: np.ndarray, into: np.ndarray,
                    env: np.ndarray) -> None:
    """Write the segment peaks ``|X_ne|`` of the receive channels of the neighbours of the 0/1
    selection ``mask`` (Ne,) bool that swap the elements ``out[b]`` (off) for ``into[b]`` (on)
    (int (B,) for one-swap neighbours, or (B, m): m elements each, ``-1`` for none) into the first run of the
    envelopes ``env`` (ntx * Ne, M, nS, B), from the selection's channel sums ``Y`` (Ne,
    2 ntx T) float64 over every receive element (``Y[e] = sum_{j in mask} A[j, e]``): a
    neighbour's channel is ``Y[e] - sum A[out, e] + sum A[into, e]`` on the receive elements it
    uses (the mask's less ``out``, and ``into``); the entries of the others are left as they are
    (zero). The same values, to rounding, as :func:`channel_peaks_into` of the neighbour masks."""
    out, into = (np.asarray(v, dtype=np.int64) for v in (out, into))
    out, into = (v.reshape(-1, 1) if v.ndim < 2 else v for v in (out, into))
    B = out.shape[0]
    # per neighbour: the receive elements it uses
    on = np.repeat(np.asarray(mask, dtype=bool)[None], B, axis=0)
    for idx, val in ((out, False), (into, True)):
        r, c = np.nonzero(idx >= 0)
        on[r, idx[r, c]] = val
    sel_b, sel_e = receive_major(on)
    _swap_peaks_kernel(A, Y, out, into, sel_b, sel_e, env.shape[0] // Y.shape[0], env)


@numba.njit(parallel=True, cache=True, nogil=True)
def _cut_windows_kernel(img, z0, x0, n, out, norms):
    """Windows ``out[b] = img[b, z0:z0 + n, x0:x0 + n] / top / norm`` with ``top`` the window's
    largest magnitude (1 when zero) and ``norm`` the L2 norm of the window divided by ``top``
    (1 when zero); ``norms[b] = norm * top``. img: (B, h, w, 2) float [re, im]; out: (B, n, n,
    2) of img's dtype; norms: (B,) of img's dtype. Divisions in img's precision, the squared
    norm summed in float64."""
    for b in numba.prange(img.shape[0]):
        zb = z0[b]
        xb = x0[b]
        one = np.ones(2, dtype=img.dtype)
        # the largest squared magnitude in float64 (exact range for float32 images); hypot
        # where the square may have overflowed or underflowed (float64 images beyond 1e+-145,
        # or an all-zero window)
        m2 = 0.0
        for i in range(n):
            row = img[b, zb + i]
            for j in range(n):
                re = np.float64(row[xb + j, 0])
                im = np.float64(row[xb + j, 1])
                m2 = max(m2, re * re + im * im)
        if not 1e-290 < m2 < 1e290:
            top = one[0] * 0
            for i in range(n):
                row = img[b, zb + i]
                for j in range(n):
                    top = max(top, np.hypot(row[xb + j, 0], row[xb + j, 1]))
        else:
            one[1] = np.sqrt(m2)
            top = one[1]
        if not top > 0:
            top = one[0]
        ss = 0.0
        for i in range(n):
            row = img[b, zb + i]
            for j in range(n):
                re = row[xb + j, 0] / top
                im = row[xb + j, 1] / top
                out[b, i, j, 0] = re
                out[b, i, j, 1] = im
                ss += np.float64(re) * np.float64(re) + np.float64(im) * np.float64(im)
        one[1] = np.sqrt(ss)
        norm = one[1]
        nd = norm if norm > 0 else one[0]
        for i in range(n):
            for j in range(n):
                out[b, i, j, 0] = out[b, i, j, 0] / nd
                out[b, i, j, 1] = out[b, i, j, 1] / nd
        norms[b] = norm * top


def cut_windows_compiled(img: np.ndarray, z0: np.ndarray, x0: np.ndarray, n: int):
    """The normalised windows (B, n, n, 2) and their norms (B,) of
    :func:`arraysel.physics.psf.window.cut_windows`, compiled (images without gradient on the
    CPU: one read of each window instead of torch's half-dozen passes). img: (B, h, w, 2) float
    [re, im]; z0, x0: (B,) window offsets."""
    out = np.empty((img.shape[0], n, n, 2), dtype=img.dtype)
    norms = np.empty(img.shape[0], dtype=img.dtype)
    _cut_windows_kernel(np.ascontiguousarray(img), np.ascontiguousarray(z0, dtype=np.int64),
                        np.ascontiguousarray(x0, dtype=np.int64), int(n), out, norms)
    return out, norms


@numba.njit(parallel=True, cache=True, nogil=True)
def _peak_stats_kernel(img, eps2, val, arg, count, cand):
    """Per image of ``img`` (B, N, 2) [re, im]: the largest magnitude ``val`` (img's dtype),
    its first index ``arg``, the pixels ``cand`` (B, N) whose magnitude is at least
    ``val - eps2`` and their number ``count`` (``eps2``: (B,) float64; the threshold formed in
    float64 from the rounded ``val``). Magnitudes compared through their float64 squares
    (exact products of float32 parts). An image with a NaN gets ``val`` NaN and no candidates,
    as torch's maximum and comparison give it."""
    npix = img.shape[1]
    for b in numba.prange(img.shape[0]):
        x = img[b]
        best = -1.0
        at = 0
        nan = False
        for p in range(npix):
            re = np.float64(x[p, 0])
            im = np.float64(x[p, 1])
            v = re * re + im * im
            nan = nan or v != v
            if v > best:
                best = v
                at = p
        arg[b] = at
        if nan:
            val[b] = np.nan
            cand[b] = False
            count[b] = 0
            continue
        val[b] = np.sqrt(best)
        t = np.float64(val[b]) - eps2[b]
        t2 = t * t if t > 0 else -1.0
        n = 0
        for p in range(npix):
            re = np.float64(x[p, 0])
            im = np.float64(x[p, 1])
            c = re * re + im * im >= t2
            cand[b, p] = c
            n += c
        count[b] = n


def peak_stats(img: np.ndarray, eps2: np.ndarray):
    """(val, arg, count, cand) of :func:`_peak_stats_kernel` for images ``img`` (B, N, 2)
    float: the certificates' peak search (:meth:`Refinement._locate`) in one compiled read of
    each image instead of torch's magnitude, maximum, comparison and count."""
    B = img.shape[0]
    val = np.empty(B, dtype=img.dtype)
    arg = np.empty(B, dtype=np.int64)
    count = np.empty(B, dtype=np.int64)
    cand = np.empty((B, img.shape[1]), dtype=np.bool_)
    _peak_stats_kernel(np.ascontiguousarray(img), np.ascontiguousarray(eps2, dtype=np.float64), val, arg, count,
                       cand)
    return val, arg, count, cand
