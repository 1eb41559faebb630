"""Hostile cases, isolation without holes: a selector class a factory made (it does not pickle by
name) runs isolated through the ``--plugin`` file that registered it; one no child process can
load is refused unless ``--in-process``; a run in this process is stopped at its deadline; a
selector (or a plugin while it loads) that replaces ``numpy.mean`` / ``torch.mean`` cannot change
a table; a run without a time budget still has a deadline.

Each case asserts the exit code, the one line that says what happened, and the numbers: every
table computed as a process the plugin never touched computes it. The toy scene keeps each case
to seconds.
"""
from __future__ import annotations

import os
import textwrap
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch

from arraysel.errors import ParameterError
from support import own_plugin_manager, time_limit  # noqa: F401  (autouse fixtures)

FACTORY = str(Path(__file__).with_name("factory_plugin.py"))
HOSTILE = str(Path(__file__).parents[1] / "hostile_plugin.py")
_bounded = time_limit(120)  # fails, instead of hanging, a test longer than this


@pytest.fixture(autouse=True)
def true_reductions():
    """Whatever a case's plugin does to this process's numpy and torch is undone after it (and
    the case fails if anything was left replaced)."""
    from arraysel.run.guard import watched_reductions

    before = watched_reductions()
    yield
    assert before.restore() == [], "a function the tables use was left replaced"


def _compare(out, selectors, *extra, budget_s="5", evals="60", seeds="0"):
    from arraysel.cli.main import main

    args = ["compare", "--selectors", selectors, "--scene", "toy", "--budget-s", budget_s, "--seeds", seeds,
            "--out", str(out), "--no-progress", "--no-figures", "--plugin", FACTORY, *extra]
    if evals:
        args += ["--budget-evals", evals]
    return main(args)


def _runs(out) -> pd.DataFrame:
    return pd.read_csv(Path(out) / "runs.csv", keep_default_na=False).set_index("config")


def _true_aocc(out) -> dict:
    """Each config's AOCC computed here, where nothing was patched."""
    from arraysel.report.stats import aocc_by_config

    return aocc_by_config(pd.read_csv(Path(out) / "trace.csv"))


def _pids(path: Path) -> list[int]:
    return [int(p) for p in path.read_text().split()] if path.exists() else []


# ------------------------------------------------------------------ item 1: no silent wrong number
def test_a_factory_made_selector_runs_isolated_and_every_table_stays_true(tmp_path, capsys, monkeypatch):
    """Issue 77, item 1: before, ``patches_means`` ran in the arraysel process (a warning only)
    and halved random's AOCC in stats.csv and table1.csv, exit code 0."""
    pids = tmp_path / "pids"
    monkeypatch.setenv("ARRAYSEL_HOSTILE_PIDS", str(pids))
    out = tmp_path / "cmp"
    assert _compare(out, "patches_means,random") == 0
    err = capsys.readouterr().err
    assert "not isolated" not in err and "runs in this process" not in err
    assert _pids(pids) and os.getpid() not in _pids(pids)  # it ran in a child
    true = _true_aocc(out)
    stats = pd.read_csv(out / "stats.csv").set_index("config")
    table = pd.read_csv(out / "table1.csv").set_index("config")
    assert 0 < true["random"] < 1
    for config in ("random", "patches_means"):
        assert stats.loc[config, "AOCC"] == pytest.approx(true[config], rel=1e-12)
        assert table.loc[config, "AOCC"] == pytest.approx(true[config], rel=1e-12)
    runs = _runs(out)
    assert runs.loc["patches_means", "error"] == "" and runs.loc["random", "error"] == ""


def test_in_process_a_selector_that_replaces_the_reductions_stops_the_compare_with_true_tables(tmp_path, capsys):
    out = tmp_path / "cmp"
    assert _compare(out, "random,patches_means,uniform", "--in-process") == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith("arraysel compare: error: patches_means seed 0: the selector replaced numpy.mean "
                              "and torch.mean in this process")
    assert "without --in-process" in err[-1]
    assert np.mean(np.array([1.0, 3.0])) == 2.0 and float(torch.mean(torch.tensor([1.0, 3.0]))) == 2.0
    runs = _runs(out)
    assert list(runs.index) == ["full", "random", "patches_means"]  # nothing ran after it
    assert "replaced numpy.mean and torch.mean" in runs.loc["patches_means", "error"]
    stats = pd.read_csv(out / "stats.csv").set_index("config")
    assert stats.loc["random", "AOCC"] == pytest.approx(_true_aocc(out)["random"], rel=1e-12)


def test_a_plugin_that_replaces_a_reduction_while_it_loads_is_refused(tmp_path, capsys):
    plugin = tmp_path / "patcher.py"
    plugin.write_text(textwrap.dedent("""
        import numpy as np
        from arraysel.selectors.hookspecs import hookimpl

        _mean = np.mean
        np.mean = lambda *a, **kw: 0.5 * _mean(*a, **kw)

        @hookimpl
        def arraysel_register_selectors(register):
            pass
    """))
    out = tmp_path / "cmp"
    assert _compare(out, "uniform", "--plugin", str(plugin)) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"arraysel compare: error: --plugin {plugin} replaced numpy.mean "
                                               f"while it was loaded")
    assert np.mean(np.array([1.0, 3.0])) == 2.0
    assert not out.exists()


def test_a_selector_no_child_process_can_load_is_refused_unless_in_process(tmp_path):
    """A class registered by hand (no plugin a child can load) that does not pickle: refused
    before anything is written, naming it and the way to run it; isolate=False runs it."""
    from arraysel.objective.toy import ToyObjective
    from arraysel.run.compare import compare
    from arraysel.selectors.contract import Budget, Selector
    from arraysel.selectors.registry import SelectorRegistry

    def made():
        class Local(Selector):
            name = "local"
            description = "every second element"
            deterministic = True

            def select(self, objective, k, seed):
                return list(range(0, 2 * k, 2))
        return Local

    reg = SelectorRegistry()
    reg.register(made())
    out = tmp_path / "cmp"
    with pytest.raises(ParameterError) as err:
        compare(ToyObjective(16, 8), ["local"], out_dir=out, seeds=[0], budget=Budget(evaluations=5), registry=reg,
                isolate=True, progress=False, figures=False)
    msg = str(err.value)
    assert "selector 'local' cannot run isolated" in msg and "--in-process (isolate=False)" in msg
    assert "load it with --plugin" not in msg and "\n" not in msg
    assert not out.exists()
    res = compare(ToyObjective(16, 8), ["local"], out_dir=out, seeds=[0], budget=Budget(evaluations=5), registry=reg,
                  isolate=False, progress=False, figures=False)
    assert res.failures == () and list(res.selections["local"].indices) == list(range(0, 16, 2))


# ------------------------------------------------------------------ item 2: the hang
@pytest.mark.parametrize("extra", [[], ["--in-process"]], ids=["child", "in-process"])
def test_a_hanging_factory_selector_is_stopped_at_its_deadline(tmp_path, capsys, monkeypatch, extra):
    """Issue 77, item 2: before, ``sleepy`` ran in the arraysel process without a deadline and
    ``compare --budget-s 2 --grace-s 3`` ran until it was killed from outside."""
    pids = tmp_path / "pids"
    monkeypatch.setenv("ARRAYSEL_HOSTILE_PIDS", str(pids))
    out = tmp_path / "cmp"
    t0 = time.monotonic()
    code = _compare(out, "sleepy,uniform", "--grace-s", "1", *extra, budget_s="1", evals="")
    took = time.monotonic() - t0
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 1 and err[-1] == ("arraysel compare: 1 run(s) failed (see the error column of runs.csv): "
                                     "sleepy seed 0")
    runs = _runs(out)
    msg = runs.loc["sleepy", "error"]
    assert msg.startswith("run failed: BudgetExceededError: stopped after ") and \
        msg.endswith("the budget was 1 s and the grace period 1 s")
    assert runs.loc["uniform", "error"] == ""
    assert took < 60, took
    assert (os.getpid() in _pids(pids)) is bool(extra)  # in a child unless --in-process


# ------------------------------------------------------------------ item 7: no time budget, still a deadline
@pytest.mark.parametrize("extra", [[], ["--in-process"]], ids=["child", "in-process"])
def test_without_a_time_budget_a_hung_run_is_stopped_after_the_grace_period(tmp_path, capsys, extra):
    """Issue 77, item 7: ``--budget-s 0`` with an evaluation budget gave a hung run no deadline."""
    from arraysel.cli.main import main

    out = tmp_path / "cmp"
    t0 = time.monotonic()
    code = main(["compare", "--selectors", "ignores_budget,uniform", "--scene", "toy", "--budget-s", "0",
                 "--budget-evals", "50", "--grace-s", "2", "--seeds", "0", "--out", str(out), "--no-progress",
                 "--no-figures", "--plugin", HOSTILE, *extra])
    took = time.monotonic() - t0
    assert code == 1, capsys.readouterr().err
    runs = _runs(out)
    msg = runs.loc["ignores_budget", "error"]
    assert msg.startswith("run failed: BudgetExceededError: stopped after ")
    assert msg.endswith("the run had no time budget and a limit of 2 s (the grace period)")
    assert runs.loc["uniform", "error"] == "" and took < 60, took


def test_without_a_time_budget_the_default_limit_is_an_hour():
    from arraysel.run.compare import _Plan
    from arraysel.run.isolation import DEFAULT_GRACE_S, UNTIMED_LIMIT_S
    from arraysel.selectors.contract import Budget

    assert _Plan.of(["uniform"], [0], Budget(evaluations=10), None, None).grace == UNTIMED_LIMIT_S == 3600
    assert _Plan.of(["uniform"], [0], Budget(seconds=5), None, None).grace == DEFAULT_GRACE_S


# ------------------------------------------------------------------ the deadline itself
def test_a_deadline_interrupts_a_run_in_the_main_thread_and_in_another():
    import threading

    from arraysel.run.deadline import RunStopped, call_with_deadline

    def hang():
        while True:
            time.sleep(30)  # one long sleep: the signal wakes it

    t0 = time.monotonic()
    with pytest.raises(RunStopped) as err:
        call_with_deadline(hang, 0.3)
    assert 0.25 < err.value.elapsed < 10 and time.monotonic() - t0 < 10
    caught = []

    def in_thread():
        def spin():
            while True:
                time.sleep(0.01)
        try:
            call_with_deadline(spin, 0.3)
        except RunStopped as exc:
            caught.append(exc.elapsed)

    th = threading.Thread(target=in_thread)
    th.start()
    th.join(20)
    assert caught and 0.25 < caught[0] < 10
    assert call_with_deadline(lambda: 42, 0.2) == 42
    time.sleep(0.6)  # a finished run is never interrupted afterwards
