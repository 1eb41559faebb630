"""Argument checks and small tensor helpers shared by :mod:`arraysel.objective.metrics` and
:mod:`arraysel.objective.losses` (one definition each)."""
from __future__ import annotations

import torch
from torch import Tensor

from arraysel.errors import ParameterError

__all__ = ["_check_tensor", "_check_kernel_shape", "_abs2", "objective_device"]


def _check_tensor(name: str, x: object) -> Tensor:
    if not isinstance(x, Tensor):
        raise ParameterError(f"{name} must be a torch.Tensor, got {type(x).__name__}")
    if not (x.is_floating_point() or x.is_complex()):
        raise ParameterError(f"{name} must be a real floating or complex tensor, got dtype {x.dtype}")
    return x


def _check_kernel_shape(name: str, x: Tensor) -> None:
    if x.dim() < 2:
        raise ParameterError(f"{name} must have shape (..., H, W), got shape {tuple(x.shape)}")
    if x.shape[-1] == 0 or x.shape[-2] == 0:
        raise ParameterError(f"{name} must have a non-empty (H, W) window, got shape {tuple(x.shape)}")


def _abs2(z: Tensor) -> Tensor:
    """|z|**2, smooth everywhere (real output)."""
    if z.is_complex():
        return torch.view_as_real(z).square().sum(-1)
    return z.square()


def objective_device(device) -> torch.device:
    """``device`` as a torch.device for an objective; ParameterError for 'cuda' without a CUDA device."""
    device = torch.device(device)
    if device.type == "cuda" and not torch.cuda.is_available():
        raise ParameterError("device = 'cuda' but no CUDA device is available; use --device cpu")
    return device
