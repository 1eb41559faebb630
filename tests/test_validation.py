"""Input validation (issue 7): scene files, masks, plugin results, CLI options, checkpoints, result files.

Every rejection must be a clear arraysel error (or exit code 2 on the command
line) whose message names the offending parameter. Nothing here builds a
large PSF model: the objectives are tiny scenes and ``ARRAYSEL_CACHE=off``.
"""
from __future__ import annotations

import ast
import math
import os
import re
from pathlib import Path

import numpy as np
import pytest
import torch

from arraysel.cli.main import main
from arraysel.errors import ParameterError, SelectionError
from arraysel.scenes.schema import load_scene

ROOT = Path(__file__).resolve().parents[1]

TINY = {"probe": {"n_elements": 8}, "selection": {"k": 4}, "transmit": {"n_tx": 1},
        "grid": {"n_x": 16, "n_z": 16, "window": 8, "pixel_per_wavelength_fs": 1.0},
        "metrics": {"r_main": 0.5, "r_guard": 1.0},
        "simulator": {"fast_margin": 2, "fast_block": 4}}


@pytest.fixture(autouse=True)
def _no_disk_cache(monkeypatch):
    monkeypatch.setenv("ARRAYSEL_CACHE", "off")


def write_scene(tmp_path, text: str, name: str = "scene.toml") -> str:
    path = tmp_path / name
    path.write_text(text)
    return str(path)


# ---------------------------------------------------------------------------
# scene files
# ---------------------------------------------------------------------------

@pytest.mark.parametrize("text,pattern", [
    ('base = "paper"\n[probe]\nn_elemnts = 8\n', r"unknown scene key 'probe\.n_elemnts'"),
    ('base = "paper"\n[prob]\nn_elements = 8\n', r"unknown scene key 'prob'"),
    ('base = "paper"\ncolour = "red"\n', r"unknown scene key 'colour'"),
    ('base = "paper"\n[probe]\nn_elements = 0\n', r"probe\.n_elements = 0 is out of range"),
    ('base = "paper"\n[probe]\nfc = -3.5e6\n', r"probe\.fc = -3500000\.0 is out of range"),
    ('base = "paper"\n[probe]\nbandwidth = 250.0\n', r"probe\.bandwidth = 250\.0 is out of range"),
    ('base = "paper"\n[acquisition]\nc = 50.0\n', r"acquisition\.c = 50\.0 is out of range"),
    ('base = "paper"\n[acquisition]\nattenuation = -1.0\n', r"acquisition\.attenuation"),
    ('base = "paper"\n[transmit]\nmax_tilt_deg = 90.0\n', r"transmit\.max_tilt_deg = 90\.0 is out of range"),
    ('base = "paper"\n[grid]\nn_x = 2.5\n', r"grid\.n_x must be an integer"),
    ('base = "paper"\n[grid]\nwindow = "big"\n', r"grid\.window must be a number"),
    ('base = "paper"\n[probe]\nbaffle = "hard"\n', r"probe\.baffle = 'hard' is not allowed"),
    ('base = "paper"\n[simulator]\nfull_frequency_directivity = 1\n',
     r"simulator\.full_frequency_directivity must be true or false"),
    ('base = "paper"\n[metrics]\nquantile = nan\n', r"metrics\.quantile must not be NaN"),
    ('base = "paper"\n[weights]\nL_PSF = -1.0\n', r"weights\.L_PSF = -1\.0 is out of range"),
    ('base = "paper"\n[selection]\nk = 65\n', r"selection\.k = 65 is out of range.*64 elements"),
    ('base = "paper"\n[grid]\nn_x = 64\nwindow = 128\n', r"grid\.window = 128 must not exceed"),
    ('base = "paper"\n[metrics]\nr_main = 3.0\nr_guard = 2.0\n', r"metrics\.r_guard must be >= metrics\.r_main"),
    ('base = "paper"\nprobe = 3\n', r"scene section 'probe' must be a table"),
    ('base = "paper"\n[acquisition]\nfs = 1e7\nfs_over_fc = 4.0\n', r"acquisition\.fs and acquisition\.fs_over_fc"),
    ('base = "nosuchscene"\n', r"unknown scene 'nosuchscene'"),
])
def test_scene_file_errors_name_the_key(tmp_path, text, pattern):
    path = write_scene(tmp_path, text)
    with pytest.raises(ParameterError, match=pattern):
        scene = load_scene(path)
        scene.psf_setup()  # some checks happen when the physics is built


@pytest.mark.parametrize("text", [
    "[probe\nn_elements = 8\n",
    'base = "paper"\n[probe]\nn_elements = \n',
    'base = "paper"\n[probe]\nname = "P4-2v"\nname = "L11-5v"\n',  # duplicate key
    "this is not toml at all",
])
def test_scene_file_bad_toml_names_the_file(tmp_path, text):
    path = write_scene(tmp_path, text)
    with pytest.raises(ParameterError, match=r"scene file .*scene\.toml' is not valid TOML"):
        load_scene(path)


def test_scene_file_missing(tmp_path):
    with pytest.raises(ParameterError, match=r"does not exist"):
        load_scene(str(tmp_path / "nope.toml"))


def test_scene_base_cycles_are_detected(tmp_path):
    a = tmp_path / "a.toml"
    b = tmp_path / "b.toml"
    a.write_text(f'base = "{b}"\n[selection]\nk = 4\n')
    b.write_text(f'base = "{a}"\n')
    with pytest.raises(ParameterError, match=r"scene base cycle"):
        load_scene(str(a))
    selfref = tmp_path / "self.toml"
    selfref.write_text(f'base = "{selfref}"\n')
    with pytest.raises(ParameterError, match=r"scene base cycle"):
        load_scene(str(selfref))


def test_scene_files_are_parsed_as_data_never_executed(tmp_path):
    marker = tmp_path / "pwned"
    payloads = [
        f'name = "__import__(\'os\').system(\'touch {marker}\')"\nbase = "paper"\n',
        f'base = "paper"\n[probe]\nname = "__import__(\'pathlib\').Path(\'{marker}\').touch()"\n',
        f'base = "paper"\n[grid]\nn_x = "__import__(\'pathlib\').Path(\'{marker}\').touch() or 64"\n',
    ]
    for text in payloads:
        path = write_scene(tmp_path, text)
        try:
            load_scene(path).psf_setup()
        except ParameterError:
            pass
        assert not marker.exists()
    # the loader itself: tomllib only, no eval/exec/pickle/import of scene content
    src = "\n".join(p.read_text() for p in sorted((ROOT / "arraysel" / "scenes").glob("*.py")))
    called = {n.func.id for p in sorted((ROOT / "arraysel" / "scenes").glob("*.py"))
              for n in ast.walk(ast.parse(p.read_text())) if isinstance(n, ast.Call) and isinstance(n.func, ast.Name)}
    assert not called & {"eval", "exec", "compile", "__import__"}
    assert "tomllib" in src and "pickle" not in src and "yaml" not in src


def test_scene_probe_name_is_checked():
    with pytest.raises(ParameterError, match=r"probe name = 'P9-9' is unknown"):
        load_scene({"base": "paper", "probe": {"name": "P9-9"}})


# ---------------------------------------------------------------------------
# masks
# ---------------------------------------------------------------------------

@pytest.mark.parametrize("sel,k,pattern", [
    ([[0, 1, 1, 2]], 4, r"selection 0: repeated element index"),
    ([[0, 1, 2, 3], [-1, 1, 2, 3]], 4, r"selection 1: element indices must be in \[0, 7\]"),
    ([[0, 1, 2, 8]], 4, r"selection 0: element indices must be in \[0, 7\]"),
    ([[0, 1, 2]], 4, r"selection 0: expected k = 4 elements, got 3"),
    ([[0, 1, 2, 3, 4]], 4, r"expected k = 4 elements, got 5"),
    ([[]], None, r"selection 0: empty selection"),
])
def test_masks_from_indices_rejects_bad_selections(sel, k, pattern):
    from arraysel.selection import masks_from_indices

    with pytest.raises(SelectionError, match=pattern):
        masks_from_indices(sel, 8, k)


def test_masks_from_indices_accepts_valid():
    from arraysel.selection import masks_from_indices

    m = masks_from_indices([[0, 7, 3, 4], np.array([1, 2, 5, 6])], 8, 4)
    assert m.shape == (2, 8) and (m.sum(1) == 4).all()


@pytest.fixture(scope="module")
def tiny_objective():
    import os as _os

    from arraysel.objective.psf_objective import Objective

    old = _os.environ.get("ARRAYSEL_CACHE")
    _os.environ["ARRAYSEL_CACHE"] = "off"
    try:
        return Objective(load_scene(dict(TINY, base="paper")))
    finally:
        if old is None:
            del _os.environ["ARRAYSEL_CACHE"]
        else:
            _os.environ["ARRAYSEL_CACHE"] = old


@pytest.mark.parametrize("masks,pattern", [
    (np.ones((2, 7)), r"masks must have shape \(B, 8\), got \(2, 7\)"),
    (np.ones((2, 3, 8)), r"masks must have shape \(B, 8\)"),
    (np.zeros((2, 8)), r"empty selection .* batch position\(s\) \[0, 1\]"),
    (np.array([[1, 1, 0, 0, 0, 0, 0, 0], [0] * 8], dtype=float), r"empty selection .* \[1\]"),
    (np.array([[1, -1, 1, 1, 0, 0, 0, 0]], dtype=float), r"mask weights must be >= 0"),
    (np.array([[1, math.nan, 1, 1, 0, 0, 0, 0]]), r"NaN or Inf"),
    (np.array([[1, math.inf, 1, 1, 0, 0, 0, 0]]), r"NaN or Inf"),
])
def test_objective_as_masks_rejects_bad_masks(tiny_objective, masks, pattern):
    with pytest.raises(SelectionError, match=pattern):
        tiny_objective.as_masks(masks)
    with pytest.raises(SelectionError):
        tiny_objective.evaluate(masks)


def test_objective_evaluate_indices_and_selection_loss_shapes(tiny_objective):
    with pytest.raises(SelectionError, match=r"repeated"):
        tiny_objective.evaluate_indices([[0, 0, 1, 2]])
    with pytest.raises(SelectionError, match=r"expected k = 4"):
        tiny_objective.evaluate_indices([[0, 1, 2]])
    with pytest.raises(SelectionError, match=r"P must have shape \(8, k\)"):
        tiny_objective.selection_loss(torch.zeros(7, 4), torch.zeros(7, 4))
    res = tiny_objective.evaluate_indices([[0, 2, 4, 6]])
    assert all(np.isfinite(res[k]).all() for k in tiny_objective.metric_names)


# ---------------------------------------------------------------------------
# plugin results: the runner puts an invalid selection in the `error` column
# ---------------------------------------------------------------------------

def _selector_returning(value, name):
    from arraysel.selectors.contract import Selector

    class Bad(Selector):
        description = "returns a fixed (invalid) result"
        deterministic = True

        def select(self, objective, k, seed):
            return value() if callable(value) else value

    Bad.name = name
    return Bad


@pytest.mark.parametrize("value,pattern", [
    ([0, 0, 1, 2], r"SelectionError: selection repeats elements"),
    ([0, 1, 2, 99], r"SelectionError: selection holds indices outside \[0, 8\)"),
    ([-1, 1, 2, 3], r"SelectionError: selection holds indices outside"),
    ([0, 1, 2], r"SelectionError: selection holds 3 elements, expected k = 4"),
    ([], r"SelectionError: selection holds 0 elements"),
    ([0.5, 1, 2, 3], r"SelectionError: selection holds a non-integer entry"),
    ([True, 1, 2, 3], r"SelectionError: selection holds a non-integer entry"),
    ("0123", r"SelectionError: a selection must be a list of element indices"),
    (None, r"SelectionError: a selection must be a list"),
    (lambda: np.array([[0, 1], [2, 3]]), r"SelectionError"),
    (lambda: torch.tensor([0, 1, 2, 2]), r"SelectionError: selection repeats"),
])
def test_runner_catches_invalid_plugin_results(value, pattern):
    from arraysel.run.experiment import ROW_COLUMNS, Experiment
    from arraysel.selectors.contract import Budget
    from arraysel.testing import ToyObjective

    row = Experiment(ToyObjective(8, 4), _selector_returning(value, "bad-result"),
                     budget=Budget(evaluations=5)).run()
    assert tuple(row) == ROW_COLUMNS
    assert re.match(pattern, row["error"]), row["error"]
    assert row["elements"] == "" and math.isnan(row["Mean"])


def test_runner_catches_invalid_result_on_a_physics_objective(tiny_objective):
    from arraysel.run.experiment import Experiment
    from arraysel.selectors.contract import Budget

    row = Experiment(tiny_objective, _selector_returning([0, 1, 1, 2], "bad-physics"),
                     budget=Budget(evaluations=5)).run()
    assert row["error"].startswith("SelectionError: selection repeats")
    good = Experiment(tiny_objective, _selector_returning([0, 2, 4, 6], "good-physics"),
                      budget=Budget(evaluations=5)).run()
    assert good["error"] == "" and math.isfinite(good["Mean"])


# ---------------------------------------------------------------------------
# command-line options: exit code 2 and a message naming the option
# ---------------------------------------------------------------------------

def _cli(argv, capsys) -> tuple[int, str]:
    try:
        code = main(argv)
    except SystemExit as exc:  # argparse's own errors (bad choice, missing option)
        code = exc.code
    return code, capsys.readouterr().err


@pytest.mark.parametrize("argv,pattern", [
    (["compare", "--scene", "toy", "--selectors", "nosuch", "--no-figures", "--no-progress"],
     r"unknown selector\(s\) nosuch"),
    (["compare", "--scene", "toy", "--selectors", "uniform", "--seeds", "a,b"], r"--seeds must be"),
    (["compare", "--scene", "toy", "--selectors", "uniform", "--seeds", "-1"], r"--seeds must"),
    (["compare", "--scene", "toy", "--selectors", "uniform", "--seeds", "1,1"], r"--seeds must list distinct"),
    (["compare", "--scene", "toy", "--selectors", "uniform", "--budget-s", "-5"], r"--budget-s = -5\.0 is out of range"),
    (["compare", "--scene", "toy", "--selectors", "uniform", "--budget-evals", "0"], r"--budget-evals = 0"),
    (["compare", "--scene", "toy", "--selectors", "uniform", "--budget-s", "0"], r"--budget-s 0 needs --budget-evals"),
    (["compare", "--scene", "toy", "--selectors", "ste", "-o", "ste.lr"], r"-o 'ste\.lr': expected SELECTOR\.KEY=VALUE"),
    (["compare", "--scene", "toy", "--selectors", "ste", "-o", "gumbel.lr=1"], r"selector 'gumbel' is not in --selectors"),
    (["compare", "--scene", "toy", "--selectors", "ste", "-o", "ste.nope=1"], r"nope"),
    (["compare", "--scene", "toy", "--selectors", "ste", "-o", "ste.lr=-1"], r"lr"),
    (["compare", "--scene", "toy", "--selectors", ""], r"--selectors is empty"),
    (["compare", "--scene", "toy", "--selectors", "uniform,uniform"], r"lists a selector twice"),
    (["compare", "--scene", "toy", "--selectors", "uniform", "--dtype", "float16"], r"--dtype.*invalid choice"),
    (["compare", "--scene", "toy", "--selectors", "uniform", "--device", "tpu"], r"--device.*invalid choice"),
    (["compare", "--scene", "toy", "--selectors", "uniform", "--budget-s", "abc"], r"--budget-s.*invalid float"),
    (["compare", "--scene", "toy"], r"--selectors"),
    (["psf", "--scene", "nosuchscene"], r"unknown scene 'nosuchscene'"),
    (["psf", "--elements", "0,1,1"], r"--elements: repeated element index"),
    (["psf", "--elements", "0,64"], r"--elements: element indices must be in \[0, 63\]"),
    (["psf", "--elements", "0,x"], r"--elements: 'x' is not an integer"),
    (["psf", "--elements", ","], r"--elements: no element index"),
    (["evaluate"], r"--masks"),
    (["nosuchcommand"], r"invalid choice"),
])
def test_cli_rejects_bad_options_with_exit_code_2(tmp_path, capsys, monkeypatch, argv, pattern):
    monkeypatch.chdir(tmp_path)
    code, err = _cli(argv, capsys)
    assert code == 2, err
    assert re.search(pattern, err), err
    assert not (tmp_path / "results").exists()


def test_cli_scene_file_errors_exit_2(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    bad = write_scene(tmp_path, 'base = "paper"\n[grid]\nn_x = -3\n')
    code, err = _cli(["psf", "--scene", bad, "--out", str(tmp_path / "k.npz")], capsys)
    assert code == 2 and "grid.n_x = -3 is out of range" in err
    code, err = _cli(["psf", "--scene", str(tmp_path / "k.npz"), "--out", "x.npz"], capsys)
    assert code == 2 and "does not exist" in err
    good = write_scene(tmp_path, 'base = "paper"\n[probe]\nn_elements = 8\n[selection]\nk = 4\n', "good.toml")
    code, err = _cli(["psf", "--scene", good, "--out", str(tmp_path / "k.txt")], capsys)
    assert code == 2 and "--out must end with .npz" in err
    masks = tmp_path / "masks.txt"
    masks.write_text("0 1 2 3\n")
    code, err = _cli(["evaluate", "--scene", good, "--masks", str(masks), "--psf-out", "k.txt"], capsys)
    assert code == 2 and "--psf-out must end with .npz" in err
    code, err = _cli(["evaluate", "--scene", good, "--masks", str(tmp_path / "none.txt")], capsys)
    assert code == 2 and "--masks: file" in err and "does not exist" in err
    assert not (tmp_path / "metrics.csv").exists()


# ---------------------------------------------------------------------------
# checkpoints: torch.load(weights_only=True) everywhere
# ---------------------------------------------------------------------------

def _torch_load_calls():
    for folder in ("arraysel", "plugins"):
        for path in sorted((ROOT / folder).rglob("*.py")):
            tree = ast.parse(path.read_text(), filename=str(path))
            for node in ast.walk(tree):
                if not isinstance(node, ast.Call):
                    continue
                f = node.func
                name = f.attr if isinstance(f, ast.Attribute) else f.id if isinstance(f, ast.Name) else None
                base = f.value.id if isinstance(f, ast.Attribute) and isinstance(f.value, ast.Name) else None
                if name == "load" and base == "torch":
                    yield path, node


def test_every_torch_load_passes_weights_only_true():
    calls = list(_torch_load_calls())
    assert calls, "expected at least the checkpoint and the PSF-cache loaders"
    for path, node in calls:
        where = f"{path.relative_to(ROOT)}:{node.lineno}"
        kw = {k.arg: k.value for k in node.keywords}
        assert "weights_only" in kw, f"{where}: torch.load without weights_only=True"
        assert isinstance(kw["weights_only"], ast.Constant) and kw["weights_only"].value is True, \
            f"{where}: weights_only must be the literal True"
    # numpy too: np.load must not unpickle
    for path in sorted((ROOT / "arraysel").rglob("*.py")):
        for m in re.finditer(r"allow_pickle\s*=\s*True", path.read_text()):
            raise AssertionError(f"{path.relative_to(ROOT)}: np.load(..., allow_pickle=True)")


def test_checkpoint_with_pickled_code_is_refused(tmp_path):
    """A checkpoint that smuggles an arbitrary object fails to load instead of running it."""
    import pickle

    class Evil:
        def __reduce__(self):
            return (os.system, (f"touch {tmp_path / 'pwned'}",))

    path = tmp_path / "evil.pt"
    with open(path, "wb") as fh:
        pickle.dump({"state": Evil()}, fh)
    with pytest.raises(Exception):
        torch.load(path, map_location="cpu", weights_only=True)
    assert not (tmp_path / "pwned").exists()


# ---------------------------------------------------------------------------
# result files are written atomically
# ---------------------------------------------------------------------------

def test_atomic_write_text_leaves_no_partial_file(tmp_path, monkeypatch):
    from arraysel.io import atomic
    from arraysel.report import tables as reporting

    target = tmp_path / "table1.csv"
    target.write_text("old complete content\n")

    real_fdopen = os.fdopen

    class Half:
        def __init__(self, fh):
            self.fh = fh

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            self.fh.close()
            return False

        def write(self, text):
            self.fh.write(text[: len(text) // 2])
            self.fh.flush()
            raise OSError(28, "No space left on device")

    monkeypatch.setattr(atomic.os, "fdopen", lambda fd, *a, **k: Half(real_fdopen(fd, *a, **k)))
    with pytest.raises(OSError, match="No space left"):
        reporting.atomic_write_text(target, "new content " * 1000)
    monkeypatch.undo()
    assert target.read_text() == "old complete content\n"  # the old file is untouched
    assert sorted(p.name for p in tmp_path.iterdir()) == ["table1.csv"]  # no temporary left behind
    # a new file that fails is not created at all
    monkeypatch.setattr(atomic.os, "fdopen", lambda fd, *a, **k: Half(real_fdopen(fd, *a, **k)))
    with pytest.raises(OSError):
        reporting.atomic_write_text(tmp_path / "runs.csv", "x" * 100)
    monkeypatch.undo()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["table1.csv"]
    # and a successful write replaces the content in one step
    reporting.atomic_write_text(target, "new\n")
    assert target.read_text() == "new\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["table1.csv"]


def test_atomic_write_survives_interrupt_during_replace(tmp_path, monkeypatch):
    from arraysel.io import atomic
    from arraysel.report import tables as reporting

    target = tmp_path / "run.json"
    target.write_text("{}\n")

    def boom(src, dst):
        raise KeyboardInterrupt

    monkeypatch.setattr(atomic.os, "replace", boom)
    with pytest.raises(KeyboardInterrupt):
        reporting.write_json(target, {"a": 1})
    monkeypatch.undo()
    assert target.read_text() == "{}\n"
    assert [p.name for p in tmp_path.iterdir()] == ["run.json"]


def test_atomic_write_bytes_leaves_no_partial_file(tmp_path, monkeypatch):
    from arraysel.io import masks as maskio

    target = tmp_path / "metrics.csv"
    target.write_bytes(b"old\n")

    def boom(src, dst):
        raise OSError("disk full")

    monkeypatch.setattr(maskio.os, "replace", boom)
    with pytest.raises(OSError):
        maskio.atomic_write_bytes(str(target), b"new" * 100)
    with pytest.raises(OSError):
        maskio.atomic_savez(str(tmp_path / "k.npz"), psf=np.zeros(3))
    monkeypatch.undo()
    assert target.read_bytes() == b"old\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["metrics.csv"]


def test_result_writers_go_through_the_atomic_helpers():
    """No result file is written with a bare open(..., 'w') / to_csv(path) / np.savez(path)."""
    bad = []
    for rel in ("arraysel/report/tables.py", "arraysel/run/experiment.py", "arraysel/io/masks.py",
                "arraysel/cli/psf.py", "arraysel/cli/evaluate.py", "arraysel/cli/compare.py"):
        src = (ROOT / rel).read_text()
        # writes to a temporary file (fd / tmp) or a memory buffer (buf) are the atomic helpers
        for pat in (r"open\((?!fd)[^)]*['\"]w", r"\.to_csv\((?!index)", r"np\.savez(_compressed)?\((?!buf)",
                    r"savefig\((?!buf|tmp)", r"\.write_text\(", r"\.write_bytes\("):
            for m in re.finditer(pat, src):
                line = src[: m.start()].count("\n") + 1
                bad.append(f"{rel}:{line}: {m.group(0)}")
    assert not bad, bad
