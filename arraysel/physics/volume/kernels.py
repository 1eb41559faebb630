"""The compiled (numba) delay-and-sum of the exact 3-D PSF for batches without gradient.

Same sums as the torch path of :meth:`~arraysel.physics.volume.psf.MatrixPSF.image` (linear
interpolation of the I/Q samples at ``tx_pos + rx_pos``, rotated by ``tx_rot * rx_rot``,
samples outside ``[0, n_time - 2]`` skipped), read once instead of in torch's dozen passes over
(pixels x elements) temporaries; parallel over pixels; the batch is the innermost, contiguous
axis. Cached on disk like :mod:`arraysel.physics.pairkernels`.
"""
from __future__ import annotations

import numba
import numpy as np

from arraysel.io.numba_cache import ensure_cache_dir

ensure_cache_dir(__file__)  # a place numba can cache the kernels in, also for a user who cannot write here


#: pixels a thread accumulates together: for each (transmit, element) it reads that element's
#: I/Q row once (it stays in the first-level cache) for all of them
PIXEL_BLOCK = 64


@numba.njit(parallel=True, cache=True, fastmath=False)
def das3(iq, rows, tx_pos, rx_pos_t, tx_rot, rx_rot_t, s0, n_time, out):
    """iq (n_tx, E, T, B) complex; rows (E,) int64: the rows of the receive geometry of those E
    elements; tx_pos, tx_rot (n_tx, P); rx_pos_t, rx_rot_t (Ne, P); s0, n_time (n_tx,) int64;
    out (P, B) complex, accumulated into. Parallel over blocks of
    :data:`PIXEL_BLOCK` pixels; within a block, transmit by transmit and element by element."""
    n_tx, n_e, _, n_b = iq.shape
    n_p = rx_pos_t.shape[1]
    n_blocks = (n_p + PIXEL_BLOCK - 1) // PIXEL_BLOCK
    for blk in numba.prange(n_blocks):
        p0 = blk * PIXEL_BLOCK
        p1 = min(n_p, p0 + PIXEL_BLOCK)
        for t in range(n_tx):
            hi = n_time[t] - 2
            st = s0[t]
            for e in range(n_e):
                row = rows[e]
                for p in range(p0, p1):
                    pos = tx_pos[t, p] + rx_pos_t[row, p]
                    if pos < 0 or pos > hi:
                        continue
                    x = pos - st
                    i0 = int(np.floor(x))
                    w = x - i0
                    r = tx_rot[t, p] * rx_rot_t[row, p]
                    for b in range(n_b):
                        a = iq[t, e, i0, b]
                        out[p, b] += r * (a + w * (iq[t, e, i0 + 1, b] - a))


@numba.njit(parallel=True, cache=True, fastmath=False)
def das3_adjoint(g, rows, tx_pos, rx_pos_t, tx_rot, rx_rot_t, s0, n_time, giq):
    """The adjoint of :func:`das3` (the gradient with respect to the I/Q samples, torch's
    conjugate convention): g (P, B) complex, the other arguments as for :func:`das3`;
    giq (n_tx, E, T, B) complex, accumulated into. Parallel over elements (each writes its rows)."""
    n_tx, n_e, _, n_b = giq.shape
    n_p = g.shape[0]
    for e in numba.prange(n_e):
        row = rows[e]
        for t in range(n_tx):
            hi = n_time[t] - 2
            st = s0[t]
            for p in range(n_p):
                pos = tx_pos[t, p] + rx_pos_t[row, p]
                if pos < 0 or pos > hi:
                    continue
                x = pos - st
                i0 = int(np.floor(x))
                w = x - i0
                r = np.conj(tx_rot[t, p] * rx_rot_t[row, p])
                for b in range(n_b):
                    v = r * g[p, b]
                    giq[t, e, i0, b] += v * (1.0 - w)
                    giq[t, e, i0 + 1, b] += v * w
