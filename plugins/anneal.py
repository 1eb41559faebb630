"""``anneal``: simulated annealing over one-in-one-out swaps (exact k, batched).

Schedule (geometric in the used budget fraction):

    T(f) = T0 * ratio ** f,    f = objective.budget.fraction() in [0, 1]

so the temperature falls from ``T0`` to ``T0 * ratio`` exactly as the run's
budget (time or evaluations, whichever is used faster) runs out; under a
budget without limits ``f = evaluations / horizon``. ``T0`` (option ``t0``,
default automatic) is the temperature at which the median uphill move among
32 random swaps of the start selection is accepted with probability 1/2:
``T0 = median(delta > 0) / ln 2``.

Batched Metropolis: each step scores ``b`` random swaps of the current
selection in one ``objective.evaluate`` call and walks through them in their
random order; the first one accepted (``u < exp(-delta / T)``, downhill moves
always) becomes the current selection and the rest of the batch is dropped.
This is exactly sequential simulated annealing that proposes the same swaps
one by one (the proposals before the accepted one were rejected), at the cost
of the dropped tail. ``b`` adapts to the acceptance rate (about two expected
acceptances' worth, between ``min_batch`` and ``batch``), so little is dropped
while the temperature is high and calls stay large when it is low.
"""
from __future__ import annotations

import math

import numpy as np

from arraysel.constraints import group_constraints
from arraysel.selectors.contract import Option, Selector, numpy_rng
from arraysel.selectors.hookspecs import hookimpl
from arraysel.selectors.moves import random_swap_pairs
from arraysel.selectors.starts import start_options, start_selection


class AnnealSelector(Selector):
    name = "anneal"
    description = "simulated annealing over element swaps, geometric temperature over the budget, batched Metropolis"
    options = {
        **start_options("uniform"),
        "t0": Option(float, None, "initial temperature (auto: the median uphill swap is accepted with "
                     "probability 1/2); 0: accept only moves that do not worsen", lo=0.0),
        "ratio": Option(float, 1e-3, "final / initial temperature", lo=1e-12, hi=1.0),
        "batch": Option(int, 128, "most swaps scored per objective call", lo=1),
        "min_batch": Option(int, 16, "fewest swaps scored per call", lo=1),
        "horizon": Option(int, 200_000, "evaluations the schedule spans when the budget has no limit", lo=1),
    }
    deterministic = False
    scores_neighbourhoods = True

    def select(self, objective, k, seed):
        o = self.options
        n = int(objective.n_elements)
        rng = numpy_rng(seed)
        start = start_selection(o["start"], objective, k, rng, o["elements"])
        gc = group_constraints(objective)  # swaps stay inside the channel groups
        if k in (0, n):
            return start
        budget = objective.budget
        cur = np.zeros(n, dtype=bool)
        cur[start] = True
        f_cur = float(objective.score(cur[None])[0])
        t0 = o["t0"]
        if t0 is None:
            a, b = random_swap_pairs(cur, 32, rng, gc)
            with np.errstate(invalid="ignore"):
                d = objective.score_swaps(cur, a, b) - f_cur
            up = d[np.isfinite(d) & (d > 0)]
            t0 = float(np.median(up)) / math.log(2) if up.size else 1e-3 * max(abs(f_cur), 1e-12)
            if not math.isfinite(t0) or t0 <= 0:
                t0 = 1e-3
        used0 = objective.evaluations
        accept_rate = 0.5
        lo, hi = min(o["min_batch"], o["batch"]), o["batch"]
        while True:
            frac = budget.fraction() if not budget.unlimited else \
                min(1.0, (objective.evaluations - used0) / o["horizon"])
            temp = t0 * o["ratio"] ** frac
            b = int(np.clip(math.ceil(2.0 / max(accept_rate, 1e-3)), lo, hi))
            a, bb = random_swap_pairs(cur, b, rng, gc)
            values = objective.score_swaps(cur, a, bb)
            with np.errstate(over="ignore", invalid="ignore"):
                delta = values - f_cur
                prob = np.where(delta <= 0, 1.0, np.exp(-np.maximum(delta, 0) / temp) if temp > 0 else 0.0)
            prob = np.where(np.isfinite(values), prob, 0.0)
            ok = np.flatnonzero(rng.random(a.size) < prob)
            seen = a.size if ok.size == 0 else int(ok[0]) + 1
            accept_rate = 0.8 * accept_rate + 0.2 * (ok.size > 0) / seen
            if ok.size:
                cur = cur.copy()
                cur[a[ok[0]]], cur[bb[ok[0]]] = False, True
                f_cur = float(values[ok[0]])
            if budget.unlimited and frac >= 1.0:
                return objective.best if objective.best is not None else start


@hookimpl
def arraysel_register_selectors(register):
    register(AnnealSelector)
