"""Where a search starts: the start selections every built-in search offers, random subsets and
the element list of an option: the framework's, which a selector calls instead of writing its own.

* :func:`random_subsets`: uniformly random ``k``-subsets, many at once;
* :func:`random_mask`: one random ``k``-selection as a boolean mask;
* :func:`greedy_selection`: greedy backward elimination (or forward selection) on a budgeted
  objective, the ``greedy`` selector's search and the ``greedy`` start of the swap searches;
* :func:`start_selection`: the start named by a selector's ``start`` option (``uniform``,
  ``random``, ``greedy`` or ``elements``), with :data:`START_CHOICES` and the two declared
  options :func:`start_options` gives (``start`` and ``elements``).

The uniform layout itself is :func:`arraysel.selectors.layouts.uniform_layout` (matrix arrays
included); element lists are parsed by :func:`arraysel.io.masks.parse_elements`, their one home.
"""
from __future__ import annotations

import math
import time

import numpy as np

from arraysel.constraints import group_constraints
from arraysel.errors import ParameterError, check_number
from arraysel.io.masks import parse_elements
from arraysel.objective.contract import element_layout
from arraysel.selectors.constrained import budget_of
from arraysel.selectors.contract import BudgetExhausted, Option
from arraysel.selectors.layouts import chirped_layouts, is_planar, planar_uniform_layout, uniform_layout

__all__ = ["START_CHOICES", "GREEDY_START_SHARE", "CHIRP_CANDIDATES", "random_subsets", "random_mask", "chirp_masks",
           "greedy_selection", "start_selection",
           "start_options"]

#: the start selections of :func:`start_selection`
START_CHOICES = ("uniform", "random", "greedy", "chirp", "elements")

#: chirped layouts (:func:`arraysel.selectors.layouts.chirped_layouts`) a ``chirp`` start scores
CHIRP_CANDIDATES = 256

#: share of a run's budget a ``greedy`` start may spend (:func:`greedy_selection`'s ``share``);
#: the search it starts gets the rest
GREEDY_START_SHARE = 0.5


def random_subsets(rng: np.random.Generator, batch: int, n: int, k: int) -> np.ndarray:
    """``(batch, k)`` sorted element indices of uniformly random ``k``-subsets of ``range(n)``."""
    if k >= n:
        return np.tile(np.arange(n), (batch, 1))
    keys = rng.random((batch, n))
    return np.sort(np.argpartition(keys, k - 1, axis=1)[:, :k], axis=1)


def random_mask(rng: np.random.Generator, n: int, k: int) -> np.ndarray:
    """One uniformly random ``k``-selection of ``n`` elements as a boolean mask ``(n,)``."""
    mask = np.zeros(n, dtype=bool)
    mask[rng.choice(n, k, replace=False)] = True
    return mask


def chirp_masks(objective, k: int, rng: np.random.Generator, m: int) -> np.ndarray:
    """``m`` random chirped selections (:func:`~arraysel.selectors.layouts.chirped_layouts`) of
    ``k`` of the objective's elements, on its element grid when it has one: ``(m, Ne)`` bool."""
    grid, _ = element_layout(objective)
    masks = chirped_layouts(rng, int(objective.n_elements), k, m, grid)
    gc = group_constraints(objective)
    return masks if gc is None else np.stack([layout_projection(objective, np.flatnonzero(r), gc) for r in masks])


def layout_projection(objective, chosen, gc=None) -> np.ndarray:
    """A layout's selection ``chosen`` made feasible under the objective's channel groups, as a
    mask: every group that holds elements of the layout keeps one (the lowest index; a group with
    a count, such as a half of separate transmit and receive apertures, up to its count); the other
    groups the selection needs (all of them under ``exactly-one``, as many as ``k`` still
    allows under ``at-most-one``) each take, one after the other, the element farthest from those
    already kept (the lowest index first without element positions)."""
    n = int(objective.n_elements)
    gc = group_constraints(objective) if gc is None else gc
    mask = np.zeros(n, dtype=bool)
    mask[np.asarray(chosen, dtype=np.int64)] = True
    if gc is None:
        return mask
    g = gc.unit_groups
    cap = np.ones(int(g.max()) + 1, dtype=np.int64) if gc.unit_group_counts is None else gc.unit_group_counts
    out = np.zeros(n, dtype=bool)
    held = np.zeros(cap.size, dtype=np.int64)  # elements each group holds so far
    total = 0
    for e in np.flatnonzero(mask):  # a group keeps its count of the layout's elements (quotas: more than one)
        if held[g[e]] < cap[g[e]] and total < gc.k_units:
            out[e] = True
            held[g[e]] += 1
            total += 1
    _, pos = element_layout(objective)
    filled = held >= cap
    if total >= gc.k_units:
        return out
    if pos is None:
        dmin = -np.arange(n, dtype=np.float64)  # no positions: the lowest index first
    elif out.any():
        dmin = _nearest_distance(pos, pos[out])
    else:
        dmin = np.zeros(n)
    while total < gc.k_units:
        cand = np.where(filled[g] | out, -np.inf, dmin)
        e = int(np.argmax(cand))
        out[e] = True
        held[g[e]] += 1
        total += 1
        filled[g[e]] = held[g[e]] >= cap[g[e]]
        if pos is not None:
            dmin = np.minimum(dmin, np.sqrt(((pos - pos[e]) ** 2).sum(-1)))
    return out


def _nearest_distance(points: np.ndarray, kept: np.ndarray) -> np.ndarray:
    """The distance from each of ``points`` (n, d) to the nearest of ``kept`` (m, d), by a k-d tree
    of ``kept`` (n log m: a virtual array of 10,240 units with 2,560 kept takes milliseconds, where
    the (n, m) distance table took seconds)."""
    from scipy.spatial import cKDTree

    return cKDTree(np.asarray(kept, dtype=np.float64)).query(np.asarray(points, dtype=np.float64))[0]


def chirp_selection(objective, k: int, rng: np.random.Generator, m: int = CHIRP_CANDIDATES) -> list[int]:
    """The best of ``m`` random chirped layouts (:func:`chirp_masks`), scored in one call
    (``m`` evaluations of the budget); when the budget ends first, the first layout."""
    masks = chirp_masks(objective, k, rng, m)
    try:
        values = np.asarray(objective.score(masks), dtype=np.float64)
        values = np.where(np.isfinite(values), values, np.inf)
        best = masks[int(np.argmin(values))]
    except BudgetExhausted:
        best = masks[0]
    return [int(i) for i in np.flatnonzero(best)]


def _evenly(items: list[int], m: int) -> list[int]:
    """``m`` evenly spaced entries of ``items``."""
    return [items[(i * len(items)) // m] for i in range(m)] if m else []


def greedy_selection(objective, k: int, backward: bool = True, share: float = 1.0) -> list[int]:
    """Greedy backward elimination (or forward selection) on a budgeted objective.

    Backward: from all ``Ne`` elements, score every set with one element removed (one
    ``objective.score`` call) and drop the element whose removal gives the lowest ``Mean``, down to
    ``k`` elements; forward: from none, add the element giving the lowest ``Mean``. Ties go to the
    lower index; NaN scores rank last.

    One element a step costs about ``(Ne + k) (Ne - k) / 2`` evaluations (6,240 for 64 of 128
    elements). When that does not fit in ``share`` of the objective's budget (its evaluations,
    and its seconds at the rate the steps so far ran), each step takes the ``s`` best-ranked
    elements at once, ``s`` the fewest that let the remaining steps fit (an unlimited budget, or
    an objective without one, gives ``s = 1``). When the budget ends before ``k`` is reached
    anyway, the remaining steps follow the ranking of the last scored batch (or an evenly spaced
    choice when none was scored), so a selection is returned either way.
    """
    gc = group_constraints(objective)
    if gc is not None and gc.group_mode != "exactly-one":
        raise ParameterError(f"greedy elimination cannot honour the channel groups ({gc.describe()}); "
                             f"constraints.groups needs another selector (swap, anneal, ste, ...)")
    check_number("share", share, lo=0.0, hi=1.0, lo_open=True)
    n = int(objective.n_elements)
    current = list(range(n)) if backward else []
    ranking: list[int] | None = None  # candidates of the last batch, best first
    pace = _GreedyPace(budget_of(objective), share)
    room = _GroupRoom(gc, backward)  # exactly-one groups (counts): a step leaves or enters open groups only
    try:
        while len(current) != k:
            cands = room.open(current if backward else [i for i in range(n) if i not in current], current)
            if objective.remaining() < len(cands):
                break
            masks = np.zeros((len(cands), n), dtype=bool)
            masks[:, current] = True
            for r, c in enumerate(cands):
                masks[r, c] = not backward
            means = pace.timed(objective.score, masks)
            order = np.lexsort((np.arange(len(cands)), means))
            ranking = [cands[i] for i in order]
            left = abs(len(current) - k)
            take = room.take(ranking, pace.per_step(left, len(cands)), current)
            if backward:
                drop = set(take)
                current = [c for c in current if c not in drop]
            else:
                current = current + take
    except BudgetExhausted:  # a start must exist even then: finish from the last ranking below
        pass
    if len(current) != k:
        need = abs(len(current) - k)
        rest = room.open(current if backward else [i for i in range(n) if i not in current], current)
        pool = [c for c in (ranking or []) if c in rest]
        for c in _evenly(rest, need) + rest:
            if c not in pool:
                pool.append(c)
        take = room.take(pool, need, current)
        if backward:
            drop = set(take)
            current = [c for c in current if c not in drop]
        else:
            current = current + take
    return sorted(current)


class _GroupRoom:
    """Which units a greedy step may drop (backward) or add (forward) under ``exactly-one``
    channel groups with counts (the transmit/receive quota): only units of groups that hold more
    (backward) or fewer (forward) than their count, and no more of a group than that difference."""

    def __init__(self, gc, backward: bool):
        self.g = None if gc is None else gc.unit_groups
        if self.g is not None:
            c = gc.unit_group_counts
            self.cap = np.ones(int(self.g.max()) + 1, dtype=np.int64) if c is None else np.asarray(c)
        self.backward = backward

    def _room(self, current) -> np.ndarray:
        held = np.bincount(self.g[np.asarray(current, dtype=np.int64)], minlength=self.cap.size)
        return held - self.cap if self.backward else self.cap - held

    def open(self, cands: list[int], current) -> list[int]:
        if self.g is None:
            return cands
        r = self._room(current)
        return [c for c in cands if r[self.g[c]] > 0]

    def take(self, ranking: list[int], m: int, current) -> list[int]:
        if self.g is None:
            return list(ranking[:m])
        r, out = self._room(current), []
        for c in ranking:
            if len(out) == m:
                break
            if r[self.g[c]] > 0:
                out.append(c)
                r[self.g[c]] -= 1
        return out


class _GreedyPace:
    """How many elements a greedy step takes so that the remaining steps fit in ``share`` of the
    budget (:func:`greedy_selection`)."""

    def __init__(self, budget, share: float):
        self.budget = budget
        self.share = float(share)
        self.per_mask = 0.0  # seconds a mask, measured on the steps so far

    def timed(self, score, masks: np.ndarray) -> np.ndarray:
        t0 = time.perf_counter()
        out = score(masks)
        self.per_mask = (time.perf_counter() - t0) / max(1, masks.shape[0])
        return out

    def _allowance(self) -> float:
        """Evaluations the greedy may still spend (``inf`` without limits)."""
        b = self.budget
        if b is None:
            return math.inf
        room = math.inf
        if b.evaluations is not None:
            room = self.share * b.evaluations - b.used_evaluations()
        if b.seconds is not None and self.per_mask > 0:
            room = min(room, (self.share * b.seconds - b.elapsed()) / self.per_mask)
        return room

    def per_step(self, left: int, scored: int) -> int:
        """Elements to take now, ``left`` still to go after a step that scored ``scored`` masks
        (backward or forward: either way the next steps score one mask fewer each)."""
        if left <= 1:
            return left
        room = self._allowance()
        if math.isinf(room):
            return 1
        # one element a step: the next steps score scored - 1, scored - 2, ... masks
        rest = left - 1
        cost_one = rest * (scored - 1) - rest * (rest - 1) / 2
        if cost_one <= room:
            return 1
        if room <= scored:  # not even one more step: take them all from this ranking
            return left
        # s a step: about (left / s - 1) more steps of about (scored - left / 2) masks each
        mean_cands = max(1.0, scored - left / 2)
        steps = max(1.0, room / mean_cands)
        return int(min(left, max(1, math.ceil(left / (steps + 1)))))


class _Unconstrained:
    """``objective`` seen without its channel groups (its layouts, before they are projected)."""

    constraints = None

    def __init__(self, objective):
        self._o = objective

    def __getattr__(self, name):
        return getattr(self._o, name)


def start_options(default: str = "uniform") -> dict[str, Option]:
    """The declared options ``start`` (one of :data:`START_CHOICES`, default ``default``) and
    ``elements`` (an element list; given, it implies ``start = elements``)."""
    return {
        "start": Option(str, default, "start selection: uniform, random, greedy (backward elimination, "
                        "up to about Ne^2/2 evaluations, at most half the budget: several elements a step "
                        f"when one a step does not fit), chirp (the best of {CHIRP_CANDIDATES} random chirped "
                        "layouts: period changing from the centre to the edges) or elements (the list in the "
                        "option elements)",
                        choices=START_CHOICES),
        "elements": Option(str, None, "start elements, e.g. '0 2 4 ...' (k distinct indices; implies "
                           "start=elements)"),
    }


def start_selection(how: str, objective, k: int, rng: np.random.Generator, elements: str | None = None,
                    option: str = "start") -> list[int]:
    """The start selection ``how`` names (see :func:`_start`); on a budgeted objective it is also
    the run's fallback (``objective.fallback``): what the run returns when its budget ends before
    a ``k``-selection is scored (a greedy start that used the whole budget, say)."""
    start = _start(how, objective, k, rng, elements, option)
    if budget_of(objective) is not None:
        objective.fallback(start)
    return start


def _start(how: str, objective, k: int, rng: np.random.Generator, elements: str | None, option: str) -> list[int]:
    """The start selection ``how`` names: ``uniform`` (:func:`uniform_layout`, matrix arrays
    included), ``random``, ``greedy`` (:func:`greedy_selection`, spends evaluations), ``chirp``
    (:func:`chirp_selection`, spends :data:`CHIRP_CANDIDATES` evaluations) or ``elements`` (the
    text of the option ``elements``); ``elements`` given means ``elements`` whatever ``how`` says."""
    n = int(objective.n_elements)
    if elements is not None:
        how = "elements"
    gc = group_constraints(objective)
    if gc is not None and how != "elements":
        if how == "greedy":  # greedy elimination cannot honour the groups: the chirped start instead
            how = "chirp"
        if how == "random":
            return [int(i) for i in np.flatnonzero(gc.random_masks(rng, 1)[0])]
        if how == "uniform":
            layout = _start(how, _Unconstrained(objective), k, rng, None, option)
            return [int(i) for i in np.flatnonzero(layout_projection(objective, layout, gc))]
    if how == "uniform":
        grid, positions = element_layout(objective)
        if 0 < k and grid is None and is_planar(positions):  # a grid with blank rows, an imported layout
            return planar_uniform_layout(positions, k)
        return uniform_layout(n, k, grid) if 0 < k else []
    if how == "random":
        return sorted(int(i) for i in rng.choice(n, k, replace=False))
    if how == "greedy":
        return greedy_selection(objective, k, backward=True, share=GREEDY_START_SHARE)
    if how == "chirp":
        return chirp_selection(objective, k, rng) if 0 < k < n else sorted(range(k))
    if how == "elements":
        if elements is None:
            raise ParameterError(f"option {option} = elements needs the option elements (e.g. -o "
                                 f"swap.elements='0 2 4 ...')")
        try:
            return sorted(parse_elements(elements, n, k, where="option elements"))
        except ValueError as exc:
            raise ParameterError(str(exc)) from None
    raise ParameterError(f"option {option} = {how!r} is not allowed; choose one of {list(START_CHOICES)}")
