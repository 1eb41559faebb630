"""``memetic``: a genetic algorithm whose best selections are improved by swap descents (exact k, batched).

Each generation breeds ``children`` selections from the population (tournaments, exact-k
crossover, swap mutation: :mod:`arraysel.selectors.population`, as ``genetic`` does) and scores
them in one call; the ``population`` best distinct selections survive. Then the best survivor
not yet improved is improved by a first-improvement swap descent
(:meth:`arraysel.selectors.localsearch.SwapSearch.descend`: neighbours scored in chunks of
``chunk``, a share of each chunk in the order the loss's gradient predicts, ``guide``), which
declares a local optimum after ``scan`` x its neighbourhood without improvement; the improved
selection replaces it. Crossover spreads what the descents found through the population; the
descents turn the population's best into local optima.
"""
from __future__ import annotations

import numpy as np

from arraysel.selectors.contract import Option, Selector, numpy_rng
from arraysel.selectors.hookspecs import hookimpl
from arraysel.selectors.localsearch import SwapSearch
from arraysel.selectors.population import POPULATION_OPTIONS, evolve, mask_key, survivors


class MemeticSelector(Selector):
    name = "memetic"
    description = "genetic algorithm whose best selections are improved by gradient-guided swap descents"
    options = {
        **POPULATION_OPTIONS,
        "chunk": Option(int, 64, "neighbours per objective call of a descent", lo=1),
        "scan": Option(float, 0.1, "fraction of a neighbourhood scored without improvement before a descent "
                       "stops (1: to a strict local optimum)", lo=0.001, hi=1.0),
        "guide": Option(float, 0.5, "first share of each descent chunk taken in the order the loss's gradient "
                        "predicts (0: random order)", lo=0.0, hi=1.0),
    }
    deterministic = False
    scores_neighbourhoods = True

    def select(self, objective, k, seed):
        o = self.options
        rng = numpy_rng(seed)
        search = SwapSearch(objective, k, rng, chunk=o["chunk"], scan=o["scan"], guide=o["guide"])
        improved: set[bytes] = set()

        def improve(pop, fit):
            """The best survivor not improved yet, descended; the result replaces it."""
            for i in range(pop.shape[0]):
                key = mask_key(pop[i])
                if key in improved or not np.isfinite(fit[i]):
                    continue
                mask, value = search.descend(pop[i], float(fit[i]))
                improved.update((key, mask_key(mask)))
                return survivors(np.concatenate([mask[None], pop]), np.concatenate([[value], fit]), o["population"])
            return pop, fit

        return evolve(objective, k, rng, o, improve)


@hookimpl
def arraysel_register_selectors(register):
    register(MemeticSelector)
