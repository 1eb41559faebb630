"""Neighbourhoods of a 3-D scene (arraysel.objective.matrix_neighbours): the neighbours' scores
from the selection's image equal the neighbour masks scored independently (every metric, float64,
a whole neighbourhood from the selection's image, a few swaps and moves of several elements as
masks), blocks of swaps along a walk of selections carry the selection's columns exactly,
gradients are untouched, and the swap engine asks for whole blocks, counts each neighbour and
finds a planted optimum."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from arraysel.objective.contract import ScoresMoves, ScoresSwaps, SwapBlock
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
    assert small._neighbourhood().dense(out).all()
    got = small.evaluate_swaps(m, out, into)
    assert small.evaluations - before == out.size
    _same(got, small.evaluate(swap_masks(m, out, into)))


def test_a_block_with_swaps_asked_twice_equals_independent_masks(small):
    m = _mask(small, 5)
    out, into = swap_pairs(m)
    pick = np.flatnonzero(np.isin(out, np.unique(out)[:2]))
    pick = np.concatenate([pick, pick[[3, 0, 50]]])     # three swaps asked for twice, in another order
    assert small._neighbourhood().dense(out[pick]).all()
    _same(small.evaluate_swaps(m, out[pick], into[pick]), small.evaluate(swap_masks(m, out[pick], into[pick])))


def test_a_few_swaps_move_by_move_equal_independent_masks(small):
    m = _mask(small, 2)
    out, into = swap_pairs(m, np.random.default_rng(2))
    out, into = out[:7], into[:7]       # sparse: each formed from its own rows
    assert not small._neighbourhood().dense(out).any()
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


def test_the_neighbourhood_prefers_blocks_of_one_outgoing_element(small):
    assert small.neighbourhood().block() == SwapBlock(outgoing=1)


def test_a_walk_of_blocks_carries_the_columns_exactly(small):
    # a descent's walk: each step every swap of one outgoing element (a block), then a move of one
    # swap (every other step two moves in a row); the columns of the last selection are carried
    # over, not formed afresh, and every score equals the neighbour masks scored independently
    m = _mask(small, 8)
    rng = np.random.default_rng(8)
    nb = small._neighbourhood()
    nb.forget()
    for step in range(6):
        out, into = swap_pairs(m, rng)
        pick = out == out[0]
        _same(small.evaluate_swaps(m, out[pick], into[pick]), small.evaluate(swap_masks(m, out[pick], into[pick])))
        m = swap_masks(m, out[:1], into[:1])[0]
        if step % 2:
            nb.select(m)   # two selections in a row without a block between: their moves add up
            o2, i2 = swap_pairs(m, rng)
            m = swap_masks(m, o2[:1], i2[:1])[0]
    assert nb._carried == 8      # five selections the blocks asked for, three in between


def test_a_descent_asks_for_whole_blocks_and_counts_each_neighbour(small):
    from arraysel.selectors.contract import Budget, BudgetedObjective, Recorder
    from arraysel.selectors.localsearch import SwapSearch

    budget = Budget(evaluations=5000).start(small)
    view = BudgetedObjective(small, budget, Recorder(small, budget), small.k)
    search = SwapSearch(view, small.k, np.random.default_rng(9), race=1, shift=0, guide=0.0)  # no model: no Hessian
    assert search.block == SwapBlock(outgoing=1)
    inner, calls = search.neighbourhood, []

    class Spy:
        def evaluate(self, mask, out, into):
            calls.append(np.asarray(out).reshape(-1))
            return inner.evaluate(mask, out, into)

        def block(self):
            return inner.block()

    search.neighbourhood = Spy()
    m = _mask(small, 9)
    v = float(search.score(m[None])[0])
    used = budget.used_evaluations()
    search.descend(m, v)
    assert calls and budget.used_evaluations() - used == sum(c.size for c in calls) == search.scored - 1
    n_in = small.n_elements - small.k
    for out in calls:   # chunk 64 of 48 swaps an outgoing element: two outgoing elements a call
        _, counts = np.unique(out, return_counts=True)
        assert counts.size <= 2 and (counts >= n_in - 1).all()     # less a neighbour seen before


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
