"""``random-swap``: local search over k-subsets by swapping one active and one inactive element.

A complete third-party plugin: the selector holds only its search. The
objective it receives counts evaluations, stops the run when the budget is
spent (it raises ``BudgetExhausted``, which the runner handles) and records
every scored selection for the trace.
"""
from __future__ import annotations

import numpy as np

from arraysel.constraints import refuse_groups
from arraysel.selectors.hookspecs import hookimpl
from arraysel.selectors.contract import Option, Selector, numpy_rng


class SwapSelector(Selector):
    name = "random-swap"
    description = "local search: best of a batch of random (active, inactive) swaps, from the uniform layout"
    options = {
        "batch": Option(int, 32, "candidate swaps scored per objective.evaluate call", lo=1),
    }
    deterministic = False

    def batch_size(self, n_elements, k):
        return self.options["batch"]

    def select(self, objective, k, seed):
        # forced elements and symmetry are the runner's (this search sees the free elements only);
        # channel groups it does not honour, and says so (docs/constraints.md)
        refuse_groups(objective, self.name)
        n = int(objective.n_elements)
        rng = numpy_rng(seed)
        current = np.zeros(n, dtype=bool)
        current[[(i * n) // k for i in range(k)]] = True
        best = float(objective.score(current[None])[0])
        while 0 < k < n:
            b = self.options["batch"]
            on, off = np.flatnonzero(current), np.flatnonzero(~current)
            cands = np.repeat(current[None], b, axis=0)
            rows = np.arange(b)
            cands[rows, rng.choice(on, b)] = False
            cands[rows, rng.choice(off, b)] = True
            means = objective.score(cands)
            i = int(np.argmin(means))
            if means[i] < best:
                best, current = float(means[i]), cands[i]
        return [int(i) for i in np.flatnonzero(current)]


@hookimpl
def arraysel_register_selectors(register):
    register(SwapSelector)
