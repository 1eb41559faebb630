"""arraysel: sparse ultrasound array design on a differentiable SIMUS objective.

``import arraysel as asel`` gives the notebook API, imported lazily (``import
arraysel`` itself loads neither torch nor pandas):

* ``asel.load_scene(name_or_path)`` -- a :class:`~arraysel.scene.Scene`
* ``asel.build_objective(scene)`` / ``asel.Objective`` -- the PSF objective
* ``asel.compare(scene, selectors, ...)`` -- DataFrames and Figures (:mod:`arraysel.api`)
* ``asel.Budget``, ``asel.selectors()`` (the registered selector names), ``asel.cache_dir()``
"""

__version__ = "0.1.0"

#: public name -> (module, attribute)
_LAZY = {
    "load_scene": ("arraysel.scene", "load_scene"),
    "Scene": ("arraysel.scene", "Scene"),
    "Objective": ("arraysel.objective", "Objective"),
    "build_objective": ("arraysel.objective", "build_objective"),
    "compare": ("arraysel.api", "compare"),
    "CompareResult": ("arraysel.api", "CompareResult"),
    "Budget": ("arraysel.selector", "Budget"),
    "Selector": ("arraysel.selector", "Selector"),
    "cache_dir": ("arraysel.cache", "cache_dir"),
}

__all__ = ["__version__", "selectors", *_LAZY]


def selectors() -> list:
    """Names of the registered selectors (built-ins and installed plugins)."""
    from .registry import get_registry

    return list(get_registry().names())


def __getattr__(name):
    if name in _LAZY:
        import importlib

        module, attr = _LAZY[name]
        value = getattr(importlib.import_module(module), attr)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'arraysel' has no attribute {name!r}")


def __dir__():
    return sorted(set(globals()) | set(_LAZY))
