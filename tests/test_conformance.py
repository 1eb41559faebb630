"""Selector conformance suite (arraysel.testing.SelectorConformance) over every registered selector.

The registry is built without installed entry points (so plugins installed on
the machine cannot change the results) and with the example plugins of
``examples/`` loaded, exactly as a third party's would be.
"""
from __future__ import annotations

from pathlib import Path

import pytest

from arraysel.objective.toy import ToyObjective
from arraysel.run.experiment import Experiment
from arraysel.selectors.contract import Budget
from arraysel.selectors.registry import build_plugin_manager, get_registry, load_plugin
from arraysel.testing import SelectorConformance

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


def _registry():
    pm = build_plugin_manager(load_entrypoints=False, disabled=())
    load_plugin(str(EXAMPLES / "single_file_plugin.py"), pm)
    load_plugin(str(EXAMPLES / "arraysel-example-plugin" / "src" / "arraysel_example_plugin" / "__init__.py"), pm)
    return get_registry(pm)


REGISTRY = _registry()

for _name in REGISTRY.names():
    _cls_name = "TestConformance_" + _name.replace("-", "_")
    globals()[_cls_name] = type(_cls_name, (SelectorConformance,), {"selector_name": _name, "registry": REGISTRY})


def test_every_builtin_is_covered():
    for name in ("uniform", "random", "ste", "gumbel", "nlopt", "greedy", "centre", "random-swap", "swap", "ils",
                 "anneal", "genetic", "memetic", "lns", "nevergrad", "spiral"):
        assert "TestConformance_" + name.replace("-", "_") in globals()



@pytest.mark.parametrize("name", REGISTRY.names())
def test_every_selector_runs_on_a_toy_matrix(name):
    # every selector of the suite on a 4 x 4 matrix (a toy objective with an element_grid): exactly
    # k distinct elements, no error, the evaluation budget respected (up to one batch, as in the suite)
    cls = REGISTRY[name]
    for k in (1, 5, 16):
        obj = ToyObjective(16, k, grid=(4, 4))
        exp = Experiment(obj, cls, options={}, budget=Budget(evaluations=60), seed=0, k=k)
        row = exp.run()
        assert row["error"] == "", f"k={k}: {row['error']}"
        sel = [int(i) for i in row["elements"].split()]
        assert len(sel) == k and len(set(sel)) == k and all(0 <= i < 16 for i in sel), f"k={k}: {sel}"
        assert row["evaluations"] <= 60 + cls().batch_size(16, k)
