"""benchmarks/bench_regression.py, the speed guard of issue 78, on a tiny setting: it runs, measures
every variant it is given, and refuses a malformed variant."""
from __future__ import annotations

import importlib.util
import json
import os
import subprocess
import sys

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SCRIPT = os.path.join(ROOT, "benchmarks", "bench_regression.py")


def _module():
    spec = importlib.util.spec_from_file_location("bench_regression", SCRIPT)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_variant_text_is_parsed_and_checked():
    mod = _module()
    assert mod.parse_variant("default") == ("default", {})
    assert mod.parse_variant("spin:OMP_WAIT_POLICY=ACTIVE,X=") == ("spin", {"OMP_WAIT_POLICY": "ACTIVE", "X": None})
    env = mod.variant_env({"OMP_WAIT_POLICY": "ACTIVE", "HOME": None})
    assert env["OMP_WAIT_POLICY"] == "ACTIVE" and "HOME" not in env
    for bad in ("", ":A=1", "a b", "x:NOVALUE"):
        with pytest.raises(SystemExit, match="--variant"):
            mod.parse_variant(bad)


def test_a_checkout_on_pythonpath_is_the_one_its_processes_import(tmp_path, monkeypatch):
    """A variant's PYTHONPATH entries are made absolute and its processes run in RUN_DIR (not a
    checkout): run in a checkout, python -c or -m would import the current folder's arraysel."""
    mod = _module()
    fake = tmp_path / "older" / "arraysel"
    fake.mkdir(parents=True)
    (fake / "__init__.py").write_text("")
    monkeypatch.chdir(tmp_path)
    env = mod.variant_env({"PYTHONPATH": "older"})
    assert env["PYTHONPATH"] == str(tmp_path / "older")
    got = subprocess.run([sys.executable, "-c", "import arraysel; print(arraysel.__file__)"], env=env,
                         cwd=mod.RUN_DIR, stdout=subprocess.PIPE, text=True, check=True).stdout.strip()
    assert got == str(fake / "__init__.py")


def test_runs_on_the_toy_scene(tmp_path):
    out = tmp_path / "guard.json"
    proc = subprocess.run([sys.executable, SCRIPT, "--scenes", "toy", "--masks", "3", "--rounds", "1",
                           "--swap-scene", "", "--variant", "plain", "--out", str(out)],
                          cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    record = json.loads(proc.stdout.strip().splitlines()[-1])
    assert record == json.loads(out.read_text())
    row = record["batches"]["toy"]["plain"]
    assert row["n"] == 3 and len(row["t1_s"]) == len(row["tN_s"]) == 1 and len(row["loads"]) == 2
    assert row["ms_per_mask"] == pytest.approx((row["tN_s"][0] - row["t1_s"][0]) / 2 * 1e3, abs=1e-2)
    assert len(row["cpu1_s"]) == len(row["cpuN_s"]) == 1 and row["cpuN_s"][0] > 0
    assert row["cpu_ms_per_mask"] == pytest.approx((row["cpuN_s"][0] - row["cpu1_s"][0]) / 2 * 1e3, abs=1e-2)
    assert record["swaps"] == {}
    assert "toy" in proc.stdout and "ms/mask" in proc.stdout
