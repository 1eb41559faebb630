"""Separate transmit and receive apertures in the 1-D physics (PSFModel's ``receive=``): the
shared selection reproduced exactly, the image bilinear in (transmit, receive), and different
transmit and receive apodizations against PyMUST."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from arraysel.errors import SelectionError
from arraysel.objective.psf_objective import Objective
from arraysel.scenes.schema import load_scene
from scene_texts import TINY_SCENE


@pytest.fixture(scope="module")
def psf(tmp_path_factory):
    p = tmp_path_factory.mktemp("scenes") / "tiny.toml"
    p.write_text(TINY_SCENE.replace("n_tx = 1", "n_tx = 3"))
    return Objective(load_scene(str(p)), dtype=torch.float64).psf


def _w(rows):
    return torch.tensor(np.asarray(rows, dtype=np.float64))


TX = [[1, 1, 1, 1, 1, 1, 1, 1],            # full transmit, sparse receive
      [1, 0, 1, 0, 1, 0, 1, 0],            # two different sparse apertures
      [0.3, 1, 0.7, 0, 0.5, 1, 0, 0.9]]    # two different apodizations
RX = [[0, 1, 0, 1, 1, 0, 0, 1],
      [0, 1, 1, 0, 0, 1, 1, 0],
      [1, 0.2, 0, 0.8, 1, 0.4, 0.6, 0]]


def test_the_same_transmit_and_receive_is_todays_result_exactly(psf):
    w = _w(TX[2:] + RX[:1])
    assert torch.equal(psf.image(w, receive=w.clone()), psf.image(w))
    assert torch.equal(psf.kernels_exact(w, receive=w.clone()), psf.kernels_exact(w))
    assert torch.equal(psf.kernels(w, receive=w.clone()), psf.kernels_exact(w))


def test_the_image_is_bilinear_in_transmit_and_receive(psf):
    t, r1, r2 = _w(TX[2:]), _w(RX[:1]), _w(RX[2:])
    a = psf.image(t, receive=2.0 * r1 - 0.5 * r2)
    b = 2.0 * psf.image(t, receive=r1) - 0.5 * psf.image(t, receive=r2)
    torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-12 * float(a.abs().max()))
    c = psf.image(3.0 * t, receive=r1)
    torch.testing.assert_close(c, 3.0 * psf.image(t, receive=r1), rtol=1e-10, atol=1e-12 * float(c.abs().max()))


def test_transmit_and_receive_are_not_interchangeable(psf):
    """Tilted plane waves delay each element's transmission: the echo sent by j and received
    by e is not the one sent by e and received by j, so (t, r) and (r, t) differ."""
    t, r = _w(TX[1:2]), _w(RX[1:2])
    a, b = psf.image(t, receive=r), psf.image(r, receive=t)
    assert float((a - b).abs().max()) > 1e-3 * float(a.abs().max())


def test_bad_receive_weights_are_refused(psf):
    with pytest.raises(SelectionError, match="receive"):
        psf.image(_w(TX), receive=_w(RX[:2]))
    with pytest.raises(SelectionError, match="shape"):
        psf.kernels_exact(_w(TX), receive=torch.ones(3, 9, dtype=torch.float64))


def test_separate_transmit_and_receive_match_pymust(psf):
    pytest.importorskip("pymust")
    from pymust_pipeline import setup_kernels, si_mse

    refs = setup_kernels(psf.setup, np.asarray(TX, dtype=float), receive=np.asarray(RX, dtype=float))
    ours = psf.kernels(_w(TX), receive=_w(RX)).numpy()
    for i, ref in enumerate(refs):
        assert si_mse(ours[i], ref) <= 1e-5, i
    # and the shared aperture of the same transmit weights is another PSF (the test can fail)
    shared = setup_kernels(psf.setup, np.asarray(TX[1:2], dtype=float))[0]
    assert si_mse(ours[1], shared) > 1e-3


# --------------------------------------------------------------------------- matrix probes (3-D exact path)
@pytest.fixture(scope="module")
def psf3():
    from arraysel.physics.volume import MatrixPSF
    from test_matrix_physics import _psf_setup

    return MatrixPSF(_psf_setup(), dtype=torch.float64)


def _w3(n, seeds, k=16):
    out = np.zeros((len(seeds), n))
    for i, s in enumerate(seeds):
        out[i, np.random.default_rng(s).choice(n, k, replace=False)] = 1
    return torch.tensor(out)


def test_3d_the_same_transmit_and_receive_is_todays_result_exactly(psf3):
    w = _w3(psf3.n_elements, [0, 1])
    assert torch.equal(psf3.image(w, receive=w.clone()), psf3.image(w))
    full = torch.ones(1, psf3.n_elements, dtype=torch.float64)
    assert torch.equal(psf3.image(full, receive=full.clone()), psf3.image(full))


def test_3d_the_image_is_bilinear_and_transmit_receive_differ(psf3):
    n = psf3.n_elements
    t, r1, r2 = _w3(n, [2]), _w3(n, [3]), _w3(n, [4])
    a = psf3.image(t, receive=2.0 * r1 - 0.5 * r2)
    b = 2.0 * psf3.image(t, receive=r1) - 0.5 * psf3.image(t, receive=r2)
    torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-12 * float(a.abs().max()))
    full = torch.ones(1, n, dtype=torch.float64)
    sparse_rx = psf3.image(full, receive=r1)                 # full transmit, sparse receive
    assert float((sparse_rx - psf3.image(r1)).abs().max()) > 1e-3 * float(sparse_rx.abs().max())
    with pytest.raises(SelectionError, match="receive"):
        psf3.image(torch.cat([t, t]), receive=r1)


def test_3d_separate_transmit_and_receive_match_pymust(psf3):
    pytest.importorskip("pymust")
    from pymust_pipeline3 import PyMUSTScene3, si_mse

    s = psf3.setup
    oracle = PyMUSTScene3(s.probe, s.acq, s.delays, s.scatterer, {k: v.numpy() for k, v in psf3.coords.items()})
    n = psf3.n_elements
    tx = torch.cat([torch.ones(1, n, dtype=torch.float64), _w3(n, [5])])
    rx = torch.cat([_w3(n, [6]), 0.5 + 0.5 * _w3(n, [7])])   # sparse receive; an apodized one
    ours = psf3.planes(tx, receive=rx)
    for i in range(2):
        ref = oracle.planes(tx[i].numpy(), receive=rx[i].numpy())
        for plane, img in ref.items():
            assert si_mse(ours[plane][i].numpy(), img) <= 1e-4, (i, plane)


# --------------------------------------------------------------------------- per-transmit apertures (3-D)
def _events(psf, seeds):
    """(len(seeds), n_tx, Ne): a different random transmit aperture for every transmit event."""
    return torch.stack([_w3(psf.n_elements, [s + 10 * n for n in range(len(psf.transmits))]) for s in seeds])


def test_3d_per_transmit_apertures_are_the_sum_of_their_events(psf3):
    n_tx, n = len(psf3.transmits), psf3.n_elements
    assert n_tx >= 2
    ev, rx = _events(psf3, [1, 2]), _w3(n, [8, 9])
    got = psf3.image(ev, receive=rx)
    one_each = sum(psf3.image(torch.where(torch.arange(n_tx)[None, :, None] == t, ev, 0.0), receive=rx)
                   for t in range(n_tx))              # an event with no transmit element adds nothing
    torch.testing.assert_close(got, one_each, rtol=1e-10, atol=1e-12 * float(got.abs().max()))
    same = torch.stack([rx[0]] * n_tx)[None]         # the same aperture for every event: today's image
    torch.testing.assert_close(psf3.image(same, receive=rx[:1]), psf3.image(rx[:1]), rtol=1e-12, atol=0.0)
    assert float((got[0] - psf3.image(ev[0, :1], receive=rx[:1])[0]).abs().max()) > 1e-3 * float(got.abs().max())
    with pytest.raises(SelectionError, match="need the receive weights"):
        psf3.image(ev)
    with pytest.raises(SelectionError, match=r"per-transmit weights must have shape \(B, %d, %d\)" % (n_tx, n)):
        psf3.image(ev[:, :1].expand(2, n_tx + 1, n), receive=rx)


def test_3d_per_transmit_fast_path_matches_the_exact_path(psf3):
    from arraysel.physics.volume.fast import MatrixFastPSF, fast_relative_error

    fast = MatrixFastPSF(psf3, dtype=torch.float64)
    ev, rx = _events(psf3, [3, 4]), _w3(psf3.n_elements, [5, 6])
    err = fast_relative_error(fast.planes(ev, receive=rx), psf3.planes(ev, receive=rx))
    assert float(err.max()) <= 1e-4
    g = ev.clone().requires_grad_(True)
    fast.image(g, receive=rx).abs().sum().backward()
    assert g.grad.shape == ev.shape and bool(torch.isfinite(g.grad).all()) and float(g.grad.abs().sum()) > 0


def test_3d_per_transmit_apertures_match_pymust(psf3):
    pytest.importorskip("pymust")
    from pymust_pipeline3 import PyMUSTScene3, si_mse

    s = psf3.setup
    oracle = PyMUSTScene3(s.probe, s.acq, s.delays, s.scatterer, {k: v.numpy() for k, v in psf3.coords.items()})
    ev, rx = _events(psf3, [7]), _w3(psf3.n_elements, [11])
    ours = psf3.planes(ev, receive=rx)
    ref = oracle.planes(ev[0].numpy(), receive=rx[0].numpy())
    for plane, img in ref.items():
        assert si_mse(ours[plane][0].numpy(), img) <= 1e-4, plane
