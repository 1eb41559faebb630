"""The objective contract: what a selector, an experiment and an executor may rely on.

:class:`ObjectiveContract` is a :class:`typing.Protocol` (structural: an objective does not
inherit from it). :class:`arraysel.objective.psf_objective.Objective` and
:class:`arraysel.objective.toy.ToyObjective` follow it; so can a user's own objective.

Capability: an objective that can be rebuilt in another process has a ``worker_factory()``
method returning a picklable zero-argument callable that builds an equal objective (a
:class:`WorkerFactory`), or ``None`` when it cannot. Executors and isolated runs use it
(:func:`arraysel.run.workers.objective_factory_for`); they never look at the objective's class.

Capability: an objective may score the one-swap neighbours of a selection in one call
(:class:`ScoresSwaps`): ``evaluate_swaps(mask, out, into)`` returns what ``evaluate`` returns for
the masks ``mask`` with element ``out[i]`` switched off and ``into[i]`` switched on, the same
values as scoring those masks independently, exploiting what they share.
:func:`arraysel.objective.neighbours.evaluate_swaps` calls it, and scores the masks with
``evaluate`` for an objective without it. More generally (:class:`ScoresMoves`),
``evaluate_moves(mask, out, into)`` scores neighbours that switch up to ``m`` elements each
(``out``, ``into`` of shape ``(B, m)``, padded with ``-1``;
:func:`arraysel.objective.neighbours.evaluate_moves`).

Capability: an objective may say how its elements are laid out (:class:`HasLayout`):
``element_grid`` is ``(ny, nx)`` for a matrix array (element index ``iy * nx + ix``) or ``None`` for a
1-D array, and ``element_positions`` the element centres, a numpy ``(Ne, 3)`` array of (x, y, z) in
metres. Selectors read them through :func:`element_layout`, which treats an objective without them
as a 1-D array.
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
from typing import Any, Callable, Protocol, runtime_checkable

import numpy as np

from arraysel.errors import ParameterError, check_number

__all__ = ["ObjectiveContract", "Rebuildable", "HasLayout", "ScoresSwaps", "ScoresMoves", "HasHessian", "WorkerFactory",
           "dtype_name", "hessian_by_rows",
           "check_element_grid", "element_layout"]


@runtime_checkable
class ObjectiveContract(Protocol):
    """Counters, sizes and the evaluation a selector needs (``docs/selectors.md``)."""

    n_elements: int
    k: int
    evaluations: int
    gradient_steps: int
    seconds: float

    def evaluate(self, masks) -> dict:
        """Metrics of hard masks ``(B, Ne)``: ``{name: float64 array (B,)}``, no gradient."""

    def mask_loss(self, weights) -> tuple[Any, dict]:
        """Differentiable loss of soft weights ``(B, Ne)``: ``(total (B,), terms)``."""

    def selection_loss(self, P, P_soft, step: int) -> tuple[Any, dict]:
        """Differentiable loss of a selection matrix ``(Ne, k)``: ``(scalar total, terms)``."""


@runtime_checkable
class Rebuildable(Protocol):
    """An objective that can be sent to worker processes as a recipe."""

    def worker_factory(self) -> Callable[[], Any] | None:
        ...


@runtime_checkable
class ScoresSwaps(Protocol):
    """An objective that scores a selection's one-swap neighbours in one call (optional capability).

    ``evaluate_swaps(mask, out, into)``: ``mask`` a boolean ``(Ne,)`` selection, ``out`` and
    ``into`` int arrays ``(B,)`` with ``mask[out]`` all True and ``mask[into]`` all False; returns
    ``{name: float64 array (B,)}`` equal to ``evaluate`` of the ``B`` neighbour masks, and counts
    ``B`` evaluations."""

    def evaluate_swaps(self, mask, out, into) -> dict:
        ...


@runtime_checkable
class ScoresMoves(Protocol):
    """An objective that scores a selection's neighbours of m-element moves in one call (optional
    capability).

    ``evaluate_moves(mask, out, into)``: ``mask`` a boolean ``(Ne,)`` selection, ``out`` and
    ``into`` int arrays ``(B, m)`` with ``mask[out]`` all True, ``mask[into]`` all False and no
    element twice in a row, a row of fewer elements padded with ``-1`` (as many in ``out[i]`` as
    in ``into[i]``); returns ``{name: float64 array (B,)}`` equal to ``evaluate`` of the ``B``
    masks with ``out[i]`` switched off and ``into[i]`` on, and counts ``B`` evaluations."""

    def evaluate_moves(self, mask, out, into) -> dict:
        ...


@runtime_checkable
class HasHessian(Protocol):
    """An objective that gives the gradient and the Hessian of its ``mask_loss`` at a selection
    (optional capability: the quadratic model by which swap descents rank swaps,
    ``model = quadratic``).

    ``mask_hessian(mask)``: ``mask`` a boolean or 0/1 ``(Ne,)`` selection; returns ``(g, H)``,
    float64 arrays ``(Ne,)`` and ``(Ne, Ne)``, and counts ``Ne`` evaluations. An objective without
    it gets the same from :func:`hessian_by_rows` on its ``mask_loss``."""

    def mask_hessian(self, mask) -> tuple[np.ndarray, np.ndarray]:
        ...


def hessian_by_rows(mask_loss, mask, dtype=None, device="cpu") -> tuple[np.ndarray, np.ndarray]:
    """The gradient ``(Ne,)`` and the Hessian ``(Ne, Ne)`` (float64) of any differentiable
    ``mask_loss`` (weights ``(B, Ne)`` to ``(total (B,), terms)``) at ``mask``: the loss of ``Ne``
    copies of ``mask`` in one call, differentiated once, then row ``i``'s gradient element ``i``
    differentiated again (row ``i`` of the Hessian). ``mask_loss`` sees, and counts, ``Ne`` weight
    vectors."""
    import torch

    m = np.asarray(mask, dtype=np.float64).reshape(-1)
    n = m.size
    w = torch.tensor(np.repeat(m[None], n, axis=0), dtype=dtype or torch.float32,
                     device=device).requires_grad_(True)
    total, _terms = mask_loss(w)
    (grads,) = torch.autograd.grad(total.sum(), w, create_graph=True)
    (H,) = torch.autograd.grad(torch.diagonal(grads).sum(), w)
    return grads.detach()[0].double().cpu().numpy(), H.detach().double().cpu().numpy()


@runtime_checkable
class HasLayout(Protocol):
    """An objective that says how its elements are laid out (optional capability)."""

    #: ``(ny, nx)`` for a matrix array (element index ``iy * nx + ix``), ``None`` for a 1-D array
    element_grid: tuple[int, int] | None
    #: element centres, numpy ``(Ne, 3)``: (x, y, z) in metres, in element-index order
    element_positions: Any


def check_element_grid(grid, n_elements: int | None = None) -> tuple[int, int]:
    """``grid`` as ``(ny, nx)`` of positive ints; with ``n_elements``, ``ny * nx`` must equal it
    (:class:`~arraysel.errors.ParameterError` naming the key otherwise)."""
    try:
        ny, nx = grid
    except (TypeError, ValueError):
        raise ParameterError(f"element_grid must be (ny, nx), got {grid!r}") from None
    ny = int(check_number("element_grid[0] (ny)", ny, lo=1, integer=True))
    nx = int(check_number("element_grid[1] (nx)", nx, lo=1, integer=True))
    if n_elements is not None and ny * nx != int(n_elements):
        raise ParameterError(f"element_grid = ({ny}, {nx}) holds {ny * nx} elements, but n_elements = {n_elements}")
    return ny, nx


def element_layout(objective) -> tuple[tuple[int, int] | None, np.ndarray | None]:
    """``(element_grid, element_positions)`` of an objective, validated; ``(None, None)`` when it
    does not declare them (a 1-D array). The grid must hold ``n_elements`` elements and the
    positions be ``(Ne, 3)`` and finite."""
    n = int(objective.n_elements)
    grid = getattr(objective, "element_grid", None)
    grid = None if grid is None else check_element_grid(grid, n)
    pos = getattr(objective, "element_positions", None)
    if pos is not None:
        pos = np.asarray(pos, dtype=np.float64)
        if pos.shape != (n, 3) or not np.isfinite(pos).all():
            raise ParameterError(f"element_positions must be a finite ({n}, 3) array of (x, y, z) in metres, "
                                 f"got shape {pos.shape}")
    return grid, pos


def dtype_name(dtype) -> str:
    """``torch.float32`` -> ``"float32"`` (a picklable, readable dtype)."""
    text = str(dtype)
    return text[len("torch."):] if text.startswith("torch.") else text


class WorkerFactory:
    """Base of the picklable objective recipes (frozen dataclasses): a stable :meth:`key` that names
    the objective in worker-side caches."""

    def key(self) -> str:
        fields = dataclasses.asdict(self)  # type: ignore[arg-type]
        text = json.dumps({"type": type(self).__name__, **fields}, sort_keys=True, default=str)
        return hashlib.sha1(text.encode()).hexdigest()[:16]
