"""A sector scene's polish inside a run (``sector.polish``, docs/sector.md): the selector searches on
the beam pattern, then the rest of its budget polishes its selection on the points' per-beam loss;
baselines are left as they are; the polish's scores are charged to the run's budget."""
from __future__ import annotations

import copy

import numpy as np
import pandas as pd
import pytest
import torch

from arraysel.objective.sector_objective import SectorObjective
from arraysel.run.experiment import Experiment
from arraysel.run.sector_report import BeamPolish, beam_polish_plan
from arraysel.scenes.schema import load_scene
from arraysel.selectors.contract import Budget
from arraysel.selectors.registry import get_registry
from scene_texts import TINY_SECTOR

TINY = copy.deepcopy(TINY_SECTOR)
TINY["sector"]["polish"] = 0.5


@pytest.fixture(scope="module")
def tiny():
    return SectorObjective(load_scene(copy.deepcopy(TINY)), dtype=torch.float32)


def test_the_plan_polishes_searches_not_baselines(tiny):
    reg = get_registry()
    for name in ("random", "uniform", "spiral"):
        assert reg[name].baseline and beam_polish_plan(tiny, reg[name], {}) is None, name
    for name in ("swap", "ste", "anneal", "gumbel"):
        plan = beam_polish_plan(tiny, reg[name], {})
        assert isinstance(plan, BeamPolish) and plan.share == 0.5 and plan.width_ratio == 1.048, name
    assert beam_polish_plan(tiny, reg["swap"], {"polish": 0.0}) is None          # the run's own option wins
    assert beam_polish_plan(tiny, reg["random"], {"polish": 0.3}).share == 0.3
    off = SectorObjective(load_scene({**copy.deepcopy(TINY), "sector": {**TINY["sector"], "polish": 0.0}}))
    assert beam_polish_plan(off, reg["swap"], {}) is None
    with pytest.raises(Exception, match="sector.polish"):
        load_scene({**copy.deepcopy(TINY), "sector": {**TINY["sector"], "polish": 0.95}})


def _loss(obj, sel, cap):
    m = np.zeros(obj.n_elements, dtype=bool)
    m[list(sel)] = True
    return float(obj.beam_loss(m[None], width_cap=cap, width_weight=300.0)[0][0])


def test_a_polished_run_lowers_the_per_beam_loss_within_its_budget(tiny):
    # random's best of 150 evaluations on the beam pattern, then 150 evaluations of polish on the points
    row = Experiment(tiny, "random", options={"polish": 0.5}, budget=Budget(evaluations=300), seed=2).execute()
    stage = Experiment(tiny, "random", options={"polish": 0.0}, budget=Budget(evaluations=150), seed=2).execute()
    assert not row["error"] and not stage["error"]
    assert 150 < row["evaluations"] <= 300 and stage["evaluations"] <= 150
    assert '"polish": 0.5' in row["options"]
    plan = BeamPolish(0.5, 1.048)
    plan.prepare(tiny)
    assert _loss(tiny, row["elements"], plan.cap) < _loss(tiny, stage["elements"], plan.cap)
    again = Experiment(tiny, "random", options={"polish": 0.5}, budget=Budget(evaluations=300), seed=2).execute()
    assert list(again["elements"]) == list(row["elements"])       # an evaluation budget: reproducible


@pytest.mark.slow
def test_compare_polishes_the_searches_of_a_sector_scene(tmp_path, tiny):
    from arraysel.run.compare import compare

    compare(tiny, ["random", "uniform", "swap"], out_dir=tmp_path, seeds=[0], budget=Budget(evaluations=300),
            progress=False)
    runs = pd.read_csv(tmp_path / "runs.csv").set_index("config")
    assert '"polish": 0.5' in runs.loc["swap", "options"]
    assert "polish" not in str(runs.loc["random", "options"]) and runs.loc["swap", "evaluations"] <= 300
    beams = pd.read_csv(tmp_path / "beams.csv")
    assert "polish=0.5" in beams.loc[beams["config"] == "swap", "options"].iloc[0]
    assert "polish=0.0" in beams.loc[beams["config"] == "random", "options"].iloc[0]


def _swaps_of_a_base(seed: int, count: int):
    """A random selection of 16 of 64 elements and ``count`` of its one-swap neighbours (row ``i``
    swaps its ``i``-th selected element for its ``i``-th unselected one)."""
    rng = np.random.default_rng(seed)
    base = np.zeros(64, dtype=bool)
    base[rng.choice(64, 16, replace=False)] = True
    on, off = np.flatnonzero(base), np.flatnonzero(~base)
    moves = np.repeat(base[None], count, axis=0)
    moves[np.arange(count), on[:count]] = False
    moves[np.arange(count), off[:count]] = True
    return base, moves


def test_moves_from_a_base_give_the_same_images_and_metrics(tiny):
    """A local search's moves scored from its selection's fast-path sums (``base``: the receive
    sums change by the rows of the elements that differ) equal the same masks scored afresh."""
    base, moves = _swaps_of_a_base(seed=5, count=6)
    moves[5] = base                                  # no move at all: the base itself
    for i in range(tiny.n_points):
        assert tiny.fast_point(i)
        a = tiny.point_images(moves, i)
        b = tiny.point_images(moves, i, base=base)
        assert torch.allclose(a, b, rtol=0, atol=1e-5 * float(a.abs().max())), i
    full = tiny.beam_metrics(moves)
    fromb = tiny.beam_metrics(moves, base=base)
    assert np.allclose(full["PSL_dB"], fromb["PSL_dB"], atol=1e-3)
    assert np.allclose(full["width_x_6dB"], fromb["width_x_6dB"], rtol=1e-4)
    far = np.roll(moves, 7, axis=1)                  # many elements differ: the full product is used
    assert torch.allclose(tiny.point_images(far, 0), tiny.point_images(far, 0, base=base), atol=1e-6)


def test_moves_from_a_base_on_a_mirrored_point():
    from test_sector_fast import SMALL   # points 1 and 2 are x-y mirrors: point 2 takes point 1's model

    obj = SectorObjective(load_scene(copy.deepcopy(SMALL)), dtype=torch.float32)
    base, moves = _swaps_of_a_base(seed=1, count=4)
    for i in (1, 2):
        assert obj.fast_point(i)
        a, b = obj.point_images(moves, i), obj.point_images(moves, i, base=base)
        assert torch.allclose(a, b, rtol=0, atol=1e-5 * float(a.abs().max())), i


def test_the_scene_sets_the_budget_and_seeds_of_its_comparison(tmp_path):
    from arraysel.cli.compare import scene_defaults
    from arraysel.errors import ParameterError

    budget, seeds = scene_defaults("matrix-1024-sector")
    assert seeds == [0] and 60 <= budget <= 300        # one run a selector, within the 30-minute comparison
    assert scene_defaults("matrix-1024") == (None, None) and scene_defaults("toy") == (None, None)
    bad = tmp_path / "bad.toml"
    bad.write_text('base = "matrix-1024-sector"\n[compare]\nseeds = [0, 0]\n')
    with pytest.raises(ParameterError, match="compare.seeds"):
        scene_defaults(str(bad))
    bad.write_text('base = "matrix-1024-sector"\n[compare]\nbudget_s = -5\n')
    with pytest.raises(ParameterError, match="compare.budget_s"):
        scene_defaults(str(bad))


def test_the_guide_proposes_the_swaps_its_gradient_predicts_best(tiny):
    from arraysel.objective.sector_polish import _Guide

    m = tiny.fresh_random_masks(1, seed=3)[0]
    guide = _Guide(tiny, top=6)
    moves = guide.moves(m, [0, 1], 8)
    assert moves.shape == (8, tiny.n_elements) and (moves.sum(1) == m.sum()).all()
    assert ((moves != m).sum(1) == 2).all() and len({r.tobytes() for r in moves}) == 8
    again = guide.moves(m, [0, 1], 8)                # the next ones: none offered twice for a selection
    assert not {r.tobytes() for r in again} & {r.tobytes() for r in moves}
    g = guide._gradient(m, [0, 1])
    assert np.isfinite(g).all() and np.abs(g).max() > 0
    loss = lambda x: float(tiny.beam_metrics(x, points=[0, 1])["PSL_dB"].max(1).mean())  # noqa: E731
    rng = np.random.default_rng(0)
    randoms = np.repeat(m[None], 8, axis=0)
    rows = np.arange(8)
    randoms[rows, rng.choice(np.flatnonzero(m), 8)] = False
    randoms[rows, rng.choice(np.flatnonzero(~m), 8)] = True
    assert loss(moves) < loss(randoms)               # the guided swaps lower the worst side lobe more
