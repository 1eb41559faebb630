"""Apodization after selection: bounded weights on the selected elements, fitted by gradient.

A selection is binary: its elements transmit and receive with weight 1. :func:`apodize` keeps
the selection and fits one weight per selected element, ``w_e in [w_min, 1]``, on the scene's own
loss (:meth:`~arraysel.objective.psf_objective.Objective.mask_loss`, the weighted PSF terms of the
scene's ``[weights]``; the physics takes soft element weights, the same weight as the transmit
apodization and the receive channel weight of the element). Unselected elements stay exactly 0.

The search starts at the binary selection (every weight 1) and keeps the best weights it met, so
the apodized loss is never above the binary one. Two methods:

* ``adam`` (default): projected Adam on the weights, each step followed by the projection onto
  ``[w_min, 1]`` and a rescaling so that the largest weight is 1 (the PSF kernel is normalised,
  so the loss does not change with a common factor of the weights);
* ``lbfgsb``: SciPy's L-BFGS-B with the bounds ``[w_min, 1]``, at most ``steps`` evaluations.

The metrics before and after are the objective's ``evaluate`` of the 0/1 mask and of the weights
(every Table-1 metric, the scene's extra columns, and for a 1-D scene the peak side-lobe level
``PSL_dB`` of the kernel: ``20 log10`` of the largest magnitude in the side region over the
peak, the worst field point of a several-point scene). ``docs/apodization.md``.
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np

from arraysel.errors import NumericalError, SelectionError, check_choice, check_number
from arraysel.objective.contract import objective_info

__all__ = ["ApodizationSettings", "ApodizationResult", "apodize", "apodize_many", "weighted_metrics", "METHODS",
           "PSL_NAME"]

#: the optimisers of :func:`apodize`
METHODS = ("adam", "lbfgsb")
#: the peak side-lobe level column added for a 1-D scene (a 3-D scene has its own)
PSL_NAME = "PSL_dB"
#: floor of ``PSL_dB`` (no side pixel)
_PSL_FLOOR_DB = -240.0


@dataclasses.dataclass(frozen=True)
class ApodizationSettings:
    """The options of :func:`apodize`, checked when built.

    w_min : the smallest weight of a selected element, in ``[0, 1)`` (0: an element may fade out)
    steps : gradient steps (``adam``) or most loss evaluations (``lbfgsb``), >= 1
    lr : Adam's learning rate, > 0 (weights are in ``[0, 1]``)
    method : ``adam`` or ``lbfgsb``
    """

    w_min: float = 0.0
    steps: int = 100
    lr: float = 0.02
    method: str = "adam"

    def __post_init__(self):
        object.__setattr__(self, "w_min", float(check_number("w_min", self.w_min, lo=0.0, hi=1.0, hi_open=True)))
        object.__setattr__(self, "steps", int(check_number("steps", self.steps, lo=1, integer=True)))
        object.__setattr__(self, "lr", float(check_number("lr", self.lr, lo=0.0, lo_open=True)))
        check_choice("method", self.method, METHODS)


@dataclasses.dataclass
class ApodizationResult:
    """What :func:`apodize` found for one selection.

    mask : bool ``(Ne,)``, the selection
    weights : float64 ``(Ne,)``, in ``[w_min, 1]`` on the selection (largest 1), 0 elsewhere
    loss_binary, loss_apodized : the scene's loss (``mask_loss``) of the mask and of the weights
    metrics_binary, metrics_apodized : ``{name: float}`` from the objective's ``evaluate``
    history : the loss at every evaluation of the search, in order (the first is the binary one)
    settings : the options used
    """

    mask: np.ndarray
    weights: np.ndarray
    loss_binary: float
    loss_apodized: float
    metrics_binary: dict
    metrics_apodized: dict
    history: list
    settings: ApodizationSettings

    @property
    def gain(self) -> float:
        """``loss_binary - loss_apodized`` (>= 0)."""
        return self.loss_binary - self.loss_apodized


def _check_mask(objective, mask) -> np.ndarray:
    n = int(objective.n_elements)
    m = np.asarray(mask)
    if m.ndim != 1 or m.size != n:
        raise SelectionError(f"mask must have shape ({n},), got {m.shape}")
    if not np.isin(m, (0, 1)).all():
        raise SelectionError("mask must be 0/1 (a binary selection; apodize fits its weights)")
    m = m.astype(bool)
    if not m.any():
        raise SelectionError("empty selection (no active element): mask")
    return m


def _psl_db(objective, kernels: np.ndarray) -> np.ndarray:
    """Peak side-lobe level (dB) of a 1-D scene's kernels ``(B, w, w)`` or ``(B, P, w, w)``: the
    largest ``|kappa|`` with ``r >= r_guard`` over the peak, the worst point of several."""
    import torch

    from arraysel.objective.metrics import psf_regions

    k = torch.as_tensor(kernels)
    kw = objective.metric_kw
    reg = psf_regions(k, pitch=kw["pitch"], wavelength=kw["wavelength"], r_main=kw["r_main"],
                      r_guard=kw["r_guard"], distance=False)
    mag = k.abs().double()
    peak = mag.flatten(-2).amax(-1)
    side = torch.where(reg.side, mag, torch.zeros_like(mag)).flatten(-2).amax(-1)
    ratio = torch.clamp(side / torch.clamp(peak, min=1e-300), min=10.0 ** (_PSL_FLOOR_DB / 20.0))
    db = 20.0 * torch.log10(ratio)
    if db.dim() == 2:       # (B, P): the worst point
        db = db.amax(-1)
    return db.numpy()


def weighted_metrics(objective, weights) -> list[dict]:
    """Every metric of weights ``(B, Ne)`` (0/1 masks or apodized): the objective's ``evaluate``
    (its Table-1 metrics and extra columns), plus ``PSL_dB`` for a 1-D scene; one dict a row."""
    w = np.atleast_2d(np.asarray(weights, dtype=np.float64))
    info = objective_info(objective)
    one_d = info.kind == "kernel" and info.metric_kw is not None
    res = objective.evaluate(w, return_kernels=True) if one_d else objective.evaluate(w)
    if one_d:
        res[PSL_NAME] = _psl_db(objective, res.pop("kernels"))
    return [{name: float(np.asarray(v)[i]) for name, v in res.items()} for i in range(w.shape[0])]


class _Loss:
    """The scene's loss of the selected elements' weights ``v`` (k,): value and gradient, float64,
    recording every value (``history``) and the best ``v`` met."""

    def __init__(self, objective, mask: np.ndarray):
        import torch

        self.objective, self.torch = objective, torch
        self.index = torch.as_tensor(np.flatnonzero(mask), device=objective.device)
        self.history: list[float] = []
        self.best = (math.inf, None)

    def __call__(self, v: np.ndarray, grad: bool = True):
        torch = self.torch
        obj = self.objective
        vt = torch.as_tensor(v, dtype=obj.dtype, device=obj.device).requires_grad_(grad)
        w = torch.zeros((1, int(obj.n_elements)), dtype=obj.dtype, device=obj.device)
        w = w.index_put((torch.zeros_like(self.index), self.index), vt)
        total, _terms = obj.mask_loss(w)
        value = float(total.detach().sum())
        self.history.append(value)
        if value < self.best[0]:
            self.best = (value, np.array(v, dtype=np.float64))
        if not grad:
            return value, None
        (g,) = torch.autograd.grad(total.sum(), vt)
        g = g.detach().double().cpu().numpy()
        if not np.isfinite(g).all():
            raise NumericalError("the gradient of the loss with respect to the weights is not finite")
        return value, g


def _project(v: np.ndarray, w_min: float) -> np.ndarray:
    """``v`` clipped to ``[w_min, 1]`` and scaled so that its largest weight is 1 (the loss does
    not change with a common factor); all at ``w_min = 0`` stays 0 (the caller stops)."""
    v = np.clip(v, w_min, 1.0)
    top = v.max()
    return np.clip(v / top, w_min, 1.0) if top > 0 else v


def _adam(loss: _Loss, v: np.ndarray, st: ApodizationSettings) -> None:
    b1, b2, eps = 0.9, 0.999, 1e-8
    m1, m2 = np.zeros_like(v), np.zeros_like(v)
    for t in range(1, st.steps + 1):
        _value, g = loss(v)
        m1 = b1 * m1 + (1 - b1) * g
        m2 = b2 * m2 + (1 - b2) * g * g
        step = st.lr * (m1 / (1 - b1 ** t)) / (np.sqrt(m2 / (1 - b2 ** t)) + eps)
        v = _project(v - step, st.w_min)
        if not v.any():
            return
    loss(v, grad=False)  # the last step's weights


def _lbfgsb(loss: _Loss, v: np.ndarray, st: ApodizationSettings) -> None:
    from scipy.optimize import minimize

    minimize(loss, v, jac=True, method="L-BFGS-B", bounds=[(st.w_min, 1.0)] * v.size,
             options={"maxfun": st.steps, "maxiter": st.steps})


def apodize(objective, mask, *, w_min: float = 0.0, steps: int = 100, lr: float = 0.02,
            method: str = "adam") -> ApodizationResult:
    """Fit bounded weights to the selected elements of ``mask`` on ``objective``'s loss.

    Parameters
    ----------
    objective : a scene's objective (:func:`arraysel.objective.build.build_objective`) or any
        objective with ``mask_loss`` and ``evaluate`` taking soft weights
    mask : 0/1 or bool ``(Ne,)``, the selection
    w_min, steps, lr, method : :class:`ApodizationSettings`

    Returns
    -------
    :class:`ApodizationResult`; its weights are the best the search met (the binary selection
    itself when nothing better was found), normalised so that the largest is 1.

    Example
    -------
    >>> from arraysel.objective.build import build_objective          # doctest: +SKIP
    >>> obj = build_objective("paper")                                 # doctest: +SKIP
    >>> res = apodize(obj, mask, steps=50)                             # doctest: +SKIP
    >>> res.metrics_binary["PSL_dB"], res.metrics_apodized["PSL_dB"]   # doctest: +SKIP
    """
    st = ApodizationSettings(w_min=w_min, steps=steps, lr=lr, method=method)
    m = _check_mask(objective, mask)
    loss = _Loss(objective, m)
    v0 = np.ones(int(m.sum()), dtype=np.float64)
    loss_binary, _g = loss(v0, grad=False)
    try:
        (_adam if st.method == "adam" else _lbfgsb)(loss, v0.copy(), st)
    except NumericalError:
        pass  # a step whose loss is not finite: keep the best weights met before it
    best, v = loss.best
    v = _project(v, st.w_min)
    weights = np.zeros(m.size, dtype=np.float64)
    weights[m] = v
    before, after = weighted_metrics(objective, np.stack([m.astype(np.float64), weights]))
    return ApodizationResult(mask=m, weights=weights, loss_binary=float(loss_binary), loss_apodized=float(best),
                             metrics_binary=before, metrics_apodized=after, history=list(loss.history),
                             settings=st)


def apodize_many(objective, selections, progress=None, **options) -> list:
    """:func:`apodize` of each selection (lists of element
    indices) on ``objective``, with ``options`` (``w_min``, ``steps``, ``lr``, ``method``);
    ``progress(i, result)`` is called after each."""
    ApodizationSettings(**options)  # bad options refused before the first fit
    out = []
    for i, sel in enumerate(selections):
        mask = np.zeros(int(objective.n_elements))
        mask[list(sel)] = 1
        res = apodize(objective, mask, **options)
        out.append(res)
        if progress is not None:
            progress(i, res)
    return out
