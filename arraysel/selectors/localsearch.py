"""Swap local search over exact-``k`` selections (shared by ``swap``, ``polish`` and others).

A *swap* replaces one active element by one inactive element, so every move
keeps exactly ``k`` active elements; a selection has ``k (Ne - k)`` swap
neighbours. :class:`SwapSearch` is an iterated local search:

1. **descent** from the current selection, in one of two modes:

   * ``first`` (default): the neighbours are visited in a random order, in
     chunks of ``chunk`` masks per ``objective.evaluate`` call; as soon as a
     chunk holds an improving neighbour the search moves to the best of that
     chunk and starts over from the new selection (a fresh random order). When
     ``scan`` x the neighbourhood was scored without improvement the
     selection is taken as a local optimum;
   * ``best``: every neighbour is scored (one batched call, split in pieces
     by the objective) and the search moves to the best one while it improves;

2. **perturbation**: from the best local optimum found, ``perturb`` random
   swaps, then a new descent; the result replaces the base when it is no
   worse (better-or-equal acceptance);
3. **restart**: after ``restart_after`` perturbations in a row that did not
   improve the best, the next descent starts from a fresh start selection
   (``restart_from``: a random one by default).

It runs until the objective raises :class:`~arraysel.selectors.contract.BudgetExhausted`
or its budget is spent (or ``max_rounds`` perturbations when given, or when
:attr:`SwapSearch.MAX_IDLE_ROUNDS` rounds in a row found nothing new to
score: the reachable selections of a tiny problem are all known). Scores of selections already
seen are kept (up to ``cache_size`` of them), so revisiting costs nothing.
The run is reproducible: all randomness comes from the generator passed in.
"""
from __future__ import annotations

import math
from typing import Callable

import numpy as np

from arraysel.errors import ParameterError, check_choice, check_number

__all__ = ["SwapSearch", "swap_neighbours", "random_swaps"]


def swap_neighbours(mask: np.ndarray, rng: np.random.Generator | None = None) -> tuple[np.ndarray, np.ndarray]:
    """All ``(on, off)`` swap pairs of a boolean mask, in a random order when ``rng`` is given."""
    on, off = np.flatnonzero(mask), np.flatnonzero(~mask)
    a = np.repeat(on, off.size)
    b = np.tile(off, on.size)
    if rng is not None:
        order = rng.permutation(a.size)
        a, b = a[order], b[order]
    return a, b


def random_swaps(mask: np.ndarray, m: int, rng: np.random.Generator) -> np.ndarray:
    """``mask`` after ``m`` random swaps (distinct elements swapped out and in)."""
    out = mask.copy()
    on, off = np.flatnonzero(mask), np.flatnonzero(~mask)
    m = min(m, on.size, off.size)
    if m <= 0:
        return out
    out[rng.choice(on, m, replace=False)] = False
    out[rng.choice(off, m, replace=False)] = True
    return out


class SwapSearch:
    """Iterated swap local search on a :class:`~arraysel.selectors.contract.BudgetedObjective`.

    Parameters
    ----------
    objective : the budgeted objective (its ``evaluate`` raises BudgetExhausted at the end)
    k : active elements
    rng : numpy Generator (all randomness)
    mode : ``first`` or ``best`` improvement
    chunk : neighbours per evaluate call in ``first`` mode
    scan : fraction of the neighbourhood scored without improvement before a
        selection counts as a local optimum (``first`` mode; 1: all of it)
    perturb : random swaps of a perturbation (0: no perturbation, restart instead)
    restart_after : non-improving perturbations in a row before a restart (0: never)
    restart_from : callable ``rng -> mask`` giving restart selections (default: random)
    max_rounds : stop after this many perturbations/restarts (None: until the budget ends)
    cache_size : most scored selections remembered
    """

    #: rounds in a row without a newly scored selection after which the search stops
    MAX_IDLE_ROUNDS = 200

    def __init__(self, objective, k: int, rng: np.random.Generator, *, mode: str = "first", chunk: int = 64,
                 scan: float = 1.0, perturb: int = 2, restart_after: int = 0,
                 restart_from: Callable[[np.random.Generator], np.ndarray] | None = None,
                 max_rounds: int | None = None, cache_size: int = 2_000_000):
        self.objective = objective
        self.n = int(objective.n_elements)
        self.k = int(k)
        self.rng = rng
        self.mode = check_choice("mode", mode, ("first", "best"))
        self.chunk = int(check_number("chunk", chunk, lo=1, integer=True))
        self.scan = float(check_number("scan", scan, lo=0.0, hi=1.0, lo_open=True))
        self.perturb = int(check_number("perturb", perturb, lo=0, integer=True))
        self.restart_after = int(check_number("restart_after", restart_after, lo=0, integer=True))
        self.restart_from = restart_from
        self.max_rounds = max_rounds
        self.cache_size = int(cache_size)
        self._cache: dict[bytes, float] = {}
        self.best_mask: np.ndarray | None = None
        self.best_value = math.inf
        self.moves = 0
        self.local_optima = 0

    # -- scoring with a cache ----------------------------------------------------
    @staticmethod
    def _key(mask: np.ndarray) -> bytes:
        return np.packbits(mask).tobytes()

    def score(self, masks: np.ndarray) -> np.ndarray:
        """Mean of each mask (NaN as +inf); selections seen before are not scored again."""
        keys = [self._key(m) for m in masks]
        out = np.full(len(keys), math.inf)
        todo = []
        for i, key in enumerate(keys):
            v = self._cache.get(key)
            if v is None:
                todo.append(i)
            else:
                out[i] = v
        if todo:
            values = self.objective.score(masks[todo])
            out[todo] = values
            if len(self._cache) + len(todo) > self.cache_size:
                self._cache.clear()
            for i, v in zip(todo, values):
                self._cache[keys[i]] = float(v)
        return out

    def _note(self, mask: np.ndarray, value: float) -> None:
        if value < self.best_value or self.best_mask is None:
            self.best_value, self.best_mask = value, mask.copy()

    # -- descent -------------------------------------------------------------------
    def _batch(self, mask: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        cands = np.repeat(mask[None], a.size, axis=0)
        rows = np.arange(a.size)
        cands[rows, a] = False
        cands[rows, b] = True
        return cands

    def descend(self, mask: np.ndarray, value: float) -> tuple[np.ndarray, float]:
        """Improve ``mask`` by swaps until it is a local optimum; return it and its value."""
        mask = mask.copy()
        while True:
            a, b = swap_neighbours(mask, self.rng)
            if a.size == 0:
                return mask, value
            moved = False
            if self.mode == "best":
                cands = self._batch(mask, a, b)
                values = self.score(cands)
                i = int(np.argmin(values))
                if values[i] < value:
                    mask, value, moved = cands[i], float(values[i]), True
            else:
                limit = max(1, int(math.ceil(self.scan * a.size)))
                for s in range(0, limit, self.chunk):
                    sl = slice(s, min(s + self.chunk, limit))
                    cands = self._batch(mask, a[sl], b[sl])
                    values = self.score(cands)
                    i = int(np.argmin(values))
                    if values[i] < value:
                        mask, value, moved = cands[i], float(values[i]), True
                        break
            if not moved:
                return mask, value
            self.moves += 1
            self._note(mask, value)

    # -- iterated local search ---------------------------------------------------------
    def _random_mask(self, rng: np.random.Generator) -> np.ndarray:
        m = np.zeros(self.n, dtype=bool)
        m[rng.choice(self.n, self.k, replace=False)] = True
        return m

    def run(self, start) -> tuple[list[int], float]:
        """Search from ``start`` (element indices or a boolean mask); return the best
        selection and its Mean. Ends by the objective's BudgetExhausted (propagated)
        or after ``max_rounds`` rounds."""
        mask = np.asarray(start)
        if mask.dtype != bool or mask.shape != (self.n,):
            idx = np.asarray(start, dtype=np.int64)
            if idx.size != self.k:
                raise ParameterError(f"a swap search start must hold k = {self.k} elements, got {idx.size}")
            mask = np.zeros(self.n, dtype=bool)
            mask[idx] = True
        if int(mask.sum()) != self.k:
            raise ParameterError(f"a swap search start must hold k = {self.k} elements, got {int(mask.sum())}")
        value = float(self.score(mask[None])[0])
        self._note(mask, value)
        base, base_value = self.descend(mask, value)
        self._note(base, base_value)
        self.local_optima += 1
        stale = 0
        rounds = 0
        idle = 0  # rounds in a row that scored nothing new (everything nearby is cached)
        if self.k in (0, self.n):
            return [int(i) for i in np.flatnonzero(self.best_mask)], self.best_value
        while self.max_rounds is None or rounds < self.max_rounds:
            rounds += 1
            if self.objective.remaining() <= 0:  # also stops a time budget when all is cached
                break
            spent = len(self._cache)
            restart = (self.restart_after and stale >= self.restart_after) or self.perturb == 0
            if restart:
                start_mask, stale = (self.restart_from or self._random_mask)(self.rng), 0
            else:
                start_mask = random_swaps(base, self.perturb, self.rng)
            v = float(self.score(start_mask[None])[0])
            cand, cand_value = self.descend(start_mask, v)
            self.local_optima += 1
            improved = cand_value < self.best_value
            self._note(cand, cand_value)
            if restart or cand_value <= base_value:
                base, base_value = cand, cand_value
            stale = 0 if improved else stale + 1
            idle = idle + 1 if len(self._cache) == spent else 0
            if idle >= self.MAX_IDLE_ROUNDS:
                break  # the reachable selections are all scored (a tiny problem)
        return [int(i) for i in np.flatnonzero(self.best_mask)], self.best_value
