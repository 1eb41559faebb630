"""A third-party plugin written against the documented selector contract (tests/thirdparty_plugin.py,
kept unchanged) still loads, passes the conformance suite and runs on a 1-D scene, a matrix scene
and a sector scene: what arraysel changes inside must not break what its users wrote."""
from __future__ import annotations

import copy
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from arraysel.objective.build import build_objective
from arraysel.run.experiment import Experiment
from arraysel.scenes.schema import load_scene
from arraysel.selectors.contract import Budget
from arraysel.selectors.registry import build_plugin_manager, get_registry, load_plugin
from arraysel.testing import SelectorConformance
from scene_texts import TINY_MATRIX_SCENE

PLUGIN = Path(__file__).with_name("thirdparty_plugin.py")


def _registry():
    pm = build_plugin_manager(load_entrypoints=False, disabled=())
    load_plugin(str(PLUGIN), pm)
    return get_registry(pm)


REGISTRY = _registry()


def _seen():
    import sys

    mod = next(m for name, m in sys.modules.items() if name.startswith("arraysel_plugin_file_")
               and getattr(m, "__file__", None) and Path(m.__file__).resolve() == PLUGIN.resolve())
    return mod.SEEN


class TestThirdPartyConformance(SelectorConformance):
    selector_name = "tp-descent"
    registry = REGISTRY


def _run(objective, k, evals=40):
    cls = REGISTRY["tp-descent"]
    exp = Experiment(objective, cls, options={"steps": 2, "batch": 4}, budget=Budget(evaluations=evals), seed=3, k=k)
    row = exp.run()
    assert row["error"] == "", row["error"]
    sel = [int(i) for i in row["elements"].split()]
    n = int(objective.n_elements)
    assert len(sel) == k == len(set(sel)) and all(0 <= i < n for i in sel)
    assert row["evaluations"] <= evals + 4
    seen = _seen()
    assert seen["n_elements"] == n and seen["dtype"] == objective.dtype and seen["scene"] is objective.scene
    assert math.isfinite(seen["first_mean"]) and row["Mean"] <= seen["first_mean"] + 1e-9
    assert seen["best_mean"] <= seen["first_mean"] + 1e-9 and len(seen["best"]) == k
    assert seen["remaining"] <= evals
    return row


def test_on_the_paper_scene():
    _run(build_objective("paper"), 32)


def test_on_the_paper_scene_with_every_element():
    row = _run(build_objective("paper"), 64, evals=12)     # k = Ne: no swap to make
    assert row["k"] == 64


def test_on_a_matrix_scene(tmp_path):
    p = tmp_path / "tiny3d.toml"
    p.write_text(TINY_MATRIX_SCENE)
    obj = build_objective(load_scene(str(p)), dtype=torch.float64)
    _run(obj, int(obj.k))


def test_on_a_sector_scene():
    from test_sector import TINY

    obj = build_objective(load_scene(copy.deepcopy(TINY)), dtype=torch.float32)
    row = _run(obj, int(obj.k), evals=24)
    assert np.isfinite(row["Mean"])
