"""Statistics over seeds of a comparison (``stats.csv``, columns
:data:`arraysel.report.columns.STATS_COLUMNS`).

For each configuration, the ``Mean`` of each of its runs (one per seed; runs without a finite
Mean are left out and counted): median, quartiles, IQR, mean, standard deviation, best and
worst, a distribution-free confidence interval of the median, and a rank test and an effect size
against the runs of the ``random`` configuration. ``docs/statistics.md`` states each statistic
and its assumptions.

* **Deterministic configurations** (:func:`deterministic_configs`): the ``full`` reference and
  every selector whose class declares ``deterministic = True`` (``uniform``, ``spiral``,
  ``greedy``: the seed does not change the result) are single values: their repeats (an older
  folder ran them once per seed) are not samples, so they get no interval and no test.
* **Confidence interval of the median** (:func:`median_ci`): the order statistics
  ``[x_(l), x_(n+1-l)]`` of the ``n`` finite Means, with the largest ``l`` whose exact coverage
  ``1 - 2 P(B <= l - 1)``, ``B ~ Binomial(n, 1/2)``, is at least the asked level
  (:data:`CI_LEVEL`, 90 % by default); the coverage is stated with the interval
  (``Mean_median_ci_level``: 93.75 % for 5 seeds). It assumes only independent runs from one
  continuous distribution (ties make it conservative). NaN, with "n/a" in the report, when even
  ``[min, max]`` covers less than the level (5 seeds are needed for 90 %, 6 for 95 %).
* **Rank test** (:func:`mann_whitney_u`): the two-sided Mann-Whitney U test of the Means against
  random's, as ``scipy.stats.mannwhitneyu`` computes it by default (exact p-value for small
  samples without ties, the normal approximation otherwise); NaN, with the reason in ``note``, when there is no ``random``
  configuration, for ``random`` itself, for a deterministic configuration, or when either side
  has fewer than 2 runs. ``p_vs_random_holm``: the p-values of one comparison adjusted for their
  number by Holm's step-down method (:func:`holm`), which controls the family-wise error rate
  under any dependence between the tests.
* **Effect size** (:func:`vargha_delaney_a`): ``A_vs_random`` = P(X < Y) + P(X = Y) / 2 for a run
  X of the configuration and a run Y of ``random``: the chance that the configuration's Mean is
  the lower (better) one. 0.5: no difference; 1: every run below every random run. It is
  Vargha and Delaney's A12 for a quantity to minimise (Cliff's delta = 2 A - 1).
* **AOCC** (:func:`aocc_by_config`): the area over the convergence curve of each run, as
  ``iohinspector`` computes it (``transform_fval`` then ``get_aocc``), averaged over the
  configuration's runs: the best-so-far ``Mean`` of the trace, on a log scale between the lowest
  and the highest finite ``best_Mean`` of the whole comparison, turned into ``1 - (log y - log
  lb) / (log ub - log lb)`` clipped to [0, 1], integrated over evaluations 0 .. the largest run's
  evaluations and divided by that length. 1: the comparison's best value at once; 0: never
  better than its worst. The bounds are the comparison's own, so AOCC ranks the selectors of one
  comparison; it is NaN without a trace.
* **Gaps** (:func:`gap_columns`): ``gap_closed`` = (uniform - median) / (uniform - full) when the
  comparison holds the ``uniform`` and ``full`` rows; ``gap_to_best_known`` = median / best
  known - 1 when the scene has a stored best-known selection (:mod:`arraysel.scenes.best_known`).
* **Expected running time** (:func:`ert_by_config`) to a target within :data:`ERT_GAPS` of the
  best known, as benchmarking defines it for runs with a budget (Hansen et al., COCO; the ERT of
  IOHprofiler): the time every run of the configuration spent until it reached the target, or
  its whole time where it did not, summed, divided by the number of runs that reached it; inf
  when none did. It reads off the trace how long a selector needs on average to come that close
  to the best known, and stays meaningful past the budget (a median that misses the target says
  only that half the runs did).
"""
from __future__ import annotations

import math
from typing import Any, NamedTuple

import numpy as np

from arraysel.report.columns import STATS_COLUMNS

__all__ = ["CI_LEVEL", "BASELINE", "MedianCI", "finite", "seed_statistics", "median_ci", "median_ci_rank",
           "rank_test", "mann_whitney_u", "holm", "vargha_delaney_a", "percent", "baseline_config", "deterministic_configs",
           "stats_table", "run_aocc", "aocc_by_config", "gap_columns", "ERT_GAPS", "ert_column", "ert_by_config"]

#: the least coverage asked of the confidence interval of the median (each interval states its own,
#: exact coverage, at least this)
CI_LEVEL = 0.90
#: the selector every configuration is tested against
BASELINE = "random"
#: targets of the expected running time: these gaps to the best-known Mean (1, 2, 3 and 10 %)
ERT_GAPS = (0.01, 0.02, 0.03, 0.10)
#: the reference row of every comparison (the full array): one value
FULL = "full"


def ert_column(gap: float) -> str:
    """The ``stats.csv`` column of the expected running time to a gap (``0.02`` -> ``ERT_s_2pct``)."""
    return f"ERT_s_{round(100 * gap):d}pct"


def finite(values) -> np.ndarray:
    """``values`` as float64 with the non-numbers and non-finite values left out."""
    import pandas as pd

    v = pd.to_numeric(pd.Series(list(values), dtype=object), errors="coerce").to_numpy(dtype=np.float64)
    return v[np.isfinite(v)]


def seed_statistics(means) -> dict[str, float]:
    """Median, quartiles (numpy's linear percentiles), IQR, mean, standard deviation (ddof 1; NaN
    for one value), best (lowest) and worst of the finite values of ``means``; NaN for none."""
    v = finite(means)
    if not v.size:
        return {k: math.nan for k in ("Mean_median", "Mean_q25", "Mean_q75", "Mean_iqr", "Mean_mean",
                                      "Mean_std", "Mean_best", "Mean_worst")}
    q25, med, q75 = (float(x) for x in np.percentile(v, [25, 50, 75]))
    return {"Mean_median": med, "Mean_q25": q25, "Mean_q75": q75, "Mean_iqr": q75 - q25,
            "Mean_mean": float(v.mean()), "Mean_std": float(v.std(ddof=1)) if v.size > 1 else math.nan,
            "Mean_best": float(v.min()), "Mean_worst": float(v.max())}


class MedianCI(NamedTuple):
    """A confidence interval of the median: its bounds, its exact coverage (a probability) and,
    when there is none, why (``note``); NaN bounds and coverage then."""

    low: float
    high: float
    coverage: float
    note: str


def median_ci_rank(n: int, level: float = CI_LEVEL) -> tuple[int, float] | None:
    """``(l, coverage)`` of the narrowest interval ``[x_(l), x_(n+1-l)]`` (1-based order
    statistics of ``n`` values) whose coverage of the median, ``1 - 2 P(B <= l - 1)`` with ``B ~
    Binomial(n, 1/2)``, is at least ``level``; None when even ``[x_(1), x_(n)]`` covers less."""
    if not 0.0 < level < 1.0:
        from arraysel.errors import ParameterError

        raise ParameterError(f"the confidence level must be between 0 and 1 (exclusive), got {level!r}")
    best = None
    tail = 0  # 2^n P(B <= l - 1), in integers
    for l in range(1, (n + 1) // 2 + 1):
        tail += math.comb(n, l - 1)
        coverage = 1.0 - 2.0 * tail / 2 ** n
        if coverage < level:
            break
        best = (l, coverage)
    return best


def median_ci(values, level: float = CI_LEVEL) -> MedianCI:
    """Distribution-free confidence interval of the median of the finite ``values`` from their
    order statistics (:func:`median_ci_rank`), with its exact coverage; NaN with the reason when
    there are too few values for ``level``."""
    v = np.sort(finite(values))
    found = median_ci_rank(int(v.size), level)
    if found is None:
        need = 2
        while 1.0 - 2.0 ** (1 - need) < level:  # [min, max] of `need` values covers 1 - 2^(1-need)
            need += 1
        return MedianCI(math.nan, math.nan, math.nan,
                        f"no confidence interval: {v.size} run(s) with a finite Mean, {need} needed for "
                        f"{percent(level)}")
    l, coverage = found
    return MedianCI(float(v[l - 1]), float(v[v.size - l]), coverage, "")


def rank_test(values, reference) -> tuple[float, float, str]:
    """Two-sided Mann-Whitney U test of the finite ``values`` against the finite ``reference``:
    ``(U, p, note)`` (:func:`mann_whitney_u`); ``(nan, nan, reason)`` when either side has fewer
    than 2 values."""
    a, b = finite(values), finite(reference)
    if a.size < 2 or b.size < 2:
        return math.nan, math.nan, (f"no rank test: {a.size} run(s) here and {b.size} of {BASELINE} with a "
                                    f"finite Mean, 2 needed on each side")
    u, p = mann_whitney_u(a, b)
    return u, p, ""


def mann_whitney_u(x, y) -> tuple[float, float]:
    """``(U, p)`` of the two-sided Mann-Whitney U test of ``x`` against ``y`` as
    ``scipy.stats.mannwhitneyu(x, y)`` computes it with its defaults (``method="auto"``, continuity
    correction), without importing scipy.stats (a second of start-up for ``arraysel report``).
    ``U`` counts the pairs where ``x`` is the larger (ties count one half). The p-value is exact
    (the null distribution of ``U``) when the samples have no ties and one has at most 8 values,
    else the normal approximation with the tie correction."""
    x, y = np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)
    n1, n2 = int(x.size), int(y.size)
    values, inverse, counts = np.unique(np.concatenate([x, y]), return_inverse=True, return_counts=True)
    ranks = (np.cumsum(counts) - (counts - 1) / 2.0)[inverse]   # average ranks, 1-based
    u1 = float(ranks[:n1].sum() - n1 * (n1 + 1) / 2)
    u = max(u1, n1 * n2 - u1)
    if (n1 > 8 and n2 > 8) or bool((counts > 1).any()):
        n = n1 + n2
        tie_term = float(np.sum(counts.astype(np.float64) ** 3 - counts))
        sd = math.sqrt(n1 * n2 / 12 * ((n + 1) - tie_term / (n * (n - 1))))
        # every value tied (sd = 0): no evidence either way, p = 1
        p = math.erfc((u - n1 * n2 / 2 - 0.5) / sd / math.sqrt(2.0)) if sd > 0 else 1.0   # 2 P(Z > z)
    else:
        p = 2.0 * _u_tail(int(round(u)), n1, n2)
    return u1, float(min(1.0, max(0.0, p)))


def _u_tail(u: int, m: int, n: int) -> float:
    """P(U >= u) under the null hypothesis for samples of ``m`` and ``n`` values without ties: the
    counts of U are the coefficients of the Gaussian binomial [m + n choose m] in q."""
    deg = m * n
    c = [1] + [0] * deg
    for i in range(1, min(m, n) + 1):   # prod_i (1 - q^(max + i)) / (1 - q^i), exact in integers
        step = max(m, n) + i
        for d in range(deg, step - 1, -1):
            c[d] -= c[d - step]
        for d in range(i, deg + 1):
            c[d] += c[d - i]
    return sum(c[u:]) / math.comb(m + n, m)


def holm(pvalues) -> np.ndarray:
    """Holm's step-down adjustment of ``pvalues`` (NaN stay NaN and are not counted): the ``i``-th
    smallest of ``m`` p-values becomes ``max_{j <= i} min(1, (m - j + 1) p_(j))``, in the given order."""
    p = np.asarray(pvalues, dtype=np.float64).reshape(-1)
    out = np.full(p.shape, math.nan)
    ok = np.flatnonzero(np.isfinite(p))
    m = ok.size
    if not m:
        return out
    order = ok[np.argsort(p[ok], kind="stable")]
    scaled = np.minimum(1.0, (m - np.arange(m)) * p[order])
    out[order] = np.maximum.accumulate(scaled)
    return out


def vargha_delaney_a(values, reference) -> float:
    """P(X < Y) + P(X = Y) / 2 for X drawn from the finite ``values`` and Y from the finite
    ``reference`` (all pairs counted): Vargha and Delaney's A for a quantity to minimise, the
    chance that ``values`` is the lower; NaN when either side is empty."""
    a, b = finite(values), finite(reference)
    if not a.size or not b.size:
        return math.nan
    lower = (a[:, None] < b[None, :]).sum()
    ties = (a[:, None] == b[None, :]).sum()
    return float((lower + 0.5 * ties) / (a.size * b.size))


def percent(x: float) -> str:
    """A probability as a percentage for a label: ``0.9375`` -> ``"93.8 %"``, ``0.9`` -> ``"90 %"``."""
    text = f"{100 * x:.1f}"
    return (text[:-2] if text.endswith(".0") else text) + " %"


def deterministic_configs(runs, selectors_meta=None) -> set[str]:
    """The configurations of ``runs`` that are single values, not samples: :data:`FULL` and each
    whose selector class declares ``deterministic = True``. ``selectors_meta`` (``run.json``'s
    ``selectors`` entries) says it per configuration when it has a ``deterministic`` key (written
    since that key exists); otherwise the selector's registered class says it (an older folder);
    a selector the registry does not know counts as stochastic."""
    declared = {str(d["config"]): bool(d["deterministic"]) for d in (selectors_meta or ())
                if isinstance(d, dict) and "config" in d and "deterministic" in d}
    out = {FULL}
    pairs = dict.fromkeys(zip(runs["config"].astype(str),
                              runs["selector"].astype(str) if "selector" in runs else runs["config"].astype(str)))
    registry = None
    for config, selector in pairs:
        if config in declared:
            if declared[config]:
                out.add(config)
            continue
        if registry is None:
            registry = _registry()
        cls = registry.get(selector) if registry else None
        if cls is not None and bool(getattr(cls, "deterministic", False)):
            out.add(config)
    return out


def _registry() -> dict:
    """``{name: selector class}`` of the process-wide registry; empty when a plugin fails to load."""
    from arraysel.errors import ArrayselError
    from arraysel.selectors.registry import get_registry

    try:
        return dict(get_registry().items())
    except ArrayselError:
        return {}


def baseline_config(runs) -> tuple[str | None, str]:
    """The configuration the rank test compares against: the one labelled :data:`BASELINE`, else
    the only one whose selector is :data:`BASELINE`. Returns ``(config, "")`` or ``(None, reason)``."""
    configs = [str(c) for c in dict.fromkeys(runs["config"])]
    if BASELINE in configs:
        return BASELINE, ""
    if "selector" in runs:
        own = [str(c) for c in dict.fromkeys(runs.loc[runs["selector"].astype(str) == BASELINE, "config"])]
        if len(own) == 1:
            return own[0], ""
        if len(own) > 1:
            return None, f"no rank test: several {BASELINE} configurations ({', '.join(own)})"
    return None, f"no rank test: the comparison has no {BASELINE} configuration"


def _median(values) -> float:
    v = finite(values)
    return float(np.median(v)) if v.size else math.nan


def _dat_rows(rows) -> list[tuple[int, float]]:
    """``(evaluations, best_Mean)`` of one run's trace rows as its IOHprofiler ``.dat`` holds them
    (:func:`arraysel.report.tables.write_ioh`): by evaluations (an ``end`` row last), evaluations
    at least 1, one row per evaluation count (the last: readers start a new run at each
    ``evaluations == 1``), and a first row ``(1, inf)`` when the first scored selection came later."""
    return [(ev, y) for ev, y, _ in dat_lines(rows)]


def dat_lines(rows) -> list[tuple[int, float, float]]:
    """``(evaluations, best_Mean, seconds)`` of each line of one run's IOHprofiler ``.dat`` block
    (see :func:`_dat_rows`)."""
    rows = sorted(rows, key=lambda t: (int(t["evaluations"]), str(t.get("event")) == "end"))
    last: dict[int, tuple[int, float, float]] = {}
    for t in rows:
        ev = max(1, int(t["evaluations"]))
        last[ev] = (ev, float(t["best_Mean"]), float(t["seconds"]))
    out = list(last.values())
    if out and int(rows[0]["evaluations"]) > 1:
        out.insert(0, (1, math.inf, 0.0))
    return out


def run_aocc(points, lb: float, ub: float, eval_max: float) -> float:
    """AOCC of one run's ``(evaluations, best-so-far y)`` points, as ``iohinspector``'s
    ``transform_fval(lb, ub, scale_log=True)`` and ``get_aocc(eval_max)`` compute it (see the module)."""
    if not points or not (0 < lb < ub) or not eval_max > 0:
        return math.nan
    e = np.array([p[0] for p in points if p[0] <= eval_max], dtype=np.float64)
    y = np.array([p[1] for p in points if p[0] <= eval_max], dtype=np.float64)
    if not e.size:
        return math.nan
    with np.errstate(divide="ignore", invalid="ignore"):
        norm = (np.log10(y) - math.log10(lb)) / (math.log10(ub) - math.log10(lb))
    eaf = 1.0 - np.clip(np.nan_to_num(norm, nan=1.0, posinf=1.0, neginf=0.0), 0.0, 1.0)
    e = np.concatenate([[0.0], e, [float(eval_max)]])
    eaf = np.concatenate([[eaf.min()], eaf, [eaf.max()]])
    order = np.argsort(e, kind="stable")
    e, eaf = e[order], eaf[order]
    return float(np.sum(np.diff(e) * eaf[:-1]) / eval_max)


def aocc_by_config(trace) -> dict[str, float]:
    """Mean AOCC of each configuration's runs (the trace's ``config``, ``seed``, ``evaluations``,
    ``best_Mean`` and ``event``; bounds and horizon from the whole trace, see the module)."""
    import pandas as pd

    if trace is None or not len(trace):
        return {}
    t = pd.DataFrame(trace)
    y = pd.to_numeric(t["best_Mean"], errors="coerce").to_numpy(dtype=np.float64)
    y = y[np.isfinite(y) & (y > 0)]
    if not y.size:
        return {}
    lb, ub = float(y.min()), float(y.max())
    if not ub > lb:
        ub = lb * (1 + 1e-12)
    eval_max = float(max(1, pd.to_numeric(t["evaluations"], errors="coerce").max()))
    out: dict[str, list[float]] = {}
    for (config, _seed), g in t.groupby(["config", "seed"], sort=False, dropna=False):
        out.setdefault(str(config), []).append(run_aocc(_dat_rows(g.to_dict("records")), lb, ub, eval_max))
    return {c: float(np.nanmean(v)) if np.isfinite(v).any() else math.nan for c, v in out.items()}


def ert_by_config(trace, best_known: float | None, gaps=ERT_GAPS) -> dict[str, dict[str, float]]:
    """``{config: {ert_column(gap): seconds}}``: the expected running time of each configuration's
    runs to a best-so-far Mean at most ``best_known * (1 + gap)`` (see the module), from the
    trace's ``config``, ``seed``, ``seconds`` and ``best_Mean`` (each run's last row its end).
    Empty without a trace or a positive finite best known."""
    import pandas as pd

    if trace is None or not len(trace) or best_known is None or not (math.isfinite(best_known) and best_known > 0):
        return {}
    t = pd.DataFrame(trace)
    t["seconds"] = pd.to_numeric(t["seconds"], errors="coerce")
    t["best_Mean"] = pd.to_numeric(t["best_Mean"], errors="coerce")
    spent: dict[str, list[float]] = {}
    hits: dict[str, list[int]] = {}  # per config, per gap: runs that reached the target
    for (config, _seed), g in t.groupby(["config", "seed"], sort=False, dropna=False):
        g = g.dropna(subset=["seconds"]).sort_values("seconds", kind="stable")
        if not len(g):
            continue
        total = float(g["seconds"].iloc[-1])
        y = g["best_Mean"].to_numpy(dtype=np.float64)
        s = g["seconds"].to_numpy(dtype=np.float64)
        c = str(config)
        spent.setdefault(c, [0.0] * len(gaps))
        hits.setdefault(c, [0] * len(gaps))
        for i, gap in enumerate(gaps):
            at = np.flatnonzero(np.isfinite(y) & (y <= best_known * (1.0 + gap)))
            spent[c][i] += float(s[at[0]]) if at.size else total
            hits[c][i] += int(at.size > 0)
    return {c: {ert_column(gap): (spent[c][i] / hits[c][i] if hits[c][i] else math.inf)
                for i, gap in enumerate(gaps)} for c in spent}


def gap_columns(runs, medians: dict[str, float], best_known: float | None) -> dict[str, tuple[float, float]]:
    """``{config: (gap_closed, gap_to_best_known)}`` of the configurations' median Means (see the
    module; NaN where the comparison lacks ``uniform`` or ``full``, or the scene a best known)."""
    def mean_of(config):
        v = finite(runs.loc[runs["config"].astype(str) == config, "Mean"])
        return float(np.median(v)) if v.size else math.nan

    uniform, full = mean_of("uniform"), mean_of("full")
    span = uniform - full
    out = {}
    for config, med in medians.items():
        closed = (uniform - med) / span if math.isfinite(span) and span != 0 else math.nan
        to_best = med / best_known - 1.0 if best_known else math.nan
        out[config] = (closed, to_best)
    return out


def stats_table(runs, trace=None, best_known: float | None = None, *, deterministic=None,
                level: float = CI_LEVEL) -> Any:
    """``stats.csv`` of a runs table (a DataFrame with ``config``, ``Mean``, ``evaluations``,
    ``seconds`` and optionally ``selector``): one row per configuration, in their order. ``trace``
    (``trace.csv``'s rows) gives the AOCC, ``best_known`` (the scene's best-known Mean) the gap to
    it; ``deterministic``: the configurations that are single values (default:
    :func:`deterministic_configs`); ``level``: the least coverage of the median's interval."""
    import pandas as pd

    single = deterministic_configs(runs) if deterministic is None else {FULL, *map(str, deterministic)}
    aoccs = aocc_by_config(trace)
    erts = ert_by_config(trace, best_known)
    base, base_note = baseline_config(runs)
    ref = runs.loc[runs["config"].astype(str) == base, "Mean"] if base is not None else []
    out = []
    for config, g in runs.groupby("config", sort=False):
        means = finite(g["Mean"])
        rec: dict[str, Any] = {"config": config, "n_seeds": int(means.size), "n_failed": int(len(g) - means.size),
                               "deterministic": str(config) in single}
        rec.update(seed_statistics(means))
        rec["AOCC"] = aoccs.get(str(config), math.nan)
        for gap in ERT_GAPS:
            rec[ert_column(gap)] = erts.get(str(config), {}).get(ert_column(gap), math.nan)
        rec["evaluations_median"] = _median(g["evaluations"])
        rec["seconds_median"] = _median(g["seconds"])
        rec.update(_versus(str(config), means, base, base_note, ref, rec["deterministic"], level))
        out.append(rec)
    adjusted = holm([r["p_vs_random"] for r in out])
    gaps = gap_columns(runs, {r["config"]: r["Mean_median"] for r in out}, best_known)
    for rec, p in zip(out, adjusted):
        rec["p_vs_random_holm"] = float(p)
        rec["gap_closed"], rec["gap_to_best_known"] = gaps[rec["config"]]
    return pd.DataFrame(out, columns=list(STATS_COLUMNS))


def _versus(config: str, means: np.ndarray, base, base_note: str, ref, single: bool, level: float) -> dict:
    """The interval of the median, the rank test and the effect size of one configuration (NaN,
    with the reasons in ``note``, where they do not apply)."""
    nan = math.nan
    if single:
        why = "the full array" if config == FULL else "deterministic"
        return {"Mean_median_ci_low": nan, "Mean_median_ci_high": nan, "Mean_median_ci_level": nan,
                "U_vs_random": nan, "p_vs_random": nan, "A_vs_random": nan,
                "note": f"{why}: a single value, no interval and no test"}
    ci = median_ci(means, level)
    if base is None:
        u, p, a, test_note = nan, nan, nan, base_note
    elif config == base:
        u, p, a, test_note = nan, nan, nan, f"no rank test: {config} is the reference"
    else:
        u, p, test_note = rank_test(means, ref)
        a = vargha_delaney_a(means, ref)
    return {"Mean_median_ci_low": ci.low, "Mean_median_ci_high": ci.high, "Mean_median_ci_level": ci.coverage,
            "U_vs_random": u, "p_vs_random": p, "A_vs_random": a,
            "note": "; ".join(n for n in (ci.note, test_note) if n)}
