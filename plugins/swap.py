"""``swap``: iterated local search by one-in-one-out element swaps (exact k, batched).

From a start selection (``uniform``, ``random``, the ``greedy`` backward
elimination, or a given element list) the search improves the selection by
swapping one active and one inactive element, with first improvement (random
neighbour order, ``chunk`` neighbours per ``objective.evaluate`` call) or best
improvement (all ``k (Ne - k)`` neighbours per step). At a local optimum it
perturbs the best selection by ``perturb`` random swaps and descends again
(iterated local search), and after ``restart_after`` non-improving
perturbations it restarts from a random selection, until the budget is spent.
See :mod:`arraysel.selectors.localsearch` for the algorithm.
"""
from __future__ import annotations

import re

import numpy as np

from arraysel.errors import ParameterError
from arraysel.selectors.hookspecs import hookimpl
from arraysel.selectors.localsearch import SwapSearch
from arraysel.selectors.contract import BudgetExhausted, Option, Selector, numpy_rng

START_CHOICES = ("uniform", "random", "greedy", "elements")


def parse_elements(option: str, text: str, n: int, k: int) -> list[int]:
    """Element indices from ``"0 2 4"`` / ``"0,2,4"``; ParameterError naming ``option`` when invalid."""
    parts = [p for p in re.split(r"[\s,;]+", text.strip()) if p]
    try:
        idx = [int(p) for p in parts]
    except ValueError:
        raise ParameterError(f"option {option} = {text!r}: expected element indices separated by spaces "
                             f"or commas") from None
    bad = [i for i in idx if not 0 <= i < n]
    if bad:
        raise ParameterError(f"option {option}: indices {bad[:5]} are outside [0, {n - 1}]")
    if len(set(idx)) != len(idx) or len(idx) != k:
        raise ParameterError(f"option {option} must list k = {k} distinct element indices, got {len(idx)} "
                             f"({len(set(idx))} distinct)")
    return sorted(idx)


def start_selection(how: str, objective, k: int, rng: np.random.Generator, elements: str | None = None,
                    option: str = "start") -> list[int]:
    """A start selection: ``uniform``, ``random``, ``greedy`` (spends evaluations) or ``elements``."""
    n = int(objective.n_elements)
    if how == "uniform":
        return [(i * n) // k for i in range(k)]
    if how == "random":
        return sorted(int(i) for i in rng.choice(n, k, replace=False))
    if how == "greedy":
        from .greedy import greedy_selection
        return greedy_selection(objective, k, backward=True)
    if how == "elements":
        if elements is None:
            raise ParameterError(f"option {option} = elements needs the option elements (e.g. -o "
                                 f"swap.elements='0 2 4 ...')")
        return parse_elements("elements", elements, n, k)
    raise ParameterError(f"option {option} = {how!r} is not allowed; choose one of {list(START_CHOICES)}")


class SwapSelector(Selector):
    name = "swap"
    description = "iterated swap local search (first/best improvement, perturbation, restarts) from any start"
    options = {
        "start": Option(str, "greedy", "start selection: uniform, random, greedy (backward elimination, "
                        "spends ~Ne^2/2 evaluations) or elements (the list in the option elements)",
                        choices=START_CHOICES),
        "elements": Option(str, None, "start elements, e.g. '0 2 4 ...' (k distinct indices; implies "
                           "start=elements)"),
        "mode": Option(str, "first", "first: move at the first chunk holding an improvement (random "
                       "order); best: score all k(Ne-k) neighbours per move", choices=("first", "best")),
        "chunk": Option(int, 64, "neighbours per objective.evaluate call in first-improvement mode", lo=1),
        "scan": Option(float, 1.0, "fraction of the neighbourhood scored without improvement before a "
                       "local optimum is declared (first mode)", lo=0.01, hi=1.0),
        "perturb": Option(int, 2, "random swaps of an iterated-local-search perturbation (0: restart "
                          "from a random selection at each local optimum)", lo=0),
        "restart_after": Option(int, 30, "perturbations in a row without a new best before a restart from "
                                "a random selection (0: never restart)", lo=0),
    }
    deterministic = False

    def batch_size(self, n_elements, k):
        return self.options["chunk"] if self.options["mode"] == "first" else k * (n_elements - k)

    def select(self, objective, k, seed):
        o = self.options
        rng = numpy_rng(seed)
        how = "elements" if o["elements"] is not None else o["start"]
        start = start_selection(how, objective, k, rng, o["elements"])
        search = SwapSearch(objective, k, rng, mode=o["mode"], chunk=o["chunk"], scan=o["scan"],
                            perturb=o["perturb"], restart_after=o["restart_after"])
        try:
            best, _ = search.run(start)
        except BudgetExhausted:
            best = objective.best
        return best if best is not None else start


@hookimpl
def arraysel_register_selectors(register):
    register(SwapSelector)
