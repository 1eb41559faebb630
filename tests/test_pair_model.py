"""The gradient and Hessian of the PSF loss from the pair basis (:mod:`arraysel.objective.pair_model`)
against torch's autograd of the same ``mask_loss``."""
from __future__ import annotations

import tomllib

import numpy as np
import pytest
import torch

from arraysel.objective.pair_model import pair_model
from scene_texts import TINY_SCENE


def _objective(dtype, fast=True, points=None):
    from arraysel.objective.psf_objective import Objective
    from arraysel.scenes.schema import load_scene

    text = TINY_SCENE if points is None else TINY_SCENE + points
    return Objective(load_scene(tomllib.loads(text)), dtype=dtype, fast=fast)


def _autograd(obj, mask):
    """``(total, g, H)`` of ``obj.mask_loss`` at ``mask`` by torch's dense autograd (float64)."""
    f = lambda w: obj.mask_loss(w[None])[0].sum()  # noqa: E731
    w = torch.tensor(mask, dtype=obj.dtype)
    return (float(f(w)), torch.autograd.functional.jacobian(f, w).double().numpy(),
            torch.autograd.functional.hessian(f, w).double().numpy())


def _masks(n, k, count, seed):
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(count):
        m = np.zeros(n, dtype=bool)
        m[rng.choice(n, k, replace=False)] = True
        out.append(m)
    return out


@pytest.mark.parametrize("k", [1, 3, 8])
def test_pair_model_equals_autograd_in_float64(k):
    obj = _objective(torch.float64)
    n = obj.n_elements
    applied = 0
    for mask in _masks(n, k, 3 if k < n else 1, seed=k):
        t_ref, g_ref, H_ref = _autograd(obj, mask)
        g_obj, H_obj = obj.mask_hessian(mask)   # the pair model where it applies, else autograd
        np.testing.assert_allclose(g_obj, g_ref, rtol=1e-8, atol=1e-8 * np.abs(g_ref).max())
        np.testing.assert_allclose(H_obj, 0.5 * (H_ref + H_ref.T), rtol=1e-8, atol=1e-8 * np.abs(H_ref).max())
        got = pair_model(obj, mask)
        if got is None:
            continue
        applied += 1
        total, g, H = got
        assert total == pytest.approx(t_ref, rel=1e-10)
        np.testing.assert_allclose(g, g_ref, rtol=1e-8, atol=1e-8 * np.abs(g_ref).max())
        np.testing.assert_allclose(H, 0.5 * (H_ref + H_ref.T), rtol=1e-8, atol=1e-8 * np.abs(H_ref).max())
        _, g_only, none = pair_model(obj, mask, hessian=False)
        assert none is None
        np.testing.assert_array_equal(g_only, g)
    # one element's kernel is too wide for tier 1 to certify on this small grid: autograd serves it
    assert applied == (0 if k == 1 else 3 if k < n else 1)


def test_pair_model_float32_agrees_with_float64():
    obj32, obj64 = _objective(torch.float32), _objective(torch.float64)
    applied = 0
    for mask in _masks(obj32.n_elements, 4, 3, seed=7):
        applied += pair_model(obj32, mask) is not None
        g32, H32 = obj32.mask_hessian(mask)
        g64, H64 = obj64.mask_hessian(mask)
        np.testing.assert_allclose(g32, g64, rtol=1e-3, atol=1e-4 * np.abs(g64).max())
        np.testing.assert_allclose(H32, H64, rtol=1e-3, atol=1e-4 * np.abs(H64).max())
    assert applied


def test_pair_model_of_a_several_point_scene_sums_its_points():
    obj = _objective(torch.float64, points='[medium]\npoints = [[0.0, "1.2 mm"], ["0.3 mm", "1.6 mm"]]\n')
    assert obj.n_points == 2
    applied = 0
    for mask in _masks(obj.n_elements, 4, 3, seed=3):
        got = pair_model(obj, mask)
        if got is None:  # a point whose kernel tier 1 does not settle: mask_hessian takes autograd
            continue
        applied += 1
        _, g, H = got
        _, g_ref, H_ref = _autograd(obj, mask)
        np.testing.assert_allclose(g, g_ref, rtol=1e-8, atol=1e-8 * np.abs(g_ref).max())
        np.testing.assert_allclose(H, 0.5 * (H_ref + H_ref.T), rtol=1e-8, atol=1e-8 * np.abs(H_ref).max())
    assert applied


def test_mask_hessian_falls_back_to_autograd_where_the_pair_model_does_not_apply(monkeypatch):
    obj = _objective(torch.float64)
    mask = _masks(obj.n_elements, 4, 1, seed=5)[0]
    g_pairs, H_pairs = obj.mask_hessian(mask)
    # no basis (the exact path only): no pair model, the same Hessian by autograd
    exact = _objective(torch.float64, fast=False)
    assert pair_model(exact, mask) is None
    g_ex, H_ex = exact.mask_hessian(mask)
    _, _, H_ref = _autograd(exact, mask)
    np.testing.assert_allclose(H_ex, 0.5 * (H_ref + H_ref.T), rtol=1e-8, atol=1e-8 * np.abs(H_ref).max())
    np.testing.assert_allclose(H_ex, H_pairs, rtol=1e-2, atol=1e-2 * np.abs(H_ex).max())  # the basis's error
    # a kernel that tier 1 does not settle: None, and mask_hessian's autograd gives the same values
    refinement = obj.psf.basis.refinement
    real = refinement.kernels

    def unsettled(w, env=None, images=None, tier_one=False):
        out, ok = real(w, env=env, images=images, tier_one=tier_one)
        return out, ok & (not tier_one)

    monkeypatch.setattr(refinement, "kernels", unsettled)
    assert pair_model(obj, mask) is None
    before = obj.evaluations
    g_auto, H_auto = obj.mask_hessian(mask)
    assert obj.evaluations - before == obj.n_elements
    np.testing.assert_allclose(g_auto, g_pairs, rtol=1e-8, atol=1e-8 * np.abs(g_auto).max())
    np.testing.assert_allclose(H_auto, H_pairs, rtol=1e-8, atol=1e-8 * np.abs(H_auto).max())
