"""Apodization after selection (arraysel.selectors.apodization, arraysel apodize): the gradient of
the weights -> loss path against finite differences, bounds, unselected elements at 0, the loss
never above the binary selection's, bad options named, the table's rows, the command end to end."""
from __future__ import annotations

import csv
import json

import numpy as np
import pytest
import torch

from arraysel.cli.main import main
from arraysel.errors import ParameterError, SelectionError
from arraysel.objective.psf_objective import Objective
from arraysel.selectors.apodization import PSL_NAME, apodize
from scene_texts import TINY_SCENE

SELECTED = [0, 2, 3, 5, 7]


@pytest.fixture(scope="module")
def tiny_path(tmp_path_factory):
    p = tmp_path_factory.mktemp("scenes") / "tiny.toml"
    p.write_text(TINY_SCENE.replace("k = 4", "k = 5"))
    return str(p)


@pytest.fixture(scope="module")
def tiny(tiny_path):
    return Objective(tiny_path, dtype=torch.float64)


def _mask(n=8, sel=SELECTED):
    m = np.zeros(n)
    m[sel] = 1
    return m


def test_gradcheck_of_the_weights_to_loss_path(tiny):
    """The gradient apodize follows: the scene's loss of the selected elements' weights, float64."""
    idx = torch.tensor(SELECTED)
    g = torch.Generator().manual_seed(0)
    v = (0.4 + 0.5 * torch.rand(len(SELECTED), generator=g, dtype=torch.float64)).requires_grad_(True)

    def f(x):
        w = torch.zeros(1, 8, dtype=torch.float64).index_put((torch.zeros_like(idx), idx), x)
        return tiny.mask_loss(w)[0]

    assert torch.autograd.gradcheck(f, (v,), eps=1e-6, atol=1e-5, rtol=1e-3)


@pytest.mark.parametrize("method, w_min", [("adam", 0.0), ("adam", 0.3), ("lbfgsb", 0.2)])
def test_weights_are_bounded_zero_off_the_selection_and_lower_the_loss(tiny, method, w_min):
    res = apodize(tiny, _mask(), w_min=w_min, steps=25, lr=0.05, method=method)
    on = _mask() > 0
    assert (res.weights[~on] == 0).all()
    assert (res.weights[on] >= w_min - 1e-12).all() and (res.weights[on] <= 1.0).all()
    assert res.weights[on].max() == pytest.approx(1.0)
    assert res.loss_apodized <= res.loss_binary
    assert res.loss_apodized < 0.99 * res.loss_binary      # the weights do help on this selection
    assert res.history[0] == pytest.approx(res.loss_binary) and min(res.history) == pytest.approx(res.loss_apodized)
    # the losses are the objective's own, of the 0/1 mask and of the weights
    again = tiny.mask_loss(torch.tensor(res.weights[None]))[0]
    assert float(again) == pytest.approx(res.loss_apodized, rel=1e-9)
    assert float(tiny.mask_loss(torch.tensor(_mask()[None]))[0]) == pytest.approx(res.loss_binary, rel=1e-9)
    ev = tiny.evaluate(_mask()[None])
    assert res.metrics_binary["Mean"] == pytest.approx(float(ev["Mean"][0]))
    assert PSL_NAME in res.metrics_apodized and res.metrics_apodized[PSL_NAME] < 0


@pytest.mark.parametrize("kw, name", [({"w_min": 1.0}, "w_min"), ({"w_min": -0.1}, "w_min"), ({"steps": 0}, "steps"),
                                      ({"lr": 0.0}, "lr"), ({"method": "sgd"}, "method"), ({"steps": 2.5}, "steps")])
def test_bad_options_are_named(tiny, kw, name):
    with pytest.raises(ParameterError, match=name):
        apodize(tiny, _mask(), **kw)


def test_bad_masks_are_refused(tiny):
    with pytest.raises(SelectionError, match="shape"):
        apodize(tiny, np.ones(9))
    with pytest.raises(SelectionError, match="0/1"):
        apodize(tiny, np.full(8, 0.5))
    with pytest.raises(SelectionError, match="empty"):
        apodize(tiny, np.zeros(8))


def _rows(path):
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


def test_cli_from_a_mask_file_writes_binary_and_apodized_rows(tiny_path, tmp_path, capsys):
    masks = tmp_path / "masks.txt"
    masks.write_text("0 2 3 5 7\n# a comment\n1,2,4,6,7\n")
    out = tmp_path / "out"
    assert main(["apodize", "--scene", tiny_path, "--masks", str(masks), "--out", str(out), "--steps", "5",
                 "--w-min", "0.1", "--dtype", "float64"]) == 0
    rows = _rows(out / "apodize.csv")
    assert [(r["selection"], r["weighting"]) for r in rows] == [("1", "binary"), ("1", "apodized"),
                                                              ("2", "binary"), ("2", "apodized")]
    assert rows[0]["elements"] == "0 2 3 5 7" and rows[0]["min_weight"] == "1"
    for b, a in zip(rows[::2], rows[1::2]):
        assert float(a["loss"]) <= float(b["loss"]) and 0.1 <= float(a["min_weight"]) <= 1
        assert {"Mean", "L_SLR_q", PSL_NAME} <= set(a)
    w = _rows(out / "weights.csv")
    assert [int(r["element"]) for r in w if r["selection"] == "1"] == SELECTED
    doc = json.loads((out / "weights.json").read_text())
    assert doc["selections"][1]["elements"] == [1, 2, 4, 6, 7] and doc["selections"][1]["options"]["steps"] == 5
    assert all(0.1 <= x <= 1 for s in doc["selections"] for x in s["weights"])
    # an earlier run is kept unless --force
    assert main(["apodize", "--scene", tiny_path, "--masks", str(masks), "--out", str(out)]) == 2
    assert "--force" in capsys.readouterr().err


@pytest.mark.parametrize("args, text", [
    (["--steps", "0"], "steps"), (["--w-min", "1.5"], "w_min"), (["--lr", "-1"], "lr"),
    (["--configs", "ste"], "--configs goes with --from-compare"),
])
def test_cli_bad_options_are_named(tiny_path, tmp_path, capsys, args, text):
    masks = tmp_path / "masks.txt"
    masks.write_text("0 2 3 5 7\n")
    code = main(["apodize", "--scene", tiny_path, "--masks", str(masks), "--out", str(tmp_path / "o"), *args])
    assert code == 2 and text in capsys.readouterr().err


def test_cli_needs_one_source(tmp_path, capsys):
    assert main(["apodize", "--scene", "paper", "--out", str(tmp_path / "o")]) == 2
    assert "--masks FILE" in capsys.readouterr().err
    assert main(["apodize", "--from-compare", str(tmp_path), "--out", str(tmp_path / "o")]) == 2
    assert "run.json" in capsys.readouterr().err


def test_cli_from_a_comparison_on_the_paper_scene(tmp_path, capsys):
    """End to end on the paper scene: a comparison folder's rows (two configs, one chosen)."""
    from arraysel.scenes.best_known import best_known
    from arraysel.scenes.schema import load_scene

    best = best_known("paper")
    sel = best["elements"]
    folder = tmp_path / "cmp"
    folder.mkdir()
    (folder / "run.json").write_text(json.dumps({"scene": load_scene("paper").to_dict()}))
    (folder / "table1.csv").write_text("config,Mean,elements\nfull,0.03,\nbest,0.0047," + " ".join(map(str, sel))
                                       + "\nuniform,0.07," + " ".join(str(i) for i in range(0, 64, 2)) + "\n")
    out = tmp_path / "out"
    assert main(["apodize", "--from-compare", str(folder), "--configs", "best", "--out", str(out),
                 "--steps", "3"]) == 0
    rows = _rows(out / "apodize.csv")
    assert [(r["config"], r["weighting"]) for r in rows] == [("best", "binary"), ("best", "apodized")]
    assert float(rows[0]["Mean"]) == pytest.approx(best["Mean"], rel=1e-4)
    assert float(rows[1]["loss"]) <= float(rows[0]["loss"])
    assert main(["apodize", "--from-compare", str(folder), "--configs", "nope", "--out", str(tmp_path / "o2")]) == 2
    assert "best" in capsys.readouterr().err
