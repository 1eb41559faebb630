"""The reduced problem a selector sees when a scene has constraints (:mod:`arraysel.constraints`).

:class:`ConstrainedObjective` wraps the run's :class:`~arraysel.selectors.contract.BudgetedObjective`:
its elements are the free **units** of the constraints (the elements neither forced on nor off, or
with symmetry one set of mirror images each), ``k`` is the number of units a selection takes, and
every mask, weight vector, selection matrix and move a selector gives is expanded to the probe's
elements (the forced-on elements added, a unit's mirror images switched with it) before it is
scored, counted and recorded. A selector of the reduced problem therefore meets the forced
elements and the symmetry whatever it does; only the channel groups remain
(``objective.constraints``, :meth:`~arraysel.constraints.Constraints.swap_pairs` and the other
search helpers), and the built-in selectors honour them by construction.
"""
from __future__ import annotations

import numpy as np

from arraysel.constraints import Constraints
from arraysel.errors import ParameterError
from arraysel.objective.contract import element_layout
from arraysel.objective.neighbours import check_moves

__all__ = ["ConstrainedObjective", "budget_of"]


class ConstrainedObjective:
    """The reduced view of ``objective`` (a budgeted objective over the probe's elements) under
    ``constraints`` (module docstring). Attributes it does not define are the wrapped objective's
    (the budget, the counters, ``device``, ``dtype``, ``best_mean``, ``remaining``)."""

    def __init__(self, objective, constraints: Constraints):
        self._inner = objective
        self.element_constraints = constraints
        self.constraints = constraints.reduced
        self.n_elements = len(constraints.units)
        self.k = constraints.k_units
        self._units = np.stack(constraints.units) if constraints.units else np.zeros((0, 1), dtype=np.int64)
        idx = np.where(constraints.unit_of >= 0, constraints.unit_of, self.n_elements + 1)
        idx[list(constraints.forced_on)] = self.n_elements
        self._index = idx  # element -> position in [unit weights..., 1 (forced on), 0 (off)]

    def __getattr__(self, name):
        if name.startswith("__") or name == "_inner":
            raise AttributeError(name)
        return getattr(self._inner, name)

    # -- geometry of the reduced problem ------------------------------------------------------
    @property
    def element_grid(self):
        """The probe's grid when every element is a unit of its own, in order (groups only)."""
        return element_layout(self._inner)[0] if self.element_constraints.simple else None

    @property
    def element_positions(self):
        """Each unit's position: that of its first element (one mirror image of a symmetric set)."""
        pos = element_layout(self._inner)[1]
        return None if pos is None else np.asarray(pos, dtype=np.float64)[self._units[:, 0]]

    # -- the run's bookkeeping in units -------------------------------------------------------
    @property
    def best(self) -> list[int] | None:
        b = self._inner.best
        return None if b is None else self.element_constraints.reduce_indices(b)

    def fallback(self, selection) -> None:
        self._inner.fallback(self.element_constraints.expand_indices(selection))

    def expand(self, masks) -> np.ndarray:
        """Element masks of unit masks (``(n_units,)`` or ``(B, n_units)``)."""
        m = np.asarray(masks)
        if hasattr(masks, "detach"):
            m = masks.detach().cpu().numpy()
        return self.element_constraints.expand(m != 0)

    def _moves(self, out, into) -> tuple[np.ndarray, np.ndarray]:
        b = out.shape[0]

        def elements(idx):  # -1 pads a row that switches fewer units: its elements pad too
            e = self._units[np.maximum(idx, 0)]
            return np.where((idx >= 0)[..., None], e, -1).reshape(b, -1)

        return elements(out), elements(into)

    # -- the Objective contract in units -------------------------------------------------------
    def evaluate(self, masks, **kwargs):
        return self._inner.evaluate(self.expand(masks), **kwargs)

    def score(self, masks) -> np.ndarray:
        return self._inner.score(self.expand(masks))

    def score_indices(self, selections) -> np.ndarray:
        sel = np.asarray(selections, dtype=np.int64).reshape(-1, self.k)
        masks = np.zeros((sel.shape[0], self.n_elements), dtype=bool)
        np.put_along_axis(masks, sel, True, axis=1)
        return self.score(masks)

    def evaluate_moves(self, mask, out, into):
        m, a, b = check_moves(mask, out, into)
        ea, eb = self._moves(a, b)
        return self._inner.evaluate_moves(self.expand(m), ea, eb)

    def evaluate_swaps(self, mask, out, into):
        return self.evaluate_moves(mask, np.asarray(out)[:, None], np.asarray(into)[:, None])

    def score_moves(self, mask, out, into) -> np.ndarray:
        m, a, b = check_moves(mask, out, into)
        ea, eb = self._moves(a, b)
        return self._inner.score_moves(self.expand(m), ea, eb)

    def score_swaps(self, mask, out, into) -> np.ndarray:
        return self.score_moves(mask, np.asarray(out)[:, None], np.asarray(into)[:, None])

    def _weights(self, w):
        """Element weights of unit weights (torch, ``(..., n_units)``): forced on 1, off 0."""
        import torch

        shape = w.shape[:-1]
        ext = torch.cat([w, torch.ones(*shape, 1, dtype=w.dtype, device=w.device),
                         torch.zeros(*shape, 1, dtype=w.dtype, device=w.device)], dim=-1)
        return ext[..., torch.as_tensor(self._index, device=w.device)]

    def mask_loss(self, weights, *args, **kwargs):
        import torch

        w = weights if isinstance(weights, torch.Tensor) else torch.as_tensor(np.asarray(weights, dtype=np.float64))
        return self._inner.mask_loss(self._weights(w), *args, **kwargs)

    def mask_hessian(self, mask):
        """``(g, H)`` of :meth:`mask_loss` in units (:meth:`loss_model`)."""
        model = self.loss_model()
        if model is None:
            raise ParameterError("mask_hessian: this objective has no model of its loss (no mask_loss)")
        return model.model(mask)

    # -- the capabilities in units -------------------------------------------------------------
    def neighbourhood(self) -> "_UnitNeighbourhood | None":
        """The wrapped objective's neighbourhood (budgeted) scoring moves of units as the moves of
        their elements; None when it has none."""
        inner = self._inner.neighbourhood()
        return None if inner is None else _UnitNeighbourhood(self, inner)

    def loss_model(self) -> "_UnitLossModel | None":
        """The wrapped objective's loss model (budgeted) in units: ``J^T g`` and ``J^T H J`` of the
        elements' at the expanded selection (``J`` the 0/1 map of units to elements)."""
        inner = self._inner.loss_model()
        return None if inner is None else _UnitLossModel(self, inner)

    def selection_loss(self, P, P_soft, *args, **kwargs):
        """The selection matrix ``(n_units, k_units)`` over the elements: a unit's row for each of
        its elements, and one column per forced-on element (its one-hot)."""
        import torch

        n_on = len(self.element_constraints.forced_on)

        def expand(M):
            rows = torch.cat([M, torch.zeros(2, M.shape[1], dtype=M.dtype, device=M.device)], dim=0)
            out = rows[torch.as_tensor(np.minimum(self._index, self.n_elements + 1), device=M.device)]
            if n_on:
                on = torch.zeros(out.shape[0], n_on, dtype=M.dtype, device=M.device)
                on[list(self.element_constraints.forced_on), torch.arange(n_on)] = 1.0
                out = torch.cat([out, on], dim=1)
            return out

        return self._inner.selection_loss(expand(P), expand(P_soft), *args, **kwargs)


class _UnitNeighbourhood:
    """A neighbourhood of elements (``inner``) seen in the units of ``view`` (a
    :class:`ConstrainedObjective`)."""

    def __init__(self, view: ConstrainedObjective, inner):
        self._view, self._inner = view, inner

    def evaluate(self, mask, out, into):
        m, a, b = check_moves(mask, out, into)
        ea, eb = self._view._moves(a, b)
        return self._inner.evaluate(self._view.expand(m), ea, eb)

    def prepare(self) -> None:
        self._inner.prepare()

    def block(self):
        """The inner neighbourhood's block where a unit is an element (channel groups only), else
        None (a unit's swap moves several elements)."""
        return self._inner.block() if self._view.element_constraints.simple else None


class _UnitLossModel:
    """A loss model of elements (``inner``) seen in the units of ``view`` (a
    :class:`ConstrainedObjective`)."""

    def __init__(self, view: ConstrainedObjective, inner):
        self._view, self._inner = view, inner
        units = view._units
        n_el = len(view.element_constraints.unit_of)
        self._J = np.zeros((n_el, view.n_elements))
        for j, u in enumerate(units):
            self._J[u, j] = 1.0

    def gradient(self, mask) -> np.ndarray:
        g = np.asarray(self._inner.gradient(self._view.expand(np.asarray(mask) != 0)), dtype=np.float64)
        return self._J.T @ g

    def model(self, mask) -> tuple[np.ndarray, np.ndarray]:
        g, H = self._inner.model(self._view.expand(np.asarray(mask) != 0))
        g, H = np.asarray(g, dtype=np.float64), np.asarray(H, dtype=np.float64)
        return self._J.T @ g, self._J.T @ H @ self._J


def budget_of(objective):
    """The run's :class:`~arraysel.selectors.budget.Budget` of a budgeted objective (a
    :class:`~arraysel.selectors.contract.BudgetedObjective`, or the :class:`ConstrainedObjective`
    over one); None for an objective a search was given without a budget."""
    from arraysel.selectors.contract import BudgetedObjective

    return objective.budget if isinstance(objective, (BudgetedObjective, ConstrainedObjective)) else None
