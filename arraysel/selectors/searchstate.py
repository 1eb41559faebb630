"""The state a swap search keeps: its settings, the scores of the selections it has seen, the model
of the loss at the current selection, the best selection, and where fresh selections come from.

:class:`SearchState` is the base of the swap engine (:class:`~arraysel.selectors.descent.SwapDescent`
moves from it, :class:`~arraysel.selectors.localsearch.SwapSearch` searches with it). Scores of
selections already seen are kept (up to ``cache_size`` of them), so revisiting costs nothing.
"""
from __future__ import annotations

import math
from typing import Callable

import numpy as np

from arraysel.errors import ParameterError
from arraysel.constraints import group_constraints
from arraysel.objective.neighbours import moves_between, neighbourhood_of, swap_masks, swap_pairs
from arraysel.objective.contract import loss_model_of
from arraysel.selection import mask_key
from arraysel.selectors.constrained import budget_of
from arraysel.selectors.contract import finite_or_inf
from arraysel.selectors.lossmodel import (GRADIENT_UPDATE_MAX, QUADRATIC_MAX_ELEMENTS, model_gradient, model_quadratic,
                                          swap_changes)
from arraysel.selectors.starts import chirp_masks, random_mask
from arraysel.selectors.swapsettings import FIELDS, FRESH_CHIRPS, SWAP, SwapSettings


class SearchState:
    """What a swap search keeps between its moves (see the module).

    Parameters
    ----------
    objective : the budgeted objective (:class:`~arraysel.selectors.contract.BudgetedObjective`:
        its ``evaluate`` raises BudgetExhausted at the end)
    k : active elements
    rng : numpy Generator (all randomness)
    settings : the engine's :class:`~arraysel.selectors.swapsettings.SwapSettings` (default:
        :data:`~arraysel.selectors.swapsettings.SWAP`, ``swap``'s)
    restart_from : callable ``rng -> mask`` giving fresh selections (default: by ``settings.fresh``)
    max_rounds : stop after this many perturbations/restarts (None: until the budget ends)
    cache_size : most scored selections remembered
    **changes : settings by name, laid over ``settings`` (``SwapSearch(obj, k, rng, chunk=8)``)

    Each setting is an attribute of the same name (``model`` resolved from None to ``quadratic``
    or ``linear`` by the number of elements; ``max_perturb`` at least ``perturb``; ``guide``,
    a descent's :class:`~arraysel.selectors.lossmodel.GuidedOrder`).
    """

    #: rounds in a row without a newly scored selection after which a search stops
    MAX_IDLE_ROUNDS = 200

    def __init__(self, objective, k: int, rng: np.random.Generator, settings: SwapSettings | None = None, *,
                 restart_from: Callable[[np.random.Generator], np.ndarray] | None = None,
                 max_rounds: int | None = None, cache_size: int = 2_000_000, **changes):
        settings = (SWAP if settings is None else settings).replace(**changes)
        self.settings = settings
        for name in FIELDS:  # read as attributes as the search goes (a benchmark may change pairs)
            setattr(self, name, getattr(settings, name))
        self.objective = objective
        #: the objective's :class:`~arraysel.objective.contract.Neighbourhood` (asked once; None:
        #: neighbours are scored as masks)
        self.neighbourhood = neighbourhood_of(objective)
        #: the :class:`~arraysel.objective.contract.SwapBlock` the neighbourhood prefers (None: a
        #: first-improvement descent scores random chunks of swaps; else whole blocks of outgoing
        #: elements, :meth:`~arraysel.selectors.descent.SwapDescent._block_chunks`)
        self.block = None if self.neighbourhood is None else self.neighbourhood.block()
        self._loss_model: list = []  # the objective's LossModel, asked once when a model is first wanted
        #: the channel groups a selection must meet (:func:`~arraysel.constraints.group_constraints`):
        #: swaps stay inside a group, moves that leave the feasible set are never scored
        self.constraints = group_constraints(objective)
        if self.constraints is not None:
            self.shift = 0  # a segment shift moves elements across groups
        self.n = int(objective.n_elements)
        self.k = int(k)
        self.rng = rng
        if settings.model is None:
            self.model = "quadratic" if self.n <= QUADRATIC_MAX_ELEMENTS else "linear"
        self.max_perturb = max(settings.perturb, settings.max_perturb)
        self.restart_from = restart_from
        self.max_rounds = max_rounds
        self.cache_size = int(cache_size)
        self._hessian: np.ndarray | None = None  # the quadratic model's Hessian, and the moves it served
        self._hessian_age = 0
        self._gradient_at: tuple[np.ndarray, np.ndarray] | None = None  # (selection, the model's gradient there)
        self._model_at: tuple[bytes, tuple[np.ndarray, np.ndarray | None] | None] | None = None
        self.gradients_updated = 0  # predictions whose gradient was carried by the Hessian
        self.hessians = 0  # Hessians formed
        self.model_used = 0.0  # share of the budget the models took (gradients, Hessians)
        self._fresh_count = 0  # fresh selections drawn (fresh = mixed alternates chirped and random)
        self._cache: dict[bytes, float] = {}
        self.best_mask: np.ndarray | None = None
        self.best_value = math.inf
        self.moves = 0
        self.local_optima = 0
        self.scored = 0  # selections scored (cache misses)

    # -- scoring with a cache ----------------------------------------------------
    def score(self, masks: np.ndarray) -> np.ndarray:
        """Mean of each mask (NaN as +inf); selections seen before are not scored again."""
        return self._cached(masks, lambda todo: self.objective.score(masks[todo]))

    def score_swaps(self, mask: np.ndarray, a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(neighbour masks, their Means)`` of the swaps ``(a[i], b[i])`` of ``mask``: the
        neighbours not seen before are scored in one call of the objective's neighbourhood
        (:attr:`neighbourhood`) when it has one, else as masks."""
        cands = swap_masks(mask, a, b)
        nb = self.neighbourhood
        if nb is None:
            return cands, self.score(cands)
        return cands, self._cached(cands, lambda todo: finite_or_inf(nb.evaluate(mask, a[todo], b[todo])["Mean"]))

    def score_moved(self, mask: np.ndarray, cands: np.ndarray) -> np.ndarray:
        """Means of the selections ``cands`` (B, Ne), each with as many elements as ``mask``: the
        ones not seen before are scored as moves from ``mask`` in one call of the objective's
        neighbourhood (:attr:`neighbourhood`) when it has one, else as masks."""
        nb = self.neighbourhood
        if self.constraints is not None:  # a move that leaves the feasible set is not scored
            ok = self.constraints.feasible_rows(cands)
            if not ok.all():
                out = np.full(len(cands), math.inf)
                if ok.any():
                    out[ok] = self.score_moved(mask, cands[ok])
                return out
        if nb is None:
            return self.score(cands)
        return self._cached(cands, lambda todo: finite_or_inf(nb.evaluate(mask, *moves_between(mask, cands[todo]))["Mean"]))

    @property
    def loss_model(self):
        """The objective's :class:`~arraysel.objective.contract.LossModel`, asked once (None: the
        search has no model of the loss, and descents try their moves in a random order)."""
        if not self._loss_model:
            self._loss_model.append(loss_model_of(self.objective))
        return self._loss_model[0]

    def _cached(self, masks: np.ndarray, scorer) -> np.ndarray:
        keys = [mask_key(m) for m in masks]
        out = np.full(len(keys), math.inf)
        todo = []
        for i, key in enumerate(keys):
            v = self._cache.get(key)
            if v is None:
                todo.append(i)
            else:
                out[i] = v
        if todo:
            idx = np.asarray(todo)
            values = scorer(idx)
            self.scored += len(todo)
            out[idx] = values
            if len(self._cache) + len(todo) > self.cache_size:
                self._cache.clear()
            for i, v in zip(todo, values):
                self._cache[keys[i]] = float(v)
        return out

    def _model(self, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray | None] | None:
        """The model of the loss at ``mask``: ``(g, None)`` (``model = linear``) or ``(g, H)``
        (``quadratic``: the gradient, and a Hessian formed afresh every ``refresh`` calls;
        :func:`~arraysel.selectors.lossmodel.model_quadratic`). None without a usable loss. Asked again at the same selection
        (the shifts after the swaps of a local optimum), it is not formed again."""
        key = mask_key(mask)
        if self._model_at is not None and self._model_at[0] == key:
            return self._model_at[1]
        before = self._budget_used()
        try:
            out = self._form_model(mask)
        finally:
            if before is not None:
                self.model_used += self._budget_used() - before
        self._model_at = (key, out)
        return out

    def _form_model(self, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray | None] | None:
        """:meth:`_model` formed afresh (a gradient, and a Hessian when one is due)."""
        if self.model == "quadratic":
            if self._hessian is None or self._hessian_age >= self.refresh:
                q = model_quadratic(self.loss_model, mask)
                if q is None:
                    return None
                g, self._hessian, self._hessian_age = q[0], q[1], 0
                self.hessians += 1
            else:
                g = self._carried_gradient(mask)
                if g is None:
                    g = model_gradient(self.loss_model, mask)
            self._hessian_age += 1
            if g is not None and self.gradient == "update":
                self._gradient_at = (mask.astype(np.float64), g)
            return None if g is None else (g, self._hessian)
        g = model_gradient(self.loss_model, mask)
        return None if g is None else (g, None)

    def _carried_gradient(self, mask: np.ndarray) -> np.ndarray | None:
        """With ``gradient = update``: the quadratic model's gradient at ``mask``, ``g + H d`` from
        the last one (``d`` the move from its selection), when ``mask`` is at most
        :data:`GRADIENT_UPDATE_MAX` elements away from that selection; else None (take the
        loss's)."""
        if self.gradient != "update" or self._gradient_at is None or self._hessian is None:
            return None
        at, g = self._gradient_at
        d = mask.astype(np.float64) - at
        if np.abs(d).sum() > 2 * GRADIENT_UPDATE_MAX:
            return None
        self.gradients_updated += 1
        return g + self._hessian @ d

    def _predict(self, mask: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray | None:
        """The predicted change of each swap ``(a[i], b[i])`` of ``mask`` (:func:`swap_changes`) by
        the model of the loss at ``mask`` (:meth:`_model`). None without a usable loss."""
        m = self._model(mask)
        return None if m is None else swap_changes(m[0], m[1], a, b)

    def _note(self, mask: np.ndarray, value: float) -> None:
        if value < self.best_value or self.best_mask is None:
            self.best_value, self.best_mask = value, mask.copy()


    # -- where selections come from ------------------------------------------------
    def _random_mask(self, rng: np.random.Generator) -> np.ndarray:
        if self.constraints is not None:
            return self.constraints.random_masks(rng, 1)[0]
        return random_mask(rng, self.n, self.k)

    def _swap_pairs(self, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The one-swaps of ``mask`` a descent tries, in a random order (feasible ones only)."""
        if self.constraints is None:
            return swap_pairs(mask, self.rng)
        a, b = self.constraints.swap_pairs(mask)
        order = self.rng.permutation(a.size)
        return a[order], b[order]

    def _fresh_mask(self, rng: np.random.Generator) -> np.ndarray:
        """A fresh selection for a restart or an extra start: ``restart_from``'s, else by ``fresh``
        (a random one, or the best of :data:`FRESH_CHIRPS` chirped layouts, scored in one call)."""
        if self.restart_from is not None:
            return self.restart_from(rng)
        chirp = self.fresh == "chirp"
        if self.fresh == "mixed":  # chirped and random in turn
            self._fresh_count += 1
            chirp = self._fresh_count % 2 == 1
        if chirp and 0 < self.k < self.n:
            masks = chirp_masks(self.objective, self.k, rng, FRESH_CHIRPS)
            values = self.score(masks)
            return masks[int(np.argmin(values))].copy()
        return self._random_mask(rng)


    def _budget_used(self) -> float | None:
        """The used share of the objective's budget (``budget.fraction()``), or None where the
        objective has no budget or its budget sets no limit."""
        budget = budget_of(self.objective)
        if budget is None or budget.unlimited:
            return None
        return float(budget.fraction())

    def _start_mask(self, start) -> np.ndarray:
        """``start`` (element indices or a boolean mask) as a boolean mask of ``k`` elements."""
        mask = np.asarray(start)
        if mask.dtype != bool or mask.shape != (self.n,):
            idx = np.asarray(start, dtype=np.int64)
            if idx.size != self.k:
                raise ParameterError(f"a swap search start must hold k = {self.k} elements, got {idx.size}")
            mask = np.zeros(self.n, dtype=bool)
            mask[idx] = True
        if int(mask.sum()) != self.k:
            raise ParameterError(f"a swap search start must hold k = {self.k} elements, got {int(mask.sum())}")
        return mask

