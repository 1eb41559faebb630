"""Hostile cases, traces that are never silently short: ``--resume`` after ``trace.csv`` was
deleted, cut short or doubled; a selector that returns a selection it never scored; IOHprofiler
files a standard reader (the installed ``iohinspector``) must load whole.

The invariant each case checks (:func:`whole`): every finished run (a finite Mean, no error) is
listed once in ``runs.csv``, has exactly one ``end`` row in ``trace.csv`` and exactly one run in
``ioh/``, whose ``best`` is the ``.dat``'s best with the mask of the selection that scored it;
``iohinspector`` reads the same runs and rows.
"""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from support import ioh_read, own_plugin_manager, time_limit  # noqa: F401  (autouse fixtures)

FACTORY = str(Path(__file__).with_name("factory_plugin.py"))
_bounded = time_limit(150)
ARGS = ["--scene", "toy", "--budget-s", "20", "--budget-evals", "40", "--no-progress", "--no-figures",
        "--plugin", FACTORY]


def _main(*argv) -> int:
    from arraysel.cli.main import main

    return main(list(argv))


def _finished(out: Path) -> list[tuple[str, int]]:
    runs = pd.read_csv(out / "runs.csv", keep_default_na=False)
    return [(c, int(s)) for c, s, m, e in zip(runs["config"], runs["seed"], runs["Mean"], runs["error"])
            if c != "full" and e == "" and m != "" and math.isfinite(float(m))]


def load_with_iohinspector(ioh: Path) -> dict:
    """``{(algorithm, run number): data rows}`` as the installed iohinspector reads ``ioh``."""
    pytest.importorskip("iohinspector")
    return ioh_read(ioh)


def whole(out: Path) -> None:
    """The invariant of the module (see its text)."""
    finished = _finished(out)
    assert len(set(finished)) == len(finished), finished
    trace = pd.read_csv(out / "trace.csv", keep_default_na=False)
    ends = [(c, int(s)) for c, s, e in zip(trace["config"], trace["seed"], trace["event"]) if e == "end"]
    assert sorted(ends) == sorted(finished), (ends, finished)
    table = pd.read_csv(out / "runs.csv", keep_default_na=False)
    runs = {(c, int(s)): r for (c, s), r in zip(zip(table["config"], table["seed"]), table.to_dict("records"))
            if c != "full"}
    ioh_runs, dat_rows = {}, {}
    for js in (out / "ioh").glob("*/IOHprofiler_*.json"):
        meta = json.loads(js.read_text())
        scen = meta["scenarios"][0]
        blocks = (js.parent / scen["path"]).read_text().split("evaluations raw_y seconds\n")[1:]
        assert len(blocks) == len(scen["runs"])
        for number, (run, block) in enumerate(zip(scen["runs"], blocks), 1):
            lines = [line.split() for line in block.strip().splitlines()]
            evals = [int(line[0]) for line in lines]
            assert evals[0] == 1 and evals.count(1) == 1 and evals == sorted(set(evals)), evals
            key = (meta["algorithm"]["name"], int(run["seed"]))
            best = min(float(line[1]) for line in lines)
            assert run["best"]["y"] == best
            row = runs[key]
            n = int(row["n_elements"])
            assert len(run["best"]["x"]) == n and sum(run["best"]["x"]) == int(row["k"])
            ioh_runs[key] = run
            dat_rows[(meta["algorithm"]["name"], number)] = len(lines)
    assert sorted(ioh_runs) == sorted(finished)
    assert load_with_iohinspector(out / "ioh") == dat_rows


# ------------------------------------------------------------------ item 3: resume after a trace was lost
def _first(out: Path, selectors="random,uniform,unscored") -> None:
    assert _main("compare", "--selectors", selectors, "--seeds", "0,1", *ARGS, "--out", str(out),
                 "--in-process") == 0
    whole(out)


def test_resume_after_trace_csv_was_deleted_runs_the_untraced_runs_again(tmp_path, capsys):
    """Issue 77, item 3: before, the finished runs were taken as done and trace.csv and ioh/
    never got their rows back (exit 0, no warning)."""
    out = tmp_path / "cmp"
    _first(out)
    before = pd.read_csv(out / "runs.csv", keep_default_na=False)
    (out / "trace.csv").unlink()
    capsys.readouterr()
    assert _main("compare", "--selectors", "random,uniform,unscored,greedy", "--seeds", "0,1", *ARGS,
                 "--out", str(out), "--in-process", "--resume") == 0
    err = capsys.readouterr().err
    assert ("4 finished run(s) of runs.csv have no single end row in" in err and
            "are run again: random seed 0, random seed 1, uniform seed 0, unscored seed 0" in err), err
    whole(out)
    assert sorted(_finished(out)) == sorted([("random", 0), ("random", 1), ("uniform", 0), ("unscored", 0),
                                             ("greedy", 0)])
    after = pd.read_csv(out / "runs.csv", keep_default_na=False)
    means = {(c, str(s)): m for c, s, m in zip(after["config"], after["seed"], after["Mean"])}
    for c, s, m in zip(before["config"], before["seed"], before["Mean"]):
        assert float(means[(c, str(s))]) == float(m)  # the same runs, made again


@pytest.mark.parametrize("damage", ["cut", "doubled", "ioh deleted"])
def test_resume_after_a_damaged_trace_or_ioh_gives_every_run_its_trace(tmp_path, capsys, damage):
    out = tmp_path / "cmp"
    _first(out)
    trace = (out / "trace.csv").read_text()
    lines = trace.splitlines(keepends=True)
    if damage == "cut":  # the end rows of the runs after the first are gone
        first_end = next(i for i, line in enumerate(lines) if ",end," in line)
        (out / "trace.csv").write_text("".join(lines[:first_end + 1]))
    elif damage == "doubled":
        (out / "trace.csv").write_text(trace + "".join(lines[1:]))
    else:
        import shutil
        shutil.rmtree(out / "ioh")
    capsys.readouterr()
    assert _main("compare", "--selectors", "random,uniform,unscored", "--seeds", "0,1", *ARGS, "--out", str(out),
                 "--in-process", "--resume") == 0
    err = capsys.readouterr().err
    assert ("are run again" in err) is (damage != "ioh deleted"), err
    whole(out)


# ------------------------------------------------------------------ item 4: a run without a trace
@pytest.mark.parametrize("extra", [[], ["--in-process"]], ids=["child", "in-process"])
def test_a_selection_returned_unscored_gets_the_rescore_as_its_end_row_and_ioh_run(tmp_path, extra):
    """Issue 77, item 4: before, ``unscored`` got a correct row but no end row and no IOH run."""
    out = tmp_path / "cmp"
    assert _main("compare", "--selectors", "unscored,uniform", "--seeds", "0", *ARGS, "--out", str(out),
                 *extra) == 0
    whole(out)
    runs = pd.read_csv(out / "runs.csv", keep_default_na=False).set_index("config")
    trace = pd.read_csv(out / "trace.csv", keep_default_na=False)
    mine = trace[trace["config"] == "unscored"]
    assert list(mine["event"]) == ["end"] and int(mine["evaluations"].iloc[0]) == 0
    assert float(mine["best_Mean"].iloc[0]) == float(runs.loc["unscored", "Mean"])
    assert mine["elements"].iloc[0] == runs.loc["unscored", "elements"] == " ".join(map(str, range(0, 64, 2)))
    meta = json.loads((out / "ioh" / "unscored" / "IOHprofiler_f1_toy.json").read_text())
    best = meta["scenarios"][0]["runs"][0]["best"]
    assert best["x"] == [int(i % 2 == 0) for i in range(64)] and best["y"] == float(runs.loc["unscored", "Mean"])


# ------------------------------------------------------------------ item 5: IOH files a standard reader loads
def test_every_selector_s_ioh_run_loads_in_iohinspector(tmp_path):
    """Issue 77, item 5: before, a run whose best had no x made iohinspector refuse the whole
    file, greedy (or any run that scored no k-selection) had no IOH run, and a run of one
    evaluation was read as two."""
    out = tmp_path / "cmp"
    assert _main("compare", "--selectors", "random,greedy,ste,uniform,unscored,one_eval", "--seeds", "0,1",
                 "--scene", "toy", "--budget-s", "1", "--no-progress", "--no-figures", "--plugin", FACTORY,
                 "--out", str(out), "--in-process") in (0, 1)
    whole(out)
    read = load_with_iohinspector(out / "ioh")
    assert {a for a, _ in read} >= {"random", "greedy", "uniform", "unscored", "one_eval"}
    assert sum(1 for a, _ in read if a == "random") == 2


def test_the_ioh_best_is_the_selection_that_scored_it_not_the_returned_one():
    """A run that returned another selection than its best scored one: best.x is the best's."""
    from arraysel.report.tables import write_ioh
    import tempfile

    rows = [{"config": "c", "seed": 0, "n_elements": 8, "k": 2, "Mean": 0.5, "evaluations": 3,
             "elements": "6 7"}]
    trace = [{"config": "c", "seed": 0, "seconds": 0.1, "evaluations": 1, "best_Mean": 0.4, "event": "improvement",
              "elements": ""},
             {"config": "c", "seed": 0, "seconds": 0.2, "evaluations": 3, "best_Mean": 0.4, "event": "end",
              "elements": "0 1"}]
    with tempfile.TemporaryDirectory() as tmp:
        path, = write_ioh(Path(tmp), rows, trace, "p")
        best = json.loads(path.read_text())["scenarios"][0]["runs"][0]["best"]
    assert best == {"evals": 1, "y": 0.4, "x": [1, 1, 0, 0, 0, 0, 0, 0]}
    assert np.isfinite(best["y"])
