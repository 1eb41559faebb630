"""arraysel: sparse ultrasound array design on a differentiable SIMUS objective.

``import arraysel as asel`` gives the notebook API, imported lazily (``import
arraysel`` itself loads neither torch nor pandas):

* ``asel.load_scene(name_or_path)`` -- a :class:`~arraysel.scenes.schema.Scene`
* ``asel.build_objective(scene)`` / ``asel.Objective`` -- the PSF objective
* ``asel.evaluate(scene, selections)`` -- a DataFrame, one row per selection (:mod:`arraysel.api`)
* ``asel.compare(scene, selectors, ...)`` -- DataFrames and Figures (:mod:`arraysel.api`)
* ``asel.Budget``, ``asel.selectors()`` (the registered selector names), ``asel.cache_dir()``

The layers, bottom up: :mod:`arraysel.physics`, :mod:`arraysel.scenes`, :mod:`arraysel.objective`,
:mod:`arraysel.selectors`, :mod:`arraysel.run`, :mod:`arraysel.report`, :mod:`arraysel.e2e`,
:mod:`arraysel.cli` (``docs/architecture.md``).
"""

import os as _os

__version__ = "0.1.0"

# OpenMP threads that sleep when idle instead of spinning, unless the user chose a policy. Scoring a
# batch alternates torch's OpenMP pool and numba's (each its own libgomp): with the default policy
# the idle pool's threads spin and take the cores the other pool needs (issue 78: 128-element
# scenes 3x slower a mask, more on a loaded machine; docs/performance.md). Read by each OpenMP
# runtime when it loads, so this must run before torch and numba are imported.
_os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
del _os

#: public name -> (module, attribute)
_LAZY = {
    "load_scene": ("arraysel.scenes.schema", "load_scene"),
    "Scene": ("arraysel.scenes.schema", "Scene"),
    "Objective": ("arraysel.objective.psf_objective", "Objective"),
    "build_objective": ("arraysel.objective.build", "build_objective"),
    "compare": ("arraysel.api", "compare"),
    "evaluate": ("arraysel.api", "evaluate"),
    "CompareResult": ("arraysel.run.compare", "CompareResult"),
    "Budget": ("arraysel.selectors.contract", "Budget"),
    "Selector": ("arraysel.selectors.contract", "Selector"),
    "cache_dir": ("arraysel.io.cache", "cache_dir"),
}

__all__ = ["__version__", "selectors", *_LAZY]


def __getattr__(name):
    if name == "selectors":  # the package is callable: asel.selectors() lists the registered names
        import importlib

        return importlib.import_module("arraysel.selectors")
    if name in _LAZY:
        import importlib

        module, attr = _LAZY[name]
        value = getattr(importlib.import_module(module), attr)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'arraysel' has no attribute {name!r}")


def __dir__():
    return sorted(set(globals()) | set(_LAZY))
