"""``swap``: local search over k-subsets by swapping one active and one inactive element."""
from __future__ import annotations

import numpy as np

from arraysel.hookspecs import hookimpl
from arraysel.selector import Option, Selector, finite_or_inf, numpy_rng


class SwapSelector(Selector):
    name = "swap"
    description = "local search: best of a batch of random (active, inactive) swaps, from the uniform layout"
    options = {
        "batch": Option(int, 32, "candidate swaps scored per objective.evaluate call", lo=1),
    }
    deterministic = True

    def batch_size(self, n_elements, k):
        return self.options["batch"]

    def select(self, objective, k, budget, seed, recorder):
        n = int(objective.n_elements)
        rng = numpy_rng(seed)
        current = np.zeros(n, dtype=bool)
        current[[(i * n) // k for i in range(k)]] = True
        if not budget.allowed(1):
            return [int(i) for i in np.flatnonzero(current)]
        best = float(finite_or_inf(objective.evaluate(current[None])["Mean"])[0])
        recorder.report(current, best)
        while 0 < k < n:
            b = budget.allowed(self.options["batch"])
            if b <= 0:
                break
            on, off = np.flatnonzero(current), np.flatnonzero(~current)
            cands = np.repeat(current[None], b, axis=0)
            rows = np.arange(b)
            cands[rows, rng.choice(on, b)] = False
            cands[rows, rng.choice(off, b)] = True
            means = finite_or_inf(objective.evaluate(cands)["Mean"])
            i = int(np.argmin(means))
            if means[i] < best:
                best, current = float(means[i]), cands[i]
                recorder.report(current, best)
        return [int(i) for i in np.flatnonzero(current)]


@hookimpl
def arraysel_register_selectors(register):
    register(SwapSelector)
