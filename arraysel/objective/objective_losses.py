"""The scene-weighted losses of :class:`~arraysel.objective.psf_objective.Objective`: the PSF loss
of soft element weights (:func:`mask_loss`), its gradient and Hessian (:func:`mask_hessian`) and
the training loss of a selection matrix (:func:`selection_loss`). The objective's methods of the
same names call these; each counts evaluations, gradient steps and time on the objective.
"""
from __future__ import annotations

import numpy as np
import torch

from arraysel.errors import NumericalError, ParameterError, SelectionError
from arraysel.objective.losses import PSF_WEIGHT_KEYS, training_loss
from arraysel.objective.pair_model import pair_model

__all__ = ["psf_loss", "mask_loss", "mask_hessian", "selection_loss"]


def psf_loss(objective, weights: torch.Tensor, kappas: list[torch.Tensor] | None = None, receive=None):
    """The scene-weighted PSF loss ``(total (B,), terms)`` of ``weights`` (B, Ne), from their
    kernels ``kappas`` (one tensor per point) when the caller has them."""
    wts = {k: objective.weights.get(k, 0.0) for k in PSF_WEIGHT_KEYS}
    need = [k for k, v in wts.items() if v > 0]
    if not need:
        z = weights.sum(-1) * 0
        return z, {}
    terms = (objective.psf_terms(weights, terms=need, receive=receive) if kappas is None
             else objective.terms_of_kernels(kappas, need))
    return training_loss(terms, wts)


def mask_loss(objective, weights: torch.Tensor, receive=None):
    """Scene-weighted PSF loss of soft weights (B, Ne) in [0, 1]: (total (B,), terms);
    ``receive``: separate receive weights (B, Ne)."""
    with objective._timed():
        w = weights[None] if weights.dim() == 1 else weights   # (B, n_tx, Ne): per transmit event
        total, terms = objective._psf_loss(w, receive=receive)
        if not bool(torch.isfinite(total.detach()).all()):
            raise NumericalError("mask_loss is not finite (NaN/Inf) for some weights")
        objective.evaluations += int(w.shape[0])
        if w.requires_grad:
            objective.gradient_steps += 1
    return total, terms


def mask_hessian(objective, mask) -> tuple[np.ndarray, np.ndarray]:
    """The gradient ``(Ne,)`` and the Hessian ``(Ne, Ne)`` (float64) of :meth:`Objective.mask_loss` at
    ``mask`` (weights ``(Ne,)``): the loss's quadratic model, by which swap descents with
    ``model = quadratic`` rank swaps: from the pair basis where it applies
    (:func:`~arraysel.objective.pair_model.pair_model`, :attr:`Objective.hessian_from_pairs`), else one
    forward pass and ``Ne`` Hessian-vector products in one batched backward pass; the same
    values to rounding. Counted as ``Ne`` evaluations and one gradient step."""
    n = objective.n_elements
    with objective._timed():
        fast = pair_model(objective, mask) if objective.hessian_from_pairs else None
        if fast is not None:
            _total, g, H = fast
        else:
            w = torch.as_tensor(np.asarray(mask, dtype=np.float64), dtype=objective.dtype,
                                device=objective.device).reshape(1, n).requires_grad_(True)
            total, _terms = objective._psf_loss(w)
            (g,) = torch.autograd.grad(total.sum(), w, create_graph=True)
            eye = torch.eye(n, dtype=objective.dtype, device=objective.device)[:, None, :]
            (H,) = torch.autograd.grad(g, w, eye, is_grads_batched=True)
            g = g.detach()[0].double().cpu().numpy()
            H = H.detach()[:, 0, :].double().cpu().numpy()
        if not (np.isfinite(g).all() and np.isfinite(H).all()):
            raise NumericalError("mask_hessian is not finite (NaN/Inf) for this selection")
        objective.evaluations += n
        objective.gradient_steps += 1
    return g, H


def selection_loss(objective, P: torch.Tensor, P_soft: torch.Tensor):
    """Training loss of a (Ne, k) selection matrix: (scalar total, terms).

    Element weights are the row sums of P (clamped to [0, 1]); L_ent and
    L_row act on P_soft (:mod:`arraysel.objective.losses`). A scene that
    weights L_conv or L_rec is trained end to end (``arraysel train``), not here.
    """
    with objective._timed():
        if P.dim() != 2 or P.shape[0] != objective.n_elements:
            raise SelectionError(f"P must have shape ({objective.n_elements}, k), got {tuple(P.shape)}")
        w = P.sum(1).clamp(0, 1)[None]
        psf = objective._psf_loss(w)[1]
        total, terms = training_loss({k: v.sum() for k, v in psf.items()}, objective.weights, P_soft=P_soft)
        if objective.settings.needs_data:
            raise ParameterError(f"scene {objective.settings.name!r} weights L_conv/L_rec: train it with "
                                 "`arraysel train` (end-to-end training computes those terms)")
        if not bool(torch.isfinite(total.detach())):
            raise NumericalError("selection_loss is not finite (NaN/Inf)")
        objective.evaluations += 1
        if P.requires_grad:
            objective.gradient_steps += 1
    return total, terms
