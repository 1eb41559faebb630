"""Known-answer tests of arraysel.objective.metrics (docs/metrics.md)."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from arraysel.errors import NumericalError, ParameterError
from arraysel.objective.losses import DEFAULT_WEIGHTS, composite_loss, l_conv, l_ent, l_rec, l_row
from arraysel.objective.metrics import (
    PSF_TERMS,
    check_finite,
    check_kernels,
    check_regions,
    circular_convolve,
    psf_metrics,
    psf_regions,
    safe_abs,
    si_mse,
)

from arraysel.objective import metric_kernels
from arraysel.physics import compiled


@pytest.fixture(params=["compiled", "torch"], autouse=True)
def metrics_path(request, monkeypatch):
    """Every test here runs twice: with the compiled pass of psf_metrics taken wherever it applies
    (no gradient, CPU), however small the batch, and with torch's operations only."""
    monkeypatch.setattr(compiled, "MIN_BATCH", 1 if request.param == "compiled" else 1 << 62)
    return request.param


# the paper scene: lambda0 = c / fc, pitch = (c / fs) / 4 with fs = 4 fc -> lambda0 / 16
C, FC = 1540.0, 3.5e6
LAM = C / FC
PITCH = (C / (4 * FC)) / 4
R_MAIN_PX, R_GUARD_PX = 24, 40        # 1.5 and 2.5 wavelengths in pixels


# ---------------------------------------------------------------- references

def np_metrics(k: np.ndarray, r_main_px: int, r_guard_px: int, q: float) -> dict[str, float]:
    """Independent numpy implementation on one (H, W) kernel, isotropic integer radii in pixels."""
    a = np.abs(k)
    i0, j0 = np.unravel_index(np.argmax(a), a.shape)
    di = np.arange(a.shape[0])[:, None] - i0
    dj = np.arange(a.shape[1])[None, :] - j0
    d2 = di ** 2 + dj ** 2                                      # exact integers
    main = d2 <= r_main_px ** 2
    side = d2 >= r_guard_px ** 2
    m = a / a.max()
    out = {
        "L_contrast": np.mean(m[side] ** 2) / np.mean(m[main] ** 2),
        "L_SLR_q": np.quantile(m[side], q) / m[main].max(),
        "L_SLR_i": np.sum(m[side] ** 2) / np.sum(m[main] ** 2),
    }
    out["L_SLR"] = (out["L_SLR_q"] + out["L_SLR_i"]) / 2
    return out


def gaussian(h, w, i0, j0, sigma, dtype=torch.float64):
    i = torch.arange(h, dtype=torch.float64)[:, None]
    j = torch.arange(w, dtype=torch.float64)[None, :]
    g = torch.exp(-((i - i0) ** 2 + (j - j0) ** 2) / (2 * sigma ** 2))
    return g.to(dtype)


# ---------------------------------------------------------------- safe_abs

@pytest.mark.parametrize("dtype", [torch.float32, torch.float64, torch.complex64, torch.complex128])
def test_safe_abs_value_and_zero_gradient(dtype):
    z = torch.tensor([0, 3, -4, 0], dtype=dtype)
    if dtype.is_complex:
        z = z + torch.tensor([0, 4j, 0, 0], dtype=dtype)
    z.requires_grad_(True)
    a = safe_abs(z)
    np.testing.assert_allclose(a.detach().numpy(), [0, 5 if dtype.is_complex else 3, 4, 0], rtol=1e-6)
    a.sum().backward()
    g = z.grad
    assert torch.isfinite(torch.view_as_real(g) if g.is_complex() else g).all()
    assert g[0] == 0 and g[3] == 0
    assert torch.allclose(g[2], torch.tensor(-1, dtype=dtype))


# ---------------------------------------------------------------- SI-MSE

@pytest.mark.parametrize("dtype,tol", [(torch.complex64, 1e-6), (torch.complex128, 1e-14)])
def test_si_mse_scale_and_phase_invariant(dtype, tol):
    g = torch.Generator().manual_seed(1)
    ref = torch.randn(3, 16, 16, dtype=dtype, generator=g)
    scale = torch.tensor([2.5, 1e-3, 40.0]) * torch.exp(1j * torch.tensor([0.3, -2.0, 3.1]))
    k = ref * scale.to(dtype)[:, None, None]
    loss = si_mse(k, ref)
    assert loss.shape == (3,)
    assert loss.abs().max() < tol


def test_si_mse_orthogonal_is_one_and_two_pixel_closed_form():
    k = torch.zeros(4, 4, dtype=torch.complex128)
    r = torch.zeros(4, 4, dtype=torch.complex128)
    k[0, 0], r[2, 3] = 1 + 1j, 3
    assert si_mse(k, r).item() == pytest.approx(1.0, abs=1e-15)
    # kappa = [1, t], ref = [1, 0]: a* = 1/(1+|t|^2), L = |t|^2 / (1 + |t|^2)
    for t in (0.5, 2j, 1 - 1j):
        k = torch.tensor([[1, t]], dtype=torch.complex128)
        r = torch.tensor([[1, 0]], dtype=torch.complex128)
        assert si_mse(k, r).item() == pytest.approx(abs(t) ** 2 / (1 + abs(t) ** 2), rel=1e-14)
    # kappa = [1, 0], ref = [1, 1]: a* = 1, residual [0, -1], L = 1/2
    assert si_mse(torch.tensor([[1.0, 0.0]]), torch.tensor([[1.0, 1.0]])).item() == pytest.approx(0.5)


def test_si_mse_broadcast_real_and_mixed_dtypes():
    g = torch.Generator().manual_seed(2)
    k = torch.randn(5, 6, 7, dtype=torch.float64, generator=g)
    r = torch.randn(6, 7, dtype=torch.complex64, generator=g)
    out = si_mse(k, r)
    assert out.shape == (5,) and out.dtype == torch.float64
    for b in range(5):
        kb = k[b].numpy().astype(complex).ravel()
        rb = r.numpy().astype(complex).ravel()
        a = np.vdot(kb, rb) / np.vdot(kb, kb)
        exp = np.sum(np.abs(a * kb - rb) ** 2) / np.sum(np.abs(rb) ** 2)
        assert out[b].item() == pytest.approx(exp, rel=1e-6)


def test_si_mse_zero_kernel_finite_and_checker_raises():
    r = torch.randn(2, 5, 5, dtype=torch.complex128)
    k = torch.randn(2, 5, 5, dtype=torch.complex128)
    k[1] = 0
    k.requires_grad_(True)
    loss = si_mse(k, r)
    assert loss[1].item() == pytest.approx(1.0)
    loss.sum().backward()
    assert torch.isfinite(torch.view_as_real(k.grad)).all()
    with pytest.raises(NumericalError, match="kappa is identically zero"):
        check_kernels(k.detach(), r)
    with pytest.raises(NumericalError, match="kappa_ref"):
        check_kernels(r, torch.zeros(5, 5))
    check_kernels(r, r[0])  # fine


def test_si_mse_gradcheck():
    g = torch.Generator().manual_seed(3)
    k = torch.randn(2, 4, 5, dtype=torch.complex128, generator=g, requires_grad=True)
    r = torch.randn(4, 5, dtype=torch.complex128, generator=g)
    assert torch.autograd.gradcheck(lambda x: si_mse(x, r), (k,), eps=1e-6, atol=1e-7, rtol=1e-5)
    kr = torch.randn(3, 4, dtype=torch.float64, generator=g, requires_grad=True)
    rr = torch.randn(3, 4, dtype=torch.float64, generator=g)
    assert torch.autograd.gradcheck(lambda x: si_mse(x, rr), (kr,), eps=1e-6, atol=1e-7, rtol=1e-5)


# ---------------------------------------------------------------- regions

def test_regions_boundary_inclusive_paper_scene():
    k = torch.zeros(128, 128)
    k[64, 64] = 1
    reg = psf_regions(k, pitch=PITCH, wavelength=LAM)
    assert reg.peak.tolist() == [64, 64]
    main, side, r = reg.main, reg.side, reg.r
    # r exactly r_main (24 px) is in the main lobe, 25 px is not
    for di, dj in [(24, 0), (0, -24), (-24, 0)]:
        assert main[64 + di, 64 + dj]
    assert not main[64 + 25, 64] and not main[64 + 17, 64 + 17]   # 17^2 + 17^2 = 578 > 576
    assert main[64 + 16, 64 + 17]                                  # 545 <= 576
    # r exactly r_guard (40 px) is in the side region: (40, 0), (24, 32), (-32, 24)
    for di, dj in [(40, 0), (24, 32), (-32, 24), (0, -40)]:
        assert side[64 + di, 64 + dj]
    assert not side[64 + 39, 64 + 1]                               # 1522 < 1600
    assert r[64 + 24, 64].item() == pytest.approx(1.5 * LAM, rel=1e-6)
    assert r[64 + 3, 64 + 4].item() == pytest.approx(5 * PITCH, rel=1e-6)
    assert r[64, 64].item() == 0
    # counts, by exact integer lattice counting
    di = np.arange(128)[:, None] - 64
    dj = np.arange(128)[None, :] - 64
    d2 = di ** 2 + dj ** 2
    assert int(main.sum()) == int((d2 <= 576).sum())
    assert int(side.sum()) == int((d2 >= 1600).sum())


def test_regions_small_by_hand_and_anisotropic_pitch():
    k = torch.zeros(9, 9)
    k[4, 4] = 1
    reg = psf_regions(k, pitch=1.0, wavelength=1.0, r_main=1.0, r_guard=3.0)
    assert int(reg.main.sum()) == 5            # centre and its 4 neighbours (r = 1 exactly)
    assert int(reg.side.sum()) == 81 - 25      # everything outside the 5 x 5 square has r >= 3
    # pitch (rows 1, cols 2): di^2 + 4 dj^2 <= 4 -> (0,0), (+-1,0), (+-2,0), (0,+-1)
    reg = psf_regions(k, pitch=(1.0, 2.0), wavelength=1.0, r_main=2.0, r_guard=2.0)
    assert int(reg.main.sum()) == 7            # 1 + 4 (rows) + 2 (cols)
    assert reg.main[4, 5] and reg.main[6, 4] and not reg.main[4, 6] and not reg.main[5, 5]
    assert reg.r[4, 6].item() == pytest.approx(4.0)


def test_regions_follow_peak_per_item():
    k = torch.zeros(3, 20, 30, dtype=torch.complex64)
    peaks = [(0, 0), (10, 15), (19, 3)]
    for b, (i, j) in enumerate(peaks):
        k[b, i, j] = 2j
        k[b, 5, 5] += 0.5       # smaller values elsewhere
    reg = psf_regions(k, pitch=0.1, wavelength=1.0, r_main=0.3, r_guard=0.5)
    assert reg.peak.tolist() == [list(p) for p in peaks]
    for b, (i, j) in enumerate(peaks):
        ii, jj = np.meshgrid(np.arange(20) - i, np.arange(30) - j, indexing="ij")
        d2 = ii ** 2 + jj ** 2
        assert np.array_equal(reg.main[b].numpy(), d2 <= 9)
        assert np.array_equal(reg.side[b].numpy(), d2 >= 25)
        np.testing.assert_allclose(reg.r[b].numpy(), 0.1 * np.sqrt(d2), rtol=1e-6)


# ---------------------------------------------------------------- PSF metrics, known answers

def test_contrast_slr_piecewise_constant_by_hand():
    # 9x9, pitch = wavelength = 1, main r <= 1 (5 px), side r >= 3 (56 px)
    b_main, g_band, c = 0.5, 0.3, 0.1
    k = torch.full((9, 9), c, dtype=torch.float64)
    k[2:7, 2:7] = g_band
    for di, dj in [(1, 0), (-1, 0), (0, 1), (0, -1)]:
        k[4 + di, 4 + dj] = b_main
    k[4, 4] = 1
    out = psf_metrics(k, pitch=1.0, wavelength=1.0, r_main=1.0, r_guard=3.0)
    assert set(out) == {"L_contrast", "L_SLR_q", "L_SLR_i", "L_SLR"}
    # mean main m^2 = (1 + 4 * 0.25) / 5 = 0.4 ; side m^2 = 0.01 on 56 px
    assert out["L_contrast"].item() == pytest.approx(0.01 / 0.4, rel=1e-12)
    assert out["L_SLR_i"].item() == pytest.approx(56 * 0.01 / 2.0, rel=1e-12)
    assert out["L_SLR_q"].item() == pytest.approx(0.1, rel=1e-12)
    assert out["L_SLR"].item() == pytest.approx((0.1 + 0.28) / 2, rel=1e-12)
    assert out["L_SLR"].shape == ()
    # a complex, scaled and phase-rotated copy gives the same numbers
    out2 = psf_metrics(k.to(torch.complex128) * (3e-4 * np.exp(1.1j)), pitch=1.0, wavelength=1.0,
                       r_main=1.0, r_guard=3.0)
    for name in out:
        assert out2[name].item() == pytest.approx(out[name].item(), rel=1e-12)


def test_contrast_slr_paper_scene_counts():
    b_main, c = 0.8, 0.02
    di = np.arange(128)[:, None] - 64
    dj = np.arange(128)[None, :] - 64
    d2 = di ** 2 + dj ** 2
    n_main, n_side = int((d2 <= 576).sum()), int((d2 >= 1600).sum())
    k = np.full((128, 128), 0.05)
    k[d2 <= 576] = b_main
    k[d2 >= 1600] = c
    k[64, 64] = 1.0
    out = psf_metrics(torch.tensor(k), pitch=PITCH, wavelength=LAM)
    s_main = 1 + b_main ** 2 * (n_main - 1)
    assert out["L_contrast"].item() == pytest.approx(c ** 2 / (s_main / n_main), rel=1e-12)
    assert out["L_SLR_i"].item() == pytest.approx(n_side * c ** 2 / s_main, rel=1e-12)
    assert out["L_SLR_q"].item() == pytest.approx(c, rel=1e-12)


@pytest.mark.parametrize("q", [0.99, 0.5, 0.9, 1.0, 0.0])
def test_slr_q_linear_ramp(q):
    # side values form a uniform ramp 0 .. c (in flat order): quantile_q = q c exactly
    c = 0.2
    k = torch.full((9, 9), 0.3, dtype=torch.float64)
    k[4, 4] = 1.0
    reg = psf_regions(k, pitch=1.0, wavelength=1.0, r_main=1.0, r_guard=3.0)
    n = int(reg.side.sum())
    k[reg.side] = torch.linspace(0, c, n, dtype=torch.float64).flip(0)
    out = psf_metrics(k, pitch=1.0, wavelength=1.0, r_main=1.0, r_guard=3.0, quantile=q,
                      terms=["L_SLR_q"])
    assert list(out) == ["L_SLR_q"]
    assert out["L_SLR_q"].item() == pytest.approx(q * c, rel=1e-12, abs=1e-15)


def test_slr_q_matches_numpy_quantile_random():
    g = torch.Generator().manual_seed(4)
    k = torch.randn(4, 40, 40, dtype=torch.complex128, generator=g)
    k[:, 20, 20] = 20
    for q in (0.99, 0.73, 0.5):
        out = psf_metrics(k, pitch=0.1, wavelength=1.0, r_main=0.5, r_guard=1.0, quantile=q)
        for b in range(4):
            ref = np_metrics(k[b].numpy(), 5, 10, q)
            assert out["L_SLR_q"][b].item() == pytest.approx(ref["L_SLR_q"], rel=1e-12)
            assert torch.quantile(k[b].abs()[psf_regions(k[b], pitch=0.1, wavelength=1.0, r_main=0.5,
                                                         r_guard=1.0).side] / 20, q).item() \
                == pytest.approx(ref["L_SLR_q"], rel=1e-12)


def test_gaussian_matches_numpy():
    k = gaussian(128, 128, 64, 64, sigma=10.0)
    out = psf_metrics(k, pitch=PITCH, wavelength=LAM)
    ref = np_metrics(k.numpy(), R_MAIN_PX, R_GUARD_PX, 0.99)
    for name, v in ref.items():
        assert out[name].item() == pytest.approx(v, rel=1e-10)
    # the isotropic Gaussian is tiny outside 2.5 lambda = 4 sigma
    assert out["L_SLR_q"].item() < math.exp(-16 / 2) * 1.01


def test_peak_away_from_centre_and_batched_equals_per_item():
    ks = torch.stack([
        gaussian(128, 128, 64, 64, 9.0),
        gaussian(128, 128, 20, 100, 7.0),          # window clipped on two sides
        gaussian(128, 128, 127, 0, 12.0),          # peak in a corner
        gaussian(128, 128, 70, 50, 6.0) + 0.01 * torch.cos(torch.arange(128.0, dtype=torch.float64) / 3),
    ]).to(torch.complex128) * torch.exp(1j * torch.linspace(0, 2, 128, dtype=torch.float64))
    ref_k = gaussian(128, 128, 64, 64, 8.0).to(torch.complex128)
    batched = psf_metrics(ks, pitch=PITCH, wavelength=LAM, kappa_ref=ref_k)
    assert set(batched) == set(PSF_TERMS)
    for b in range(len(ks)):
        single = psf_metrics(ks[b], pitch=PITCH, wavelength=LAM, kappa_ref=ref_k)
        npref = np_metrics(ks[b].numpy(), R_MAIN_PX, R_GUARD_PX, 0.99)
        for name in PSF_TERMS:
            assert batched[name][b].item() == pytest.approx(single[name].item(), rel=1e-12, abs=1e-300)
        for name, v in npref.items():
            assert batched[name][b].item() == pytest.approx(v, rel=1e-10)
        expected_mean = (single["L_PSF"] + single["L_contrast"] + single["L_SLR_q"]
                         + single["L_SLR_i"]).item() / 4
        assert single["Mean"].item() == pytest.approx(expected_mean, rel=1e-12)
    # extra leading dimensions are kept
    out = psf_metrics(ks.reshape(2, 2, 128, 128), pitch=PITCH, wavelength=LAM, terms=("L_SLR",))
    assert out["L_SLR"].shape == (2, 2)
    torch.testing.assert_close(out["L_SLR"].reshape(-1), batched["L_SLR"])


def test_float32_agrees_with_float64():
    g = torch.Generator().manual_seed(5)
    k64 = gaussian(128, 128, 60, 70, 8.0).to(torch.complex128) \
        + 0.01 * torch.randn(128, 128, dtype=torch.complex128, generator=g)
    r64 = gaussian(128, 128, 64, 64, 8.0).to(torch.complex128)
    o64 = psf_metrics(k64[None], pitch=PITCH, wavelength=LAM, kappa_ref=r64)
    o32 = psf_metrics(k64[None].to(torch.complex64), pitch=PITCH, wavelength=LAM,
                      kappa_ref=r64.to(torch.complex64))
    for name in PSF_TERMS:
        assert o32[name].dtype == torch.float32
        assert o32[name].item() == pytest.approx(o64[name].item(), rel=2e-5)


def _small_kernel(seed=6):
    g = torch.Generator().manual_seed(seed)
    k = 0.3 * torch.randn(2, 12, 12, dtype=torch.complex128, generator=g)
    k[0, 6, 5] = 4.0 + 1j
    k[1, 3, 8] = -3.0j
    return k


@pytest.mark.slow
def test_psf_metrics_gradcheck():
    # pitch 0.5, wavelength 1: main r <= 3 px, side r >= 5 px; random values -> no ties
    k = _small_kernel().requires_grad_(True)
    ref = torch.randn(12, 12, dtype=torch.complex128, generator=torch.Generator().manual_seed(7))

    def f(x):
        out = psf_metrics(x, pitch=0.5, wavelength=1.0, kappa_ref=ref, quantile=0.9)
        return torch.stack([out[n] for n in PSF_TERMS])

    assert torch.autograd.gradcheck(f, (k,), eps=1e-7, atol=1e-6, rtol=1e-4)
    kr = k.detach().real.clone().requires_grad_(True)

    def fr(x):
        out = psf_metrics(x, pitch=0.5, wavelength=1.0, quantile=0.95, terms=["L_SLR", "L_contrast"])
        return torch.stack([out["L_SLR"], out["L_contrast"]])

    assert torch.autograd.gradcheck(fr, (kr,), eps=1e-7, atol=1e-6, rtol=1e-4)


@pytest.mark.parametrize("dtype", [torch.complex64, torch.float32, torch.complex128])
def test_gradients_finite_with_exact_zeros_and_ties(dtype):
    # main lobe only: the side region is all zeros (quantile among ties), exact zeros in the main lobe
    k = torch.zeros(3, 32, 32, dtype=dtype)
    k[0] = gaussian(32, 32, 16, 16, 2.0).to(dtype)
    k[0, 15, 16] = 0
    k[0][gaussian(32, 32, 16, 16, 2.0) < 1e-3] = 0
    k[1, 10, 10] = 1
    k[1, 10, 11] = 1            # tie for the peak
    # k[2] stays all zero
    k.requires_grad_(True)
    ref = gaussian(32, 32, 16, 16, 2.0).to(dtype)
    out = psf_metrics(k, pitch=0.1, wavelength=1.0, kappa_ref=ref)
    for name, v in out.items():
        assert torch.isfinite(v).all(), name
    assert out["L_SLR_q"][0].item() == 0 and out["L_contrast"][0].item() == 0
    assert out["L_SLR_q"][2].item() == 0 and out["L_SLR_i"][2].item() == 0
    assert out["L_PSF"][2].item() == pytest.approx(1.0)
    composite_loss(out, {n: 1.0 for n in PSF_TERMS}).backward()
    g = torch.view_as_real(k.grad) if k.grad.is_complex() else k.grad
    assert torch.isfinite(g).all()


# ---------------------------------------------------------------- argument errors

def test_psf_metrics_argument_errors():
    k = torch.randn(16, 16)
    with pytest.raises(ParameterError, match="needs kappa_ref"):
        psf_metrics(k, pitch=0.1, wavelength=1.0, terms=["Mean"])
    with pytest.raises(ParameterError, match="unknown PSF metric"):
        psf_metrics(k, pitch=0.1, wavelength=1.0, terms=["L_foo"])
    with pytest.raises(ParameterError, match="quantile"):
        psf_metrics(k, pitch=0.1, wavelength=1.0, quantile=1.5)
    with pytest.raises(ParameterError, match="r_guard"):
        psf_metrics(k, pitch=0.1, wavelength=1.0, r_main=2.0, r_guard=1.0)
    with pytest.raises(ParameterError, match="pitch"):
        psf_metrics(k, pitch=-0.1, wavelength=1.0)
    with pytest.raises(ParameterError, match="broadcast"):
        psf_metrics(k, pitch=0.1, wavelength=1.0, kappa_ref=torch.randn(3, 16, 16))
    with pytest.raises(ParameterError, match="dtype"):
        psf_metrics(torch.ones(4, 4, dtype=torch.int64), pitch=0.1, wavelength=1.0)
    reg = psf_regions(torch.randn(2, 5, 5), pitch=0.1, wavelength=1.0)
    with pytest.raises(ParameterError, match="side region"):
        check_regions(reg)
    check_regions(psf_regions(k, pitch=0.1, wavelength=0.2))   # side: r >= 5 px


# ---------------------------------------------------------------- training terms

def test_circular_convolve_delta_identity_and_shift():
    g = torch.Generator().manual_seed(8)
    img = torch.randn(2, 128, 128, dtype=torch.complex128, generator=g)
    delta = torch.zeros(128, 128, dtype=torch.complex128)
    delta[64, 64] = 1
    torch.testing.assert_close(circular_convolve(delta, img), img)
    shifted = torch.zeros(128, 128, dtype=torch.complex128)
    shifted[64, 65] = 1          # one column right of the centre -> image moves one column right
    torch.testing.assert_close(circular_convolve(shifted, img), torch.roll(img, 1, dims=-1))
    # a smaller window: its centre (h//2, w//2) is the zero shift too
    small = torch.zeros(5, 4)
    small[2, 2] = 1
    real_img = torch.randn(16, 16, dtype=torch.float64, generator=g)
    y = circular_convolve(small, real_img)
    assert not y.is_complex()
    torch.testing.assert_close(y, real_img)


def test_circular_convolve_matches_direct_sum():
    g = torch.Generator().manual_seed(9)
    ker = torch.randn(3, 4, dtype=torch.complex128, generator=g)
    img = torch.randn(6, 7, dtype=torch.complex128, generator=g)
    h, w = ker.shape
    H, W = img.shape
    k_np, i_np = ker.numpy(), img.numpy()
    expect = np.zeros((H, W), complex)
    for i in range(H):
        for j in range(W):
            for a in range(h):
                for b in range(w):
                    expect[i, j] += k_np[a, b] * i_np[(i - a + h // 2) % H, (j - b + w // 2) % W]
    np.testing.assert_allclose(circular_convolve(ker, img).numpy(), expect, atol=1e-12)
    # real path equals the complex path
    yr = circular_convolve(ker.real, img.real)
    np.testing.assert_allclose(yr.numpy(), circular_convolve(ker.real.to(torch.complex128),
                                                             img.real).real.numpy(), atol=1e-12)
    with pytest.raises(ParameterError, match="larger"):
        circular_convolve(torch.ones(8, 8), torch.ones(6, 7))


def test_l_conv_and_l_rec_known_answers():
    assert l_conv(torch.ones(2, 3, 4), torch.zeros(2, 3, 4)).item() == pytest.approx(12.0)
    y = torch.zeros(2, 3, 4, dtype=torch.complex64)
    y[0] = 1j
    assert l_conv(y, torch.zeros(3, 4)).item() == pytest.approx(6.0)     # items 12 and 0
    assert l_conv(torch.ones(3, 4), torch.zeros(3, 4)).shape == ()
    assert l_rec(torch.full((2, 1, 3, 4), 3.0), torch.ones(2, 1, 3, 4)).item() == pytest.approx(4.0)


def test_l_ent_known_answers():
    assert l_ent(torch.full((64, 32), 1 / 64, dtype=torch.float64)).item() == pytest.approx(math.log(64))
    p = torch.tensor([[0.5, 1.0], [0.5, 0.0], [0.0, 0.0], [0.0, 0.0]], dtype=torch.float64,
                     requires_grad=True)
    e = l_ent(p)
    assert e.item() == pytest.approx(math.log(2) / 2)          # columns: log 2 and 0
    e.backward()
    assert torch.isfinite(p.grad).all()
    # through a masked softmax: exact zeros, finite gradient on the logits
    logits = torch.randn(8, 3, dtype=torch.float64, requires_grad=True)
    mask = torch.zeros(8, 3, dtype=torch.bool)
    mask[:2, 1] = True
    p = torch.softmax(logits.masked_fill(mask, float("-inf")), dim=0)
    assert (p[:2, 1] == 0).all()
    l_ent(p).backward()
    assert torch.isfinite(logits.grad).all()
    assert torch.autograd.gradcheck(lambda x: l_ent(torch.softmax(x, 0)),
                                    (torch.randn(5, 3, dtype=torch.float64, requires_grad=True),))


def test_l_row_known_answers():
    p = torch.tensor([[1.0, 1.0], [1.0, 0.0], [0.5, 0.5], [0.0, 0.0]])
    assert l_row(p).item() == pytest.approx(1.0)               # row sums 2, 1, 1, 0
    assert l_row(torch.tensor([[1.0, 1.0, 1.0]])).item() == pytest.approx(4.0)
    assert l_row(torch.eye(4)[:, :2]).item() == 0
    batched = torch.stack([p, torch.zeros(4, 2)])
    assert l_row(batched).item() == pytest.approx(0.5)


def test_composite_loss_and_default_weights():
    assert dict(DEFAULT_WEIGHTS) == {"L_PSF": 10, "L_conv": 1, "L_rec": 10, "L_contrast": 10,
                                     "L_SLR": 10, "L_ent": 1, "L_row": 10}
    terms = {"L_PSF": torch.tensor(0.1), "L_conv": torch.tensor(2.0), "L_rec": torch.tensor(0.3),
             "L_contrast": torch.tensor([1e-3, 3e-3]), "L_SLR": torch.tensor(0.05),
             "L_ent": torch.tensor(1.5), "L_row": torch.tensor(0.0)}
    expect = 10 * 0.1 + 2.0 + 10 * 0.3 + 10 * 2e-3 + 10 * 0.05 + 1.5 + 0.0
    assert composite_loss(terms, DEFAULT_WEIGHTS).item() == pytest.approx(expect, rel=1e-6)
    assert composite_loss(terms).item() == pytest.approx(expect, rel=1e-6)
    # zero weights are skipped: the term may be missing or NaN
    w = dict(DEFAULT_WEIGHTS, L_conv=0.0, L_rec=0.0)
    t2 = dict(terms, L_conv=torch.tensor(float("nan")))
    del t2["L_rec"]
    assert composite_loss(t2, w).item() == pytest.approx(expect - 2.0 - 3.0, rel=1e-6)
    with pytest.raises(ParameterError, match="L_rec"):
        composite_loss(t2, DEFAULT_WEIGHTS)
    assert composite_loss(terms, {"L_PSF": 0.0}).item() == 0


def test_check_finite():
    x = torch.tensor([1.0, 2.0])
    assert check_finite("L_PSF", x) is x
    with pytest.raises(NumericalError, match=r"L_SLR_q is not finite: 1 NaN and 1 Inf"):
        check_finite("L_SLR_q", torch.tensor([1.0, float("nan"), float("inf")]))
    with pytest.raises(NumericalError, match="kappa"):
        check_finite("kappa", torch.tensor([1 + 1j, complex("nan")]))


@pytest.mark.parametrize("scale", [1e-30, 1e30])
def test_float32_extreme_scales_give_same_metrics(scale):
    # raw (unnormalised) kernels: |kappa|^2 would under/overflow float32 without internal scaling
    k = (gaussian(64, 64, 30, 33, 5.0) + 0.003 * torch.cos(torch.arange(64.0, dtype=torch.float64))).to(
        torch.complex64)
    ref = gaussian(64, 64, 32, 32, 5.0).to(torch.complex64)
    kw = dict(pitch=0.1, wavelength=1.0, r_main=0.8, r_guard=1.5)
    base = psf_metrics(k, kappa_ref=ref, **kw)
    big = psf_metrics(k * scale, kappa_ref=ref * (1 / scale), **kw)
    for name in PSF_TERMS:
        assert big[name].item() == pytest.approx(base[name].item(), rel=1e-5)
        assert base[name].item() > 0


def test_terms_selection_returns_only_requested():
    k = gaussian(32, 32, 16, 16, 3.0)
    out = psf_metrics(k, pitch=0.1, wavelength=1.0, kappa_ref=k, terms="L_PSF")
    assert list(out) == ["L_PSF"] and out["L_PSF"].item() == pytest.approx(0.0, abs=1e-15)
    out = psf_metrics(k, pitch=0.1, wavelength=1.0, kappa_ref=k, terms=["Mean", "L_SLR"])
    assert list(out) == ["Mean", "L_SLR"]
    out = psf_metrics(k, pitch=0.1, wavelength=1.0)
    assert list(out) == ["L_contrast", "L_SLR_q", "L_SLR_i", "L_SLR"]


def test_elementwise_reduction_path_matches_matmul_path(monkeypatch):
    # accelerators reduce with multiply-and-sum instead of matmul: check both agree (on CPU)
    import arraysel.objective.reductions as R

    ks = _small_kernel(11).repeat(3, 1, 1)
    ks[2] = ks[2].conj() * 0.5
    ref = torch.randn(12, 12, dtype=torch.complex128, generator=torch.Generator().manual_seed(12))
    kw = dict(pitch=0.5, wavelength=1.0, kappa_ref=ref, quantile=0.9)
    a = psf_metrics(ks, **kw)
    b_ref = si_mse(ks, ks.flip(0))
    monkeypatch.setattr(R, "use_matmul", lambda x: False)
    b = psf_metrics(ks, **kw)
    for name in PSF_TERMS:
        torch.testing.assert_close(a[name], b[name], rtol=1e-12, atol=1e-15)
    torch.testing.assert_close(si_mse(ks, ks.flip(0)), b_ref, rtol=1e-12, atol=1e-15)


def test_shared_peak_batch_matches_one_by_one():
    """A batch whose kernels share their peak pixel (the usual case: windows are cut around
    the peak) uses broadcast regions; every metric equals the one-kernel evaluation."""
    g = torch.Generator().manual_seed(3)
    n = 33
    yy, xx = torch.meshgrid(torch.arange(n), torch.arange(n), indexing="ij")
    base = torch.exp(-((yy - 16.0) ** 2 + (xx - 16.0) ** 2) / 8.0)
    noise = 0.05 * torch.randn(5, n, n, dtype=torch.complex64, generator=g)
    kappa = base.to(torch.complex64)[None] * (1 + 0.1 * torch.arange(5)[:, None, None]) + noise
    kappa[:, 16, 16] = 3.0  # one common peak
    ref = base.to(torch.complex64)
    kw = dict(pitch=1e-4, wavelength=2e-4, kappa_ref=ref)
    batch = psf_metrics(kappa, **kw)
    for i in range(5):
        one = psf_metrics(kappa[i], **kw)
        for name, v in one.items():
            assert torch.allclose(batch[name][i], v, rtol=1e-5, atol=1e-7), name
    # distinct peaks take the per-kernel path and agree as well
    kappa[2, 16, 16] = 0.5
    kappa[2, 10, 12] = 3.0
    batch = psf_metrics(kappa, **kw)
    for i in range(5):
        one = psf_metrics(kappa[i], **kw)
        for name, v in one.items():
            assert torch.allclose(batch[name][i], v, rtol=1e-5, atol=1e-7), name


# ---------------------------------------------------------------- the compiled pass

def _psf_like(b, h, w, dtype, seed):
    """Kernels with a main lobe, side lobes and noise; peaks moved to edges and corners."""
    g = torch.Generator().manual_seed(seed)
    i = torch.arange(h, dtype=torch.float64)[:, None]
    j = torch.arange(w, dtype=torch.float64)[None, :]
    ks = []
    for n in range(b):
        i0 = float(torch.randint(0, h, (1,), generator=g))
        j0 = float(torch.randint(0, w, (1,), generator=g))
        lobe = torch.exp(-((i - i0) ** 2 + (j - j0) ** 2) / 40.0) * torch.exp(1j * 0.4 * (i - i0))
        side = 0.05 * torch.cos((j - j0) / 2.0) * torch.exp(-((i - i0) / 30.0) ** 2)
        noise = 0.01 * torch.randn(h, w, dtype=torch.complex128, generator=g)
        ks.append(lobe + side + noise)
    return (torch.stack(ks) * 1e-3).to(dtype)


@pytest.mark.parametrize("dtype", [torch.complex64, torch.complex128, torch.float32, torch.float64])
def test_compiled_pass_equals_torch_operations(dtype):
    """The compiled pass against torch's operations in float64 (the same definitions): float64
    kernels to rounding; float32 ones closer than torch's own float32 operations; the quantile's
    order statistics are the same pixels (k2 is formed as torch forms it)."""
    h, w = 48, 40
    ks = _psf_like(10, h, w, torch.complex128, 3)
    if not dtype.is_complex:
        ks = ks.real
    ks[3] = 0                                             # a zero kernel
    ks[4] = ks[4] * 1e30 if dtype in (torch.complex128, torch.float64) else ks[4] * 1e20
    ks[5, 7, 9] = ks[5].abs().max() * 2                  # a single-pixel peak
    ks[6, 2, 3] = ks[6, 20, 30] = ks[6].abs().max() * 2   # a tie: the first in row-major order
    ref = _psf_like(1, h, w, torch.complex128, 11)[0]
    k = ks.to(dtype)
    r = ref.to(torch.complex64 if dtype in (torch.complex64, torch.float32) else torch.complex128)
    for q, rm, rg in [(0.99, 1.5, 2.5), (0.5, 1.0, 1.0), (0.0, 2.0, 3.0), (1.0, 0.3, 0.7), (0.99, 1.0, 80.0)]:
        kw = dict(pitch=0.1, wavelength=1.0, r_main=rm, r_guard=rg, quantile=q)
        fast = psf_metrics(k, kappa_ref=r, compiled=True, **kw)
        slow = psf_metrics(k, kappa_ref=r, compiled=False, **kw)
        exact = psf_metrics(k.to(torch.complex128 if dtype.is_complex else torch.float64),
                            kappa_ref=r.to(torch.complex128), compiled=False, **kw)
        for name in PSF_TERMS:
            assert fast[name].dtype == slow[name].dtype
            assert bool(torch.isfinite(fast[name]).all())
            f, s_, e = fast[name].double(), slow[name].double(), exact[name]
            if dtype in (torch.complex128, torch.float64):
                torch.testing.assert_close(f, e, rtol=1e-12, atol=1e-14)
            else:
                assert float((f - e).abs().max()) <= max(float((s_ - e).abs().max()), 1e-7) + 1e-7, name
        torch.testing.assert_close(fast["L_SLR_q"], slow["L_SLR_q"], rtol=2e-7, atol=0)
        # the zero kernel: L_PSF 1, ratios 0, as the torch path
        assert fast["L_PSF"][3].item() == pytest.approx(1.0) and fast["L_SLR_i"][3].item() == 0.0
    # r_guard beyond the window: an empty side region gives 0 side terms on both paths
    kw = dict(pitch=0.1, wavelength=1.0, r_main=1.0, r_guard=80.0)
    fast = psf_metrics(k, kappa_ref=r, compiled=True, **kw)
    assert float(fast["L_SLR_i"].abs().max()) == 0.0 and float(fast["L_SLR_q"].abs().max()) == 0.0


def test_compiled_pass_known_answers_and_non_finite_kernels():
    # the piecewise-constant kernel of test_contrast_slr_piecewise_constant_by_hand, batched with
    # copies shifted so that the regions are cut by the window's edges differently
    k = torch.full((9, 9), 0.1, dtype=torch.float64)
    k[2:7, 2:7] = 0.3
    for di, dj in [(1, 0), (-1, 0), (0, 1), (0, -1)]:
        k[4 + di, 4 + dj] = 0.5
    k[4, 4] = 1
    out = psf_metrics(k[None].to(torch.complex128), pitch=1.0, wavelength=1.0, r_main=1.0, r_guard=3.0,
                      kappa_ref=k, compiled=True)
    assert out["L_PSF"].item() == pytest.approx(0.0, abs=1e-15)
    assert out["L_contrast"].item() == pytest.approx(0.01 / 0.4, rel=1e-12)
    assert out["L_SLR_i"].item() == pytest.approx(56 * 0.01 / 2.0, rel=1e-12)
    assert out["L_SLR_q"].item() == pytest.approx(0.1, rel=1e-12)
    # SI-MSE: a scaled, phase-rotated copy scores 0, an orthogonal kernel 1
    a = torch.zeros(2, 4, 4, dtype=torch.complex128)
    a[0, 1, 1] = 2j
    a[1, 2, 2] = 1
    ref = torch.zeros(4, 4, dtype=torch.complex128)
    ref[1, 1] = 1
    out = psf_metrics(a, pitch=1.0, wavelength=1.0, r_main=1.0, r_guard=1.0, kappa_ref=ref, compiled=True)
    assert out["L_PSF"].tolist() == pytest.approx([0.0, 1.0], abs=1e-15)
    # a NaN or Inf entry gives NaN metrics for that kernel only, never a finite number
    ks = _psf_like(4, 16, 16, torch.complex64, 5)
    ks[1, 3, 3] = float("nan")
    ks[2, 4, 4] = float("inf")
    out = psf_metrics(ks, pitch=0.1, wavelength=1.0, kappa_ref=ks[0], compiled=True)
    for name in PSF_TERMS:
        assert bool(torch.isnan(out[name][1:3]).all()), name
        assert bool(torch.isfinite(out[name][[0, 3]]).all()), name


def test_compiled_pass_is_taken_only_where_it_applies(monkeypatch):
    calls = []
    real = metric_kernels.psf_metrics_compiled
    monkeypatch.setattr(metric_kernels, "psf_metrics_compiled", lambda *a, **k: calls.append(1) or real(*a, **k))
    monkeypatch.setattr(compiled, "MIN_BATCH", 3)
    k = _psf_like(3, 16, 16, torch.complex64, 2)
    kw = dict(pitch=0.1, wavelength=1.0, kappa_ref=k[0])
    psf_metrics(k, **kw)
    assert len(calls) == 1
    # fewer kernels than the smallest batch: torch, unless told
    psf_metrics(k[:2], **kw)
    assert len(calls) == 1
    psf_metrics(k[:2], compiled=True, **kw)
    assert len(calls) == 2
    calls.clear()
    psf_metrics(k, **kw)
    assert len(calls) == 1
    # a gradient wanted, a reference of higher precision, compiled=False, half precision: torch
    x = k.clone().requires_grad_(True)
    out = psf_metrics(x, **kw)
    out["Mean"].sum().backward()
    assert x.grad is not None and bool(torch.isfinite(torch.view_as_real(x.grad)).all())
    psf_metrics(k, pitch=0.1, wavelength=1.0, kappa_ref=k[0].to(torch.complex128))
    psf_metrics(k, compiled=False, **kw)
    psf_metrics(k.real.half(), pitch=0.1, wavelength=1.0)
    assert len(calls) == 1
    with torch.no_grad():
        psf_metrics(x, **kw)
    assert len(calls) == 2
