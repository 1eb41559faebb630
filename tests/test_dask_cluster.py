"""A real Dask cluster, started the way a user starts one on several machines: ``dask scheduler``
and two ``dask worker`` processes (Dask's own command-line tools), each a process of its own on
127.0.0.1. ``arraysel compare --executor dask --scheduler tcp://...`` against it must give the
same tables as a local run (every column but the timing ones, budgets in evaluations), and a
worker killed in the middle of a run must cost nothing: the run is done again on a worker.

Every test is bounded by an alarm; the cluster's processes are killed at the end of the module.
"""
from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from arraysel.selectors.contract import Budget, Option, Selector
from support import time_limit

pytest.importorskip("distributed")

HERE = Path(__file__).resolve().parent
_bounded = time_limit(120)
BIN = Path(sys.executable).parent


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _start(args: list[str], log: Path) -> subprocess.Popen:
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(HERE), os.environ.get("PYTHONPATH", "")])}
    with open(log, "wb") as fh:
        return subprocess.Popen([str(BIN / "dask"), *args], stdout=fh, stderr=subprocess.STDOUT, env=env,
                                start_new_session=True)


def _stop(proc: subprocess.Popen) -> None:
    if proc.poll() is None:
        os.killpg(proc.pid, signal.SIGTERM)
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait(10)


@pytest.fixture(scope="module")
def cluster(tmp_path_factory):
    """``tcp://127.0.0.1:PORT`` of a scheduler with two single-threaded workers (separate
    processes, each under Dask's nanny)."""
    import distributed

    logs = tmp_path_factory.mktemp("dask-logs")
    port = _free_port()
    address = f"tcp://127.0.0.1:{port}"
    procs = [_start(["scheduler", "--host", "127.0.0.1", "--port", str(port), "--no-dashboard"],
                    logs / "scheduler.log")]
    try:
        for i in range(2):
            procs.append(_start(["worker", address, "--host", "127.0.0.1", "--nthreads", "1", "--nworkers", "1",
                                 "--no-dashboard", "--death-timeout", "60", "--name", f"w{i}"],
                                logs / f"worker{i}.log"))
        with distributed.Client(address, timeout="30s", set_as_default=False) as client:
            client.wait_for_workers(2, timeout=60)
        yield address
    finally:
        for p in reversed(procs):
            _stop(p)


def _arraysel(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "arraysel", *args], cwd=cwd, capture_output=True, text=True,
                          timeout=100)


def _same(a: pd.DataFrame, b: pd.DataFrame) -> None:
    """Equal but for the timing columns (floats to 1e-6)."""
    assert list(a.columns) == list(b.columns) and len(a) == len(b)
    for c in a.columns:
        if "seconds" in c:
            continue
        x, y = a[c], b[c]
        if pd.api.types.is_float_dtype(x) and pd.api.types.is_float_dtype(y):
            np.testing.assert_allclose(x.to_numpy(), y.to_numpy(), rtol=1e-6, equal_nan=True, err_msg=c)
        else:
            assert list(x.astype(str)) == list(y.astype(str)), c


@pytest.mark.slow
def test_compare_on_a_cli_started_cluster_gives_the_local_tables(cluster, tmp_path):
    common = ["compare", "--scene", "toy", "--selectors", "random,swap,uniform", "--seeds", "0,1",
              "--budget-s", "0", "--budget-evals", "300", "--no-figures", "--no-progress"]
    local = _arraysel(*common, "--out", "local", cwd=tmp_path)
    assert local.returncode == 0, local.stderr
    dask = _arraysel(*common, "--out", "dask", "--executor", "dask", "--scheduler", cluster, cwd=tmp_path)
    assert dask.returncode == 0, dask.stderr
    assert "leaked semaphore" not in dask.stderr + local.stderr
    for name in ("runs.csv", "table1.csv", "trace.csv"):
        _same(pd.read_csv(tmp_path / "local" / name, keep_default_na=False),
              pd.read_csv(tmp_path / "dask" / name, keep_default_na=False))
    import json
    meta = json.loads((tmp_path / "dask" / "run.json").read_text())
    assert meta["executor"]["scheduler"] == cluster and meta["executor"]["workers"] == 2
    warm = meta["worker_warm_ups"]  # one warm-up per worker that ran something, timed once
    assert 1 <= len(warm) <= 2 and len({(w["host"], w["pid"]) for w in warm}) == len(warm)
    assert all(w["threads"] >= 1 and w["ready_s"] >= w["warm_s"] >= 0 and not w["warm_error"] for w in warm)


def _ancestors() -> list[int]:
    """This process's parent, its parent, ... (from ``/proc``)."""
    out, pid = [], os.getppid()
    while pid > 1 and len(out) < 20:
        out.append(pid)
        pid = int(Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[1])
    return out


class SlowOnce(Selector):
    """Deterministic: the first time (no marker file), writes its ancestors' pids (one is the
    Dask worker running it) in the marker and waits to be killed; then the best of 30 masks."""

    name = "slow_once"
    description = "waits to be killed with its worker once, then the best of 30 random masks"
    options = {"marker": Option(str, "", "the file that says it ran once")}
    deterministic = True

    def select(self, objective, k, seed):
        marker = Path(self.options["marker"])
        if not marker.exists():
            marker.write_text(" ".join(map(str, [os.getpid(), *_ancestors()])))
            time.sleep(90)  # killed with its worker long before
        rng = np.random.default_rng(seed)
        n = int(objective.n_elements)
        masks = np.zeros((30, n), dtype=bool)
        for row in masks:
            row[rng.choice(n, size=k, replace=False)] = True
        means = objective.evaluate(masks)["Mean"]
        return np.flatnonzero(masks[int(np.argmin(means))]).tolist()


@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="needs /proc to find the worker process")
def test_a_worker_killed_mid_run_costs_nothing(cluster, tmp_path):
    from arraysel.objective.toy import ToyObjective
    from arraysel.run.compare import compare
    from arraysel.run.executors import DaskExecutor
    from arraysel.selectors.registry import SelectorRegistry, build_plugin_manager, get_registry

    base = get_registry(build_plugin_manager(load_entrypoints=False, disabled=()))
    reg = SelectorRegistry()
    for name in ("uniform", "random"):
        reg.register(base[name])
    reg.register(SlowOnce)
    marker = tmp_path / "ran-once"
    sels = [("slow_once", {"marker": str(marker)}), ("random", {"n": 120}), "uniform"]
    budget = Budget(evaluations=120)

    def run(out, executor=None):
        compare(ToyObjective(16, 8), sels, out_dir=out, seeds=[0, 1], budget=budget, registry=reg,
                progress=False, figures=False, executor=executor)
        return pd.read_csv(out / "runs.csv", keep_default_na=False)

    marker.write_text("local")  # the reference run must not wait
    ref = run(tmp_path / "local")
    marker.unlink()
    killed = []

    def killer(workers: set[int]):
        end = time.monotonic() + 60
        while time.monotonic() < end and not (marker.exists() and marker.read_text().strip()):
            time.sleep(0.1)
        pid = next(p for p in map(int, marker.read_text().split()) if p in workers)
        os.kill(pid, signal.SIGKILL)  # the Dask worker process running the run (its nanny restarts it)
        killed.append(pid)

    with DaskExecutor(scheduler=cluster, retries=1) as ex:
        workers = set(ex.client.run(os.getpid).values())
        thread = threading.Thread(target=killer, args=(workers,), daemon=True)
        thread.start()
        runs = run(tmp_path / "dask", ex)
    thread.join(5)
    assert killed and killed[0] != os.getpid()
    run_pid = int(marker.read_text().split()[0])  # the killed worker's run (and template) ended too
    end = time.monotonic() + 20
    while time.monotonic() < end and Path(f"/proc/{run_pid}").exists() and \
            Path(f"/proc/{run_pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z":
        time.sleep(0.2)
    assert not Path(f"/proc/{run_pid}").exists() or \
        Path(f"/proc/{run_pid}/stat").read_text().rsplit(")", 1)[1].split()[0] == "Z"
    _same(ref, runs)  # the killed run was done again; nothing lost, nothing different
    assert (runs["error"] == "").all()
