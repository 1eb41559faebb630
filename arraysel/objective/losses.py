"""The training loss: its terms (``docs/metrics.md``, "Training terms"), their weights and their weighted sum.

One home for the loss, used by every objective and trainer:

* :func:`l_ent`, :func:`l_row` -- the selection regularisers; both act on ``P_soft`` (the
  masked-softmax columns). ``L_row`` on the straight-through ``P`` would always be 0 (its
  one-hot columns pick distinct elements), so every caller passes ``P_soft``
  (:func:`selection_terms`).
* :func:`l_conv`, :func:`l_rec` -- the end-to-end data terms.
* :data:`DEFAULT_WEIGHTS` -- the paper's weights; :data:`PSF_WEIGHT_KEYS` the PSF terms a
  scene can weight (``L_SLR`` is the mean of ``L_SLR_q`` and ``L_SLR_i``).
* :func:`training_loss` -- **the** training loss, the one function that assembles it for the PSF
  objective, the toy objective and the end-to-end trainer: ``sum_name weights[name] *
  terms[name] / scales[name]`` over :data:`LOSS_KEYS` in that order, with ``L_ent`` and ``L_row``
  computed from ``P_soft`` when given; the terms keep their shape (``(B,)`` for a batch of masks).
* :func:`check_weights` -- a weight mapping checked against :data:`LOSS_KEYS` (one vocabulary:
  the scene's ``[weights]`` names), missing names taking :data:`DEFAULT_WEIGHTS`.
* :func:`weighted_sum` -- ``sum_name weight[name] * term[name]`` over given keys;
  :func:`composite_loss` -- the weighted sum reduced to a scalar, with the checks a user-facing
  function needs.
"""
from __future__ import annotations

from types import MappingProxyType
from typing import Iterable, Mapping

import torch
from torch import Tensor

from arraysel.errors import ParameterError, check_choice, check_number
from arraysel.objective.tensors import _abs2, _check_kernel_shape, _check_tensor

__all__ = ["DEFAULT_WEIGHTS", "PSF_WEIGHT_KEYS", "SELECTION_WEIGHT_KEYS", "DATA_WEIGHT_KEYS", "LOSS_KEYS",
           "l_conv", "l_rec", "l_ent", "l_row", "weighted_sum", "selection_terms",
           "composite_loss", "check_weights", "training_loss"]

#: weights of the total training loss, those of the paper (read-only; copy with ``dict(...)``)
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
#: the end-to-end data terms (they need images: ``arraysel train``)
DATA_WEIGHT_KEYS = ("L_conv", "L_rec")
#: every term of the training loss, in the order :func:`training_loss` sums them
LOSS_KEYS = PSF_WEIGHT_KEYS + DATA_WEIGHT_KEYS + SELECTION_WEIGHT_KEYS
#: the trainer's former short weight names, refused with a pointer to the scene's names
_FORMER_NAMES = {"psf": "L_PSF", "conv": "L_conv", "rec": "L_rec", "contrast": "L_contrast",
                 "slr": "L_SLR", "ent": "L_ent", "row": "L_row"}


def l_conv(y_c: Tensor, y_ref: Tensor, reduction: str = "sum") -> Tensor:
    """``L_conv``: squared L2 norm ``||Y_c - Y_ref||^2`` over the last two axes (``docs/metrics.md``),
    mean over the rest.

    ``reduction='mean'`` takes the mean of ``|Y_c - Y_ref|^2`` over the last two axes instead of
    the sum (``H W`` times smaller: the scale of :func:`l_rec`, the trainer's default).
    """
    y_c = _check_tensor("Y_c", y_c)
    y_ref = _check_tensor("Y_ref", y_ref)
    _check_kernel_shape("Y_c", y_c)
    check_choice("reduction", reduction, ("sum", "mean"))
    sq = _abs2(y_c - y_ref)
    d = sq.sum((-2, -1)) if reduction == "sum" else sq.mean((-2, -1))
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


def selection_terms(P_soft: Tensor, weights: Mapping[str, float] | None = None) -> dict[str, Tensor]:
    """``L_ent`` and ``L_row`` of a selection, both on ``P_soft`` ``(Ne, k)``; with ``weights``,
    only the terms whose weight is non-zero."""
    out = {}
    if weights is None or weights.get("L_ent", 0):
        out["L_ent"] = l_ent(P_soft)
    if weights is None or weights.get("L_row", 0):
        out["L_row"] = l_row(P_soft)
    return out


def check_weights(weights: Mapping[str, float] | None = None, *, name: str = "weights") -> dict[str, float]:
    """A complete weight mapping in the scene's vocabulary (:data:`LOSS_KEYS`): the given
    weights over :data:`DEFAULT_WEIGHTS`, each a finite number >= 0.

    An unknown name raises :class:`ParameterError`; the trainer's former short names (``psf``,
    ``conv``, ...) raise one that names the new key.
    """
    if weights is None:
        return dict(DEFAULT_WEIGHTS)
    if not isinstance(weights, Mapping):
        raise ParameterError(f"{name} must be a mapping of loss-term names to weights "
                             f"({', '.join(LOSS_KEYS)}), got {type(weights).__name__}")
    out = dict(DEFAULT_WEIGHTS)
    for key, value in weights.items():
        if key in _FORMER_NAMES:
            raise ParameterError(f"{name}[{key!r}]: the loss weights take the scene's names; "
                                 f"use {_FORMER_NAMES[key]!r}")
        if key not in DEFAULT_WEIGHTS:
            raise ParameterError(f"{name}[{key!r}]: unknown loss term; known: {', '.join(LOSS_KEYS)}")
        out[key] = float(check_number(f"{name}[{key!r}]", value, lo=0))
    return out


def training_loss(terms: Mapping[str, Tensor], weights: Mapping[str, float], *,
                  P_soft: Tensor | None = None, scales: Mapping[str, float] | None = None
                  ) -> tuple[Tensor, dict[str, Tensor]]:
    """The training loss: ``(total, terms)``, the one place it is assembled.

    ``terms`` holds the terms the caller computed (the PSF terms of a batch of masks, the data
    terms of a batch of images; other keys such as ``L_SLR_q`` or ``Mean`` ride along and are
    not summed). With ``P_soft`` ``(Ne, k)`` the selection regularisers ``L_ent`` and ``L_row``
    whose weight is non-zero are computed from it and added to the terms. ``total`` is
    ``sum_name weights[name] * terms[name] / scales[name]`` over :data:`LOSS_KEYS` in that order,
    for the names with a non-zero weight that are in ``terms`` (``scales``: ``1`` for a name it
    lacks, the trainer's ``balance='initial'``); the terms keep their shape. A zero scalar when
    nothing is weighted.
    """
    terms = dict(terms)
    if P_soft is not None:
        terms.update(selection_terms(P_soft, weights))
    scales = scales or {}
    scaled = {key: terms[key] / scales[key] if key in scales else terms[key]
              for key in LOSS_KEYS if key in terms and weights.get(key, 0.0)}
    total = weighted_sum(scaled, weights)
    if not isinstance(total, Tensor):  # nothing weighted: a zero on the terms' device and dtype
        ref = next((t for t in terms.values() if isinstance(t, Tensor) and not t.is_complex()), None)
        total = torch.zeros((), dtype=ref.dtype if ref is not None else torch.get_default_dtype(),
                            device=ref.device if ref is not None else None)
    return total, terms
