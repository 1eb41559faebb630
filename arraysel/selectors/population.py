"""Populations of exact-``k`` selections: what the evolutionary searches share (the ``genetic``
and ``memetic`` selectors), in the framework so that a plugin calls it instead of copying it.

* :data:`POPULATION_OPTIONS`: the options such a selector declares;
* :func:`initial_population`: the uniform layout and random ``k``-selections;
* :func:`exact_k_crossover`: a child with exactly ``k`` elements from two parents;
* :func:`breed`: ``children`` new selections by tournaments, crossover and swap mutation, none
  equal to a member of the population or to an earlier child;
* :func:`survivors`: the ``mu`` best distinct selections of parents and children (elitist);
* :func:`evolve`: the search itself (``genetic``; ``memetic`` with its improvement step);
* :func:`first_population`: a search's initial population, scored in one call;
* :func:`next_generation`: one generation (breed, score the children in one call, survive) under
  the :data:`POPULATION_OPTIONS` of a selector.
"""
from __future__ import annotations

import numpy as np

from arraysel.constraints import group_constraints
from arraysel.selection import mask_key, survivors
from arraysel.selectors.contract import Option
from arraysel.selectors.layouts import uniform_layout
from arraysel.selectors.moves import random_swaps
from arraysel.selectors.starts import chirp_masks, random_subsets

#: a ``chirp`` initial population keeps the best ``population`` of ``CHIRP_POOL x population``
#: random chirped layouts
CHIRP_POOL = 4

__all__ = ["POPULATION_OPTIONS", "CHIRP_POOL", "evolve", "first_population", "next_generation", "initial_population",
           "exact_k_crossover", "tournament", "breed", "survivors", "mask_key"]

#: the declared options of a population search (a selector's ``options`` include them)
POPULATION_OPTIONS = {
    "population": Option(int, 32, "selections kept (mu)", lo=2),
    "children": Option(int, 64, "children per generation (lambda), scored in one evaluate call", lo=1),
    "tournament": Option(int, 3, "tournament size of parent selection", lo=1),
    "crossover": Option(float, 0.9, "probability that a child is a crossover (else a copy)", lo=0.0, hi=1.0),
    "mutation": Option(float, 1.0, "mean number of random swaps per child (Poisson)", lo=0.0),
    "init": Option(str, "random", "initial population: random (the uniform layout and random selections) or "
                   f"chirp (the best of {CHIRP_POOL} x population random chirped layouts)",
                   choices=("random", "chirp")),
}


def initial_population(rng: np.random.Generator, mu: int, n: int, k: int, constraints=None) -> np.ndarray:
    """``(mu, n)`` boolean masks: the uniform layout first, then random ``k``-selections (under
    channel-group ``constraints``: random feasible selections only)."""
    if constraints is not None:
        return constraints.random_masks(rng, mu)
    pop = np.zeros((mu, n), dtype=bool)
    np.put_along_axis(pop, random_subsets(rng, mu, n, k), True, axis=1)
    pop[0] = False
    pop[0, uniform_layout(n, k)] = True
    return pop


def exact_k_crossover(p1: np.ndarray, p2: np.ndarray, rng: np.random.Generator, constraints=None) -> np.ndarray:
    """A child mask with exactly ``p1.sum()`` elements: the common ones plus a random fill
    from the symmetric difference (under channel-group ``constraints`` their
    :meth:`~arraysel.constraints.Constraints.crossover`)."""
    if constraints is not None:
        return constraints.crossover(p1, p2, rng)
    child = p1 & p2
    need = int(p1.sum()) - int(child.sum())
    if need > 0:
        diff = np.flatnonzero(p1 ^ p2)
        child[rng.choice(diff, need, replace=False)] = True
    return child


def tournament(fit: np.ndarray, size: int, rng: np.random.Generator) -> int:
    """Index of the lowest value among ``size`` distinct random members."""
    idx = rng.choice(fit.size, size=min(size, fit.size), replace=False)
    return int(idx[np.argmin(fit[idx])])


def breed(pop: np.ndarray, fit: np.ndarray, children: int, rng: np.random.Generator, *, tournament_size: int = 3,
          crossover: float = 0.9, mutation: float = 1.0, constraints=None) -> np.ndarray:
    """``(children, n)`` child masks: parents by tournaments of ``tournament_size``; with
    probability ``crossover`` an :func:`exact_k_crossover` of two parents, else a copy of one;
    then ``Poisson(mutation)`` random swaps; a child equal to a member or an earlier child gets
    one more swap."""
    out = np.zeros((children, pop.shape[1]), dtype=bool)
    known = {mask_key(m) for m in pop}
    for c in range(children):
        i = tournament(fit, tournament_size, rng)
        if rng.random() < crossover:
            j = tournament(fit, tournament_size, rng)
            child = exact_k_crossover(pop[i], pop[j], rng, constraints)
        else:
            child = pop[i].copy()
        child = random_swaps(child, int(rng.poisson(mutation)), rng, constraints)
        key = mask_key(child)
        if key in known:
            child = random_swaps(child, 1, rng, constraints)
            key = mask_key(child)
        known.add(key)
        out[c] = child
    return out


def next_generation(objective, pop: np.ndarray, fit: np.ndarray, rng: np.random.Generator,
                    options: dict) -> tuple[np.ndarray, np.ndarray]:
    """One generation of a population search with the :data:`POPULATION_OPTIONS` ``options``:
    :func:`breed` ``children`` selections, score them in one ``objective.score`` call (it spends
    budget every generation, and raises :class:`~arraysel.selectors.contract.BudgetExhausted` when
    the budget ends) and keep the :func:`survivors`."""
    children = breed(pop, fit, options["children"], rng, tournament_size=options["tournament"],
                     crossover=options["crossover"], mutation=options["mutation"],
                     constraints=group_constraints(objective))
    cfit = objective.score(children)
    return survivors(np.concatenate([pop, children]), np.concatenate([fit, cfit]), options["population"])


def first_population(objective, k: int, rng: np.random.Generator,
                     options: dict) -> tuple[np.ndarray, np.ndarray | None]:
    """``(population, scores)``: the :func:`initial_population` of ``options["population"]``
    selections of ``k`` of the objective's elements, scored in one call (``init = chirp``: the
    best distinct ``population`` of ``CHIRP_POOL x population`` chirped layouts,
    :func:`~arraysel.selectors.starts.chirp_masks`, scored in one call); the scores are ``None``
    (nothing scored) when ``k`` is 0 or ``Ne``: there is one selection, the population's first."""
    n = int(objective.n_elements)
    mu = options["population"]
    if k in (0, n):
        return initial_population(rng, mu, n, k), None
    if options.get("init", "random") == "chirp":
        pool = chirp_masks(objective, k, rng, CHIRP_POOL * mu)
        pop, fit = survivors(pool, objective.score(pool), mu)
        if pop.shape[0] < mu:  # duplicate layouts (a tiny array): random selections fill the rest
            extra = initial_population(rng, mu - pop.shape[0], n, k, group_constraints(objective))
            pop, fit = np.concatenate([pop, extra]), np.concatenate([fit, objective.score(extra)])
        return pop, fit
    pop = initial_population(rng, mu, n, k, group_constraints(objective))
    return pop, objective.score(pop)


def evolve(objective, k: int, rng: np.random.Generator, options: dict, improve=None) -> list[int]:
    """A population search with the :data:`POPULATION_OPTIONS` ``options``: the
    :func:`first_population`, then :func:`next_generation` after generation, each followed by
    ``improve(pop, scores) -> (pop, scores)`` when given (a memetic step), until the budget ends
    (the objective's :class:`~arraysel.selectors.contract.BudgetExhausted`; the runner returns the
    best selection scored). For ``k`` = 0 or ``Ne`` it returns the one selection there is."""
    pop, fit = first_population(objective, k, rng, options)
    if fit is None:
        return [int(i) for i in np.flatnonzero(pop[0])]
    while True:
        pop, fit = next_generation(objective, pop, fit, rng, options)
        if improve is not None:
            pop, fit = improve(pop, fit)
