"""The objective's capabilities as a run's budget sees them: its neighbourhood and its loss model.

A search asks the objective once for what makes it fast (:mod:`arraysel.objective.contract`:
``objective.neighbourhood()``, a :class:`~arraysel.objective.contract.Neighbourhood` that scores a
selection's neighbours in one call; ``objective.loss_model()``, a
:class:`~arraysel.objective.contract.LossModel` that gives the gradient and the Hessian of the
loss). :class:`~arraysel.selectors.contract.BudgetedObjective` hands them out wrapped here, each
on the run's :class:`~arraysel.selectors.budget.BudgetGate` (the one interface its budget is spent
through): the scoring of :class:`BudgetedNeighbourhood` is counted, clipped and recorded like
``evaluate`` of the neighbour masks (:meth:`~arraysel.selectors.budget.BudgetGate.masks`), and
:class:`BudgetedLossModel` checks that the budget allows what a gradient (one evaluation) or a
Hessian (``Ne``) costs before it asks (:meth:`~arraysel.selectors.budget.BudgetGate.losses`).

An objective without a capability is said once in the log (logger ``arraysel``, warning), so a
search that runs without it does so visibly: :func:`say_without`.
"""
from __future__ import annotations

import logging
import weakref

import numpy as np

from arraysel.objective.neighbours import check_moves, move_masks

__all__ = ["BudgetedNeighbourhood", "BudgetedLossModel", "say_without", "WITHOUT"]

_log = logging.getLogger("arraysel.selectors.capabilities")

#: what a search does without each capability (the log line's second half)
WITHOUT = {
    "neighbourhood": "search runs without a neighbourhood: each neighbour is scored as its own mask",
    "loss model": "search runs without a model of the loss: descents try their moves in a random order",
}

_said: "weakref.WeakKeyDictionary" = weakref.WeakKeyDictionary()
_said_ids: set = set()


def say_without(objective, capability: str) -> None:
    """Log once for ``objective`` (the objective a run wraps) that searches on it run without
    ``capability`` (a key of :data:`WITHOUT`)."""
    try:
        said = _said.setdefault(objective, set())
    except TypeError:  # an objective that takes no weak reference: remembered by id
        said = _said_ids
        capability_key = (id(objective), capability)
        if capability_key in said:
            return
        said.add(capability_key)
    else:
        if capability in said:
            return
        said.add(capability)
    _log.warning("objective %s: %s", type(objective).__name__, WITHOUT[capability])


class BudgetedNeighbourhood:
    """The wrapped objective's :class:`~arraysel.objective.contract.Neighbourhood` charged to the
    run's budget: :meth:`evaluate` scores the neighbours in the pieces the budget allows and
    records them (``gate`` the run's :class:`~arraysel.selectors.budget.BudgetGate`)."""

    def __init__(self, gate, inner):
        self._gate = gate
        self._inner = inner
        self._block = inner.block()

    def block(self):
        """The :class:`~arraysel.objective.contract.SwapBlock` the wrapped neighbourhood prefers."""
        return self._block

    def evaluate(self, mask, out, into) -> dict[str, np.ndarray]:
        """``{name: float64 (B,)}`` of the neighbours of ``mask`` that switch ``out[i]`` off and
        ``into[i]`` on (``(B, m)`` or ``(B,)``), counted, clipped and recorded like
        ``evaluate`` of their masks. For a neighbourhood that prefers blocks the moves go to it
        ordered by their first outgoing element, in pieces of whole blocks (``outgoing`` x ``Ne``)."""
        m, a, b = check_moves(mask, out, into)
        gate = self._gate
        if self._block is None:
            return gate.masks(int(a.shape[0]), lambda sl: self._inner.evaluate(m, a[sl], b[sl]),
                              lambda sl: move_masks(m, a[sl], b[sl]))
        order = np.argsort(a[:, 0], kind="stable")
        a, b = a[order], b[order]
        res = gate.masks(int(a.shape[0]), lambda sl: self._inner.evaluate(m, a[sl], b[sl]),
                         lambda sl: move_masks(m, a[sl], b[sl]), piece=max(gate.piece, self._block.outgoing * m.size))
        back = np.empty_like(order)
        back[order] = np.arange(order.size)
        return {k: v[back] for k, v in res.items()}

    def prepare(self) -> None:
        """Nothing: a run's objective is prepared before its budget starts (the runners)."""


class BudgetedLossModel:
    """The wrapped objective's :class:`~arraysel.objective.contract.LossModel` charged to the run's
    budget: a gradient needs one evaluation, a model ``n_elements`` (:class:`BudgetExhausted
    <arraysel.selectors.budget.BudgetExhausted>` when the budget does not allow them; ``gate`` the
    run's :class:`~arraysel.selectors.budget.BudgetGate`)."""

    def __init__(self, gate, inner, n_elements: int):
        self._gate = gate
        self._inner = inner
        self._n = int(n_elements)

    def _allow(self, n: int, what: str) -> None:
        self._gate.enter()
        self._gate.losses(n, f"{what} ({n} evaluations)")

    def gradient(self, mask) -> np.ndarray:
        self._allow(1, "the loss's gradient")
        return self._inner.gradient(mask)

    def model(self, mask) -> tuple[np.ndarray, np.ndarray]:
        self._allow(self._n, "the loss's Hessian")
        return self._inner.model(mask)

