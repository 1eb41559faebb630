"""The objective: the contract (``contract``), metrics, loss terms (``losses``), the PSF objective
(``psf_objective``) and the toy objective (``toy``).

``from arraysel.objective import build_objective, Objective`` keeps working: the PSF objective's public
names are re-exported here, lazily, so that importing a light submodule (``losses``, ``metrics``:
used by the relaxations every selector plugin imports) does not load the PSF operator.
"""
_PSF_NAMES = ("AGGREGATES", "METRIC_NAMES", "PSF_WEIGHT_KEYS", "Objective", "build_objective", "masks_from_indices",
              "point_metric_names")

__all__ = list(_PSF_NAMES)


def __getattr__(name):
    if name in _PSF_NAMES:
        from arraysel.objective import build, psf_objective

        value = getattr(build if name == "build_objective" else psf_objective, name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'arraysel.objective' has no attribute {name!r}")


def __dir__():
    return sorted(set(globals()) | set(_PSF_NAMES))
