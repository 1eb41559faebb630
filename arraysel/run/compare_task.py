"""The compare task: one ``(selector, seed)`` experiment of ``arraysel compare`` as a picklable item
(:func:`compare_item`) and the function a worker runs on it (:func:`compare_task`)."""
from __future__ import annotations

import dataclasses
import os
import pickle
import sys

from arraysel.errors import ParameterError, error_text as _error_text
from arraysel.run.experiment import Experiment
from arraysel.selectors.contract import BudgetExceededError
from arraysel.selectors.registry import load_plugin

__all__ = ["compare_item", "compare_task"]


def _plugin_specs(cls) -> tuple[str, ...]:
    """``--plugin`` files a worker must load before it can unpickle ``cls``."""
    mod = sys.modules.get(cls.__module__)
    if cls.__module__.startswith("arraysel_plugin_file_") and getattr(mod, "__file__", None):
        return (mod.__file__,)
    return ()


def compare_item(config: str, cls, options: dict, budget, seed: int) -> dict:
    """The picklable description of one compare run (see :func:`compare_task`)."""
    try:
        blob = pickle.dumps(cls)
    except Exception as exc:
        raise ParameterError(
            f"selector class {cls.__qualname__} cannot be sent to worker processes ({_error_text(exc)}); "
            f"define it at module level of an importable module, or load it with --plugin") from None
    return {"config": config, "selector": blob, "plugins": _plugin_specs(cls), "options": dict(options),
            "budget": budget.fresh(), "seed": int(seed)}


@dataclasses.dataclass
class _Raise:
    """Returned by a worker instead of raising an error that must stop the comparison
    (not retried: it is not the worker's fault)."""

    exception: BaseException


def compare_task(objective, item) -> dict | _Raise:
    """Run one ``(selector, seed)`` experiment on a worker: ``{"row": ..., "trace": [...]}`` (the
    row's ``elements``: its :class:`~arraysel.selection.Selection`, :meth:`Experiment.execute`)."""
    for spec in item["plugins"]:
        load_plugin(spec)
    cls = pickle.loads(item["selector"])
    exp = Experiment(objective, cls, options=item["options"], budget=item["budget"], seed=item["seed"],
                     config=item["config"])
    try:
        row = exp.execute()
    except BudgetExceededError as exc:
        return _Raise(exc)
    return {"row": row, "trace": [dict(t) for t in exp.trace], "pid": os.getpid()}

