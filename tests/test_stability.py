"""Numerical stability of the relaxations, the PSF synthesis, the metrics and the reconstruction (issue 7).

Every physics case uses a small scene (P4-2v at 3.5 MHz with ``Ne`` elements,
a 32 x 32 grid, a 16 x 16 window) and ``ARRAYSEL_CACHE=off`` so that nothing
is read from or written to the on-disk cache. The whole file runs in well
under a minute on 2 CPU cores.

Tolerances (float32 eps = 1.2e-7, float64 eps = 2.2e-16):

* unit norm of a kernel: |norm - 1| <= 1e-5 in float32 (the norm is one sum
  of 256 squares, rounding ~ 16 eps) and 1e-12 in float64;
* float32 vs float64 kernels of the same selection: max |k32 - k64| <= 1e-5
  (unit-norm kernels; measured ~3e-8 on every scene here, the margin covers
  other BLAS builds and the accumulation over Ne x time x transmits);
* float32 vs float64 metrics: relative 1e-3 plus absolute 1e-6 (the metrics
  are ratios of sums of squares of side-lobe levels as low as -60 dB, whose
  float32 rounding is relative to the peak, not to the side lobe).
"""
from __future__ import annotations

import functools
import math

import numpy as np
import pytest
import torch

from arraysel.objective import losses as L
from arraysel.objective import metrics as M
from arraysel.errors import NumericalError, ParameterError
from arraysel.physics.probes import Acquisition, get_probe
from arraysel.physics.psf import PSFModel, PSFSetup, window_and_normalise
from arraysel.e2e.recon import ConvolutionOperator, Reconstructor, UnrolledISTA, complex_soft_threshold
from arraysel.selectors.relax import gumbel_noise, sequential_selection

FC = 3.5e6
LAMBDA = 1540.0 / FC
NORM_TOL = {torch.float32: 1e-5, torch.float64: 1e-12}
K32_VS_K64_ATOL = 1e-5
METRIC_RTOL, METRIC_ATOL = 1e-3, 1e-6


@pytest.fixture(autouse=True)
def _no_disk_cache(monkeypatch):
    monkeypatch.setenv("ARRAYSEL_CACHE", "off")


# ---------------------------------------------------------------------------
# helpers
# ---------------------------------------------------------------------------

def make_setup(ne=16, *, tilts=(0.0,), depth=None, x=0.0, n=32, window=16, bandwidth=None, width=None,
               attenuation=0.0, tx_cycles=1.0, reflectivity=1.0) -> PSFSetup:
    """A small scene: pixel = c / fs = lambda / 4, the grid centred on the scatterer when it is deep enough."""
    kw = dict(fc=FC, n_elements=ne)
    if bandwidth is not None:
        kw["bandwidth"] = bandwidth
    if width is not None:
        kw["width"] = width
    probe = get_probe("P4-2v", **kw)
    acq = Acquisition.for_probe(probe, attenuation=attenuation, tx_cycles=tx_cycles)
    pixel = acq.c / acq.fs
    if depth is None:
        depth = (n // 2) * pixel
    z_offset = max(0, int(round(depth / pixel)) - n // 2)
    return PSFSetup(probe=probe, acq=acq, tilts=tuple(tilts), n_x=n, n_z=n, pixel=pixel, z_offset=z_offset,
                    window=window, scatterer=(x, depth), reflectivity=reflectivity)


@functools.lru_cache(maxsize=None)
def _model_cached(key, dtype, fast):
    return PSFModel(make_setup(**dict(key)), dtype=dtype, fast=fast, margin=2, block=4)


def model(dtype=torch.float32, fast=True, **setup_kw) -> PSFModel:
    """PSF models are deterministic and read-only here: build each one once per session.

    (Built inside a test, so ARRAYSEL_CACHE is off when they are made.)
    """
    return _model_cached(tuple(sorted(setup_kw.items())), dtype, fast)


def selections(ne: int, k: int, seed: int = 0) -> torch.Tensor:
    """(3, Ne) 0/1 masks with k active elements: the first k, every (Ne/k)-th, a random k."""
    rng = np.random.default_rng(seed)
    out = np.zeros((3, ne))
    out[0, :k] = 1
    out[1, np.round(np.linspace(0, ne - 1, k)).astype(int)] = 1
    out[2, rng.choice(ne, k, replace=False)] = 1
    assert (out.sum(1) == k).all()
    return torch.tensor(out)


def assert_unit_kernels(k: torch.Tensor, dtype) -> None:
    assert torch.isfinite(torch.view_as_real(k)).all(), "kernel holds NaN/Inf"
    norms = torch.linalg.vector_norm(k.reshape(k.shape[0], -1).to(torch.complex128), dim=1)
    assert torch.allclose(norms, torch.ones_like(norms), rtol=0, atol=NORM_TOL[dtype]), norms


# metric regions in wavelengths, scaled down so that the 16 x 16 window (4 wavelengths)
# has a non-empty side-lobe region: main lobe within 3 pixels, side lobes beyond 5
R_MAIN, R_GUARD = 0.75, 1.25


def metrics_of(m: PSFModel, k: torch.Tensor, ref: torch.Tensor) -> dict:
    s = m.setup
    return M.psf_metrics(k, kappa_ref=ref, pitch=s.pitch, wavelength=s.wavelength, r_main=R_MAIN,
                         r_guard=R_GUARD)


def check_model(m: PSFModel, masks: torch.Tensor, *, grad: bool = True) -> torch.Tensor:
    """Kernels of ``masks`` are finite and unit-norm; metrics and their gradients are finite."""
    w = masks.to(m.dtype).clone().requires_grad_(grad)
    k = m.kernels(w)
    assert k.shape == (masks.shape[0], m.setup.window, m.setup.window)
    assert_unit_kernels(k, m.dtype)
    ref = m.reference_kernel().to(k.dtype)
    assert_unit_kernels(ref[None], m.dtype)
    M.check_regions(M.psf_regions(k.detach(), pitch=m.setup.pitch, wavelength=m.setup.wavelength,
                                  r_main=R_MAIN, r_guard=R_GUARD))  # side lobes are measured
    met = metrics_of(m, k, ref)
    for name, v in met.items():
        assert torch.isfinite(v).all(), (name, v)
        assert (v >= 0).all(), (name, v)
    assert (met["L_SLR_i"] > 0).all()
    if grad:
        loss = sum(met[t].sum() for t in ("L_PSF", "L_contrast", "L_SLR_q", "L_SLR_i"))
        (g,) = torch.autograd.grad(loss, w)
        assert torch.isfinite(g).all(), g
    return k.detach()


# ---------------------------------------------------------------------------
# relaxations: temperatures 1e-3 .. 1e3, logits up to 1e4
# ---------------------------------------------------------------------------

def _draw(variant: str, logits, tau, gen):
    """The draws of the ``ste`` (arg-max or sampled) and ``gumbel`` (hard or soft) selectors."""
    from arraysel_plugins.gumbel import GumbelSelector
    from arraysel_plugins.ste import STESelector

    if variant.startswith("ste"):
        sel = STESelector(draw="sample" if variant == "ste-sample" else "argmax")
    else:
        sel = GumbelSelector(variant="soft" if variant == "gumbel-soft" else "hard")
    return sel.draw(logits, tau, gen)


def _logits(ne, k, scale, dtype, gen):
    lg = torch.randn(ne, k, generator=gen, dtype=torch.float64).to(dtype) * scale
    if scale >= 1e4:  # saturate some entries at +-1e4 exactly
        lg[0] = 1e4
        lg[1] = -1e4
        lg[2, 0] = 1e4
    return lg


@pytest.mark.parametrize("variant", ["ste-argmax", "ste-sample", "gumbel-hard", "gumbel-soft"])
@pytest.mark.parametrize("tau", [1e-3, 1e-1, 1.0, 1e1, 1e3])
def test_relaxation_extreme_temperatures_and_logits(variant, tau):
    for dtype in (torch.float32, torch.float64):
        for ne, k in [(8, 1), (8, 2), (8, 7), (8, 8), (64, 32), (256, 3)]:
            for scale in (0.0, 1.0, 1e2, 1e4):
                gen = torch.Generator().manual_seed(ne * 1000 + k)
                logits = _logits(ne, k, scale, dtype, gen).requires_grad_(True)
                rel = _draw(variant, logits, tau, gen)
                where = (variant, tau, dtype, ne, k, scale)
                for name in ("P", "P_soft", "P_hard"):
                    t = getattr(rel, name)
                    assert t.shape == (ne, k) and t.dtype == dtype, where
                    assert torch.isfinite(t).all(), (name, where)
                # exactly k distinct, valid elements, matching the one-hot columns
                assert len(rel.indices) == k and len(set(rel.indices)) == k, where
                assert all(0 <= i < ne for i in rel.indices), where
                assert torch.equal(rel.P_hard.argmax(0), torch.tensor(rel.indices)), where
                assert torch.equal(rel.P_hard.sum(0), torch.ones(k, dtype=dtype)), where
                # soft columns are distributions over the elements still available
                ps = rel.P_soft.detach().double()
                assert (ps >= 0).all() and torch.allclose(ps.sum(0), torch.ones(k, dtype=torch.float64),
                                                          atol=1e-5), where
                for j in range(1, k):
                    assert (ps[rel.indices[:j], j] == 0).all(), where
                if variant != "gumbel-soft":  # straight-through: forward value is the hard matrix
                    assert torch.allclose(rel.P.detach(), rel.P_hard), where
                # gradients through P (straight-through) and P_soft, with the loss terms
                target = torch.randn(ne, k, generator=gen, dtype=torch.float64).to(dtype)
                loss = (rel.P * target).sum() + L.l_ent(rel.P_soft) + L.l_row(rel.P_soft)
                (g,) = torch.autograd.grad(loss, logits)
                assert torch.isfinite(g).all(), where


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_relaxation_non_finite_logits_still_give_k_distinct_elements(bad):
    logits = torch.randn(8, 8)
    logits[3] = bad
    logits[:, 2] = bad
    for noise in (None, gumbel_noise((8, 8), torch.Generator().manual_seed(0))):
        rel = sequential_selection(logits, 1e-3, noise=noise)
        assert sorted(rel.indices) == list(range(8))
        assert torch.isfinite(rel.P_soft).all() and torch.isfinite(rel.P_hard).all()


def test_gumbel_noise_is_finite_at_the_uniform_extremes():
    for dtype in (torch.float32, torch.float64):
        g = gumbel_noise((200_000,), torch.Generator().manual_seed(1), dtype=dtype)
        assert torch.isfinite(g).all()
        finfo = torch.finfo(dtype)
        lo = -math.log(-math.log(finfo.tiny))
        hi = -math.log(-math.log1p(-finfo.eps))
        assert lo - 1e-3 <= float(g.min()) and float(g.max()) <= hi + 1e-3


# ---------------------------------------------------------------------------
# PSF kernels: k = 1, 2, Ne-1, Ne; Ne from 8 to 256
# ---------------------------------------------------------------------------

@pytest.mark.parametrize("ne,fast", [(8, False), (8, True), (16, False), (16, True), (32, False),
                                     (32, True), (64, False)])
def test_kernels_finite_unit_norm_for_every_k(ne, fast):
    # the fast path is not swept at Ne = 64: its basis build (an eigh of the
    # 2080 x 2080 pair Gram matrix) takes seconds; test_psf_physics covers it
    m = model(ne=ne, fast=fast)
    for k in sorted({1, 2, ne - 1, ne}):
        check_model(m, selections(ne, k, seed=k))


def test_kernels_soft_weights_and_extreme_weight_ratios():
    m = model(ne=16, fast=True)
    w = torch.rand(4, 16, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    w[1] = 1e-6          # uniformly tiny weights: the kernel is scale invariant
    w[2, ::2] = 1e-12    # weights spanning 12 decades
    w[3] = torch.where(torch.arange(16) == 5, 1.0, 1e-30)
    k = check_model(m, w)
    # scale invariance: w and 1e-6 w give the same kernel
    k1 = m.kernels(torch.ones(1, 16))
    assert (k[1] - k1[0]).abs().max() <= 1e-5


def test_kernels_256_elements_tiny_grid():
    # exact path only: the fast path's pair basis has Ne(Ne+1)/2 = 32896 pairs and its
    # (pairs x pairs) Gram matrix alone would take 8.6 GB (see the issue-7 report)
    m = model(ne=256, n=16, window=8, fast=False)
    check_model(m, selections(256, 1))
    check_model(m, selections(256, 2))
    check_model(m, selections(256, 255))
    check_model(m, selections(256, 256)[:1])


def test_fast_path_too_large_falls_back_to_exact_path(monkeypatch, caplog):
    """A basis above ARRAYSEL_BASIS_MAX_GIB is not built: the exact path gives the same kernels."""
    monkeypatch.setenv("ARRAYSEL_CACHE", "off")
    setup = make_setup(ne=16)
    monkeypatch.setenv("ARRAYSEL_BASIS_MAX_GIB", "1e-6")
    with caplog.at_level("WARNING", logger="arraysel.physics.psf"):
        m = PSFModel(setup, dtype=torch.float64, fast=True, margin=2, block=4)
    assert m.basis is None and m.basis_bytes() > 2 ** 10
    assert "ARRAYSEL_BASIS_MAX_GIB" in caplog.text
    masks = selections(16, 5)
    ke = model(ne=16, dtype=torch.float64, fast=False).kernels(masks)
    assert torch.allclose(m.kernels(masks), ke)
    monkeypatch.setenv("ARRAYSEL_BASIS_MAX_GIB", "lots")
    with pytest.raises(ParameterError, match="ARRAYSEL_BASIS_MAX_GIB"):
        PSFModel(setup, fast=True, margin=2, block=4)


def test_all_zero_image_raises_numerical_error():
    for fast in (False, True):
        m = model(ne=8, fast=fast)
        for dtype in (torch.float32, torch.float64):
            with pytest.raises(NumericalError, match="all zero"):
                m.kernels(torch.zeros(2, 8, dtype=dtype))
            w = torch.ones(2, 8, dtype=dtype)
            w[1] = 0  # one empty selection in the batch is enough
            with pytest.raises(NumericalError):
                m.kernels(w)
    with pytest.raises(NumericalError):
        window_and_normalise(torch.zeros(1, 8, 8, dtype=torch.complex64), 4)
    nan = torch.zeros(1, 8, 8, dtype=torch.complex64)
    nan[0, 4, 4] = complex(math.nan, 0)
    with pytest.raises(NumericalError):
        window_and_normalise(nan, 4)


@pytest.mark.parametrize("dtype", [torch.complex64, torch.complex128])
def test_compiled_window_cut_equals_torch(dtype, monkeypatch):
    """cut_windows compiled (images without gradient, on the CPU) against torch's operations:
    the same windows and norms to rounding, on scales from subnormal to near overflow, a zero
    image (zero window, norm 0) and a non-finite one (NaN out, as torch)."""
    from arraysel.physics import compiled
    from arraysel.physics.psf import window as W

    g = torch.Generator().manual_seed(1)
    img = torch.randn(12, 40, 36, dtype=dtype, generator=g)
    tiny, huge = (1e-41, 1e37) if dtype == torch.complex64 else (1e-310, 1e300)
    img[1] *= tiny
    img[2] *= huge
    img[3] = 0
    z0 = torch.randint(0, 40 - 16 + 1, (12,), generator=g)
    x0 = torch.randint(0, 36 - 16 + 1, (12,), generator=g)
    img[4, z0[4] + 3, x0[4] + 5] = complex(math.nan, 0)
    monkeypatch.setattr(compiled, "MIN_BATCH", 1)
    fast, nf = W.cut_windows(img, z0, x0, 16)
    monkeypatch.setattr(compiled, "MIN_BATCH", 1 << 62)
    slow, ns = W.cut_windows(img, z0, x0, 16)
    assert fast.dtype == slow.dtype and nf.dtype == ns.dtype
    ok = torch.tensor([i != 4 for i in range(12)])
    rtol = 1e-5 if dtype == torch.complex64 else 1e-12
    torch.testing.assert_close(fast[ok], slow[ok], rtol=rtol, atol=rtol * 1e-3)
    torch.testing.assert_close(nf[ok], ns[ok], rtol=rtol, atol=0)
    assert float(nf[3]) == 0.0 and bool((fast[3] == 0).all())
    assert bool(torch.isnan(nf[4])) and bool(torch.isnan(torch.view_as_real(fast[4])).any())
    norms = torch.linalg.vector_norm(torch.view_as_real(fast[ok]).reshape(11, -1), dim=1)
    torch.testing.assert_close(norms[[0, 1, 2, 4, 5, 6, 7, 8, 9, 10]].double(),
                               torch.ones(10, dtype=torch.float64), rtol=rtol, atol=0)


# ---------------------------------------------------------------------------
# extreme physics: near field, deep and attenuated, tilts, bandwidths, widths
# ---------------------------------------------------------------------------

@pytest.mark.parametrize("fraction", [0.1, 0.25, 0.5])
def test_scatterer_a_fraction_of_a_wavelength_from_the_probe(fraction):
    for fast in (False, True):
        for dtype in (torch.float32, torch.float64):
            m = model(ne=16, depth=fraction * LAMBDA, fast=fast, dtype=dtype)
            check_model(m, selections(16, 8))


DEEP_2DB = dict(ne=8, depth=0.30, attenuation=2.0, bandwidth=10.0)  # |image| ~ 1e-21
DEEP_4DB = dict(ne=8, depth=0.30, attenuation=4.0, bandwidth=10.0)  # |image| ~ 4e-41


@pytest.mark.slow   # 23 s: the whole RF -> I/Q pipeline of a deep scene in float64
def test_iq_from_spectra_is_the_rf_iq_pipeline():
    """The exact path's I/Q (one product from the spectra) is the I/Q matrix applied to the RF
    record, to float64 rounding, on a shallow and on the deep attenuated scene."""
    from arraysel.physics.beamform import iq_matrix
    from arraysel.physics.simus import spectra_to_rf

    for case in ({}, DEEP_2DB):
        m = model(dtype=torch.float64, fast=False, **case)
        s = m.setup
        w = selections(m.n_elements, 4)
        for n, t in enumerate(m.transmits):
            Q = iq_matrix(t.grid.n_time, s.acq.fs, s.probe.fc,
                          s.probe.bandwidth if s.iq_bandwidth is None else s.iq_bandwidth)
            want = spectra_to_rf(m.spectra(w, n), t.grid).to(torch.complex128) @ Q.T
            got = m.iq(w, n)
            assert float((got - want).abs().max()) <= 1e-11 * float(want.abs().max())


@pytest.mark.slow   # 18 s: float64 and float32 models of a 30 cm scene
def test_deep_strongly_attenuated_scatterer_is_finite():
    """30 cm, 2 dB/cm/MHz, 10 % bandwidth: the echo is ~1e-21 (float64 reference)."""
    m64 = model(dtype=torch.float64, fast=False, **DEEP_2DB)
    masks = selections(8, 4)
    # image_scale: the physical unit of image() if PSFModel rescales its spectra (1 otherwise)
    img = m64.image(masks).abs().amax() * getattr(m64, "image_scale", 1.0)
    assert 0 < float(img) < 1e-15
    check_model(m64, masks)
    for fast in (False, True):
        k = model(dtype=torch.float32, fast=fast, **DEEP_2DB).kernels(masks)
        assert torch.isfinite(torch.view_as_real(k)).all()


@pytest.mark.parametrize("case, fast", [
    pytest.param(DEEP_2DB, False, id="2dB-exact"), pytest.param(DEEP_2DB, True, id="2dB-fast"),
    pytest.param(DEEP_4DB, False, id="4dB-exact", marks=pytest.mark.slow),   # 38 s on the exact path
    pytest.param(DEEP_4DB, True, id="4dB-fast")])
def test_deep_attenuated_float32_kernel_is_the_float64_one(case, fast):
    """The kernel is normalised, so a tiny echo (4 dB/cm/MHz: ~4e-41, a float32 subnormal)
    must give a finite, unit-norm kernel close to the float64 one, never 0/0 or a zero kernel.

    Tolerance (loosened from 1e-5 to 2e-2): the record is long (~5500 samples) and strong
    attenuation leaves the low-frequency, out-of-band part of the echo orders of magnitude
    above the in-band part that forms the PSF; float32 rounding of the former leaks through
    the I/Q filter. Measured with the proposed psf.py fix: 3e-4 .. 9e-3.
    """
    masks = selections(8, 4)
    k64 = check_model(model(dtype=torch.float64, fast=False, **case), masks)
    k32 = check_model(model(dtype=torch.float32, fast=fast, **case), masks)
    assert (k32.to(torch.complex128) - k64).abs().max() <= 2e-2


@pytest.mark.parametrize("fast", [False, True], ids=["exact", "fast"])
@pytest.mark.parametrize("reflectivity", [1e-30, 1e-40])
def test_kernel_is_independent_of_the_echo_amplitude(reflectivity, fast):
    """The kernel is unit-norm: scaling the echo by 1e-20 .. 1e-40 must not change it in float32."""
    masks = selections(8, 4)
    k_ref = model(ne=8, fast=fast).kernels(masks)
    k = check_model(model(ne=8, reflectivity=reflectivity, fast=fast), masks)
    assert (k - k_ref).abs().max() <= 1e-5


@pytest.mark.parametrize("reflectivity", [1e-10, 1e-20])
def test_tiny_echo_within_float32_range_is_handled(reflectivity):
    """|image| ~ 1e-9 .. 1e-19 (in float32's normal range) gives the kernel of reflectivity 1."""
    masks = selections(8, 4)
    for fast in (False, True):
        k_ref = model(ne=8, fast=fast).kernels(masks)
        k = check_model(model(ne=8, reflectivity=reflectivity, fast=fast), masks)
        assert (k - k_ref).abs().max() <= 1e-5


@pytest.mark.parametrize("case", [
    dict(tilts=(-math.pi / 4, 0.0, math.pi / 4)),
    dict(tilts=(math.pi / 4,)),
    dict(tilts=(-math.pi / 4,), x=-8 * 1540.0 / 14e6),
    dict(bandwidth=10.0),
    dict(bandwidth=150.0),
    dict(bandwidth=150.0, tilts=(-math.pi / 4, math.pi / 4)),
    dict(width=0.999 * 0.300e-3),
    dict(width=0.300e-3),
], ids=["tilts+-45", "tilt+45", "tilt-45-offaxis", "bw10", "bw150", "bw150-tilts45", "width.999pitch",
        "width=pitch"])
def test_extreme_tilts_bandwidths_and_widths(case):
    for fast in (False, True):
        m = model(ne=16, fast=fast, **case)
        for k in (1, 2, 8, 16):
            check_model(m, selections(16, k, seed=k))


@pytest.mark.parametrize("case", [
    dict(),
    dict(tilts=(-math.pi / 4, math.pi / 4)),
    dict(bandwidth=150.0),
    dict(depth=8 * LAMBDA),
    dict(depth=0.25 * LAMBDA),
    dict(depth=0.5 * LAMBDA),
], ids=["default", "tilts45", "bw150", "8lambda", "near0.25lambda", "near0.5lambda"])
def test_fast_path_matches_exact_path(case):
    """The fast path is the exact kernel up to its SVD truncation plus rounding (both float64).

    The fast path certifies each kernel's relative L2 error against a rigorous bound
    (|c - (c U) U^T| sigma_{r+1} over the window's norm) and sends a kernel whose bound exceeds
    PSFModel's kernel_tol (5e-3) to the exact path, so every kernel is within 5e-3 in L2: a weak
    selection in the near field (a quarter wavelength from the probe, 5 elements) has a truncation
    error of 3.5e-2 and must be recomputed. Measured on certified kernels: <= 1.4e-3."""
    from arraysel.physics.psf.refinement import Refinement
    masks = torch.cat([selections(16, 5), selections(16, 2), torch.ones(1, 16)])
    kf = model(ne=16, fast=True, dtype=torch.float64, **case).kernels(masks)
    ke = model(ne=16, fast=False, dtype=torch.float64, **case).kernels(masks)
    err = torch.linalg.vector_norm((kf - ke).reshape(len(masks), -1), dim=1)
    assert (err <= Refinement.kernel_tol).all(), err


# ---------------------------------------------------------------------------
# float32 vs float64 of the same PSF computation
# ---------------------------------------------------------------------------

@pytest.mark.parametrize("case", [dict(ne=16), dict(ne=16, tilts=(-math.pi / 4, 0.0, math.pi / 4)),
                                  dict(ne=32), dict(ne=16, depth=0.25 * LAMBDA),
                                  dict(ne=16, bandwidth=150.0)],
                         ids=["ne16", "tilts45", "ne32", "near", "bw150"])
@pytest.mark.parametrize("fast", [False, True], ids=["exact", "fast"])
def test_float32_matches_float64(case, fast):
    ne = case["ne"]
    masks = torch.cat([selections(ne, ne // 2), selections(ne, 2), torch.ones(1, ne)])
    m32 = model(dtype=torch.float32, fast=fast, **case)
    m64 = model(dtype=torch.float64, fast=fast, **case)
    k32 = m32.kernels(masks)
    k64 = m64.kernels(masks)
    assert k32.dtype == torch.complex64 and k64.dtype == torch.complex128
    # tolerance: see the module docstring (eps32 x accumulation length, with a 300x margin)
    assert (k32.to(torch.complex128) - k64).abs().max() <= K32_VS_K64_ATOL
    met32 = metrics_of(m32, k32, m32.reference_kernel())
    met64 = metrics_of(m64, k64, m64.reference_kernel())
    for name in met64:
        np.testing.assert_allclose(met32[name].double().numpy(), met64[name].numpy(),
                                   rtol=METRIC_RTOL, atol=METRIC_ATOL, err_msg=name)


# ---------------------------------------------------------------------------
# metrics on degenerate kernels
# ---------------------------------------------------------------------------

def test_metrics_finite_for_degenerate_kernels():
    n = 16
    pitch, lam = 1540.0 / 14e6, LAMBDA
    delta = torch.zeros(n, n, dtype=torch.complex64)
    delta[8, 8] = 1
    flat = torch.ones(n, n, dtype=torch.complex64) / n
    tiny = delta * 1e-30          # squares underflow in float32
    sub = delta * 1e-44           # float32 subnormal
    huge = flat * 1e30            # squares overflow in float32
    zero = torch.zeros(n, n, dtype=torch.complex64)
    batch = torch.stack([delta, flat, tiny, sub, huge, zero]).requires_grad_(True)
    met = M.psf_metrics(batch, pitch=pitch, wavelength=lam, kappa_ref=flat, r_main=R_MAIN, r_guard=R_GUARD)
    val = {name: v.detach() for name, v in met.items()}
    for name, v in met.items():
        assert torch.isfinite(v).all(), (name, v)
    # scale invariance of every metric (tiny/sub/huge vs the unscaled kernels)
    for name in M.PSF_TERMS:
        assert val[name][2] == pytest.approx(float(val[name][0]), abs=1e-6), name
        assert val[name][3] == pytest.approx(float(val[name][0]), abs=1e-6), name
        assert val[name][4] == pytest.approx(float(val[name][1]), abs=1e-6), name
    total = sum(met[t].sum() for t in ("L_PSF", "L_contrast", "L_SLR_q", "L_SLR_i"))
    (g,) = torch.autograd.grad(total, batch)
    # the metrics are scale invariant, so their gradient scales as 1/|kappa|: for the
    # subnormal kernel (1e-44) the true gradient (~1e44) exceeds float32's range; every
    # other kernel, the zero one included, must have a finite gradient
    keep = [0, 1, 2, 4, 5]
    assert torch.isfinite(torch.view_as_real(g[keep])).all()
    with pytest.raises(NumericalError, match="identically zero"):
        M.check_kernels(batch.detach())


# ---------------------------------------------------------------------------
# reconstruction: soft threshold, ISTA with an ill-conditioned kernel
# ---------------------------------------------------------------------------

@pytest.mark.parametrize("dtype", [torch.complex64, torch.complex128, torch.float32, torch.float64])
def test_complex_soft_threshold_gradient_at_zero(dtype):
    Z = torch.zeros(2, 1, 4, 4, dtype=dtype)
    Z[0, 0, 0, 0] = 1e-30
    Z[0, 0, 0, 1] = 3.0
    Z = Z.requires_grad_(True)
    for lam in (0.0, 1e-3, 1.0):
        lam_t = torch.tensor(lam, requires_grad=True)
        out = complex_soft_threshold(Z, lam_t)
        assert torch.isfinite(torch.view_as_real(out) if out.is_complex() else out).all()
        loss = (out.abs() ** 2).sum() + out.real.sum()
        gz, gl = torch.autograd.grad(loss, (Z, lam_t))
        gz_r = torch.view_as_real(gz) if gz.is_complex() else gz
        assert torch.isfinite(gz_r).all() and torch.isfinite(gl)
        if lam > 0:  # below the threshold the output is 0 with gradient 0
            assert (gz_r[1] == 0).all()


def _ill_conditioned_kernel(n=16, depth=1e-6, dtype=torch.complex64):
    """A kernel whose spectrum |K| spans [~depth, 2]: (delta - (1 - depth) shifted delta) / ..."""
    k = torch.zeros(n, n, dtype=dtype)
    k[n // 2, n // 2] = 1.0
    k[n // 2, n // 2 + 1] = -(1.0 - depth)
    return k


@pytest.mark.parametrize("dtype", [torch.complex64, torch.complex128])
@pytest.mark.parametrize("depth", [1e-3, 1e-7, 0.0])
def test_ista_with_near_zero_spectrum_is_bounded(dtype, depth):
    n = 16
    kappa = _ill_conditioned_kernel(n, depth, dtype).requires_grad_(True)
    op = ConvolutionOperator(kappa)
    K = op.K.detach()
    assert float(K.abs().min()) <= max(10 * depth, 1e-6)  # near-zero (or zero) frequencies
    ista = UnrolledISTA(n_layers=12, lam=1e-4)
    real = torch.float64 if dtype == torch.complex128 else torch.float32
    with torch.no_grad():  # raw step parameters from -50 to +50 (sigmoid saturates at 0 and 1)
        ista.a.copy_(torch.linspace(-50, 50, 12))
        ista.b.copy_(torch.linspace(-50, 50, 12))
    L = op.lipschitz.detach()
    alphas = ista.alphas(L)
    assert (alphas >= 0).all()
    assert (alphas <= 2.0 / L * (1 + 1e-6)).all(), (alphas, 2 / L)
    assert (ista.lambdas() >= 0).all()
    x = torch.randn(3, 1, n, n, generator=torch.Generator().manual_seed(0), dtype=real)
    y = op.A(x.to(dtype)).detach()
    iterates = ista(y, op, return_all=True)
    # each layer is non-expansive around 0 when alpha <= 2/||A||^2, so
    # ||x_t|| <= ||x_{t-1}|| + alpha_t ||A^H y||: the iterates stay bounded
    aty = float(torch.linalg.vector_norm(op.A_adjoint(y).detach()))
    bound = 0.0
    for t, xt in enumerate(iterates):
        bound += float(alphas[t].detach()) * aty
        assert torch.isfinite(torch.view_as_real(xt)).all(), t
        assert float(torch.linalg.vector_norm(xt.detach())) <= bound * (1 + 1e-4) + 1e-6, t
    loss = (iterates[-1].abs() ** 2).mean()
    g = torch.autograd.grad(loss, [kappa, ista.a, ista.b])
    for gi in g:
        assert torch.isfinite(torch.view_as_real(gi) if gi.is_complex() else gi).all()


def test_reconstructor_with_ill_conditioned_kernel_has_finite_gradients():
    torch.manual_seed(0)
    net = Reconstructor(n_layers=4, base_channels=4)
    kappa = _ill_conditioned_kernel(16, 0.0).requires_grad_(True)
    x = torch.rand(2, 1, 16, 16)
    y = ConvolutionOperator(kappa.detach()).A(x)
    out = net(y, kappa)
    loss = L.l_rec(out, x) + L.l_conv(M.circular_convolve(kappa, x.to(kappa.dtype)), y)
    assert torch.isfinite(loss)
    loss.backward()
    assert torch.isfinite(torch.view_as_real(kappa.grad)).all()
    for p in net.parameters():
        assert p.grad is None or torch.isfinite(p.grad).all()


def test_ista_rejects_a_zero_kernel():
    op = ConvolutionOperator(torch.zeros(8, 8, dtype=torch.complex64))
    with pytest.raises(NumericalError):
        UnrolledISTA(2)(torch.zeros(1, 1, 8, 8), op)


# ---------------------------------------------------------------------------
# composite loss: terms whose scales differ by 1e4
# ---------------------------------------------------------------------------

@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_composite_loss_with_terms_1e4_apart(dtype):
    m = model(ne=16, fast=True, dtype=dtype)
    w = torch.full((1, 16), 0.5, dtype=dtype).requires_grad_(True)
    kappa = m.kernels(w)
    met = metrics_of(m, kappa, m.reference_kernel())
    img = torch.rand(2, 32, 32, generator=torch.Generator().manual_seed(0), dtype=dtype)
    y_ref = M.circular_convolve(m.reference_kernel(), img).detach()
    y = M.circular_convolve(kappa[0], img)
    terms = dict(met)
    terms["L_conv"] = L.l_conv(y * 1e4, y_ref * 1e4)           # ~1e4 larger than usual
    terms["L_rec"] = L.l_rec(y.real * 1e-2, y_ref.real * 1e-2)  # ~1e4 smaller than usual
    P_soft = torch.softmax(torch.randn(16, 4, dtype=dtype) * 1e3, dim=0)
    terms["L_ent"] = L.l_ent(P_soft)
    terms["L_row"] = L.l_row(P_soft)
    for name, v in terms.items():
        assert torch.isfinite(v).all(), name
    total = L.composite_loss(terms)
    assert torch.isfinite(total)
    (g,) = torch.autograd.grad(total, w)
    assert torch.isfinite(g).all() and float(g.abs().max()) > 0
    # weights 1e4 apart, on scalars: the small term's gradient is not absorbed
    a = torch.tensor(1.0, dtype=dtype, requires_grad=True)
    b = torch.tensor(1.0, dtype=dtype, requires_grad=True)
    tot = L.composite_loss({"big": a * 1e4, "small": b * 1e-4}, {"big": 1e4, "small": 1.0})
    ga, gb = torch.autograd.grad(tot, (a, b))
    assert torch.isfinite(tot) and float(ga) == pytest.approx(1e8) and float(gb) == pytest.approx(1e-4)


# ---------------------------------------------------------------------------
# end to end: the matrix selectors with extreme temperatures on a tiny physics scene
# ---------------------------------------------------------------------------

@pytest.mark.parametrize("selector,options", [
    ("ste", {"tau_start": 1e3, "tau_end": 1e-3, "tau_steps": 6, "lr": 1e4, "init_std": 1e4}),
    ("gumbel", {"tau_start": 1e-3, "tau_end": 1e-3, "lr": 1e3, "variant": "soft"}),
])
def test_matrix_selectors_with_extreme_settings_return_valid_rows(selector, options):
    from arraysel.objective.psf_objective import Objective
    from arraysel.run.experiment import Experiment
    from arraysel.scenes.schema import load_scene
    from arraysel.selectors.contract import Budget

    scene = load_scene({"base": "paper", "probe": {"n_elements": 16}, "selection": {"k": 4},
                        "transmit": {"n_tx": 1}, "grid": {"n_x": 32, "n_z": 32, "window": 16,
                                                          "pixel_per_wavelength_fs": 1.0},
                        "metrics": {"r_main": R_MAIN, "r_guard": R_GUARD},
                        "simulator": {"fast_margin": 2, "fast_block": 4}})
    obj = Objective(scene)
    row = Experiment(obj, selector, options=dict(options, steps=8), budget=Budget(evaluations=20)).run()
    assert row["error"] == "", row["error"]
    assert math.isfinite(row["Mean"])
    assert len(set(row["elements"].split())) == 4
