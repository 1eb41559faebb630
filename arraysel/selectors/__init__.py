"""Selection strategies: the selector contract, the plugin hooks and registry, relaxations and swap search.

The built-in selectors themselves live in the top-level ``plugins/`` folder (installed as
``arraysel_plugins``) and register exactly as a third-party plugin does.  A plugin imports
what it needs from here::

    from arraysel.selectors import BudgetExhausted, Option, Selector, hookimpl

``arraysel.selectors()`` (this package, called) returns the registered selector names, as
``asel.selectors()`` always has.
"""
from __future__ import annotations

import sys
import types

from arraysel.selectors.contract import (Budget, BudgetedObjective, BudgetExceededError, BudgetExhausted, Option,
                                         Recorder, Selector, check_selection, indices_to_mask, mask_to_indices,
                                         numpy_rng, top_k, torch_rng)
from arraysel.selectors.hookspecs import hookimpl, hookspec

__all__ = [
    "Budget", "BudgetedObjective", "BudgetExceededError", "BudgetExhausted", "Option", "Recorder", "Selector",
    "check_selection", "indices_to_mask", "mask_to_indices", "numpy_rng", "top_k", "torch_rng",
    "hookimpl", "hookspec", "names",
]


def names() -> list[str]:
    """Names of the registered selectors (built-ins and installed plugins)."""
    from arraysel.selectors.registry import get_registry

    return list(get_registry().names())


class _CallablePackage(types.ModuleType):
    """Lets ``arraysel.selectors()`` keep listing the selector names now that the name is also this package."""

    def __call__(self) -> list[str]:
        return names()


sys.modules[__name__].__class__ = _CallablePackage
