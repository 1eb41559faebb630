"""The one selection type (arraysel.selection.Selection): its forms, its checks, and the figures
and tables that take it."""
from __future__ import annotations

import math
import pickle

import numpy as np
import pytest

from arraysel.errors import SelectionError
from arraysel.selection import Selection, format_elements


def test_forms_round_trip():
    s = Selection.of(np.array([6, 0, 2]), 8)
    assert s.indices == (0, 2, 6) and s.n_elements == 8 and len(s) == 3 and list(s) == [0, 2, 6]
    assert s.text == str(s) == format_elements([0, 2, 6]) == "0 2 6"
    assert s.mask.dtype == bool and s.mask.nonzero()[0].tolist() == [0, 2, 6]
    assert Selection.from_text(s.text, 8) == s == Selection.from_mask(s.mask)
    assert Selection.from_mask(np.array([0.9, 0.1, 0.6])) == Selection((0, 2), 3)
    assert pickle.loads(pickle.dumps(s)) == s
    empty = Selection.from_text("", 4)
    assert len(empty) == 0 and empty.text == "" and not empty.mask.any()


@pytest.mark.parametrize("make, match", [
    (lambda: Selection.of([0, 0, 1], 4), "repeats"),
    (lambda: Selection.of([0, 4], 4), r"\[0, 3\]"),
    (lambda: Selection.of([0, 1], 4, k=3), "k = 3"),
    (lambda: Selection.of([0.5], 4), "whole numbers"),
    (lambda: Selection.from_text("0 two", 4), "not a list of element indices"),
    (lambda: Selection((0,), 0), "n_elements"),
])
def test_bad_selections_are_refused_by_name(make, match):
    with pytest.raises(SelectionError, match=match):
        make()


def test_best_rows_keep_the_run_table1_keeps():
    import pandas as pd

    from arraysel.report.columns import ROW_COLUMNS
    from arraysel.report.tables import best_rows, table1

    rows = [{c: "" for c in ROW_COLUMNS} for _ in range(5)]
    for r, (config, seed, mean, elements) in zip(rows, [("a", 0, 0.5, "0 1"), ("b", 0, math.nan, "2 3"),
                                                        ("a", 1, 0.25, "1 2"), ("b", 1, math.nan, "0 3"),
                                                        ("a", 2, math.nan, "0 2")]):
        r.update(config=config, seed=seed, Mean=mean, elements=elements, error="")
    best = best_rows(rows)
    assert list(best) == ["a", "b"] and best["a"]["elements"] == "1 2" and best["b"]["elements"] == "2 3"
    table = table1(pd.DataFrame(rows, columns=list(ROW_COLUMNS))).set_index("config")
    assert all(table.loc[c, "elements"] == best[c]["elements"] for c in best)


def test_selections_figure_draws_the_non_empty_selections():
    from matplotlib.figure import Figure

    from arraysel.report import plots

    sels = {"uniform": Selection.of([0, 2], 4), "failed": Selection.from_text("", 4),
            "full": Selection.of(range(4), 4)}
    fig = plots.selections_figure(sels)
    assert isinstance(fig, Figure)
    assert [t.get_text() for t in fig.axes[0].get_yticklabels()] == ["uniform", "full"]
    image = fig.axes[0].images[0].get_array()
    assert np.array_equal(np.asarray(image), [[1, 0, 1, 0], [1, 1, 1, 1]])


def test_flagged_elements_lists_each_rows_elements_padded():
    from arraysel.selection import flagged_elements

    flags = np.array([[0, 1, 0, 1, 1], [0, 0, 0, 0, 0], [1, 0, 0, 0, 0]], dtype=bool)
    assert flagged_elements(flags).tolist() == [[1, 3, 4], [-1, -1, -1], [0, -1, -1]]
    assert flagged_elements(flags, 4).tolist() == [[1, 3, 4, -1], [-1, -1, -1, -1], [0, -1, -1, -1]]
    assert flagged_elements(np.zeros((2, 5), dtype=bool)).shape == (2, 0)
    assert flagged_elements(np.zeros((0, 5), dtype=bool)).shape == (0, 0)
    assert flagged_elements(flags).dtype == np.int64
    with pytest.raises(SelectionError, match="width"):
        flagged_elements(flags, 2)
