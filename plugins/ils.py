"""``ils``: multi-start iterated local search over an elite pool, with path relinking (exact k, batched).

Several starts (the ``start`` selection and ``starts - 1`` random ones) are each improved by swap
descents (first or best improvement, the neighbours scored in one call each) into local optima;
the best distinct ones form an elite pool. Each round then either relinks two elites (a greedy
swap path from one towards the other, whose best intermediate selection is descended) or
perturbs an elite by a number of random swaps that grows while no round finds a new best; a
long run without a new best brings a fresh random start. See
:class:`arraysel.selectors.localsearch.EliteSearch`.
"""
from __future__ import annotations

from arraysel.selectors.contract import Option, Selector, numpy_rng
from arraysel.selectors.hookspecs import hookimpl
from arraysel.selectors.localsearch import FRESH_CHIRPS, FRESH_CHOICES, EliteSearch
from arraysel.selectors.moves import shift_options
from arraysel.selectors.starts import start_options, start_selection


class IteratedLocalSearch(Selector):
    name = "ils"
    description = "multi-start iterated swap local search: elite pool, path relinking, growing perturbations"
    options = {
        **start_options("greedy"),
        "starts": Option(int, 2, "starting selections (the start and random ones), each descended first", lo=1),
        "elite": Option(int, 8, "distinct local optima kept in the elite pool", lo=1),
        "relink": Option(float, 0.3, "probability that a round relinks two elites (else it perturbs one)",
                         lo=0.0, hi=1.0),
        "mode": Option(str, "first", "descent: first (move at the first chunk holding an improvement) or best "
                       "(all k(Ne-k) neighbours a move)", choices=("first", "best")),
        "chunk": Option(int, 64, "neighbours per objective call in first-improvement mode", lo=1),
        "guide": Option(float, 0.5, "first share of each first-mode chunk taken in the order the loss's "
                        "gradient predicts (adapts to where improvements come from; 0: random order)",
                        lo=0.0, hi=1.0),
        "perturb": Option(int, 2, "random swaps of the first perturbation after a new best", lo=1),
        "max_perturb": Option(int, 8, "most random swaps of a perturbation", lo=1),
        "restart_after": Option(int, 40, "rounds in a row without a new best before a fresh random start "
                                "(0: never)", lo=0),
        "fresh": Option(str, "random", "extra starts and restarts: random selections, chirp (the best of "
                        f"{FRESH_CHIRPS} random chirped layouts each, scored in one call), or mixed (chirped "
                        "and random in turn)", choices=FRESH_CHOICES),
        **shift_options(),
    }
    deterministic = False
    scores_neighbourhoods = True

    def select(self, objective, k, seed):
        o = self.options
        rng = numpy_rng(seed)
        start = start_selection(o["start"], objective, k, rng, o["elements"])
        search = EliteSearch(objective, k, rng, starts=o["starts"], elite=o["elite"], relink=o["relink"],
                             mode=o["mode"], chunk=o["chunk"], guide=o["guide"], perturb=o["perturb"],
                             max_perturb=o["max_perturb"], restart_after=o["restart_after"], fresh=o["fresh"],
                             shift=o["shift"], shift_len=o["shift_len"], shift_scan=o["shift_scan"])
        return search.run(start)[0]


@hookimpl
def arraysel_register_selectors(register):
    register(IteratedLocalSearch)
