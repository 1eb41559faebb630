"""The compiled (numba) combination of the beam pattern's frequencies, forward and backward.

:class:`~arraysel.physics.beampattern.BeamPattern` computes, for every frequency ``f`` and
pixel ``x``, the real and imaginary parts of the transmit and receive array factors; the energy
pattern is ``I[x] = sum_f w_f |T_f[x]|^2 |R_f[x]|^2``. torch's operations read and write those
(F, X) arrays half a dozen times; these kernels read them once, in parallel over the pixels, and
write ``I`` (or, backward, the gradients of the four arrays). Cached on disk like the other
compiled kernels (:mod:`arraysel.physics.compiled`).
"""
from __future__ import annotations

import numba

#: the arrays are (F, V, X): frequencies, rows of the half grid, (selection, column) pairs; the
#: output (V, X). Threads share the rows.


@numba.njit(parallel=True, cache=True, fastmath=False)
def energy_shared(tre, tim, w, out):
    """out[v, x] = sum_f w[f] (tre[f, v, x]^2 + tim[f, v, x]^2)^2."""
    n_f, n_v, n_x = tre.shape
    for v in numba.prange(n_v):
        for x in range(n_x):
            out[v, x] = 0.0
        for f in range(n_f):
            wf = w[f]
            for x in range(n_x):
                p = tre[f, v, x] * tre[f, v, x] + tim[f, v, x] * tim[f, v, x]
                out[v, x] += wf * p * p


@numba.njit(parallel=True, cache=True, fastmath=False)
def energy_shared_grad(tre, tim, w, g, gre, gim):
    """The gradients (F, V, X) of ``sum g * out`` (:func:`energy_shared`) with respect to tre
    and tim: ``4 w[f] g |T|^2 (tre, tim)``."""
    n_f, n_v, n_x = tre.shape
    for v in numba.prange(n_v):
        for f in range(n_f):
            wf = 4.0 * w[f]
            for x in range(n_x):
                c = wf * g[v, x] * (tre[f, v, x] * tre[f, v, x] + tim[f, v, x] * tim[f, v, x])
                gre[f, v, x] = c * tre[f, v, x]
                gim[f, v, x] = c * tim[f, v, x]


@numba.njit(parallel=True, cache=True, fastmath=False)
def energy_pair(tre, tim, rre, rim, w, out):
    """out[v, x] = sum_f w[f] |T_f[v, x]|^2 |R_f[v, x]|^2."""
    n_f, n_v, n_x = tre.shape
    for v in numba.prange(n_v):
        for x in range(n_x):
            out[v, x] = 0.0
        for f in range(n_f):
            wf = w[f]
            for x in range(n_x):
                pt = tre[f, v, x] * tre[f, v, x] + tim[f, v, x] * tim[f, v, x]
                pr = rre[f, v, x] * rre[f, v, x] + rim[f, v, x] * rim[f, v, x]
                out[v, x] += wf * pt * pr


@numba.njit(parallel=True, cache=True, fastmath=False)
def energy_pair_grad(tre, tim, rre, rim, w, g, gtre, gtim, grre, grim):
    """The gradients (F, V, X) of ``sum g * out`` (:func:`energy_pair`) with respect to the four
    arrays."""
    n_f, n_v, n_x = tre.shape
    for v in numba.prange(n_v):
        for f in range(n_f):
            wf = 2.0 * w[f]
            for x in range(n_x):
                pt = tre[f, v, x] * tre[f, v, x] + tim[f, v, x] * tim[f, v, x]
                pr = rre[f, v, x] * rre[f, v, x] + rim[f, v, x] * rim[f, v, x]
                ct = wf * g[v, x] * pr
                cr = wf * g[v, x] * pt
                gtre[f, v, x] = ct * tre[f, v, x]
                gtim[f, v, x] = ct * tim[f, v, x]
                grre[f, v, x] = cr * rre[f, v, x]
                grim[f, v, x] = cr * rim[f, v, x]
