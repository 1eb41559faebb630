"""The one interface a run's budget is spent through (arraysel.selectors.budget.BudgetGate): masks
scored in the pieces the budget allows and recorded, losses admitted, a closed run refused; the
budgeted objective, its neighbourhood and its loss model all spend through the same gate."""
from __future__ import annotations

import numpy as np
import pytest

from arraysel.errors import ArrayselError
from arraysel.objective.toy import ToyObjective
from arraysel.selectors.budget import Budget, BudgetExhausted, BudgetGate, Recorder
from arraysel.selectors.contract import BudgetedObjective


def _masks(n: int, ne: int = 16, k: int = 8, seed: int = 3) -> np.ndarray:
    rng = np.random.default_rng(seed)
    out = np.zeros((n, ne), dtype=bool)
    for row in out:
        row[rng.choice(ne, k, replace=False)] = True
    return out


def test_the_gate_scores_what_the_budget_allows_then_ends_the_search():
    obj = ToyObjective(16, 8)
    budget = Budget(evaluations=5).start(obj)
    rec = Recorder(obj, budget)
    gate = BudgetGate(budget, rec, k=8, piece=2)
    masks = _masks(8)
    calls = []

    def call(sl):
        calls.append((sl.start, sl.stop))
        return obj.evaluate(masks[sl])

    with pytest.raises(BudgetExhausted, match="5 of 8 masks"):
        gate.masks(8, call, lambda sl: masks[sl])
    assert calls == [(0, 2), (2, 4), (4, 5)] and budget.used_evaluations() == 5
    means = obj.evaluate(masks[:5])["Mean"]
    assert rec.best == sorted(np.flatnonzero(masks[int(np.argmin(means))]).tolist())
    assert rec.best_mean == pytest.approx(float(means.min()))
    with pytest.raises(BudgetExhausted, match="a Hessian"):
        gate.losses(1, "a Hessian")
    gate.enter()
    assert gate.first_call_s is not None
    gate.close()
    with pytest.raises(ArrayselError, match="run has ended"):
        gate.enter()


def test_the_budgeted_objective_and_its_capabilities_share_one_gate():
    obj = ToyObjective(16, 8)
    budget = Budget(evaluations=40).start(obj)
    view = BudgetedObjective(obj, budget, Recorder(obj, budget), k=8)
    base = _masks(1)[0]
    on, off = np.flatnonzero(base)[:3], np.flatnonzero(~base)[:3]
    got = view.score_swaps(base, on, off)
    assert got.shape == (3,) and budget.used_evaluations() == 3 and view.first_call_s is not None
    model = view.loss_model()           # the toy has a loss model and no neighbourhood
    assert model is not None and model._gate is view.gate and view.neighbourhood() is None
    small = Budget(evaluations=10).start(obj)
    tight = BudgetedObjective(obj, small, Recorder(obj, small), k=8)
    with pytest.raises(BudgetExhausted, match="Hessian"):
        tight.mask_hessian(base)            # 16 evaluations: more than the budget allows
    view.close()
    with pytest.raises(ArrayselError, match="run has ended"):
        view.evaluate(base[None])
    with pytest.raises(ArrayselError, match="run has ended"):
        view.dtype  # a forwarded attribute is refused too
