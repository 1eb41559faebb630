"""The training loss: its terms (SPEC section 3), their weights and their weighted sum.

One home for the loss, used by every objective and trainer:

* :func:`l_ent`, :func:`l_row` -- the selection regularisers; both act on ``P_soft`` (the
  masked-softmax columns). ``L_row`` on the straight-through ``P`` would always be 0 (its
  one-hot columns pick distinct elements), so every caller passes ``P_soft``
  (:func:`selection_terms`).
* :func:`l_conv`, :func:`l_rec` -- the end-to-end data terms.
* :data:`DEFAULT_WEIGHTS` -- the paper's weights; :data:`PSF_WEIGHT_KEYS` the PSF terms a
  scene can weight (``L_SLR`` is the mean of ``L_SLR_q`` and ``L_SLR_i``).
* :func:`weighted_sum` -- ``sum_name weight[name] * term[name]`` in a fixed order, keeping the
  terms' shape (``(B,)`` for a batch of masks); :func:`composite_loss` -- the same, reduced to
  a scalar, with the checks a user-facing function needs.
"""
from __future__ import annotations

from types import MappingProxyType
from typing import Iterable, Mapping

import torch
from torch import Tensor

from arraysel.errors import ParameterError, check_number
from arraysel.objective.tensors import _abs2, _check_kernel_shape, _check_tensor

__all__ = ["DEFAULT_WEIGHTS", "PSF_WEIGHT_KEYS", "SELECTION_WEIGHT_KEYS", "l_conv", "l_rec", "l_ent", "l_row",
           "weighted_sum", "psf_weighted_sum", "selection_terms", "composite_loss"]

#: weights of the total training loss, SPEC section 3 (read-only; copy with ``dict(...)``)
DEFAULT_WEIGHTS: Mapping[str, float] = MappingProxyType({
    "L_PSF": 10.0,
    "L_conv": 1.0,
    "L_rec": 10.0,
    "L_contrast": 10.0,
    "L_SLR": 10.0,
    "L_ent": 1.0,
    "L_row": 10.0,
})
#: the PSF terms a scene weights, in the order they are summed
PSF_WEIGHT_KEYS = ("L_PSF", "L_contrast", "L_SLR")
#: the selection regularisers, in the order they are summed (after the PSF terms)
SELECTION_WEIGHT_KEYS = ("L_ent", "L_row")


def l_conv(y_c: Tensor, y_ref: Tensor) -> Tensor:
    """``L_conv``: squared L2 norm ``||Y_c - Y_ref||^2`` over the last two axes, mean over the rest."""
    y_c = _check_tensor("Y_c", y_c)
    y_ref = _check_tensor("Y_ref", y_ref)
    _check_kernel_shape("Y_c", y_c)
    d = _abs2(y_c - y_ref).sum((-2, -1))
    return d.mean() if d.dim() else d


def l_rec(i_hat: Tensor, i_ref: Tensor) -> Tensor:
    """``L_rec``: mean of ``|I_hat - I_ref|^2`` over all pixels and batch items."""
    i_hat = _check_tensor("I_hat", i_hat)
    i_ref = _check_tensor("I_ref", i_ref)
    return _abs2(i_hat - i_ref).mean()


def l_ent(p_soft: Tensor) -> Tensor:
    """``L_ent``: mean entropy (nats) of the columns of ``P_soft`` ``(..., Ne, k)``.

    Column ``j`` is a distribution over the ``Ne`` elements (sums to 1);
    ``H_j = -sum_i p_ij log p_ij`` with ``0 log 0 = 0`` (value and gradient
    finite at exact zeros). Averaged over columns and leading dimensions.
    """
    p = _check_tensor("P_soft", p_soft)
    if p.is_complex() or p.dim() < 2:
        raise ParameterError(f"P_soft must be a real tensor of shape (..., Ne, k), got {p.dtype} "
                             f"{tuple(p.shape)}")
    pos = p > 0
    logp = torch.log(torch.where(pos, p, torch.ones_like(p)))
    ent = -torch.where(pos, p * logp, torch.zeros_like(p)).sum(-2)
    return ent.mean()


def l_row(p: Tensor) -> Tensor:
    """``L_row``: ``sum_i relu(sum_j P_ij - 1)^2`` for ``P`` ``(..., Ne, k)``; mean over leading dims.

    Penalises an element (row) used by more than one of the k columns.
    """
    p = _check_tensor("P", p)
    if p.is_complex() or p.dim() < 2:
        raise ParameterError(f"P must be a real tensor of shape (..., Ne, k), got {p.dtype} "
                             f"{tuple(p.shape)}")
    pen = torch.relu(p.sum(-1) - 1).pow(2).sum(-1)
    return pen.mean() if pen.dim() else pen


def composite_loss(terms: Mapping[str, Tensor], weights: Mapping[str, float] = DEFAULT_WEIGHTS) -> Tensor:
    """Weighted sum ``sum_name weights[name] * terms[name]``.

    Names with weight 0 are skipped (their term may be missing or even
    non-finite); a term with no entry in ``weights`` is ignored; a non-zero
    weight whose term is missing raises :class:`ParameterError`. A term that
    is not a scalar (e.g. a ``(B,)`` metric) enters through its mean.
    """
    total: Tensor | None = None
    for name, wt in weights.items():
        wt = check_number(f"weights[{name!r}]", wt)
        if wt == 0:
            continue
        if name not in terms:
            raise ParameterError(f"loss term {name!r} has weight {wt} but was not computed; "
                                 f"available: {sorted(terms)}")
        t = terms[name]
        if not isinstance(t, Tensor):
            t = torch.as_tensor(t)
        if t.is_complex():
            raise ParameterError(f"loss term {name!r} is complex")
        t = t.mean() if t.dim() else t
        total = wt * t if total is None else total + wt * t
    if total is None:
        ref = next((t for t in terms.values() if isinstance(t, Tensor)), None)
        return torch.zeros((), dtype=ref.dtype if ref is not None else torch.get_default_dtype(),
                           device=ref.device if ref is not None else None)
    return total


def weighted_sum(terms: Mapping[str, Tensor], weights: Mapping[str, float], keys: Iterable[str] | None = None):
    """``w[a] * terms[a] + w[b] * terms[b] + ...`` over ``keys`` (default: the keys of ``terms``)
    whose weight is non-zero, summed left to right; ``0`` when there are none. The terms keep
    their shape (no reduction)."""
    total = 0
    for name in (terms if keys is None else keys):
        wt = weights.get(name, 0.0)
        if wt:
            total = total + wt * terms[name]
    return total


def psf_weighted_sum(terms: Mapping[str, Tensor], weights: Mapping[str, float]):
    """The weighted PSF part of the loss (:data:`PSF_WEIGHT_KEYS`), shape of the terms."""
    return weighted_sum(terms, weights, PSF_WEIGHT_KEYS)


def selection_terms(P_soft: Tensor, weights: Mapping[str, float] | None = None) -> dict[str, Tensor]:
    """``L_ent`` and ``L_row`` of a selection, both on ``P_soft`` ``(Ne, k)``; with ``weights``,
    only the terms whose weight is non-zero."""
    out = {}
    if weights is None or weights.get("L_ent", 0):
        out["L_ent"] = l_ent(P_soft)
    if weights is None or weights.get("L_row", 0):
        out["L_row"] = l_row(P_soft)
    return out
