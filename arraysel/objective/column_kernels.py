"""The compiled pass of a 3-D neighbourhood's block of swaps (:mod:`arraysel.objective.matrix_neighbours`).

A block's batched product gives, per pixel, the cross terms ``X`` of its outgoing elements against
every element. The image of the swap ``(a off, e on)`` at pixel ``p`` is then
``u_e(p) + v_a(p) - X_ae(p)`` (``u_e = S_e + D_e``, ``v_a = img - S_a + D_a``), and what the metrics
read of it is ``|img|^2`` and the sums ``<k, k>`` and ``<k, r>`` against the reference.
:func:`block_power` forms them in one pass over a chunk of pixels, straight into the rows of the
neighbours' ``|img|^2`` (one row per neighbour, the layout the metrics take), so the block's images
are never written out, negated, gathered or transposed. Sums are accumulated in float64.
"""
from __future__ import annotations

import numba
import numpy as np

from arraysel.io.numba_cache import ensure_cache_dir
from arraysel.objective.metric_kernels import _heap_keep

ensure_cache_dir(__file__)  # a place numba can cache the kernels in, also for a user who cannot write here

__all__ = ["block_power", "lobe_sums", "peaks"]

#: fast-math flags of the float64 sums: reordered and contracted, NaN and Inf kept
_SUMS = {"reassoc", "contract", "nsz"}


@numba.njit(cache=True, nogil=True, fastmath=_SUMS)
def block_power(X, first, ur, ui, vr, vi, rr, ri, ai, ei, p0, k2, sums):
    """For the neighbours ``i`` (the swaps ``ai[i]`` of the block off, element ``ei[i]`` on) and the
    chunk's pixels ``p`` (rows ``p0 + p`` of the images): ``k2[i, p0 + p] = re^2 + im^2`` of
    ``re = ur[p, e] + vr[p, a] - X[p, 0, first + a, e]`` (``im`` alike from ``ui``, ``vi``, ``X[p, 1]``),
    and adds to ``sums[i]`` the chunk's ``<k, k>``, ``Re <k, r>`` and ``Im <k, r>`` (``<k, r> =
    sum k conj(r)``, reference ``rr + i ri``). ``X`` (c, 2, rows, Ne); ``ur``, ``ui`` (c, Ne);
    ``vr``, ``vi`` (c, A); ``rr``, ``ri`` (c,)."""
    c = X.shape[0]
    for i in range(ai.shape[0]):
        a = ai[i]
        e = ei[i]
        ax = a + first
        kk = 0.0
        kre = 0.0
        kim = 0.0
        for p in range(c):
            re = ur[p, e] + vr[p, a] - X[p, 0, ax, e]
            im = ui[p, e] + vi[p, a] - X[p, 1, ax, e]
            v = re * re + im * im
            k2[i, p0 + p] = v
            kk += v
            r0 = np.float64(rr[p])
            r1 = np.float64(ri[p])
            kre += r0 * re + r1 * im
            kim += r1 * re - r0 * im
        sums[i, 0] += kk
        sums[i, 1] += kre
        sums[i, 2] += kim


@numba.njit(cache=True, nogil=True, fastmath=_SUMS)
def _masked_sums(row, main, side):
    """float64 sums of ``row`` over the 0/1 weights ``main`` and ``side``."""
    s_main = 0.0
    s_side = 0.0
    for j in range(row.shape[0]):
        v = np.float64(row[j])
        s_main += v * main[j]
        s_side += v * side[j]
    return s_main, s_side


@numba.njit(cache=True, nogil=True)
def lobe_sums(k2, rows, main, side, side_idx, m, s_main, s_side, top):
    """For the rows ``rows`` of ``k2`` (M, N) (the images whose peaks share one position): the
    float64 sums over the main and side regions (0/1 weights ``main``, ``side`` (N,)) into
    ``s_main``, ``s_side``, and the ``m`` largest side values (pixels ``side_idx``), largest
    first, into ``top`` (len(rows), m), kept in a min-heap while the side is read."""
    heap = np.empty(max(m, 1), dtype=k2.dtype)
    for t in range(rows.shape[0]):
        row = k2[rows[t]]
        a, b = _masked_sums(row, main, side)
        s_main[t] = a
        s_side[t] = b
        size = 0
        thr = -np.inf          # the heap's least once it is full: most values fall below it
        for j in range(side_idx.shape[0]):
            v = row[side_idx[j]]
            if v > thr or size < m:
                size = _heap_keep(heap, size, m, v)
                if size == m:
                    thr = heap[0]
        srt = np.sort(heap[:size])
        for j in range(size):
            top[t, j] = srt[size - 1 - j]


@numba.njit(cache=True, nogil=True)
def peaks(k2, crows, peak_val, peak, c_peak):
    """Per row of ``k2`` (M, N): its largest value ``peak_val`` and the first column holding it
    ``peak`` (as ``torch.max``), and, when ``crows`` (the columns of the C-plane's pixels, in the
    plane's order) is not empty, the first C-plane pixel holding the plane's largest value
    ``c_peak`` (as ``torch.argmax`` over the gathered plane)."""
    n_c = crows.shape[0]
    for t in range(k2.shape[0]):
        row = k2[t]
        best = row[0]
        at = 0
        for j in range(1, row.shape[0]):
            v = row[j]
            if v > best or (v != v and best == best):    # a NaN wins, as in torch
                best = v
                at = j
        peak_val[t] = best
        peak[t] = at
        if n_c:
            cb = row[crows[0]]
            ci = 0
            for f in range(1, n_c):
                v = row[crows[f]]
                if v > cb or (v != v and cb == cb):
                    cb = v
                    ci = f
            c_peak[t] = ci
