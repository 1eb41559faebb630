"""The column schema of ``arraysel compare``'s files: one definition that the runs (``arraysel.run``)
write and the tables (``arraysel.report.tables``, ``arraysel.report.stats``,
``arraysel.report.summary``) read."""
from __future__ import annotations

from arraysel.objective.names import MERIT_NAMES, METRIC_NAMES  # torch-free: `arraysel report` loads no torch

__all__ = ["METRICS", "TABLE1_METRICS", "ROW_COLUMNS", "TRACE_COLUMNS", "TABLE1_COLUMNS", "STATS_COLUMNS",
           "PAPER_NAMES", "MERIT_COLUMNS"]

METRICS = METRIC_NAMES
#: columns of a run row, in this order; ``budget_flag`` says when a run's time budget did not
#: measure its search (:func:`arraysel.run.experiment.budget_flag`), else it is empty
ROW_COLUMNS = ("config", "selector", "seed", "k", "n_elements", *METRICS, "seconds", "evaluations",
               "gradient_steps", "objective_seconds", "overhead_seconds", "elements", "options", "error",
               "budget_flag")
#: columns of ``trace.csv``: one ``improvement`` row per new best, then one ``end`` row at the
#: run's last evaluation and time; ``elements``, on the ``end`` row only, is the selection that
#: scored its ``best_Mean``
TRACE_COLUMNS = ("config", "seed", "seconds", "evaluations", "gradient_steps", "best_Mean", "event", "elements")
#: the metrics of ``table1.csv``'s leading columns (``L_SLR``, their mean, comes later)
TABLE1_METRICS = tuple(m for m in METRICS if m != "L_SLR")

#: columns of ``table1.csv``: one row per configuration, every value but ``seeds`` and ``error``
#: taken from ONE run of ``runs.csv``, the configuration's listed selection: the run with the
#: lowest finite ``Mean`` over its seeds (``seed`` names it; the first run when none has a
#: finite Mean). ``seeds``: the configuration's runs; ``error``: the errors of all its runs;
#: ``AOCC``: the mean over its runs (as in ``stats.csv``).
TABLE1_COLUMNS = ("config", *TABLE1_METRICS, "seconds", "evaluations", "elements", "L_SLR", "gradient_steps",
                  "overhead_seconds", "AOCC", "seed", "seeds", "error")

#: columns a 3-D scene's runs add (the 2-D array figures of merit); ``table1.csv`` carries them
#: after :data:`TABLE1_COLUMNS` when the runs have them
MERIT_COLUMNS = MERIT_NAMES

#: columns of ``stats.csv``: one row per configuration, statistics of its runs' ``Mean`` over seeds
#: (runs without a finite Mean are left out and counted in ``n_failed``; ``docs/statistics.md``):
#:
#: * ``n_seeds`` runs used, ``n_failed`` runs left out;
#: * ``deterministic``: True for a single value, not a sample (the ``full`` row, a selector whose
#:   class declares ``deterministic``): no interval, no test;
#: * ``Mean_median``, ``Mean_q25``, ``Mean_q75``, ``Mean_iqr`` (``q75 - q25``; numpy's linear
#:   percentiles), ``Mean_mean``, ``Mean_std`` (ddof 1), ``Mean_best`` (lowest), ``Mean_worst``;
#: * ``AOCC``: the mean area over the convergence curve of its runs (iohinspector's definition,
#:   bounds from the comparison's trace; :mod:`arraysel.report.stats`);
#: * ``gap_closed`` = (uniform - median) / (uniform - full), ``gap_to_best_known`` = median / the
#:   scene's best-known Mean - 1 (NaN where the comparison or the scene lacks what they need);
#: * ``ERT_s_1pct``, ``ERT_s_2pct``, ``ERT_s_3pct``, ``ERT_s_10pct``: expected running time, in
#:   seconds, to a selection within 1, 2, 3 and 10 % of the scene's best-known Mean (the seconds of
#:   its runs until they reached it, or all their seconds where they did not, summed, over the
#:   runs that reached it; inf where none did, NaN without a trace or a best known;
#:   :func:`arraysel.report.stats.ert_by_config`);
#: * ``Mean_median_ci_low`` / ``_high``: distribution-free confidence interval of the median from
#:   the order statistics, ``Mean_median_ci_level`` its exact coverage (at least 90 %; NaN when the
#:   runs are too few for that level; :func:`arraysel.report.stats.median_ci`);
#: * ``evaluations_median``, ``seconds_median``;
#: * ``U_vs_random``, ``p_vs_random``: two-sided Mann-Whitney U test of the runs' Means against
#:   those of the ``random`` configuration (as ``scipy.stats.mannwhitneyu`` computes it); ``p_vs_random_holm``:
#:   the p-values Holm-adjusted over the configurations tested; ``A_vs_random``: Vargha-Delaney A,
#:   the chance that a run's Mean is below a random run's (0.5: no difference);
#: * ``note``: why a statistic is NaN (too few runs, deterministic, no ``random`` configuration, ...).
STATS_COLUMNS = ("config", "n_seeds", "n_failed", "deterministic", "Mean_median", "Mean_q25", "Mean_q75",
                 "Mean_iqr", "Mean_mean", "Mean_std", "Mean_best", "Mean_worst", "AOCC", "gap_closed",
                 "gap_to_best_known", "ERT_s_1pct", "ERT_s_2pct", "ERT_s_3pct", "ERT_s_10pct", "Mean_median_ci_low",
                 "Mean_median_ci_high", "Mean_median_ci_level", "evaluations_median", "seconds_median",
                 "U_vs_random", "p_vs_random", "p_vs_random_holm", "A_vs_random", "note")

#: the paper's names of the Table-1 metrics: ``{column: (plain text / Markdown, LaTeX)}``
PAPER_NAMES = {
    "L_PSF": ("L_PSF", r"$\mathcal{L}_{\mathrm{PSF}}$"),
    "L_contrast": ("L_contrast", r"$\mathcal{L}_{\mathrm{contrast}}$"),
    "L_SLR_q": ("L_SLR_q", r"$\mathcal{L}_{\mathrm{SLR},q}$"),
    "L_SLR_i": ("L_SLR_i", r"$\mathcal{L}_{\mathrm{SLR},i}$"),
    "L_SLR": ("L_SLR", r"$\mathcal{L}_{\mathrm{SLR}}$"),
    "Mean": ("Mean", "Mean"),
}
