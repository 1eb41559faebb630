"""``genetic``: a steady (mu + lambda) genetic algorithm on exact-k selections (batched).

* population: ``population`` selections, random ones plus the uniform layout;
* parents: tournaments of ``tournament`` selections (lowest Mean wins);
* exact-k crossover: the child keeps every element both parents share and
  fills the remaining ``k - |common|`` places with a uniformly random subset
  of the elements only one parent has (so it always has exactly ``k``);
  with probability ``1 - crossover`` the child is a copy of the first parent;
* mutation: ``Poisson(mutation)`` random swaps (one active element out, one
  inactive in); a child equal to a population member gets one more swap;
* survival: the ``population`` best distinct selections of parents and
  children (elitist truncation);
* one ``objective.evaluate`` call per generation scores all ``children``.

The population machinery is the framework's (:mod:`arraysel.selectors.population`).
"""
from __future__ import annotations

from arraysel.selectors.contract import Selector, numpy_rng
from arraysel.selectors.hookspecs import hookimpl
from arraysel.selectors.population import POPULATION_OPTIONS, evolve


class GeneticSelector(Selector):
    name = "genetic"
    description = "genetic algorithm: exact-k crossover, swap mutation, tournament, elitist (mu+lambda)"
    options = dict(POPULATION_OPTIONS)
    deterministic = False

    def select(self, objective, k, seed):
        return evolve(objective, k, numpy_rng(seed), self.options)


@hookimpl
def arraysel_register_selectors(register):
    register(GeneticSelector)
