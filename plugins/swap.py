"""``swap``: iterated local search by one-in-one-out element swaps (exact k, batched).

From a start selection (``chirp``, the default: the best of 256 chirped layouts; ``uniform``,
``random``, the ``greedy`` backward elimination, or a given element list) the search improves
the selection by swapping one active and one inactive element, with first improvement (chunks
of ``chunk`` neighbours per call, a share ``guide`` of each in the order a model of the loss
predicts, the rest in a random order) or best improvement (all ``k (Ne - k)`` neighbours per
step, scored in one call). At a local optimum it perturbs the best selection by ``perturb``
random swaps (growing by one swap after each perturbation without a new best, up to
``max_perturb``) and descends again (iterated local search), and after ``restart_after``
non-improving perturbations it restarts from a fresh selection (``fresh``: chirped and random
in turn by default), until the budget is spent. With ``race`` above 1 (16 by default) the first
descent is a race of descents from the start and ``race - 1`` fresh selections (successive
halving; by default its turns share a third of the budget); the search goes on from the winner.
With ``shift`` above 0 (6 by default) a descent that no swap improves tries segment shifts
(runs of consecutive elements rotated by up to ``shift`` places) before it ends. With the
quadratic model (the default up to 256 elements) the guided share of each chunk is ranked by
the loss's gradient and Hessian, which puts the best swaps first, so a small ``scan`` (0.125 by
default) ends a descent cheaply. The defaults are the configuration that measured best at 20 s
and 120 s a run on the built-in scenes, :data:`arraysel.selectors.swapsettings.SWAP`
(``docs/selectors.md`` lists the options in one table). See
:mod:`arraysel.selectors.localsearch` for the algorithm.
"""
from __future__ import annotations

from arraysel.selectors.contract import Selector, numpy_rng
from arraysel.selectors.hookspecs import hookimpl
from arraysel.selectors.localsearch import SwapSearch
from arraysel.selectors.starts import start_options, start_selection
from arraysel.selectors.swapsettings import SWAP, settings_from, swap_options


class SwapSelector(Selector):
    name = "swap"
    description = "iterated swap local search (first/best improvement, perturbation, restarts) from any start"
    options = {**start_options("chirp"), **swap_options(SWAP)}
    deterministic = False
    scores_neighbourhoods = True

    def search(self, objective, k: int, rng) -> SwapSearch:
        """The :class:`SwapSearch` this selector runs, with its options, on ``objective``."""
        return SwapSearch(objective, k, rng, settings_from(SWAP, self.options))

    def select(self, objective, k, seed):
        o = self.options
        rng = numpy_rng(seed)
        start = start_selection(o["start"], objective, k, rng, o["elements"])
        search = self.search(objective, k, rng)
        return search.run(start)[0]


@hookimpl
def arraysel_register_selectors(register):
    register(SwapSelector)
