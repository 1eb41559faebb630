"""The compare task: one ``(selector, seed)`` experiment of ``arraysel compare`` as a picklable item
(:func:`compare_item`) and the function a worker runs on it (:func:`compare_task`).

A selector class travels to the run's process pickled by name when it can; one that cannot (a
class a factory made, say) travels as its registered name and the plugin that registered it (a
``--plugin`` file by path, or a module by name), which the run's process loads before it looks
the name up. A class that can travel neither way cannot run isolated (:func:`compare_item` says
so, naming it).
"""
from __future__ import annotations

import dataclasses
import importlib.util
import os
import pickle
import sys

from arraysel.errors import ArrayselError, ParameterError, error_text as _error_text
from arraysel.run.experiment import Experiment
from arraysel.selectors.contract import BudgetExceededError
from arraysel.selectors.registry import BUILTIN_PLUGINS, get_registry, load_plugin

__all__ = ["compare_item", "compare_task", "plugin_spec"]


def _plugin_specs(cls) -> tuple[str, ...]:
    """``--plugin`` files a worker must load before it can unpickle ``cls``."""
    mod = sys.modules.get(cls.__module__)
    if cls.__module__.startswith("arraysel_plugin_file_") and getattr(mod, "__file__", None):
        return (mod.__file__,)
    return ()


def plugin_spec(origin: str | None) -> str | None:
    """What a run's process loads to register the selectors of the plugin ``origin`` (a
    registry's origin label): the path of a ``--plugin`` file, the name of a ``--plugin``
    module; ``""`` for a built-in or installed plugin (every process registers those);
    ``None`` when the selector was registered some other way (a registry made by hand)."""
    if not origin or origin.startswith("<"):
        return None
    if origin.startswith("file:"):
        return origin[len("file:"):]
    if origin in BUILTIN_PLUGINS or " (" in origin:  # built-in, or installed: "name (dist version)"
        return ""
    if not all(part.isidentifier() for part in origin.split(".")):
        return None
    try:  # a module a child can import (not a plugin object registered by hand under that name)
        return origin if importlib.util.find_spec(origin) is not None else None
    except (ImportError, ValueError):
        return None


def compare_item(config: str, cls, options: dict, budget, seed: int, origin: str | None = None) -> dict:
    """The picklable description of one compare run (see :func:`compare_task`); ``origin``: the
    registry's origin of the selector (how a class that does not pickle by name is found again).
    Raises :class:`ParameterError` naming the selector when its class can reach another process
    neither way."""
    item = {"config": config, "name": cls.name, "qualname": cls.__qualname__, "plugins": _plugin_specs(cls),
            "options": dict(options), "budget": budget.fresh(), "seed": int(seed)}
    try:
        item["selector"] = pickle.dumps(cls)
        return item
    except Exception as exc:
        why = _error_text(exc)
    spec = plugin_spec(origin)
    if spec is None:
        raise ParameterError(
            f"selector {cls.name!r} cannot run isolated: its class {cls.__qualname__} does not pickle by name "
            f"({why}) and it was not registered by a plugin a child process can load (origin: "
            f"{origin or 'unknown'}); register it from a --plugin file or an importable module, or run it "
            f"in this process with --in-process (isolate=False), not isolated")
    item["selector"] = None
    item["plugins"] = tuple(dict.fromkeys([*item["plugins"], *([spec] if spec else [])]))
    return item


@dataclasses.dataclass
class _Raise:
    """Returned by a worker instead of raising an error that must stop the comparison
    (not retried: it is not the worker's fault)."""

    exception: BaseException


def _selector_class(item: dict):
    """The selector class of ``item``: unpickled, or looked up by name once its plugins are loaded."""
    if item.get("selector") is not None:
        return pickle.loads(item["selector"])
    registry = get_registry()
    name = item["name"]
    cls = registry[name] if name in registry else None
    if cls is None or cls.__qualname__ != item["qualname"]:
        found = "not registered" if cls is None else f"registered as class {cls.__qualname__}"
        raise ArrayselError(f"selector {name!r} (class {item['qualname']}) is {found} in the run's process "
                            f"after loading {', '.join(item['plugins']) or 'the installed plugins'}")
    return cls


def compare_task(objective, item) -> dict | _Raise:
    """Run one ``(selector, seed)`` experiment on a worker: ``{"row": ..., "trace": [...]}`` (the
    row's ``elements``: its :class:`~arraysel.selection.Selection`, :meth:`Experiment.execute`)."""
    for spec in item["plugins"]:
        load_plugin(spec)
    cls = _selector_class(item)
    exp = Experiment(objective, cls, options=item["options"], budget=item["budget"], seed=item["seed"],
                     config=item["config"])
    try:
        row = exp.execute()
    except BudgetExceededError as exc:
        return _Raise(exc)
    return {"row": row, "trace": [dict(t) for t in exp.trace], "pid": os.getpid()}
