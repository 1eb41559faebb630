"""``greedy``: backward elimination from the full array, or forward selection.

Backward: start from all ``Ne`` elements; at each step score every set with
one element removed (one batched call) and drop the element whose removal
gives the lowest ``Mean``; stop at ``k`` elements. Forward: start empty and
add the element giving the lowest ``Mean``. Ties go to the lower index; NaN
scores rank last. When the budget runs out before ``k`` is reached, the
remaining steps follow the ranking of the last scored batch
(:func:`arraysel.selectors.starts.greedy_selection`).
"""
from __future__ import annotations

from arraysel.selectors.contract import Option, Selector
from arraysel.selectors.hookspecs import hookimpl
from arraysel.selectors.starts import greedy_selection


class GreedySelector(Selector):
    name = "greedy"
    description = "greedy backward elimination from the full array (or forward selection)"
    options = {
        "direction": Option(str, "backward", "backward: remove from the full array; forward: add to an "
                            "empty one", choices=("backward", "forward")),
    }
    deterministic = True

    def select(self, objective, k, seed):
        return greedy_selection(objective, k, backward=self.options["direction"] == "backward")


@hookimpl
def arraysel_register_selectors(register):
    register(GreedySelector)
