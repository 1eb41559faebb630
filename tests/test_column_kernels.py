"""The compiled passes of a 3-D neighbourhood's blocks (arraysel.objective.column_kernels) against
the torch operations they stand for: the swaps' |img|^2 and sums, the peaks, and the lobes' sums
and largest side values (heap seeded anywhere, ties, a zero image)."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from arraysel.objective.column_kernels import block_power, lobe_sums, peaks


@pytest.mark.parametrize("first", [0, 1])
def test_block_power_forms_each_swap_and_its_sums(first):
    rng = np.random.default_rng(first)
    c, A, ne, p0, n_pix = 7, 3, 11, 5, 20
    X = rng.standard_normal((c, 2, first + A, ne))
    ur, ui = rng.standard_normal((c, ne)), rng.standard_normal((c, ne))
    vr, vi = rng.standard_normal((c, A)), rng.standard_normal((c, A))
    rr, ri = rng.standard_normal(c), rng.standard_normal(c)
    rows = np.full((A, ne), -1, dtype=np.int64)
    ai, ei = np.array([0, 0, 2, 1, 2]), np.array([3, 10, 0, 4, 7])
    rows[ai, ei] = np.arange(ai.size)
    k2 = np.full((ai.size, n_pix), -1.0)
    acc = np.zeros((3, A, ne))
    block_power(X, first, ur, ui, vr, vi, rr, ri, rows, p0, k2, acc, np.empty((c, ne)))
    img = ur[:, None, :] + vr[:, :, None] - X[:, 0, first:] + 1j * (ui[:, None, :] + vi[:, :, None] - X[:, 1, first:])
    ref = rr + 1j * ri
    for i, (a, e) in enumerate(zip(ai, ei)):
        k = img[:, a, e]
        np.testing.assert_allclose(k2[i, p0:p0 + c], np.abs(k) ** 2, rtol=1e-12)
        assert (k2[i, :p0] == -1).all() and (k2[i, p0 + c:] == -1).all()
        kr = np.sum(np.conj(k) * ref)
        np.testing.assert_allclose(acc[:, a, e], [np.sum(np.abs(k) ** 2), kr.real, kr.imag], rtol=1e-12)


def test_peaks_are_torch_max_and_argmax_of_the_plane():
    rng = np.random.default_rng(3)
    k2 = rng.random((6, 40)).astype(np.float32)
    k2[1] = 0.0                      # all equal: the first
    k2[2, [5, 30]] = 2.0             # a tie: the first
    crows = rng.permutation(40)[:15].astype(np.int64)
    k2[3, crows[[4, 9]]] = 3.0       # a tie in the plane: the first in the plane's order
    pv, pk, cpk = np.empty(6, np.float32), np.empty(6, np.int64), np.empty(6, np.int64)
    peaks(k2, crows, pv, pk, cpk)
    tv, tk = torch.max(torch.from_numpy(k2), 1)
    np.testing.assert_array_equal(pv, tv.numpy())
    np.testing.assert_array_equal(pk, tk.numpy())
    np.testing.assert_array_equal(cpk, torch.argmax(torch.from_numpy(k2[:, crows]), 1).numpy())


@pytest.mark.parametrize("m", [0, 1, 5, 17])
def test_lobe_sums_keep_the_largest_side_values(m):
    rng = np.random.default_rng(m)
    n = 300
    k2 = (rng.random((9, n)) ** 6).astype(np.float32)
    k2[4] = 0.0                                        # a zero image
    k2[5, :40] = 0.5                                   # ties among the largest
    main = (rng.random(n) < 0.1).astype(np.float64)
    side = (rng.random(n) < 0.6).astype(np.float64)
    side_idx = np.flatnonzero(side)
    rows = np.array([8, 0, 2, 4, 5, 7], dtype=np.int64)
    seeds = rng.choice(side_idx, m, replace=False).astype(np.int64)    # any side pixels will do
    free = side.astype(np.float32)
    free[seeds] = 0
    s_main, s_side, top = np.empty(rows.size), np.empty(rows.size), np.empty((rows.size, max(m, 1)))
    lobe_sums(k2, rows, main, side, seeds, free, m, s_main, s_side, top)
    sub = k2[rows].astype(np.float64)
    np.testing.assert_allclose(s_main, sub @ main, rtol=1e-12)
    np.testing.assert_allclose(s_side, sub @ side, rtol=1e-12)
    if m:
        want = torch.topk(torch.from_numpy(k2[rows][:, side_idx]), m, dim=1).values.double().numpy()
        np.testing.assert_array_equal(top[:, :m], want)
