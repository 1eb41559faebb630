"""The Table-1 metrics of a batch of complex PSF kernels in one compiled pass per kernel.

:func:`arraysel.objective.metrics.psf_metrics` is written with torch so that it runs on any
device and carries gradients. Scoring masks needs neither, and there torch's dozen passes over
the batch (scale, ``|kappa|^2``, peak, three dot products, the residual, the regions gathered per
kernel, a ``topk`` for the quantile) cost more than the kernels themselves on the paper scene.
:func:`psf_metrics_compiled` computes the same quantities, with the same conventions, in three
passes over each kernel, kernels in parallel:

1. the kernel's scale ``s = max(|Re|, |Im|)`` (1 for a zero kernel);
2. ``k2 = (Re/s)^2 + (Im/s)^2`` in the kernel's precision (the values torch ranks, so the peak
   and the quantile's order statistics are the same pixels), its first maximum (the peak),
   ``<k, k>`` and ``<k, r>`` against the scaled reference ``r``;
3. around the peak: the residual ``|a k - r|^2`` of SI-MSE, the sums of ``k2`` over the main
   and side regions (read from the offset tables of
   :func:`arraysel.objective.metrics._offset_tables`), and the side values' two order
   statistics of the quantile, kept in a min-heap of the largest values (for ``q = 0.99`` about
   1 % of the side).

Sums are accumulated in float64 and the results rounded to the kernel's real dtype, so they
agree with the torch path to its own rounding (float32 sums of 16384 terms; the tests compare
the two). Everything here works on numpy arrays; the caller converts.
"""
from __future__ import annotations

import math

import numba
import numpy as np

from arraysel.io.numba_cache import ensure_cache_dir

ensure_cache_dir(__file__)  # a place numba can cache the kernels in, also for a user who cannot write here


#: fast-math flags of the float64 sums: reordered (so that they vectorise) and contracted, but
#: NaN and Inf kept (a non-finite kernel gives NaN metrics, as the torch path does)
_SUMS = {"reassoc", "contract", "nsz"}


@numba.njit(cache=True, nogil=True)
def _heap_keep(heap, size, m, v):
    """Offer ``v`` to the min-heap ``heap[:size]`` that keeps the ``m`` largest values seen;
    returns the new size."""
    if size < m:
        j = size
        while j > 0:
            parent = (j - 1) // 2
            if heap[parent] <= v:
                break
            heap[j] = heap[parent]
            j = parent
        heap[j] = v
        return size + 1
    if v > heap[0]:
        j = 0
        while True:
            c = 2 * j + 1
            if c >= m:
                break
            if c + 1 < m and heap[c + 1] < heap[c]:
                c += 1
            if heap[c] >= v:
                break
            heap[j] = heap[c]
            j = c
        heap[j] = v
    return size


@numba.njit(cache=True, nogil=True)
def _scaled(xf, qf, k2):
    """The kernel ``xf`` (2 N,) [re, im interleaved] divided by its scale ``s = max |xf|`` into
    ``qf`` (1 for a zero kernel), and ``k2 = Re^2 + Im^2`` of ``qf``: in the kernel's own
    precision, operation for operation as torch forms them (no fast-math: ``k2`` is ranked)."""
    s = np.abs(xf).max()
    if not s > 0:
        s = np.ones(1, dtype=xf.dtype)[0]
    for i in range(xf.shape[0]):
        qf[i] = xf[i] / s
    for p in range(k2.shape[0]):
        k2[p] = qf[2 * p] * qf[2 * p] + qf[2 * p + 1] * qf[2 * p + 1]


@numba.njit(cache=True, nogil=True, fastmath=_SUMS)
def _dots(qf, rf, rsf):
    """float64 ``<k, k>`` and ``<k, r>`` (real, imaginary) of the scaled kernel ``qf`` and the
    reference ``rf`` (``rsf``: the reference as ``(Im, -Re)`` pairs), all (2 N,) interleaved."""
    kk = 0.0
    krr = 0.0
    kri = 0.0
    for i in range(qf.shape[0]):
        v = np.float64(qf[i])
        kk += v * v
        krr += v * np.float64(rf[i])
        kri += v * np.float64(rsf[i])
    return kk, krr, kri


@numba.njit(cache=True, nogil=True, fastmath=_SUMS)
def _residual(qf, rf, ar, ai):
    """float64 ``|a k - r|^2`` of the scaled kernel ``qf``, formed term by term (so that it
    reaches 0 to rounding when ``k`` is a multiple of ``r``)."""
    resid = 0.0
    for p in range(qf.shape[0] // 2):
        re = np.float64(qf[2 * p])
        im = np.float64(qf[2 * p + 1])
        dr = ar * re - ai * im - np.float64(rf[2 * p])
        di = ar * im + ai * re - np.float64(rf[2 * p + 1])
        resid += dr * dr + di * di
    return resid


@numba.njit(cache=True, nogil=True, fastmath=_SUMS)
def _row_sums(k2row, mrow, srow):
    """float64 sums of one kernel row ``k2row`` over its main and side table rows (0/1)."""
    s_main = 0.0
    s_side = 0.0
    for j in range(k2row.shape[0]):
        v = np.float64(k2row[j])
        s_main += v * mrow[j]
        s_side += v * srow[j]
    return s_main, s_side


@numba.njit(cache=True, nogil=True)
def _regions(k2, h, w, r0, c0, tmain, tside, heap, m):
    """Sums of ``k2`` (h w,) over the main and side regions of a kernel whose peak puts its
    pixel (i, j) at offset-table entry (r0 + i, c0 + j); the min-heap ``heap`` receives the
    ``m`` largest side values (``m = 0``: none wanted)."""
    s_main = 0.0
    s_side = 0.0
    size = 0
    for i in range(h):
        k2row = k2[i * w:(i + 1) * w]
        srow = tside[r0 + i, c0:c0 + w]
        a, c = _row_sums(k2row, tmain[r0 + i, c0:c0 + w], srow)
        s_main += a
        s_side += c
        if m > 0:
            for j in range(w):
                if srow[j] and (size < m or k2row[j] > heap[0]):
                    size = _heap_keep(heap, size, m, k2row[j])
    return s_main, s_side


@numba.njit(parallel=True, cache=True, nogil=True)
def _metrics_kernel(k, ref, ref_swap, rr, h, w, tmain, tside, nmain, nside, q, out):
    """Metrics of the kernels ``k`` (B, 2 h w) [re, im interleaved] against one scaled reference
    ``ref`` (2 h w,) of squared norm ``rr`` (``ref_swap``: its (Im, -Re) pairs).

    tmain, tside: (2h - 1, 2w - 1) uint8 region tables over offsets from the peak; nmain,
    nside: their summed-area tables ((2h) x (2w), zero first row and column), which count a
    kernel's region pixels without a pass; q: the side-lobe quantile. out: (B, 4) float64
    L_PSF, L_contrast, L_SLR_q, L_SLR_i.
    """
    nb = k.shape[0]
    npix = k.shape[1] // 2
    for b in numba.prange(nb):
        xf = k[b]
        # scalars in the kernel's precision (numba would widen a float32 mixed with a literal)
        cast = np.empty(2, dtype=xf.dtype)
        cast[0] = 0.0
        # 1. the scaled kernel and k2 (as torch forms them), k2's first maximum
        qf = np.empty(2 * npix, dtype=xf.dtype)
        k2 = np.empty(npix, dtype=xf.dtype)
        _scaled(xf, qf, k2)
        best = k2.max()
        if not best == best:
            # a NaN or Inf entry: every metric NaN
            for t in range(4):
                out[b, t] = np.nan
            continue
        arg = 0
        while k2[arg] != best:
            arg += 1
        # 2. SI-MSE: a = <k, r> / <k, k> (0 for a kernel whose <k, k> underflows), |a k - r|^2
        kk, krr, kri = _dots(qf, ref, ref_swap)
        if kk > np.finfo(xf.dtype).tiny:
            ar = krr / kk
            ai = kri / kk
        else:
            ar = 0.0
            ai = 0.0
        out[b, 0] = _residual(qf, ref, ar, ai) / rr if rr != 0 else 0.0
        # 3. the regions around the peak: rows h-1-i0 .. 2h-2-i0 of the tables, same for columns;
        # the quantile's ascending ranks lo <= hi (as torch.quantile) come from a min-heap of the
        # m largest side values: its root is rank lo, the smaller child of the root rank lo + 1
        i0 = arg // w
        r0 = h - 1 - i0
        c0 = w - 1 - (arg - i0 * w)
        n_main = nmain[r0 + h, c0 + w] - nmain[r0, c0 + w] - nmain[r0 + h, c0] + nmain[r0, c0]
        n_side = nside[r0 + h, c0 + w] - nside[r0, c0 + w] - nside[r0 + h, c0] + nside[r0, c0]
        pos = q * (max(n_side, 1) - 1)
        lo = int(math.floor(pos))
        hi = int(math.ceil(pos))
        m = n_side - lo if n_side > 0 else 0
        heap = np.empty(max(m, 1), dtype=xf.dtype)
        s_main, s_side = _regions(k2, h, w, r0, c0, tmain, tside, heap, m)
        c_side = s_side / n_side if n_side > 0 else 0.0
        c_main = s_main / n_main if n_main > 0 else 0.0
        out[b, 1] = c_side / c_main if c_main != 0 else 0.0
        out[b, 3] = s_side / s_main if s_main != 0 else 0.0
        # 4. the side quantile, interpolated
        qs = cast[0]
        if n_side > 0:
            v_lo = heap[0]
            v_hi = v_lo
            if hi > lo:
                v_hi = heap[1]
                if m > 2 and heap[2] < v_hi:
                    v_hi = heap[2]
            # in the kernel's precision, as torch: the square roots of the two order statistics,
            # then the interpolation
            cast[1] = pos - lo
            sl = np.sqrt(v_lo) if v_lo > 0 else cast[0]
            sh = np.sqrt(v_hi) if v_hi > 0 else cast[0]
            qs = sl + cast[1] * (sh - sl)
        peak = np.sqrt(best) if best > 0 else cast[0]
        out[b, 2] = qs / peak if peak != 0 else 0.0


def psf_metrics_compiled(k: np.ndarray, ref: np.ndarray, rr: float, shape: tuple[int, int],
                         tmain: np.ndarray, tside: np.ndarray, q: float) -> np.ndarray:
    """(B, 4) float64 L_PSF, L_contrast, L_SLR_q, L_SLR_i of the kernels ``k`` (B, h w, 2)
    float32 or float64 [re, im], against the reference ``ref`` (h w, 2) of the same dtype,
    already divided by its scale, whose squared norm is ``rr``; ``tmain``, ``tside``: the
    (2h - 1, 2w - 1) boolean region tables over offsets from the peak."""
    h, w = shape
    tm = np.ascontiguousarray(tmain, dtype=np.uint8)
    ts = np.ascontiguousarray(tside, dtype=np.uint8)
    nm = np.zeros((2 * h, 2 * w), dtype=np.int64)
    ns = np.zeros((2 * h, 2 * w), dtype=np.int64)
    nm[1:, 1:] = tm.cumsum(0).cumsum(1)
    ns[1:, 1:] = ts.cumsum(0).cumsum(1)
    ref = np.ascontiguousarray(ref)
    swap = np.stack([ref[:, 1], -ref[:, 0]], axis=1)
    out = np.empty((k.shape[0], 4), dtype=np.float64)
    _metrics_kernel(np.ascontiguousarray(k).reshape(k.shape[0], -1), ref.reshape(-1), swap.reshape(-1),
                    float(rr), h, w, tm, ts, nm, ns, float(q), out)
    return out
