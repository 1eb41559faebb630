"""``lns``: large-neighbourhood search: windows of elements re-solved on the quadratic model (exact k, batched).

The swap engine (``swap``'s race, descents, perturbations and restarts; the settings
:data:`arraysel.selectors.window.LNS`) whose descents, at each local optimum of swaps and shifts,
free a window of ``width`` elements near one random centre or two (``window``) and re-solve it:
every placement of the window's active elements is ranked by the quadratic model of the loss
(exact on the model, by enumeration; at most ``cap`` placements, a wider window is narrowed), the
``verify`` best predicted are scored exactly in one call, and the best is taken when it improves,
followed by a new swap descent. ``windows`` windows in a row without improvement end the
descent. Channel groups are kept: a placement that leaves them is never scored. See
:class:`arraysel.selectors.window.WindowSearch`.
"""
from __future__ import annotations

from arraysel.selectors.contract import Selector, numpy_rng
from arraysel.selectors.hookspecs import hookimpl
from arraysel.selectors.starts import start_options, start_selection
from arraysel.selectors.swapsettings import settings_from, swap_options
from arraysel.selectors.window import LNS, WindowSearch, window_options

#: the window options (the rest are swap-engine settings or the start's)
WINDOW_OPTIONS = ("width", "verify", "windows", "window", "kick", "radius", "cap")


class LargeNeighbourhoodSearch(Selector):
    name = "lns"
    description = "large-neighbourhood search: windows of elements re-solved on the quadratic model, verified exactly"
    options = {**start_options("chirp"), **window_options(), **swap_options(LNS)}
    deterministic = False
    scores_neighbourhoods = True

    def select(self, objective, k, seed):
        o, rng = self.options, numpy_rng(seed)
        search = WindowSearch(objective, k, rng, settings_from(LNS, o), **{n: o[n] for n in WINDOW_OPTIONS})
        return search.run(start_selection(o["start"], objective, k, rng, o["elements"]))[0]


@hookimpl
def arraysel_register_selectors(register):
    register(LargeNeighbourhoodSearch)
