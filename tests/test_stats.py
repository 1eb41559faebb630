"""Known-answer tests of table1.csv (one run per row) and stats.csv (statistics over seeds)."""
from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest
from scipy import stats as sps

from arraysel.report.columns import ROW_COLUMNS, STATS_COLUMNS, TABLE1_COLUMNS, TABLE1_METRICS
from arraysel.errors import ParameterError
from arraysel.report.stats import (baseline_config, deterministic_configs, holm, mann_whitney_u, median_ci,
                                   median_ci_rank, rank_test, seed_statistics, stats_table, vargha_delaney_a)
from arraysel.report.tables import read_runs, rebuild_tables, table1
from arraysel.run.compare import compare
from arraysel.selection import indices_to_mask, parse_element_text
from arraysel.selectors.contract import Budget
from arraysel.selectors.registry import build_plugin_manager, get_registry
from arraysel.testing import ToyObjective


@pytest.fixture(scope="module")
def reg():
    return get_registry(build_plugin_manager(load_entrypoints=False, disabled=()))


def _runs(spec: dict[str, list[float]], selector: dict[str, str] | None = None) -> pd.DataFrame:
    """A runs table: per config, one run per Mean (seeds 0, 1, ...); the other metrics derived
    from the Mean so that a row's values identify its run."""
    rows = []
    for config, means in spec.items():
        for seed, m in enumerate(means):
            ok = math.isfinite(m)  # a failed run has no time or count (as arraysel.run.experiment writes it)
            rows.append({"config": config, "selector": (selector or {}).get(config, config), "seed": seed,
                         "k": 2, "n_elements": 4, "L_PSF": 4 * m, "L_contrast": 0.0, "L_SLR_q": 0.0,
                         "L_SLR_i": 0.0, "L_SLR": 0.0, "Mean": m, "seconds": 10.0 + seed if ok else math.nan,
                         "evaluations": 100 * (seed + 1) if ok else math.nan, "gradient_steps": 0, "objective_seconds": 1.0,
                         "overhead_seconds": 0.5, "elements": f"{seed} 3", "options": "",
                         "error": "" if ok else "boom"})
    return pd.DataFrame(rows, columns=list(ROW_COLUMNS))


# ---------------------------------------------------------------------------
# the statistics, on hand-made values
# ---------------------------------------------------------------------------

def test_seed_statistics_known_values():
    s = seed_statistics([5.0, 1.0, 3.0, 2.0, 4.0, float("nan"), "x"])
    assert s == pytest.approx({"Mean_median": 3.0, "Mean_q25": 2.0, "Mean_q75": 4.0, "Mean_iqr": 2.0,
                               "Mean_mean": 3.0, "Mean_std": math.sqrt(2.5), "Mean_best": 1.0, "Mean_worst": 5.0})
    one = seed_statistics([0.25])
    assert one["Mean_median"] == one["Mean_best"] == one["Mean_worst"] == 0.25 and one["Mean_iqr"] == 0.0
    assert math.isnan(one["Mean_std"])
    assert all(math.isnan(v) for v in seed_statistics([float("nan")]).values())


def test_mannwhitneyu_known_p_values():
    # [1,2,3] below [4,5,6]: 1 of the C(6,3) = 20 arrangements is as extreme on each side -> p = 2/20
    u, p, note = rank_test([1.0, 2.0, 3.0], [4.0, 5.0, 6.0])
    assert (u, p, note) == (0.0, pytest.approx(0.1), "")
    # 3 against 4 fully separated: p = 2 / C(7,3) = 2/35; U counts the pairs where the first is larger
    u, p, _ = rank_test([7.0, 8.0, 9.0], [1.0, 2.0, 3.0, 4.0])
    assert u == 12.0 and p == pytest.approx(2 / 35)
    u, p, note = rank_test([1.0], [4.0, 5.0])
    assert math.isnan(u) and math.isnan(p) and "2 needed" in note


def test_mann_whitney_u_is_scipys():
    """The test as scipy.stats.mannwhitneyu computes it (exact and normal, ties, every size)."""
    rng = np.random.default_rng(0)
    for _ in range(400):
        n1, n2 = (int(v) for v in rng.integers(1, 24, 2))
        if rng.random() < 0.3:   # ties: the normal approximation with the tie correction
            x, y = rng.integers(0, 5, n1).astype(float), rng.integers(0, 5, n2).astype(float)
        else:
            x, y = rng.normal(size=n1), rng.normal(size=n2) + rng.normal()
        ref = sps.mannwhitneyu(x, y)
        u, p = mann_whitney_u(x, y)
        assert u == ref.statistic and p == pytest.approx(ref.pvalue, rel=1e-9, abs=1e-300), (x, y)
    assert mann_whitney_u([2.0, 2.0], [2.0, 2.0]) == (2.0, 1.0)


def test_median_interval_known_answers():
    # [min, max] of n values misses the median when all n fall on one side: coverage 1 - 2 / 2^n
    assert median_ci_rank(5) == (1, pytest.approx(1 - 2 / 32))          # 93.75 %
    assert median_ci_rank(4) is None and median_ci_rank(3) is None      # 87.5 %, 75 % < 90 %
    assert median_ci_rank(5, 0.95) is None and median_ci_rank(6, 0.95) == (1, pytest.approx(1 - 2 / 64))
    # n = 8 at 90 %: [x_(2), x_(7)] covers 1 - 2 (1 + 8) / 256 = 92.97 %; [x_(3), x_(6)] only 71.1 %
    assert median_ci_rank(8) == (2, pytest.approx(1 - 2 * 9 / 256))
    ci = median_ci([3.0, 1.0, float("nan"), 5.0, 2.0, 4.0])
    assert (ci.low, ci.high, ci.coverage, ci.note) == (1.0, 5.0, pytest.approx(0.9375), "")
    ci = median_ci([0.5, 0.7, 0.6])
    assert math.isnan(ci.low) and math.isnan(ci.coverage) and "5 needed for 90 %" in ci.note
    assert "6 needed for 95 %" in median_ci([0.5] * 5, 0.95).note
    assert median_ci([0.3] * 5)[:3] == (0.3, 0.3, pytest.approx(0.9375))   # ties: the interval is a point
    with pytest.raises(ParameterError, match="confidence level"):
        median_ci_rank(5, 1.0)


@pytest.mark.parametrize("n, level", [(5, 0.90), (8, 0.90), (8, 0.95), (11, 0.90), (12, 0.95), (20, 0.95)])
def test_median_interval_agrees_with_scipys_quantile_test(n, level):
    x = np.random.default_rng(n).lognormal(size=n)
    ci = median_ci(x, level)
    ref = sps.quantile_test(x, q=float(np.median(x)), p=0.5).confidence_interval(level)
    assert (ci.low, ci.high) == (ref.low, ref.high)


@pytest.mark.parametrize("n, level", [(5, 0.90), (8, 0.90), (8, 0.95), (11, 0.90), (12, 0.95)])
def test_median_interval_covers_at_its_stated_level_by_simulation(n, level):
    """40,000 samples of n lognormal values (true median 1): the share of intervals holding the
    median is the stated coverage within 2 points (the simulation's standard error is < 0.15 points)."""
    x = np.random.default_rng(1000 + n).lognormal(size=(40_000, n))
    l, stated = median_ci_rank(n, level)
    xs = np.sort(x, axis=1)
    low, high = xs[:, l - 1], xs[:, n - l]
    for i in range(50):  # the function gives these bounds
        assert median_ci(x[i], level)[:2] == (low[i], high[i])
    covered = float(np.mean((low <= 1.0) & (1.0 <= high)))
    assert stated >= level and abs(covered - stated) < 0.02, (covered, stated)


def test_holm_known_answers():
    # sorted 0.005, 0.01, 0.03, 0.04 (m = 4): 4 x 0.005, 3 x 0.01, 2 x 0.03, max(0.06, 1 x 0.04)
    got = holm([0.01, 0.04, 0.03, 0.005, float("nan")])
    assert got[:4] == pytest.approx([0.03, 0.06, 0.06, 0.02]) and math.isnan(got[4])
    assert holm([0.5, 0.9]).tolist() == [1.0, 1.0] and holm([0.02]).tolist() == [0.02]
    assert holm([]).size == 0 and np.isnan(holm([float("nan")])).all()


def test_vargha_delaney_a_known_answers():
    assert vargha_delaney_a([1.0, 2.0, 3.0], [4.0, 5.0, 6.0]) == 1.0     # always lower (better)
    assert vargha_delaney_a([4.0, 5.0], [1.0, 2.0]) == 0.0
    # pairs (1,2) (1,3) (2,3) lower, (2,2) a tie: (3 + 0.5) / 4
    assert vargha_delaney_a([1.0, 2.0], [2.0, 3.0]) == 0.875
    assert vargha_delaney_a([1.0, 1.0], [1.0]) == 0.5 and math.isnan(vargha_delaney_a([], [1.0]))
    a, b = np.random.default_rng(0).normal(size=7), np.random.default_rng(1).normal(size=9)
    u = sps.mannwhitneyu(a, b).statistic        # pairs where a is the larger (ties half)
    assert vargha_delaney_a(a, b) == pytest.approx(1 - u / (7 * 9))


def test_deterministic_selectors_are_single_values_never_tested():
    runs = _runs({"full": [0.05], "uniform": [0.4, 0.4, 0.4], "random": [0.5, 0.6, 0.7, 0.8, 0.9],
                  "a": [0.1, 0.2, 0.3, 0.15, 0.25], "b": [0.55, 0.65, 0.75, 0.85, 0.95]})
    s = stats_table(runs).set_index("config")                  # uniform's class declares it
    assert s["deterministic"].to_dict() == {"full": True, "uniform": True, "random": False, "a": False, "b": False}
    for c in ("full", "uniform"):
        assert s.loc[c, ["Mean_median_ci_low", "p_vs_random", "p_vs_random_holm", "A_vs_random"]].isna().all()
        assert "a single value, no interval and no test" in s.loc[c, "note"]
    assert s.loc["uniform", "Mean_median"] == 0.4
    # two tests in the family: Holm doubles the smaller p (a: 2/252), then max(., 1 x p_b)
    p_a, p_b = s.loc["a", "p_vs_random"], s.loc["b", "p_vs_random"]
    assert p_a == pytest.approx(2 / 252) and s.loc["a", "p_vs_random_holm"] == pytest.approx(2 * p_a)
    assert s.loc["b", "p_vs_random_holm"] == pytest.approx(max(2 * p_a, p_b))
    assert s.loc["a", "A_vs_random"] == 1.0 and s.loc["b", "A_vs_random"] == pytest.approx(10 / 25)
    assert s.loc["a", "Mean_median_ci_level"] == pytest.approx(0.9375)
    # run.json's declaration wins over the registry, and a caller may say it
    meta = [{"config": "uniform", "deterministic": False}, {"config": "a", "deterministic": True}]
    assert deterministic_configs(runs, meta) == {"full", "a"}
    assert stats_table(runs, deterministic=["b"]).set_index("config")["deterministic"].sum() == 2


def test_stats_table_known_medians_iqr_and_p():
    runs = _runs({"full": [0.05], "random": [0.5, 0.6, 0.7, 0.8], "a": [0.3, 0.1, float("nan"), 0.2],
                  "b": [0.9, 0.4]})
    st = stats_table(runs)
    assert tuple(st.columns) == STATS_COLUMNS and list(st["config"]) == ["full", "random", "a", "b"]
    s = st.set_index("config")
    assert (s.loc["a", "n_seeds"], s.loc["a", "n_failed"]) == (3, 1)
    assert s.loc["a", ["Mean_median", "Mean_q25", "Mean_q75", "Mean_iqr", "Mean_best", "Mean_worst"]].tolist() == \
        pytest.approx([0.2, 0.15, 0.25, 0.1, 0.1, 0.3])
    assert s.loc["random", ["Mean_median", "Mean_q25", "Mean_q75", "Mean_iqr"]].tolist() == \
        pytest.approx([0.65, 0.575, 0.725, 0.15])
    assert s.loc["a", "evaluations_median"] == 200 and s.loc["a", "seconds_median"] == pytest.approx(11.0)
    assert s.loc["a", "U_vs_random"] == 0 and s.loc["a", "p_vs_random"] == pytest.approx(2 / 35)
    assert s.loc["b", "p_vs_random"] == pytest.approx(sps.mannwhitneyu([0.9, 0.4], [0.5, 0.6, 0.7, 0.8]).pvalue)
    assert math.isnan(s.loc["random", "p_vs_random"]) and "reference" in s.loc["random", "note"]
    assert math.isnan(s.loc["full", "p_vs_random"]) and math.isnan(s.loc["full", "Mean_median_ci_low"])
    assert "a single value" in s.loc["full", "note"] and s.loc["a", "note"].startswith("no confidence interval")


def test_rank_test_without_random_is_nan_with_a_reason():
    s = stats_table(_runs({"a": [0.1, 0.2], "b": [0.3, 0.4]})).set_index("config")
    assert s["p_vs_random"].isna().all() and s["U_vs_random"].isna().all()
    assert s["note"].str.endswith("; no rank test: the comparison has no random configuration").all()
    # a random configuration with options is the reference when it is the only random one
    runs = _runs({"random(polish=0.5)": [0.5, 0.6], "a": [0.1, 0.2]}, selector={"random(polish=0.5)": "random"})
    assert baseline_config(runs) == ("random(polish=0.5)", "")
    assert stats_table(runs).set_index("config").loc["a", "p_vs_random"] == pytest.approx(1 / 3)


# ---------------------------------------------------------------------------
# table1: every value of a row from one run
# ---------------------------------------------------------------------------

def test_table1_rows_are_the_best_runs():
    runs = _runs({"full": [0.05], "a": [0.3, 0.1, float("nan"), 0.2], "dead": [float("nan"), float("nan")]})
    t = table1(runs)
    assert tuple(t.columns) == TABLE1_COLUMNS and list(t["config"]) == ["full", "a", "dead"]
    a = t.set_index("config").loc["a"]
    best = runs[(runs["config"] == "a") & (runs["seed"] == 1)].iloc[0]
    for col in TABLE1_COLUMNS:
        if col not in ("config", "seeds", "error", "AOCC"):
            assert a[col] == best[col], col
    assert a["seeds"] == 4 and a["error"] == "seed 2: boom"
    dead = t.set_index("config").loc["dead"]
    assert dead["seed"] == 0 and math.isnan(dead["Mean"]) and dead["error"] == "seed 0: boom; seed 1: boom"


def _check_rows_are_their_elements(table, objective, rtol):
    n = int(objective.n_elements)
    for _, row in table.iterrows():
        idx = parse_element_text(row["elements"])
        got = objective.evaluate(indices_to_mask(idx, n)[None, :])
        for m in TABLE1_METRICS + ("L_SLR",):
            assert float(row[m]) == pytest.approx(float(np.asarray(got[m])[0]), rel=rtol, abs=1e-12), \
                (row["config"], m)


def test_toy_table1_metrics_are_those_of_its_elements(reg, tmp_path):
    obj = ToyObjective(16, 8)
    table = compare(obj, ["random", "ste", "uniform"], out_dir=tmp_path, seeds=[0, 1, 2],
                    budget=Budget(evaluations=40), registry=reg, progress=False, figures=False).table
    runs = read_runs(tmp_path / "runs.csv")
    t1 = pd.read_csv(tmp_path / "table1.csv", keep_default_na=False)
    _check_rows_are_their_elements(t1, obj, 1e-6)
    for _, row in t1[t1["config"] != "full"].iterrows():  # the best seed's run, by Mean
        mine = runs[runs["config"] == row["config"]]
        assert row["Mean"] == pytest.approx(mine["Mean"].min())
        assert int(row["seed"]) == int(mine.loc[mine["Mean"].idxmin(), "seed"])
    assert list(table["config"]) == list(t1["config"])
    # rebuilding from runs.csv gives the same files
    before = [(tmp_path / f).read_text() for f in ("table1.csv", "stats.csv")]
    rebuild_tables(tmp_path)
    assert [(tmp_path / f).read_text() for f in ("table1.csv", "stats.csv")] == before


def test_resume_rebuilds_the_tables_from_every_run(reg, tmp_path):
    obj = ToyObjective(12, 6)
    compare(obj, ["random"], out_dir=tmp_path, seeds=[0, 1], budget=Budget(evaluations=20), registry=reg,
            progress=False, figures=False)
    compare(obj, ["random"], out_dir=tmp_path, seeds=[0, 1, 2, 3], budget=Budget(evaluations=20), registry=reg,
            progress=False, figures=False, resume=True)
    runs = read_runs(tmp_path / "runs.csv")
    st = pd.read_csv(tmp_path / "stats.csv").set_index("config")
    means = runs.loc[runs["config"] == "random", "Mean"].to_numpy()
    assert len(means) == 4 and st.loc["random", "n_seeds"] == 4
    assert st.loc["random", "Mean_median"] == pytest.approx(np.median(means))
    t1 = pd.read_csv(tmp_path / "table1.csv").set_index("config")
    assert t1.loc["random", "Mean"] == pytest.approx(means.min()) and t1.loc["random", "seeds"] == 4


def test_paper_table1_metrics_are_those_of_its_elements(reg, tmp_path, paper_objective):
    compare(paper_objective, ["uniform", "random"], out_dir=tmp_path, seeds=[0, 1],
            budget=Budget(evaluations=12), registry=reg, progress=False, figures=False)
    t1 = pd.read_csv(tmp_path / "table1.csv", keep_default_na=False)
    assert list(t1["config"]) == ["full", "uniform", "random"]
    _check_rows_are_their_elements(t1, paper_objective, 1e-5)


def test_api_result_carries_the_stats_table(tmp_path):
    import arraysel as asel

    res = asel.compare("toy", ["uniform", "random", "ste"], seeds=[0, 1], budget_s=None, budget_evals=30,
                       out_dir=tmp_path, progress=False, figures=False)
    assert tuple(res.stats.columns) == STATS_COLUMNS
    assert list(res.stats["config"]) == list(res.table["config"]) == ["full", "uniform", "random", "ste"]
    s = res.stats.set_index("config")
    means = res.runs.loc[res.runs["config"] == "ste", "Mean"]
    assert s.loc["ste", "Mean_median"] == pytest.approx(means.median())
    assert s.loc["ste", "p_vs_random"] == pytest.approx(
        sps.mannwhitneyu(means, res.runs.loc[res.runs["config"] == "random", "Mean"]).pvalue)
    assert s.loc["uniform", "note"].startswith("deterministic") and s.loc["uniform", "deterministic"]
    assert s.loc["ste", "note"].startswith("no confidence interval: 2 run(s)")
    assert res.table.set_index("config").loc["ste", "Mean"] == pytest.approx(means.min())


# ---------------------------------------------------------------------------
# anytime score (AOCC) and the gaps
# ---------------------------------------------------------------------------

def test_aocc_of_a_run_by_hand():
    from arraysel.report.stats import run_aocc

    # y = lb from evaluation 5 on, ub before: eaf 0 on [0, 5), 1 on [5, 10] -> 0.5
    assert run_aocc([(1, 1.0), (5, 0.01)], lb=0.01, ub=1.0, eval_max=10) == pytest.approx(0.5)
    # the geometric middle (log scale) from the start: eaf 0.5 everywhere
    assert run_aocc([(1, 0.1)], lb=0.01, ub=1.0, eval_max=4) == pytest.approx(0.5)
    # an infinite first value (no selection scored yet) counts as the worst
    assert run_aocc([(1, math.inf), (3, 0.01)], lb=0.01, ub=1.0, eval_max=4) == pytest.approx(0.25)
    assert math.isnan(run_aocc([], lb=0.01, ub=1.0, eval_max=4))


def test_aocc_equals_iohinspector_on_the_ioh_files(tmp_path):
    iohinspector = pytest.importorskip("iohinspector")
    import warnings

    import pandas as pd
    from iohinspector.metrics import get_aocc
    from iohinspector.metrics.utils import transform_fval

    from arraysel.report.stats import aocc_by_config
    from arraysel.run.compare import compare
    from arraysel.selectors.contract import Budget
    from arraysel.selectors.registry import build_plugin_manager, get_registry
    from arraysel.testing import ToyObjective

    reg = get_registry(build_plugin_manager(load_entrypoints=False, disabled=()))
    compare(ToyObjective(16, 8), ["uniform", "random", "swap", "greedy"], out_dir=tmp_path, seeds=[0, 1],
            budget=Budget(evaluations=300), registry=reg, progress=False, figures=False)
    trace = pd.read_csv(tmp_path / "trace.csv")
    mine = aocc_by_config(trace)
    dm = iohinspector.DataManager()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        dm.add_folder(str(tmp_path / "ioh"))
    y = trace["best_Mean"].to_numpy()
    y = y[np.isfinite(y)]
    ref = get_aocc(transform_fval(dm.load(monotonic=True, include_meta_data=True), lb=y.min(), ub=y.max()),
                   eval_max=int(trace["evaluations"].max()), free_vars=["algorithm_name"])
    ref = dict(zip(ref["algorithm_name"], ref["AOCC"]))
    assert set(mine) == set(ref) == {"uniform", "random", "swap", "greedy"}
    for config, value in ref.items():
        assert mine[config] == pytest.approx(value, rel=1e-12, abs=1e-12), config
    # the files carry it: stats.csv and table1.csv
    st = pd.read_csv(tmp_path / "stats.csv").set_index("config")
    t1 = pd.read_csv(tmp_path / "table1.csv").set_index("config")
    for config, value in ref.items():
        assert st.loc[config, "AOCC"] == pytest.approx(value) and t1.loc[config, "AOCC"] == pytest.approx(value)


def test_gap_closed_and_gap_to_best_known():
    runs = _runs({"full": [0.01], "uniform": [0.05], "a": [0.02, 0.04, 0.03]})
    s = stats_table(runs, best_known=0.02).set_index("config")
    assert s.loc["a", "gap_closed"] == pytest.approx((0.05 - 0.03) / (0.05 - 0.01))
    assert s.loc["a", "gap_to_best_known"] == pytest.approx(0.03 / 0.02 - 1)
    assert s.loc["uniform", "gap_closed"] == 0 and s.loc["full", "gap_closed"] == 1
    s = stats_table(_runs({"full": [0.01], "a": [0.02]})).set_index("config")
    assert s["gap_closed"].isna().all() and s["gap_to_best_known"].isna().all()


def test_expected_running_time_to_the_best_known_sums_every_runs_time_over_the_runs_that_reached_it():
    from arraysel.report.stats import ert_by_config, ert_column

    bk = 0.01
    rows = [  # config a: seed 0 reaches 10 % at 2 s and 2 % at 5 s (ends 10 s); seed 1 reaches 10 % at 3 s,
        # never 2 % (ends 12 s); config b: one run that reaches nothing (ends 7 s)
        ("a", 0, 1.0, 0.020, "improvement"), ("a", 0, 2.0, 0.0108, "improvement"),
        ("a", 0, 5.0, 0.01015, "improvement"), ("a", 0, 10.0, 0.01015, "end"),
        ("a", 1, 3.0, 0.0109, "improvement"), ("a", 1, 12.0, 0.0109, "end"),
        ("b", 0, 1.0, 0.5, "improvement"), ("b", 0, 7.0, 0.5, "end"),
    ]
    trace = pd.DataFrame([dict(zip(("config", "seed", "seconds", "best_Mean", "event"), r), evaluations=1,
                               gradient_steps=0) for r in rows])
    erts = ert_by_config(trace, bk)
    assert erts["a"][ert_column(0.10)] == pytest.approx((2.0 + 3.0) / 2)
    assert erts["a"][ert_column(0.03)] == pytest.approx((5.0 + 12.0) / 1)
    assert erts["a"][ert_column(0.02)] == pytest.approx((5.0 + 12.0) / 1)
    assert erts["a"][ert_column(0.01)] == math.inf and erts["b"][ert_column(0.10)] == math.inf
    assert ert_column(0.02) == "ERT_s_2pct" and ert_by_config(trace, None) == {} and ert_by_config(None, bk) == {}
    # stats.csv carries them; NaN without a best known or a trace
    runs = _runs({"a": [0.01015, 0.0109], "b": [0.5]})
    s = stats_table(runs, trace, best_known=bk).set_index("config")
    assert s.loc["a", "ERT_s_10pct"] == pytest.approx(2.5) and s.loc["b", "ERT_s_2pct"] == math.inf
    assert stats_table(runs, trace)[["ERT_s_1pct", "ERT_s_10pct"]].isna().all().all()
    assert stats_table(runs, None, best_known=bk)["ERT_s_2pct"].isna().all()
