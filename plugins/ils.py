"""``ils``: multi-start iterated local search over an elite pool, with path relinking (exact k, batched).

Several starts (the ``start`` selection and ``starts - 1`` random ones) are each improved by swap
descents (first or best improvement, the neighbours scored in one call each) into local optima;
the best distinct ones form an elite pool. Each round then either relinks two elites (a greedy
swap path from one towards the other, whose best intermediate selection is descended) or
perturbs an elite by a number of random swaps that grows while no round finds a new best; a
long run without a new best brings a fresh random start. The descents are ``swap``'s (the
settings :data:`arraysel.selectors.swapsettings.ILS`). See
:class:`arraysel.selectors.elite.EliteSearch`.
"""
from __future__ import annotations

from arraysel.selectors.contract import Option, Selector, numpy_rng
from arraysel.selectors.elite import ELITE, RELINK, STARTS, EliteSearch
from arraysel.selectors.hookspecs import hookimpl
from arraysel.selectors.starts import start_options, start_selection
from arraysel.selectors.swapsettings import ILS, settings_from, swap_options

#: the settings of the swap engine ils declares as options (the others are the ILS preset's)
ILS_OPTIONS = ("mode", "chunk", "guide", "scan", "perturb", "max_perturb", "restart_after", "fresh", "shift",
               "shift_len", "shift_scan", "model")


class IteratedLocalSearch(Selector):
    name = "ils"
    description = "multi-start iterated swap local search: elite pool, path relinking, growing perturbations"
    options = {
        **start_options("greedy"),
        "starts": Option(int, STARTS, "starting selections (the start and random ones), each descended first", lo=1),
        "elite": Option(int, ELITE, "distinct local optima kept in the elite pool", lo=1),
        "relink": Option(float, RELINK, "probability that a round relinks two elites (else it perturbs one)",
                         lo=0.0, hi=1.0),
        **swap_options(ILS, ILS_OPTIONS),
    }
    deterministic = False
    scores_neighbourhoods = True

    def select(self, objective, k, seed):
        o = self.options
        rng = numpy_rng(seed)
        start = start_selection(o["start"], objective, k, rng, o["elements"])
        search = EliteSearch(objective, k, rng, settings_from(ILS, o), starts=o["starts"], elite=o["elite"],
                             relink=o["relink"])
        return search.run(start)[0]


@hookimpl
def arraysel_register_selectors(register):
    register(IteratedLocalSearch)
