"""Selector conformance suite (arraysel.testing.SelectorConformance) over every registered selector.

The registry is built without installed entry points (so plugins installed on
the machine cannot change the results) and with the example plugins of
``examples/`` loaded, exactly as a third party's would be.
"""
from __future__ import annotations

from pathlib import Path

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
    for name in ("uniform", "random", "ste", "gumbel", "nlopt", "greedy", "centre", "random-swap", "swap",
                 "anneal", "genetic", "nevergrad", "spiral"):
        assert "TestConformance_" + name.replace("-", "_") in globals()
