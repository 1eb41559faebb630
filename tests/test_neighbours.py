"""One-swap neighbourhoods (arraysel.objective.neighbours): the pairs, the masks, the scores through an
objective's own ``evaluate_swaps`` or by independent masks, and the runner's bookkeeping of them."""
from __future__ import annotations

import numpy as np
import pytest

from arraysel.errors import SelectionError
from arraysel.objective.contract import ScoresSwaps
from arraysel.objective.neighbours import evaluate_swaps, swap_masks, swap_pairs
from arraysel.selectors.contract import Budget, BudgetedObjective, BudgetExhausted, Recorder
from arraysel.testing import ToyObjective


def _mask(n, on):
    m = np.zeros(n, dtype=bool)
    m[list(on)] = True
    return m


def test_swap_pairs_list_every_neighbour_once():
    m = _mask(7, [0, 3, 5])
    out, into = swap_pairs(m)
    assert out.size == 3 * 4 and set(zip(out.tolist(), into.tolist())) == {(a, b) for a in (0, 3, 5)
                                                                           for b in (1, 2, 4, 6)}
    cands = swap_masks(m, out, into)
    assert (cands.sum(1) == 3).all() and len({c.tobytes() for c in cands}) == 12
    o2, i2 = swap_pairs(m, np.random.default_rng(0))
    assert sorted(zip(o2.tolist(), i2.tolist())) == sorted(zip(out.tolist(), into.tolist()))


def test_bad_swaps_name_the_argument():
    m = _mask(6, [0, 1, 2])
    with pytest.raises(SelectionError, match="out must name active elements"):
        swap_masks(m, [3], [4])
    with pytest.raises(SelectionError, match="into must name inactive elements"):
        swap_masks(m, [0], [1])
    with pytest.raises(SelectionError, match="into holds element indices outside"):
        swap_masks(m, [0], [9])
    with pytest.raises(SelectionError, match="same length"):
        swap_masks(m, [0, 1], [4])
    with pytest.raises(SelectionError, match="one selection"):
        swap_masks(np.ones((2, 6), bool), [0], [1])


def test_fallback_scores_equal_independent_masks_in_float64():
    obj = ToyObjective(14, 6, dtype=__import__("torch").float64)
    m = _mask(14, [0, 2, 5, 7, 9, 12])
    out, into = swap_pairs(m, np.random.default_rng(3))
    got = evaluate_swaps(obj, m, out, into)
    ref = obj.evaluate(swap_masks(m, out, into))
    assert set(got) == set(ref)
    for key in ref:
        np.testing.assert_allclose(got[key], ref[key], rtol=1e-13, atol=0)


class _OwnSwaps(ToyObjective):
    """A toy objective with the capability: scores the neighbours from the base mask's array factor
    and the two elements' terms (what the capability is for), and counts its calls."""

    calls = 0

    def evaluate_swaps(self, mask, out, into):
        type(self).calls += 1
        return self.evaluate(swap_masks(mask, out, into))


def test_an_objective_s_own_neighbourhood_scoring_is_used_and_budgeted():
    obj = _OwnSwaps(12, 5)
    assert isinstance(obj, ScoresSwaps) and not isinstance(ToyObjective(12, 5), ScoresSwaps)
    budget = Budget(evaluations=20).start(obj)
    rec = Recorder(obj, budget)
    view = BudgetedObjective(obj, budget, rec, 5, piece=8)
    m = _mask(12, [0, 3, 6, 8, 10])
    out, into = swap_pairs(m)                                   # 35 neighbours, 20 allowed
    with pytest.raises(BudgetExhausted, match="20 of 35 masks"):
        view.score_swaps(m, out, into)
    assert obj.evaluations == 20 and _OwnSwaps.calls == 3      # pieces of 8, 8, 4
    means = obj.evaluate(swap_masks(m, out[:20], into[:20]))["Mean"]
    assert rec.best_mean == pytest.approx(float(means.min()))
    assert rec.best == sorted(np.flatnonzero(swap_masks(m, out[:20], into[:20])[int(np.argmin(means))]).tolist())


def test_budgeted_neighbourhood_equals_budgeted_masks():
    # the same scores, counts and trace as scoring the neighbour masks with evaluate
    m = _mask(10, [1, 4, 6, 8])
    out, into = swap_pairs(m, np.random.default_rng(1))
    results = []
    for how in ("swaps", "masks"):
        obj = ToyObjective(10, 4)
        budget = Budget(evaluations=100).start(obj)
        rec = Recorder(obj, budget)
        view = BudgetedObjective(obj, budget, rec, 4)
        v = view.score_swaps(m, out, into) if how == "swaps" else view.score(swap_masks(m, out, into))
        results.append((v, obj.evaluations, rec.best, [r["evaluations"] for r in rec.rows]))
    np.testing.assert_array_equal(results[0][0], results[1][0])
    assert results[0][1:] == results[1][1:]
