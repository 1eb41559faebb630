"""``compare`` returns a CompareResult (the tables it wrote, each run's Selection, the failures);
its run modes are interchangeable runners; its store forms a selection's text at the file edge."""
from __future__ import annotations

import json
import math

import pandas as pd
import pytest

from arraysel.report.tables import read_runs
from arraysel.run.compare import CompareResult, compare
from arraysel.run.runners import InProcessRunner, IsolatedRunner, RunSpec, failure_row, make_runner
from arraysel.run.store import CompareStore, file_row
from arraysel.run.workers import TaskFailed
from arraysel.selection import Selection
from arraysel.selectors.contract import Budget, BudgetExceededError, Selector
from arraysel.selectors.registry import SelectorRegistry, build_plugin_manager, get_registry
from arraysel.testing import ToyObjective


class Broken(Selector):
    name = "broken"
    description = "raises"

    def select(self, objective, k, seed):
        raise RuntimeError("selector exploded")


@pytest.fixture(scope="module")
def reg():
    base = get_registry(build_plugin_manager(load_entrypoints=False, disabled=()))
    reg = SelectorRegistry()
    for name in ("uniform", "random"):
        reg.register(base[name])
    reg.register(Broken)
    return reg


@pytest.mark.parametrize("isolate", [False, True], ids=["in-process", "isolated"])
def test_the_result_is_what_the_files_hold(reg, tmp_path, isolate):
    obj = ToyObjective(16, 8)
    res = compare(obj, ["uniform", "random", "broken"], out_dir=tmp_path, seeds=[0, 1],
                  budget=Budget(evaluations=20), registry=reg, progress=False, figures=False, isolate=isolate)
    assert isinstance(res, CompareResult) and res.out_dir == str(tmp_path)
    t1 = pd.read_csv(tmp_path / "table1.csv", keep_default_na=False, na_values=["", "nan", "NaN"])
    assert list(res.table["config"]) == list(t1["config"]) == ["full", "uniform", "random", "broken"]
    for col in ("Mean", "L_PSF", "AOCC", "seed", "seeds"):
        pd.testing.assert_series_equal(pd.to_numeric(res.table[col], errors="coerce"), t1[col].astype(float),
                                       check_dtype=False, check_names=False)
    assert list(res.table["elements"].fillna("")) == list(t1["elements"].fillna(""))
    pd.testing.assert_frame_equal(res.runs, read_runs(tmp_path / "runs.csv"), check_dtype=False)
    stats = pd.read_csv(tmp_path / "stats.csv")
    assert list(res.stats.columns) == list(stats.columns)
    pd.testing.assert_series_equal(res.stats["Mean_median"], stats["Mean_median"], check_dtype=False)
    assert len(res.trace) == len(pd.read_csv(tmp_path / "trace.csv"))
    # the selections: each config's listed one (full: every element), each run's own
    by = t1.set_index("config")
    assert set(res.selections) == {"full", "uniform", "random", "broken"}
    for config, sel in res.selections.items():
        assert isinstance(sel, Selection) and sel.text == (by.loc[config, "elements"] if config != "broken" else "")
    assert res.selections["full"] == Selection(tuple(range(16)), 16) and len(res.selections["broken"]) == 0
    assert set(res.run_selections) == {("uniform", 0), ("random", 0), ("random", 1)}
    assert all(len(s) == 8 for s in res.run_selections.values())
    failed = json.loads((tmp_path / "run.json").read_text())["failed_runs"]
    assert list(res.failures) == failed == ["broken seed 0", "broken seed 1"]
    with pytest.raises(AttributeError):
        res.table = None  # frozen


def test_resume_reads_each_selection_back_once(reg, tmp_path):
    obj = ToyObjective(8, 1)  # one element: "5" in runs.csv must stay a selection, not a number
    first = compare(obj, ["random"], out_dir=tmp_path, seeds=[0], budget=Budget(evaluations=5), registry=reg,
                    progress=False, figures=False)
    text = read_runs(tmp_path / "runs.csv").set_index("config").loc["random", "elements"]
    assert len(text.split()) == 1
    again = compare(obj, ["random"], out_dir=tmp_path, seeds=[0, 1], budget=Budget(evaluations=5), registry=reg,
                    progress=False, figures=False, resume=True)
    assert again.run_selections[("random", 0)] == first.run_selections[("random", 0)]
    assert again.run_selections[("random", 0)].text == text
    runs = read_runs(tmp_path / "runs.csv")
    assert list(runs.loc[runs["config"] == "random", "seed"]) == [0, 1]
    assert runs.loc[(runs["config"] == "random") & (runs["seed"] == 0), "elements"].item() == text


def test_the_store_forms_and_reads_the_text(tmp_path):
    row = {"config": "a", "elements": Selection((4, 0, 2), 8)}
    assert file_row(row)["elements"] == "0 2 4" and row["elements"] == Selection((0, 2, 4), 8)
    assert file_row({"elements": None})["elements"] == ""
    store = CompareStore(tmp_path, Budget(evaluations=1), None)
    assert store.previous(8) == ([], [])  # no runs.csv yet
    (tmp_path / "runs.csv").write_text("config,seed\nx,0\n")
    with pytest.raises(Exception, match="damaged"):
        store.previous(8)


def test_failure_rows_are_made_in_one_place():
    obj = ToyObjective(12, 6)
    spec = RunSpec("uniform", get_registry()["uniform"], {"a": 1}, 3)
    budget = Budget(seconds=5.0)
    over = failure_row(obj, spec, BudgetExceededError("too many"), budget, 2.0)
    assert over["error"] == "BudgetExceededError: too many" and over["elements"] is None
    assert over["seed"] == 3 and over["options"] == '{"a": 1}' and math.isnan(over["Mean"])
    lost = failure_row(obj, spec, BudgetExceededError("too many"), budget, 2.0, lost=True)
    assert lost["error"] == "run lost: BudgetExceededError: too many"
    timeout = failure_row(obj, spec, TaskFailed("stopped after 7 s", kind="timeout"), budget, 2.0)
    assert timeout["error"] == ("run failed: BudgetExceededError: stopped after 7 s; the budget was 5 s and the "
                                "grace period 2 s")
    died = failure_row(obj, spec, TaskFailed("exit code 3", kind="died"), budget, 2.0)
    assert died["error"] == "run failed: exit code 3"
    assert set(over) == set(lost) == set(timeout) == set(died)


def test_the_runners_are_interchangeable():
    obj = ToyObjective(12, 6)
    budget = Budget(evaluations=10)
    todo = [RunSpec("uniform", get_registry()["uniform"], {}, 0), RunSpec("random", get_registry()["random"], {}, 1)]
    here = make_runner(obj, budget, 1.0, math.nan)
    away = make_runner(obj, budget, 30.0, math.nan, isolate=True)
    assert isinstance(here, InProcessRunner) and isinstance(away, IsolatedRunner)
    got = {}
    for name, runner in (("here", here), ("away", away)):
        runner.prepare(todo)
        try:
            got[name] = [(i, row["elements"], row["Mean"], row["error"]) for i, row, _ in runner.run(todo)]
        finally:
            runner.close()
    assert [g[0] for g in got["here"]] == [0, 1]
    assert got["here"] == got["away"]
    assert all(isinstance(g[1], Selection) for g in got["here"])
