"""Hostile cases, ``arraysel report`` on hand-edited or half-written folders: deleted rows, NaN
and text cells, extra columns, a file cut short, a run listed twice, a seed that is not one.

An edit the tables can be built from gives the numbers of the rows that are there (a deleted
run is one seed fewer, a NaN Mean one failed run, an extra column is ignored); an edit that would
be read silently as something else (a line cut short, a run listed twice, text where a number
goes) is refused in one line naming the file and the line, exit code 2.
"""
from __future__ import annotations

import shutil
from pathlib import Path

import pandas as pd
import pytest

from arraysel.cli.main import main
from support import own_plugin_manager, time_limit  # noqa: F401  (autouse fixtures)

_bounded = time_limit(120)


@pytest.fixture(scope="module")
def finished(tmp_path_factory) -> Path:
    from arraysel.selectors import registry

    out = tmp_path_factory.mktemp("rep") / "cmp"
    registry.reset()
    try:
        assert main(["compare", "--selectors", "random,uniform", "--scene", "toy", "--seeds", "0,1,2", "--budget-s",
                     "20", "--budget-evals", "40", "--out", str(out), "--no-progress", "--no-figures",
                     "--in-process"]) == 0
    finally:
        registry.reset()
    return out


def _copy(finished: Path, tmp_path: Path) -> Path:
    folder = tmp_path / "cmp"
    shutil.copytree(finished, folder)
    return folder


def _edit_lines(path: Path, edit) -> None:
    path.write_text("".join(edit(path.read_text().splitlines(keepends=True))))


def _edit_cells(path: Path, edit) -> None:
    table = pd.read_csv(path, keep_default_na=False, dtype=str)
    edit(table)
    table.to_csv(path, index=False)


def _row(table, config, seed):
    return table.index[(table["config"] == config) & (table["seed"] == str(seed))][0]


def _report(folder: Path, capsys) -> tuple[int, dict, list[str]]:
    """Exit code, ``{selector: cells}`` of the Markdown table, stderr lines."""
    code = main(["report", str(folder)])
    out, err = capsys.readouterr()
    rows = {}
    for line in out.splitlines():
        cells = [c.strip() for c in line.strip("|").split("|")]
        if line.startswith("| ") and cells[0] not in ("selector", "---"):
            rows[cells[0]] = cells
    return code, rows, err.strip().splitlines()


def _median(means) -> str:
    return f"{pd.Series(means).median():.4g}"


def _random_means(folder: Path) -> list[float]:
    runs = pd.read_csv(folder / "runs.csv")
    return list(runs.loc[runs["config"] == "random", "Mean"].dropna())


# ------------------------------------------------------------------ edits the tables are built from
def test_a_deleted_run_is_one_seed_fewer(finished, tmp_path, capsys):
    folder = _copy(finished, tmp_path)
    _edit_cells(folder / "runs.csv", lambda t: t.drop(index=_row(t, "random", 1), inplace=True))
    code, rows, err = _report(folder, capsys)
    assert code == 0 and err == []
    assert rows["random"][6] == "2" and rows["random"][7].startswith(_median(_random_means(folder)) + " [")


def test_a_nan_mean_is_a_failed_run_and_shows_as_one(finished, tmp_path, capsys):
    folder = _copy(finished, tmp_path)
    _edit_cells(folder / "runs.csv", lambda t: t.loc.__setitem__((_row(t, "random", 2), "Mean"), "nan"))
    code, rows, err = _report(folder, capsys)
    assert code == 0 and rows["random"][6] == "2 (+1 failed)"
    assert rows["random"][7].startswith(_median(_random_means(folder)) + " [")


def test_extra_columns_a_deleted_full_row_and_a_missing_trace_change_nothing_else(finished, tmp_path, capsys):
    _, want, _ = _report(finished, capsys)
    folder = _copy(finished, tmp_path)
    _edit_cells(folder / "runs.csv", lambda t: (t.insert(0, "notes", "mine"), t.__setitem__("extra", 1.5)))
    code, rows, err = _report(folder, capsys)
    assert code == 0 and rows == want
    _edit_cells(folder / "runs.csv", lambda t: t.drop(index=_row(t, "full", ""), inplace=True))
    (folder / "trace.csv").unlink()
    code, rows, err = _report(folder, capsys)
    assert code == 0 and rows == {k: v for k, v in want.items() if k != "full"}


def test_a_table_saved_by_pandas_with_float_seeds_is_read(finished, tmp_path, capsys):
    _, want, _ = _report(finished, capsys)
    folder = _copy(finished, tmp_path)
    pd.read_csv(finished / "runs.csv").to_csv(folder / "runs.csv", index=False)  # seeds become 0.0, 1.0, ...
    code, rows, err = _report(folder, capsys)
    assert code == 0 and rows == want


# ------------------------------------------------------------------ edits that would be read as something else
REFUSED = {
    "last line cut short": ("runs.csv", lambda p: _edit_lines(p, lambda L: L[:-1] + [L[-1][:40]]),
                            "line 6 has 7 fields, the header 20: the file was cut short or edited"),
    "last number cut short": ("runs.csv", lambda p: _edit_lines(p, lambda L: L[:-1] + [L[-1][:L[-1].index(",0.") + 5]]),
                              "fields, the header 20: the file was cut short or edited"),
    "a run listed twice": ("runs.csv", lambda p: _edit_lines(p, lambda L: L + [L[2]]), "both list random seed 0"),
    "text in a number column": ("runs.csv", lambda p: _edit_cells(p, lambda t: t.loc.__setitem__(
        (_row(t, "random", 1), "Mean"), "0.1o")), "Mean = '0.1o' is not a number"),
    "a seed that is not a whole number": ("runs.csv", lambda p: _edit_cells(p, lambda t: t.loc.__setitem__(
        (_row(t, "random", 1), "seed"), "1.5")), "random has seed '1.5', not a whole number >= 0"),
    "a run without a seed": ("runs.csv", lambda p: _edit_cells(p, lambda t: t.loc.__setitem__(
        (_row(t, "random", 1), "seed"), "")), "random has seed '', not a whole number >= 0"),
    "trace cut short": ("trace.csv", lambda p: p.write_text(p.read_text()[:150]),
                        "the file was cut short or edited"),
    "text in the trace": ("trace.csv", lambda p: _edit_cells(p, lambda t: t.loc.__setitem__((1, "best_Mean"), "x")),
                          "best_Mean = 'x' is not a number"),
}


@pytest.mark.parametrize("case", sorted(REFUSED))
def test_an_edit_that_would_be_read_as_something_else_is_refused_naming_the_line(finished, tmp_path, capsys, case):
    name, edit, said = REFUSED[case]
    folder = _copy(finished, tmp_path)
    edit(folder / name)
    code, rows, err = _report(folder, capsys)
    assert code == 2 and rows == {} and len(err) == 1, err
    assert err[0].startswith(f"arraysel report: error: {folder / name} cannot be read (ValueError: line") and \
        said in err[0], err[0]
    assert main(["report", str(folder), "--rebuild"]) == 2  # nor are tables rebuilt from it
    assert (folder / "stats.csv").read_text() == (finished / "stats.csv").read_text()
    capsys.readouterr()


def test_resume_refuses_a_runs_csv_that_lists_a_run_twice(finished, tmp_path, capsys):
    folder = _copy(finished, tmp_path)
    _edit_lines(folder / "runs.csv", lambda L: L + [L[2]])
    code = main(["compare", "--selectors", "random,uniform", "--scene", "toy", "--seeds", "0,1,2", "--budget-s", "20",
                 "--budget-evals", "40", "--out", str(folder), "--no-progress", "--no-figures", "--in-process",
                 "--resume"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and "is damaged (ValueError: lines 3 and 7 both list random seed 0)" in err[-1], err
