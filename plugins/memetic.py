"""``memetic``: a genetic algorithm whose best selections are improved by swap descents (exact k, batched).

Each generation breeds ``children`` selections from the population (tournaments, exact-k
crossover, swap mutation: :mod:`arraysel.selectors.population`, as ``genetic`` does) and scores
them in one call; the ``population`` best distinct selections survive. Then the best survivor
not yet improved is improved by a first-improvement swap descent
(:meth:`arraysel.selectors.descent.SwapDescent.descend`, with ``swap``'s descent settings,
:data:`arraysel.selectors.swapsettings.MEMETIC`: neighbours scored in chunks of ``chunk``, a
share of each chunk in the order the model of the loss predicts, ``guide``), which declares a
local optimum after ``scan`` x its neighbourhood without improvement; the improved selection
replaces it. Crossover spreads what the descents found through the population; the
descents turn the population's best into local optima.
"""
from __future__ import annotations

import numpy as np

from arraysel.selectors.contract import Selector, numpy_rng
from arraysel.selectors.hookspecs import hookimpl
from arraysel.selectors.localsearch import SwapSearch
from arraysel.selectors.population import POPULATION_OPTIONS, evolve, mask_key, survivors
from arraysel.selectors.swapsettings import MEMETIC, settings_from, swap_options


class MemeticSelector(Selector):
    name = "memetic"
    description = "genetic algorithm whose best selections are improved by gradient-guided swap descents"
    options = {**POPULATION_OPTIONS, **swap_options(MEMETIC, ("chunk", "scan", "guide"))}
    deterministic = False
    scores_neighbourhoods = True

    def select(self, objective, k, seed):
        o = self.options
        rng = numpy_rng(seed)
        search = SwapSearch(objective, k, rng, settings_from(MEMETIC, o))
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
