"""The names of the objective's metrics, without torch: the one definition that the metric modules
(:mod:`arraysel.objective.metrics`, :mod:`arraysel.objective.metrics3d`) and the table schema
(:mod:`arraysel.report.columns`) import, so that reading a finished comparison loads no torch."""
from __future__ import annotations

__all__ = ["METRIC_NAMES", "MERIT_NAMES"]

#: the Table-1 metrics, in table order
METRIC_NAMES: tuple[str, ...] = ("L_PSF", "L_contrast", "L_SLR_q", "L_SLR_i", "L_SLR", "Mean")
#: the figures of merit of 2-D sparse-array papers, computed next to the Table-1 terms
MERIT_NAMES: tuple[str, ...] = ("PSL_dB", "width_x_6dB", "width_y_6dB")
