"""The quadratic model of the loss (gradient and Hessian) and the searches that rank swaps by it
(``swap``'s descents with ``model = quadratic``)."""
from __future__ import annotations

import tomllib

import numpy as np
import pytest
import torch

from arraysel.errors import ParameterError
from arraysel.objective.contract import HasHessian, hessian_by_rows
from arraysel.objective.neighbours import swap_masks, swap_pairs
from arraysel.selectors.contract import Budget, BudgetedObjective, BudgetExhausted, Recorder
from arraysel.selectors.localsearch import (SwapSearch, loss_quadratic, move_changes, random_swaps, shift_moves,
                                           shift_segments, shifted_masks, swap_changes)
from arraysel.testing import ToyObjective
from scene_texts import TINY_SCENE
from support import PLAIN


class Quadratic:
    """``f(w) = c + q . w + w' Q w / 2`` on ``n`` elements: a loss whose quadratic model is exact."""

    def __init__(self, n=9, k=4, seed=0, hessian=True):
        rng = np.random.default_rng(seed)
        a = rng.normal(size=(n, n))
        self.Q, self.q, self.c = a + a.T, rng.normal(size=n), 3.0
        self.n_elements, self.k, self.dtype = n, k, torch.float64
        self.evaluations = self.gradient_steps = 0
        self.seconds = 0.0
        if not hessian:
            self.mask_hessian = None

    def f(self, w):
        return self.c + w @ self.q + 0.5 * np.einsum("bi,ij,bj->b", w, self.Q, w)

    def evaluate(self, masks):
        masks = np.asarray(masks, dtype=np.float64)
        self.evaluations += len(masks)
        return {"Mean": self.f(masks)}

    def mask_loss(self, weights):
        w = weights if weights.dim() == 2 else weights[None]
        Q, q = torch.as_tensor(self.Q), torch.as_tensor(self.q)
        self.evaluations += w.shape[0]
        self.gradient_steps += int(w.requires_grad)
        return self.c + w @ q + 0.5 * ((w @ Q) * w).sum(1), {}


def _budgeted(obj, evaluations):
    """A budgeted view of ``obj``, as a run gives a selector."""
    budget = Budget(evaluations=evaluations).start(obj)
    return BudgetedObjective(obj, budget, Recorder(obj, budget), obj.k)


def _tiny_objective(dtype):
    from arraysel.objective.psf_objective import Objective
    from arraysel.scenes.schema import load_scene

    return Objective(load_scene(tomllib.loads(TINY_SCENE)), dtype=dtype)


def test_quadratic_model_predicts_every_swap_of_a_quadratic_loss_exactly():
    obj = Quadratic(hessian=False)
    mask = np.zeros(obj.n_elements, dtype=bool)
    mask[[0, 3, 4, 7]] = True
    g, H = loss_quadratic(obj, mask)
    np.testing.assert_allclose(H, obj.Q, rtol=1e-12)
    np.testing.assert_allclose(g, obj.q + obj.Q @ mask, rtol=1e-12)
    a, b = swap_pairs(mask)
    exact = obj.f(swap_masks(mask, a, b).astype(float)) - obj.f(mask[None].astype(float))
    np.testing.assert_allclose(swap_changes(g, H, a, b), exact, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(swap_changes(g, None, a, b), g[b] - g[a])


def test_hessian_by_rows_counts_ne_evaluations_and_the_budget_checks_them():
    obj = Quadratic(hessian=False)
    mask = np.arange(obj.n_elements) < obj.k
    g, H = hessian_by_rows(obj.mask_loss, mask, torch.float64)
    np.testing.assert_allclose(H, obj.Q, rtol=1e-12)
    assert obj.evaluations == obj.n_elements
    obj.evaluations = 0
    view = _budgeted(obj, obj.n_elements + 1)
    loss_quadratic(view, mask)
    assert obj.evaluations == obj.n_elements
    with pytest.raises(BudgetExhausted):
        loss_quadratic(view, mask)  # one evaluation left, the Hessian needs Ne


def test_no_quadratic_model_without_a_finite_differentiable_loss():
    class NoLoss:
        n_elements, k = 6, 3
    assert loss_quadratic(NoLoss(), np.arange(6) < 3) is None
    obj = Quadratic(hessian=False)
    obj.Q[0, 0] = np.nan
    assert loss_quadratic(obj, np.arange(obj.n_elements) < obj.k) is None


@pytest.mark.parametrize("dtype,rtol", [(torch.float64, 1e-9), (torch.float32, 2e-3)])
def test_psf_objective_hessian_equals_the_hessian_of_its_mask_loss(dtype, rtol):
    # the objective's own batched Hessian-vector products against rows differentiated twice and
    # against torch's dense Hessian of the same loss, float64
    obj = _tiny_objective(dtype)
    assert isinstance(obj, HasHessian)
    n = obj.n_elements
    mask = np.zeros(n, dtype=bool)
    mask[np.random.default_rng(1).choice(n, n // 2, replace=False)] = True
    before = obj.evaluations
    g, H = obj.mask_hessian(mask)
    assert obj.evaluations - before == n
    ref = _tiny_objective(torch.float64)
    f = lambda w: ref.mask_loss(w[None])[0].sum()  # noqa: E731
    w = torch.tensor(mask, dtype=torch.float64)
    H_ref = torch.autograd.functional.hessian(f, w).numpy()
    g_ref = torch.autograd.functional.jacobian(f, w).numpy()
    scale = np.abs(H_ref).max()
    np.testing.assert_allclose(H, H_ref, rtol=rtol, atol=rtol * scale)
    np.testing.assert_allclose(g, g_ref, rtol=rtol, atol=rtol * np.abs(g_ref).max())
    g2, H2 = hessian_by_rows(ref.mask_loss, mask, torch.float64)
    np.testing.assert_allclose(H2, H_ref, rtol=1e-9, atol=1e-9 * scale)


def test_psf_quadratic_model_ranks_swaps_better_than_the_gradient():
    # why descents rank swaps by it: on a PSF objective the model's predicted changes of one swap
    # correlate with the true ones more than the gradient's alone
    obj = _tiny_objective(torch.float64)
    n = obj.n_elements
    mask = np.zeros(n, dtype=bool)
    mask[np.random.default_rng(2).choice(n, n // 2, replace=False)] = True
    g, H = loss_quadratic(obj, mask)
    a, b = swap_pairs(mask)
    true = obj.evaluate_swaps(mask, a, b)["Mean"] - obj.evaluate(mask[None])["Mean"][0]
    r2 = np.corrcoef(swap_changes(g, H, a, b), true)[0, 1]
    r1 = np.corrcoef(swap_changes(g, None, a, b), true)[0, 1]
    assert r2 > max(r1, 0.5), (r1, r2)


def test_quadratic_descents_without_a_loss_take_the_random_order():
    class Plain:
        def __init__(self):
            self.inner = ToyObjective(12, 6)
            self.n_elements, self.k = 12, 6
            self.evaluations = self.gradient_steps = 0
            self.seconds = 0.0

        def evaluate(self, masks):
            self.evaluations += len(masks)
            return self.inner.evaluate(masks)

    view = _budgeted(Plain(), 10_000)
    search = SwapSearch(view, 6, np.random.default_rng(3), PLAIN, model="quadratic", scan=0.5)
    start = np.arange(12) < 6
    mask, value = search.descend(start, float(view.score(start[None])[0]))
    assert search.hessians == 0 and not search._guided and value <= float(view.score(start[None])[0])


@pytest.mark.parametrize("k", [1, 15, 16])
def test_quadratic_descents_at_extreme_k(k):
    obj = ToyObjective(16, k)
    view = _budgeted(obj, 2000)
    search = SwapSearch(view, k, np.random.default_rng(0), PLAIN, model="quadratic", refresh=2, scan=0.25, max_rounds=5)
    sel, value = search.run(np.arange(16) < k)
    assert len(sel) == k and np.isfinite(value)


def test_swap_search_predictions_by_the_linear_and_the_quadratic_model():
    obj = Quadratic(n=10, k=5, hessian=False, seed=5)
    mask = np.zeros(10, dtype=bool)
    mask[[0, 2, 3, 6, 9]] = True
    a, b = swap_pairs(mask)
    exact = obj.f(swap_masks(mask, a, b).astype(float)) - obj.f(mask[None].astype(float))
    g = obj.q + obj.Q @ mask
    lin = SwapSearch(obj, 5, np.random.default_rng(0), PLAIN)
    np.testing.assert_allclose(lin._predict(mask, a, b), g[b] - g[a], rtol=1e-12)
    quad = SwapSearch(obj, 5, np.random.default_rng(0), PLAIN, model="quadratic", refresh=3)
    rng = np.random.default_rng(1)
    for _ in range(7):  # at seven selections in turn (a descent's moves)
        other = random_swaps(mask, 2, rng)
        c, d = swap_pairs(other)
        want = obj.f(swap_masks(other, c, d).astype(float)) - obj.f(other[None].astype(float))
        np.testing.assert_allclose(quad._predict(other, c, d), want, rtol=1e-10, atol=1e-12)
        np.testing.assert_allclose(quad._predict(mask, a, b), exact, rtol=1e-10, atol=1e-12)
    assert quad.hessians == 5  # formed at the 1st, 4th, 7th, 10th and 13th selection of 14
    steps = obj.gradient_steps
    quad._predict(mask, a, b)  # asked again at the same selection: the model is not formed again
    assert obj.gradient_steps == steps


def test_move_changes_of_any_move_are_exact_on_a_quadratic_loss():
    obj = Quadratic(n=12, k=5, hessian=False, seed=7)
    mask = np.zeros(12, dtype=bool)
    mask[[1, 2, 5, 8, 11]] = True
    g, H = obj.q + obj.Q @ mask, obj.Q
    moves = shift_moves(12, 6, 3)
    cands = shifted_masks(mask, moves)
    exact = obj.f(cands.astype(float)) - obj.f(mask[None].astype(float))
    # as the few elements a shift changes (padded with Ne), and as whole selections
    at, source = shift_segments(12, moves)
    ext = np.append(mask, False)
    d = ext[source].astype(np.int8) - ext[at]
    assert (at == 12).any()  # padded rows among them
    np.testing.assert_allclose(move_changes(g, H, at, d, block=7), exact, rtol=1e-10, atol=1e-12)
    whole = np.tile(np.arange(12), (len(cands), 1))
    np.testing.assert_allclose(move_changes(g, H, whole, cands - mask.astype(float)), exact, rtol=1e-10, atol=1e-12)
    a, b = swap_pairs(mask)  # a swap is a move of two elements: the same change as swap_changes
    np.testing.assert_allclose(move_changes(g, H, np.stack([a, b], 1), np.tile([-1.0, 1.0], (len(a), 1))),
                               swap_changes(g, H, a, b), rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(move_changes(g, None, at, d), (cands - mask.astype(float)) @ g, rtol=1e-10,
                               atol=1e-12)


def test_guided_shifts_take_the_best_predicted_shift_first_and_stop_at_shift_scan():
    # on a quadratic loss the model is exact: with every chunk taken from the prediction, the
    # first chunk holds the best shift, and a selection no shift improves is left after
    # shift_scan shifts, not all of them
    obj = Quadratic(n=16, k=7, hessian=False, seed=8)
    view = _budgeted(obj, 1_000_000)
    search = SwapSearch(view, 7, np.random.default_rng(2), PLAIN, model="quadratic", guide=1.0, shift=3, shift_len=8,
                        shift_scan=40, chunk=16)
    search.shift_guide.hi = 1.0
    mask = np.arange(16) % 2 == 0
    mask[14] = False
    cands = np.unique(shifted_masks(mask, shift_moves(16, 8, 3)), axis=0)
    cands = cands[(cands != mask).any(axis=1)]
    values = obj.f(cands.astype(float))
    value = float(obj.f(mask[None].astype(float))[0])
    assert values.min() < value  # this start has an improving shift
    before = search.scored
    moved, moved_value = search._shift_step(mask, value)
    assert moved_value == pytest.approx(values.min()) and search.scored - before == 16
    # at a selection no shift improves, the step gives up after shift_scan scored shifts
    best = cands[int(np.argmin(values))]
    while True:
        c = np.unique(shifted_masks(best, shift_moves(16, 8, 3)), axis=0)
        v = obj.f(c.astype(float))
        if v.min() >= obj.f(best[None].astype(float))[0]:
            break
        best = c[int(np.argmin(v))]
    assert len(c) > 60
    before = search.scored
    assert search._shift_step(best, float(obj.f(best[None].astype(float))[0])) is None
    assert search.scored - before <= 40


def test_quadratic_descents_confirm_local_optima_from_a_small_scan():
    # a descent that scans only the best predicted fifth of the neighbourhood ends where a full scan
    # would: on a quadratic loss the model is exact, so no improving swap is left outside that fifth
    obj = Quadratic(n=14, k=7, hessian=False, seed=6)
    view = _budgeted(obj, 100_000)
    search = SwapSearch(view, 7, np.random.default_rng(1), PLAIN, model="quadratic", refresh=1, scan=0.2, guide=1.0)
    mask, value = search.descend(np.arange(14) < 7, float(view.score((np.arange(14) < 7)[None])[0]))
    a, b = swap_pairs(mask)
    assert (view.score(swap_masks(mask, a, b)) >= value - 1e-12).all()
    assert search.hessians >= 1


def test_bad_model_options_name_the_option():
    obj = ToyObjective(12, 6)
    with pytest.raises(Exception, match="model"):
        SwapSearch(obj, 6, np.random.default_rng(0), PLAIN, model="cubic")
    with pytest.raises(Exception, match="refresh"):
        SwapSearch(obj, 6, np.random.default_rng(0), PLAIN, model="quadratic", refresh=0)


def test_updated_gradients_follow_the_exact_ones_on_a_quadratic_loss():
    # gradient = update carries the model's gradient along the moves (g + H d) instead of a backward
    # pass at each: on a quadratic loss that is the exact gradient, so the descents take the same
    # moves with fewer gradient steps
    runs = {}
    for gradient in ("exact", "update"):
        obj = Quadratic(n=24, k=10, hessian=False, seed=4)
        view = _budgeted(obj, 1_000_000)
        search = SwapSearch(view, 10, np.random.default_rng(5), PLAIN, model="quadratic", refresh=3, scan=0.3,
                            guide=1.0, gradient=gradient)
        start = np.arange(24) < 10
        mask, value = search.descend(start, float(view.score(start[None])[0]))
        runs[gradient] = (mask, value, search.moves, obj.gradient_steps, search.gradients_updated)
    (m0, v0, moves0, steps0, upd0), (m1, v1, moves1, steps1, upd1) = runs["exact"], runs["update"]
    np.testing.assert_array_equal(m1, m0)
    assert v1 == v0 and moves1 == moves0 and moves0 > 3
    assert upd0 == 0 and upd1 > 0 and steps1 == steps0 - upd1


def test_an_updated_gradient_is_taken_afresh_beyond_two_swaps():
    obj = Quadratic(n=12, k=6, hessian=False, seed=2)
    search = SwapSearch(obj, 6, np.random.default_rng(0), PLAIN, model="quadratic", refresh=100, gradient="update")
    mask = np.arange(12) < 6
    search._model(mask)
    near = random_swaps(mask, 2, np.random.default_rng(1))
    g, _ = search._model(near)
    np.testing.assert_allclose(g, obj.q + obj.Q @ near, rtol=1e-12)
    assert search.gradients_updated == 1
    far = ~mask  # every element moved
    search._model(far)
    assert search.gradients_updated == 1
    with pytest.raises(ParameterError, match="gradient"):
        SwapSearch(obj, 6, np.random.default_rng(0), PLAIN, gradient="carried")


def test_compound_steps_take_several_improving_swaps_of_a_chunk_at_once():
    # a linear loss: every improving swap improves independently, so a chunk's improving swaps on
    # distinct elements improve together; the descent ends at the same optimum (the k elements of
    # least weight) in fewer steps, each step's value that of its selection
    runs = {}
    for compound in (0, 8):
        obj = Quadratic(n=30, k=12, hessian=False, seed=6)
        obj.Q[:] = 0.0
        view = _budgeted(obj, 1_000_000)
        search = SwapSearch(view, 12, np.random.default_rng(2), PLAIN, chunk=64, scan=1.0, guide=0.0, compound=compound)
        start = np.argsort(obj.q)[-12:]
        mask0 = np.zeros(30, dtype=bool)
        mask0[start] = True
        steps = list(search._descent(mask0, float(view.score(mask0[None])[0])))
        for m, v in steps:
            assert v == pytest.approx(float(obj.f(m[None].astype(float))[0]), rel=1e-12)
        runs[compound] = (steps[-1][0], len(steps), search.compound_moves)
    best = np.zeros(30, dtype=bool)
    best[np.argsort(obj.q)[:12]] = True
    for compound, (mask, steps, taken) in runs.items():
        np.testing.assert_array_equal(mask, best)
    assert runs[0][2] == 0 and runs[8][2] > 0 and runs[8][1] < runs[0][1]


def test_a_compound_step_is_the_best_of_its_prefixes_and_the_best_swap():
    obj = Quadratic(n=16, k=7, hessian=False, seed=3)
    search = SwapSearch(_budgeted(obj, 1_000_000), 7, np.random.default_rng(0), PLAIN, compound=4)
    mask = np.arange(16) < 7
    value = float(obj.f(mask[None].astype(float))[0])
    a, b = swap_pairs(mask)
    values = obj.f(swap_masks(mask, a, b).astype(float))
    assert int((values < value).sum()) >= 2
    best = int(np.argmin(values))
    got, v = search._compound_step(mask, value, a, b, values,
                                   (swap_masks(mask, a[best:best + 1], b[best:best + 1])[0], float(values[best])))
    # every prefix of the improving swaps on distinct elements, best first, and the best swap alone
    cands, used, cur = [swap_masks(mask, a[[np.argmin(values)]], b[[np.argmin(values)]])[0]], set(), mask.copy()
    for j in np.argsort(values, kind="stable"):
        if values[j] >= value or len(used) == 8:
            break
        if a[j] in used or b[j] in used:
            continue
        used.update((a[j], b[j]))
        cur = cur.copy()
        cur[a[j]], cur[b[j]] = False, True
        cands.append(cur)
    fv = obj.f(np.asarray(cands, dtype=float))
    assert v == pytest.approx(float(fv.min()), rel=1e-12) and v == pytest.approx(float(obj.f(got[None] * 1.0)[0]))
    assert int(got.sum()) == 7
    with pytest.raises(ParameterError, match="compound"):
        SwapSearch(obj, 7, np.random.default_rng(0), PLAIN, compound=-1)
