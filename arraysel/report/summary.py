"""A finished comparison as a table a paper takes as it is (``arraysel report``).

:func:`load_comparison` reads a folder written by ``arraysel compare`` (``run.json``, ``runs.csv``)
and builds its ``table1.csv`` and ``stats.csv`` tables from ``runs.csv`` (the one source: an
older folder whose tables were written by another version reads the same);
:func:`summary_rows` joins them into one row per configuration: the Table-1 metrics of its
listed selection (the best of its seeds by Mean), then the statistics of its Means over seeds
(median [IQR], the order-statistic confidence interval of the median with its exact coverage,
Holm-adjusted Mann-Whitney p and Vargha-Delaney A against random; a deterministic selector's
single value, untested; ``docs/statistics.md``).
:func:`to_markdown` and :func:`to_latex` write that table (no extra dependency: the writers
are here); :func:`to_text` is the plain table ``arraysel compare`` prints.
"""
from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path
from typing import Any

from arraysel.errors import ParameterError
from arraysel.report.columns import PAPER_NAMES, ROW_COLUMNS, TABLE1_METRICS
from arraysel.report.stats import BASELINE, CI_LEVEL, percent

__all__ = ["Comparison", "load_comparison", "summary_rows", "SUMMARY_HEADERS", "headers", "to_markdown",
           "to_latex", "to_text", "render", "report", "FORMATS"]

#: output formats of :func:`render`
FORMATS = ("md", "latex")


@dataclasses.dataclass
class Comparison:
    """A finished comparison folder: ``meta`` (``run.json``), ``runs``, ``table`` (``table1.csv``)
    and ``stats`` (``stats.csv``) as DataFrames, built from ``runs.csv``."""

    folder: Path
    meta: dict
    runs: Any
    table: Any
    stats: Any
    #: the least coverage asked of the median's interval
    level: float = CI_LEVEL


def load_comparison(folder, level: float = CI_LEVEL) -> Comparison:
    """Read a finished comparison folder (its statistics with a median interval of coverage at
    least ``level``). Raises :class:`ParameterError` with a one-line message when ``folder`` is
    not one (no folder, no or unreadable ``run.json`` / ``runs.csv``, a run that did not finish,
    missing columns)."""
    import pandas as pd

    from arraysel.report.stats import deterministic_configs, stats_table
    from arraysel.report.tables import best_known_mean, read_runs, read_trace, table1

    folder = Path(folder)
    if not folder.is_dir():
        raise ParameterError(f"{str(folder)!r} is not a folder; give the --out folder of `arraysel compare`")
    meta_path, runs_path = folder / "run.json", folder / "runs.csv"
    if not meta_path.is_file():
        raise ParameterError(f"{str(folder)!r} has no run.json: not the folder of `arraysel compare`")
    try:
        meta = json.loads(meta_path.read_bytes().decode("utf-8"))
    except (OSError, ValueError) as exc:
        raise ParameterError(f"{meta_path} cannot be read ({type(exc).__name__}: {exc})") from None
    if not isinstance(meta, dict) or "selectors" not in meta:
        raise ParameterError(f"{meta_path} is not the run.json of `arraysel compare` (no 'selectors' entry)")
    status = meta.get("status")
    if status != "finished":
        raise ParameterError(f"the comparison in {str(folder)!r} is not finished (run.json status: {status!r}); "
                             f"finish it with `arraysel compare ... --resume`")
    if not runs_path.is_file():
        raise ParameterError(f"{str(folder)!r} has no runs.csv")
    try:
        runs = read_runs(runs_path)
    except (OSError, ValueError, UnicodeDecodeError, pd.errors.ParserError) as exc:
        raise ParameterError(f"{runs_path} cannot be read ({type(exc).__name__}: {exc})") from None
    if "budget_flag" not in runs.columns:  # written before the column existed: no flags
        runs["budget_flag"] = ""
    missing = [c for c in ROW_COLUMNS if c not in runs.columns]
    if missing:
        raise ParameterError(f"{runs_path} lacks the column(s) {', '.join(missing)}")
    if not len(runs):
        raise ParameterError(f"{runs_path} holds no runs")
    try:
        trace = read_trace(folder / "trace.csv") if (folder / "trace.csv").is_file() else None
    except (OSError, ValueError, UnicodeDecodeError, pd.errors.ParserError) as exc:
        raise ParameterError(f"{folder / 'trace.csv'} cannot be read ({type(exc).__name__}: {exc})") from None
    stats = stats_table(runs, trace, best_known_mean(folder), level=level,
                        deterministic=deterministic_configs(runs, meta.get("selectors")))
    return Comparison(folder=folder, meta=meta, runs=runs, table=table1(runs, dict(zip(stats["config"], stats["AOCC"]))),
                      stats=stats, level=level)


#: the columns of :func:`summary_rows`, by key: (plain / Markdown header, LaTeX header); the
#: interval's header names its coverage when every interval has the same (:func:`headers`)
SUMMARY_HEADERS = {
    "config": ("selector", "selector"),
    **{m: PAPER_NAMES[m] for m in TABLE1_METRICS},
    "seeds": ("seeds", "seeds"),
    "median_iqr": ("median Mean [IQR]", r"median Mean [IQR]"),
    "ci": ("CI of median (coverage)", r"CI of median (coverage)"),
    "p": (f"p vs {BASELINE} (Holm)", rf"$p$ vs {BASELINE} (Holm)"),
    "a": (f"A vs {BASELINE}", rf"$A$ vs {BASELINE}"),
}


def _coverages(comp: Comparison) -> list[float]:
    """The distinct exact coverages of the comparison's median intervals."""
    import numpy as np

    c = comp.stats["Mean_median_ci_level"].to_numpy(dtype=np.float64) if "Mean_median_ci_level" in comp.stats \
        else np.array([])
    return sorted({float(x) for x in c[np.isfinite(c)]})


def headers(comp: Comparison) -> dict[str, tuple[str, str]]:
    """:data:`SUMMARY_HEADERS` of ``comp``: the interval's header names the coverage (e.g. "93.8 %
    CI of median") when all its intervals have one and the same."""
    out = dict(SUMMARY_HEADERS)
    cov = _coverages(comp)
    if len(cov) == 1:
        out["ci"] = (f"{percent(cov[0])} CI of median", percent(cov[0]).replace(" %", r"\,\%") + " CI of median")
    return out


def _num(v, latex: bool, digits: int = 4) -> str:
    """``v`` to ``digits`` significant digits; "-" for NaN / missing; LaTeX powers of ten."""
    try:
        x = float(v)
    except (TypeError, ValueError):
        return "-"
    if not math.isfinite(x):
        return "-"
    text = f"{x:.{digits}g}"
    if latex and "e" in text:
        mant, exp = text.split("e")
        text = rf"${mant}\times10^{{{int(exp)}}}$"
    return text


def _int(v) -> str:
    try:
        x = float(v)
    except (TypeError, ValueError):
        return "-"
    return f"{int(x):d}" if math.isfinite(x) else "-"


def summary_rows(comp: Comparison, latex: bool = False) -> list[dict[str, str]]:
    """One dict of formatted cells per configuration (keys :data:`SUMMARY_HEADERS`), ``full`` first.
    A deterministic configuration is a single value ("-" for the interval and the test); "n/a":
    too few seeds for the interval's level."""
    stats = comp.stats.set_index("config")
    per_cell = len(_coverages(comp)) > 1  # the coverage in each cell, not the header
    rows = []
    for _, r in comp.table.iterrows():
        s = stats.loc[r["config"]]
        single = bool(s.get("deterministic", False))
        cell = {"config": str(r["config"])}
        for m in TABLE1_METRICS:
            cell[m] = _num(r[m], latex)
        cell["seeds"] = _int(s["n_seeds"]) + (f" (+{_int(s['n_failed'])} failed)" if s["n_failed"] else "")
        if single:
            cell["seeds"] += " (deterministic)" if r["config"] != "full" else ""
            cell["median_iqr"] = _num(s["Mean_median"], latex)
            cell["ci"] = cell["p"] = cell["a"] = "-"
        else:
            cell["median_iqr"] = f"{_num(s['Mean_median'], latex)} [{_num(s['Mean_iqr'], latex, 2)}]"
            cell["ci"] = _ci_cell(s, latex, per_cell)
            cell["p"] = _num(s.get("p_vs_random_holm"), latex, 2)
            cell["a"] = _num(s.get("A_vs_random"), latex, 2)
        rows.append(cell)
    return rows


def _ci_cell(s, latex: bool, per_cell: bool) -> str:
    try:
        coverage = float(s.get("Mean_median_ci_level"))
    except (TypeError, ValueError):
        coverage = math.nan
    if not math.isfinite(coverage):
        return "n/a"
    text = f"{_num(s['Mean_median_ci_low'], latex)} - {_num(s['Mean_median_ci_high'], latex)}"
    if per_cell:
        text += f" ({percent(coverage)})".replace(" %", r"\,\%" if latex else " %")
    return text


def _best_row(comp: Comparison) -> int | None:
    """Index of the configuration (not ``full``) whose listed selection has the lowest Mean."""
    import numpy as np

    means = [float(m) if c != "full" else math.inf for c, m in zip(comp.table["config"], comp.table["Mean"])]
    means = [m if math.isfinite(m) else math.inf for m in means]
    i = int(np.argmin(means)) if means else 0
    return i if means and math.isfinite(means[i]) else None


def _caption(comp: Comparison) -> str:
    meta = comp.meta
    budget = meta.get("budget") or {}
    parts = []
    if budget.get("seconds"):
        parts.append(f"{budget['seconds']:g} s")
    if budget.get("evaluations"):
        parts.append(f"{budget['evaluations']:,} evaluations")
    scene = meta.get("scene_name") or "?"
    return (f"Scene {scene}, k = {meta.get('k', '?')} of {meta.get('n_elements', '?')} elements, "
            f"budget {' and '.join(parts) or 'none'} per run. Metrics: of each selector's listed selection, "
            f"the best of its seeds by Mean (lower is better). Over seeds: median Mean [IQR]; distribution-free "
            f"confidence interval of the median from order statistics, at its exact coverage (at least "
            f"{percent(comp.level)}; n/a: too few seeds for that); two-sided Mann-Whitney U test of the Means "
            f"against {BASELINE}'s, Holm-adjusted over the selectors; A: the chance that a run ends below a "
            f"{BASELINE} run (Vargha-Delaney; 0.5 no difference). Deterministic selectors: one value, not "
            f"tested.")


def to_markdown(comp: Comparison) -> str:
    """A GitHub-flavoured Markdown table (caption line, table; the best Mean in bold)."""
    rows = summary_rows(comp)
    best = _best_row(comp)
    heads = headers(comp)
    keys = list(heads)

    def esc(t: str) -> str:
        return t.replace("|", r"\|")

    lines = ["| " + " | ".join(esc(heads[k][0]) for k in keys) + " |",
             "|" + "|".join("---" if k == "config" else "---:" for k in keys) + "|"]
    for i, r in enumerate(rows):
        cells = [esc(r[k]) for k in keys]
        if i == best:
            cells[keys.index("Mean")] = f"**{cells[keys.index('Mean')]}**"
        lines.append("| " + " | ".join(cells) + " |")
    return _caption(comp) + "\n\n" + "\n".join(lines) + "\n"


_LATEX_SPECIAL = {"\\": r"\textbackslash{}", "&": r"\&", "%": r"\%", "$": r"\$", "#": r"\#", "_": r"\_",
                  "{": r"\{", "}": r"\}", "~": r"\textasciitilde{}", "^": r"\textasciicircum{}"}


def _latex_text(t: str) -> str:
    return "".join(_LATEX_SPECIAL.get(ch, ch) for ch in t)


def to_latex(comp: Comparison) -> str:
    """A LaTeX ``table`` with a ``booktabs`` tabular (``\\usepackage{booktabs}``); the best Mean in bold."""
    rows = summary_rows(comp, latex=True)
    best = _best_row(comp)
    heads = headers(comp)
    keys = list(heads)
    out = [r"\begin{table}", r"\centering", r"\caption{" + _latex_text(_caption(comp)) + "}",
           r"\begin{tabular}{l" + "r" * (len(keys) - 1) + "}", r"\toprule",
           " & ".join(heads[k][1] for k in keys) + r" \\", r"\midrule"]
    for i, r in enumerate(rows):
        cells = [_latex_text(r["config"])] + [r[k].replace(" - ", "--") for k in keys[1:]]
        if i == best:
            cells[keys.index("Mean")] = r"\textbf{" + cells[keys.index("Mean")] + "}"
        out.append(" & ".join(cells) + r" \\")
    out += [r"\bottomrule", r"\end{tabular}", r"\end{table}"]
    return "\n".join(out) + "\n"


def to_text(table, stats) -> str:
    """The plain table ``arraysel compare`` prints: each configuration's listed selection (Mean,
    its seed) and the statistics over seeds."""
    import pandas as pd

    cols = ["config", "Mean", "seed", "seeds", "evaluations", "Mean_median", "Mean_iqr", "Mean_median_ci_low",
            "Mean_median_ci_high", "Mean_median_ci_level", "AOCC", "gap_closed", "gap_to_best_known",
            "p_vs_random_holm", "A_vs_random", "error"]
    joined = table.drop(columns=["AOCC"], errors="ignore").merge(stats.drop(columns=["note"]), on="config",
                                                                 how="left", sort=False)
    with pd.option_context("display.width", 200, "display.max_colwidth", 60, "display.max_columns", 20):
        return joined[[c for c in cols if c in joined]].to_string(index=False)


def render(folder, fmt: str = "md", level: float = CI_LEVEL) -> str:
    """The table of the comparison in ``folder`` as Markdown (``"md"``) or LaTeX (``"latex"``),
    the median's interval of coverage at least ``level``."""
    if fmt not in FORMATS:
        raise ParameterError(f"format must be one of {', '.join(FORMATS)}, got {fmt!r}")
    comp = load_comparison(folder, level)
    return to_markdown(comp) if fmt == "md" else to_latex(comp)


def report(folder, fmt: str = "md", out=None, rebuild: bool = False,
           level: float = CI_LEVEL) -> tuple[str, list[Path]]:
    """``arraysel report``: the table of the finished comparison in ``folder`` (:func:`render`,
    the median's interval of coverage at least ``level``); written atomically to ``out`` when
    given; with ``rebuild``, ``table1.csv`` and ``stats.csv`` of the folder are rewritten from its
    ``runs.csv`` first (at the default level). Returns ``(text, paths written)``."""
    from arraysel.io.atomic import atomic_write_text, check_writable
    from arraysel.report.tables import write_tables

    if fmt not in FORMATS:
        raise ParameterError(f"format must be one of {', '.join(FORMATS)}, got {fmt!r}")
    if out is not None:
        check_writable(out, "--out")
    comp = load_comparison(folder, level)
    written: list[Path] = []
    if rebuild:
        write_tables(comp.folder, comp.runs)
        written += [comp.folder / "table1.csv", comp.folder / "stats.csv"]
    text = to_markdown(comp) if fmt == "md" else to_latex(comp)
    if out is not None:
        atomic_write_text(out, text)
        written.append(Path(out))
    return text, written
