"""The command's start: light commands load no torch, pandas or matplotlib; ``python -m arraysel``;
the global ``-v`` / ``-q`` logging flags; one-line errors. Each runs in a fresh interpreter."""
from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

import arraysel

HEAVY = ("torch", "pandas", "matplotlib")


def _env(tmp_path, **extra) -> dict:
    return {**os.environ, "ARRAYSEL_CACHE": str(tmp_path / "cache"), **extra}


def _python(code: str, tmp_path, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", code, *args], cwd=tmp_path, env=_env(tmp_path),
                          capture_output=True, text=True, timeout=300)


_LOADED = """
import contextlib, io, json, sys
from arraysel.cli.main import main
out = io.StringIO()
try:
    with contextlib.redirect_stdout(out):
        code = main(sys.argv[1:])
except SystemExit as exc:  # --help
    code = exc.code
print(json.dumps({"code": code, "out": out.getvalue(), "heavy": [m for m in %r if m in sys.modules]}))
""" % (HEAVY,)


@pytest.mark.parametrize("argv", [["--help"], ["scenes"], ["scenes", "paper"], ["cache", "path"],
                                  ["cache", "info"], ["-q", "scenes", "--json"], ["list"], ["list", "-v", "--json"],
                                  ["report", "--help"]])
def test_light_commands_import_no_torch_pandas_or_matplotlib(argv, tmp_path):
    proc = _python(_LOADED, tmp_path, *argv)
    assert proc.returncode == 0, proc.stderr
    res = json.loads(proc.stdout.splitlines()[-1])
    assert res["code"] == 0 and res["out"].strip()
    assert res["heavy"] == [], f"arraysel {' '.join(argv)} imported {res['heavy']}"


def _finished_folder(folder):
    """A finished comparison folder written by hand (run.json, runs.csv): what `report` reads."""
    from arraysel.report.columns import ROW_COLUMNS

    folder.mkdir()
    (folder / "run.json").write_text(json.dumps({"status": "finished", "scene_name": "toy", "k": 2,
                                                 "n_elements": 4, "budget": {"evaluations": 10},
                                                 "selectors": [{"config": "random", "selector": "random"},
                                                               {"config": "uniform", "selector": "uniform"}]}))
    rows = [{**dict.fromkeys(ROW_COLUMNS, ""), "config": c, "selector": c, "seed": s, "k": 2, "n_elements": 4,
             "Mean": m, "L_PSF": m, "L_contrast": 0, "L_SLR_q": 0, "L_SLR_i": 0, "L_SLR": 0, "seconds": 1,
             "evaluations": 10, "gradient_steps": 0, "objective_seconds": 0.5, "overhead_seconds": 0.1,
             "elements": "0 2"}
            for c, s, m in [("random", 0, 0.3), ("random", 1, 0.2), ("random", 2, 0.4), ("random", 3, 0.25),
                            ("random", 4, 0.35), ("uniform", 0, 0.5)]]
    lines = [",".join(ROW_COLUMNS)] + [",".join(str(r[c]) for c in ROW_COLUMNS) for r in rows]
    (folder / "runs.csv").write_text("\n".join(lines) + "\n")
    return folder


def test_report_imports_no_torch_and_states_the_intervals_coverage(tmp_path):
    folder = _finished_folder(tmp_path / "cmp")
    proc = _python(_LOADED.replace("%r" % (HEAVY,), "('torch', 'matplotlib', 'scipy.stats')"), tmp_path,
                   "report", str(folder))
    assert proc.returncode == 0, proc.stderr
    res = json.loads(proc.stdout.splitlines()[-1])
    assert res["code"] == 0 and res["heavy"] == [], res["heavy"]
    assert "| 93.8 % CI of median |" in res["out"] and "| 1 (deterministic) |" in res["out"]


def test_the_check_can_fail(tmp_path):
    """The checks above can fail: ``psf`` imports torch first thing (then refuses the scene)."""
    proc = _python(_LOADED, tmp_path, "psf", "--scene", "no-such-scene")
    assert "torch" in json.loads(proc.stdout.splitlines()[-1])["heavy"]


def test_python_m_arraysel_is_the_command(tmp_path):
    run = lambda *a: subprocess.run([sys.executable, "-m", "arraysel", *a], cwd=tmp_path, env=_env(tmp_path),
                                    capture_output=True, text=True, timeout=300)
    help_ = run("--help")
    assert help_.returncode == 0 and help_.stdout.startswith("usage: arraysel ")
    for command in ("evaluate", "compare", "scenes", "cache", "-v, --verbose", "-q, --quiet"):
        assert command in help_.stdout
    version = run("--version")
    assert version.returncode == 0 and version.stdout.strip() == f"arraysel {arraysel.__version__}"
    scenes = run("scenes")
    assert scenes.returncode == 0 and "paper" in scenes.stdout


_SMALL_WINDOW = 'base = "paper-e2e"\n[grid]\nwindow = 8\n'  # allowed, with a warning (end-to-end scene)


def test_quiet_hides_warnings_that_are_shown_by_default(tmp_path):
    scene = tmp_path / "small.toml"
    scene.write_text(_SMALL_WINDOW, encoding="utf-8")
    run = lambda *a: subprocess.run([sys.executable, "-m", "arraysel", *a], cwd=tmp_path, env=_env(tmp_path),
                                    capture_output=True, text=True, timeout=300)
    default, quiet = run("scenes", str(scene)), run("-q", "scenes", str(scene))
    assert default.returncode == quiet.returncode == 0
    assert "does not fit grid.window" in default.stderr and len(default.stderr.splitlines()) == 1
    assert quiet.stderr == "" and quiet.stdout == default.stdout


@pytest.mark.parametrize("flags, level", [((), "WARNING"), (("-v",), "INFO"), (("-vv",), "DEBUG"),
                                          (("-q",), "ERROR"), (("-qq",), "CRITICAL")])
def test_verbosity_flags_set_the_arraysel_logger_level(flags, level, tmp_path):
    code = ("import logging, sys\nfrom arraysel.cli.main import main\n"
            "assert main(sys.argv[1:]) == 0\n"
            "print(logging.getLevelName(logging.getLogger('arraysel').getEffectiveLevel()))")
    proc = _python(code, tmp_path, *flags, "cache", "path")
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.splitlines()[-1] == level


def test_verbose_and_quiet_together_are_refused(tmp_path):
    proc = _python("from arraysel.cli.main import main; main(['-v', '-q', 'scenes'])", tmp_path)
    assert proc.returncode == 2 and "not allowed with argument" in proc.stderr


def test_verbose_shows_the_basis_builds_steps(tmp_path):
    """-v lets the information records through: the PSF basis build's steps (a tiny scene, not cached)."""
    scene = tmp_path / "tiny.toml"
    scene.write_text('base = "paper"\n[probe]\nn_elements = 8\n[selection]\nk = 4\n[transmit]\nn_tx = 1\n'
                     '[grid]\nn_x = 32\nn_z = 32\nwindow = 16\npixel_per_wavelength_fs = 1.0\n'
                     '[metrics]\nr_main = 0.75\nr_guard = 1.25\n'
                     '[simulator]\nfast_margin = 2\nfast_block = 4\n', encoding="utf-8")
    proc = subprocess.run([sys.executable, "-m", "arraysel", "-v", "psf", "--scene", str(scene),
                           "--elements", "0,2,4,6", "--out", str(tmp_path / "psf.npz")], cwd=tmp_path,
                          env=_env(tmp_path, ARRAYSEL_CACHE="off"), capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr
    assert "building the PSF fast-path basis: 8 elements" in proc.stderr
    assert "basis built in" in proc.stderr


def test_an_error_is_one_line_on_stderr_and_exit_code_2(tmp_path):
    for flags in ((), ("-q",), ("-v",)):
        proc = subprocess.run([sys.executable, "-m", "arraysel", *flags, "scenes", "no-such-scene"], cwd=tmp_path,
                              env=_env(tmp_path), capture_output=True, text=True, timeout=300)
        assert proc.returncode == 2, proc.stderr
        assert proc.stderr.startswith("arraysel scenes: error: ") and len(proc.stderr.splitlines()) == 1
