"""The kernel convention of the paper scene (``docs/paper-scene.md``): the ``window`` x ``window`` cut of the image centred on the peak
of its magnitude (clipped to the grid), normalised to unit L2 norm."""
from __future__ import annotations

import torch

from arraysel.errors import NumericalError
from arraysel.physics import compiled


def window_start(peak: torch.Tensor, size: int, n: int) -> torch.Tensor:
    return torch.clamp(peak - size // 2, 0, n - size)


def window_and_normalise(img: torch.Tensor, size: int, peak=None) -> torch.Tensor:
    """Cut the (size x size) window centred on the peak of |img| (clipped), L2-normalised.

    img: (B, nz, nx) complex. Raises NumericalError if an image is all zero.
    """
    B, nz, nx = img.shape
    mag = img.detach().abs().reshape(B, -1)
    if peak is None:
        peak = mag.argmax(dim=1)
    pz = peak // nx
    px = peak % nx
    z0 = window_start(pz, size, nz)
    x0 = window_start(px, size, nx)
    ar = torch.arange(size, device=img.device)
    zi = (z0[:, None] + ar[None])[:, :, None]
    xi = (x0[:, None] + ar[None])[:, None, :]
    bi = torch.arange(B, device=img.device)[:, None, None]
    win = img[bi, zi, xi]
    top = mag.gather(1, peak[:, None])[:, 0]
    if bool((top == 0).any()) or not bool(torch.isfinite(mag).all()):
        raise NumericalError("PSF image is all zero or not finite for some selection "
                             "(is the selection empty, or the scatterer outside the grid?)")
    return unit_norm(win, top)


def scale_complex(x: torch.Tensor, s: torch.Tensor) -> torch.Tensor:
    """``x / s`` (s real, one per batch item) through the real view: torch's complex division
    by a promoted real returns inf/NaN for a subnormal divisor."""
    return torch.view_as_complex(torch.view_as_real(x) / s.reshape(-1, *([1] * x.dim())))


def unit_norm(win: torch.Tensor, top: torch.Tensor, with_norm: bool = False):
    """Windows (B, h, w) divided by their L2 norm; ``top`` (B,) > 0 is a detached scale
    (the peak magnitude) applied first, so squares of tiny or huge values cannot under/overflow.
    With ``with_norm`` also the (detached) norms themselves."""
    top = top.detach().to(win.real.dtype)
    win = scale_complex(win, top)
    norm = torch.linalg.vector_norm(torch.view_as_real(win).reshape(win.shape[0], -1), dim=1)
    out = scale_complex(win, torch.where(norm > 0, norm, torch.ones_like(norm)))
    return (out, norm.detach() * top) if with_norm else out


def cut_windows(img: torch.Tensor, z0: torch.Tensor, x0: torch.Tensor, size: int):
    """Windows (B, size, size) of ``img`` (B, h, w) at offsets (z0, x0), L2-normalised, and
    their (detached) norms (scaled by each window's peak magnitude first; an all-zero window
    stays zero). A batch of at least :data:`~arraysel.physics.compiled.MIN_BATCH` images without
    gradient on the CPU is cut by a compiled kernel
    (:func:`~arraysel.physics.peakkernels.cut_windows_compiled`: the same values to rounding)."""
    B = img.shape[0]
    if (B >= compiled.MIN_BATCH and not img.requires_grad and img.device.type == "cpu"
            and img.dtype in (torch.complex64, torch.complex128)):
        from arraysel.physics.peakkernels import cut_windows_compiled

        win, norm = cut_windows_compiled(torch.view_as_real(img.resolve_conj()).numpy(),
                                         z0.cpu().numpy(), x0.cpu().numpy(), size)
        return torch.view_as_complex(torch.from_numpy(win)), torch.from_numpy(norm)
    ar = torch.arange(size, device=img.device)
    zi = (z0[:, None] + ar[None])[:, :, None]
    xi = (x0[:, None] + ar[None])[:, None, :]
    bi = torch.arange(B, device=img.device)[:, None, None]
    win = img[bi, zi, xi]
    top = win.detach().abs().reshape(B, -1).amax(dim=1)
    return unit_norm(win, torch.where(top > 0, top, torch.ones_like(top)), with_norm=True)
