"""Tests of arraysel.selectors.relax: temperature schedule, sequential draws, Gumbel noise, stability."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from arraysel.selectors.relax import (column_entropy, cosine_temperature, gumbel_noise, project_capped_simplex,
                            row_penalty, selection_weights, sequential_selection)

DTYPES = [torch.float32, torch.float64]


def test_cosine_temperature_schedule():
    assert cosine_temperature(0) == pytest.approx(6.0)
    assert cosine_temperature(750) == pytest.approx(3.6)
    assert cosine_temperature(1500) == pytest.approx(1.2)
    assert cosine_temperature(10_000) == pytest.approx(1.2)
    taus = [cosine_temperature(s) for s in range(0, 1600, 10)]
    assert all(b <= a for a, b in zip(taus, taus[1:]))
    assert cosine_temperature(5, 2.0, 1.0, 0) == 1.0


@pytest.mark.parametrize("dtype", DTYPES)
def test_sequential_selection_draws_distinct_one_hot_columns(dtype):
    g = torch.Generator().manual_seed(0)
    logits = torch.randn(10, 6, generator=g, dtype=dtype, requires_grad=True)
    rel = sequential_selection(logits, 2.0)
    assert len(set(rel.indices)) == 6
    assert torch.equal(rel.P.detach(), rel.P_hard)
    torch.testing.assert_close(rel.P_soft.sum(dim=0), torch.ones(6, dtype=dtype))
    for j, i in enumerate(rel.indices):
        # elements drawn by earlier columns have zero probability in column j
        assert float(rel.P_soft.detach()[rel.indices[:j], j].abs().sum()) == 0.0
        assert rel.P_hard[i, j] == 1
    (rel.P * torch.arange(10, dtype=dtype)[:, None]).sum().backward()
    assert logits.grad is not None and torch.isfinite(logits.grad).all()
    assert float(logits.grad.abs().sum()) > 0


def _draw_column_by_column(logits, tau, noise=None, sample=False, generator=None):
    """The HARD-STE draw (docs/training.md) written out one column at a time (the definition the
    batched :func:`sequential_selection` must reproduce bit for bit)."""
    n, k = logits.shape
    scores = (logits if noise is None else logits + noise) / tau
    finfo = torch.finfo(logits.dtype)
    available = torch.ones(n, dtype=torch.bool)
    soft, chosen = [], []
    for j in range(k):
        s = scores[:, j].masked_fill(~available, -math.inf)
        p = torch.exp(torch.log_softmax(s, dim=0))
        pick = torch.nan_to_num(s.detach(), nan=finfo.min, posinf=finfo.max, neginf=finfo.min)
        i = int(torch.argmax(pick.masked_fill(~available, -math.inf)))
        probs = p.detach()
        if sample and bool(torch.isfinite(probs).all()) and float(probs.sum()) > 0:
            i = int(torch.multinomial(probs, 1, generator=generator))
        soft.append(torch.nan_to_num(p, nan=0.0))
        chosen.append(i)
        available[i] = False
    return torch.stack(soft, dim=1), chosen


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("case", ["normal", "large", "ties", "nonfinite"])
@pytest.mark.parametrize("shape", [(64, 32), (7, 7), (9, 1)])
def test_batched_draw_equals_the_column_by_column_definition(dtype, case, shape):
    """The draws (picked on the host) and the soft columns (all at once) equal the column by
    column definition exactly: the same elements, the same P_soft and P_hard bits, the same
    gradient bits, with and without Gumbel noise, by arg-max and by sampling."""
    n, k = shape
    g = torch.Generator().manual_seed(11)
    base = torch.randn(n, k, generator=g, dtype=dtype)
    if case == "large":
        base = base * 1e4
    elif case == "ties":
        base = torch.zeros(n, k, dtype=dtype)
    elif case == "nonfinite":
        base[0, 0] = math.nan
        base[1, :] = math.inf
        base[-1, -1] = -math.inf
    noise = gumbel_noise((n, k), g, dtype=dtype)
    weight = torch.linspace(-1, 1, n * k, dtype=dtype).reshape(n, k)
    for tau in (1e-3, 2.0, 1e3):
        for kw in ({}, {"noise": noise}, {"sample": True}):
            results = []
            for draw in ("batched", "reference"):
                logits = base.clone().requires_grad_(True)
                gen = torch.Generator().manual_seed(5)
                if draw == "batched":
                    rel = sequential_selection(logits, tau, generator=gen, **kw)
                    P_soft, chosen, P_hard = rel.P_soft, rel.indices, rel.P_hard
                else:
                    P_soft, chosen = _draw_column_by_column(logits, tau, generator=gen, **kw)
                    P_hard = torch.zeros(n, k, dtype=dtype)
                    P_hard[chosen, range(k)] = 1
                ((P_hard - P_soft).detach() + P_soft).mul(weight).sum().add(P_soft.square().sum()).backward()
                results.append((chosen, P_soft.detach(), P_hard, logits.grad))
            (c1, s1, h1, g1), (c2, s2, h2, g2) = results
            assert c1 == c2
            assert torch.equal(h1, h2)
            torch.testing.assert_close(s1, s2, rtol=0, atol=0, equal_nan=True)
            torch.testing.assert_close(g1, g2, rtol=0, atol=0, equal_nan=True)


def test_argmax_draw_ignores_temperature_and_soft_variant():
    logits = torch.tensor([[0.0, 5.0], [3.0, 4.0], [1.0, 0.0]])
    for tau in (1e-3, 1.0, 1e3):
        assert sequential_selection(logits, tau).indices == [1, 0]
    soft = sequential_selection(logits, 1.0, hard=False)
    assert torch.equal(soft.P, soft.P_soft)


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("tau", [1e-3, 1e-1, 1.0, 1e2, 1e3])
@pytest.mark.parametrize("scale", [1.0, 1e4])
def test_stable_at_extreme_temperatures_and_logits(dtype, tau, scale):
    g = torch.Generator().manual_seed(1)
    logits = (scale * (2 * torch.rand(16, 8, generator=g, dtype=dtype) - 1)).requires_grad_(True)
    noise = gumbel_noise((16, 8), g, dtype=dtype)
    for rel in (sequential_selection(logits, tau), sequential_selection(logits, tau, noise=noise),
                sequential_selection(logits, tau, sample=True, generator=g)):
        assert len(set(rel.indices)) == 8
        assert torch.isfinite(rel.P).all() and torch.isfinite(rel.P_soft).all()
        loss = (rel.P * torch.linspace(0, 1, 16, dtype=dtype)[:, None]).sum() + column_entropy(rel.P_soft)
        logits.grad = None
        loss.backward()
        assert torch.isfinite(logits.grad).all()


def test_nan_and_inf_logits_still_give_distinct_elements():
    logits = torch.full((6, 4), math.nan)
    logits[2, :] = math.inf
    logits[3, 1] = -math.inf
    rel = sequential_selection(logits, 1.0)
    assert len(set(rel.indices)) == 4 and all(0 <= i < 6 for i in rel.indices)


def test_k_equal_n_and_errors():
    rel = sequential_selection(torch.zeros(5, 5), 1.0)
    assert sorted(rel.indices) == [0, 1, 2, 3, 4]
    with pytest.raises(ValueError):
        sequential_selection(torch.zeros(3, 4), 1.0)
    with pytest.raises(ValueError):
        sequential_selection(torch.zeros(3, 2), 0.0)


@pytest.mark.parametrize("dtype", DTYPES)
def test_gumbel_noise_is_finite_and_standard(dtype):
    g = torch.Generator().manual_seed(2)
    x = gumbel_noise((200_000,), g, dtype=dtype)
    assert torch.isfinite(x).all()
    assert float(x.mean()) == pytest.approx(0.5772, abs=0.01)  # Euler-Mascheroni constant
    assert float(x.var()) == pytest.approx(math.pi ** 2 / 6, rel=0.03)
    # the clamp keeps even u = 0 or 1 finite
    assert torch.isfinite(gumbel_noise((10,), torch.Generator().manual_seed(3), dtype=dtype)).all()


def test_gumbel_max_samples_the_softmax():
    g = torch.Generator().manual_seed(4)
    logits = torch.tensor([[1.0], [0.0], [-1.0], [2.0]])
    counts = np.zeros(4)
    for _ in range(4000):
        counts[sequential_selection(logits, 1.0, noise=gumbel_noise((4, 1), g)).indices[0]] += 1
    np.testing.assert_allclose(counts / counts.sum(), torch.softmax(logits[:, 0], 0).numpy(), atol=0.03)


def test_same_generator_same_draws():
    logits = torch.randn(12, 5, generator=torch.Generator().manual_seed(0))
    draws = []
    for _ in range(2):
        g = torch.Generator().manual_seed(7)
        draws.append(sequential_selection(logits, 1.0, noise=gumbel_noise((12, 5), g)).indices)
    assert draws[0] == draws[1]


def test_weights_entropy_and_row_penalty():
    P = torch.tensor([[1.0, 0.0], [0.0, 1.0], [0.0, 0.0]])
    torch.testing.assert_close(selection_weights(P), torch.tensor([1.0, 1.0, 0.0]))
    assert float(column_entropy(P)) == 0.0
    assert float(column_entropy(torch.full((4, 2), 0.25))) == pytest.approx(math.log(4))
    assert float(row_penalty(P)) == 0.0
    assert float(row_penalty(torch.tensor([[1.0, 1.0], [0.0, 0.0]]))) == pytest.approx(1.0)


@pytest.mark.parametrize("k", [1.0, 3.0, 7.5, 10.0])
def test_project_capped_simplex(k):
    w = torch.randn(3, 10, generator=torch.Generator().manual_seed(5), dtype=torch.float64) * 3
    x = project_capped_simplex(w, k)
    assert (x >= 0).all() and (x <= 1).all()
    torch.testing.assert_close(x.sum(dim=-1), torch.full((3,), k, dtype=torch.float64), atol=1e-9, rtol=0)
    feasible = torch.full((10,), k / 10, dtype=torch.float64)
    torch.testing.assert_close(project_capped_simplex(feasible, k), feasible, atol=1e-9, rtol=0)


def test_decay_length_is_named_tau_steps_like_the_scene_key():
    assert cosine_temperature(750, 6.0, 1.2, tau_steps=1500) == pytest.approx(3.6)
