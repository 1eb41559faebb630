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
"""
from __future__ import annotations

import numpy as np

from arraysel.selectors.contract import Option, Selector, numpy_rng
from arraysel.selectors.hookspecs import hookimpl
from arraysel.selectors.layouts import uniform_layout
from arraysel.selectors.localsearch import random_swaps
from arraysel.selectors.starts import random_subsets


def exact_k_crossover(p1: np.ndarray, p2: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """A child mask with exactly ``p1.sum()`` elements: the common ones plus a random fill
    from the symmetric difference."""
    child = p1 & p2
    need = int(p1.sum()) - int(child.sum())
    if need > 0:
        diff = np.flatnonzero(p1 ^ p2)
        child[rng.choice(diff, need, replace=False)] = True
    return child


class GeneticSelector(Selector):
    name = "genetic"
    description = "genetic algorithm: exact-k crossover, swap mutation, tournament, elitist (mu+lambda)"
    options = {
        "population": Option(int, 32, "selections kept (mu)", lo=2),
        "children": Option(int, 64, "children per generation (lambda), scored in one evaluate call", lo=1),
        "tournament": Option(int, 3, "tournament size of parent selection", lo=1),
        "crossover": Option(float, 0.9, "probability that a child is a crossover (else a copy)", lo=0.0, hi=1.0),
        "mutation": Option(float, 1.0, "mean number of random swaps per child (Poisson)", lo=0.0),
    }
    deterministic = False

    def select(self, objective, k, seed):
        o = self.options
        n = int(objective.n_elements)
        rng = numpy_rng(seed)
        mu = o["population"]
        pop = np.zeros((mu, n), dtype=bool)
        np.put_along_axis(pop, random_subsets(rng, mu, n, k), True, axis=1)
        pop[0] = False
        pop[0, uniform_layout(n, k)] = True
        if k in (0, n):
            return [int(i) for i in np.flatnonzero(pop[0])]
        fit = objective.score(pop)
        while True:
            children = np.zeros((o["children"], n), dtype=bool)
            known = {np.packbits(m).tobytes() for m in pop}
            for c in range(o["children"]):
                i = self._tournament(fit, rng)
                if rng.random() < o["crossover"]:
                    j = self._tournament(fit, rng)
                    child = exact_k_crossover(pop[i], pop[j], rng)
                else:
                    child = pop[i].copy()
                child = random_swaps(child, int(rng.poisson(o["mutation"])), rng)
                key = np.packbits(child).tobytes()
                if key in known:
                    child = random_swaps(child, 1, rng)
                    key = np.packbits(child).tobytes()
                known.add(key)
                children[c] = child
            cfit = objective.score(children)
            allm = np.concatenate([pop, children])
            allf = np.concatenate([fit, cfit])
            order = np.lexsort((np.arange(allf.size), allf))
            keep, seen = [], set()
            for idx in order:
                key = np.packbits(allm[idx]).tobytes()
                if key not in seen:
                    seen.add(key)
                    keep.append(idx)
                if len(keep) == mu:
                    break
            pop, fit = allm[keep], allf[keep]

    def _tournament(self, fit: np.ndarray, rng: np.random.Generator) -> int:
        idx = rng.choice(fit.size, size=min(self.options["tournament"], fit.size), replace=False)
        return int(idx[np.argmin(fit[idx])])


@hookimpl
def arraysel_register_selectors(register):
    register(GeneticSelector)
