"""Known-answer tests of table1.csv (one run per row) and stats.csv (statistics over seeds)."""
from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest
from scipy import stats as sps

from arraysel.report.columns import ROW_COLUMNS, STATS_COLUMNS, TABLE1_COLUMNS, TABLE1_METRICS
from arraysel.report.stats import baseline_config, median_ci, rank_test, seed_statistics, stats_table
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


def test_bootstrap_ci_of_the_median_known_answers():
    # two values: the resampled median is a (1/4), (a+b)/2 (1/2) or b (1/4) -> the 95 % interval is [a, b]
    assert median_ci([1.0, 2.0])[:2] == (1.0, 2.0)
    assert median_ci([0.3, 0.3, 0.3]) == (0.3, 0.3, "")
    low, high, note = median_ci([0.5])
    assert math.isnan(low) and math.isnan(high) and "2 needed" in note
    v = [0.11, 0.15, 0.12, 0.30, 0.13, 0.14, 0.16]
    low, high, _ = median_ci(v)
    assert min(v) <= low <= np.median(v) <= high <= max(v) and low < high
    assert median_ci(v) == median_ci(v)          # a fixed seed: the same interval
    ref = sps.bootstrap((np.array(v),), np.median, confidence_level=0.95, n_resamples=9999, method="percentile",
                        rng=np.random.default_rng(0), vectorized=True, axis=-1).confidence_interval
    assert (low, high) == (ref.low, ref.high)


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
    assert "no confidence interval" in s.loc["full", "note"] and s.loc["a", "note"] == ""


def test_rank_test_without_random_is_nan_with_a_reason():
    s = stats_table(_runs({"a": [0.1, 0.2], "b": [0.3, 0.4]})).set_index("config")
    assert s["p_vs_random"].isna().all() and s["U_vs_random"].isna().all()
    assert (s["note"] == "no rank test: the comparison has no random configuration").all()
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
    assert s.loc["uniform", "note"].startswith("no confidence interval") and s.loc["ste", "note"] == ""
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
