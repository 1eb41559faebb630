"""Hostile runs of ``arraysel compare``: a real SIGKILL at each write stage then ``--resume``,
SIGTERM, SIGKILL of the supervisor during a run, two compares into one folder, ``--resume`` beside
a live run, a stale lock.

Each case asserts that no data is lost (every run is in runs.csv once, with its trace and IOH
entry, and the same numbers as an uninterrupted compare), a one-line message and the right exit
code. The toy scene keeps every case to seconds.
"""
from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pandas as pd
import pytest

from arraysel.run.outdir import LOCK_NAME
from support import own_plugin_manager, time_limit  # noqa: F401  (autouse fixtures)

PLUGIN = str(Path(__file__).with_name("hostile_plugin.py"))
TEST_LIMIT_S = 150
ARGS = ["--scene", "toy", "--budget-s", "30", "--budget-evals", "60", "--seeds", "0,1", "--no-progress",
        "--no-figures"]
SELECTORS = "random,greedy,uniform"
EXPECTED = {("random", 0), ("random", 1), ("greedy", 0), ("uniform", 0)}

#: runs `arraysel compare ARGS...` and kills itself (SIGKILL) just before the Nth write of a file
#: whose path contains TARGET (argv: TARGET N ARGS...)
_KILLER = """
import os, signal, sys
import arraysel.report.tables as tables
target, nth = sys.argv[1], int(sys.argv[2])
seen = [0]
write = tables.atomic_write_text
def killing(path, text):
    if target in str(path):
        seen[0] += 1
        if seen[0] == nth:
            os.kill(os.getpid(), signal.SIGKILL)
    return write(path, text)
tables.atomic_write_text = killing
from arraysel.cli.main import main
sys.exit(main(sys.argv[3:]))
"""


_bounded = time_limit(TEST_LIMIT_S)  # fails, instead of hanging, a test longer than this




def _main(*argv) -> int:
    from arraysel.cli.main import main

    return main(list(argv))


def _python(*argv, env=None, **kw) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, *argv], env={**os.environ, **(env or {})}, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, **kw)


def _cli(*argv, env=None) -> subprocess.Popen:
    return _python("-c", "import sys; from arraysel.cli.main import main; sys.exit(main(sys.argv[1:]))",
                   *argv, env=env)


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """An uninterrupted compare: the numbers every resumed folder must reproduce."""
    from arraysel.selectors import registry

    registry.reset()
    out = tmp_path_factory.mktemp("ref") / "cmp"
    try:
        assert _main("compare", "--selectors", SELECTORS, *ARGS, "--out", str(out), "--in-process") == 0
    finally:
        registry.reset()
    runs = pd.read_csv(out / "runs.csv", keep_default_na=False)
    return {(c, str(s)): float(m) for c, s, m in zip(runs["config"], runs["seed"], runs["Mean"])}


def _consistent(out: Path, reference=None):
    """Every expected run once in runs.csv, each with one trace end row, nothing traced that is not
    listed, IOH json/dat agreeing with each other and with the rows, run.json finished."""
    runs = pd.read_csv(out / "runs.csv", keep_default_na=False)
    runs = runs[runs["config"] != "full"]
    keys = [(c, int(s)) for c, s in zip(runs["config"], runs["seed"])]
    assert sorted(keys) == sorted(EXPECTED) and len(set(keys)) == len(keys), keys
    assert (runs["error"] == "").all(), runs["error"]
    trace = pd.read_csv(out / "trace.csv")
    traced = [(c, int(s)) for c, s, e in zip(trace["config"], trace["seed"], trace["event"]) if e == "end"]
    for key, evals in zip(keys, runs["evaluations"]):
        if float(evals) > 0 and key[0] != "uniform":
            assert traced.count(key) == 1, (key, traced)
    assert {(c, int(s)) for c, s in zip(trace["config"], trace["seed"])} <= set(keys)
    ioh = {}
    for js in (out / "ioh").glob("*/IOHprofiler_*.json"):
        meta = json.loads(js.read_text())
        scen = meta["scenarios"][0]
        blocks = (js.parent / scen["path"]).read_text().split("evaluations raw_y seconds\n")[1:]
        assert len(blocks) == len(scen["runs"])
        for run, block in zip(scen["runs"], blocks):
            best = min(float(line.split()[1]) for line in block.strip().splitlines())
            assert run["best"]["y"] == pytest.approx(best, rel=1e-12)
            ioh[(meta["algorithm"]["name"], run["seed"])] = run["best"]["y"]
    assert set(ioh) == set(traced)
    assert json.loads((out / "run.json").read_text())["status"] == "finished"
    assert not list(out.glob(LOCK_NAME))
    if reference is not None:
        for (c, s), mean in zip(keys, runs["Mean"]):
            assert float(mean) == pytest.approx(reference[(c, str(s))], rel=1e-6), (c, s)


# ---------------------------------------------------------------------------
# kills at each write stage, then --resume
# ---------------------------------------------------------------------------

@pytest.mark.parametrize("target, nth", [
    ("trace.csv", 3),       # before the trace of the second run: it and the later ones are run again
    pytest.param("IOHprofiler", 4, marks=pytest.mark.slow),  # between trace.csv and ioh/
    ("runs.csv", 3),        # between trace.csv + ioh/ and runs.csv (the case that used to lose a trace)
    pytest.param("table1.csv", 3, marks=pytest.mark.slow),   # between runs.csv and table1.csv
    pytest.param("run.json", 2, marks=pytest.mark.slow),     # after the last run, before "finished"
])
def test_a_kill_at_any_write_then_resume_gives_a_consistent_folder(tmp_path, reference, target, nth):
    out = tmp_path / "cmp"
    args = ["compare", "--selectors", SELECTORS, *ARGS, "--out", str(out), "--in-process"]
    proc = _python("-c", _KILLER, target, str(nth), *args)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == -signal.SIGKILL, err
    assert _main(*args, "--resume") == 0
    _consistent(out, reference)


def test_resume_after_a_kill_in_a_child_run_keeps_the_finished_runs(tmp_path, reference, capsys):
    """SIGKILL of the whole compare while a run is in its child: the finished runs stay, the
    child does not outlive its supervisor, and --resume finishes the folder."""
    out = tmp_path / "cmp"
    pids = tmp_path / "pids"
    proc = _cli("compare", "--selectors", "uniform,ignores_budget", *ARGS, "--out", str(out), "--plugin", PLUGIN,
                env={"ARRAYSEL_HOSTILE_PIDS": str(pids)})
    child = _wait_for_pid(pids, proc)
    proc.kill()
    proc.communicate(timeout=30)
    _wait_gone(child, 15)
    runs = pd.read_csv(out / "runs.csv", keep_default_na=False)
    assert list(runs["config"]) == ["full", "uniform"]
    assert not (out / LOCK_NAME).exists() or _main("compare", "--selectors", SELECTORS, *ARGS, "--out", str(out),
                                                  "--in-process", "--resume") == 0
    _consistent(out, reference)


# ---------------------------------------------------------------------------
# signals and orphans
# ---------------------------------------------------------------------------

def _wait_for_pid(path: Path, proc, limit: float = 60.0) -> int:
    deadline = time.monotonic() + limit
    while time.monotonic() < deadline:
        if path.exists() and path.read_text().strip():
            return int(path.read_text().split()[0])
        if proc.poll() is not None:
            raise AssertionError(f"compare ended early: {proc.communicate()}")
        time.sleep(0.1)
    raise AssertionError("the hanging run never started")


def _gone(pid: int) -> bool:
    import psutil

    try:
        return psutil.Process(pid).status() == psutil.STATUS_ZOMBIE
    except psutil.NoSuchProcess:
        return True


def _wait_gone(pid: int, limit: float) -> None:
    deadline = time.monotonic() + limit
    while not _gone(pid) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert _gone(pid), f"process {pid} is still running"


@pytest.mark.parametrize("extra", [[], pytest.param(["--executor", "process", "--workers", "2"],
                                                    marks=pytest.mark.slow)], ids=["child", "process"])
def test_sigterm_stops_the_children_and_says_interrupted(tmp_path, extra):
    out = tmp_path / "cmp"
    pids = tmp_path / "pids"
    proc = _cli("compare", "--selectors", "ignores_budget,uniform", *ARGS, "--out", str(out), "--plugin", PLUGIN,
                *extra, env={"ARRAYSEL_HOSTILE_PIDS": str(pids)})
    child = _wait_for_pid(pids, proc)
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 128 + signal.SIGTERM, err
    assert err.strip().splitlines()[-1] == "arraysel compare: terminated (SIGTERM)"
    assert "Traceback" not in err
    _wait_gone(child, 10)
    assert json.loads((out / "run.json").read_text())["status"] == "interrupted"
    assert not [p.name for p in out.rglob("*") if p.name.endswith(".tmp") or p.name == LOCK_NAME]


# ---------------------------------------------------------------------------
# the lock on --out
# ---------------------------------------------------------------------------

def test_a_second_compare_and_a_resume_beside_a_live_run_are_refused(tmp_path, capsys):
    out = tmp_path / "cmp"
    pids = tmp_path / "pids"
    first = _cli("compare", "--selectors", "uniform,ignores_budget", "--scene", "toy", "--budget-s", "2",
                 "--grace-s", "2", "--seeds", "0", "--no-progress", "--no-figures", "--out", str(out),
                 "--plugin", PLUGIN, env={"ARRAYSEL_HOSTILE_PIDS": str(pids)})
    _wait_for_pid(pids, first)
    for extra in ([], ["--resume"], ["--force"]):
        capsys.readouterr()
        assert _main("compare", "--selectors", "uniform", *ARGS, "--out", str(out), "--in-process", *extra) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and str(out) in err[0] and f"pid {first.pid}" in err[0], err
        assert "in use by another arraysel compare" in err[0]
    _, ferr = first.communicate(timeout=60)
    assert first.returncode == 1, ferr  # ignores_budget failed; nothing of the refused runs mixed in
    runs = pd.read_csv(out / "runs.csv", keep_default_na=False)
    assert list(runs["config"]) == ["full", "uniform", "ignores_budget"]
    assert not (out / LOCK_NAME).exists()


def test_a_stale_lock_of_a_dead_process_is_taken_over(tmp_path):
    out = tmp_path / "cmp"
    out.mkdir()
    (out / LOCK_NAME).write_text("999999999\n")  # left by a killed run: its flock went with it
    assert _main("compare", "--selectors", "uniform", *ARGS, "--out", str(out), "--in-process") == 0
    assert not (out / LOCK_NAME).exists()


def test_the_lock_is_reentrant_in_a_process_and_released(tmp_path):
    from arraysel.errors import ParameterError
    from arraysel.run.outdir import lock_out_dir

    out = tmp_path / "cmp"
    with lock_out_dir(out):
        with lock_out_dir(out):
            assert (out / LOCK_NAME).read_text().strip() == str(os.getpid())
        other = _python("-c", "import sys; from arraysel.run.outdir import lock_out_dir\n"
                              "with lock_out_dir(sys.argv[1]): pass", str(out))
        _, err = other.communicate(timeout=60)
        assert other.returncode == 1 and f"pid {os.getpid()}" in err and "ParameterError" in err
    assert not (out / LOCK_NAME).exists()
    with lock_out_dir(out):  # free again
        pass
    assert isinstance(math.pi, float) and ParameterError
