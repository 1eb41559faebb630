"""Tests of arraysel.e2e.recon: convolution operator, unrolled ISTA, head, metrics."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from arraysel.errors import ParameterError
from arraysel.e2e.recon import (ConvolutionOperator, Reconstructor, ResidualHead, UnrolledISTA,
                            complex_soft_threshold, convolve, features, mse, psnr, ssim)

DEVICES = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])


pytestmark = pytest.mark.usefixtures("one_thread")


@pytest.fixture(params=DEVICES)
def device(request):
    return torch.device(request.param)


def _crandn(*shape, gen, dtype=torch.float64):
    return torch.complex(torch.randn(shape, generator=gen, dtype=dtype),
                         torch.randn(shape, generator=gen, dtype=dtype))


# -- convolution operator -------------------------------------------------------

@pytest.mark.parametrize("n", [7, 8])
def test_delta_kernel_at_centre_is_identity_and_shift(n, device):
    k = torch.zeros(n, n, dtype=torch.complex128, device=device)
    k[n // 2, n // 2] = 1
    x = torch.randn(2, 1, n, n, dtype=torch.float64, device=device)
    torch.testing.assert_close(ConvolutionOperator(k).A(x), x.to(torch.complex128))
    k2 = torch.zeros_like(k)
    k2[n // 2 + 1, n // 2 - 2] = 1  # one row down, two columns left
    y = ConvolutionOperator(k2).A(x).real
    torch.testing.assert_close(y, torch.roll(x, shifts=(1, -2), dims=(-2, -1)))


def test_convolution_matches_direct_sum():
    n, c = 6, 3
    gen = torch.Generator().manual_seed(0)
    k = _crandn(n, n, gen=gen)
    x = _crandn(1, 1, n, n, gen=gen)
    kn, xn = k.numpy(), x[0, 0].numpy()
    ref = np.zeros((n, n), complex)
    for i in range(n):
        for j in range(n):
            for u in range(n):
                for v in range(n):
                    ref[i, j] += kn[u, v] * xn[(i - (u - c)) % n, (j - (v - c)) % n]
    np.testing.assert_allclose(convolve(k, x)[0, 0].numpy(), ref, atol=1e-12)


@pytest.mark.parametrize("n,m", [(6, 4), (5, 7), (8, 8)])
def test_linear_convolution_matches_direct_sum_without_wraparound(n, m):
    """Linear ('same') convolution: the scene is zero outside its field, nothing wraps around."""
    from arraysel.e2e.recon import LinearConvolutionOperator

    c = m // 2
    gen = torch.Generator().manual_seed(3)
    k = _crandn(m, m, gen=gen).to(torch.complex128)
    x = _crandn(1, 1, n, n, gen=gen).to(torch.complex128)
    kn, xn = k.numpy(), x[0, 0].numpy()
    ref = np.zeros((n, n), complex)
    for i in range(n):
        for j in range(n):
            for u in range(m):
                for v in range(m):
                    a, b = i - (u - c), j - (v - c)
                    if 0 <= a < n and 0 <= b < n:
                        ref[i, j] += kn[u, v] * xn[a, b]
    op = LinearConvolutionOperator(k, n)
    np.testing.assert_allclose(op.A(x)[0, 0].numpy(), ref, atol=1e-12)
    assert op.adjointness_test(generator=gen) < 1e-12
    # a point on the left edge spreads to the right only: the circular model would wrap it
    e = torch.zeros(1, 1, n, n, dtype=torch.complex128)
    e[0, 0, n // 2, 0] = 1
    y = op.A(e)[0, 0]
    assert m - c < n and float(y[:, m - c:].abs().max()) < 1e-12  # reaches columns 0 .. m-1-c only
    assert float(y[:, :m - c].abs().max()) > 0.1
    # lipschitz bounds ||A||^2 (power iteration)
    v = _crandn(1, 1, n, n, gen=gen).to(torch.complex128)
    for _ in range(200):
        v = op.A_adjoint(op.A(v))
        v = v / torch.linalg.vector_norm(v)
    assert float(torch.linalg.vector_norm(op.A(v)) ** 2) <= float(op.lipschitz) * (1 + 1e-9)


def test_reconstructor_reblur_and_magnitude_base():
    """init_magnitude_base: the head starts as |input| + eta r; reblur feeds op_ref.A(X) to it."""
    from arraysel.e2e.recon import LinearConvolutionOperator

    torch.manual_seed(0)
    model = Reconstructor(2, base_channels=4).init_magnitude_base()
    with torch.no_grad():
        model.head.eta.zero_()
    gen = torch.Generator().manual_seed(4)
    k = torch.zeros(5, 5, dtype=torch.complex64)
    k[2, 2] = 1
    op = LinearConvolutionOperator(k, 8)
    y = _crandn(2, 1, 8, 8, gen=gen)
    out, x = model(y, op, return_x=True)
    torch.testing.assert_close(out, x.abs(), atol=1e-6, rtol=1e-6)
    shift = torch.zeros(5, 5, dtype=torch.complex64)
    shift[3, 2] = 1  # one row down
    ref = LinearConvolutionOperator(shift, 8)
    out2 = model(y, op, reblur=ref)
    torch.testing.assert_close(out2, ref.A(x).abs(), atol=1e-6, rtol=1e-6)


def test_identity_head_start_returns_its_base_input_at_step_0():
    """init_identity_head: at step 0 I_hat = |z| exactly (z = X, or the re-imaged estimate),
    whatever the random head weights; reblur_mode='correct' feeds z = Y + op_ref.A(X) - op.A(X)."""
    from arraysel.e2e.recon import LinearConvolutionOperator

    gen = torch.Generator().manual_seed(5)
    k = _crandn(5, 5, gen=gen).to(torch.complex64)
    op = LinearConvolutionOperator(k, 8)
    ref = LinearConvolutionOperator(_crandn(5, 5, gen=gen).to(torch.complex64), 8)
    y = _crandn(2, 1, 8, 8, gen=gen).to(torch.complex64)
    for mode in ("image", "correct"):
        torch.manual_seed(0)
        model = Reconstructor(3, base_channels=4, reblur_mode=mode).init_identity_head()
        assert float(model.head.eta.detach()) == 0.0
        out, x = model(y, op, return_x=True)
        assert float(x.detach().abs().max()) > 0  # a non-trivial estimate: the test can fail
        torch.testing.assert_close(out, x.abs(), atol=1e-6, rtol=1e-6)
        out_r = model(y, op, reblur=ref)
        z = y + ref.A(x) - op.A(x) if mode == "correct" else ref.A(x)
        torch.testing.assert_close(out_r, z.abs(), atol=1e-5, rtol=1e-5)
    # 'correct' with the reference kernel itself passes the measurement through unchanged
    torch.testing.assert_close(model(y, op, reblur=op), y.abs(), atol=1e-5, rtol=1e-5)
    # without init_identity_head the random residual branch moves the output (eta = 0.1)
    torch.manual_seed(0)
    plain = Reconstructor(3, base_channels=4, reblur_mode="correct").init_magnitude_base()
    assert float((plain(y, op, reblur=op) - y.abs()).detach().abs().max()) > 1e-4
    # the residual branch still learns: eta gets a gradient at step 0
    model.zero_grad()
    ((model(y, op, reblur=ref) - 1.0) ** 2).mean().backward()
    assert model.head.eta.grad is not None and float(model.head.eta.grad.abs()) > 0
    with pytest.raises(ParameterError, match="reblur_mode"):
        Reconstructor(2, base_channels=4, reblur_mode="reblur")


@pytest.mark.parametrize("dtype,tol", [(torch.complex128, 1e-12), (torch.complex64, 1e-5)])
def test_adjointness(dtype, tol, device):
    gen = torch.Generator().manual_seed(1)
    op = ConvolutionOperator(_crandn(16, 16, gen=gen).to(dtype=dtype, device=device))
    assert op.adjointness_test(generator=gen) < tol


def test_lipschitz_is_operator_norm_squared():
    gen = torch.Generator().manual_seed(2)
    op = ConvolutionOperator(_crandn(12, 12, gen=gen))
    x = _crandn(1, 1, 12, 12, gen=gen)
    for _ in range(300):  # power iteration on A^H A
        x = op.A_adjoint(op.A(x))
        x = x / torch.linalg.vector_norm(x)
    est = torch.linalg.vector_norm(op.A(x)) ** 2
    assert float(est) == pytest.approx(float(op.lipschitz), rel=1e-6)


def test_operator_rejects_bad_shapes():
    with pytest.raises(ParameterError):
        ConvolutionOperator(torch.zeros(4, 5))
    with pytest.raises(ParameterError):
        ConvolutionOperator(torch.zeros(4, 4)).A(torch.zeros(1, 1, 5, 5))


# -- soft threshold ----------------------------------------------------------------

def test_soft_threshold_values():
    z = torch.tensor([3 + 4j, 0.1 + 0j, 0j, -2 + 0j], dtype=torch.complex128)
    out = complex_soft_threshold(z, 1.0, eps=1e-300)
    torch.testing.assert_close(out, torch.tensor([3 * 0.8 + 4j * 0.8, 0, 0, -1 + 0j],
                                                 dtype=torch.complex128))
    torch.testing.assert_close(complex_soft_threshold(torch.tensor([-2.0, 0.5]), 1.0, eps=1e-30),
                               torch.tensor([-1.0, 0.0]))


@pytest.mark.parametrize("lam", [0.0, 0.3])
def test_soft_threshold_gradient_finite_at_zero(lam):
    for z0 in (torch.zeros(4, dtype=torch.complex128), torch.zeros(4, dtype=torch.float64)):
        z = z0.clone().requires_grad_(True)
        lamt = torch.tensor(lam, dtype=torch.float64, requires_grad=True)
        out = complex_soft_threshold(z, lamt)
        (out.real.sum() + out.abs().sum()).backward()
        assert torch.isfinite(torch.view_as_real(z.grad) if z.grad.is_complex() else z.grad).all()
        assert torch.isfinite(lamt.grad)


def test_soft_threshold_gradcheck():
    gen = torch.Generator().manual_seed(3)
    z = (_crandn(6, gen=gen) * 2).requires_grad_(True)
    lam = torch.tensor(0.5, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda a, b: complex_soft_threshold(a, b, 1e-3), (z, lam),
                                    eps=1e-6, atol=1e-5, rtol=1e-4)


# -- unrolled ISTA ------------------------------------------------------------------

def _numpy_ista(kappa, y, alphas, lams, eps):
    """Plain numpy ISTA, written independently of arraysel (explicit FFT roll)."""
    K = np.fft.fft2(np.fft.ifftshift(kappa))
    A = lambda v: np.fft.ifft2(K * np.fft.fft2(v))
    AH = lambda v: np.fft.ifft2(np.conj(K) * np.fft.fft2(v))
    x = np.zeros_like(y)
    for a, lam in zip(alphas, lams):
        z = x - a * AH(A(x) - y)
        mag = np.abs(z)
        x = z / (mag + eps) * np.maximum(mag - lam, 0)
    return x


def test_ista_matches_numpy_reference():
    n, T = 16, 5
    gen = torch.Generator().manual_seed(4)
    kappa = _crandn(n, n, gen=gen) * torch.exp(-torch.arange(n, dtype=torch.float64) / 3)
    y = _crandn(2, 1, n, n, gen=gen)
    fractions = torch.tensor([0.2, 0.5, 0.9, 0.7, 0.4], dtype=torch.float64)
    lams = torch.tensor([0.05, 0.1, 0.01, 0.2, 0.02], dtype=torch.float64)
    ista = UnrolledISTA(T, eps=1e-8).double()
    ista.initialise(fractions, lams)
    op = ConvolutionOperator(kappa)
    L = float(op.lipschitz)
    torch.testing.assert_close(ista.alphas(L), fractions * 2 / L)
    torch.testing.assert_close(ista.lambdas(), lams)
    out = ista(y, op)
    ref = np.stack([_numpy_ista(kappa.numpy(), y[b, 0].numpy(), (fractions * 2 / L).numpy(),
                                lams.numpy(), 1e-8) for b in range(2)])[:, None]
    np.testing.assert_allclose(out.detach().numpy(), ref, rtol=1e-10, atol=1e-12)


def test_ista_step_size_bounded_for_any_raw_parameter():
    ista = UnrolledISTA(6)
    with torch.no_grad():
        ista.a.copy_(torch.tensor([-1e4, -30.0, 0.0, 5.0, 80.0, 1e6]))
        ista.b.copy_(torch.tensor([-1e4, -3.0, 0.0, 1.0, 50.0, 1e6]))
    for L in (1e-3, 1.0, 37.5, 1e5):
        a = ista.alphas(L)
        assert torch.all(a <= 2 / L * (1 + 1e-6)) and torch.all(a >= 0)
    assert torch.all(ista.lambdas() >= 0)
    with pytest.raises(ParameterError):
        ista.initialise(1.0, 0.1)


def test_ista_recovers_sparse_signal_and_converges():
    n = 16
    k = torch.zeros(n, n, dtype=torch.complex128)
    k[n // 2, n // 2], k[n // 2, n // 2 + 1], k[n // 2 + 1, n // 2] = 1.0, 0.5, 0.25j
    x = torch.zeros(1, 1, n, n, dtype=torch.complex128)
    x[0, 0, 3, 4], x[0, 0, 10, 12] = 2.0, -1.5j
    op = ConvolutionOperator(k)
    ista = UnrolledISTA(200, step_fraction=0.9, lam=1e-4).double()
    with torch.no_grad():
        its = ista(op.A(x), op, return_all=True)
    errs = [float(torch.linalg.vector_norm(xt - x)) for xt in its]
    assert errs[-1] < 1e-2 * errs[0]


# -- features and head --------------------------------------------------------------

def test_features_values_and_stability_at_zero():
    X = torch.tensor([[[[3 + 4j, 0j]]]], dtype=torch.complex128, requires_grad=True)
    phi = features(X, eps=1e-6)
    assert phi.shape == (1, 5, 1, 2)
    torch.testing.assert_close(phi[0, :, 0, 0], torch.tensor([3, 4, 5, 0.6, 0.8], dtype=torch.float64))
    torch.testing.assert_close(phi[0, :, 0, 1], torch.zeros(5, dtype=torch.float64))
    phi.sum().backward()
    assert torch.isfinite(torch.view_as_real(X.grad)).all()
    assert features(torch.rand(2, 1, 4, 4)).shape == (2, 5, 4, 4)


@pytest.mark.parametrize("n", [16, 15])
def test_head_shapes_and_skips(n):
    torch.manual_seed(0)
    head = ResidualHead()  # paper widths: 32, 64, 128
    phi = torch.randn(2, 5, n, n)
    out, mid = head(phi, return_intermediates=True)
    assert out.shape == (2, 1, n, n)
    for name, ch in [("x1", 32), ("x2", 64), ("x3", 128), ("x4", 64), ("skip", 64), ("x5", 32),
                     ("r", 1), ("b", 1)]:
        assert mid[name].shape == (2, ch, n, n), name
    seen = {}
    head.conv5.register_forward_pre_hook(lambda m, a: seen.__setitem__("conv5", a[0]))
    head.out.register_forward_pre_hook(lambda m, a: seen.__setitem__("out", a[0]))
    out2 = head(phi)
    torch.testing.assert_close(seen["conv5"], mid["x4"] + mid["x2"] + head.proj(mid["x3"]))
    torch.testing.assert_close(seen["out"], mid["x5"] + mid["x1"])
    torch.testing.assert_close(out2, mid["b"] + head.eta * mid["r"])
    # LeakyReLU(0.1) after the hidden convolutions: x1 = act(conv1(phi))
    torch.testing.assert_close(mid["x1"], torch.nn.functional.leaky_relu(head.conv1(phi), 0.1))
    # no activation on the output conv, the base or the projection
    torch.testing.assert_close(mid["r"], head.out(mid["x5"] + mid["x1"]))
    torch.testing.assert_close(mid["b"], head.base(phi))


def test_zero_residual_gives_base_branch():
    head = ResidualHead(base_channels=4)
    with torch.no_grad():
        head.eta.zero_()
    phi = torch.randn(3, 5, 8, 8)
    assert torch.equal(head(phi), head.base(phi))


def test_reconstructor_end_to_end_gradients():
    n = 16
    gen = torch.Generator().manual_seed(6)
    kappa = _crandn(n, n, gen=gen).to(torch.complex64).requires_grad_(True)
    rec = Reconstructor(n_layers=3, base_channels=4)
    y = convolve(kappa, torch.rand(2, 1, n, n))
    out, x = rec(y, kappa, return_x=True)
    assert out.shape == (2, 1, n, n) and x.shape == (2, 1, n, n) and x.is_complex()
    out.square().mean().backward()
    assert torch.isfinite(torch.view_as_real(kappa.grad)).all() and kappa.grad.abs().sum() > 0
    for name, p in rec.named_parameters():
        assert p.grad is not None and torch.isfinite(p.grad).all(), name


# -- metrics -------------------------------------------------------------------------

def test_mse_psnr():
    x = torch.zeros(2, 1, 4, 4)
    y = torch.full((2, 1, 4, 4), 0.1)
    assert float(mse(x, y)) == pytest.approx(0.01)
    assert float(psnr(x, y)) == pytest.approx(20.0)
    assert float(psnr(x, y, data_range=10)) == pytest.approx(40.0)
    assert psnr(x, x).item() == math.inf
    assert mse(x, y, reduction="none").shape == (2,)


def test_ssim_identical_is_one():
    x = torch.rand(2, 1, 24, 24, generator=torch.Generator().manual_seed(7))
    torch.testing.assert_close(ssim(x, x), torch.tensor(1.0))


@pytest.mark.parametrize("a,b", [(0.2, 0.7), (0.0, 1.0), (0.5, 0.5)])
def test_ssim_constant_images_analytic(a, b):
    x = torch.full((1, 1, 16, 16), a, dtype=torch.float64)
    y = torch.full((1, 1, 16, 16), b, dtype=torch.float64)
    c1 = 0.01 ** 2
    expected = (2 * a * b + c1) / (a * a + b * b + c1)  # sigma terms: C2 / C2 = 1
    assert float(ssim(x, y)) == pytest.approx(expected, rel=1e-9)


def test_ssim_single_window_by_hand():
    gen = torch.Generator().manual_seed(8)
    x = torch.rand(1, 1, 11, 11, generator=gen, dtype=torch.float64)
    y = (x + 0.3 * torch.rand(1, 1, 11, 11, generator=gen, dtype=torch.float64)).clamp(0, 1)
    g = np.exp(-((np.arange(11) - 5.0) ** 2) / (2 * 1.5 ** 2))
    w = np.outer(g, g) / np.outer(g, g).sum()
    xn, yn = x[0, 0].numpy(), y[0, 0].numpy()
    mx, my = (w * xn).sum(), (w * yn).sum()
    vx, vy = (w * (xn - mx) ** 2).sum(), (w * (yn - my) ** 2).sum()
    cxy = (w * (xn - mx) * (yn - my)).sum()
    c1, c2 = 0.01 ** 2, 0.03 ** 2
    ref = (2 * mx * my + c1) * (2 * cxy + c2) / ((mx ** 2 + my ** 2 + c1) * (vx + vy + c2))
    assert float(ssim(x, y)) == pytest.approx(ref, rel=1e-10)
    assert float(ssim(x, y)) == pytest.approx(float(ssim(y, x)), rel=1e-12)
    with pytest.raises(ParameterError, match="window"):
        ssim(x[..., :10, :10], y[..., :10, :10])
