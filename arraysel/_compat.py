"""Old flat module paths (before the 0.2 layout) keep importing, with a DeprecationWarning.

``import arraysel.selector`` still works and gives :mod:`arraysel.selectors.contract` (the same module
object, so ``isinstance`` and monkeypatching agree); the warning names the new path.
"""
from __future__ import annotations

import importlib
import importlib.util
import sys
import warnings

#: old module (under ``arraysel.``) -> where it lives now
MOVED = {
    "probes": "physics.probes", "delays": "physics.delays", "simus": "physics.simus",
    "beamform": "physics.beamform", "psf": "physics.psf", "pairkernels": "physics.pairkernels",
    "scene": "scenes.schema",
    "atomic": "io.atomic", "cache": "io.cache", "maskio": "io.masks",
    "metrics": "objective.metrics",
    "selector": "selectors.contract", "hookspecs": "selectors.hookspecs", "registry": "selectors.registry",
    "relax": "selectors.relax", "localsearch": "selectors.localsearch",
    "runner": "run._legacy_runner", "executors": "run._legacy_executors", "allocator": "io.allocator",
    "reporting": "report.tables",
    "data": "e2e.data", "recon": "e2e.recon", "training": "e2e.trainer", "e2e_figures": "e2e.figures",
    "commands": "cli",
    **{f"commands.{c}": f"cli.{c}" for c in ("compare", "evaluate", "list", "psf", "scenes", "cache", "train")},
}
#: old modules whose names now live in several modules: where each went (said in the warning)
SPLIT = {
    "runner": "Experiment in arraysel.run.experiment, compare in arraysel.run.compare, the output-folder "
              "checks in arraysel.run.outdir, ROW_COLUMNS in arraysel.report.columns",
    "executors": "the executors in arraysel.run.executors, the random search in arraysel.run.random_search, "
                 "the objective factories next to their objectives (arraysel.objective.psf_objective, "
                 "arraysel.objective.toy), IsolatedWorker in arraysel.run.isolation",
}


class _Alias:
    """A meta-path finder and loader (duck-typed: importing importlib.abc would cost every start ~10 ms)."""

    def find_spec(self, fullname, path=None, target=None):
        if fullname.startswith("arraysel.") and fullname[len("arraysel."):] in MOVED:
            return importlib.util.spec_from_loader(fullname, self)
        return None

    def create_module(self, spec):
        new = "arraysel." + MOVED[spec.name[len("arraysel."):]]
        old = spec.name[len("arraysel."):]
        where = f" ({SPLIT[old]})" if old in SPLIT else ""
        warnings.warn(f"{spec.name} has moved to {new}{where}; import from there (the old path will be removed "
                      f"in 0.3)", DeprecationWarning, stacklevel=3)
        return importlib.import_module(new)

    def exec_module(self, module):  # the target module is already executed
        pass


_FINDER = _Alias()


def install() -> None:
    if _FINDER not in sys.meta_path:
        sys.meta_path.insert(0, _FINDER)  # before the path finder, so an old sub-module is never loaded twice
