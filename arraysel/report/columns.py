"""The column schema of ``arraysel compare``'s files: one definition that the runs (``arraysel.run``)
write and the tables (``arraysel.report.tables``) read."""
from __future__ import annotations

from arraysel.objective.metrics import METRIC_NAMES

__all__ = ["METRICS", "TABLE1_METRICS", "ROW_COLUMNS", "TRACE_COLUMNS"]

METRICS = METRIC_NAMES
#: columns of a run row, in this order
ROW_COLUMNS = ("config", "selector", "seed", "k", "n_elements", *METRICS, "seconds", "evaluations",
               "gradient_steps", "objective_seconds", "overhead_seconds", "elements", "options", "error")
#: columns of ``trace.csv``: one ``improvement`` row per new best, then one ``end`` row at the
#: run's last evaluation and time
TRACE_COLUMNS = ("config", "seed", "seconds", "evaluations", "gradient_steps", "best_Mean", "event")
#: the metrics of ``table1.csv``'s leading columns (``L_SLR``, their mean, comes later)
TABLE1_METRICS = tuple(m for m in METRICS if m != "L_SLR")
