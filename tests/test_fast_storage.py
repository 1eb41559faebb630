"""The fast 3-D path's storage: the transmit tensor without padding, and the receive matrix and
transmit tensor held in float16 (``FastSettings(storage="float16")``).

Known answers: the block-wise product with a float16 tensor equals the product with the same
rounded tensor in float64 (to rounding of the sum), for real and complex operands and for column
counts that do not divide the block; its gradient passes ``gradcheck``; a float16 model's images
are within 1e-6 (relative squared error) of the exact path's and are restored bit for bit from
its state, which takes half the bytes of the float32 model's."""
import numpy as np
import pytest
import torch

from arraysel.errors import ParameterError
from arraysel.physics.volume import FastSettings, MatrixFastPSF, MatrixPSF
from arraysel.physics.volume import stored
from arraysel.physics.volume.stored import store, stored_product

from test_matrix_fast import _plane_errors, _setup, _weights

pytestmark = pytest.mark.usefixtures("one_thread")


@pytest.mark.parametrize("complex_", [False, True])
@pytest.mark.parametrize("block", [3, 2048])
def test_stored_product_equals_the_rounded_product(monkeypatch, complex_, block):
    monkeypatch.setattr(stored, "STORED_BLOCK", block)
    g = torch.Generator().manual_seed(1)
    cols = 11
    dense = torch.randn(7, cols, generator=g, dtype=torch.float64) * torch.logspace(-6, 3, cols, dtype=torch.float64)
    dense[:, 4] = 0   # an all-zero column: scale 1
    x = torch.randn(4, 7, generator=g, dtype=torch.float64)
    if complex_:
        dense = torch.complex(dense, torch.randn(7, cols, generator=g, dtype=torch.float64))
        x = torch.complex(x, torch.randn(4, 7, generator=g, dtype=torch.float64))
    S, scale = store(dense)
    assert S.dtype == torch.float16 and float(S.abs().max()) == 1.0 and scale.dtype == torch.float32
    assert S.shape == (7, 2 * cols if complex_ else cols) and scale.shape == (cols,)
    if complex_:   # one scale for both parts of a column
        restored = torch.view_as_complex(S.double().reshape(7, cols, 2).contiguous()) * scale.double()
    else:
        restored = S.double() * scale.double()
    # each entry within float16's rounding of its column's largest
    top = dense.abs().amax(0) if not complex_ else torch.view_as_real(dense).abs().amax((0, 2))
    assert bool(((restored - dense).abs() <= 2 ** -11 * top + 1e-300).all())
    ref = x @ restored
    got = stored_product(x, S, scale)
    assert got.shape == ref.shape and got.dtype == x.dtype
    assert torch.allclose(got, ref, rtol=1e-12, atol=1e-12)
    # float32 operands give float32 products (never the stored precision)
    x32 = x.to(torch.complex64 if complex_ else torch.float32)
    assert stored_product(x32, S, scale).dtype == x32.dtype
    # the gradient in x: the product is linear in x
    xg = x.clone().requires_grad_(True)
    assert torch.autograd.gradcheck(lambda a: stored_product(a, S, scale), (xg,), eps=1e-6, atol=1e-8)


def test_float_storage_is_the_plain_product():
    S = torch.randn(5, 6, dtype=torch.float64)
    x = torch.randn(2, 5, dtype=torch.float64)
    assert torch.equal(stored_product(x, S), x @ S)


def test_storage_key_is_checked():
    with pytest.raises(ParameterError, match="storage"):
        FastSettings(storage="bfloat16")


@pytest.fixture(scope="module")
def models():
    # diverging waves steered in x and y: transmits of different ranks, so the tensor is unpadded
    exact = MatrixPSF(_setup(nx=6, ny=5, scat=(1e-3, -0.5e-3, 20e-3)), dtype=torch.float64)
    full = MatrixFastPSF(exact, FastSettings(tol=1e-6, replicas=2), dtype=torch.float32)
    low = MatrixFastPSF(exact, FastSettings(tol=1e-6, replicas=2, storage="float16"), dtype=torch.float32)
    return exact, full, low


def test_transmit_tensor_is_unpadded(models):
    _, full, _ = models
    ranks = full.sizes["transmit_ranks"]
    assert len(set(ranks)) > 1, ranks
    st = full.state()
    assert st["Psi"].shape[0] == sum(ranks) < len(ranks) * max(ranks)
    # each element's coefficients are the transmit coefficients of its unit selection
    unit = torch.eye(full.n_elements)[[0, 7, full.n_elements - 1]]
    got = full.transmit_coefficients(unit)
    assert torch.allclose(got, full.element_coefficients()[[0, 7, full.n_elements - 1]])


def test_float16_storage_images_state_and_bytes(models):
    exact, full, low = models
    assert low.storage == "float16" and full.storage == "float32"
    assert low._B.dtype == torch.float16 and low._Psi.dtype == torch.float16
    assert low.check["max_relative_error"] <= low.settings.check_tol
    w = _weights(exact.n_elements)
    with torch.no_grad():
        ref = exact.planes(w)
        got = low.planes(w.float())
        err_low = _plane_errors(got, ref)
        err_full = _plane_errors(full.planes(w.float()), ref)
    assert err_low.max() <= 1e-6, err_low
    assert all(v.dtype == torch.complex64 and bool(torch.isfinite(torch.view_as_real(v)).all()) for v in got.values())
    # restored from its state: the same tensors, the same images
    st = low.state()
    assert st["B"].dtype == torch.float16 and st["Psi"].dtype == torch.float16
    back = MatrixFastPSF.from_state(exact.setup, st, low.settings, dtype=torch.float32)
    assert back.storage == "float16"
    with torch.no_grad():
        again = back.planes(w.float())
    for k in got:
        assert torch.equal(again[k], got[k])
    assert low.sizes["bytes"] < 0.55 * full.sizes["bytes"]
    assert err_full.max() <= 1e-5
    # a state whose transmit tensor does not match its ranks is refused
    bad = dict(st, ranks=st["ranks"] + 1)
    with pytest.raises(ValueError, match="do not fit"):
        MatrixFastPSF.from_state(exact.setup, bad, low.settings)


def test_float16_build_stores_what_storing_the_float32_model_would(models):
    # the float16 model is rounded a block of pixels at a time as it is built (never held whole in
    # float32): the same bits as storing the float32 model's tensors whole
    _, full, low = models
    B, B_scale = store(full._B)
    Psi, Psi_scale = store(full._Psi)
    assert torch.equal(low._B, B) and torch.equal(low._B_scale, B_scale)
    assert torch.equal(low._Psi, Psi) and torch.equal(low._Psi_scale, Psi_scale)


def test_float16_storage_gradient_and_moves(models):
    exact, full, low = models
    ne = exact.n_elements
    w = torch.zeros(2, ne)
    w[:, ::3] = 1
    w[1, 1] = 0.5
    grads = []
    for model in (full, low):
        wg = w.clone().requires_grad_(True)
        img = model.image(wg)
        (img.abs() ** 2).sum().backward()
        grads.append(wg.grad)
    assert float((grads[1] - grads[0]).norm() / grads[0].norm()) <= 1e-2
    # moves scored from a base selection's receive sums equal the same selections scored afresh
    base = w[0]
    moves = base.repeat(3, 1)
    moves[0, 0], moves[0, 1] = 0, 1
    moves[1, 3], moves[1, 2] = 0, 1
    with torch.no_grad():
        a = low.image(moves, base=base)
        b = low.image(moves)
    np.testing.assert_allclose(a.numpy(), b.numpy(), rtol=1e-4, atol=1e-5 * float(b.abs().max()))
