"""The fast path's scalable build (issue 17): windowed channels, the sketched compression of
the pair images used for probes with many elements, and the build without strips.

Small grids keep these tests fast; the sketch and the strip-free path are forced on small
probes by lowering their thresholds, and a 128-element probe is built on a tiny grid."""
import math

import numpy as np
import pytest
import torch

from arraysel.objective.metrics import si_mse
from arraysel.physics.probes import Acquisition, get_probe
from arraysel.physics.psf import PairBasis, PSFModel, PSFSetup
from arraysel.physics.psf.build import BasisBuilder
from arraysel.physics.psf.certificate import Certificates
from arraysel.physics.psf.refinement import Refinement


def _setup(n_elements=8, probe="P4-2v", fc=3.5e6, n=24, pixel=1e-4, depth=2e-3, window=8):
    p = get_probe(probe, fc=fc, n_elements=n_elements)
    z_offset = max(0, int(round(depth / pixel)) - n // 2)
    return PSFSetup(probe=p, acq=Acquisition.for_probe(p), tilts=(-0.1, 0.1), n_x=n, n_z=n, pixel=pixel,
                    z_offset=z_offset, window=window, scatterer=(0.0, depth))


def _weights(n, count, seed=0):
    rng = np.random.default_rng(seed)
    return torch.tensor(rng.uniform(0.1, 1, size=(count, n)))


@pytest.fixture
def no_cache(monkeypatch):
    monkeypatch.setenv("ARRAYSEL_CACHE", "off")


@pytest.mark.parametrize("keep", [True, False])
@pytest.mark.parametrize("columns", [12, 24])
def test_sketched_basis_matches_exact_and_bounds_hold(no_cache, monkeypatch, columns, keep):
    """With fewer sketch columns than pairs (36 here) the basis is compressed from the sketch;
    its per-pixel and window error bounds still cover the exact image on E, whether the second
    pass reads the pair images kept from the first or computes them again."""
    monkeypatch.setattr(BasisBuilder, "sketch_columns", columns)
    if not keep:
        monkeypatch.setattr(BasisBuilder, "keep_images_max_bytes", 0)
    model = PSFModel(_setup(), dtype=torch.float64, fast=True, margin=2, block=4, rank_tol=1e-12)
    fast = model.basis.finer or model.basis
    assert fast.missed >= 0 and fast.rank <= columns
    assert BasisBuilder.keeps_images(fast.pairs_e.numel(), fast.npix, model.dtype) is keep
    w = _weights(8, 6)
    with torch.no_grad():
        img, eps, win_err = fast.images(w, with_error=True)
        ref = model.image(w, rows=fast.rows, cols=fast.cols)
    err = (img - ref).abs().reshape(w.shape[0], -1)
    assert bool((err.amax(1) <= eps * (1 + 1e-9) + 1e-12).all())
    n = model.setup.window
    werr = (img - ref)[:, :n, :n].abs().reshape(w.shape[0], -1).norm(dim=1)
    assert bool((werr <= win_err * (1 + 1e-9) + 1e-12).all())
    k, ok = model.basis.kernels(w)
    ke = model.kernels_exact(w)
    for i in range(w.shape[0]):
        if bool(ok[i]):
            assert float(si_mse(k[i], ke[i])) <= fast.refinement.kernel_tol ** 2


def test_missed_spectral_bound_lies_between_the_exact_norm_and_frobenius():
    """The pixel-tile bound of what a sketch missed: never below the exact spectral norm of
    ``(I - Q Q^T) H`` (from an SVD) nor above its Frobenius norm, tighter as tiles merge,
    equal to the exact norm (to the rounding slack) with one tile covering the image (padded
    past its edge), and well below the Frobenius norm when the missed part spreads over many
    directions (noise)."""
    from arraysel.physics.psf.build import _missed_spectral, _tile_grams

    gen = torch.Generator().manual_seed(3)
    P, shape = 400, (8, 12)
    N = 2 * shape[0] * shape[1]

    def randn(*size):
        return torch.randn(*size, generator=gen, dtype=torch.float64)

    # the tiles' Gram matrices are those of the tiles' real and imaginary columns
    H = randn(5, N)
    g = _tile_grams(H, shape, 4)
    assert g.shape == (6, 32, 32)
    re = H[:, :N // 2].reshape(5, 8, 12)[:, 4:8, 8:12].reshape(5, 16)
    im = H[:, N // 2:].reshape(5, 8, 12)[:, 4:8, 8:12].reshape(5, 16)
    Hg = torch.cat([re, im], dim=1)
    torch.testing.assert_close(g[5], Hg.T @ Hg)
    for noise, sketch in ((1e-2, 14), (1e-3, 24)):
        H = randn(P, 12) @ randn(12, N) * 10 + noise * randn(P, N)
        Q = torch.linalg.qr(H @ randn(N, sketch))[0]
        B = Q.T @ H
        R = H - Q @ B
        exact = float(torch.linalg.matrix_norm(R, ord=2))
        frob = float(R.norm())
        bounds = [_missed_spectral(_tile_grams(H, shape, t), _tile_grams(B, shape, t), P, sketch)
                  for t in (1, 2, 4, 12)]  # nested tilings; 12: one tile, padded
        for b in bounds:
            assert exact <= b <= frob * (1 + 1e-3)  # the rounding slack may exceed it a little
        assert all(b1 <= b0 * (1 + 1e-6) for b0, b1 in zip(bounds, bounds[1:]))
        assert bounds[-1] <= exact * (1 + 1e-2)  # one tile: the exact norm and its rounding slack
    assert bounds[-1] < 0.6 * frob  # the noise-like residual of the second case


def test_without_strips_fast_equals_exact(no_cache, monkeypatch):
    """Above the strip budget the strips are not built: loose blocks are beamformed exactly
    from the windowed channels, and the kernels still equal the exact path's."""
    monkeypatch.setattr(PairBasis, "strip_max_bytes", 0)
    model = PSFModel(_setup(), dtype=torch.float64, fast=True, margin=2, block=4)
    assert not model.basis.strips and model.basis.npix2 == 0
    w = _weights(8, 5, seed=3)
    w[0] = 0
    w[0, [0, 7]] = 1  # the two outermost elements: side lobes beside E
    kf, fallback = model.kernels(w, return_info=True)
    ke = model.kernels_exact(w)
    for i in range(5):
        assert float(si_mse(kf[i], ke[i])) < 1e-10


def test_windowed_channels_cover_every_grid_read(no_cache):
    """The channel windows hold every sample any grid pixel reads, and the windowed pair I/Q
    equals the I/Q matrix applied to the full record."""
    model = PSFModel(_setup(), dtype=torch.float64, fast=True, margin=2, block=4)
    fast = model.basis
    s = model.setup
    from arraysel.physics.beamform import das_plan, iq_matrix
    from arraysel.physics.simus import spectra_to_rf

    Z, X = torch.meshgrid(model.z_grid, model.x_grid, indexing="ij")
    for n, t in enumerate(model.transmits):
        p = das_plan(X, Z, t.delays, s.probe, s.acq.fs, s.acq.c, t.grid.n_time, fnumber=s.fnumber, fc=s.probe.fc)
        valid = p.rot.abs() > 0
        local = p.i0 - fast.certificates.window_offset[n][None, :]
        assert bool((local[valid] >= 0).all()) and bool((local[valid] + 1 <= fast.certificates.window_samples - 1).all())
        spec = t.rx_factor[:, None, :] * t.tx_field[None, :, :]
        iq = spectra_to_rf(spec, t.grid).to(torch.complex128) @ iq_matrix(t.grid.n_time, *t.iq_band).T  # (e, j, T)
        ne = model.n_elements
        Ac = fast.pair_iq()
        for e in range(ne):
            o = int(fast.certificates.window_offset[n, e])
            k = min(fast.certificates.window_samples, iq.shape[-1] - o)
            ref = iq[e, :, o:o + k]
            assert float((Ac[:, n, e, :k] - ref).abs().max()) <= 1e-6 * float(ref.abs().max())
        # the channels of a selection are its weighted sums of the pair signals
        w = _weights(8, 2, seed=7)
        ch = fast.channels(w)[:, n]  # (B, e, T)
        want = torch.einsum("bj,jet->bet", w.to(Ac.dtype), Ac[:, n]) * w.to(Ac.dtype)[:, :, None]
        assert float((ch - want).abs().max()) <= 1e-9 * float(want.abs().max())


@pytest.mark.slow
def test_gradcheck_fast_path_128_elements(no_cache):
    """Gradients of the fast kernels of a 128-element probe (sketched build) in float64."""
    setup = _setup(n_elements=128, probe="L11-5v", fc=7.6e6, n=32, pixel=2.5e-5, depth=6e-3, window=12)
    model = PSFModel(setup, dtype=torch.float64, fast=True, margin=2, block=4)
    assert model.basis is not None
    w0 = torch.linspace(0.5, 1.0, 128, dtype=torch.float64)[None]
    k, ok = model.basis.kernels(w0)
    assert bool(ok.all())
    ke = model.kernels_exact(w0)
    assert float(si_mse(k[0], ke[0])) < 1e-6

    def f(w):
        return torch.view_as_real(model.basis.kernels(w)[0])

    assert torch.autograd.gradcheck(f, (w0.clone().requires_grad_(True),), eps=1e-6, atol=1e-6, rtol=1e-4)


def test_basis_memory_estimate_covers_the_build(no_cache):
    """The guard's estimate is of the right size: at least the stored tensors."""
    model = PSFModel(_setup(n_elements=16), dtype=torch.float32, fast=True, margin=2, block=4)
    fast = model.basis.finer or model.basis
    stored = sum(t.numel() * t.element_size() for t in fast.state().values() if isinstance(t, torch.Tensor))
    assert model.basis_bytes() >= stored



def test_cached_basis_carries_the_window_estimate(monkeypatch, tmp_path):
    """A cold start reads the memory guard's window estimate from the cached basis instead of
    planning the grid again; it is the number the model computes. The loaded basis keeps its
    ``strips`` flag."""
    from arraysel.physics.psf.store import stored_window_estimate

    monkeypatch.setenv("ARRAYSEL_CACHE", str(tmp_path))
    first = PSFModel(_setup(), dtype=torch.float64, fast=True, margin=2, block=4)
    assert stored_window_estimate(first) == first._estimate_window()
    second = PSFModel(_setup(), dtype=torch.float64, fast=True, margin=2, block=4)
    assert second.window_estimate() == first._estimate_window()
    assert second.basis_bytes() == first.basis_bytes()
    # the loaded basis states whether it has strips, as the built one does
    assert second.basis.strips is first.basis.strips is True
    monkeypatch.setenv("ARRAYSEL_CACHE", "off")
    assert stored_window_estimate(first) is None


def test_exact_windows_settle_kernels_whose_error_bound_fails(no_cache, monkeypatch):
    """A selection whose peak and window are certified but whose image error bound exceeds
    ``kernel_tol`` gets its window delay-and-summed exactly from its channels (no whole-grid
    exact path): with ``kernel_tol = 0`` every kernel comes from there and equals the exact
    path's; beyond ``exact_windows_max`` selections the exact path still takes over."""
    model = PSFModel(_setup(), dtype=torch.float64, fast=True, margin=2, block=4)
    fast = model.basis
    monkeypatch.setattr(Refinement, "channel_group", 2)  # channels formed 2 selections at a time
    w = _weights(8, 5, seed=11)
    ke = model.kernels_exact(w)
    for basis in (fast, fast.finer):
        if basis is not None:
            monkeypatch.setattr(basis.refinement, "kernel_tol", 0.0)
    called = []
    real = Refinement._exact_windows

    def spy(self, *a):
        called.append(a[0].shape[0])
        return real(self, *a)

    monkeypatch.setattr(Refinement, "_exact_windows", spy)
    k, fallback = model.kernels(w, return_info=True)
    assert sum(called) == 5 and not bool(fallback.any())
    for i in range(5):
        assert float(si_mse(k[i], ke[i])) < 1e-12
    # differentiable like the rest of the fast path
    w1 = w[:1].clone().requires_grad_(True)
    assert torch.autograd.gradcheck(lambda v: torch.view_as_real(model.kernels(v)), (w1,), eps=1e-6, atol=1e-6,
                                    rtol=1e-4)
    monkeypatch.setattr(Refinement, "exact_windows_max", 2)
    called.clear()
    k, fallback = model.kernels(w, return_info=True)
    assert not called and bool(fallback.all())


def test_compiled_das_equals_das_apply():
    """The compiled delay-and-sum (refinement and exact windows, no gradient) is ``das_apply``'s
    sum, entries outside the aperture (zero rotation) included as zeros, on any rows."""
    from arraysel.physics.beamform import das_apply
    from arraysel.physics.pairkernels import das_plan_rows, das_stacked_raw

    gen = torch.Generator().manual_seed(3)
    ntx, ne, T, npix = 3, 5, 40, 17
    x = torch.complex(torch.randn(ntx, ne, T, generator=gen, dtype=torch.float64),
                      torch.randn(ntx, ne, T, generator=gen, dtype=torch.float64))
    plans, want = [], 0
    for n in range(ntx):
        i0 = torch.randint(0, T - 1, (npix, ne), generator=gen)
        wt = torch.rand(npix, ne, generator=gen, dtype=torch.float64)
        rot = torch.polar(torch.ones(npix, ne, dtype=torch.float64), torch.rand(npix, ne, generator=gen, dtype=torch.float64) * 6.3)
        rot[torch.rand(npix, ne, generator=gen) < 0.3] = 0  # outside the aperture
        plans.append((i0.numpy(), wt.numpy(), torch.view_as_real(rot).numpy()))
        want = want + das_apply(x[n], i0, wt, rot)
    got = torch.from_numpy(das_plan_rows(torch.view_as_real(x).numpy(), plans, np.arange(npix)))
    assert torch.allclose(torch.complex(got[:, 0], got[:, 1]), want, rtol=1e-12, atol=1e-12)
    rows = np.array([16, 0, 5, 5])
    got = torch.from_numpy(das_plan_rows(torch.view_as_real(x).numpy(), plans, rows))
    assert torch.allclose(torch.complex(got[:, 0], got[:, 1]), want[rows], rtol=1e-12, atol=1e-12)
    # the plans stacked over the transmits, one call (the refinement's block sums), channels in
    # time order (one-sample segments) with unit receive weights
    stacked = [np.stack(a) for a in zip(*plans)]
    got = torch.from_numpy(das_stacked_raw(torch.view_as_real(x).permute(1, 3, 0, 2).contiguous().numpy(),
                                           np.ones(ne), *stacked, 1))
    assert torch.allclose(torch.complex(got[:, 0], got[:, 1]), want, rtol=1e-12, atol=1e-12)
    # and on raw channels: samples in segment-offset-major order, receive weights applied inside
    seg = 4
    we = torch.rand(ne, generator=gen, dtype=torch.float64)
    we[1] = 0
    raw = torch.view_as_real(x).permute(1, 3, 0, 2).reshape(ne, 2, ntx, T // seg, seg).transpose(-1, -2)
    raw = raw.reshape(ne, 2, ntx, T).contiguous()
    raw[1] = float("nan")  # a receive element of zero weight: its channel is not read
    got = torch.from_numpy(das_stacked_raw(raw.numpy(), we.numpy(), *stacked, seg))
    want_w = sum(das_apply(x[n] * we[:, None], torch.from_numpy(plans[n][0]), torch.from_numpy(plans[n][1]),
                           torch.view_as_complex(torch.from_numpy(plans[n][2]))) for n in range(ntx))
    assert torch.allclose(torch.complex(got[:, 0], got[:, 1]), want_w, rtol=1e-12, atol=1e-12)


def test_block_sums_in_chunks_with_kept_transmit_distances_equal_the_exact_image(no_cache, monkeypatch):
    """The refinement's block delay-and-sums equal the exact image on those blocks whether the
    blocks are planned and summed a few at a time (``das_blocks``), their plans made afresh
    from the kept transmit distances (plans evicted) or read from the plan cache, for raw
    channels, complex channels without gradient and complex channels with one."""
    model = PSFModel(_setup(), dtype=torch.float64, fast=True, margin=2, block=4)
    fast = model.basis
    monkeypatch.setattr(Refinement, "das_blocks", 2)
    b = model.block
    w = _weights(8, 1, seed=5)
    ref = model.image(w)[0]
    blocks = [(0, 0), (5, 1), (2, 4), (1, 5), (3, 3)]
    want = torch.cat([ref[qz * b:(qz + 1) * b, qx * b:(qx + 1) * b].reshape(-1) for qz, qx in blocks])
    X = fast.channels(w)[0]
    raw = next(iter(fast.refinement._grouped_channels(w, [0], raw=True)))[1]
    first = None
    for attempt in range(3):
        if attempt == 1:
            fast.refinement._block_plans.clear()  # evicted: made again from the kept transmit distances
            assert set(blocks) <= set(fast.refinement._block_dtx)
        for chan in (raw, X, X.clone().requires_grad_(True)):
            got = fast.refinement._das(chan, blocks).detach()
            first = got if first is None else first
            torch.testing.assert_close(got, first, rtol=1e-12, atol=1e-12 * float(ref.abs().max()))
    # the windowed pair I/Q signals are stored in single precision
    torch.testing.assert_close(first, want, rtol=0, atol=1e-6 * float(ref.abs().max()))


def test_certified_peak_whose_window_leaves_e_gets_an_exact_window(no_cache, monkeypatch):
    """Without strips, a selection whose peak is certified but whose window does not fit in E
    (a peak near E's edge) has its window beamformed exactly, not the whole grid: forced here by
    reporting every window as not fitting."""
    monkeypatch.setattr(PairBasis, "strip_max_bytes", 0)
    model = PSFModel(_setup(), dtype=torch.float64, fast=True, margin=2, block=4)
    fast = model.basis
    assert not fast.strips
    from arraysel.physics.psf import refinement

    real = refinement._windows

    def never_fits(*a):
        z0, x0, fits = real(*a)
        return z0, x0, torch.zeros_like(fits)

    monkeypatch.setattr(refinement, "_windows", never_fits)
    w = _weights(8, 4, seed=5)
    k, fallback = model.kernels(w, return_info=True)
    assert not bool(fallback.any())
    ke = model.kernels_exact(w)
    for i in range(4):
        assert float(si_mse(k[i], ke[i])) < 1e-12


def test_band_images_only_for_peaks_tier_one_cannot_certify(no_cache, monkeypatch):
    """Tier 2 (the band's image, a product with every strip pair image) serves only selections
    whose peak tier 1 could not certify. A certified peak whose error bound is too loose gets an
    exact window instead, so the strips' pair images are not read (they are most of the
    paper scene's basis). Forcing tier 1 to fail still routes selections through the band."""
    model = PSFModel(_setup(), dtype=torch.float64, fast=True, margin=2, block=4)
    fast = model.basis
    assert fast.strips and fast.npix2 > 0
    cls = type(fast)
    w = _weights(8, 5, seed=11)
    ke = model.kernels_exact(w)
    band_calls = []
    real_band = cls.band_images

    def band_spy(self, *a, **kw):
        band_calls.append(a[0].shape[0])
        return real_band(self, *a, **kw)

    monkeypatch.setattr(cls, "band_images", band_spy)
    monkeypatch.setattr(fast.refinement, "kernel_tol", 0.0)  # every error bound fails, every peak is certified
    k, fallback = model.kernels(w, return_info=True)
    assert not band_calls and not bool(fallback.any())
    for i in range(5):
        assert float(si_mse(k[i], ke[i])) < 1e-12
    # tier 1 cannot certify any peak: the band is consulted for every selection
    monkeypatch.setattr(fast.refinement, "kernel_tol", Refinement.kernel_tol)
    real_bound = Certificates.bound

    def tier1_fails(self, w_, tier=1, per_block=False, env=None):
        b = real_bound(self, w_, tier, per_block=per_block, env=env)
        return b + float("inf") if tier == 1 else b

    real_refine = Refinement.refine

    def refine_tier1_fails(self, w_, threshold, env=None, tier=2, bounds=None):
        if tier == 1:
            return torch.zeros(w_.shape[0], dtype=torch.bool)
        return real_refine(self, w_, threshold, env=env, tier=tier, bounds=bounds)

    monkeypatch.setattr(Certificates, "bound", tier1_fails)
    monkeypatch.setattr(Refinement, "refine", refine_tier1_fails)
    k, fallback = model.kernels(w, return_info=True)
    assert sum(band_calls) == 5
    for i in torch.nonzero(~fallback).flatten().tolist():
        assert float(si_mse(k[i], ke[i])) < 1e-6


def test_pair_image_kernel_equals_the_definition():
    """The compiled pair-image kernel against a direct evaluation of its definition on random
    signals and plans: ``D_ej(p) = sum_n rot (x[i] + (x[i+1] - x[i]) w)`` with ``x`` the I/Q of
    (rx e, tx j), ``H_ej = D_ej + D_je`` for ``e < j`` and ``H_ee = D_ee``; entries with a zero
    rotation (outside the aperture) are skipped, whatever their sample index."""
    from arraysel.physics.pairkernels import pair_images

    rng = np.random.default_rng(5)
    ntx, ne, T, npix = 3, 19, 12, 37  # 19 elements: two symmetrisation blocks; 37 pixels: three groups
    X = rng.standard_normal((ntx, ne, T, 2, ne)).astype(np.float32)
    i0 = rng.integers(0, T - 1, (ntx, ne, npix)).astype(np.int32)
    wt = rng.random((ntx, ne, npix)).astype(np.float32)
    ang = rng.random((ntx, ne, npix)) * 2 * np.pi
    rr, ri = np.cos(ang).astype(np.float32), np.sin(ang).astype(np.float32)
    off = rng.random((ntx, ne, npix)) < 0.2
    rr[off], ri[off] = 0, 0
    i0[off] = T + 5  # never read
    got = pair_images(X, (i0, wt, rr, ri))
    x = X[:, :, :, 0, :].astype(np.float64) + 1j * X[:, :, :, 1, :]
    D = np.zeros((npix, ne, ne), dtype=complex)
    for n in range(ntx):
        for e in range(ne):
            for p in range(npix):
                if not off[n, e, p]:
                    i, w = i0[n, e, p], float(wt[n, e, p])
                    D[p, e] += complex(rr[n, e, p], ri[n, e, p]) * (x[n, e, i] + (x[n, e, i + 1] - x[n, e, i]) * w)
    e, j = np.triu_indices(ne)
    H = D[:, e, j] + np.where(e < j, D[:, j, e], 0)
    assert got.shape == (2, npix, ne * (ne + 1) // 2)
    np.testing.assert_allclose(got[0] + 1j * got[1], H, rtol=0, atol=1e-12 * np.abs(H).max())


def test_sparse_sketch_and_row_gram_equal_their_definitions():
    """The sparse sign sketch's compiled accumulation against ``np.add.at`` (repeated hits add
    up), in float32 and float64, over more columns than one parallel chunk; and the build's
    symmetric Gram matrices ``A A^T`` against a product, for both memory orders of ``A``."""
    from arraysel.physics.pairkernels import sparse_sketch_add
    from arraysel.physics.psf.build import _row_gram

    rng = np.random.default_rng(2)
    Ht = rng.standard_normal((40, 2500))
    hit = rng.integers(0, 30, (40, 8))
    hit[0, :2] = 5  # a repeated hit
    sign = np.where(rng.random((40, 8)) < 0.5, -1.0, 1.0) / np.sqrt(8)
    ref = np.zeros((30, 2500))
    for k in range(8):
        np.add.at(ref, hit[:, k], Ht * sign[:, k, None])
    for dtype, tol in ((np.float64, 1e-12), (np.float32, 1e-5)):
        Y = np.ones((30, 2500), dtype=dtype)
        sparse_sketch_add(Y, Ht, hit, sign)
        np.testing.assert_allclose(Y, ref + 1, rtol=0, atol=tol * np.abs(ref).max())
    A = torch.from_numpy(rng.standard_normal((7, 300)))
    torch.testing.assert_close(_row_gram(A), A @ A.T, rtol=1e-12, atol=1e-12)
    At = A.T.contiguous().T  # column-major
    torch.testing.assert_close(_row_gram(At), A @ A.T, rtol=1e-12, atol=1e-12)
    assert torch.equal(_row_gram(A), _row_gram(A).T)


def test_dense_pair_images_equal_the_tiles_in_both_layouts(no_cache, monkeypatch):
    """The pair images on E filled a few pixels per kernel call equal one call over every
    pixel, in both layouts ((P, 2 Npix) and its transpose) and in float32."""
    from arraysel.physics.pairkernels import pair_images

    model = PSFModel(_setup(), dtype=torch.float64, fast=True, margin=2, block=4)
    fast = model.basis
    builder = BasisBuilder(model, fast.layout, fast.certificates.segment)
    builder.sample_ranges()
    assert torch.equal(builder.window_offset, fast.certificates.window_offset)
    X = builder.windowed_pair_iq()
    plan = builder.local_plan(fast.rows, torch.arange(fast.cols.start, fast.cols.stop))
    ref = torch.from_numpy(pair_images(X, plan))  # (2, Npix, P)
    ref = torch.cat([ref[0].T, ref[1].T], dim=1)
    monkeypatch.setattr(BasisBuilder, "build_tile_bytes", 36 * 16 * 50)  # 50 pixels a call
    tiled = builder.dense_pair_images(X, plan)
    assert tiled.shape == ref.shape == (36, 2 * fast.npix) and fast.npix > 100
    assert float(ref.abs().max()) > 0
    torch.testing.assert_close(tiled, ref, rtol=0, atol=0)
    torch.testing.assert_close(builder.dense_pair_images(X, plan, transposed=True), ref.T.contiguous(), rtol=0, atol=0)
    single = builder.dense_pair_images(X, plan, torch.float32)
    torch.testing.assert_close(single.double(), ref, rtol=1e-6, atol=1e-6 * float(ref.abs().max()))
    # tiles of pixels (the sketched build's passes), each yielded in a reused buffer: several
    # tiles a kernel call, and tiles larger than a call's share
    from arraysel.physics.psf.build import _tile_pixels, _tile_rows

    tiles = _tile_pixels(fast.shape, 4)
    for pixels_a_call in (40, 10):
        monkeypatch.setattr(BasisBuilder, "build_tile_bytes", 36 * 16 * pixels_a_call)
        got = [(G, Ht.clone()) for G, Ht in builder.pair_image_tiles(X, plan, tiles)]
        assert [G for G, _ in got] == tiles
        for G, Ht in got:
            torch.testing.assert_close(Ht, ref[:, _tile_rows(G, fast.npix)].T, rtol=0, atol=0)


def test_build_time_estimate_counts_the_delay_and_sum_passes(monkeypatch):
    """The first-run message's time estimate follows the pair images' delay-and-sum work: a
    sketched build that cannot keep its pair images computes those on E twice."""
    monkeypatch.setattr(BasisBuilder, "sketch_columns", 12)  # 36 pairs: sketched
    model = PSFModel(_setup(), dtype=torch.float32, fast=False, margin=2, block=4)
    kept = model.basis_build_seconds()
    monkeypatch.setattr(BasisBuilder, "keep_images_max_bytes", 0)
    twice = model.basis_build_seconds()
    assert 0 < kept < twice < 2 * kept
    assert model.basis_stored_bytes() > 0
    # the memory estimate holds the kept images only when they are kept
    monkeypatch.setattr(BasisBuilder, "keep_images_max_bytes", 2 << 30)
    with_kept = model.basis_bytes()
    monkeypatch.setattr(BasisBuilder, "keep_images_max_bytes", 0)
    assert model.basis_bytes() < with_kept


@pytest.mark.parametrize("unused", [[], [0, 7, 8, 11]])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_block_sums_from_raw_channels_equal_those_from_the_channels(no_cache, dtype, unused):
    """The refinement's block delay-and-sum reads the certificate product's raw channels
    (``RawChannels``: stored sample order, receive weights not applied) to the same values as
    from :meth:`channels`, on whole blocks and on chosen pixel rows, whether every receive
    element is used (the whole product) or some are used by none of the selections (their
    channels are not formed)."""
    from arraysel.physics.psf.refinement import RawChannels

    model = PSFModel(_setup(n_elements=12), dtype=dtype)
    basis = model.basis
    w = _weights(12, 3, seed=4).to(dtype)
    w[0, [1, 5, 6]] = 0
    w[:, unused] = 0
    nb = -(-24 // model.block)
    blocks = [(0, 0), (nb - 1, 0), (nb // 2, nb - 1)]
    raws = list(basis.refinement._grouped_channels(w, [0, 1, 2], raw=True))
    assert all(isinstance(x, RawChannels) for _, x in raws)
    tol = 1e-5 if dtype == torch.float32 else 1e-12
    for (i, raw), x in zip(raws, basis.channels(w)):
        for rows in (None, [torch.tensor([0, 5]), torch.tensor([3]), torch.tensor([1, 2])]):
            a = basis.refinement._das(raw, blocks, rows)
            b = basis.refinement._das(x, blocks, rows)
            assert a.dtype == b.dtype
            assert torch.allclose(a, b, rtol=tol, atol=tol * float(b.abs().max()))
    # with a gradient the channels stay complex tensors
    assert not any(isinstance(x, RawChannels) for _, x in basis.refinement._grouped_channels(w.requires_grad_(), [0], raw=True))


def _mixed_weights(ne, seed):
    """Selections with every pattern the receive products group by: soft weights (all elements
    at once), one zero, a 0/1 mask, a mask of one element, and all elements off."""
    w = _weights(ne, 5, seed=seed)
    w[1, 2] = 0
    w[2] = (torch.arange(ne) % 3 == 0).double()
    w[3] = 0
    w[3, ne - 1] = 0.7
    w[4] = 0
    return w


@pytest.mark.parametrize("step_bytes", [0, 1 << 30, "rows"])
def test_envelopes_are_the_running_maxima_of_the_channels(no_cache, monkeypatch, step_bytes):
    """The certificate's segment envelopes equal the maxima of ``|X_ne(t)|`` over every run of
    1 .. max_run segments (clipped at the window's end), computed from the selection's channels,
    whether the receive products are formed one receive element a step or whole runs at once,
    or each channel is summed compiled from the rows its selection uses, for one selection and
    for batches mixing soft weights, masks and empty selections."""
    model = PSFModel(_setup(), dtype=torch.float64, fast=True, margin=2, block=4)
    fast = model.basis
    cert = fast.certificates
    rows = step_bytes == "rows"
    monkeypatch.setattr(Certificates, "_channels_from_rows", lambda self, w: rows)
    monkeypatch.setattr(Certificates, "receive_step_bytes", 0 if rows else step_bytes)
    monkeypatch.setattr(Certificates, "receive_subset_min", 2)
    ntx, ne, sg = len(model.transmits), model.n_elements, cert.segment
    nS, M = cert.window_samples // sg, cert.max_run
    mixed = _mixed_weights(ne, seed=2)
    for w in (mixed[:1], mixed[2:3], mixed):
        B = w.shape[0]
        env = cert.envelopes(w).view(ntx, ne, M, nS, B)
        seg = fast.channels(w).abs().view(B, ntx, ne, nS, sg).amax(-1)  # (B, ntx, ne, nS)
        for m in range(M):
            for a in range(nS):
                want = seg[:, :, :, a:min(nS, a + m + 1)].amax(-1).permute(1, 2, 0)
                torch.testing.assert_close(env[:, :, m, a], want, rtol=1e-12, atol=1e-15)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_envelopes_of_a_few_selections_from_their_rows(no_cache, monkeypatch, dtype):
    """A few selections' envelopes with each channel summed compiled from the rows its selection
    uses, against the receive products: equal within float32 rounding (the compiled sums are
    float64), NaN where a weight is NaN on both paths. They serve a loop of small batches (after
    ``compiled_bound_warm`` of them, so a cold single-mask run loads no compiled code) and only
    when they read less: not a batch of MIN_BATCH, not soft weights on every element, not
    weights that need a gradient."""
    from arraysel.physics import compiled

    model = PSFModel(_setup(n_elements=16), dtype=dtype, fast=True, margin=2, block=4)
    fast = model.basis.certificates
    cls = Certificates
    real = cls._channels_from_rows
    ne = model.n_elements
    mask = torch.zeros(1, ne, dtype=dtype)
    mask[0, [0, 3, 4, 9, 15]] = 1
    soft = _mixed_weights(ne, seed=4)[:1].to(dtype)
    nan = mask.clone()
    nan[0, 3] = math.nan
    rtol = 1e-12 if dtype == torch.float64 else 1e-5
    for w in (mask, soft, _mixed_weights(ne, seed=5)[:3].to(dtype), nan):
        got = {}
        for rows in (False, True):
            monkeypatch.setattr(cls, "_channels_from_rows", lambda self, w, rows=rows: rows)
            got[rows] = fast.envelopes(w)
        scale = float(got[False].nan_to_num().abs().max())
        torch.testing.assert_close(got[True], got[False], rtol=rtol, atol=rtol * scale, equal_nan=True)
        assert bool(got[True].isnan().any()) is (w is nan)
    monkeypatch.setattr(cls, "_channels_from_rows", real)
    fast._small_calls.clear()
    seen = [real(fast, mask) for _ in range(fast.compiled_bound_warm + 2)]
    assert seen == [False] * fast.compiled_bound_warm + [True, True]
    assert not real(fast, torch.ones(1, ne, dtype=dtype))  # every row of every receive element
    assert not real(fast, mask.expand(compiled.MIN_BATCH, ne))  # a batch: one product reads less
    assert not real(fast, mask.clone().requires_grad_(True))


@pytest.mark.parametrize("step_bytes", [0, 1 << 30])
def test_compiled_envelopes_of_a_batch_equal_torchs(no_cache, monkeypatch, step_bytes):
    """A float32 batch of at least MIN_BATCH selections has its receive products reduced to
    segment peaks and runs compiled: the envelopes equal torch's reduction of the same products
    to one rounding of the root (torch's vectorised root is not always the nearest float), zero on the
    receive elements a selection does not use, NaN in the same entries; float64, a gradient or a
    small batch keep torch's operations."""
    from arraysel.physics import compiled

    model = PSFModel(_setup(n_elements=16), dtype=torch.float32, fast=True, margin=2, block=4)
    cert = model.basis.certificates
    monkeypatch.setattr(Certificates, "receive_step_bytes", step_bytes)
    ne = model.n_elements
    rng = np.random.default_rng(7)
    masks = torch.zeros(2 * compiled.MIN_BATCH, ne)
    for b in range(masks.shape[0]):
        masks[b, rng.choice(ne, 1 + b % ne, replace=False)] = 1
    w = torch.cat([masks, _mixed_weights(ne, seed=3).float()])
    w[-1, 5] = math.nan
    from arraysel.physics.psf import certificate

    assert certificate.compiled_envelopes(w)
    assert not certificate.compiled_envelopes(w[:compiled.MIN_BATCH - 1])
    assert not certificate.compiled_envelopes(w.double())
    assert not certificate.compiled_envelopes(w.clone().requires_grad_(True))
    got = cert.envelopes(w)
    monkeypatch.setattr(certificate, "compiled_envelopes", lambda w: False)
    want = cert.envelopes(w)
    assert torch.equal(got.isnan(), want.isnan()) and bool(got.isnan().any())
    torch.testing.assert_close(got, want, rtol=2.5e-7, atol=0, equal_nan=True)
    ntx, M, nS = len(model.transmits), cert.max_run, cert.window_samples // cert.segment
    off = (w[:-1] == 0).T[None, :, None, None, :].expand(ntx, ne, M, nS, -1)  # the last: NaN everywhere
    assert bool((got.view(ntx, ne, M, nS, -1)[..., :-1][off] == 0).all())


def test_batches_write_their_envelopes_in_the_last_batchs_memory(no_cache, monkeypatch):
    """Refinement.kernels writes a batch's envelopes in the memory of the last batch's (no fresh
    pages for every batch) when it is large enough, and the kernels equal those of envelopes in
    memory of their own; a small batch, or a second caller while the memory is in use, gets its
    own."""
    from arraysel.physics import compiled
    from arraysel.physics.psf import refinement as refinement_module

    model = PSFModel(_setup(n_elements=16), dtype=torch.float32, fast=True, margin=2, block=4)
    basis, ref = model.basis, model.basis.refinement
    rng = np.random.default_rng(11)
    w = torch.zeros(2 * compiled.MIN_BATCH, 16)
    for b in range(w.shape[0]):
        w[b, rng.choice(16, 8, replace=False)] = 1
    k1, ok1 = basis.kernels(w)
    assert len(ref._env_pool) == 1
    buf = ref._env_pool[0]
    assert buf.numel() == basis.certificates.envelope_size(w.shape[0])
    k2, ok2 = basis.kernels(w.flip(0))
    assert ref._env_pool == [buf]  # the same memory again
    assert torch.equal(k2, k1.flip(0)) and torch.equal(ok2, ok1.flip(0))
    k3, _ = basis.kernels(w[:compiled.MIN_BATCH])  # smaller: the same memory
    assert ref._env_pool == [buf] and torch.equal(k3, k1[:compiled.MIN_BATCH])
    scratch = refinement_module._envelope_scratch
    assert scratch(ref._env_pool, ref.certificates, w[:compiled.MIN_BATCH - 1]) is None  # small: its own
    taken = scratch(ref._env_pool, ref.certificates, w)
    assert taken is buf and scratch(ref._env_pool, ref.certificates, w) is not buf  # in use: new memory
    ref._env_pool.append(taken)
    monkeypatch.setattr(refinement_module, "_envelope_scratch", lambda pool, certificates, wd: None)
    k4, ok4 = basis.kernels(w)
    assert torch.equal(k4, k1) and torch.equal(ok4, ok1)


@pytest.mark.parametrize("subset_min", [1, 1000])
@pytest.mark.parametrize("step_bytes", [0, 1 << 30])
def test_receive_products_cover_each_used_receive_element_once(no_cache, monkeypatch, step_bytes, subset_min):
    """The receive products cover, for every selection, each receive element of non-zero weight
    exactly once, with the values of the whole product ``w @ pair_channels``: per receive
    element's own selections (and no other element), or for a small batch every selection on
    the elements any of them uses (and no element none uses)."""
    model = PSFModel(_setup(), dtype=torch.float64, fast=True, margin=2, block=4)
    fast = model.basis
    cert = fast.certificates
    monkeypatch.setattr(Certificates, "receive_step_bytes", step_bytes)
    monkeypatch.setattr(Certificates, "receive_subset_min", subset_min)
    ne = model.n_elements
    w = _mixed_weights(ne, seed=3)
    w[:, 4] = 0  # an element no selection uses
    whole = (w @ cert.pair_channels).view(w.shape[0], ne, -1)
    seen = torch.zeros(w.shape[0], ne, dtype=torch.long)
    for e0, e1, s, y in cert._receive_products(w):
        rows = torch.arange(w.shape[0]) if s is None else s
        seen[rows, e0:e1] += 1
        torch.testing.assert_close(y.reshape(rows.numel(), e1 - e0, -1), whole[rows, e0:e1], rtol=1e-12, atol=1e-14)
    used = (w != 0).long()
    if subset_min == 1:
        assert torch.equal(seen, used)
    else:
        assert torch.equal(seen, used.amax(0, keepdim=True).expand_as(seen))


def test_refine_with_the_batch_per_block_bounds_settles_as_from_the_envelopes(no_cache):
    """``refine`` given the columns of a batch's per-block bounds (what ``kernels`` passes on)
    settles each selection as it does forming the bounds from the selections' own envelopes,
    on both tiers, with thresholds that leave some blocks loose and some selections unsettled."""
    model = PSFModel(_setup(), dtype=torch.float64, fast=True, margin=2, block=4)
    fast = model.basis
    cert, refinement = fast.certificates, fast.refinement
    w = _mixed_weights(model.n_elements, seed=7)
    env = cert.envelopes(w)
    for tier in ([1, 2] if cert.block_envelopes_band.shape[0] else [1]):
        bounds = cert.bound(w, tier, per_block=True, env=env)
        if not bounds.shape[0]:
            continue
        rows = torch.tensor([3, 0, 1])
        for q in (0.2, 0.5, 1.0):
            thr = bounds[:, rows].quantile(q, dim=0) * 1.0001
            want = refinement.refine(w[rows], thr, env=env[:, rows], tier=tier)
            got = refinement.refine(w[rows], thr, tier=tier, bounds=bounds[:, rows])
            assert torch.equal(got, want)


def test_strip_bounds_read_runs_of_slots_in_place_as_the_gathered_factors(paper_objective, monkeypatch):
    """The strips' factor bounds of increasing slots in a few runs (read in place) equal those
    of the gathered factors, bit for bit, for runs, single slots, every slot and slots in too
    many runs (which take the gather)."""
    from arraysel.physics.psf import refinement

    fast = paper_objective.psf.basis
    n = fast.strip_left.shape[0]
    assert n >= 64  # the paper scene's strips: 576 blocks
    c = fast._pairs(_mixed_weights(fast.model.n_elements, seed=5).to(fast.strip_left.dtype))
    cases = [torch.arange(n), torch.tensor([n // 2]), torch.cat([torch.arange(0, 3), torch.arange(5, n - 1)]),
             torch.cat([torch.arange(10, 40), torch.arange(100, 180), torch.arange(300, 301)]), torch.arange(0, n, 2)]
    real = refinement._runs
    for slots in cases:
        got = fast.refinement.strip_bounds(c, slots)
        monkeypatch.setattr(refinement, "_runs", lambda s, most=32: None)
        want = fast.refinement.strip_bounds(c, slots)
        monkeypatch.setattr(refinement, "_runs", real)
        assert torch.equal(got, want)
    assert refinement._runs(torch.tensor([2, 3, 4, 7, 9, 10])) == [(2, 5), (7, 8), (9, 11)]
    assert refinement._runs(torch.tensor([3, 2])) is None
    assert refinement._runs(torch.arange(0, 20, 2), most=4) is None
    assert refinement._runs(torch.arange(0, 20, 2), most=10) == [(i, i + 1) for i in range(0, 20, 2)]


def test_fast_batches_follow_the_memory_budget_and_do_not_change_the_scores(paper_objective, monkeypatch):
    """The fast path takes as many masks at once as keep their tensors within
    ``fast_batch_bytes`` (at most 256; the paper scene: 256), and ``evaluate`` scores the same
    whatever the batch (to float32 rounding)."""
    from arraysel.physics.psf.operator import PSFModel as Model

    psf = paper_objective.psf
    per = psf.basis.bytes_per_selection()
    # envelopes of 7 x 64 channels, 3 runs of 65 segments, the 144 x 144 image twice, 2176 block
    # bounds, the 128 x 128 window twice (float32)
    assert per == 7 * 64 * 3 * 65 * 4 + 2 * 2 * 144 * 144 * 4 + 2176 * 12 + 2 * 2 * 128 * 128 * 4
    assert psf.masks_per_batch() == min(256, Model.fast_batch_bytes // per) == 256
    masks = np.zeros((23, 64), dtype=np.float32)
    rng = np.random.default_rng(4)
    for m in masks:
        m[rng.choice(64, 32, replace=False)] = 1
    want = paper_objective.evaluate(masks)
    # batches of at least compiled.MIN_BATCH, so that both runs take the compiled passes
    monkeypatch.setattr(Model, "fast_batch_bytes", 12 * per + 1)
    assert psf.masks_per_batch() == 12
    calls = []
    real = Model.kernels
    monkeypatch.setattr(Model, "kernels", lambda self, w, **kw: calls.append(w.shape[0]) or real(self, w, **kw))
    got = paper_objective.evaluate(masks)
    assert calls == [12, 11]
    for name in want:  # the same to float32 rounding (the products' blocking depends on the batch)
        np.testing.assert_allclose(got[name], want[name], rtol=1e-5, atol=1e-9, err_msg=name)


def test_compiled_block_bounds_equal_the_sparse_product(no_cache, monkeypatch):
    """The certificates' block bounds summed compiled (channel by channel, the channels of
    unused receive elements skipped) equal the sparse product of the block matrix with the
    envelopes, on both tiers, per block and as the maximum, for one selection and for a mixed
    batch."""
    model = PSFModel(_setup(), dtype=torch.float64, fast=True, margin=2, block=4)
    fast = model.basis.certificates
    ne = model.n_elements
    mixed = _mixed_weights(ne, seed=6)
    mixed[:, 3] = 0
    tiers = [1, 2] if fast.block_envelopes_band.shape[0] else [1]
    from arraysel.physics import compiled

    default = compiled.MIN_BATCH
    monkeypatch.setattr(compiled, "MIN_BATCH", 1)  # every batch compiled (by default a small one takes the product)
    for w in (mixed[2:3], mixed):
        env = fast.envelopes(w)
        for tier in tiers:
            S = fast.block_envelopes_e if tier == 1 else fast.block_envelopes_band
            want = torch.sparse.mm(S, env)
            got = fast.bound(w, tier, per_block=True, env=env)
            torch.testing.assert_close(got, want, rtol=1e-12, atol=0)
            torch.testing.assert_close(fast.bound(w, tier, env=env), want.amax(0), rtol=1e-12, atol=0)
    assert fast.bound(mixed[4:5], 1).abs().max() == 0  # no element used: nothing to bound
    # by default a small batch takes the sparse product for the first calls (a cold run need
    # not load the compiled sums), and the compiled sums in a loop of them
    from arraysel.physics import pairkernels

    monkeypatch.setattr(compiled, "MIN_BATCH", default)

    calls = []
    real = pairkernels.block_bound_sums
    monkeypatch.setattr(pairkernels, "block_bound_sums", lambda *a, **k: calls.append(1) or real(*a, **k))
    fresh = PSFModel(_setup(), dtype=torch.float64, fast=True, margin=2, block=4).basis.certificates
    env = fresh.envelopes(mixed[2:3])
    want = fresh.bound(mixed[2:3], 1, env=env)
    seen = [len(calls)]
    for _ in range(fresh.compiled_bound_warm + 1):
        torch.testing.assert_close(fresh.bound(mixed[2:3], 1, env=env), want, rtol=1e-12, atol=0)
        seen.append(len(calls))
    assert seen[:fresh.compiled_bound_warm] == [0] * fresh.compiled_bound_warm and seen[-1] >= 1


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_compiled_peak_search_equals_torch(no_cache, monkeypatch, dtype):
    """The certificates' peak search compiled (batches without gradient on the CPU) against
    torch's: the same peak pixels, thresholds and flags, with the error bounds as computed and
    widened so that many pixels tie and the ambiguous images are settled exactly."""
    from arraysel.physics import compiled

    model = PSFModel(_setup(n_elements=16), dtype=dtype, fast=True, margin=2, block=4)
    fast = model.basis
    w = _weights(16, 12, seed=3)
    w[4] = (torch.arange(16) % 2 == 0).to(dtype)
    w = w.to(dtype)
    img, eps, _ = fast.images(w, with_error=True)
    r0, c0 = fast.rows.start, fast.cols.start
    peak = img.abs().reshape(len(w), -1).amax(1)
    tied = 0
    for e in (eps, eps + 0.005 * peak, eps + 0.03 * peak, eps + 0.2 * peak):
        got = {}
        for name, least in (("compiled", 1), ("torch", 1 << 62)):
            monkeypatch.setattr(compiled, "MIN_BATCH", least)
            got[name] = fast.refinement._locate(img, e, w, r0, c0)
        (pz, px, thr, ok), (qz, qx, thr_t, ok_t) = got["compiled"], got["torch"]
        assert torch.equal(ok, ok_t)
        assert torch.equal(pz[ok], qz[ok]) and torch.equal(px[ok], qx[ok])
        torch.testing.assert_close(thr, thr_t, rtol=1e-6, atol=0)
        mag = img.abs().reshape(len(w), -1)
        tied += int(((mag >= (mag.amax(1) - 2 * e)[:, None]).sum(1) > 1).sum())
    assert tied > 10  # the widened bounds made near-ties that were settled exactly
    # an image with a NaN is never located, as on torch's path
    bad = img.clone()
    bad[2, 1, 1] = complex(float("nan"), 0)
    for least in (1, 1 << 62):
        monkeypatch.setattr(compiled, "MIN_BATCH", least)
        ok = fast.refinement._locate(bad, eps, w, r0, c0)[3]
        assert not bool(ok[2]) and bool(ok[[0, 1, 3]].all())


def test_moved_block_values_are_the_quadratic_form():
    """``moved_block_values`` gives ``w^T G w`` for ``w = s + d`` from ``g = G s`` and
    ``s^T G s``, whatever d (a swap, a far selection, soft weights, none), rows padded."""
    from arraysel.physics.pairkernels import moved_block_values

    rng = np.random.default_rng(0)
    ne, n2 = 7, 6
    G = rng.normal(size=(ne, ne, n2))
    G = (G + G.transpose(1, 0, 2)) / 2
    s = (rng.random(ne) < 0.5).astype(float)
    g = np.tensordot(G, s, axes=([1], [0]))
    W = np.stack([s, s, 1 - s, rng.uniform(0, 1, ne)])
    W[1, [0, 1]] = 1 - W[1, [0, 1]]
    d = W - s
    idx = np.full((4, ne), -1)
    val = np.zeros((4, ne))
    for r in range(4):
        nz = np.flatnonzero(d[r])
        idx[r, :nz.size], val[r, :nz.size] = nz, d[r, nz]
    got = moved_block_values(G, g, s @ g, idx, val)
    want = np.einsum("re,ejp,rj->rp", W, G, W)
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-12)


def test_block_pair_matrix_gives_each_selections_block_image(no_cache):
    """A block's pair matrix (from the stored pair channels) gives the image of any selection on
    that block as the delay-and-sum of the selection's own channels does: 0/1 masks, soft
    weights, one element, none."""
    from arraysel.physics.pairkernels import block_pair_matrix

    model = PSFModel(_setup(), dtype=torch.float64, fast=True, margin=2, block=4)
    fast = model.basis
    cert, refinement = fast.certificates, fast.refinement
    w = _mixed_weights(model.n_elements, seed=3)
    ne = model.n_elements
    y = cert.pair_channels.numpy().reshape(ne, ne, 2, len(model.transmits), cert.window_samples)
    for key in [tuple(int(v) for v in fast.layout.blocks1[q]) for q in (0, len(fast.layout.blocks1) // 2)]:
        i0, wt, rot = refinement._plans_for_blocks([key])[0]
        G = block_pair_matrix(y, i0.numpy(), wt.numpy(), torch.view_as_real(rot).numpy(), cert.segment)
        n = G.shape[2] // 2
        got = np.einsum("re,ejp,rj->rp", w.numpy(), G, w.numpy())
        for r, x in refinement._grouped_channels(w, list(range(w.shape[0])), raw=True):
            want = refinement._das(x, [key]).numpy()
            np.testing.assert_allclose(got[r, :n] + 1j * got[r, n:], want, rtol=1e-9, atol=1e-9 * max(1.0, np.abs(want).max()))


@pytest.mark.parametrize("tier", [1, 2])
def test_hot_blocks_settle_as_the_block_delay_and_sums(no_cache, monkeypatch, tier):
    """Blocks made hot at once (``HotBlocks.after = 0``) settle every selection as the block
    delay-and-sums do, for thresholds that leave some blocks loose and some selections
    unsettled, with a reference selection carried from batch to batch (a search's held sums
    moving by one swap, then none held) or too small a memory for any block (delay-and-sums; the
    class's memory or the cap ``ARRAYSEL_MEMORY_GIB``)."""
    from arraysel.physics.psf.hotblocks import HotBlocks

    model = PSFModel(_setup(), dtype=torch.float64, fast=True, margin=2, block=4)
    fast = model.basis
    cert, refinement = fast.certificates, fast.refinement
    if tier == 2 and not cert.block_envelopes_band.shape[0]:
        pytest.skip("no tier-2 blocks")
    ne = model.n_elements
    base = (torch.arange(ne) % 2 == 0).double()
    batches = [torch.cat([base[None], _mixed_weights(ne, seed=s)]) for s in range(3)]
    moved = base.clone()
    moved[0], moved[1] = 0, 1
    batches.append(torch.stack([moved, base, 1 - base]))
    blocks = [tuple(int(v) for v in q) for q in (fast.layout.blocks1 if tier == 1 else fast.layout.blocks2)]
    cases = []
    for w in batches:
        bounds = cert.bound(w, tier, per_block=True)
        cases += [(w, bounds.quantile(q, dim=0) * 1.0001) for q in (0.3, 0.7, 1.0)]
        # thresholds just above and just below each selection's exact largest value on the blocks
        top = torch.stack([refinement._das(x, blocks).abs().max()
                           for _, x in refinement._grouped_channels(w, list(range(w.shape[0])), raw=True)])
        cases.append((w, top * torch.where(torch.arange(w.shape[0]) % 2 == 0, 1.001, 0.999)))
    want = [refinement.refine(w, thr, tier=tier) for w, thr in cases]
    assert any(bool((~o).any()) for o in want) and any(bool(o.any()) for o in want)
    refinement.hot.after = 0
    held = [(base.numpy().astype(bool).tobytes(), None, 0), (moved.numpy().astype(bool).tobytes(), None, 0), None]
    for step, sums in enumerate(held):
        cert._swap_sums = sums
        got = [refinement.refine(w, thr, tier=tier) for w, thr in cases]
        assert all(torch.equal(a, b) for a, b in zip(got, want)), step
    assert refinement.hot.settled > 0 and refinement.hot.matrices
    # no room: every block stays beamformed (the class's memory, or the memory cap)
    for room in ({"max_bytes": 0}, {"env": "0.000001"}):
        refinement.hot.clear()
        refinement.hot.max_bytes = room.get("max_bytes", HotBlocks.max_bytes)
        monkeypatch.setenv("ARRAYSEL_MEMORY_GIB", room.get("env", "4"))
        got = [refinement.refine(w, thr, tier=tier) for w, thr in cases]
        assert all(torch.equal(a, b) for a, b in zip(got, want)) and not refinement.hot.matrices
