"""Hostile cases, a matrix scene (a 4 x 4 probe, tests/scene_texts.py) under the process and Dask
executors with a process killed in the middle of a run: the run's own process, the worker it was
forked from (the process pool's warm template), a Dask worker (its nanny starts it again), and a
run that kills its process every time.

A run killed once is made again: every row, trace and IOH run is that of a comparison nobody
disturbed (:func:`test_hostile_traces.whole`, the same numbers), exit code 0. A run killed every
time gets a ``run lost`` row after its retries, and the others are whole, exit code 1.
"""
from __future__ import annotations

import os
import signal
import threading
import time
from pathlib import Path

import pandas as pd
import pytest

from arraysel.cli.main import main
from scene_texts import TINY_MATRIX_SCENE
from support import own_plugin_manager, time_limit  # noqa: F401  (autouse fixtures)
from test_hostile_traces import whole

KILLER = str(Path(__file__).with_name("killer_plugin.py"))
_bounded = time_limit(240)
SELECTORS = "dies_once,random,uniform"
COMMON = ["--seeds", "0,1", "--budget-evals", "12", "--budget-s", "120", "--no-progress", "--no-figures",
          "--plugin", KILLER]


@pytest.fixture(autouse=True)
def guard(monkeypatch):
    monkeypatch.setenv("ARRAYSEL_HOSTILE_TEST_PID", str(os.getpid()))


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("scene") / "tiny3d.toml"
    path.write_text(TINY_MATRIX_SCENE)
    return path


def _means(out: Path) -> dict:
    runs = pd.read_csv(out / "runs.csv", keep_default_na=False)
    return {(c, str(s)): float(m) for c, s, m in zip(runs["config"], runs["seed"], runs["Mean"]) if m != ""}


@pytest.fixture(scope="module")
def reference(scene, tmp_path_factory) -> dict:
    """The comparison nobody disturbed (the marker exists: ``dies_once`` does not die)."""
    from arraysel.selectors import registry

    tmp = tmp_path_factory.mktemp("ref")
    marker = tmp / "marker"
    marker.write_text("done\n")
    old = os.environ.get("ARRAYSEL_HOSTILE_MARKER")
    os.environ["ARRAYSEL_HOSTILE_MARKER"] = str(marker)
    registry.reset()
    try:
        assert main(["compare", "--scene", str(scene), "--selectors", SELECTORS, *COMMON, "--out", str(tmp / "cmp"),
                     "--in-process"]) == 0
    finally:
        registry.reset()
        os.environ.pop("ARRAYSEL_HOSTILE_MARKER") if old is None else os.environ.__setitem__(
            "ARRAYSEL_HOSTILE_MARKER", old)
    return _means(tmp / "cmp")


@pytest.mark.parametrize("kill", ["self", "worker"], ids=["its own process", "the worker it was forked from"])
def test_a_matrix_run_killed_mid_run_on_the_process_executor_is_made_again(scene, reference, tmp_path, monkeypatch,
                                                                          capsys, kill):
    marker = tmp_path / "marker"
    monkeypatch.setenv("ARRAYSEL_HOSTILE_MARKER", str(marker))
    monkeypatch.setenv("ARRAYSEL_HOSTILE_KILL", kill)
    out = tmp_path / "cmp"
    code = main(["compare", "--scene", str(scene), "--selectors", SELECTORS, *COMMON, "--out", str(out),
                 "--executor", "process", "--workers", "2", "--retries", "1"])
    assert code == 0, capsys.readouterr().err
    killed = [int(p) for p in marker.read_text().split()]
    assert os.getpid() not in killed[:2]
    whole(out)
    assert _means(out) == reference


def test_a_matrix_run_that_kills_its_process_every_time_is_lost_alone(scene, reference, tmp_path, capsys):
    out = tmp_path / "cmp"
    code = main(["compare", "--scene", str(scene), "--selectors", "dies_always,random,uniform", "--seeds", "0,1",
                 "--budget-evals", "12", "--budget-s", "120", "--no-progress", "--no-figures", "--plugin", KILLER,
                 "--out", str(out), "--executor", "process", "--workers", "2", "--retries", "1"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 1 and err[-1] == ("arraysel compare: 1 run(s) failed (see the error column of runs.csv): "
                                     "dies_always seed 0"), err
    runs = pd.read_csv(out / "runs.csv", keep_default_na=False).set_index("config")
    assert runs.loc["dies_always", "error"].startswith("run lost: worker process died (2 attempt(s)): the run ended "
                                                       "its process (exit code -9) without a result")
    whole(out)
    means = _means(out)
    assert {k: v for k, v in means.items() if k[0] != "dies_always"} == \
        {k: v for k, v in reference.items() if k[0] != "dies_once"}


@pytest.mark.slow
@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="needs /proc to find the worker process")
def test_a_dask_worker_killed_mid_run_on_a_matrix_scene_costs_nothing(scene, reference, tmp_path, monkeypatch):
    pytest.importorskip("distributed")
    from arraysel.objective.build import build_objective
    from arraysel.run.compare import compare
    from arraysel.run.executors import DaskExecutor
    from arraysel.scenes.schema import load_scene
    from arraysel.selectors.contract import Budget
    from arraysel.selectors.registry import get_registry, load_plugin

    load_plugin(KILLER)
    marker = tmp_path / "marker"
    monkeypatch.setenv("ARRAYSEL_HOSTILE_MARKER", str(marker))
    monkeypatch.setenv("ARRAYSEL_HOSTILE_KILL", "wait")
    killed = []

    def killer(workers: set):
        end = time.monotonic() + 180
        while time.monotonic() < end and not (marker.exists() and marker.read_text().strip()):
            time.sleep(0.1)
        pid = next(p for p in map(int, marker.read_text().split()) if p in workers)
        os.kill(pid, signal.SIGKILL)  # the Dask worker running the run; its nanny starts it again
        killed.append(pid)

    obj = build_objective(load_scene(str(scene)))
    with DaskExecutor(workers=2, retries=1) as ex:
        workers = set(ex.client.run(os.getpid).values())
        thread = threading.Thread(target=killer, args=(workers,), daemon=True)
        thread.start()
        res = compare(obj, SELECTORS.split(","), out_dir=tmp_path / "cmp", seeds=[0, 1],
                      budget=Budget(seconds=120, evaluations=12), registry=get_registry(), progress=False,
                      figures=False, executor=ex)
    thread.join(5)
    assert killed and killed[0] != os.getpid() and res.failures == ()
    whole(tmp_path / "cmp")
    assert _means(tmp_path / "cmp") == reference
