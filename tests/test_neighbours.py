"""One-swap neighbourhoods and moves of several elements (arraysel.objective.neighbours): the pairs,
the masks, the scores through an objective's own ``evaluate_swaps``/``evaluate_moves`` or by
independent masks, and the runner's bookkeeping of them."""
from __future__ import annotations

import numpy as np
import pytest

from arraysel.errors import SelectionError
from arraysel.objective.contract import ScoresMoves, ScoresSwaps
from arraysel.objective.neighbours import evaluate_moves, evaluate_swaps, move_masks, swap_masks, swap_pairs
from arraysel.selectors.contract import Budget, BudgetedObjective, BudgetExhausted, Recorder
from arraysel.testing import ToyObjective


@pytest.fixture(autouse=True)
def _row_sums_always(monkeypatch):
    # the small test scenes' bases have so few columns that swap_images would form the product
    # (c U) V of each neighbour rather than sum its rows; these tests check the row sums (the
    # product has a test of its own)
    from arraysel.physics.psf.basis import PairBasis

    monkeypatch.setattr(PairBasis, "move_row_cost", 0)


def _mask(n, on):
    m = np.zeros(n, dtype=bool)
    m[list(on)] = True
    return m


def _random_moves(m, size, rng, count):
    """``count`` random moves of ``size`` elements of the selection ``m``: (count, size) each."""
    on, off = np.flatnonzero(m), np.flatnonzero(~m)
    out = np.stack([rng.choice(on, size, replace=False) for _ in range(count)])
    into = np.stack([rng.choice(off, size, replace=False) for _ in range(count)])
    return out, into


def _padded(moves):
    """One (B, m) pair of arrays from moves of different sizes, rows padded with -1."""
    width = max(o.shape[1] for o, _ in moves)
    pad = [np.pad(v, ((0, 0), (0, width - v.shape[1])), constant_values=-1) for o, i in moves for v in (o, i)]
    return np.concatenate(pad[0::2]), np.concatenate(pad[1::2])


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


def test_move_masks_and_bad_moves_name_the_argument():
    m = _mask(8, [0, 2, 4, 6])
    got = move_masks(m, [[0, 2], [4, 6]], [[1, 3], [5, 7]])
    assert got.tolist() == [_mask(8, [1, 3, 4, 6]).tolist(), _mask(8, [0, 2, 5, 7]).tolist()]
    np.testing.assert_array_equal(move_masks(m, [0, 4], [1, 5]), swap_masks(m, [0, 4], [1, 5]))  # (B,): m = 1
    assert move_masks(m, np.zeros((0, 2), int), np.zeros((0, 2), int)).shape == (0, 8)
    with pytest.raises(SelectionError, match="out names an element twice"):
        move_masks(m, [[0, 0]], [[1, 3]])
    with pytest.raises(SelectionError, match="into names an element twice"):
        move_masks(m, [[0, 2]], [[3, 3]])
    with pytest.raises(SelectionError, match="one shape"):
        move_masks(m, [[0, 2]], [[1]])
    with pytest.raises(SelectionError, match="out must name active elements"):
        move_masks(m, [[0, 1]], [[3, 5]])
    with pytest.raises(SelectionError, match="into holds element indices outside"):
        move_masks(m, [[0, 2]], [[3, 8]])


def test_moves_are_scored_by_the_objective_s_own_scoring_or_as_masks():
    m = _mask(14, [0, 2, 5, 7, 9, 12])
    out, into = _random_moves(m, 3, np.random.default_rng(0), 20)
    obj = ToyObjective(14, 6, dtype=torch.float64)
    got, ref = evaluate_moves(obj, m, out, into), obj.evaluate(move_masks(m, out, into))
    assert set(got) == set(ref) and all(np.array_equal(got[key], ref[key]) for key in ref)
    # one element a move: the objective's evaluate_swaps, where it has only that
    own = _OwnSwaps(14, 6)
    _OwnSwaps.calls = 0
    got = evaluate_moves(own, m, out[:, :1], into[:, :1])
    assert _OwnSwaps.calls == 1
    np.testing.assert_array_equal(got["Mean"], own.evaluate(swap_masks(m, out[:, 0], into[:, 0]))["Mean"])


def test_budgeted_moves_equal_budgeted_masks():
    # the same scores, counts and trace as scoring the moved masks with evaluate, and the budget
    # ends a call part-way as it does for masks
    m = _mask(10, [1, 4, 6, 8])
    out, into = _random_moves(m, 2, np.random.default_rng(1), 30)
    results = []
    for how in ("moves", "masks"):
        obj = ToyObjective(10, 4)
        budget = Budget(evaluations=100).start(obj)
        rec = Recorder(obj, budget)
        view = BudgetedObjective(obj, budget, rec, 4, piece=8)
        v = view.score_moves(m, out, into) if how == "moves" else view.score(move_masks(m, out, into))
        results.append((v, obj.evaluations, rec.best, [r["evaluations"] for r in rec.rows]))
    np.testing.assert_array_equal(results[0][0], results[1][0])
    assert results[0][1:] == results[1][1:]
    obj = ToyObjective(10, 4)
    budget = Budget(evaluations=20).start(obj)
    view = BudgetedObjective(obj, budget, Recorder(obj, budget), 4, piece=8)
    with pytest.raises(BudgetExhausted, match="20 of 30 masks"):
        view.score_moves(m, out, into)
    assert obj.evaluations == 20


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
        calls.append(int(out.shape[0]))
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
def test_swap_and_move_envelopes_equal_the_envelopes_of_the_neighbour_masks(monkeypatch, dtype, rtol):
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
    # moves of 1 to 4 elements in one call, rows padded with -1
    out, into = _padded([_random_moves(m, size, np.random.default_rng(size), 3) for size in (1, 2, 3, 4)])
    w = torch.as_tensor(move_masks(m, out, into), dtype=dtype)
    got = basis.certificates.swap_envelopes(torch.as_tensor(m, dtype=dtype), torch.as_tensor(out), torch.as_tensor(into))
    ref = basis.certificates.envelopes(w)
    np.testing.assert_allclose(got.numpy(), ref.numpy(), rtol=rtol, atol=rtol * float(ref.abs().max()))


@pytest.mark.parametrize("dtype, rtol", [(torch.float64, 1e-12), (torch.float32, 1e-5)])
def test_held_channel_sums_follow_a_walk_of_moves(monkeypatch, dtype, rtol):
    # a search's next selection is a swap or a shift away: its channel sums are the held ones
    # corrected by the rows switched (counted, refreshed after swap_sums_refresh in a row; a
    # selection farther away is summed afresh), and its neighbours' envelopes are those of the
    # neighbour masks either way
    monkeypatch.setenv("ARRAYSEL_CACHE", "off")
    obj = _tiny_objective(dtype, probe={"n_elements": 10}, selection={"k": 6})
    cert = obj.psf.basis.certificates
    monkeypatch.setattr(type(cert), "swap_sums_refresh", 3)
    rng = np.random.default_rng(5)
    m = _mask(10, [0, 1, 4, 5, 7, 9])
    counts = []
    for step in range(7):
        out, into = swap_pairs(m, rng)
        got = cert.swap_envelopes(torch.as_tensor(m, dtype=dtype), torch.as_tensor(out), torch.as_tensor(into))
        counts.append(cert._swap_sums[2])
        A = cert.pair_channels.numpy().astype(np.float64)
        fresh = A[np.flatnonzero(m)].sum(0).reshape(10, -1)
        np.testing.assert_allclose(cert._swap_sums[1], fresh, rtol=1e-12, atol=1e-12 * np.abs(fresh).max())
        ref = cert.envelopes(torch.as_tensor(swap_masks(m, out, into), dtype=dtype))
        np.testing.assert_allclose(got.numpy(), ref.numpy(), rtol=rtol, atol=rtol * float(ref.abs().max()))
        if step == 4:   # the mirror image: too many elements switched, summed afresh
            m = m[::-1].copy()
        else:
            m = swap_masks(m, out[step:step + 1], into[step:step + 1])[0]
    assert counts == [0, 1, 2, 3, 0, 0, 1]


def test_receive_major_visits_every_used_channel_once_receive_element_by_element():
    from arraysel.physics.pairkernels import receive_major

    used = np.random.default_rng(0).random((5, 7)) < 0.5
    sel_b, sel_e = receive_major(used)
    assert sel_b.dtype == sel_e.dtype == np.int64
    assert sorted(zip(sel_b.tolist(), sel_e.tolist())) == sorted(zip(*(v.tolist() for v in np.nonzero(used))))
    assert list(zip(sel_e.tolist(), sel_b.tolist())) == sorted(zip(sel_e.tolist(), sel_b.tolist()))


@pytest.mark.parametrize("dtype, rtol", [(torch.float64, 1e-12), (torch.float32, 1e-5)])
def test_refinement_channels_of_neighbours_from_the_held_sums_equal_the_product(monkeypatch, dtype, rtol):
    # the I/Q channels the refinement delay-and-sums, for selections 0 to 2 elements away from the
    # one whose neighbourhood is scored: corrected from its held channel sums, the same values (on
    # the receive elements each uses) as the product with every pair channel
    from arraysel.physics.psf.certificate import Certificates

    monkeypatch.setenv("ARRAYSEL_CACHE", "off")
    obj = _tiny_objective(dtype, probe={"n_elements": 10}, selection={"k": 6})
    basis = obj.psf.basis
    cert, ref = basis.certificates, basis.refinement
    m = _mask(10, [0, 1, 4, 5, 7, 9])
    out, into = _padded([_random_moves(m, size, np.random.default_rng(size), 3) for size in (1, 2)])
    w = torch.as_tensor(np.concatenate([move_masks(m, out, into), m[None]]), dtype=dtype)
    idx = list(range(w.shape[0]))
    cert._swap_sums = None
    want = [x for _, x in ref._grouped_channels(w, idx, raw=True)]
    assert cert.swap_moves(w) is None                         # no sums held
    cert.swap_envelopes(torch.as_tensor(m, dtype=dtype), torch.as_tensor(out[:1]), torch.as_tensor(into[:1]))
    before = cert.corrected
    got = [x for _, x in ref._grouped_channels(w, idx, raw=True)]
    assert cert.corrected - before == len(idx)
    for b, (g, x) in enumerate(zip(got, want)):
        used = w[b].numpy() != 0
        assert g.y.dtype == x.y.dtype and np.array_equal(g.we, x.we) and g.segment == x.segment
        scale = float(np.abs(x.y[used]).max())
        np.testing.assert_allclose(g.y[used], x.y[used], rtol=rtol, atol=rtol * scale)
    # formed afresh: soft weights, a gradient, selections further away than swap_channels_most,
    # or so far that the correction reads as many rows as the product (3 elements of 6)
    assert cert.swap_moves(w * 0.5) is None
    assert cert.swap_moves(w.clone().requires_grad_(True)) is None
    far = torch.as_tensor(move_masks(m, *_random_moves(m, 3, np.random.default_rng(0), 1)), dtype=dtype)
    assert cert.swap_moves(far) is None
    monkeypatch.setattr(Certificates, "swap_channels_most", 1)
    assert cert.swap_moves(w) is None and cert.swap_moves(w[:3]) is not None


@pytest.mark.parametrize("dtype, rtol", [(torch.float64, 1e-10), (torch.float32, 2e-4)])
@pytest.mark.slow
def test_neighbourhood_refined_block_by_block_equals_independent_masks(monkeypatch, dtype, rtol):
    # block bounds made loose (x 1000): every neighbour's peak is settled by the refinement's block
    # delay-and-sums, from channels corrected from the selection's sums; the scores are those
    # of the masks scored alone (whose channels are the product)
    from arraysel.physics.psf.certificate import Certificates

    monkeypatch.setenv("ARRAYSEL_CACHE", "off")
    real = Certificates.bound

    def loose(self, *a, **kw):
        return real(self, *a, **kw) * 1000

    monkeypatch.setattr(Certificates, "bound", loose)
    obj = _tiny_objective(dtype, probe={"n_elements": 12}, selection={"k": 5})
    ref_ = obj.psf.basis.refinement
    m = _mask(12, [0, 3, 4, 8, 11])
    out, into = swap_pairs(m, np.random.default_rng(3))
    got = obj.evaluate_swaps(m, out, into, return_kernels=True)
    assert obj.psf.basis.certificates.corrected > 0
    obj.psf.basis.certificates._swap_sums = None
    ref = obj.evaluate(swap_masks(m, out, into), return_kernels=True)
    _assert_same_scores(got, ref, rtol)


@pytest.mark.parametrize("rows", ["kept", "formed", "product", "mixed"])
@pytest.mark.parametrize("dtype, rtol", [(torch.float64, 1e-10), (torch.float32, 2e-4)])
def test_psf_objective_moves_equal_independent_masks(monkeypatch, dtype, rtol, rows):
    # moves of 1 to 3 elements on a 12-element scene with two field points, every key and kernel
    # as the masks scored alone: the images summed from kept pair-image rows, from rows formed
    # for the call, the product (c U) V of each neighbour, or each where it costs less; then moves
    # of 0 to 4 elements in one call (rows padded with -1)
    from arraysel.physics.psf.basis import PairBasis

    monkeypatch.setenv("ARRAYSEL_CACHE", "off")
    obj = _tiny_objective(dtype, probe={"n_elements": 12}, selection={"k": 5},
                          medium={"points": [[0.0, 0.02], [0.001, 0.021]]})
    assert isinstance(obj, ScoresMoves)
    if rows == "formed":
        for p in obj.psfs:
            p.basis.swap_rows_max_bytes = 0
    else:
        assert obj.prepare_neighbourhoods() is True
    if rows == "product":
        monkeypatch.setattr(PairBasis, "move_row_cost", 10 ** 9)
    elif rows == "mixed":   # rows for moves of one element, the product for wider ones
        monkeypatch.setattr(PairBasis, "move_row_cost", obj.psf.basis.U.shape[1] // 4 if obj.psf.basis.U is not None
                            else 0)
    calls = _spy_swap_envelopes(monkeypatch)
    rng = np.random.default_rng(6)
    m = _mask(12, [0, 3, 4, 8, 11])
    for size in (1, 2, 3):
        out, into = _random_moves(m, size, rng, 12)
        got = obj.evaluate_moves(m, out, into, return_kernels=True)
        ref = obj.evaluate(move_masks(m, out, into), return_kernels=True)
        _assert_same_scores(got, ref, rtol)
        m = move_masks(m, out[:1], into[:1])[0]        # a search's step: the next base
    assert calls == [12] * 6                            # one call a field point and size
    if rows == "formed":
        assert all("_swap_rows" not in p.basis.__dict__ for p in obj.psfs)
    out, into = _padded([_random_moves(m, size, rng, 4) for size in (2, 4, 1, 3)] + [(-np.ones((1, 1), int),) * 2])
    got = obj.evaluate_moves(m, out, into, return_kernels=True)
    _assert_same_scores(got, obj.evaluate(move_masks(m, out, into), return_kernels=True), rtol)
    assert calls[6:] == [17, 17]                        # 4 moves each of 1 to 4 elements and one of none
    none = np.zeros((2, 0), dtype=int)
    _assert_same_scores(obj.evaluate_moves(m, none, none), obj.evaluate(np.stack([m, m])), rtol)


def test_moves_between_lists_the_switched_elements():
    from arraysel.objective.neighbours import moves_between

    m = _mask(8, [0, 2, 4, 6])
    cands = np.stack([_mask(8, [1, 2, 4, 6]), _mask(8, [0, 2, 4, 6]), _mask(8, [1, 3, 5, 6])])
    out, into = moves_between(m, cands)
    assert out.tolist() == [[0, -1, -1], [-1, -1, -1], [0, 2, 4]]
    assert into.tolist() == [[1, -1, -1], [-1, -1, -1], [1, 3, 5]]
    np.testing.assert_array_equal(move_masks(m, out, into), cands)
    with pytest.raises(SelectionError, match="as many active elements"):
        moves_between(m, _mask(8, [0])[None])
    with pytest.raises(SelectionError, match="as many elements in each row"):
        move_masks(m, [[0, -1]], [[1, 3]])


def test_move_rows_sum_signed_rows_in_float64():
    from arraysel.physics.pairkernels import move_rows

    rng = np.random.default_rng(0)
    C = 5000                                          # not a multiple of the column chunk
    H = rng.standard_normal((30, C)).astype(np.float32)
    y, G = rng.standard_normal(C), rng.standard_normal((10, C))
    out, into = rng.integers(0, 10, (7, 3)), rng.integers(0, 10, (7, 3))
    pidx, psign = rng.integers(0, 30, (7, 5)), np.array([1.0, 1.0, -1.0, 1.0, -1.0])
    ref = y - G[out].sum(1) + G[into].sum(1) + (psign[None, :, None] * H[pidx].astype(np.float64)).sum(1)
    got = move_rows(H, y, G, out, into, pidx, psign)
    assert got.shape == (7, C) and got.dtype == np.float32
    np.testing.assert_allclose(got, ref.astype(np.float32), rtol=1e-6, atol=1e-6)
    assert move_rows(H, y, G, out[:0], into[:0], pidx[:0], psign).shape == (0, C)


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


@pytest.mark.slow
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
    # the outer elements (moving peaks) and a random selection of a built-in scene: 64 one-swap
    # neighbours and 64 segment shifts each, every key and kernel as the masks scored alone
    # (builds the scene's basis: minutes)
    from arraysel.objective.neighbours import moves_between
    from arraysel.objective.psf_objective import Objective
    from arraysel.selectors.localsearch import shift_moves, shifted_masks

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
        # segment shifts of the selection, as moves of up to 12 elements in padded chunks
        cands = shifted_masks(m, shift_moves(n, 24, 6, rng)[:96])
        cands = cands[(cands != m).any(1)][:64]
        got = obj.evaluate_moves(m, *moves_between(m, cands), return_kernels=True)
        _assert_same_scores(got, obj.evaluate(cands, return_kernels=True), rtol=rtol,
                            atol=1e-6 if dtype == torch.float32 else 1e-12)


def _walk_images(obj, m, rng, moves, dtype, tol):
    """A search's walk: at each step the neighbours' images on E against the product of each
    neighbour, then a move to one of them (every third step a further jump of two elements, and
    every fifth of three: the base is carried by rows over moves of up to
    ``swap_base_moved_max`` elements and formed afresh beyond, from the bases the objective
    keeps); returns the selection reached."""
    basis = obj.psf.basis
    bases = obj.swap_bases(obj.psf)
    for step in range(moves):
        out, into = swap_pairs(m, rng)
        out, into = out[:16], into[:16]
        w = torch.as_tensor(swap_masks(m, out, into), dtype=dtype)
        with torch.no_grad():
            img, eps, werr = basis.swap_images(torch.as_tensor(m, dtype=dtype), torch.as_tensor(out),
                                               torch.as_tensor(into), w, bases)
            img_r, eps_r, werr_r = basis.images(w, with_error=True)
        assert float((img - img_r).abs().amax()) <= tol * float(img_r.abs().amax()), step
        assert torch.equal(eps, eps_r) and torch.equal(werr, werr_r)
        m = swap_masks(m, out[step % 16:step % 16 + 1], into[step % 16:step % 16 + 1])[0]
        if step % 3 == 2:
            on, off = np.flatnonzero(m), np.flatnonzero(~m)
            m = swap_masks(m, on[:1], off[:1])[0]
        if step % 5 == 4:
            on, off = np.flatnonzero(m), np.flatnonzero(~m)
            m = move_masks(m, on[None, -3:], off[None, :3])[0]
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
    monkeypatch.setattr(type(basis), "swap_base_refresh", 6)
    monkeypatch.setattr(type(basis), "swap_base_moved_max", 2)
    updated = []
    real = type(basis).swap_base

    def spy(self, mask, bases=None):
        out = real(self, mask, bases)
        updated.append(bases.latest()[3])
        return out

    monkeypatch.setattr(type(basis), "swap_base", spy)
    rng = np.random.default_rng(4)
    m = _walk_images(obj, _mask(12, [0, 2, 3, 7, 9, 11]), rng, 14, dtype, tol)
    assert 2 in np.diff(updated) and 0 in updated[1:]       # a two-element move by rows; bases formed afresh
    assert obj.swap_bases(obj.psf).latest()[3] >= 1   # the last bases were updated by rows
    out, into = swap_pairs(m, rng)
    _assert_same_scores(obj.evaluate_swaps(m, out, into, return_kernels=True),
                        obj.evaluate(swap_masks(m, out, into), return_kernels=True),
                        rtol=1e-10 if dtype == torch.float64 else 2e-4, atol=0 if dtype == torch.float64 else 1e-6)


@pytest.mark.parametrize("kept", [3, 1])
def test_interleaved_walks_each_keep_their_base(monkeypatch, kept):
    # three walks taking turns, a swap each turn (a race's descents): with room for three bases
    # each walk finds its own and carries it by rows (three bases formed in all); with room for
    # one, a turn forms its base afresh unless the last walk's happens to be a swap away; the
    # images equal the product either way
    from arraysel.objective.neighbours import prepare_neighbourhoods

    monkeypatch.setenv("ARRAYSEL_CACHE", "off")
    obj = _tiny_objective(torch.float64, probe={"n_elements": 12}, selection={"k": 6})
    basis = obj.psf.basis
    assert prepare_neighbourhoods(obj) >= 0
    entry = 16 * (12 + 1) * basis.npix
    monkeypatch.setattr(type(basis), "swap_base_max_bytes", kept * entry + entry // 2)
    monkeypatch.setattr(type(basis), "swap_base_moved_max", 1)   # a walk's own last base only
    formed, reachable = [], []
    real = type(basis).swap_base

    def spy(self, mask, bases=None):
        m = mask.cpu().numpy() != 0
        kept_masks = [e[0].numpy() for e in bases.kept.values()]
        reachable.append(any((k & ~m).sum() <= 1 for k in kept_masks))   # a kept base a swap away
        out = real(self, mask, bases)
        formed.append(bases.latest()[3] == 0)
        return out

    monkeypatch.setattr(type(basis), "swap_base", spy)
    rng = np.random.default_rng(11)
    walks = [_mask(12, rng.choice(12, 6, replace=False)) for _ in range(3)]
    for turn in range(4):
        for i, m in enumerate(walks):
            walks[i] = _walk_images(obj, m, rng, 1, torch.float64, 1e-11)
            assert len(obj.swap_bases(obj.psf)) <= kept
    assert formed == [not r for r in reachable]               # formed afresh exactly when none is at hand
    assert sum(formed) == 3 if kept == 3 else sum(formed) >= 9


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
