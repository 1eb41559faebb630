"""Tests of arraysel.run.experiment / reporting: experiment rows, budgets, compare outputs, resume."""
from __future__ import annotations

import json
import math

import numpy as np
import pandas as pd
import pytest

from arraysel.cli.compare import build_objective
from arraysel.errors import ArrayselError, ParameterError
from arraysel.selectors.registry import SelectorRegistry, build_plugin_manager, get_registry
from arraysel.report.columns import ROW_COLUMNS, STATS_COLUMNS, TABLE1_COLUMNS, TRACE_COLUMNS
from arraysel.run.compare import compare
from arraysel.run.experiment import Experiment
from arraysel.selectors.contract import Budget, BudgetExceededError, Option, Selector, check_selection
from arraysel.testing import ToyObjective


@pytest.fixture(scope="module")
def reg():
    return get_registry(build_plugin_manager(load_entrypoints=False, disabled=()))


class Broken(Selector):
    name = "broken"
    description = "raises"

    def select(self, objective, k, seed):
        raise RuntimeError("selector exploded")


class Repeats(Selector):
    name = "repeats"
    description = "returns an invalid selection"

    def select(self, objective, k, seed):
        return [0] * k


class Greedy4Budget(Selector):
    name = "hog"
    description = "ignores its budget"

    def batch_size(self, n_elements, k):
        return 4

    def select(self, objective, k, seed):
        # past the budgeted view (which would stop at the budget), on the objective it wraps
        objective._inner.evaluate(np.ones((100, objective.n_elements), dtype=bool))
        return list(range(k))


class Interrupts(Selector):
    name = "interrupts"
    description = "Ctrl-C on seed 1"
    options = {"when": Option(int, 1, "seed that interrupts", lo=0)}

    def select(self, objective, k, seed):
        if seed == self.options["when"]:
            raise KeyboardInterrupt
        return list(range(k))


def test_uniform_row_has_fixed_columns_and_every_second_element(reg):
    obj = ToyObjective(64, 32)
    exp = Experiment(obj, "uniform", budget=Budget(evaluations=5), registry=reg)
    row = exp.run()
    assert tuple(row) == ROW_COLUMNS
    assert row["elements"] == " ".join(str(i) for i in range(0, 64, 2))
    assert row["error"] == "" and math.isfinite(row["Mean"])
    assert row["evaluations"] == 1 and row["config"] == "uniform"
    assert row["overhead_seconds"] >= 0


def test_random_n1_is_a_random_mask_chosen_once(reg):
    obj = ToyObjective(16, 8)
    row = Experiment(obj, "random", options={"n": 1}, budget=Budget(evaluations=100), registry=reg).run()
    assert row["evaluations"] == 1 and row["config"] == "random(n=1)"
    assert len(row["elements"].split()) == 8


def test_random_is_independent_of_chunking(reg):
    rows = [Experiment(ToyObjective(16, 8), "random", options={"chunk": c}, seed=4,
                       budget=Budget(evaluations=300), registry=reg).run() for c in (1, 7, 1024)]
    assert len({r["elements"] for r in rows}) == 1


def test_greedy_finds_the_toy_target(reg):
    obj = ToyObjective(16, 8)
    row = Experiment(obj, "greedy", budget=Budget(evaluations=1000), registry=reg).run()
    assert row["elements"] == " ".join(map(str, obj.target))


@pytest.mark.parametrize("cls,message", [(Broken, "RuntimeError: selector exploded"),
                                         (Repeats, "SelectionError: selection repeats")])
def test_selector_failures_land_in_the_error_column(cls, message):
    row = Experiment(ToyObjective(12, 4), cls, budget=Budget(evaluations=10)).run()
    assert row["error"].startswith(message)
    assert row["elements"] == "" and math.isnan(row["Mean"])


def test_budget_overrun_raises():
    with pytest.raises(BudgetExceededError, match="used 100 objective evaluations"):
        Experiment(ToyObjective(12, 4), Greedy4Budget, budget=Budget(evaluations=10)).run()
    # within one batch of slack is accepted
    row = Experiment(ToyObjective(12, 4), Greedy4Budget, budget=Budget(evaluations=96)).run()
    assert row["error"] == ""


def test_options_and_k_are_validated(reg):
    with pytest.raises(ParameterError, match="has no option"):
        Experiment(ToyObjective(12, 4), "ste", options={"nope": 1}, registry=reg).run()
    with pytest.raises(ParameterError, match="out of range"):
        Experiment(ToyObjective(12, 4), "ste", options={"lr": -1.0}, registry=reg).run()
    with pytest.raises(ParameterError, match="k = 13"):
        Experiment(ToyObjective(12, 4), "uniform", k=13, registry=reg).run()


def test_check_selection():
    assert check_selection(np.array([3, 1]), 4, 2) == [1, 3]
    for bad, msg in [([1, 1], "repeats"), ([0, 9], "outside"), ([0], "expected k"), ([0.5, 1], "non-integer"),
                     ("01", "list of element")]:
        with pytest.raises(Exception, match=msg):
            check_selection(bad, 4, 2)


def test_budget_queries():
    obj = ToyObjective(8, 4)
    b = Budget(evaluations=10).start(obj)
    assert b.allowed(4) == 4 and not b.exhausted()
    obj.evaluate(np.ones((8, 8), dtype=bool))
    assert b.remaining_evaluations() == 2 and b.allowed(4) == 2
    obj.evaluate(np.ones((2, 8), dtype=bool))
    assert b.exhausted() and b.allowed(4) == 0 and b.fraction() == 1.0
    with pytest.raises(ParameterError):
        Budget(seconds=-1)
    with pytest.raises(ArrayselError, match="before start"):
        Budget(seconds=1).exhausted()


def test_compare_writes_all_files(reg, tmp_path):
    obj = ToyObjective(16, 8)
    table = compare(obj, ["ste", "random", "uniform"], out_dir=tmp_path, seeds=[0, 1],
                    budget=Budget(evaluations=60, seconds=10), registry=reg, progress=False,
                    command_line=["arraysel", "compare"]).table
    names = {p.name for p in tmp_path.iterdir()}
    assert {"table1.csv", "stats.csv", "runs.csv", "trace.csv", "ioh", "run.json", "masks.png",
            "psfs.png", "profiles.png", "trace.png", "anytime.png"} <= names
    assert not [n for n in names if n.endswith(".tmp")]
    t1 = pd.read_csv(tmp_path / "table1.csv", keep_default_na=False)
    assert list(t1.columns[:9]) == ["config", "L_PSF", "L_contrast", "L_SLR_q", "L_SLR_i", "Mean", "seconds",
                                    "evaluations", "elements"]
    assert tuple(t1.columns) == TABLE1_COLUMNS
    assert tuple(pd.read_csv(tmp_path / "stats.csv").columns) == STATS_COLUMNS
    assert list(t1["config"]) == ["full", "ste", "random", "uniform"]
    assert t1.set_index("config").loc["full", "elements"] == " ".join(map(str, range(16)))
    assert list(table["config"]) == list(t1["config"])
    runs = pd.read_csv(tmp_path / "runs.csv")
    # full, ste and random per seed, uniform once (deterministic)
    assert tuple(runs.columns) == ROW_COLUMNS and len(runs) == 6
    trace = pd.read_csv(tmp_path / "trace.csv")
    assert tuple(trace.columns) == TRACE_COLUMNS and set(trace["config"]) == {"ste", "random", "uniform"}
    for _, g in trace.groupby(["config", "seed"]):
        # improvements strictly decrease; the run ends with one `end` row at its last evaluation
        assert list(g["event"]) == ["improvement"] * (len(g) - 1) + ["end"]
        assert (np.diff(g["best_Mean"].iloc[:-1]) < 0).all()
        assert g["best_Mean"].iloc[-1] == g["best_Mean"].min()
        assert g["evaluations"].iloc[-1] >= g["evaluations"].iloc[:-1].max()
    assert {p.name for p in (tmp_path / "ioh").iterdir()} == {"ste", "random", "uniform"}
    meta = json.loads((tmp_path / "run.json").read_text())
    assert meta["status"] == "finished" and meta["seeds"] == [0, 1]
    assert meta["scene"]["name"] == "toy" and meta["command_line"] == ["arraysel", "compare"]
    assert {"arraysel", "torch", "numpy", "python"} <= set(meta["versions"])
    assert meta["figure_errors"] == []


def test_single_seed_has_no_std_columns(reg, tmp_path):
    compare(ToyObjective(12, 6), ["uniform"], out_dir=tmp_path, budget=Budget(evaluations=5),
            registry=reg, progress=False, figures=False)
    t1 = pd.read_csv(tmp_path / "table1.csv")
    assert not [c for c in t1.columns if c.endswith("_std")]


def test_failing_selector_keeps_the_comparison_going(tmp_path):
    reg = SelectorRegistry()
    reg.register(Broken)
    reg.register(get_registry(build_plugin_manager(load_entrypoints=False, disabled=()))["uniform"])
    compare(ToyObjective(12, 6), ["broken", "uniform"], out_dir=tmp_path, budget=Budget(evaluations=5),
            registry=reg, progress=False, figures=False)
    t1 = pd.read_csv(tmp_path / "table1.csv", keep_default_na=False).set_index("config")
    assert "selector exploded" in t1.loc["broken", "error"] and t1.loc["uniform", "error"] == ""


def test_interrupt_keeps_finished_rows_and_resume_finishes(tmp_path, capsys):
    reg = SelectorRegistry()
    reg.register(Interrupts)
    obj = ToyObjective(12, 6)
    with pytest.raises(KeyboardInterrupt):
        compare(obj, ["interrupts"], out_dir=tmp_path, seeds=[0, 1, 2], budget=Budget(evaluations=5),
                registry=reg, progress=False, figures=False)
    assert "--resume" in capsys.readouterr().err
    runs = pd.read_csv(tmp_path / "runs.csv")
    assert list(runs["config"]) == ["full", "interrupts"] and list(runs["seed"].dropna()) == [0]
    assert json.loads((tmp_path / "run.json").read_text())["status"] == "interrupted"
    compare(obj, [("interrupts", {"when": 99})], out_dir=tmp_path, seeds=[0, 1, 2],
            budget=Budget(evaluations=5), registry=reg, progress=False, figures=False, resume=True)
    # the option changes the config label, so all three seeds of the new config run
    runs = pd.read_csv(tmp_path / "runs.csv")
    assert sorted(runs[runs["config"] == "interrupts(when=99)"]["seed"]) == [0, 1, 2]


def test_resume_skips_finished_runs(reg, tmp_path):
    obj = ToyObjective(12, 6)
    compare(obj, ["random"], out_dir=tmp_path, seeds=[0], budget=Budget(evaluations=5), registry=reg,
            progress=False, figures=False)
    before = obj.evaluations
    compare(obj, ["random"], out_dir=tmp_path, seeds=[0, 1], budget=Budget(evaluations=5), registry=reg,
            progress=False, figures=False, resume=True)
    runs = pd.read_csv(tmp_path / "runs.csv")
    assert sorted(runs["seed"].dropna()) == [0, 1]
    resumed = obj.evaluations - before
    # what a compare of seed 1 alone costs (full row, the run, its final evaluation): seed 0 is not rerun
    before = obj.evaluations
    compare(obj, ["random"], out_dir=tmp_path / "one", seeds=[1], budget=Budget(evaluations=5), registry=reg,
            progress=False, figures=False)
    assert resumed == obj.evaluations - before


def test_compare_rejects_unknown_selectors(reg, tmp_path):
    with pytest.raises(ParameterError, match="known selectors"):
        compare(ToyObjective(12, 6), ["nope"], out_dir=tmp_path, registry=reg, progress=False)


def test_toy_scene_builds_the_toy_objective():
    assert build_objective("toy", "cpu", "float64").n_elements == 64


def test_toy_objective_contract():
    import torch
    obj = ToyObjective(10, 5, dtype=torch.float64)
    m = np.zeros((3, 10), dtype=bool)
    m[:, obj.target] = True
    m[1] = True
    out = obj.evaluate(m)
    assert set(out) == set(obj.metric_names) and all(v.dtype == np.float64 and v.shape == (3,) for v in out.values())
    assert out["L_PSF"][0] == 0.0 and obj.evaluations == 3 and obj.gradient_steps == 0
    assert math.isnan(obj.evaluate(np.zeros((1, 10)))["Mean"][0])
    w = torch.full((2, 10), 0.5, dtype=torch.float64, requires_grad=True)
    total, terms = obj.mask_loss(w)
    assert total.shape == (2,) and obj.gradient_steps == 1 and obj.evaluations == 6
    total.sum().backward()
    assert torch.isfinite(w.grad).all()
    assert torch.autograd.gradcheck(lambda x: obj.mask_loss(x)[0], (w.detach().clone().requires_grad_(),),
                                    eps=1e-6, atol=1e-5)
    assert obj.kernels(m).shape == (3, 128, 128) and obj.reference_kernel().shape == (128, 128)
    assert obj.seconds > 0


def test_run_progress_bar_counts_the_evaluations(reg, capsys):
    """The in-run bar follows the budget's counters; its total is the random selector's n."""
    exp = Experiment(ToyObjective(16, 8), "random", options={"n": 300, "chunk": 64}, seed=1,
                     budget=Budget(evaluations=1000), registry=reg, progress=True)
    row = exp.run()
    assert row["evaluations"] == 300 and row["error"] == ""
    err = capsys.readouterr().err
    assert "300/300" in err and "best Mean" in err
    # the same run without the bar gives the same row (the bar only reads counters)
    quiet = Experiment(ToyObjective(16, 8), "random", options={"n": 300, "chunk": 64}, seed=1,
                       budget=Budget(evaluations=1000), registry=reg).run()
    assert quiet["elements"] == row["elements"] and quiet["Mean"] == row["Mean"]


def test_nlopt_restarts_use_the_budget_and_stay_reproducible(reg):
    pytest.importorskip("nlopt")

    def run(**opts):
        return Experiment(ToyObjective(16, 8), "nlopt", options=opts, seed=3,
                          budget=Budget(evaluations=600), registry=reg).run()

    once = run(restarts=0)
    many = run()
    again = run()
    assert once["error"] == "" and many["error"] == ""
    assert many["evaluations"] > once["evaluations"]          # the restarts spend the budget
    assert many["evaluations"] <= 600 + 2
    assert many["Mean"] <= once["Mean"] + 1e-12               # the first run is the same, best kept
    assert (many["elements"], many["Mean"]) == (again["elements"], again["Mean"])
