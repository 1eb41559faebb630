"""Objective.selection_loss: the row term acts on P_soft (issue 13, item 6)."""
from __future__ import annotations

import pytest
import torch

from arraysel.objective import losses as L
from arraysel.objective.psf_objective import Objective
from arraysel.scenes.schema import load_scene

TINY = {"probe": {"n_elements": 8}, "selection": {"k": 4}, "transmit": {"n_tx": 1},
        "grid": {"n_x": 16, "n_z": 16, "window": 8, "pixel_per_wavelength_fs": 1.0},
        "metrics": {"r_main": 0.5, "r_guard": 1.0},
        "simulator": {"fast_margin": 2, "fast_block": 4}}


@pytest.fixture
def tiny(monkeypatch):
    monkeypatch.setenv("ARRAYSEL_CACHE", "off")
    return Objective(load_scene(dict(TINY, base="paper")))


def test_row_term_acts_on_p_soft_not_on_the_straight_through_p(tiny):
    assert tiny.weights.get("L_row", 0) > 0
    n, k = 8, 4
    P = torch.zeros(n, k)
    P[[0, 2, 4, 6], range(k)] = 1.0          # a valid hard selection: every row sums to <= 1
    P_soft = torch.full((n, k), 0.05)
    P_soft[0, :] = 0.65                      # element 0 carries most of every column's mass
    P_soft = P_soft / P_soft.sum(0, keepdim=True)
    assert float(L.l_row(P)) == 0.0 and float(L.l_row(P_soft)) > 0.1
    P_st = (P - P_soft).detach() + P_soft.clone().requires_grad_(True)
    total, terms = tiny.selection_loss(P_st, P_soft, 0)
    assert float(terms["L_row"]) == pytest.approx(float(L.l_row(P_soft)), rel=1e-6)
    assert float(terms["L_row"]) > 0.1       # the old code (L_row of P) gave exactly 0 here
