"""The objective: metrics, loss terms, the PSF objective and the toy objective.

``from arraysel.objective import build_objective, Objective`` keeps working: the PSF objective's public
names are re-exported here.
"""
from arraysel.objective.psf_objective import (AGGREGATES, METRIC_NAMES, PSF_WEIGHT_KEYS, Objective, build_objective,
                                              masks_from_indices, point_metric_names)

__all__ = ["AGGREGATES", "METRIC_NAMES", "PSF_WEIGHT_KEYS", "Objective", "build_objective", "masks_from_indices",
           "point_metric_names"]
