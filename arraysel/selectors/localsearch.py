"""The swap engine: iterated local search by swaps over exact-``k`` selections.

A *swap* replaces one active element by one inactive element, so every move keeps exactly ``k``
active elements; a selection has ``k (Ne - k)`` swap neighbours. ``swap``, the ``polish`` option,
``memetic`` and ``ils`` run this engine, each with a preset of its one settings object
(:mod:`arraysel.selectors.swapsettings`). The engine is split by concept:

* :mod:`arraysel.selectors.swapsettings`: :class:`SwapSettings`, its defaults and the presets;
* :mod:`arraysel.selectors.searchstate`: the scores seen (a cache), the model of the loss, the
  best selection, fresh selections (:class:`~arraysel.selectors.searchstate.SearchState`);
* :mod:`arraysel.selectors.descent`: a descent to a local optimum
  (:class:`~arraysel.selectors.descent.SwapDescent`): first improvement in chunks of
  ``chunk``, a share ``guide`` of each in the order a model of the loss predicts (the gradient,
  or with the Hessian: ``model``), a local optimum declared after ``scan`` x the neighbourhood
  without improvement; or best improvement; then segment shifts (``shift``) and two-swaps
  (``pairs``) at a local optimum of swaps;
* this module: :class:`SwapSearch`, the race and the iterated local search;
* :mod:`arraysel.selectors.elite`: :class:`EliteSearch`, an elite pool with path relinking (``ils``).

:meth:`SwapSearch.run` from a start selection:

1. **race** (``race`` above 1, successive halving): descents from the start and from ``race - 1``
   fresh selections (``fresh``: random, chirped layouts, or both, ``mixed``) move in turns of
   ``race_quota`` scored selections (doubled each turn; automatic: the turns share
   :data:`RACE_SHARE` of the budget), the better half going on after each turn; the winner's
   local optimum is where the search goes on. Where a descent's outcome depends mostly on its
   start (a probe whose good selections are block layouts, such as l11-5v), this spends the
   budget on the promising starts;
2. **perturbation**: from the best local optimum found, ``perturb`` random swaps, then a new
   descent; the result replaces the base when it is no worse. With ``max_perturb`` above
   ``perturb`` the strength grows by one swap after each perturbation that found no new best, up
   to ``max_perturb``, and falls back to ``perturb`` after one that did;
3. **restart**: after ``restart_after`` perturbations in a row that did not improve the best, the
   next descent starts from a fresh selection (``restart_from``, else by ``fresh``).

It runs until the objective raises :class:`~arraysel.selectors.contract.BudgetExhausted` or its
budget is spent (or ``max_rounds`` perturbations when given, or when
:attr:`~arraysel.selectors.searchstate.SearchState.MAX_IDLE_ROUNDS` rounds in a row found
nothing new to score: the reachable selections of a tiny problem are all known). The run is
reproducible: all randomness comes from the generator passed in.
"""
from __future__ import annotations

import math

import numpy as np

from arraysel.selection import survivors
from arraysel.selectors.descent import SwapDescent
# the moves, the loss's models, the settings and the elite-pool search live in their own modules;
# their names stay importable from here
from arraysel.selectors.elite import EliteSearch
from arraysel.selectors.lossmodel import (GRADIENT_CHOICES, GRADIENT_UPDATE_MAX, MODEL_CHOICES, PAIR_WIDTH,
                                          QUADRATIC_MAX_ELEMENTS, GuidedOrder, best_pair_swaps, loss_gradient,
                                          loss_quadratic, model_options, move_changes, swap_changes)
from arraysel.selectors.moves import (SHIFT_LEN, SHIFT_SCAN, apply_shifts, random_swap_pairs, random_swaps,
                                      shift_moves, shift_options, shift_segments, shifted_masks)
from arraysel.selectors.starts import CHIRP_CANDIDATES, chirp_masks
from arraysel.selectors.swapsettings import (FRESH_CHIRPS, FRESH_CHOICES, ILS, MEMETIC, POLISH, RACE_CHIRP_PROBE,
                                             RACE_CHIRP_SHARE, RACE_QUOTA, RACE_SHARE, SWAP, SwapSettings)

__all__ = ["SwapSearch", "EliteSearch", "SwapSettings", "SWAP", "POLISH", "MEMETIC", "ILS",
           "FRESH_CHOICES", "FRESH_CHIRPS", "RACE_SHARE", "RACE_QUOTA", "RACE_CHIRP_SHARE", "RACE_CHIRP_PROBE",
           # from arraysel.selectors.moves and arraysel.selectors.lossmodel
           "SHIFT_LEN", "SHIFT_SCAN", "random_swaps", "random_swap_pairs", "shift_moves", "shift_segments",
           "shifted_masks", "apply_shifts", "shift_options", "MODEL_CHOICES", "QUADRATIC_MAX_ELEMENTS", "PAIR_WIDTH",
           "GRADIENT_CHOICES", "GRADIENT_UPDATE_MAX", "GuidedOrder", "loss_gradient", "loss_quadratic",
           "swap_changes", "move_changes", "best_pair_swaps", "model_options"]


class SwapSearch(SwapDescent):
    """Iterated swap local search on a :class:`~arraysel.selectors.contract.BudgetedObjective`
    (see the module): a race of first descents, then rounds of perturbation (or restart) and
    descent from the best local optimum.

    Constructed as :class:`~arraysel.selectors.searchstate.SearchState`:
    ``SwapSearch(objective, k, rng, settings=SWAP, *, restart_from=None, max_rounds=None,
    cache_size=2_000_000, **changes)``, the settings a
    :class:`~arraysel.selectors.swapsettings.SwapSettings` (``swap``'s measured best by
    default) and ``changes`` settings by name laid over it.
    """

    def run(self, start) -> tuple[list[int], float]:
        """Search from ``start`` (element indices or a boolean mask); return the best
        selection and its Mean. With ``race`` above 1, descents from it and ``race - 1``
        fresh selections are raced (:meth:`race_descents`) and the search goes on from the
        winner's local optimum. Ends by the objective's BudgetExhausted (propagated) or after
        ``max_rounds`` rounds."""
        mask = self._start_mask(start)
        if self.k in (0, self.n):
            self._note(mask, float(self.score(mask[None])[0]))
        else:
            if self.race > 1:
                mask = self.race_descents([mask] + self._race_starts(self.race - 1))
            self.iterate(mask)
        return [int(i) for i in np.flatnonzero(self.best_mask)], self.best_value

    def race_descents(self, starts: list[np.ndarray]) -> np.ndarray:
        """Successive halving of descents (:meth:`descend`) from ``starts``: each in turn moves
        for its share of the turn, then the better half by value goes on with its share doubled,
        until one is left; its descent is finished and its local optimum returned. A share is
        ``race_quota`` more scored selections in the first turn, doubled each turn; automatic
        (``race_quota`` None), each of the ``ceil(log2(len(starts)))`` turns has an equal part of
        :data:`RACE_SHARE` of the budget, split evenly among its descents, and what the models of
        the loss take is not charged to a turn (:meth:`_race_used`; without a limited budget,
        :data:`RACE_QUOTA` selections). A descent moves on while its share is not used up, so it
        may overrun it by the cost of one move. A descent that has reached its local
        optimum scores nothing more while it stays in the race."""
        racers = []
        for m in starts:
            v = float(self.score(m[None])[0])
            self._note(m, v)
            racers.append([self._descent(m, v), m, v, False])
        quota = self.race_quota
        turn_share = RACE_SHARE / max(1, math.ceil(math.log2(len(racers))))
        if quota is None and self._budget_used() is None:
            quota = RACE_QUOTA
        spent = self._race_used if quota is None else (lambda: self.scored)  # what a turn charges
        while len(racers) > 1:
            for r in racers:
                stop = spent() + (turn_share / len(racers) if quota is None else quota)
                while not r[3] and spent() < stop:
                    try:
                        r[1], r[2] = next(r[0])
                    except StopIteration:
                        r[3] = True
            racers.sort(key=lambda r: r[2])
            self.local_optima += sum(r[3] for r in racers[len(racers) // 2:])  # the winner's: in iterate
            racers = racers[:len(racers) // 2]
            if quota is not None:
                quota *= 2
        descent, mask, _, _ = racers[0]
        for mask, _ in descent:
            pass
        return mask

    def iterate(self, mask: np.ndarray) -> None:
        """The iterated local search from ``mask`` (see the module): descent, then rounds of
        perturbation (or restart) and descent; ends after ``max_rounds`` rounds, when the budget
        is spent or when nothing new is left to score (BudgetExhausted propagates). The best
        selection is ``best_mask``."""
        value = float(self.score(mask[None])[0])
        self._note(mask, value)
        base, base_value = self.descend(mask, value)
        self.local_optima += 1
        best = base_value
        stale = rounds = idle = 0  # idle: rounds in a row that scored nothing new
        strength = self.perturb
        while self.max_rounds is None or rounds < self.max_rounds:
            rounds += 1
            if self.objective.remaining() <= 0:  # also stops a time budget when all is cached
                return
            spent = self.scored
            restart = (self.restart_after and stale >= self.restart_after) or self.perturb == 0
            if restart:
                start_mask, stale, strength = self._fresh_mask(self.rng), 0, self.perturb
            else:
                start_mask = self.perturbed(base, strength)
            v = float(self.score(start_mask[None])[0])
            self._note(start_mask, v)
            cand, cand_value = self.descend(start_mask, v)
            self.local_optima += 1
            improved = cand_value < best  # (the descent's moves are noted: compare with the best before)
            best = min(best, cand_value)
            if restart or cand_value <= base_value:
                base, base_value = cand, cand_value
            stale = 0 if improved else stale + 1
            strength = self.perturb if improved else min(self.max_perturb, strength + 1)
            idle = idle + 1 if self.scored == spent else 0
            if idle >= self.MAX_IDLE_ROUNDS:
                return  # the reachable selections are all scored (a tiny problem)

    def perturbed(self, base: np.ndarray, strength: int) -> np.ndarray:
        """The start of a round's descent from ``base``: ``strength`` random swaps (feasible ones
        under channel groups)."""
        if self.constraints is None:
            return random_swaps(base, strength, self.rng)
        return random_swaps(base, strength, self.rng, self.constraints)

    # -- the race -------------------------------------------------------------------
    def _race_starts(self, m: int) -> list[np.ndarray]:
        """The ``m`` extra starts of a race: by ``restart_from`` or ``fresh = random``, fresh
        selections; by ``fresh = chirp``, the ``m`` best distinct of ``m`` x :attr:`race_chirps`
        chirped layouts (:meth:`_race_chirps`); by ``fresh = mixed``, ``c = ceil(m / 2)`` chosen
        so from ``c`` x that many, then ``m - c`` random selections."""
        c = self.race_chirped(m)
        if c == 0:
            return [self._fresh_mask(self.rng) for _ in range(m)]
        masks, values = self._race_chirps(c)
        chirped = list(survivors(masks, values, c)[0])
        return chirped + [self._random_mask(self.rng) for _ in range(m - c)]

    def race_chirped(self, m: int) -> int:
        """How many of a race's ``m`` extra starts (:meth:`_race_starts`) are chirped layouts, the
        first ones; the rest are fresh selections (``restart_from``'s, or random)."""
        if self.restart_from is not None or self.fresh == "random":
            return 0
        return m if self.fresh == "chirp" else (m + 1) // 2

    def _race_chirps(self, c: int) -> tuple[np.ndarray, np.ndarray]:
        """The chirped layouts ``c`` chirped race starts are chosen from, and their Means.

        With :attr:`race_chirps` set, ``c`` x that many, scored in one call. Automatic (None):
        :data:`RACE_CHIRP_PROBE` a start are scored first; the share of the budget they used
        gives what one costs, and as many more as bring the total to
        :data:`RACE_CHIRP_SHARE` of the budget (at most
        :data:`~arraysel.selectors.starts.CHIRP_CANDIDATES` a start, that many without a
        limited budget) are scored in a second call."""
        if self.race_chirps is not None:
            masks = chirp_masks(self.objective, self.k, self.rng, c * self.race_chirps)
            return masks, self.score(masks)
        first = chirp_masks(self.objective, self.k, self.rng, c * RACE_CHIRP_PROBE)
        before = self._budget_used()
        values = self.score(first)
        after = self._budget_used()
        total = c * CHIRP_CANDIDATES
        if before is not None and after > before:
            total = min(total, int(RACE_CHIRP_SHARE * first.shape[0] / (after - before) + 1e-6))
        more = total - first.shape[0]
        if more <= 0:
            return first, values
        extra = chirp_masks(self.objective, self.k, self.rng, more)
        return np.concatenate([first, extra]), np.concatenate([values, self.score(extra)])

    def _race_used(self) -> float:
        """The used share of the budget less what the models took (:attr:`model_used`): what an
        automatic race charges a descent's turn, so a descent that forms a Hessian moves as far
        as one that reuses it."""
        return self._budget_used() - self.model_used

