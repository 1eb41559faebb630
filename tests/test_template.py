"""Tests of arraysel.run.template: warm templates and the runs forked from them, threads per
worker, and the budget flag of a run's row."""
from __future__ import annotations

import math
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from arraysel.objective.toy import ToyObjectiveFactory
from arraysel.run.experiment import Experiment, budget_flag, late_start_flag
from arraysel.run.template import WarmTemplate, run_with_retries, threads_per_worker, warm_objective
from arraysel.run.workers import TaskFailed
from arraysel.selectors.contract import Budget, Option, Selector
from support import time_limit

_bounded = time_limit(120)


def _who(objective, item):
    """pid, parent pid, torch threads, and the objective's evaluations so far (then one more)."""
    import torch
    before = int(objective.evaluations)
    objective.evaluate(np.ones((1, objective.n_elements), dtype=bool))
    return {"pid": os.getpid(), "ppid": os.getppid(), "threads": torch.get_num_threads(), "evaluations": before,
            "item": item}


def _edit(objective, item):
    objective.evaluate = None  # a hostile run: changes the objective in its own process
    return "edited"


def _hang(objective, item):
    time.sleep(60)


def _kill_template(objective, item):
    os.kill(os.getppid(), signal.SIGKILL)
    time.sleep(30)


def _exit(objective, item):
    os._exit(5)


@pytest.fixture
def template():
    t = WarmTemplate(ToyObjectiveFactory(16, 8), threads=1)
    yield t
    t.close()


def test_runs_fork_from_one_warm_template(template):
    first = template.run(_who, 1)
    second = template.run(_who, 2)
    info = template.info
    assert first["ppid"] == second["ppid"] == info["pid"]  # children of the one template
    assert first["pid"] != second["pid"] and first["pid"] != os.getpid()
    # the template warmed the objective; each run starts from that state, not from the other run's
    assert first["evaluations"] == second["evaluations"] > 0
    assert info["warm_steps"][:3] == ["evaluate(1)", "evaluate(8)", "evaluate(64)"] and not info["warm_error"]
    assert info["ready_s"] >= info["warm_s"] >= 0 and info["threads"] == 1
    assert template.warm_ups == [info]


def test_a_run_that_edits_the_objective_changes_nothing_for_the_next(template):
    assert template.run(_edit, 0) == "edited"
    assert template.run(_who, 0)["evaluations"] > 0  # evaluate() still there


def test_a_hung_run_is_stopped_at_its_deadline_and_the_template_goes_on(template):
    t0 = time.monotonic()
    res = template.run(_hang, 0, timeout=1.0)
    assert isinstance(res, TaskFailed) and res.kind == "timeout" and "did not return in time" in res.message
    assert time.monotonic() - t0 < 30
    assert template.run(_who, 0)["ppid"] == template.info["pid"]
    assert len(template.warm_ups) == 1  # the same template: not warmed again


def test_a_run_that_exits_or_kills_its_template_costs_only_its_result(template):
    res = template.run(_exit, 0)
    assert isinstance(res, TaskFailed) and res.kind == "died" and "exit code 5" in res.message
    res = template.run(_kill_template, 0)
    assert isinstance(res, TaskFailed) and res.kind == "died" and "template" in res.message
    again = template.run(_who, 0)  # a new template, warmed again
    assert again["ppid"] == template.info["pid"] and len(template.warm_ups) == 2
    res = run_with_retries(template, _exit, 0, None, retries=1)
    assert isinstance(res, TaskFailed) and res.attempts == 2 and "2 attempt(s)" in res.message


def test_each_run_gets_the_templates_threads():
    t = WarmTemplate(ToyObjectiveFactory(16, 8), threads=2)
    try:
        assert t.run(_who, 0)["threads"] == 2 and t.info["threads"] == 2
    finally:
        t.close()


def test_a_broken_factory_fails_the_run_with_its_reason():
    t = WarmTemplate(ToyObjectiveFactory(0, 8), threads=1)
    try:
        res = t.run(_who, 0)
        assert isinstance(res, TaskFailed) and res.kind == "failed" and "could not be built" in res.message
    finally:
        t.close()


def test_warm_objective_reports_its_steps_and_errors():
    obj = ToyObjectiveFactory(16, 8)()
    info = warm_objective(obj)
    assert "evaluate(64)" in info["warm_steps"] and info["warm_error"] == ""
    obj2 = ToyObjectiveFactory(16, 8, fail_after=0)()
    bad = warm_objective(obj2)
    assert "evaluate(1)" in bad["warm_error"] and "evaluate(1)" not in bad["warm_steps"]


def test_threads_per_worker_shares_the_cores():
    assert threads_per_worker(2, cores=2) == 1 and threads_per_worker(2, cores=16) == 8
    assert threads_per_worker(1, cores=4) == 4 and threads_per_worker(8, cores=2) == 1


def test_no_semaphore_is_left_to_the_resource_tracker(tmp_path):
    """Runs that end, time out or crash leave no named semaphore behind (numba's lock is made in
    the template, which releases it when it ends)."""
    code = (
        "import sys; sys.path.insert(0, %r)\n"
        "from test_template import _who, _hang, _exit\n"
        "from arraysel.objective.toy import ToyObjectiveFactory\n"
        "from arraysel.run.template import WarmTemplate\n"
        "if __name__ == '__main__':\n"
        "    t = WarmTemplate(ToyObjectiveFactory(16, 8), threads=1)\n"
        "    t.run(_who, 0); t.run(_hang, 0, timeout=0.5); t.run(_exit, 0); t.run(_who, 0)\n"
        "    t.close()\n" % os.path.dirname(__file__))
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=100, cwd=tmp_path)
    assert out.returncode == 0, out.stderr
    assert "leaked" not in out.stderr, out.stderr


def _row(seconds, error="", flag=""):
    return {"seconds": seconds, "error": error, "budget_flag": flag}


def test_budget_flag_says_when_the_budget_did_not_measure_the_search():
    b = Budget(seconds=10)
    assert budget_flag(_row(10.2), b, 30) == ""
    assert budget_flag(_row(41.0), b, 30).startswith("overran: 41.0 s of a 10 s budget")
    killed = budget_flag(_row(math.nan, "run failed: BudgetExceededError: stopped after 40.1 s (its limit ...)"), b, 30)
    assert killed.startswith("overran: stopped at its deadline")
    late = late_start_flag(7.5, b)
    assert late.startswith("late start: its first objective call came 7.5 s") and late_start_flag(4.0, b) == ""
    assert budget_flag(_row(41.0, flag=late), b, 30).endswith("; " + late)  # the run's own flag is kept
    assert budget_flag(_row(500.0, flag=late), Budget(evaluations=10), 30) == ""
    assert late_start_flag(None, b) == "" and late_start_flag(9.0, Budget(evaluations=5)) == ""


class _SlowStart(Selector):
    """Spends ``wait`` seconds before its first objective call, then scores one uniform layout."""
    name = "slow-start"
    options = {"wait": Option(float, 0.0, "seconds to wait before searching")}

    def select(self, objective, k, seed):
        time.sleep(self.options["wait"])
        mask = np.zeros(objective.n_elements, dtype=bool)
        mask[:k] = True
        objective.score(mask[None, :])
        return list(range(k))


@pytest.mark.parametrize("wait, late", [(0.0, False), (0.7, True)])
def test_a_run_that_starts_its_search_late_is_flagged(wait, late):
    objective = ToyObjectiveFactory(n_elements=8, k=3)()
    row = Experiment(objective, _SlowStart, {"wait": wait}, Budget(seconds=1.0)).run()
    assert row["error"] == ""
    if late:
        assert row["budget_flag"].startswith("late start: its first objective call came 0.")
        assert budget_flag(row, Budget(seconds=1.0), 30) == row["budget_flag"]  # compare keeps it
    else:
        assert row["budget_flag"] == ""


def test_a_template_that_ended_between_runs_is_replaced(template):
    first = template.run(_who, 0)
    os.kill(template.info["pid"], signal.SIGKILL)
    template.proc.join(10)
    again = template.run(_who, 0)
    assert again["ppid"] != first["ppid"] and len(template.warm_ups) == 2


class _ThreadProbe(Selector):
    """Records the torch and numba thread counts its run sees (in this process)."""
    name = "thread_probe"
    description = "records thread counts"
    seen: list = []

    def select(self, objective, k, seed):
        import numba
        import torch
        type(self).seen.append((torch.get_num_threads(), numba.get_num_threads()))
        return list(range(k))


def test_a_run_in_this_process_gets_the_threads_asked_for_and_they_are_restored_after(tmp_path):
    """``--in-process --threads 1``: each run (and the warm-up) has one torch and one numba thread;
    the counts the process had are back after the comparison."""
    import numba
    import torch

    from arraysel.objective.toy import ToyObjective
    from arraysel.run.compare import compare
    from arraysel.selectors.registry import SelectorRegistry

    if int(numba.config.NUMBA_NUM_THREADS) < 2:
        pytest.skip("numba has one thread here: nothing to restrict")
    reg = SelectorRegistry()
    reg.register(_ThreadProbe)
    before = torch.get_num_threads(), numba.get_num_threads()
    torch.set_num_threads(2)
    numba.set_num_threads(2)
    _ThreadProbe.seen.clear()
    try:
        compare(ToyObjective(16, 8), ["thread_probe"], out_dir=tmp_path, seeds=[0, 1], budget=Budget(evaluations=5),
                registry=reg, progress=False, figures=False, isolate=False, threads=1)
        assert _ThreadProbe.seen == [(1, 1), (1, 1)]
        assert (torch.get_num_threads(), numba.get_num_threads()) == (2, 2)
        _ThreadProbe.seen.clear()  # without threads: the runs see the process's own counts
        compare(ToyObjective(16, 8), ["thread_probe"], out_dir=tmp_path, seeds=[0], budget=Budget(evaluations=5),
                registry=reg, progress=False, figures=False, isolate=False, force=True)
        assert _ThreadProbe.seen == [(2, 2)]
    finally:
        torch.set_num_threads(before[0])
        numba.set_num_threads(before[1])
