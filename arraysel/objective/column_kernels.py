"""The compiled passes of a 3-D neighbourhood's blocks of swaps (:mod:`arraysel.objective.matrix_neighbours`).

A block's batched product gives, per pixel, the cross terms ``X`` of its outgoing elements against
every element. The image of the swap ``(a off, e on)`` at pixel ``p`` is then
``u_e(p) + v_a(p) - X_ae(p)`` (``u_e = S_e + D_e``, ``v_a = img - S_a + D_a``), and what the metrics
read of it is ``|img|^2`` and the sums ``<k, k>`` and ``<k, r>`` against the reference.

* :func:`block_power` forms them for a chunk of pixels along the contiguous element rows of ``X``
  (vectorised, float64 sums) and writes ``|img|^2`` of the swaps asked for into one row per
  neighbour (the layout the metrics take), so the block's images are never written out whole,
  negated, gathered or transposed by torch;
* :func:`peaks` finds each row's peak and the C-plane's peak in one pass (as ``torch.max`` and
  ``torch.argmax``: the first of equal values);
* :func:`lobe_sums` sums the main and side regions and keeps the side's largest values (the
  quantile's order statistics) in a min-heap seeded with the pixels largest in a first image, so
  that most of the side is only compared with the heap's least, a span at a time.

:class:`~arraysel.objective.columns3d.ColumnMetrics` calls the last two for every 3-D neighbourhood;
``tests/test_column_kernels.py`` checks them against the torch operations.
"""
from __future__ import annotations

import numba
import numpy as np

from arraysel.io.numba_cache import ensure_cache_dir
from arraysel.objective.metric_kernels import _heap_keep, _row_sums

ensure_cache_dir(__file__)  # a place numba can cache the kernels in, also for a user who cannot write here

__all__ = ["block_power", "lobe_sums", "peaks"]

#: fast-math flags of the float64 sums: reordered and contracted, NaN and Inf kept
_SUMS = {"reassoc", "contract", "nsz"}


@numba.njit(cache=True, nogil=True, fastmath=_SUMS)
def block_power(X, first, ur, ui, vr, vi, rr, ri, rows, p0, k2, sums, tile):
    """For the swaps ``(a off, e on)`` of the block and the chunk's pixels ``p`` (rows ``p0 + p`` of
    the images): ``re = ur[p, e] + vr[p, a] - X[p, 0, first + a, e]`` (``im`` alike from ``ui``,
    ``vi``, ``X[p, 1]``); adds the chunk's ``<k, k>``, ``Re <k, r>``, ``Im <k, r>`` (``<k, r> =
    sum conj(k) r``, reference ``rr + i ri``) to ``sums[:, a, e]`` for every ``e`` (one pass along
    the contiguous rows, vectorised), and writes ``|img|^2`` of the swaps asked for (``rows[a, e]``
    >= 0: the neighbour's row of ``k2``) into ``k2[rows[a, e], p0 + p]``, through the chunk's
    ``tile`` (c, Ne). ``X`` (c, 2, first + A, Ne); ``ur``, ``ui`` (c, Ne); ``vr``, ``vi`` (c, A);
    ``rr``, ``ri`` (c,); ``sums`` float64 (3, A, Ne)."""
    c = X.shape[0]
    ne = X.shape[3]
    for a in range(rows.shape[0]):
        kk = sums[0, a]
        kre = sums[1, a]
        kim = sums[2, a]
        for p in range(c):
            xr = X[p, 0, first + a]
            xi = X[p, 1, first + a]
            u0 = ur[p]
            u1 = ui[p]
            t = tile[p]
            v0 = vr[p, a]
            v1 = vi[p, a]
            r0 = np.float64(rr[p])
            r1 = np.float64(ri[p])
            for e in range(ne):
                re = u0[e] + v0 - xr[e]
                im = u1[e] + v1 - xi[e]
                v = re * re + im * im
                t[e] = v
                kk[e] += v
                kre[e] += r0 * re + r1 * im
                kim[e] += r1 * re - r0 * im
        for e0 in range(0, ne, 16):        # 16 elements at a time: their rows' lines stay in cache
            e1 = min(ne, e0 + 16)
            for p in range(c):
                t = tile[p]
                for e in range(e0, e1):
                    i = rows[a, e]
                    if i >= 0:
                        k2[i, p0 + p] = t[e]


#: pixels per span whose largest value :func:`lobe_sums` compares with the heap's least first
_SPAN = 16


@numba.njit(cache=True, nogil=True, fastmath=_SUMS)
def _span_max(row, weights, s0, s1):
    """The largest of ``row[j] * weights[j]`` over ``s0 <= j < s1`` (``row >= 0``; 0 when empty)."""
    best = row[s0] * weights[s0]
    for j in range(s0 + 1, s1):
        best = max(best, row[j] * weights[j])
    return best


@numba.njit(cache=True, nogil=True)
def lobe_sums(k2, rows, main, side, seeds, free, m, s_main, s_side, top):
    """For the rows ``rows`` of ``k2`` (M, N) (``|img|^2 >= 0`` of images whose peaks share one
    position): the float64 sums over the main and side regions (0/1 weights ``main``, ``side``
    (N,)) into ``s_main``, ``s_side``, and the ``m`` largest side values, largest first, into
    ``top`` (len(rows), m). The heap of the largest values starts from the ``m`` side pixels
    ``seeds`` (those likely largest), then takes the other side pixels (0/1 ``free``, row type)
    above its least, read a span at a time: a span whose largest value is below it is skipped."""
    heap = np.empty(max(m, 1), dtype=k2.dtype)
    n = k2.shape[1]
    for t in range(rows.shape[0]):
        row = k2[rows[t]]
        a, b = _row_sums(row, main, side)
        s_main[t] = a
        s_side[t] = b
        if m == 0:
            continue
        size = 0
        for j in range(m):
            size = _heap_keep(heap, size, m, row[seeds[j]])
        for s0 in range(0, n, _SPAN):
            s1 = min(n, s0 + _SPAN)
            if not _span_max(row, free, s0, s1) <= heap[0]:
                for j in range(s0, s1):
                    if free[j] > 0 and not row[j] <= heap[0]:
                        size = _heap_keep(heap, size, m, row[j])
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
