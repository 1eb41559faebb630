"""Swap local search over exact-``k`` selections (shared by ``swap``, ``polish`` and others).

A *swap* replaces one active element by one inactive element, so every move
keeps exactly ``k`` active elements; a selection has ``k (Ne - k)`` swap
neighbours. :class:`SwapSearch` is an iterated local search:

1. **descent** from the current selection, in one of two modes:

   * ``first`` (default): the neighbours are visited in a random order, in
     chunks of ``chunk`` masks per ``objective.evaluate`` call (with ``lead`` above 0 the first
     chunk from each selection holds ``lead`` masks and each next one twice as many, up to
     ``chunk``: cheap steps while most chunks hold an improving swap); as soon as a
     chunk holds an improving neighbour the search moves to the best of that
     chunk and starts over from the new selection (a fresh random order). When
     ``scan`` x the neighbourhood was scored without improvement the
     selection is taken as a local optimum. With *gradient guidance*
     (``guide`` > 0, an objective with ``mask_loss``), a share of each chunk
     is taken from the swaps a model of the loss at the selection predicts to
     improve most, the rest in the random order; the share adapts to where the
     chunks' best moves come from (:class:`GuidedOrder`). The model is the
     gradient (``model = linear``: ``g[into] - g[out]``) or the gradient and the
     Hessian (``quadratic``, :func:`swap_changes`; a Hessian formed every
     ``refresh`` moves). The quadratic model puts the best swaps first, so a
     small ``scan`` (the best predicted eighth of the neighbourhood, say) ends
     a descent several times more cheaply, at a selection that is nearly, if
     not always, a local optimum;
   * ``best``: every neighbour is scored (one batched call, split in pieces
     by the objective) and the search moves to the best one while it improves;

   with ``shift`` above 0, a selection no swap improves is tried with *segment shifts*
   (:func:`shift_moves`: the active and inactive elements of a run of at most ``shift_len``
   consecutive indices rotated by up to ``shift`` places, k kept), the distinct ones that change
   the selection, ``chunk`` a call (scored as moves of several elements from the selection,
   :meth:`SwapSearch.score_moved`, when the objective has ``score_moves``); the descent goes on
   swapping from the best of the first chunk that improves, and ends when ``shift_scan`` shifts
   (or all) improve nothing. A shift moves a group of elements together, such as a block of a
   periodic layout, which single swaps can only do through worse selections. In a guided descent
   the shifts are ordered as the swaps are: a share of each chunk (its own :class:`GuidedOrder`)
   in the order the model predicts (:func:`move_changes`), the rest in a random order. The
   improving shifts are then mostly among the first few hundred, so a ``shift_scan`` of 512, say,
   ends a descent for a fraction of a full scan's cost (several thousand shifts); with ``pairs``
   above 0 and the quadratic model, a selection neither swaps nor shifts improve is tried with
   the ``pairs`` two-swaps (two elements off, two on) the model predicts best
   (:func:`best_pair_swaps`), ``chunk`` a call in that order, and the descent goes on from the
   first improving one;

2. **perturbation**: from the best local optimum found, ``perturb`` random
   swaps, then a new descent; the result replaces the base when it is no
   worse (better-or-equal acceptance). With ``max_perturb`` above ``perturb``
   the strength grows by one swap after each perturbation that found no new
   best, up to ``max_perturb``, and falls back to ``perturb`` after one that
   did (variable-strength perturbation: a good selection's basin is often
   wider than a two-swap step, which a descent undoes);
3. **restart**: after ``restart_after`` perturbations in a row that did not
   improve the best, the next descent starts from a fresh start selection
   (``restart_from``, or ``fresh``: a random one by default, the best of
   :data:`FRESH_CHIRPS` random chirped layouts, :func:`arraysel.selectors.starts.chirp_masks`,
   or with ``fresh = mixed`` chirped and random in turn, chirped first).

With ``race`` above 1 the first descent is a **race** (successive halving): descents from the
start and from ``race - 1`` fresh selections (``fresh = chirp``: the best distinct of
``(race - 1) x race_chirps`` chirped layouts, scored in one call, ``race_chirps`` by default
:data:`~arraysel.selectors.starts.CHIRP_CANDIDATES`; ``fresh = mixed``: half of them, rounded
up, chosen so, the rest random) move in
turns of ``race_quota`` scored selections each, the better half going on after each turn with
the quota doubled; the winner's local optimum is where the iterated local search goes on (with ``race_quota`` None
the turns share :data:`RACE_SHARE` of the budget instead, less what the models of the loss
take, and with ``race_chirps`` None the chirped layouts take :data:`RACE_CHIRP_SHARE`). Where
a descent's outcome depends mostly on its start (a probe whose good selections are block
layouts, such as l11-5v), this spends the budget on the promising starts. Mixed extra starts let
one race hold both kinds of funnel: chirped block layouts, and the nearly alternating layouts a
descent from a random selection reaches (c5-2v's best), for half the cost of choosing chirped ones.

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
from arraysel.objective.neighbours import move_masks, moves_between, swap_masks, swap_pairs
from arraysel.selection import mask_key, survivors
# the moves and the loss's models live in their own modules; their names stay importable from here
from arraysel.selectors.lossmodel import (GRADIENT_CHOICES, GRADIENT_UPDATE_MAX, MODEL_CHOICES, PAIR_WIDTH,
                                          QUADRATIC_MAX_ELEMENTS, GuidedOrder,
                                          best_pair_swaps, loss_gradient, loss_quadratic, model_options,
                                          move_changes, swap_changes)
from arraysel.selectors.moves import (SHIFT_LEN, SHIFT_SCAN, apply_shifts, random_swap_pairs, random_swaps,
                                      shift_moves, shift_options, shift_segments, shifted_masks)
from arraysel.selectors.starts import CHIRP_CANDIDATES, chirp_masks, random_mask

#: where fresh selections (restarts, extra starts) come from (``mixed``: chirped and random in turn)
FRESH_CHOICES = ("random", "chirp", "mixed")
#: chirped layouts a ``fresh = chirp`` restart scores (one call), keeping the best
FRESH_CHIRPS = 32

#: share of the budget an automatic race (``race_quota`` None) gives its turns: each turn an
#: equal part of it, split evenly among the descents still racing
RACE_SHARE = 1.0 / 3.0
#: selections a raced descent scores in the first turn without a limited budget (``race_quota``
#: None on an objective whose budget has no limit)
RACE_QUOTA = 500
#: share of the budget an automatic ``race_chirps`` (None) spends on a race's chirped layouts
RACE_CHIRP_SHARE = 0.1
#: chirped layouts an automatic ``race_chirps`` scores first for each chirped start, to learn
#: what one costs
RACE_CHIRP_PROBE = 16

__all__ = ["FRESH_CHOICES", "FRESH_CHIRPS", "RACE_SHARE", "RACE_QUOTA", "RACE_CHIRP_SHARE", "RACE_CHIRP_PROBE",
           "SwapSearch", "EliteSearch",
           # from arraysel.selectors.moves and arraysel.selectors.lossmodel
           "SHIFT_LEN", "SHIFT_SCAN", "random_swaps", "random_swap_pairs", "shift_moves", "shift_segments",
           "shifted_masks", "shift_options", "MODEL_CHOICES", "QUADRATIC_MAX_ELEMENTS", "PAIR_WIDTH", "GuidedOrder",
           "loss_gradient", "loss_quadratic", "swap_changes", "move_changes", "best_pair_swaps", "model_options"]


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
    max_perturb : most random swaps of a perturbation, its strength growing from ``perturb`` by
        one after each perturbation without a new best (None: ``perturb``, a fixed strength)
    restart_after : non-improving perturbations in a row before a restart (0: never)
    restart_from : callable ``rng -> mask`` giving restart selections (default: by ``fresh``)
    fresh : ``random`` (a uniformly random selection), ``chirp`` (the best of
        :data:`FRESH_CHIRPS` random chirped layouts, scored in one call) or ``mixed`` (the two in
        turn, chirped first): the restarts' selections, and a race's extra starts
        (:meth:`_race_starts`)
    guide : first share of each ``first``-mode chunk taken in the order the loss's gradient
        predicts (:class:`GuidedOrder`; 0: random order only, no gradient computed)
    max_rounds : stop after this many perturbations/restarts (None: until the budget ends)
    cache_size : most scored selections remembered
    race : descents raced by successive halving (:meth:`race_descents`) before the iterated local
        search: the one from the start and ``race - 1`` from fresh selections (1: no race)
    race_quota : selections each raced descent scores in the first turn (doubled each turn);
        None: the turns share :data:`RACE_SHARE` of the budget (:meth:`race_descents`)
    race_chirps : chirped layouts scored for each chirped extra start of a race (``fresh`` =
        ``chirp`` or ``mixed``; :meth:`_race_starts`); None: as many as
        :data:`RACE_CHIRP_SHARE` of the budget allows, at most
        :data:`~arraysel.selectors.starts.CHIRP_CANDIDATES`
    shift : largest displacement of a segment shift (:func:`shift_moves`); above 0, a descent at
        a local optimum of swaps scores segment shifts (random order, ``chunk`` a call) and
        goes on swapping from the first improving one; after ``shift_scan`` shifts without
        improvement (or all of them) the selection is a local optimum of both moves (0: swaps only)
    shift_len : longest segment a shift moves
    shift_scan : shifts scored without improvement before a local optimum is declared
    model : how a guided descent predicts the change of a swap: ``linear`` (the gradient) or
        ``quadratic`` (the gradient and the Hessian, :func:`loss_quadratic`); None: quadratic on
        arrays of at most :data:`QUADRATIC_MAX_ELEMENTS` elements, linear on larger ones
    refresh : ``quadratic``: predictions between Hessians
    gradient : ``quadratic``: the gradient of each prediction between Hessians: ``exact`` (the
        loss's, one backward pass each) or ``update`` (the model's own gradient carried along the
        moves, ``g + H d``, from the last exact one while the selection is at most
        :data:`GRADIENT_UPDATE_MAX` elements away from it; exact otherwise)
    guide_shifts : in a guided descent, order the segment shifts by the model too (:meth:`_shift_step`;
        False: a random order, as an unguided descent scores them)
    pairs : above 0, a guided descent with the quadratic model that neither swaps nor shifts
        improve scores the ``pairs`` two-swaps its model predicts best (:meth:`_pair_step`) and
        goes on from the first improving one (0: no two-swaps)
    lead : ``first`` mode: above 0, the first chunk scored from each selection holds ``lead``
        neighbours and each next one twice as many, up to ``chunk``
        (:meth:`GuidedOrder.chunks`; 0: ``chunk`` from the first)
    compound : ``first`` mode: above 1, a chunk whose best swap improves takes up to ``compound``
        of its improving swaps together (distinct elements, best first) when that scores better
        (:meth:`_compound_step`; 0 or 1: one swap a step)
    """

    #: rounds in a row without a newly scored selection after which the search stops
    MAX_IDLE_ROUNDS = 200

    def __init__(self, objective, k: int, rng: np.random.Generator, *, mode: str = "first", chunk: int = 64,
                 scan: float = 1.0, perturb: int = 2, max_perturb: int | None = None, restart_after: int = 0,
                 restart_from: Callable[[np.random.Generator], np.ndarray] | None = None,
                 guide: float = 0.5, max_rounds: int | None = None, cache_size: int = 2_000_000,
                 fresh: str = "random", race: int = 1, race_quota: int | None = RACE_QUOTA,
                 race_chirps: int | None = CHIRP_CANDIDATES, shift: int = 0,
                 shift_len: int = SHIFT_LEN, shift_scan: int = SHIFT_SCAN, model: str | None = "linear",
                 refresh: int = 8, guide_shifts: bool = True, pairs: int = 0, gradient: str = "exact",
                 compound: int = 0, lead: int = 0):
        self.objective = objective
        self.n = int(objective.n_elements)
        if model is None:
            model = "quadratic" if self.n <= QUADRATIC_MAX_ELEMENTS else "linear"
        self.model = check_choice("model", model, MODEL_CHOICES)
        self.refresh = int(check_number("refresh", refresh, lo=1, integer=True))
        self._hessian: np.ndarray | None = None  # the quadratic model's Hessian, and the moves it served
        self._hessian_age = 0
        self.gradient = check_choice("gradient", gradient, GRADIENT_CHOICES)
        self._gradient_at: tuple[np.ndarray, np.ndarray] | None = None  # (selection, the model's gradient there)
        self.gradients_updated = 0  # predictions whose gradient was carried by the Hessian
        self.hessians = 0  # Hessians formed
        self.model_used = 0.0  # share of the budget the models took (gradients, Hessians)
        self.k = int(k)
        self.rng = rng
        self.mode = check_choice("mode", mode, ("first", "best"))
        self.chunk = int(check_number("chunk", chunk, lo=1, integer=True))
        self.scan = float(check_number("scan", scan, lo=0.0, hi=1.0, lo_open=True))
        self.perturb = int(check_number("perturb", perturb, lo=0, integer=True))
        self.max_perturb = self.perturb if max_perturb is None else \
            int(check_number("max_perturb", max_perturb, lo=self.perturb, integer=True))
        self.restart_after = int(check_number("restart_after", restart_after, lo=0, integer=True))
        self.restart_from = restart_from
        self.fresh = check_choice("fresh", fresh, FRESH_CHOICES)
        self._fresh_count = 0  # fresh selections drawn (fresh = mixed alternates chirped and random)
        self.race = int(check_number("race", race, lo=1, integer=True))
        self.race_quota = None if race_quota is None else \
            int(check_number("race_quota", race_quota, lo=1, integer=True))
        self.race_chirps = None if race_chirps is None else \
            int(check_number("race_chirps", race_chirps, lo=1, integer=True))
        self.shift = int(check_number("shift", shift, lo=0, integer=True))
        self.shift_len = int(check_number("shift_len", shift_len, lo=2, integer=True))
        self.shift_scan = int(check_number("shift_scan", shift_scan, lo=1, integer=True))
        self.shifts = 0  # improving segment shifts taken
        self.pairs = int(check_number("pairs", pairs, lo=0, integer=True))
        self.pair_moves = 0  # improving two-swaps taken
        self.compound = int(check_number("compound", compound, lo=0, integer=True))
        self.lead = int(check_number("lead", lead, lo=0, integer=True))
        self.compound_moves = 0  # steps that took several swaps of a chunk together
        self._shifts: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None  # (at, source, keys); formed once
        self.guide = GuidedOrder(float(check_number("guide", guide, lo=0.0, hi=1.0)))
        self.shift_guide = GuidedOrder(self.guide.share)  # the shifts' guided share adapts on its own
        self.guide_shifts = bool(guide_shifts)
        self._model_at: tuple[bytes, tuple[np.ndarray, np.ndarray | None] | None] | None = None
        self._guided = self.guide.share > 0 and callable(getattr(objective, "mask_loss", None))
        self.max_rounds = max_rounds
        self.cache_size = int(cache_size)
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
        neighbours not seen before are scored in one call of the objective's ``score_swaps``
        (:mod:`arraysel.objective.neighbours`) when it has one."""
        cands = swap_masks(mask, a, b)
        own = getattr(self.objective, "score_swaps", None)
        if own is None:
            return cands, self.score(cands)
        return cands, self._cached(cands, lambda todo: own(mask, a[todo], b[todo]))

    def score_moved(self, mask: np.ndarray, cands: np.ndarray) -> np.ndarray:
        """Means of the selections ``cands`` (B, Ne), each with as many elements as ``mask``: the
        ones not seen before are scored as moves from ``mask`` in one call of the objective's
        ``score_moves`` (:mod:`arraysel.objective.neighbours`) when it has one."""
        own = getattr(self.objective, "score_moves", None)
        if own is None:
            return self.score(cands)
        return self._cached(cands, lambda todo: own(mask, *moves_between(mask, cands[todo])))

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
        :func:`loss_quadratic`). None without a usable loss. Asked again at the same selection
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
                q = loss_quadratic(self.objective, mask)
                if q is None:
                    return None
                g, self._hessian, self._hessian_age = q[0], q[1], 0
                self.hessians += 1
            else:
                g = self._carried_gradient(mask)
                if g is None:
                    g = loss_gradient(self.objective, mask)
            self._hessian_age += 1
            if g is not None and self.gradient == "update":
                self._gradient_at = (mask.astype(np.float64), g)
            return None if g is None else (g, self._hessian)
        g = loss_gradient(self.objective, mask)
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

    # -- descent -------------------------------------------------------------------
    def descend(self, mask: np.ndarray, value: float) -> tuple[np.ndarray, float]:
        """Improve ``mask`` by swaps until it is a local optimum; return it and its value."""
        mask = mask.copy()
        for mask, value in self._descent(mask, value):
            pass
        return mask, value

    def _descent(self, mask: np.ndarray, value: float):
        """:meth:`descend` one move at a time: yields ``(mask, value)`` after each improving swap
        and ends at a local optimum."""
        while True:
            a, b = swap_pairs(mask, self.rng)
            if a.size == 0:
                return
            moved = False
            if self.mode == "best":
                cands, values = self.score_swaps(mask, a, b)
                i = int(np.argmin(values))
                if values[i] < value:
                    mask, value, moved = cands[i], float(values[i]), True
            else:
                limit = max(1, int(math.ceil(self.scan * a.size)))
                pred = None
                if self._guided and self.guide.wants_gradient():
                    pred = self._predict(mask, a, b)
                    self._guided = pred is not None  # an objective without a usable gradient: never again
                for pick, ng in self.guide.chunks(a, b, pred, self.chunk, limit, self.lead):
                    cands, values = self.score_swaps(mask, a[pick], b[pick])
                    i = int(np.argmin(values))
                    if values[i] < value:
                        self.guide.credit(None if pred is None else bool(i < ng))
                        step = cands[i], float(values[i])
                        if self.compound > 1:
                            step = self._compound_step(mask, value, a[pick], b[pick], values, step)
                        (mask, value), moved = step, True
                        break
            if not moved and self.shift:
                found = self._shift_step(mask, value)
                if found is not None:
                    (mask, value), moved = found, True
                    self.shifts += 1
            if not moved and self.pairs:
                found = self._pair_step(mask, value)
                if found is not None:
                    (mask, value), moved = found, True
                    self.pair_moves += 1
            if not moved:
                return
            self.moves += 1
            self._note(mask, value)
            yield mask, value

    def _compound_step(self, mask: np.ndarray, value: float, a: np.ndarray, b: np.ndarray,
                       values: np.ndarray, single: tuple[np.ndarray, float]) -> tuple[np.ndarray, float]:
        """The move a chunk of swaps ``(a[i], b[i])`` of ``mask`` whose Means are ``values`` leads
        to, when its best one, ``single`` (its selection and Mean), improves on ``value``
        (``compound`` above 1): the improving swaps that switch distinct elements, best first,
        are taken together as far as that scores best (the prefixes of up to ``compound`` of
        them, scored in one call as moves, :meth:`score_moved`), so a descent where many swaps
        improve at once takes several a step; ``single`` when fewer than two such swaps improve
        or no prefix scores below it."""
        order = np.argsort(values, kind="stable")
        taken, used = [], set()
        for j in order:
            if not values[j] < value or len(taken) == self.compound:
                break
            if int(a[j]) in used or int(b[j]) in used:
                continue
            taken.append(j)
            used.update((int(a[j]), int(b[j])))
        if len(taken) < 2:
            return single
        prefixes = np.repeat(mask[None], len(taken) - 1, axis=0)   # row p: the first p + 2 swaps
        for q, j in enumerate(taken):
            prefixes[max(0, q - 1):, a[j]] = False
            prefixes[max(0, q - 1):, b[j]] = True
        pv = self.score_moved(mask, prefixes)
        j = int(np.argmin(pv))
        if pv[j] < single[1]:
            self.compound_moves += 1
            return prefixes[j].copy(), float(pv[j])
        return single

    def _shift_step(self, mask: np.ndarray, value: float) -> tuple[np.ndarray, float] | None:
        """The best shift of the first chunk holding one that improves on ``value``, or None after
        ``shift_scan`` shifts (or all) without improvement. Only the distinct shifted selections
        that differ from ``mask`` are scored, in a random order or, in a guided descent, a share
        of each chunk in the order the model predicts (:func:`move_changes`, :attr:`shift_guide`).
        A shift is held as the few elements it changes (:func:`shift_segments`); only the
        selections of the chunks scored are formed."""
        if self._shifts is None:
            at, source = shift_segments(self.n, shift_moves(self.n, self.shift_len, self.shift))
            keys = np.random.default_rng(0).integers(1, 2 ** 62, size=self.n + 1, dtype=np.int64)
            keys[self.n] = 0
            self._shifts = (at, source, keys)
        at, source, keys = self._shifts
        order = self.rng.permutation(len(at))
        at, source = at[order], source[order]
        extended = np.append(mask, False)
        d = extended[source].astype(np.int8) - extended[at]
        # equal changes give equal keys (sums mod 2**64 of a key an element): one of each is kept
        key = (d.astype(np.int64) * keys[at]).sum(axis=1)
        _, first = np.unique(key, return_index=True)
        first = np.sort(first)  # the random order
        first = first[np.any(d[first] != 0, axis=1)]
        if first.size == 0:
            return None
        at, source, d = at[first], source[first], d[first]
        pred = None
        if self._guided and self.guide_shifts and self.shift_guide.wants_gradient():
            m = self._model(mask)
            self._guided = m is not None
            pred = None if m is None else move_changes(m[0], m[1], at, d)
        index = np.arange(first.size)
        for pick, ng in self.shift_guide.chunks(index, index, pred, self.chunk, min(self.shift_scan, index.size)):
            cands = apply_shifts(extended, at[pick], source[pick])
            values = self.score_moved(mask, cands)
            i = int(np.argmin(values))
            if values[i] < value:
                self.shift_guide.credit(None if pred is None else bool(i < ng))
                return cands[i].copy(), float(values[i])
        return None

    def _pair_step(self, mask: np.ndarray, value: float) -> tuple[np.ndarray, float] | None:
        """The best two-swap of the first chunk holding one that improves on ``value``, among the
        ``pairs`` two-swaps the quadratic model at ``mask`` predicts best
        (:func:`best_pair_swaps`), scored ``chunk`` a call in that order (as moves of two elements,
        :meth:`score_moved`); None when none of them improves, or without a quadratic model
        (``model = linear``, or an objective without a usable loss)."""
        model = self._model(mask) if self._guided else None
        if model is None or model[1] is None:
            return None
        out, into, _ = best_pair_swaps(model[0], model[1], mask, self.pairs)
        for s in range(0, out.shape[0], self.chunk):
            cands = move_masks(mask, out[s:s + self.chunk], into[s:s + self.chunk])
            values = self.score_moved(mask, cands)
            j = int(np.argmin(values))
            if values[j] < value:
                return cands[j].copy(), float(values[j])
        return None

    # -- iterated local search ---------------------------------------------------------
    def _random_mask(self, rng: np.random.Generator) -> np.ndarray:
        return random_mask(rng, self.n, self.k)

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

    def _budget_used(self) -> float | None:
        """The used share of the objective's budget (``budget.fraction()``), or None where the
        objective has no budget or its budget sets no limit."""
        budget = getattr(self.objective, "budget", None)
        if budget is None or getattr(budget, "unlimited", True) or not callable(getattr(budget, "fraction", None)):
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
                start_mask = random_swaps(base, strength, self.rng)
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


class EliteSearch(SwapSearch):
    """Multi-start iterated local search over an elite pool, with path relinking.

    1. **starts**: the given start and ``starts - 1`` random selections, each improved by a
       descent (:meth:`SwapSearch.descend`) into a local optimum; the distinct local optima
       found so far, at most ``elite`` of them, the best first, form the *elite pool*;
    2. **rounds**, until the budget ends: with probability ``relink`` (and at least two
       elites) a *path relinking* from one elite towards another (:meth:`relink`), otherwise a
       *perturbation* of an elite (a random one of the better half) by ``strength`` random
       swaps; then a descent from the result, which enters the pool when it is new and better
       than its worst member (replacing it). ``strength`` starts at ``perturb``, grows by one
       after each round that found no new best (up to ``max_perturb``) and falls back to
       ``perturb`` when one does (variable-strength perturbation);
    3. **restart**: after ``restart_after`` rounds in a row without a new best, a fresh random
       selection is descended and enters the pool (which keeps the best elites).

    Path relinking from ``A`` towards ``B`` walks, one swap at a time, from ``A`` to ``B``: each
    step scores (one batched call) the swaps of an element of ``A`` not in ``B`` for one of ``B``
    not in ``A`` still to be made (at most ``relink_batch`` of them, a random subset when there
    are more) and takes the best; the best selection strictly between the two ends is the
    result. It combines what two good, different selections share.

    Every call of the objective is a batch; the run is reproducible from the generator. It
    ends like :class:`SwapSearch` (the objective's BudgetExhausted, or ``max_rounds``).
    """

    def __init__(self, objective, k: int, rng: np.random.Generator, *, starts: int = 4, elite: int = 8,
                 relink: float = 0.5, relink_batch: int = 256, max_perturb: int = 8, **kw):
        super().__init__(objective, k, rng, **kw)
        self.starts = int(check_number("starts", starts, lo=1, integer=True))
        self.elite = int(check_number("elite", elite, lo=1, integer=True))
        self.relink_p = float(check_number("relink", relink, lo=0.0, hi=1.0))
        self.relink_batch = int(check_number("relink_batch", relink_batch, lo=1, integer=True))
        # replaces SwapSearch's max_perturb (which must be >= perturb): here any count >= 0, used as
        # at least 1 by the rounds' own strength schedule (run)
        self.max_perturb = int(check_number("max_perturb", max_perturb, lo=0, integer=True))
        self.pool: list[tuple[float, bytes, np.ndarray]] = []  # (value, key, mask), best first
        self.relinks = 0

    def _enter(self, mask: np.ndarray, value: float) -> None:
        """Offer a local optimum to the elite pool (distinct selections, the best ``elite``)."""
        self._note(mask, value)
        key = mask_key(mask)
        if any(key == kk for _, kk, _ in self.pool) or not math.isfinite(value):
            return
        if len(self.pool) >= self.elite:
            if value >= self.pool[-1][0]:
                return
            self.pool.pop()
        self.pool.append((value, key, mask.copy()))
        self.pool.sort(key=lambda e: e[0])

    def relink(self, a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, float] | None:
        """The best selection strictly between ``a`` and ``b`` on a greedy swap path from ``a``
        towards ``b`` (see the class); None when they are one swap apart or less."""
        cur = a.copy()
        best: tuple[np.ndarray, float] | None = None
        while True:
            outs = np.flatnonzero(cur & ~b)
            ins = np.flatnonzero(b & ~cur)
            if outs.size <= 1:  # the next swap would reach b
                return best
            o = np.repeat(outs, ins.size)
            i = np.tile(ins, outs.size)
            if o.size > self.relink_batch:
                pick = self.rng.choice(o.size, self.relink_batch, replace=False)
                o, i = o[pick], i[pick]
            cands, values = self.score_swaps(cur, o, i)
            j = int(np.argmin(values))
            cur = cands[j]
            if best is None or values[j] < best[1]:
                best = (cur.copy(), float(values[j]))

    def run(self, start) -> tuple[list[int], float]:
        """Search from ``start`` (element indices or a boolean mask) and ``starts - 1`` random
        selections; return the best selection and its Mean (see the class)."""
        mask = self._start_mask(start)
        if self.k in (0, self.n):
            value = float(self.score(mask[None])[0])
            self._note(mask, value)
            return [int(i) for i in np.flatnonzero(self.best_mask)], self.best_value
        for s in range(self.starts):
            m = mask if s == 0 else self._fresh_mask(self.rng)
            v = float(self.score(m[None])[0])
            self._note(m, v)
            m, v = self.descend(m, v)
            self.local_optima += 1
            self._enter(m, v)
        strength = max(1, self.perturb)
        stale = rounds = idle = 0
        while self.max_rounds is None or rounds < self.max_rounds:
            rounds += 1
            if self.objective.remaining() <= 0:
                break
            spent = self.scored
            best_before = self.best_value
            if not self.pool or (self.restart_after and stale >= self.restart_after):
                m, stale = self._fresh_mask(self.rng), 0  # (an empty pool: nothing finite scored yet)
                v = float(self.score(m[None])[0])
            elif len(self.pool) >= 2 and self.rng.random() < self.relink_p:
                i, j = self.rng.choice(len(self.pool), 2, replace=False)
                found = self.relink(self.pool[i][2], self.pool[j][2])
                self.relinks += 1
                if found is None:
                    idle = idle + 1 if self.scored == spent else 0
                    continue
                m, v = found
            else:
                half = max(1, (len(self.pool) + 1) // 2)
                base = self.pool[int(self.rng.integers(half))][2]
                m = random_swaps(base, strength, self.rng)
                v = float(self.score(m[None])[0])
            m, v = self.descend(m, v)
            self.local_optima += 1
            self._enter(m, v)
            if self.best_value < best_before:
                stale, strength = 0, max(1, self.perturb)
            else:
                stale += 1
                strength = min(max(1, self.max_perturb), strength + 1)
            idle = idle + 1 if self.scored == spent else 0
            if idle >= self.MAX_IDLE_ROUNDS:
                break
        return [int(i) for i in np.flatnonzero(self.best_mask)], self.best_value
