"""Hook specifications of arraysel's plugin system (pluggy project ``"arraysel"``).

A plugin is any module or object with functions decorated by :data:`hookimpl`.
Built-in selectors (the modules of :mod:`arraysel_plugins`) are registered by
exactly the same mechanism as a third party's plugin; see ``docs/selectors.md``.

Example
-------
>>> from arraysel.selectors.hookspecs import hookimpl
>>> from arraysel.selectors.contract import Selector
>>> class Mine(Selector):
...     name = "mine"
...     description = "keep the first k elements"
...     def select(self, objective, k, seed):
...         return list(range(k))
>>> @hookimpl
... def arraysel_register_selectors(register):
...     register(Mine)
"""
from __future__ import annotations

import pluggy

#: the pluggy project name; also the entry-point group (``[project.entry-points.arraysel]``)
PROJECT_NAME = "arraysel"

hookspec = pluggy.HookspecMarker(PROJECT_NAME)
hookimpl = pluggy.HookimplMarker(PROJECT_NAME)


@hookspec
def arraysel_register_selectors(register):
    """Register selection strategies.

    Call ``register(SelectorClass)`` once per strategy, where ``SelectorClass``
    is a subclass of :class:`arraysel.selectors.contract.Selector` with a unique
    ``name``. Every plugin's implementation is called once when the selector
    registry is built; return values are ignored (results combine through the
    ``register`` callback, not through the return value). Registering a name
    that another plugin already registered raises
    :class:`arraysel.selectors.registry.DuplicateSelectorError`.
    """
