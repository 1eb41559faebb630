"""The capabilities a search obtains from the objective once (``objective.neighbourhood()``,
``objective.loss_model()``): the quadratic model of a small matrix scene, the log line of a search
that runs without a capability, and errors that are not swallowed."""
from __future__ import annotations

import logging

import numpy as np
import pytest
import torch

from arraysel.objective.contract import LossModel, Neighbourhood, hessian_by_rows, loss_model_of
from arraysel.objective.neighbours import neighbourhood_of
from arraysel.selectors.contract import Budget, BudgetedObjective, Recorder
from arraysel.selectors.localsearch import SwapSearch
from arraysel.testing import ToyObjective
from scene_texts import TINY_MATRIX_SCENE
from support import PLAIN


def _budgeted(obj, evaluations):
    budget = Budget(evaluations=evaluations).start(obj)
    return BudgetedObjective(obj, budget, Recorder(obj, budget), obj.k)


@pytest.fixture(scope="module")
def tiny_matrix(tmp_path_factory):
    from arraysel.objective.matrix_objective import MatrixObjective

    p = tmp_path_factory.mktemp("scenes") / "tiny3d.toml"
    p.write_text(TINY_MATRIX_SCENE)
    return MatrixObjective(str(p), dtype=torch.float64)


def test_a_small_matrix_scene_has_a_quadratic_model_and_searches_use_it(tiny_matrix):
    # a matrix scene of <= 256 elements ranks swaps by the quadratic model (model = auto): its
    # Hessian is the Hessian of its mask_loss, and a descent forms it (it used to read a 1-D pair
    # model that a matrix scene never builds, and the error was swallowed: no model, no word)
    obj = tiny_matrix
    model = loss_model_of(obj)
    assert isinstance(model, LossModel)
    mask = np.zeros(obj.n_elements, dtype=bool)
    mask[[0, 5, 10, 15]] = True
    g, H = model.model(mask)
    g2, H2 = hessian_by_rows(obj.mask_loss, mask, torch.float64)
    np.testing.assert_allclose(H, H2, rtol=1e-9, atol=1e-9 * np.abs(H2).max())
    np.testing.assert_allclose(g, g2, rtol=1e-9, atol=1e-9 * np.abs(g2).max())
    np.testing.assert_allclose(model.gradient(mask), g2, rtol=1e-9, atol=1e-9 * np.abs(g2).max())
    view = _budgeted(obj, 400)
    search = SwapSearch(view, obj.k, np.random.default_rng(0), PLAIN, model=None, scan=0.5)
    assert search.model == "quadratic"
    search.descend(mask, float(view.score(mask[None])[0]))
    assert search.hessians >= 1 and search._guided


def test_the_matrix_neighbourhood_is_the_fast_path_s_and_scores_as_the_masks(tiny_matrix):
    from arraysel.objective.neighbours import swap_masks, swap_pairs

    nb = neighbourhood_of(tiny_matrix)
    assert isinstance(nb, Neighbourhood)
    mask = np.zeros(tiny_matrix.n_elements, dtype=bool)
    mask[[1, 6, 11, 12]] = True
    a, b = swap_pairs(mask)
    got = nb.evaluate(mask, a, b)["Mean"]
    want = tiny_matrix.evaluate(swap_masks(mask, a, b))["Mean"]
    np.testing.assert_allclose(got, want, rtol=1e-9)


def test_a_search_without_a_neighbourhood_or_a_loss_model_says_so_once(caplog):
    class Plain:  # the contract's evaluate only: no neighbourhood, no mask_loss
        def __init__(self):
            self.inner = ToyObjective(12, 6)
            self.n_elements, self.k = 12, 6
            self.evaluations = self.gradient_steps = 0
            self.seconds = 0.0

        def evaluate(self, masks):
            self.evaluations += len(masks)
            return self.inner.evaluate(masks)

    obj = Plain()
    start = np.arange(12) < 6
    with caplog.at_level(logging.WARNING, logger="arraysel"):
        for seed in range(2):  # two runs on the objective: one line each capability
            view = _budgeted(obj, 200)
            search = SwapSearch(view, 6, np.random.default_rng(seed), PLAIN, scan=0.5)
            search.descend(start, float(view.score(start[None])[0]))
    lines = [r.getMessage() for r in caplog.records if r.name.startswith("arraysel")]
    assert sum("without a neighbourhood" in m for m in lines) == 1, lines
    assert sum("without a model of the loss" in m for m in lines) == 1, lines
    # an objective with a loss model says nothing of it
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="arraysel"):
        view = _budgeted(ToyObjective(12, 6), 200)
        assert view.loss_model() is not None
    assert not [r for r in caplog.records if "without" in r.getMessage()]


def test_an_error_of_the_loss_model_is_not_swallowed():
    class Broken(ToyObjective):
        def loss_model(self):
            class Model:
                def gradient(self, mask):
                    raise RuntimeError("broken gradient")

                def model(self, mask):
                    raise RuntimeError("broken Hessian")
            return Model()

    obj = Broken(12, 6)
    view = _budgeted(obj, 500)
    search = SwapSearch(view, 6, np.random.default_rng(0), PLAIN, model="quadratic", scan=0.5)
    start = np.arange(12) < 6
    with pytest.raises(RuntimeError, match="broken Hessian"):
        search.descend(start, float(view.score(start[None])[0]))
