"""Argument checks and small tensor helpers shared by :mod:`arraysel.objective.metrics`,
:mod:`arraysel.objective.losses` and the objective (one definition each): the check of a batch of
masks (:func:`checked_masks`) and the selections a fast path is checked on (:func:`check_masks`)."""
from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from arraysel.errors import ParameterError, SelectionError

__all__ = ["_check_tensor", "_check_kernel_shape", "_abs2", "objective_device", "checked_masks", "check_masks",
           "ReadOnlyKw"]


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


def checked_masks(masks, n_elements: int, device, dtype, n_events: int = 0) -> torch.Tensor:
    """``masks`` (B, Ne) or (Ne,) (numpy or torch) as a (B, Ne) tensor on ``device`` in ``dtype``;
    with ``n_events`` > 1 (a scene whose transmit events may have apertures of their own) also
    ``(B, n_events, Ne)``, one transmit aperture per event, checked row by row. SelectionError for
    a wrong shape, a NaN or Inf, a negative weight or an empty selection."""
    m = masks if isinstance(masks, torch.Tensor) else torch.as_tensor(np.asarray(masks, dtype=np.float64))
    if m.dim() == 1:
        m = m[None]
    if n_events > 1 and m.dim() == 3 and m.shape[1:] == (n_events, n_elements):
        return checked_masks(m.reshape(-1, n_elements), n_elements, device, dtype).reshape(m.shape)
    if m.dim() != 2 or m.shape[1] != n_elements:
        also = f" or (B, {n_events}, {n_elements}) (per transmit event)" if n_events > 1 else ""
        raise SelectionError(f"masks must have shape (B, {n_elements}){also}, got {tuple(m.shape)}")
    m = m.to(device, dtype)
    if not bool(torch.isfinite(m).all()):
        raise SelectionError("masks contain NaN or Inf")
    if bool((m < 0).any()):
        raise SelectionError("mask weights must be >= 0")
    if bool((m.sum(1) == 0).any()):
        bad = torch.nonzero(m.sum(1) == 0).flatten().tolist()
        raise SelectionError(f"empty selection (no active element) at batch position(s) {bad}")
    return m


def check_masks(n: int, k: int) -> torch.Tensor:
    """The full array and two random selections of ``k`` elements (seed 0), where the check must hold."""
    g = torch.Generator().manual_seed(0)
    checks = [torch.ones(n, dtype=torch.float64)]
    for _ in range(2):
        m = torch.zeros(n, dtype=torch.float64)
        m[torch.randperm(n, generator=g)[:k]] = 1
        checks.append(m)
    return torch.stack(checks)


class ReadOnlyKw(dict):
    """An objective's ``metric_kw``: the metrics' radii and scales, fixed when the objective is built
    (its scorers hold them). Changing one raises a TypeError that says where they are set, where a
    plain dict would take the change and score on with the old values, silently."""

    def _refuse(self, *args, **kwargs):
        raise TypeError("objective.metric_kw is read-only: the metrics' radii and scales are fixed when the "
                        "objective is built; set them in the scene's [metrics] section")

    __setitem__ = __delitem__ = update = pop = popitem = clear = setdefault = _refuse
    __ior__ = _refuse

    def __reduce__(self):
        return (ReadOnlyKw, (dict(self),))
