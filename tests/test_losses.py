"""The loss has one home (arraysel.objective.losses): every objective, the relaxations and the
end-to-end trainer use it, and the agreed behaviour (L_ent and L_row on P_soft) is pinned here."""
from __future__ import annotations

import math

import pytest
import torch

from arraysel.errors import ParameterError
from arraysel.objective import losses as L
from arraysel.objective import metrics as M
from arraysel.objective.toy import ToyObjective
from arraysel.selectors import relax


def _straight_through(n=8, k=4):
    """A valid hard selection P (rows sum to <= 1) whose P_soft puts most of every column on element 0
    (the same case as tests/test_selection_loss.py, where the PSF objective is pinned)."""
    P = torch.zeros(n, k, dtype=torch.float64)
    P[[0, 2, 4, 6], range(k)] = 1.0
    P_soft = torch.full((n, k), 0.05, dtype=torch.float64)
    P_soft[0, :] = 0.65
    P_soft = P_soft / P_soft.sum(0, keepdim=True)
    return relax.Relaxation((P - P_soft) + P_soft, P_soft, P, [0, 2, 4, 6])


def test_one_definition_of_each_term():
    # the loss terms live in objective.losses only (objective.metrics holds the PSF metrics)
    assert not any(hasattr(M, n) for n in ("l_ent", "l_row", "l_conv", "l_rec", "composite_loss", "DEFAULT_WEIGHTS"))
    assert relax.column_entropy is L.l_ent and relax.row_penalty is L.l_row
    from arraysel.e2e import trainer
    assert trainer.entropy_loss is L.l_ent and trainer.row_loss is L.l_row


def test_row_term_is_taken_on_p_soft():
    rel = _straight_through()
    assert float(L.l_row(rel.P)) == 0.0          # distinct one-hot columns: never over 1
    assert float(L.l_row(rel.P_soft)) > 0.0
    terms = L.selection_terms(rel.P_soft)
    assert float(terms["L_row"]) == float(L.l_row(rel.P_soft))
    assert float(terms["L_ent"]) == float(L.l_ent(rel.P_soft))
    assert set(L.selection_terms(rel.P_soft, {"L_ent": 0.0, "L_row": 2.0})) == {"L_row"}


def test_toy_selection_loss_uses_the_shared_terms():
    obj = ToyObjective(8, 4)
    rel = _straight_through()
    total, terms = obj.selection_loss(rel.P.float(), rel.P_soft.float(), 0)
    assert float(terms["L_row"]) == pytest.approx(float(L.l_row(rel.P_soft.float())), rel=1e-6)
    assert float(terms["L_row"]) > 0
    w = L.DEFAULT_WEIGHTS
    expect = (w["L_PSF"] * terms["L_PSF"] + w["L_contrast"] * terms["L_contrast"] + w["L_SLR"] * terms["L_SLR"]
              + w["L_ent"] * terms["L_ent"] + w["L_row"] * terms["L_row"])
    assert float(total) == pytest.approx(float(expect), rel=1e-6)
    # the mask loss is the weighted PSF part only
    mtotal, mterms = obj.mask_loss(rel.P.sum(1).detach().float()[None])
    assert float(mtotal[0]) == pytest.approx(float(L.training_loss(mterms, {k: w[k] for k in L.PSF_WEIGHT_KEYS})[0][0]),
                                             rel=1e-6)


def test_entropy_matches_the_former_relax_formula():
    p = torch.softmax(torch.randn(16, 4, generator=torch.Generator().manual_seed(1), dtype=torch.float64), 0)
    p = torch.cat([p, torch.zeros(3, 4, dtype=torch.float64)])
    old = -torch.where(p > 0, p * torch.log(p.clamp_min(torch.finfo(p.dtype).tiny)), torch.zeros_like(p)).sum(0).mean()
    assert float(L.l_ent(p)) == pytest.approx(float(old), rel=1e-12)
    old_row = torch.relu(p.sum(1) - 1.0).pow(2).sum()
    assert float(L.l_row(p)) == pytest.approx(float(old_row), rel=1e-12)


def test_weighted_sum_order_zeros_and_shape():
    terms = {"a": torch.tensor([1.0, 2.0]), "b": torch.tensor([3.0, 4.0]), "c": torch.tensor([math.nan, 0.0])}
    out = L.weighted_sum(terms, {"a": 2.0, "b": 0.5, "c": 0.0})
    assert out.tolist() == [3.5, 6.0]                # c has weight 0: skipped, NaN and all
    assert L.weighted_sum(terms, {}) == 0
    assert L.weighted_sum(terms, {"a": 1.0, "b": 1.0}, keys=("b",)).tolist() == [3.0, 4.0]
    assert L.PSF_WEIGHT_KEYS == ("L_PSF", "L_contrast", "L_SLR")


def test_training_loss_is_the_one_weighted_sum_of_every_caller():
    """training_loss sums LOSS_KEYS in order, adds L_ent / L_row of P_soft, divides by scales,
    skips unweighted and extra terms, and keeps the terms' shape."""
    rel = _straight_through()
    terms = {"L_PSF": torch.tensor([1.0, 2.0]), "L_SLR": torch.tensor([0.5, 0.25]),
             "L_SLR_q": torch.tensor([math.nan, math.nan]), "L_conv": torch.tensor([4.0, 8.0])}
    w = {"L_PSF": 2.0, "L_SLR": 4.0, "L_conv": 0.0, "L_ent": 1.0, "L_row": 3.0}
    total, out = L.training_loss(terms, w, P_soft=rel.P_soft, scales={"L_PSF": 2.0})
    reg = float(L.l_ent(rel.P_soft)) + 3.0 * float(L.l_row(rel.P_soft))
    assert total.tolist() == pytest.approx([1.0 + 2.0 + reg, 2.0 + 1.0 + reg])
    assert set(out) == set(terms) | {"L_ent", "L_row"}
    zero, _ = L.training_loss({"L_PSF": torch.ones(2, dtype=torch.float64)}, {"L_PSF": 0.0})
    assert zero.dtype == torch.float64 and float(zero) == 0.0
    assert L.LOSS_KEYS == ("L_PSF", "L_contrast", "L_SLR", "L_conv", "L_rec", "L_ent", "L_row")
    assert set(L.LOSS_KEYS) == set(L.DEFAULT_WEIGHTS)


def test_weights_take_the_scene_names_only():
    from arraysel.e2e.config import TrainConfig

    assert L.check_weights(None) == dict(L.DEFAULT_WEIGHTS)
    assert L.check_weights({"L_rec": 0})["L_rec"] == 0.0 and L.check_weights({})["L_PSF"] == 10.0
    with pytest.raises(ParameterError, match="'L_PSF'"):
        L.check_weights({"psf": 1.0})
    with pytest.raises(ParameterError, match="unknown loss term"):
        L.check_weights({"L_nope": 1.0})
    with pytest.raises(ParameterError, match="L_row"):
        L.check_weights({"L_row": -1.0})
    assert TrainConfig(weights={"L_conv": 0}).weights["L_conv"] == 0.0
    with pytest.raises(ParameterError, match="'L_conv'"):
        TrainConfig(weights={"conv": 0})


def test_training_loss_gradcheck():
    """The assembled loss is differentiable in the terms and in P_soft (float64 gradcheck)."""
    gen = torch.Generator().manual_seed(3)
    psf = torch.rand(2, dtype=torch.float64, generator=gen, requires_grad=True)
    logits = torch.randn(6, 3, dtype=torch.float64, generator=gen, requires_grad=True)
    w = {"L_PSF": 10.0, "L_SLR": 2.0, "L_ent": 1.0, "L_row": 10.0}

    def f(psf, logits):
        p_soft = torch.softmax(logits, 0)
        total, _ = L.training_loss({"L_PSF": psf, "L_SLR": psf ** 2}, w, P_soft=p_soft * 1.5,
                                   scales={"L_SLR": 3.0})
        return total

    assert torch.autograd.gradcheck(f, (psf, logits), eps=1e-6, atol=1e-8, rtol=1e-6)
