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
and 120 s a run on the built-in scenes (``docs/selectors.md``, "The defaults of swap"). See
:mod:`arraysel.selectors.localsearch` for the algorithm.
"""
from __future__ import annotations

from arraysel.selectors.contract import Option, Selector, numpy_rng
from arraysel.selectors.hookspecs import hookimpl
from arraysel.selectors.localsearch import (FRESH_CHIRPS, FRESH_CHOICES, RACE_CHIRP_SHARE, RACE_QUOTA, RACE_SHARE,
                                            SwapSearch)
from arraysel.selectors.lossmodel import model_options
from arraysel.selectors.moves import shift_options
from arraysel.selectors.starts import CHIRP_CANDIDATES, start_options, start_selection


class SwapSelector(Selector):
    name = "swap"
    description = "iterated swap local search (first/best improvement, perturbation, restarts) from any start"
    options = {
        **start_options("chirp"),
        "mode": Option(str, "first", "first: move at the first chunk holding an improvement (random "
                       "order); best: score all k(Ne-k) neighbours per move", choices=("first", "best")),
        "chunk": Option(int, 64, "neighbours per objective call in first-improvement mode", lo=1),
        "lead": Option(int, 0, "first mode: neighbours in the first chunk a descent scores from each selection, "
                       "each next chunk twice as many up to chunk (cheap steps while most chunks hold an "
                       "improving swap; 0: chunk from the first)", lo=0),
        "guide": Option(float, 0.875, "first share of each first-mode chunk taken in the order the loss's "
                        "gradient predicts (adapts to where improvements come from; 0: random order)",
                        lo=0.0, hi=1.0),
        "scan": Option(float, 0.125, "fraction of the neighbourhood scored without improvement before a "
                       "local optimum is declared (first mode)", lo=0.01, hi=1.0),
        "perturb": Option(int, 2, "random swaps of an iterated-local-search perturbation (0: restart "
                          "from a fresh selection, see fresh, at each local optimum)", lo=0),
        "max_perturb": Option(int, 2, "most random swaps of a perturbation: the strength grows from perturb by "
                              "one after each perturbation without a new best (variable strength; perturb "
                              "or less: fixed)", lo=0),
        "restart_after": Option(int, 30, "perturbations in a row without a new best before a restart from "
                                "a fresh selection, see fresh (0: never restart)", lo=0),
        "fresh": Option(str, "mixed", "restarts and the extra starts of a race: random selections, chirp "
                        f"(the best of {FRESH_CHIRPS} random chirped layouts each, scored in one call; a race's: "
                        "the best distinct of one call), or mixed (chirped and random in turn; a race: half "
                        "of its extra starts chirped, rounded up, the rest random)", choices=FRESH_CHOICES),
        "race": Option(int, 16, "first descents raced by successive halving: the one from start and race - 1 "
                       "from fresh selections, the better half going on after each turn (1: no race)", lo=1),
        "race_quota": Option(int, None, "selections each raced descent scores in the first turn (doubled "
                             f"each turn); auto: the turns share {RACE_SHARE:.3g} of the budget, each an equal "
                             f"part split among its descents ({RACE_QUOTA} without a limited budget)", lo=1),
        "race_chirps": Option(int, None, "chirped layouts scored for each chirped extra start of "
                              "a race (fresh = chirp or mixed: the best distinct of race_chirps x their number, "
                              "in one call; fewer leave more of a short budget to the descents); auto: as many "
                              f"as {RACE_CHIRP_SHARE:.3g} of the budget allows, at most {CHIRP_CANDIDATES}",
                              lo=1),
        **shift_options(shift=6, shift_scan=512),
        "compound": Option(int, 0, "first mode: a chunk whose best swap improves takes up to compound of its "
                           "improving swaps on distinct elements together, best first, when that scores better "
                           "(the prefixes scored in one call; 0 or 1: one swap a step)", lo=0),
        "pairs": Option(int, 0, "two-swaps (two elements off, two on) scored at a local optimum of swaps and "
                        "shifts, the ones the quadratic model predicts best, in that order (0: none)", lo=0),
        **model_options(),
    }
    deterministic = False
    scores_neighbourhoods = True

    def search(self, objective, k: int, rng) -> SwapSearch:
        """The :class:`SwapSearch` this selector runs, with its options, on ``objective``."""
        o = self.options
        return SwapSearch(objective, k, rng, mode=o["mode"], chunk=o["chunk"], guide=o["guide"], scan=o["scan"],
                          perturb=o["perturb"], max_perturb=max(o["perturb"], o["max_perturb"]),
                          restart_after=o["restart_after"], fresh=o["fresh"],
                          race=o["race"], race_quota=o["race_quota"], race_chirps=o["race_chirps"],
                          shift=o["shift"],
                          shift_len=o["shift_len"], shift_scan=o["shift_scan"], model=o["model"],
                          refresh=o["refresh"], gradient=o["gradient"], pairs=o["pairs"],
                          compound=o["compound"], lead=o["lead"])

    def select(self, objective, k, seed):
        o = self.options
        rng = numpy_rng(seed)
        start = start_selection(o["start"], objective, k, rng, o["elements"])
        search = self.search(objective, k, rng)
        return search.run(start)[0]


@hookimpl
def arraysel_register_selectors(register):
    register(SwapSelector)
