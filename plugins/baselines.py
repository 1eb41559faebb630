"""Baseline selectors named by the paper (``docs/paper-scene.md``): ``uniform`` and ``random``."""
from __future__ import annotations

import time

import numpy as np

from arraysel.constraints import group_constraints
from arraysel.objective.contract import element_layout
from arraysel.selectors.hookspecs import hookimpl
from arraysel.selectors.layouts import is_planar, planar_uniform_layout, uniform_layout
from arraysel.selectors.contract import Option, Selector, numpy_rng
from arraysel.selectors.starts import layout_projection, random_subsets


class UniformSelector(Selector):
    """k evenly spaced elements (:func:`arraysel.selectors.layouts.uniform_layout`).

    On a 1-D array ``floor(i Ne / k)``, i = 0..k-1 (every second one for k = Ne/2); on a matrix
    array (``objective.element_grid``) the same rule in both directions on a sub-grid of about
    ``k`` elements, made exactly ``k`` by the fewest documented changes; on a matrix array known
    by its element centres only (a grid with blank rows, an imported layout) the same on the grid
    the centres lie on, or the farthest-point spread of an irregular layout
    (:func:`arraysel.selectors.layouts.planar_uniform_layout`).
    """

    name = "uniform"
    description = "k evenly spaced elements (every second element for k = Ne/2; both directions on a matrix)"
    options = {}
    deterministic = True
    baseline = True

    def select(self, objective, k, seed):
        n = int(objective.n_elements)
        grid, positions = element_layout(objective)
        if grid is None and is_planar(positions):  # a grid with blank rows, an imported layout
            chosen = planar_uniform_layout(positions, k)
        else:
            chosen = uniform_layout(n, k, grid)
        mask = layout_projection(objective, chosen)  # channel groups: the documented projection
        objective.evaluate(mask[None])
        return [int(i) for i in np.flatnonzero(mask)]


class RandomSelector(Selector):
    """Best of N uniformly random k-subsets, scored in chunks by ``objective.evaluate``.

    N is bounded by the budget; ``n = 1`` is "a random mask chosen once".
    """

    name = "random"
    description = "best of n random k-subsets (n = 1: a random mask chosen once)"
    options = {
        "n": Option(int, 500_000, "number of random subsets to try (bounded by the budget)", lo=1),
        "chunk": Option(int, 1024, "most subsets per objective.evaluate call (smaller when masks "
                        "are slow, so a time budget is not overrun by much)", lo=1),
    }
    deterministic = False
    baseline = True

    def planned_evaluations(self, n_elements, k):
        return self.options["n"]

    def select(self, objective, k, seed):
        n = int(objective.n_elements)
        rng = numpy_rng(seed)
        total, chunk = self.options["n"], self.options["chunk"]
        budget = objective.budget
        gc = group_constraints(objective)  # channel groups: uniform random feasible selections
        best, best_mean = None, np.inf
        first = None
        drawn = 0
        # the chunk grows from a few masks to `chunk` so that one call lasts
        # about `target` seconds; the subsets drawn do not depend on chunking
        target = 2.0 if budget.seconds is None else min(2.0, max(0.05, 0.02 * budget.seconds))
        size = 1  # the first call is one mask, so a slow objective overruns by one mask at most
        while drawn < total:
            b = int(min(size, total - drawn, objective.remaining()))
            if b <= 0:
                break
            subsets = random_subsets(rng, b, n, k) if gc is None else \
                np.nonzero(gc.random_masks(rng, b))[1].reshape(b, k)
            t0 = time.perf_counter()
            if first is None:
                first = subsets[0]
            masks = np.zeros((b, n), dtype=bool)
            np.put_along_axis(masks, subsets, True, axis=1)
            means = objective.score(masks)
            drawn += b
            per_mask = max((time.perf_counter() - t0) / b, 1e-9)
            size = int(min(chunk, 4 * b, max(1, target / per_mask)))
            i = int(np.argmin(means))
            if means[i] < best_mean:
                best, best_mean = subsets[i], float(means[i])
        if best is None:  # no finite score (or no budget): one random subset
            best = first if first is not None else (random_subsets(rng, 1, n, k)[0] if gc is None else
                                                    np.flatnonzero(gc.random_masks(rng, 1)[0]))
        return [int(i) for i in best]


@hookimpl
def arraysel_register_selectors(register):
    register(UniformSelector)
    register(RandomSelector)
