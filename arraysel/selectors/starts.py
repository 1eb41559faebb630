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

import numpy as np

from arraysel.errors import ParameterError
from arraysel.io.masks import parse_elements
from arraysel.objective.contract import element_layout
from arraysel.selectors.contract import BudgetExhausted, Option
from arraysel.selectors.layouts import uniform_layout

__all__ = ["START_CHOICES", "random_subsets", "random_mask", "greedy_selection", "start_selection",
           "start_options"]

#: the start selections of :func:`start_selection`
START_CHOICES = ("uniform", "random", "greedy", "elements")


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


def _evenly(items: list[int], m: int) -> list[int]:
    """``m`` evenly spaced entries of ``items``."""
    return [items[(i * len(items)) // m] for i in range(m)] if m else []


def greedy_selection(objective, k: int, backward: bool = True) -> list[int]:
    """Greedy backward elimination (or forward selection) on a budgeted objective.

    Backward: from all ``Ne`` elements, score every set with one element removed (one
    ``objective.score`` call) and drop the element whose removal gives the lowest ``Mean``, down to
    ``k`` elements; forward: from none, add the element giving the lowest ``Mean``. Ties go to the
    lower index; NaN scores rank last. When the budget ends before ``k`` is reached, the remaining
    steps follow the ranking of the last scored batch (or an evenly spaced choice when none was
    scored), so a selection is returned either way.
    """
    n = int(objective.n_elements)
    current = list(range(n)) if backward else []
    ranking: list[int] | None = None  # candidates of the last batch, best first
    try:
        while len(current) != k:
            cands = current if backward else [i for i in range(n) if i not in current]
            if objective.remaining() < len(cands):
                break
            masks = np.zeros((len(cands), n), dtype=bool)
            masks[:, current] = True
            for r, c in enumerate(cands):
                masks[r, c] = not backward
            means = objective.score(masks)
            order = np.lexsort((np.arange(len(cands)), means))
            ranking = [cands[i] for i in order]
            if backward:
                current.remove(ranking[0])
            else:
                current.append(ranking[0])
    except BudgetExhausted:  # a start must exist even then: finish from the last ranking below
        pass
    if len(current) != k:
        need = abs(len(current) - k)
        rest = current if backward else [i for i in range(n) if i not in current]
        pool = [c for c in (ranking or []) if c in rest]
        for c in _evenly(rest, need) + rest:
            if c not in pool:
                pool.append(c)
        if backward:
            drop = set(pool[:need])
            current = [c for c in current if c not in drop]
        else:
            current = current + pool[:need]
    return sorted(current)


def start_options(default: str = "uniform") -> dict[str, Option]:
    """The declared options ``start`` (one of :data:`START_CHOICES`, default ``default``) and
    ``elements`` (an element list; given, it implies ``start = elements``)."""
    return {
        "start": Option(str, default, "start selection: uniform, random, greedy (backward elimination, "
                        "spends about Ne^2/2 evaluations) or elements (the list in the option elements)",
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
    note = getattr(type(objective), "fallback", None)
    if note is not None:
        objective.fallback(start)
    return start


def _start(how: str, objective, k: int, rng: np.random.Generator, elements: str | None, option: str) -> list[int]:
    """The start selection ``how`` names: ``uniform`` (:func:`uniform_layout`, matrix arrays
    included), ``random``, ``greedy`` (:func:`greedy_selection`, spends evaluations) or
    ``elements`` (the text of the option ``elements``); ``elements`` given means ``elements``
    whatever ``how`` says."""
    n = int(objective.n_elements)
    if elements is not None:
        how = "elements"
    if how == "uniform":
        grid, _ = element_layout(objective)
        return uniform_layout(n, k, grid) if 0 < k else []
    if how == "random":
        return sorted(int(i) for i in rng.choice(n, k, replace=False))
    if how == "greedy":
        return greedy_selection(objective, k, backward=True)
    if how == "elements":
        if elements is None:
            raise ParameterError(f"option {option} = elements needs the option elements (e.g. -o "
                                 f"swap.elements='0 2 4 ...')")
        try:
            return sorted(parse_elements(elements, n, k, where="option elements"))
        except ValueError as exc:
            raise ParameterError(str(exc)) from None
    raise ParameterError(f"option {option} = {how!r} is not allowed; choose one of {list(START_CHOICES)}")
