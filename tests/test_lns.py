"""``lns``, the large-neighbourhood search (issue 75): a window's re-solve is exact (against brute
force, on the model and on the objective), the selector finds the planted optimum, it is
reproducible per seed and keeps channel groups."""
from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from arraysel.constraints import Constraints
from arraysel.run.experiment import Experiment
from arraysel.selectors.contract import Budget, BudgetedObjective, Recorder
from arraysel.selectors.registry import build_plugin_manager, get_registry
from arraysel.selectors.window import WindowSearch, placements
from arraysel.testing import ToyObjective


@pytest.fixture(scope="module")
def reg():
    return get_registry(build_plugin_manager(load_entrypoints=False, disabled=()))


def _search(n=10, k=5, **kw):
    obj = ToyObjective(n, k)
    budget = Budget().start(obj)
    view = BudgetedObjective(obj, budget, Recorder(obj, budget), k)
    return obj, WindowSearch(view, k, np.random.default_rng(0), **kw)


def _window_masks(mask, window):
    """Every selection that keeps ``mask`` outside ``window`` and its count inside: brute force."""
    m = int(mask[window].sum())
    out = []
    for combo in itertools.combinations(window.tolist(), m):
        c = mask.copy()
        c[window] = False
        c[list(combo)] = True
        out.append(c)
    return np.array(out)


def test_placements_are_every_subset_once():
    p = placements(6, 3)
    assert p.shape == (20, 6) and (p.sum(axis=1) == 3).all()
    assert len({r.tobytes() for r in p}) == 20


def test_the_models_ranking_of_a_window_is_exact_against_brute_force():
    obj, s = _search(radius=0)
    mask = np.zeros(10, dtype=bool)
    mask[[0, 2, 3, 7, 9]] = True
    window = np.array([1, 2, 3, 4, 5, 6, 7])
    g, H = s._model(mask)
    masks = _window_masks(mask, window)
    masks = masks[np.any(masks != mask, axis=1)]
    dx = masks.astype(np.float64) - mask
    brute = dx @ g + 0.5 * np.einsum("bi,ij,bj->b", dx, H, dx)
    d = (masks[:, window].astype(np.int8) - mask[window])
    order = s._ranked(mask, window, d, s.verify)
    assert order.size == s.verify and len(brute) == math.comb(7, 3) - 1
    np.testing.assert_allclose(brute[order], np.sort(brute)[:s.verify], rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_window_verified_whole_finds_its_exact_best(seed):
    obj, s = _search(n=12, k=6, verify=10_000, radius=0)
    rng = np.random.default_rng(seed)
    mask = np.zeros(12, dtype=bool)
    mask[rng.choice(12, 6, replace=False)] = True
    value = float(s.score(mask[None])[0])
    window = np.sort(rng.choice(12, 8, replace=False))
    masks = _window_masks(mask, window)
    means = obj.evaluate(masks)["Mean"]
    found = s.resolve(mask, value, window)
    if means.min() < value:
        assert found is not None and found[1] == pytest.approx(means.min(), rel=1e-9)
        assert found[0].sum() == 6 and (found[0][np.setdiff1d(np.arange(12), window)]
                                         == mask[np.setdiff1d(np.arange(12), window)]).all()
    else:
        assert found is None


def test_windows_are_near_their_centres_and_narrowed_to_the_cap():
    _, s = _search(n=40, k=20, width=8, window="near")
    w = s.window()
    assert w.size == 8 and np.ptp(w) == 7  # 1-D: a contiguous run (of indices)
    _, s = _search(n=40, k=20, width=12, window="two")
    w = s.window()
    assert w.size == 12 and len(set(w.tolist())) == 12
    _, s = _search(n=40, k=20, width=16, cap=100)
    mask = np.arange(40) % 2 == 0
    fitted = s.fitted(mask, np.arange(16))
    assert math.comb(fitted.size, int(mask[fitted].sum())) <= 100 and fitted.size == 8


@pytest.mark.parametrize("options,seeds", [({}, (0, 1, 2)), ({"width": 6, "window": "two"}, (0, 1)),
                                           ({"start": "random", "race": 1, "verify": 4}, (0, 1))])
def test_lns_finds_the_planted_optimum(reg, options, seeds):
    obj = ToyObjective(14, 7)
    combos = np.array(list(itertools.combinations(range(14), 7)))
    masks = np.zeros((len(combos), 14), dtype=bool)
    np.put_along_axis(masks, combos, True, axis=1)
    best = combos[int(np.argmin(obj.evaluate(masks)["Mean"]))].tolist()
    for seed in seeds:
        row = Experiment(ToyObjective(14, 7), "lns", options=options, budget=Budget(evaluations=1500), seed=seed,
                         registry=reg).run()
        assert row["error"] == "" and row["elements"] == " ".join(map(str, best)), (seed, row["Mean"])


def test_lns_is_reproducible_and_takes_windows(reg):
    rows = [Experiment(ToyObjective(24, 12), "lns", options={"width": 8}, budget=Budget(evaluations=600), seed=4,
                       registry=reg).run() for _ in range(2)]
    assert rows[0]["error"] == "" and rows[0]["elements"] == rows[1]["elements"] and rows[0]["Mean"] == rows[1]["Mean"]
    obj, s = _search(n=24, k=12, width=8, windows=4)
    start = np.arange(24) < 12
    s.max_rounds = 3
    s.run(start)
    assert s.windows_tried > 0 and s.best_value <= float(obj.evaluate(start[None])["Mean"][0])


def test_lns_keeps_channel_groups(reg):
    cons = Constraints(16, 4, groups="mux-16-4")
    obj = ToyObjective(16, 4, grid=(4, 4), constraints=cons)
    row = Experiment(obj, "lns", options={"width": 8}, budget=Budget(evaluations=400), seed=0, k=4,
                     registry=reg).run()
    assert row["error"] == ""
    assert cons.feasible([int(i) for i in row["elements"].split()])


def test_a_window_kick_moves_within_its_radius_which_grows_with_the_strength():
    _, s = _search(n=20, k=10, radius=1, width=10, max_perturb=4)  # perturb: the engine's 2
    base = np.arange(20) % 2 == 0
    radii = []
    verified = s.verified
    s.verified = lambda mask, window, radius=None: radii.append(radius) or verified(mask, window, radius)
    for strength, most in ((2, 1), (4, 3)):
        kicked = s.perturbed(base, strength)
        assert kicked.sum() == 10 and 1 <= int((kicked & ~base).sum()) <= most
    assert radii == [1, 3]
