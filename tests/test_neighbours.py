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


# ---------------------------------------------------------------- the PSF objective's own neighbourhoods
import tomllib  # noqa: E402

import torch  # noqa: E402

from scene_texts import TINY_SCENE  # noqa: E402


def _tiny_objective(dtype, **over):
    from arraysel.objective.psf_objective import Objective
    from arraysel.scenes.schema import load_scene

    tree = tomllib.loads(TINY_SCENE)
    for sec, keys in over.items():
        tree.setdefault(sec, {}).update(keys)
    return Objective(load_scene(tree), dtype=dtype)


def _assert_same_scores(got, ref, rtol, atol=0.0):
    assert set(got) == set(ref)
    for key in ref:
        if key == "kernels":
            np.testing.assert_allclose(got[key], ref[key], rtol=0, atol=max(atol, rtol), err_msg=key)
        else:
            np.testing.assert_allclose(got[key], ref[key], rtol=rtol, atol=atol, err_msg=key)


def _spy_swap_envelopes(monkeypatch):
    from arraysel.physics.psf.certificate import Certificates

    calls = []
    real = Certificates.swap_envelopes

    def spy(self, mask, out, into):
        calls.append(int(out.numel()))
        return real(self, mask, out, into)

    monkeypatch.setattr(Certificates, "swap_envelopes", spy)
    return calls


@pytest.mark.parametrize("dtype, rtol", [(torch.float64, 1e-10), (torch.float32, 2e-4)])
def test_psf_objective_neighbourhood_equals_independent_masks(monkeypatch, dtype, rtol):
    # a 12-element scene with two field points: every Table-1 key (headline, per point, mean,
    # worst), the kernels, the counters; the neighbourhood goes through the corrected envelopes
    monkeypatch.setenv("ARRAYSEL_CACHE", "off")
    obj = _tiny_objective(dtype, probe={"n_elements": 12}, selection={"k": 5},
                          medium={"points": [[0.0, 0.02], [0.001, 0.021]]})
    assert all(p.basis is not None for p in obj.psfs) and isinstance(obj, ScoresSwaps)
    calls = _spy_swap_envelopes(monkeypatch)
    m = _mask(12, [0, 3, 4, 8, 11])
    out, into = swap_pairs(m, np.random.default_rng(2))
    evaluate_swaps(obj, m, out, into)
    assert calls == [35, 35]                                 # one call a field point
    assert obj.evaluations == 35
    fb = obj.fallbacks
    got = obj.evaluate_swaps(m, out, into, return_kernels=True)
    fb_swaps = obj.fallbacks - fb
    fb = obj.fallbacks
    ref = obj.evaluate(swap_masks(m, out, into), return_kernels=True)
    assert obj.fallbacks - fb == fb_swaps and obj.evaluations == 105
    assert "Mean@p1" in ref and "Mean@worst" in ref
    _assert_same_scores(got, ref, rtol)
    # a step of a search: the best neighbour's neighbourhood, with the pair-image rows kept from
    # the last one, and again with none kept
    best = int(np.argmin(ref["Mean"]))
    m2 = swap_masks(m, out[best:best + 1], into[best:best + 1])[0]
    o2, i2 = swap_pairs(m2)
    ref2 = obj.evaluate(swap_masks(m2, o2, i2), return_kernels=True)
    _assert_same_scores(obj.evaluate_swaps(m2, o2, i2, return_kernels=True), ref2, rtol)
    for p in obj.psfs:
        p.basis.__dict__.pop("_swap_rows", None)
        p.basis.swap_rows_max_bytes = 0
    _assert_same_scores(obj.evaluate_swaps(m2, o2, i2, return_kernels=True), ref2, rtol)
    assert all("_swap_rows" not in p.basis.__dict__ for p in obj.psfs)
    # the memory cap bounds the kept rows too
    for p in obj.psfs:
        p.basis.swap_rows_max_bytes = 1 << 40
    monkeypatch.setenv("ARRAYSEL_MEMORY_GIB", "1e-9")
    assert all(p.basis.swap_rows_cap() < 2 for p in obj.psfs)
    _assert_same_scores(obj.evaluate_swaps(m2, o2, i2, return_kernels=True), ref2, rtol)
    assert all("_swap_rows" not in p.basis.__dict__ for p in obj.psfs)
    monkeypatch.setenv("ARRAYSEL_MEMORY_GIB", "0.5")
    assert all(p.basis.swap_rows_cap() == 2 ** 29 for p in obj.psfs)


@pytest.mark.parametrize("dtype, rtol", [(torch.float64, 1e-12), (torch.float32, 1e-5)])
def test_swap_envelopes_equal_the_envelopes_of_the_neighbour_masks(monkeypatch, dtype, rtol):
    monkeypatch.setenv("ARRAYSEL_CACHE", "off")
    obj = _tiny_objective(dtype, probe={"n_elements": 10}, selection={"k": 6})
    basis = obj.psf.basis
    m = _mask(10, [0, 1, 4, 5, 7, 9])
    out, into = swap_pairs(m)
    w = torch.as_tensor(swap_masks(m, out, into), dtype=dtype)
    got = basis.certificates.swap_envelopes(torch.as_tensor(m, dtype=dtype), torch.as_tensor(out), torch.as_tensor(into))
    ref = basis.certificates.envelopes(w)
    assert got.shape == ref.shape and got.dtype == ref.dtype
    scale = float(ref.abs().max())
    np.testing.assert_allclose(got.numpy(), ref.numpy(), rtol=rtol, atol=rtol * scale)
    # the receive elements a neighbour does not use have no channel
    ntx, ne = len(obj.psf.transmits), 10
    env = got.view(ntx, ne, -1, w.shape[0]).permute(0, 1, 3, 2)   # (ntx, Ne, B, runs x segments)
    unused = w.T == 0
    assert bool(unused.any()) and float(env[:, unused].abs().sum()) == 0.0
    assert bool((env[:, ~unused].amax(-1) > 0).all())


def test_empty_or_bad_neighbourhoods(monkeypatch):
    monkeypatch.setenv("ARRAYSEL_CACHE", "off")
    obj = _tiny_objective(torch.float64)
    m = _mask(8, [1, 2, 5, 6])
    got = obj.evaluate_swaps(m, [], [])
    assert set(got) == set(obj.metric_names) and all(v.shape == (0,) for v in got.values())
    with pytest.raises(SelectionError, match="out must name active elements"):
        obj.evaluate_swaps(m, [0], [3])
    with pytest.raises(SelectionError, match=r"shape \(8,\)"):
        obj.evaluate_swaps(_mask(9, [0]), [0], [1])


def test_paper_neighbourhood_equals_independent_masks_where_the_peak_moves(paper_objective, monkeypatch):
    # the outer elements only: a wide gap, strong sidelobes, and neighbours whose peaks lie on
    # many different pixels (and off the base's); every key and kernel as the masks scored alone
    obj = paper_objective
    calls = _spy_swap_envelopes(monkeypatch)
    m = _mask(64, list(range(16)) + list(range(48, 64)))
    out, into = swap_pairs(m, np.random.default_rng(0))
    out, into = out[:48], into[:48]
    w = torch.as_tensor(swap_masks(m, out, into), dtype=torch.float32)
    with torch.no_grad():
        base_peak = int(obj.psf.basis.images(torch.as_tensor(m[None], dtype=torch.float32)).abs().flatten().argmax())
        peaks = obj.psf.basis.images(w).abs().flatten(1).argmax(1)
    assert bool((peaks != base_peak).any()) and len(set(peaks.tolist())) > 3
    got = obj.evaluate_swaps(m, out, into, return_kernels=True)
    assert calls == [out.size]
    ref = obj.evaluate(swap_masks(m, out, into), return_kernels=True)
    _assert_same_scores(got, ref, rtol=2e-4, atol=1e-6)
    # the images on E of the neighbours (from the selection's image and pair-image rows) against
    # the product of each neighbour, and their error bounds
    basis = obj.psf.basis
    with torch.no_grad():
        img, eps, werr = basis.swap_images(torch.as_tensor(m, dtype=torch.float32), torch.as_tensor(out),
                                           torch.as_tensor(into), w)
        img_r, eps_r, werr_r = basis.images(w, with_error=True)
    top = float(img_r.abs().amax())
    assert float((img - img_r).abs().amax()) <= 1e-5 * top
    assert torch.equal(eps, eps_r) and torch.equal(werr, werr_r)


@pytest.mark.slow
@pytest.mark.parametrize("scene, dtype, rtol", [("paper", torch.float64, 1e-9), ("l11-5v", torch.float32, 2e-4)])
def test_builtin_neighbourhoods_equal_independent_masks(scene, dtype, rtol):
    # the outer elements (moving peaks) and a random selection of a built-in scene: 64 neighbours
    # each, every key and kernel as the masks scored alone (builds the scene's basis: minutes)
    from arraysel.objective.psf_objective import Objective

    obj = Objective(scene, dtype=dtype)
    n, k = obj.n_elements, obj.k
    rng = np.random.default_rng(5)
    for m in (_mask(n, list(range(k // 2)) + list(range(n - k + k // 2, n))),
              _mask(n, rng.choice(n, k, replace=False))):
        out, into = swap_pairs(m, rng)
        out, into = out[:64], into[:64]
        fb = obj.fallbacks
        got = obj.evaluate_swaps(m, out, into, return_kernels=True)
        fb_swaps, fb = obj.fallbacks - fb, obj.fallbacks
        ref = obj.evaluate(swap_masks(m, out, into), return_kernels=True)
        assert obj.fallbacks - fb == fb_swaps
        _assert_same_scores(got, ref, rtol=rtol, atol=1e-6 if dtype == torch.float32 else 1e-12)


def _walk_images(obj, m, rng, moves, dtype, tol):
    """A search's walk: at each step the neighbours' images on E against the product of each
    neighbour, then a move to one of them (every third step a two-swap jump, which the base is
    formed afresh for); returns the selection reached."""
    basis = obj.psf.basis
    for step in range(moves):
        out, into = swap_pairs(m, rng)
        out, into = out[:16], into[:16]
        w = torch.as_tensor(swap_masks(m, out, into), dtype=dtype)
        with torch.no_grad():
            img, eps, werr = basis.swap_images(torch.as_tensor(m, dtype=dtype), torch.as_tensor(out),
                                               torch.as_tensor(into), w)
            img_r, eps_r, werr_r = basis.images(w, with_error=True)
        assert float((img - img_r).abs().amax()) <= tol * float(img_r.abs().amax()), step
        assert torch.equal(eps, eps_r) and torch.equal(werr, werr_r)
        m = swap_masks(m, out[step % 16:step % 16 + 1], into[step % 16:step % 16 + 1])[0]
        if step % 3 == 2:
            on, off = np.flatnonzero(m), np.flatnonzero(~m)
            m = swap_masks(m, on[:1], off[:1])[0]
    return m


@pytest.mark.parametrize("dtype, tol", [(torch.float64, 1e-11), (torch.float32, 2e-6)])
def test_neighbourhood_base_carried_by_rows_along_a_walk_equals_the_products(monkeypatch, dtype, tol):
    # with every pair-image row kept (prepare_neighbourhoods), a selection one swap from the last
    # one has its image and rows G updated by rows, refreshed from the basis every few moves; the
    # neighbours' images stay those of the product, step after step
    from arraysel.objective.neighbours import prepare_neighbourhoods

    monkeypatch.setenv("ARRAYSEL_CACHE", "off")
    obj = _tiny_objective(dtype, probe={"n_elements": 12}, selection={"k": 6})
    basis = obj.psf.basis
    assert prepare_neighbourhoods(obj) >= 0
    monkeypatch.setattr(type(basis), "swap_base_refresh", 4)
    rng = np.random.default_rng(4)
    m = _walk_images(obj, _mask(12, [0, 2, 3, 7, 9, 11]), rng, 14, dtype, tol)
    assert basis._swap_base_held[4] >= 1                      # the last bases were updated by rows
    out, into = swap_pairs(m, rng)
    _assert_same_scores(obj.evaluate_swaps(m, out, into, return_kernels=True),
                        obj.evaluate(swap_masks(m, out, into), return_kernels=True),
                        rtol=1e-10 if dtype == torch.float64 else 2e-4, atol=0 if dtype == torch.float64 else 1e-6)


def test_paper_neighbourhoods_with_all_rows_kept_along_a_walk(paper_objective, monkeypatch):
    obj = paper_objective
    basis = obj.psf.basis
    assert basis.U is not None                                 # the compressed basis: rows are U V
    assert obj.prepare_neighbourhoods() is True
    H, have = basis._swap_rows
    assert bool(have.all()) and H.shape[0] == basis.pairs_e.numel()
    pairs = torch.tensor([0, 7, basis.pairs_e.numel() - 1])
    torch.testing.assert_close(H[pairs], basis.U[pairs] @ basis.V)
    rng = np.random.default_rng(8)
    _walk_images(obj, _mask(64, rng.choice(64, 32, replace=False)), rng, 8, torch.float32, 1e-5)
