"""``asel.evaluate``: a pandas DataFrame, one row per selection, the numbers of ``arraysel evaluate``."""
from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

import arraysel as asel
from arraysel.errors import ParameterError, SelectionError
from arraysel.objective.metrics import METRIC_NAMES
from arraysel.selection import Selection


def test_one_row_per_selection_with_every_metric():
    sels = [list(range(0, 64, 2)), range(32), Selection(tuple(range(32, 64)), 64)]
    df = asel.evaluate("toy", sels)
    assert isinstance(df, pd.DataFrame) and len(df) == 3
    assert list(df.columns) == ["elements", "k", *METRIC_NAMES]
    assert df["elements"][1] == " ".join(map(str, range(32))) and df["k"].tolist() == [32, 32, 32]
    from arraysel.objective.build import objective_for
    from arraysel.selection import masks_from_indices

    ref = objective_for("toy").evaluate(masks_from_indices([list(range(0, 64, 2))], 64))
    for m in METRIC_NAMES:
        assert df[m][0] == pytest.approx(float(ref[m][0]), rel=1e-12)
    masks = np.zeros((2, 64), dtype=bool)
    masks[0, ::2] = masks[1, :32] = True
    by_mask = asel.evaluate("toy", masks)
    pd.testing.assert_frame_equal(by_mask, df.iloc[:2])
    assert asel.evaluate("toy", [masks[0]])["Mean"][0] == df["Mean"][0]
    assert asel.evaluate("toy", []).empty


def test_bad_selections_are_refused():
    with pytest.raises(SelectionError, match="selection 1: repeated"):
        asel.evaluate("toy", [range(32), [0, 0] + list(range(2, 32))])
    with pytest.raises(ParameterError, match=r"\(B, 64\) masks"):
        asel.evaluate("toy", np.ones((2, 8)))


def test_the_same_numbers_as_the_command(tmp_path):
    from scene_texts import TINY_SCENE

    from arraysel.cli.main import main

    scene = tmp_path / "tiny.toml"
    scene.write_text(TINY_SCENE)
    (tmp_path / "m.txt").write_text("0 2 5 7\n1 2 3 4\n")
    assert main(["evaluate", "--scene", str(scene), "--masks", str(tmp_path / "m.txt"),
                 "--out", str(tmp_path / "e.csv")]) == 0
    cli = pd.read_csv(tmp_path / "e.csv")
    df = asel.evaluate(str(scene), [[0, 2, 5, 7], [1, 2, 3, 4]])
    assert df["elements"].tolist() == cli["elements"].tolist()
    for m in METRIC_NAMES:
        np.testing.assert_allclose(df[m], cli[m], rtol=1e-7)        # the CSV holds 8 digits
