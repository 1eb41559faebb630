"""``greedy``: backward elimination from the full array, or forward selection.

Backward: start from all ``Ne`` elements; at each step score every set with
one element removed (one batched ``objective.evaluate`` call) and drop the
element whose removal gives the lowest ``Mean``; stop at ``k`` elements.
Forward: start empty and add the element giving the lowest ``Mean``.
Ties go to the lower index; NaN scores rank last. When the budget runs out
before ``k`` is reached, the remaining steps follow the ranking of the last
scored batch (or an evenly spaced choice when none was scored).
"""
from __future__ import annotations

import numpy as np

from arraysel.selectors.hookspecs import hookimpl
from arraysel.selectors.contract import BudgetExhausted, Option, Selector


def _evenly(items: list[int], m: int) -> list[int]:
    """``m`` evenly spaced entries of ``items``."""
    return [items[(i * len(items)) // m] for i in range(m)] if m else []


class GreedySelector(Selector):
    name = "greedy"
    description = "greedy backward elimination from the full array (or forward selection)"
    options = {
        "direction": Option(str, "backward", "backward: remove from the full array; forward: add to an "
                            "empty one", choices=("backward", "forward")),
    }
    deterministic = True

    def batch_size(self, n_elements, k):
        return n_elements

    def select(self, objective, k, seed):
        return greedy_selection(objective, k, backward=self.options["direction"] == "backward")


def greedy_selection(objective, k: int, backward: bool = True) -> list[int]:
    """Greedy backward elimination (or forward selection) on a budgeted objective; when the
    budget ends first, the remaining steps follow the last ranking (see the module docstring)."""
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
            best = ranking[0]
            if backward:
                current.remove(best)
            else:
                current.append(best)
    except BudgetExhausted:
        pass
    if len(current) != k:  # budget ran out: finish without scoring
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


@hookimpl
def arraysel_register_selectors(register):
    register(GreedySelector)
