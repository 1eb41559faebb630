"""Neighbourhoods of a 3-D scene (arraysel.objective.matrix_neighbours): the neighbours' scores
from the selection's image equal the neighbour masks scored independently (every metric, float64,
a whole neighbourhood from the selection's image, a few swaps and moves of several elements as
masks), gradients are untouched,
and the swap engine uses it and finds a planted optimum."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from arraysel.objective.contract import ScoresMoves, ScoresSwaps
from arraysel.objective.matrix_objective import MatrixObjective
from arraysel.objective.neighbours import move_masks, swap_masks, swap_pairs
from scene_texts import TINY_MATRIX_SCENE

#: an 8 x 8 probe, 16 of 64 elements
SMALL = (TINY_MATRIX_SCENE.replace("nx = 4", "nx = 8").replace("ny = 4", "ny = 8").replace("k = 4", "k = 16")
         .replace('name = "tiny3d"', 'name = "small3d"'))


@pytest.fixture(scope="module")
def small(tmp_path_factory):
    p = tmp_path_factory.mktemp("scenes") / "small3d.toml"
    p.write_text(SMALL)
    obj = MatrixObjective(str(p), dtype=torch.float64)
    assert obj.fast
    return obj


def _mask(obj, seed):
    rng = np.random.default_rng(seed)
    m = np.zeros(obj.n_elements, dtype=bool)
    m[rng.choice(obj.n_elements, obj.k, replace=False)] = True
    return m


def _same(got, ref, rtol=1e-10):
    assert set(got) == set(ref)
    for k in ref:
        np.testing.assert_allclose(got[k], ref[k], rtol=rtol, atol=1e-12, err_msg=k)


def test_the_matrix_objective_has_the_capabilities(small):
    assert isinstance(small, ScoresSwaps) and isinstance(small, ScoresMoves)


@pytest.mark.parametrize("seed", [0])
def test_whole_neighbourhood_equals_independent_masks(small, seed):
    m = _mask(small, seed)
    out, into = swap_pairs(m, np.random.default_rng(seed))
    assert out.size == 16 * 48
    before = small.evaluations
    assert small._neighbourhood().dense(out)
    got = small.evaluate_swaps(m, out, into)
    assert small.evaluations - before == out.size
    _same(got, small.evaluate(swap_masks(m, out, into)))


def test_a_few_swaps_move_by_move_equal_independent_masks(small):
    m = _mask(small, 2)
    out, into = swap_pairs(m, np.random.default_rng(2))
    out, into = out[:7], into[:7]       # sparse: scored as masks
    assert not small._neighbourhood().dense(out)
    _same(small.evaluate_swaps(m, out, into), small.evaluate(swap_masks(m, out, into)))


def test_moves_of_several_elements_equal_independent_masks(small):
    m = _mask(small, 3)
    rng = np.random.default_rng(3)
    on, off = np.flatnonzero(m), np.flatnonzero(~m)
    out = np.stack([rng.choice(on, 3, replace=False) for _ in range(12)])
    into = np.stack([rng.choice(off, 3, replace=False) for _ in range(12)])
    out[:4, 2] = into[:4, 2] = -1       # moves of two elements, padded
    _same(small.evaluate_moves(m, out, into), small.evaluate(move_masks(m, out, into)))


def test_a_walk_of_selections_keeps_each_image_right(small):
    # the held image follows the selection: after a move, the next neighbourhood is the new one's
    m = _mask(small, 4)
    rng = np.random.default_rng(4)
    for _ in range(3):
        out, into = swap_pairs(m, rng)
        got = small.evaluate_swaps(m, out, into)
        assert small._neighbourhood()._key == m.tobytes()
        _same(got, small.evaluate(swap_masks(m, out, into)))
        m = swap_masks(m, out[:1], into[:1])[0]


def test_gradients_are_unaffected(small):
    m = _mask(small, 5)
    w = torch.tensor(m, dtype=torch.float64)[None].clone().requires_grad_(True)
    small.psf_terms(w)["Mean"].sum().backward()
    g0 = w.grad.clone()
    out, into = swap_pairs(m)
    small.evaluate_swaps(m, out, into)
    w.grad = None
    small.psf_terms(w)["Mean"].sum().backward()
    assert torch.equal(g0, w.grad)


def test_float32_neighbourhood_is_within_rounding(small, tmp_path):
    p = tmp_path / "small3d.toml"
    p.write_text(SMALL)
    obj = MatrixObjective(str(p), dtype=torch.float32)
    m = _mask(obj, 6)
    out, into = swap_pairs(m)
    got, ref = obj.evaluate_swaps(m, out, into), obj.evaluate(swap_masks(m, out, into))
    np.testing.assert_allclose(got["Mean"], ref["Mean"], rtol=1e-4)


def test_exact_path_scores_the_masks(tmp_path):
    p = tmp_path / "tiny.toml"
    p.write_text(TINY_MATRIX_SCENE.replace("[volume]", "[volume]\nfast = false"))
    obj = MatrixObjective(str(p), dtype=torch.float64)
    assert not obj.fast and obj._neighbourhood() is None
    m = _mask(obj, 7)
    out, into = swap_pairs(m)
    _same(obj.evaluate_swaps(m, out, into), obj.evaluate(swap_masks(m, out, into)))


@pytest.mark.slow
def test_swap_finds_the_planted_optimum_of_a_small_matrix_scene(tmp_path):
    # 4 x 4 probe, k = 4: 1820 selections, the best found by scoring all of them; swap with a
    # budget of about a third of them finds it
    from itertools import combinations

    from arraysel.run.experiment import Experiment
    from arraysel.selectors.contract import Budget
    from test_conformance import REGISTRY

    p = tmp_path / "tiny.toml"
    p.write_text(TINY_MATRIX_SCENE)
    obj = MatrixObjective(str(p), dtype=torch.float64)
    combos = np.array(list(combinations(range(16), 4)))
    masks = np.zeros((len(combos), 16), dtype=bool)
    np.put_along_axis(masks, combos, True, axis=1)
    best = float(np.min(obj.evaluate(masks)["Mean"]))
    row = Experiment(obj, REGISTRY["swap"], options={}, budget=Budget(evaluations=600), seed=0, k=4).run()
    assert row["error"] == "", row["error"]
    assert row["Mean"] == pytest.approx(best, rel=1e-9)
