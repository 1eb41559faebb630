"""Convolutional forward model, unrolled ISTA and the residual CNN head of the paper (``docs/training.md``).

Shapes: scenes, measurements and reconstructions are ``(B, 1, n, n)``
tensors; a PSF kernel ``kappa`` is ``(n, n)`` complex. The kernel's centre
pixel ``(n // 2, n // 2)`` is the zero shift, so a kernel equal to 1 there
and 0 elsewhere is the identity. All convolutions are circular (FFT).
"""
from __future__ import annotations

import math

import torch
import torch.nn as nn
import torch.nn.functional as F

from arraysel.errors import NumericalError, ParameterError, check_choice, check_number
from arraysel.objective.metrics import kernel_spectrum

__all__ = [
    "ConvolutionOperator", "LinearConvolutionOperator", "convolve", "complex_soft_threshold", "UnrolledISTA", "features",
    "ResidualHead", "Reconstructor", "mse", "psnr", "ssim",
]


def _complex_dtype(dtype: torch.dtype) -> torch.dtype:
    if dtype.is_complex:
        return dtype
    return torch.complex128 if dtype == torch.float64 else torch.complex64


class ConvolutionOperator:
    """Circular convolution with a PSF kernel: ``A(x) = IFFT2(FFT2(kappa_0) . FFT2(x))``.

    The one circular convolution of the package,
    :func:`arraysel.objective.metrics.circular_convolve`, with its transfer function
    (:func:`~arraysel.objective.metrics.kernel_spectrum`) computed once per kernel.

    ``kappa``: ``(n, n)`` real or complex tensor; ``kappa_0`` is ``kappa``
    rolled so that its pixel ``(n//2, n//2)`` lands on ``(0, 0)``. Gradients
    flow to ``kappa`` (the operator is rebuilt from the current kernel at
    every training step).

    Example
    -------
    >>> k = torch.zeros(8, 8, dtype=torch.complex64); k[4, 4] = 1
    >>> x = torch.randn(2, 1, 8, 8)
    >>> torch.allclose(ConvolutionOperator(k).A(x).real, x, atol=1e-6)
    True
    """

    def __init__(self, kappa: torch.Tensor):
        if not isinstance(kappa, torch.Tensor) or kappa.ndim != 2 or kappa.shape[0] != kappa.shape[1]:
            shape = tuple(kappa.shape) if isinstance(kappa, torch.Tensor) else type(kappa).__name__
            raise ParameterError(f"kappa must be a square (n, n) tensor, got {shape}")
        self.kappa = kappa.to(_complex_dtype(kappa.dtype))
        self.n = kappa.shape[-1]
        self.K = kernel_spectrum(self.kappa, (self.n, self.n))

    @property
    def lipschitz(self) -> torch.Tensor:
        """``||A||^2 = max |FFT2(kappa)|^2`` (a 0-d real tensor, attached to the graph)."""
        return (self.K.real ** 2 + self.K.imag ** 2).max()

    def _check(self, x: torch.Tensor) -> torch.Tensor:
        if x.shape[-2:] != (self.n, self.n):
            raise ParameterError(f"input has spatial shape {tuple(x.shape[-2:])}, the kernel is "
                                 f"{self.n} x {self.n}")
        return x.to(self.K.dtype)

    def A(self, x: torch.Tensor) -> torch.Tensor:
        """Forward model ``kappa (*) x`` (complex output, same shape as ``x``)."""
        return torch.fft.ifft2(self.K * torch.fft.fft2(self._check(x)))

    def A_adjoint(self, y: torch.Tensor) -> torch.Tensor:
        """Adjoint ``A^H y``: correlation with the kernel, ``IFFT2(conj(K) . FFT2(y))``."""
        return torch.fft.ifft2(self.K.conj() * torch.fft.fft2(self._check(y)))

    __call__ = A

    def adjointness_test(self, batch: int = 2, generator: torch.Generator | None = None) -> float:
        """Relative error ``|<A x, y> - <x, A^H y>| / |<A x, y>|`` for random complex x, y.

        Close to machine precision (about 1e-7 in complex64, 1e-15 in
        complex128) for a correct adjoint.
        """
        shape = (batch, 1, self.n, self.n)
        real = torch.float64 if self.K.dtype == torch.complex128 else torch.float32

        def rnd():
            return torch.complex(torch.randn(shape, generator=generator, dtype=real),
                                 torch.randn(shape, generator=generator, dtype=real)).to(self.K.device)

        with torch.no_grad():
            x, y = rnd(), rnd()
            lhs = torch.vdot(self.A(x).flatten(), y.flatten())
            rhs = torch.vdot(x.flatten(), self.A_adjoint(y).flatten())
            return float((lhs - rhs).abs() / lhs.abs().clamp_min(torch.finfo(real).tiny))


class LinearConvolutionOperator(ConvolutionOperator):
    """Linear ("same") convolution of an ``n x n`` scene with an ``m x m`` kernel.

    ``A(x) = crop_n(kappa * x)``: the scene is zero outside its ``n x n``
    field, the kernel's centre pixel ``(m//2, m//2)`` is the zero shift, and
    the output is the ``n x n`` field again. Nothing wraps around: it is
    computed as a circular convolution on an ``N x N`` grid with
    ``N = n + m`` (>= n + m - 1), the scene zero-padded, then cropped.
    ``A_adjoint`` is the exact adjoint (pad, correlate, crop).
    ``lipschitz = max |FFT_N(kappa)|^2`` is an upper bound of ``||A||^2``
    (equal to it for circular convolution on the padded grid), which is what
    the ISTA step size needs. Same interface as :class:`ConvolutionOperator`.
    """

    def __init__(self, kappa: torch.Tensor, n: int):
        if not isinstance(kappa, torch.Tensor) or kappa.ndim != 2 or kappa.shape[0] != kappa.shape[1]:
            shape = tuple(kappa.shape) if isinstance(kappa, torch.Tensor) else type(kappa).__name__
            raise ParameterError(f"kappa must be a square (m, m) tensor, got {shape}")
        self.n = check_number("n", n, lo=1, integer=True)
        self.kappa = kappa.to(_complex_dtype(kappa.dtype))
        m = kappa.shape[-1]
        self.grid = self.n + m
        self.K = kernel_spectrum(self.kappa, (self.grid, self.grid))

    def _pad(self, x: torch.Tensor) -> torch.Tensor:
        g = self.grid - self.n
        return F.pad(self._check(x), (0, g, 0, g))

    def A(self, x: torch.Tensor) -> torch.Tensor:
        """``crop_n(kappa * x)`` (complex output, same shape as ``x``)."""
        return torch.fft.ifft2(self.K * torch.fft.fft2(self._pad(x)))[..., :self.n, :self.n]

    def A_adjoint(self, y: torch.Tensor) -> torch.Tensor:
        """Adjoint: zero-pad, correlate with the kernel, crop."""
        return torch.fft.ifft2(self.K.conj() * torch.fft.fft2(self._pad(y)))[..., :self.n, :self.n]

    __call__ = A


def convolve(kappa: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """``Y = kappa (*) x`` (circular, kernel centre at ``(n//2, n//2)``), as ``L_conv`` uses."""
    return ConvolutionOperator(kappa).A(x)


def complex_soft_threshold(Z: torch.Tensor, lam: torch.Tensor | float, eps: float = 1e-8) -> torch.Tensor:
    """Complex soft threshold ``Z / (|Z| + eps) * max(|Z| - lam, 0)``.

    Works for real or complex ``Z``; ``lam`` broadcasts against ``Z``. The
    gradient is finite everywhere, including ``Z = 0`` (where it is zero for
    ``lam >= 0``): ``|Z|`` is differentiated as ``sgn(Z)``, which is 0 at 0,
    and ``eps`` keeps ``Z / (|Z| + eps)`` bounded.
    """
    mag = Z.abs()
    return Z / (mag + eps) * torch.relu(mag - lam)


def _inv_softplus(y: float) -> float:
    return y + math.log(-math.expm1(-y))


class UnrolledISTA(nn.Module):
    """``n_layers`` unrolled ISTA iterations with a learned step and threshold per layer.

    ``X_0 = 0``; ``X_{t+1} = prox_{lambda_t}(X_t - alpha_t A^H (A X_t - Y))`` with
    ``prox`` = :func:`complex_soft_threshold`.

    Parametrisation (keeps the iteration stable whatever the raw values):

    * ``alpha_t = (2 / L) * sigmoid(a_t)`` with ``L = ||A||^2 =
      max |FFT2(kappa)|^2`` computed from the current kernel, so
      ``0 < alpha_t <= 2 / ||A||^2`` by construction. ``L`` is detached: it
      normalises the step and is not a path for the kernel's gradient.
    * ``lambda_t = softplus(b_t) >= 0``.

    ``step_fraction`` (in (0, 1)) initialises ``alpha_t = step_fraction * 2 / L``
    and ``lam`` initialises ``lambda_t``.
    """

    def __init__(self, n_layers: int = 8, *, step_fraction: float = 0.5, lam: float = 1e-3,
                 eps: float = 1e-8):
        super().__init__()
        n_layers = check_number("n_layers", n_layers, lo=1, integer=True)
        self.eps = check_number("eps", eps, lo=0, lo_open=True)
        self.a = nn.Parameter(torch.zeros(n_layers))
        self.b = nn.Parameter(torch.zeros(n_layers))
        self.initialise(step_fraction, lam)

    @property
    def n_layers(self) -> int:
        return self.a.numel()

    @torch.no_grad()
    def initialise(self, step_fraction: float | torch.Tensor, lam: float | torch.Tensor) -> None:
        """Set every (or each, for tensors of length ``n_layers``) ``alpha_t = step_fraction * 2/L`` and ``lambda_t = lam``."""
        f = torch.as_tensor(step_fraction, dtype=torch.float64).expand(self.n_layers)
        lm = torch.as_tensor(lam, dtype=torch.float64).expand(self.n_layers)
        if (f <= 0).any() or (f >= 1).any():
            raise ParameterError(f"step_fraction must lie in (0, 1), got {step_fraction!r}")
        if (lm <= 0).any():
            raise ParameterError(f"lam must be > 0, got {lam!r}")
        self.a.copy_(torch.logit(f))
        self.b.copy_(torch.tensor([_inv_softplus(float(v)) for v in lm], dtype=torch.float64))

    def alphas(self, lipschitz: torch.Tensor | float) -> torch.Tensor:
        """Step sizes ``(n_layers,)`` for an operator with ``||A||^2 = lipschitz``."""
        L = torch.as_tensor(lipschitz, dtype=self.a.dtype, device=self.a.device).detach()
        if not torch.isfinite(L) or L <= 0:
            raise NumericalError(f"||A||^2 = {float(L)}: the PSF kernel is zero or not finite")
        return 2.0 / L * torch.sigmoid(self.a)

    def lambdas(self) -> torch.Tensor:
        """Thresholds ``(n_layers,)``."""
        return F.softplus(self.b)

    def forward(self, y: torch.Tensor, op: ConvolutionOperator, *, return_all: bool = False):
        """Reconstruct ``X`` (complex, shape of ``y``) from measurements ``y = A(x)``."""
        alphas, lambdas = self.alphas(op.lipschitz), self.lambdas()
        y = op._check(y)
        aty = op.A_adjoint(y)
        x = torch.zeros_like(y)
        iterates = []
        for t in range(self.n_layers):
            grad = op.A_adjoint(op.A(x)) - aty
            x = complex_soft_threshold(x - alphas[t] * grad, lambdas[t], self.eps)
            iterates.append(x)
        return iterates if return_all else x


def features(X: torch.Tensor, eps: float = 1e-4) -> torch.Tensor:
    """``phi(X) = [Re X, Im X, |X|, cos angle X, sin angle X]`` -> ``(B, 5, n, n)`` real.

    ``X``: ``(B, 1, n, n)`` real or complex. The angle terms are computed as
    ``Re X / m`` and ``Im X / m`` with ``m = sqrt(|X|^2 + eps^2)``: equal to
    ``cos``/``sin`` of the angle up to a relative ``eps^2 / (2 |X|^2)``, 0 at
    ``X = 0``, with gradient bounded by ``1/eps`` (``torch.angle`` is not
    differentiable at 0). ``|X|`` uses ``torch.abs`` (gradient 0 at 0).
    """
    if X.ndim != 4 or X.shape[1] != 1:
        raise ParameterError(f"features expects (B, 1, n, n), got {tuple(X.shape)}")
    if not X.is_complex():
        X = X.to(_complex_dtype(X.dtype))
    re, im = X.real, X.imag
    m = torch.sqrt(re * re + im * im + eps * eps)
    return torch.cat([re, im, X.abs(), re / m, im / m], dim=1)


class ResidualHead(nn.Module):
    """Residual CNN head of the paper's Fig. 2 (5 feature channels -> 1 image).

    With ``c = base_channels`` (32 in the paper) and ``act`` = LeakyReLU(0.1);
    every 3x3 convolution has padding 1, so the ``n x n`` size is kept::

        x1 = act(conv3x3(phi, 5 -> c))
        x2 = act(conv3x3(x1, c -> 2c))
        x3 = act(conv3x3(x2, 2c -> 4c))
        x4 = act(conv3x3(x3, 4c -> 2c))
        x5 = act(conv3x3(x4 + x2 + proj1x1(x3), 2c -> c))
        r  = conv3x3(x5 + x1, c -> 1)
        b  = conv1x1(phi, 5 -> 1)
        I_hat = b + eta * r

    The activation follows each of the five hidden 3x3 convolutions (x1..x5).
    The three linear maps ``proj1x1`` (a projection on a skip path), the
    output convolution ``r`` and the base ``b`` have no activation, so the
    output and the residual can take any sign. ``eta`` is a learned scalar
    (initial value ``eta``).
    """

    def __init__(self, in_channels: int = 5, base_channels: int = 32, eta: float = 0.1,
                 negative_slope: float = 0.1):
        super().__init__()
        c = check_number("base_channels", base_channels, lo=1, integer=True)
        cin = check_number("in_channels", in_channels, lo=1, integer=True)
        self.conv1 = nn.Conv2d(cin, c, 3, padding=1)
        self.conv2 = nn.Conv2d(c, 2 * c, 3, padding=1)
        self.conv3 = nn.Conv2d(2 * c, 4 * c, 3, padding=1)
        self.conv4 = nn.Conv2d(4 * c, 2 * c, 3, padding=1)
        self.proj = nn.Conv2d(4 * c, 2 * c, 1)
        self.conv5 = nn.Conv2d(2 * c, c, 3, padding=1)
        self.out = nn.Conv2d(c, 1, 3, padding=1)
        self.base = nn.Conv2d(cin, 1, 1)
        self.eta = nn.Parameter(torch.tensor(float(eta)))
        self.act = nn.LeakyReLU(negative_slope)

    def forward(self, phi: torch.Tensor, *, return_intermediates: bool = False):
        act = self.act
        x1 = act(self.conv1(phi))
        x2 = act(self.conv2(x1))
        x3 = act(self.conv3(x2))
        x4 = act(self.conv4(x3))
        s = x4 + x2 + self.proj(x3)
        x5 = act(self.conv5(s))
        r = self.out(x5 + x1)
        b = self.base(phi)
        out = b + self.eta * r
        if return_intermediates:
            return out, {"x1": x1, "x2": x2, "x3": x3, "x4": x4, "skip": s, "x5": x5,
                         "r": r, "b": b}
        return out


class Reconstructor(nn.Module):
    """Unrolled ISTA + :func:`features` + :class:`ResidualHead`: ``(y, kappa) -> I_hat``.

    ``forward(y, kappa_or_op)`` takes measurements ``y`` ``(B, 1, n, n)`` and
    the kernel (or a :class:`ConvolutionOperator`) and returns the real
    reconstruction ``(B, 1, n, n)``; ``return_x=True`` also returns the ISTA
    output. With ``reblur=op_ref`` the head sees, instead of ``X``, the
    features of the ISTA estimate re-imaged with another kernel (e.g. the
    full array's), by ``reblur_mode``:

    * ``'image'``: ``op_ref.A(X)``;
    * ``'correct'``: ``Y + op_ref.A(X) - op.A(X)``, the measurement corrected
      from the selection's kernel to the reference one by the ISTA estimate.
      It equals ``Y`` at ``X = 0`` and for ``op = op_ref`` whatever ``X``,
      and ``op_ref.A(X) + noise`` when ``op.A(X) = Y - noise``: a short
      (unconverged, shrunk) ISTA then does not degrade a good measurement,
      it only adds what the selection's kernel misses.

    Parameter groups: ``self.ista`` and ``self.head``.
    """

    def __init__(self, n_layers: int = 8, *, base_channels: int = 32, step_fraction: float = 0.5,
                 lam: float = 1e-3, eta: float = 0.1, feature_eps: float = 1e-4,
                 reblur_mode: str = "image"):
        super().__init__()
        self.ista = UnrolledISTA(n_layers, step_fraction=step_fraction, lam=lam)
        self.head = ResidualHead(5, base_channels, eta=eta)
        self.feature_eps = check_number("feature_eps", feature_eps, lo=0, lo_open=True)
        self.reblur_mode = check_choice("reblur_mode", reblur_mode, ("image", "correct"))

    @torch.no_grad()
    def init_magnitude_base(self) -> "Reconstructor":
        """Start the head's base ``b = conv1x1(phi)`` as the magnitude channel ``|X|``
        (weights 0, 0, 1, 0, 0, bias 0): the head then starts from the envelope of its
        input (with ``reblur``: the reference kernel's image of the ISTA estimate) and
        learns the residual. Returns ``self``."""
        self.head.base.weight.zero_()
        self.head.base.weight[0, 2] = 1.0
        self.head.base.bias.zero_()
        return self

    @torch.no_grad()
    def init_identity_head(self) -> "Reconstructor":
        """:meth:`init_magnitude_base` and ``eta = 0``: the head starts as the exact
        identity on the magnitude of its input (``I_hat = |z|`` at step 0, ``z`` the ISTA
        estimate or, with ``reblur``, its re-imaged version); the residual branch gets
        its gradient through ``eta``. Returns ``self``."""
        self.init_magnitude_base()
        self.head.eta.zero_()
        return self

    def forward(self, y: torch.Tensor, kappa: torch.Tensor | ConvolutionOperator, *,
                return_x: bool = False, reblur: ConvolutionOperator | None = None):
        op = kappa if isinstance(kappa, ConvolutionOperator) else ConvolutionOperator(kappa)
        x = self.ista(y, op)
        # reblur: the ISTA estimate of the scatterers imaged with another (the full array's)
        # kernel before the head, for targets that are that kernel's envelope image
        if reblur is None:
            z = x
        elif self.reblur_mode == "correct":
            z = op._check(y) + reblur.A(x) - op.A(x)
        else:
            z = reblur.A(x)
        phi = features(z, self.feature_eps).to(self.head.base.weight.dtype)
        out = self.head(phi)
        return (out, x) if return_x else out


# ---------------------------------------------------------------------------
# Metrics
# ---------------------------------------------------------------------------

def _pair(x: torch.Tensor, y: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    if x.shape != y.shape:
        raise ParameterError(f"images differ in shape: {tuple(x.shape)} vs {tuple(y.shape)}")
    if x.ndim == 2:
        x, y = x[None, None], y[None, None]
    elif x.ndim == 3:
        x, y = x[:, None], y[:, None]
    if x.ndim != 4:
        raise ParameterError(f"images must be (H, W), (B, H, W) or (B, C, H, W), got {tuple(x.shape)}")
    return x, y


def _reduce(v: torch.Tensor, reduction: str) -> torch.Tensor:
    if reduction == "mean":
        return v.mean()
    if reduction == "none":
        return v
    raise ParameterError(f"reduction = {reduction!r} is not allowed; choose one of ['mean', 'none']")


def mse(x: torch.Tensor, y: torch.Tensor, reduction: str = "mean") -> torch.Tensor:
    """Mean squared error per image (over C, H, W), averaged over the batch unless ``reduction='none'``."""
    x, y = _pair(x, y)
    return _reduce(((x - y) ** 2).flatten(1).mean(1), reduction)


def psnr(x: torch.Tensor, y: torch.Tensor, data_range: float = 1.0, reduction: str = "mean") -> torch.Tensor:
    """PSNR in dB per image, ``10 log10(data_range^2 / MSE)``, then averaged (``inf`` for identical images)."""
    data_range = check_number("data_range", data_range, lo=0, lo_open=True)
    m = mse(x, y, reduction="none")
    return _reduce(10 * torch.log10(data_range ** 2 / m), reduction)


def _gaussian_window(size: int, sigma: float, dtype, device) -> torch.Tensor:
    g = torch.arange(size, dtype=dtype, device=device) - (size - 1) / 2
    g = torch.exp(-(g ** 2) / (2 * sigma ** 2))
    return g / g.sum()


def ssim(x: torch.Tensor, y: torch.Tensor, data_range: float = 1.0, *, win_size: int = 11,
         sigma: float = 1.5, k1: float = 0.01, k2: float = 0.03, reduction: str = "mean"
         ) -> torch.Tensor:
    """Structural similarity (Wang et al. 2004) with a Gaussian window.

    Local statistics use an ``win_size x win_size`` Gaussian window (std
    ``sigma``) over the *valid* part of the image only (no padding, as in the
    original implementation), biased (weighted) variances, ``C1 = (k1 L)^2``,
    ``C2 = (k2 L)^2`` with ``L = data_range``. The SSIM map is averaged per
    image (and per channel), then over the batch unless ``reduction='none'``.
    Images must be at least ``win_size`` pixels on each side.
    """
    x, y = _pair(x, y)
    if min(x.shape[-2:]) < win_size:
        raise ParameterError(f"ssim: images of {tuple(x.shape[-2:])} are smaller than the "
                             f"{win_size} x {win_size} window")
    dtype = x.dtype if x.dtype in (torch.float32, torch.float64) else torch.float32
    x, y = x.to(dtype), y.to(dtype)
    c = x.shape[1]
    g = _gaussian_window(win_size, sigma, dtype, x.device)
    w = (g[:, None] * g[None, :]).expand(c, 1, win_size, win_size)

    def filt(t):
        return F.conv2d(t, w, groups=c)

    mx, my = filt(x), filt(y)
    sxx = filt(x * x) - mx * mx
    syy = filt(y * y) - my * my
    sxy = filt(x * y) - mx * my
    c1, c2 = (k1 * data_range) ** 2, (k2 * data_range) ** 2
    s = ((2 * mx * my + c1) * (2 * sxy + c2)) / ((mx * mx + my * my + c1) * (sxx + syy + c2))
    return _reduce(s.flatten(1).mean(1), reduction)
