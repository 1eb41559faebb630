"""A single-file arraysel plugin: load it with ``--plugin examples/single_file_plugin.py``.

    arraysel list --plugin examples/single_file_plugin.py
    arraysel compare --plugin examples/single_file_plugin.py --selectors centre,uniform --scene toy

It registers ``centre``: the k contiguous elements in the middle of the array
(a compact aperture, the opposite of a spread-out one).
"""
from arraysel.selectors.hookspecs import hookimpl
from arraysel.selectors.contract import Selector, indices_to_mask


class CentreSelector(Selector):
    name = "centre"
    description = "the k contiguous elements in the middle of the array"
    options = {}
    deterministic = True

    def batch_size(self, n_elements, k):
        return 1

    def select(self, objective, k, seed):
        start = (objective.n_elements - k) // 2
        chosen = list(range(start, start + k))
        groups = getattr(objective, "constraints", None)  # a scene's channel groups (docs/constraints.md)
        if groups is not None:  # the feasible selection nearest the centre block
            chosen = groups.project(indices_to_mask(chosen, objective.n_elements))
        objective.evaluate(indices_to_mask(chosen, objective.n_elements)[None])  # scored for the trace
        return chosen


@hookimpl
def arraysel_register_selectors(register):
    register(CentreSelector)
