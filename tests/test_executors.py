"""Tests of arraysel.run.executors: process pool and Dask executors for compare and random search.

Workers are local processes; the Dask cluster listens on 127.0.0.1 only. Every
test is bounded by an alarm (``TEST_LIMIT_S``). Selectors that kill their
worker (``os._exit``) refuse to do so in the pytest process itself.
"""
from __future__ import annotations

import os
import pickle
import sys

import numpy as np
import pandas as pd
import pytest

from arraysel.errors import ArrayselError, ParameterError
from arraysel.objective.toy import ToyObjectiveFactory
from arraysel.run.executors import LocalExecutor, ProcessExecutor, TaskFailed, make_executor
from arraysel.run.random_search import distributed_evaluate, distributed_random_search
from arraysel.selectors.starts import random_subsets
from arraysel.run.workers import objective_factory_for
from arraysel.selectors.registry import SelectorRegistry, build_plugin_manager, get_registry
from arraysel.report.columns import ROW_COLUMNS
from arraysel.run.compare import compare
from arraysel.selectors.contract import Budget, Option, Selector, numpy_rng
from arraysel.testing import ToyObjective
from support import time_limit

TEST_LIMIT_S = 60
# the pytest process; workers inherit the variable and must not overwrite it
os.environ.setdefault("ARRAYSEL_TEST_PARENT_PID", str(os.getpid()))


def _die():
    if str(os.getpid()) == os.environ.get("ARRAYSEL_TEST_PARENT_PID"):
        raise RuntimeError("refusing to kill the test process")
    sys.stdout.flush()
    os._exit(3)


class BestOfBatch(Selector):
    """Deterministic: best of one batch of 40 random masks."""

    name = "best_of_batch"
    description = "best of 40 random masks, scored in one call"
    options = {"marker": Option(str, "", "crash the worker once unless this file exists")}
    deterministic = True

    def batch_size(self, n_elements, k):
        return 40

    def select(self, objective, k, seed):
        marker = self.options["marker"]
        if marker and not os.path.exists(marker):
            with open(marker, "w") as fh:
                fh.write(str(os.getpid()))
            _die()
        n = int(objective.n_elements)
        subsets = random_subsets(numpy_rng(seed), 40, n, k)
        masks = np.zeros((40, n), dtype=bool)
        np.put_along_axis(masks, subsets, True, axis=1)
        means = objective.evaluate(masks)["Mean"]
        return subsets[int(np.argmin(means))].tolist()


class AlwaysCrash(Selector):
    name = "always_crash"
    description = "kills its worker every time"

    def select(self, objective, k, seed):
        _die()


_bounded = time_limit(TEST_LIMIT_S)  # fails, instead of hanging, a test longer than this


@pytest.fixture(scope="module")
def reg():
    base = get_registry(build_plugin_manager(load_entrypoints=False, disabled=()))
    r = SelectorRegistry()
    for name in ("uniform", "random", "greedy"):
        r.register(base[name])
    r.register(BestOfBatch)
    r.register(AlwaysCrash)
    return r


SELECTORS = [("random", {"n": 150}), "uniform", "greedy", "best_of_batch"]
BUDGET = Budget(evaluations=150, seconds=30)


def _run(tmp, reg, executor=None, selectors=SELECTORS, seeds=(0, 1)):
    table = compare(ToyObjective(16, 8), selectors, out_dir=tmp, seeds=list(seeds), budget=BUDGET,
                    registry=reg, progress=False, figures=False, executor=executor).table
    runs = pd.read_csv(tmp / "runs.csv", keep_default_na=False)
    trace = pd.read_csv(tmp / "trace.csv", keep_default_na=False)
    return table, runs, trace


def _same(a: pd.DataFrame, b: pd.DataFrame):
    """Equal but for timing columns; floats to 1e-6 (the `random` selector sizes its batches from
    measured times, so batched float32 sums may differ in the last bits between any two runs)."""
    cols = [c for c in a.columns if "seconds" not in c]
    assert list(a.columns) == list(b.columns) and len(a) == len(b)
    for c in cols:
        x, y = a[c], b[c]
        if pd.api.types.is_float_dtype(x) and pd.api.types.is_float_dtype(y):
            np.testing.assert_allclose(x.to_numpy(), y.to_numpy(), rtol=1e-6, equal_nan=True, err_msg=c)
        else:
            assert list(x.astype(str)) == list(y.astype(str)), c


@pytest.fixture(scope="module")
def local_reference(reg, tmp_path_factory):
    return _run(tmp_path_factory.mktemp("local"), reg)


# ---------------------------------------------------------------------------
# no workers needed
# ---------------------------------------------------------------------------

def test_make_executor_checks_arguments():
    with pytest.raises(ParameterError, match="--workers needs"):
        make_executor("local", workers=2)
    with pytest.raises(ParameterError, match="only used with --executor dask"):
        make_executor("process", scheduler="tcp://127.0.0.1:8786")
    with pytest.raises(ParameterError, match="not both"):
        make_executor("dask", workers=2, scheduler="tcp://127.0.0.1:8786")
    with pytest.raises(ParameterError, match="not allowed"):
        make_executor("threads")
    with pytest.raises(ParameterError, match="workers"):
        make_executor("process", workers=0)
    assert make_executor("local").in_process


def test_dask_missing_gives_install_hint(monkeypatch):
    monkeypatch.setitem(sys.modules, "distributed", None)  # import distributed -> ImportError
    with pytest.raises(ParameterError, match=r"pip install arraysel\[dask\]"):
        make_executor("dask", workers=1)


def test_factories_are_picklable_and_rebuild_the_objective():
    obj = ToyObjective(20, 6, seed=5, nan_element=3)
    f = objective_factory_for(obj)
    g = pickle.loads(pickle.dumps(f))
    assert g == f and g.key() == f.key() and ToyObjectiveFactory(20, 6).key() != f.key()
    built = g()
    assert built.target == obj.target and built.nan_element == 3
    with pytest.raises(ParameterError, match="objective_factory"):
        objective_factory_for(object())


def test_random_search_is_the_best_of_all_chunks():
    factory = ToyObjectiveFactory(24, 8)
    res = distributed_random_search(factory, 1000, None, 7, None, 128)
    # brute force: the same chunks, scored at once, first minimum
    obj = factory()
    streams = np.random.SeedSequence(7).spawn(res.n_chunks)
    subsets = np.concatenate([random_subsets(np.random.default_rng(s), min(128, 1000 - 128 * i), 24, 8)
                              for i, s in enumerate(streams)])
    masks = np.zeros((1000, 24), dtype=bool)
    np.put_along_axis(masks, subsets, True, axis=1)
    means = obj.evaluate(masks)["Mean"]
    best = int(np.argmin(means))
    assert res.elements == subsets[best].tolist() and res.mean == pytest.approx(means[best])
    assert res.n_chunks == 8 and res.chunk_index == best // 128


def test_local_executor_reports_failures():
    res = list(LocalExecutor().run_tasks(ToyObjectiveFactory(8, 4, fail_after=0), _evaluate_one, [0]))
    assert isinstance(res[0][1], TaskFailed) and "toy objective failure" in res[0][1].message
    with pytest.raises(ArrayselError, match="chunk 0 of 1 failed"):
        distributed_random_search(ToyObjectiveFactory(8, 4, fail_after=0), 10, None, 0, None, 10)


def _evaluate_one(objective, item):
    return objective.evaluate(np.ones((1, objective.n_elements), dtype=bool))["Mean"][0]


# ---------------------------------------------------------------------------
# process pool
# ---------------------------------------------------------------------------

@pytest.fixture(scope="module")
def pool():
    with ProcessExecutor(workers=2, retries=0) as ex:
        yield ex


def test_process_compare_matches_local(pool, reg, local_reference, tmp_path):
    table, runs, trace = _run(tmp_path, reg, pool)
    ref_table, ref_runs, ref_trace = local_reference
    _same(ref_runs, runs)
    _same(ref_trace, trace)
    _same(ref_table, table)


def test_process_random_search_and_evaluate_match_local(pool):
    factory = ToyObjectiveFactory(64, 32)
    ref = distributed_random_search(factory, 6000, None, 11, None, 500)  # in-process: 1 worker
    r2 = distributed_random_search(factory, 6000, None, 11, pool, 500)
    assert ref.elements == r2.elements and ref.mean == r2.mean
    assert (ref.workers, r2.workers) == (1, 2)
    masks = np.random.default_rng(0).random((300, 64)) < 0.5
    got = distributed_evaluate(factory, masks, pool, chunk=64)
    want = factory().evaluate(masks)
    for m in want:
        np.testing.assert_array_equal(got[m], want[m])


def test_process_worker_death_loses_only_its_run(reg, tmp_path):
    """A worker that dies loses only the run that killed it. One retry: when ``always_crash``
    breaks the pool before ``best_of_batch`` has crashed its own worker, ``best_of_batch``
    crashes on its isolated rerun and is charged an attempt (it did kill its worker), so with
    no retry the outcome would depend on which worker died first."""
    marker = tmp_path / "crashed-once"
    sels = [("best_of_batch", {"marker": str(marker)}), "always_crash", "uniform"]
    marker.write_text("local")  # the local reference must not crash
    ref = _run(tmp_path / "local", reg, None, sels, seeds=[0])[1]
    marker.unlink()
    with ProcessExecutor(workers=2, retries=1) as pool:
        table, runs, _ = _run(tmp_path / "pool", reg, pool, sels, seeds=[0])
    assert marker.exists() and marker.read_text() != str(os.getpid())  # a worker died on it
    assert list(runs["config"]) == list(ref["config"]) and tuple(runs.columns) == ROW_COLUMNS
    by = runs.set_index("config")
    lab = f"best_of_batch(marker={marker})"
    assert by.loc[lab, "error"] == "" and by.loc[lab, "elements"] == ref.set_index("config").loc[lab, "elements"]
    assert by.loc["uniform", "error"] == ""
    assert "run lost: worker process died" in by.loc["always_crash", "error"]
    assert "always_crash" in set(table["config"]) and pool.restarts >= 2


# ---------------------------------------------------------------------------
# Dask distributed
# ---------------------------------------------------------------------------

@pytest.fixture(scope="module")
def dask_ex():
    pytest.importorskip("distributed")
    from arraysel.run.executors import DaskExecutor
    with DaskExecutor(workers=2, retries=1) as ex:
        yield ex


def test_dask_cluster_is_on_loopback(dask_ex):
    addrs = [dask_ex.client.scheduler.address, *dask_ex.client.nthreads()]
    assert all(a.startswith("tcp://127.0.0.1:") for a in addrs), addrs
    assert dask_ex.workers == 2


def test_dask_compare_matches_local(dask_ex, reg, local_reference, tmp_path):
    table, runs, trace = _run(tmp_path, reg, dask_ex)
    ref_table, ref_runs, ref_trace = local_reference
    _same(ref_runs, runs)
    _same(ref_trace, trace)
    _same(ref_table, table)


def test_dask_random_search_matches_local_and_pool(dask_ex, pool):
    factory = ToyObjectiveFactory(64, 32)
    ref = distributed_random_search(factory, 6000, None, 11, None, 500)
    rd = distributed_random_search(factory, 6000, None, 11, dask_ex, 500)
    rp = distributed_random_search(factory, 6000, None, 11, pool, 500)
    assert ref.elements == rd.elements == rp.elements and ref.mean == rd.mean == rp.mean
    assert rd.worker_pids == 2 or rd.worker_pids == 1  # both workers usually take chunks


def test_dask_worker_death_loses_only_its_run(dask_ex, reg, tmp_path):
    marker = tmp_path / "crashed-once"
    sels = [("best_of_batch", {"marker": str(marker)}), "always_crash", "uniform"]
    marker.write_text("local")
    ref = _run(tmp_path / "local", reg, None, sels, seeds=[0])[1]
    marker.unlink()
    _, runs, _ = _run(tmp_path / "dask", reg, dask_ex, sels, seeds=[0])
    assert marker.exists()
    assert list(runs["config"]) == list(ref["config"])
    by = runs.set_index("config")
    lab = f"best_of_batch(marker={marker})"
    assert by.loc[lab, "error"] == "" and by.loc[lab, "elements"] == ref.set_index("config").loc[lab, "elements"]
    assert by.loc["uniform", "error"] == ""
    assert "run lost: worker process died" in by.loc["always_crash", "error"]
    assert by.loc["always_crash", "elements"] == "" and by.loc["always_crash", "Mean"] == ""  # NaN


def test_threads_per_run_are_cores_over_workers_unless_given():
    from arraysel.run.template import threads_per_worker
    with ProcessExecutor(workers=2) as ex:
        assert ex.threads == threads_per_worker(2) and ex.describe()["threads"] == ex.threads
    assert make_executor("process", workers=2, threads=3).threads == 3
    with pytest.raises(ParameterError, match="--threads"):
        make_executor("process", workers=2, threads=0)


def test_compare_cli_checks_threads(tmp_path, capsys):
    from arraysel.cli.main import main
    rc = main(["compare", "--scene", "toy", "--selectors", "uniform", "--budget-evals", "5", "--threads", "0",
               "--out", str(tmp_path / "o"), "--no-progress", "--no-figures"])
    assert rc == 2 and "--threads" in capsys.readouterr().err
