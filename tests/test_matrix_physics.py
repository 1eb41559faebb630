"""Matrix probes and the 3-D physics (arraysel.physics.volume) against PyMUST 0.1.9's 3-D
functions (txdelay3, pfield3, simus3, rf2iq, dasmtx3), and their gradients.

Tolerances: delays 1e-15 s (same formulas); RF 1e-4 relative L2 (PyMUST computes in float32:
measured 1.3e-5); DAS 1e-9 relative (same plan); every plane of the exact 3-D PSF SI-MSE <= 1e-4
against the PyMUST pipeline (measured 1e-13 to 1e-11 in float64)."""
import math

import numpy as np
import pytest
import torch

from arraysel.errors import ParameterError, SelectionError
from arraysel.physics.beamform import das_apply
from arraysel.physics.probes import Acquisition, MatrixProbe, get_probe, list_probes
from arraysel.physics.volume import (PLANES, MatrixPSF, MatrixPSFSetup, das_plan3, diverging_delays3,
                                     element_responses3, focused_delays3, peak_normalise, plane_wave_delays3,
                                     simulate_rf3, tilt_grid, virtual_sources3)

pymust = pytest.importorskip("pymust")
from pymust_pipeline3 import PyMUSTScene3, must_param, si_mse  # noqa: E402

pytestmark = pytest.mark.usefixtures("one_thread")


def _small(nx=8, ny=8, **kw):
    return get_probe("MATRIX-32x32", nx=nx, ny=ny, **kw)


# --------------------------------------------------------------------------- probes
def test_catalogue_matrix_probe():
    p = get_probe("matrix-32x32")
    assert isinstance(p, MatrixProbe) and p.name == "MATRIX-32x32" and "MATRIX-32x32" in list_probes()
    assert (p.nx, p.ny, p.n_elements, p.grid_shape) == (32, 32, 1024, (32, 32))
    assert (p.pitch_x, p.pitch_y, p.width, p.height, p.fc, p.bandwidth, p.baffle) == \
        (300e-6, 300e-6, 250e-6, 250e-6, 3e6, 70.0, "soft")
    assert p.is_matrix and not get_probe("P4-2v").is_matrix
    assert p.aperture == pytest.approx((31 * 300e-6, 31 * 300e-6))


def test_element_index_is_iy_times_nx_plus_ix():
    p = _small(nx=5, ny=3, pitch_y=400e-6)
    pos = p.element_positions()
    assert pos.shape == (15, 3) and pos.dtype == np.float64 and not pos[:, 2].any()
    for iy in range(3):
        for ix in range(5):
            e = int(p.element_index(ix, iy))
            assert e == iy * 5 + ix
            assert pos[e, 0] == pytest.approx((ix - 2) * 300e-6) and pos[e, 1] == pytest.approx((iy - 1) * 400e-6)
    ix, iy = p.element_grid(np.arange(15))
    np.testing.assert_array_equal(iy * 5 + ix, np.arange(15))
    np.testing.assert_allclose(pos[:, 0].reshape(p.grid_shape)[0], (np.arange(5) - 2) * 300e-6)
    assert p.mask([0, 14]).tolist() == [1.0] + [0.0] * 13 + [1.0]


@pytest.mark.parametrize("kw, key", [(dict(width=301e-6), "width"), (dict(height=0.0), "height"),
                                     (dict(nx=0), "nx"), (dict(ny=2.5), "ny"), (dict(pitch_x=-1e-3), "pitch_x"),
                                     (dict(fc=math.inf), "fc"), (dict(bandwidth=250), "bandwidth"),
                                     (dict(radius=1.0), "radius"), (dict(n_elements=64), "n_elements")])
def test_bad_geometry_names_the_key(kw, key):
    with pytest.raises(ParameterError, match=key):
        _small(**kw)


def test_bad_indices_name_the_key():
    p = _small(nx=4, ny=4)
    with pytest.raises(ParameterError, match=r"elements.*\[0, 15\]"):
        p.mask([3, 16])
    with pytest.raises(ParameterError, match="k = 17"):
        p.mask(list(range(16)) + [0])
    with pytest.raises(ParameterError, match="repeat"):
        p.mask([1, 1])
    with pytest.raises(ParameterError, match="ix"):
        p.element_index(4, 0)


# --------------------------------------------------------------------------- delays
def _param(probe, acq=None):
    param = must_param(probe, acq or Acquisition.for_probe(probe))
    param.radius, param.pitch = math.inf, probe.pitch_x  # PyMUST 0.1.9's txdelay3 reads these
    return param


def test_plane_wave_delays_match_txdelay3():
    p = _small(nx=6, ny=5)
    param = _param(p)
    for tx, ty in [(0.0, 0.0), (0.1, 0.0), (0.0, -0.2), (0.15, 0.2)]:
        ref = np.asarray(pymust.txdelay3(param, tx, ty)).ravel()
        ours = plane_wave_delays3(p, ty, -tx, 1540.0)[0]  # MUST's tilts are about the axes
        np.testing.assert_allclose(ours, ref, rtol=0, atol=1e-15)
    d = plane_wave_delays3(p, [0.1, -0.1], [0.0, 0.2])
    assert d.shape == (2, 30) and (d.min(1) == 0).all()
    assert (np.diff(d[0].reshape(5, 6), axis=1) > 0).all()  # +x tilt: +x fires later


def test_focused_and_diverging_delays_match_txdelay3():
    p = _small(nx=5, ny=7)
    param = _param(p)
    for x0, y0, z0 in [(1e-3, -2e-3, 20e-3), (0.0, 0.0, -3e-3), (-2e-3, 1e-3, -1e-3)]:
        ref = np.asarray(pymust.txdelay3(np.array([x0]), np.array([y0]), np.array([z0]), param)).ravel()
        np.testing.assert_allclose(focused_delays3(p, x0, y0, z0)[0], ref, rtol=0, atol=1e-15)
    src = virtual_sources3([0.0, 0.2], [0.1, 0.0], 5e-3)
    assert np.linalg.norm(src, axis=1) == pytest.approx([5e-3, 5e-3])
    assert src[1, 0] < 0 and src[1, 1] == 0 and (src[:, 2] < 0).all()
    d = diverging_delays3(p, [0.0, 0.2], [0.1, 0.0], 5e-3)
    np.testing.assert_allclose(d, focused_delays3(p, src[:, 0], src[:, 1], src[:, 2]), atol=0)
    ax, ay = tilt_grid(3, 3, 10, 5)
    assert len(ax) == 9 and ax[:3] == pytest.approx(np.deg2rad([-10, 0, 10])) and ay[0] == pytest.approx(-np.deg2rad(5))


def test_delay_errors_name_the_key():
    p = _small(nx=3, ny=3)
    with pytest.raises(ParameterError, match="tilts_x"):
        plane_wave_delays3(p, 1.0, 1.0)
    with pytest.raises(ParameterError, match="z0"):
        focused_delays3(p, 0, 0, 0)
    with pytest.raises(ParameterError, match="distance"):
        diverging_delays3(p, 0, 0, -1e-3)
    with pytest.raises(ParameterError, match="MatrixProbe"):
        plane_wave_delays3(get_probe("P4-2v"), 0, 0)


# --------------------------------------------------------------------------- field and RF
def test_element_responses_match_pfield3_spectra():
    """One element, split 3 x 2 (800 x 500 um at 3 MHz), attenuation: pfield3's spectrum at
    points all around it (relative error <= 1e-4: PyMUST computes in float32)."""
    p = get_probe("MATRIX-32x32", nx=3, ny=2, pitch_x=900e-6, pitch_y=720e-6, width=800e-6, height=500e-6)
    acq = Acquisition.for_probe(p, attenuation=0.5)
    param = _param(p, acq)
    e = 4
    apod = np.zeros(p.n_elements)
    apod[e] = 1
    param.TXapodization = apod
    rng = np.random.default_rng(0)
    pts = np.stack([rng.uniform(-8e-3, 8e-3, 30), rng.uniform(-8e-3, 8e-3, 30), rng.uniform(0.2e-3, 12e-3, 30)], 1)
    cols = [np.ascontiguousarray(pts[:, i]).reshape(-1, 1, 1) for i in range(3)]
    _, spect, idx = pymust.pfield3(*cols, np.zeros((1, p.n_elements)), param)
    spect = spect.reshape(30, -1)
    f = torch.as_tensor(np.linspace(0, 2 * p.fc, idx.size)[idx])
    from arraysel.physics.simus import probe_response, pulse_spectrum
    ph = (pulse_spectrum(f, p.fc) * probe_response(f, p.fc, p.bandwidth)).numpy()
    ours = element_responses3(torch.as_tensor(pts), f, p, acq.c, acq.attenuation)[:, e].numpy() * ph
    err = np.abs(ours - spect).max(1) / np.abs(spect).max(1)
    assert err.max() <= 1e-4, err.max()


@pytest.mark.parametrize("kw, att", [(dict(nx=8, ny=6), 0.0), (dict(nx=4, ny=3, width=290e-6, baffle="rigid"), 0.5),
                                     (dict(nx=3, ny=3, pitch_x=900e-6, width=800e-6, baffle=1.5), 0.3)])
def test_rf_matches_simus3(kw, att):
    p = _small(**kw)
    acq = Acquisition.for_probe(p, attenuation=att)
    param = _param(p, acq)
    d = diverging_delays3(p, 0.1, -0.05, 3e-3)[0]
    pts = np.array([[1e-3, -2e-3, 20e-3], [-3e-3, 1e-3, 15e-3]])
    m = (np.random.default_rng(1).random(p.n_elements) < 0.5).astype(float)
    m[0] = 1
    param.TXapodization = m.copy()
    RF, _ = pymust.simus3(pts[:, 0].copy(), pts[:, 1].copy(), pts[:, 2].copy(), np.array([1.0, 0.7]),
                          d.reshape(1, -1), param)
    RF = RF * m[None]
    rf, _ = simulate_rf3(pts, [1.0, 0.7], d, p, acq, tx_apod=m, rx_apod=m)
    assert rf.shape == RF.shape
    assert np.linalg.norm(rf.numpy() - RF) / np.linalg.norm(RF) <= 1e-4


def test_das_plan_matches_dasmtx3():
    p = _small(nx=6, ny=5)
    acq = Acquisition.for_probe(p)
    param = _param(p, acq)
    rng = np.random.default_rng(3)
    pts = np.stack([rng.uniform(-4e-3, 4e-3, 50), rng.uniform(-4e-3, 4e-3, 50), rng.uniform(2e-3, 12e-3, 50)], 1)
    nt = 300
    iq = rng.standard_normal((nt, p.n_elements)) + 1j * rng.standard_normal((nt, p.n_elements))
    for d in (plane_wave_delays3(p, 0.1, -0.2)[0], diverging_delays3(p, 0.0, 0.2, 2e-3)[0]):
        cols = [np.ascontiguousarray(pts[:, i]).reshape(-1, 1, 1) for i in range(3)]
        M = pymust.dasmtx3(1j * np.array([nt, p.n_elements]), *cols, d.reshape(1, -1), param).tocsr()
        ref = M @ iq.flatten(order="F")
        plan = das_plan3(torch.as_tensor(pts), d, p, acq.fs, acq.c, nt, p.fc)
        ours = das_apply(torch.as_tensor(iq.T.copy()), plan.i0, plan.w, plan.rot).numpy()
        assert np.abs(ours - ref).max() <= 1e-9 * np.abs(ref).max()


# --------------------------------------------------------------------------- the exact 3-D PSF
def _psf_setup(nx=8, ny=8, tilts=(2, 2), pixel_wl=0.5, halves=(3e-3, 3e-3, 2e-3), scat=(0.5e-3, -0.3e-3, 15e-3)):
    p = _small(nx=nx, ny=ny)
    acq = Acquisition.for_probe(p)
    ax, ay = tilt_grid(*tilts, 10, 10)
    d = diverging_delays3(p, ax, ay, 5e-3, acq)
    return MatrixPSFSetup(p, acq, d, scat, half_x=halves[0], half_y=halves[1], half_z=halves[2],
                          pixel=pixel_wl * acq.c / p.fc)


def _masks(p, k, seed=0):
    full = np.ones(p.n_elements)
    uni = np.zeros((p.ny, p.nx))
    uni[::2, ::2] = 1  # thinned in both directions
    rng = np.random.default_rng(seed)
    rnd = p.mask(rng.choice(p.n_elements, k, replace=False))
    return {"full": full, "uniform": uni.ravel(), "random": rnd}


@pytest.fixture(scope="module")
def small_psf():
    setup = _psf_setup()
    masks = _masks(setup.probe, 16)
    oracle = PyMUSTScene3(setup.probe, setup.acq, setup.delays, setup.scatterer,
                          {k: v.numpy() for k, v in MatrixPSF(setup, torch.float64).coords.items()})
    return setup, masks, {name: oracle.planes(m) for name, m in masks.items()}


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_exact_planes_match_pymust(small_psf, dtype):
    setup, masks, ref = small_psf
    model = MatrixPSF(setup, dtype=dtype)
    planes = model.planes(torch.tensor(np.stack(list(masks.values()))))
    assert set(planes) == set(PLANES)
    for i, name in enumerate(masks):
        for plane in PLANES:
            got = planes[plane][i].to(torch.complex128).numpy()
            assert got.shape == ref[name][plane].shape
            assert si_mse(got, ref[name][plane]) <= 1e-4, (name, plane)


def test_planes_geometry_and_peak(small_psf):
    setup, masks, _ = small_psf
    model = MatrixPSF(setup, dtype=torch.float64)
    xs, ys, zs = setup.scatterer
    for name, c in model.coords.items():
        h, w = c.shape[:2]
        assert c.shape[-1] == 3 and c.dtype == torch.float64
        np.testing.assert_allclose(c[h // 2, w // 2].numpy(), [xs, ys, zs], atol=1e-15)
    n = [round(2 * h / setup.pixel) for h in (setup.half_x, setup.half_y, setup.half_z)]
    assert n == [23, 23, 16] and model.coords["xy"].shape[:2] == (23, 23) and model.coords["xz"].shape[:2] == (16, 23)
    assert torch.all(model.coords["xy"][..., 2] == zs) and torch.all(model.coords["xz"][..., 1] == ys)
    assert torch.all(model.coords["yz"][..., 0] == xs)
    assert torch.allclose(model.coords["xy"][0, 1, :2] - model.coords["xy"][0, 0, :2],
                          torch.tensor([setup.pixel, 0.0], dtype=torch.float64))
    full = peak_normalise(model.planes(torch.ones(1, 64, dtype=torch.float64)))
    peak = max(float(v.abs().max()) for v in full.values())
    assert peak == pytest.approx(1.0)
    # the full array's peak lies within a pixel of the scatterer on every plane
    for v in full.values():
        h, w = v.shape[1:]
        i = int(v[0].abs().argmax())
        assert abs(i // w - h // 2) <= 1 and abs(i % w - w // 2) <= 1


@pytest.mark.parametrize("compiled", [False, True])
def test_batch_equals_single_and_zero_weights_are_skipped_exactly(monkeypatch, compiled):
    import arraysel.physics.volume.psf as vpsf

    monkeypatch.setattr(vpsf, "COMPILED_MIN_ENTRIES", 0 if compiled else 1 << 60)
    setup = _psf_setup(nx=5, ny=4, tilts=(2, 1), halves=(1e-3, 1e-3, 1e-3), pixel_wl=1.0)
    model = MatrixPSF(setup, dtype=torch.float64, pixel_chunk=7)
    w = torch.tensor(np.random.default_rng(2).uniform(0, 1, (3, 20)))
    w[0, :5] = 0
    batch = model.image(w)
    for i in range(3):
        one = model.image(w[i:i + 1])  # zero columns are dropped here, kept in the batch
        assert torch.allclose(batch[i], one[0], rtol=1e-12, atol=1e-12 * float(one.abs().max()))
    with torch.enable_grad():
        wg = w[:1].clone().requires_grad_(True)
        assert torch.allclose(model.image(wg)[0].detach(), batch[0], rtol=1e-12, atol=1e-12 * float(batch.abs().max()))


def test_compiled_and_torch_paths_agree(monkeypatch, small_psf):
    import arraysel.physics.volume.psf as vpsf

    setup, masks, _ = small_psf
    w = torch.tensor(np.random.default_rng(4).uniform(0, 1, (2, 64)))
    for dtype, tol in ((torch.float64, 1e-12), (torch.float32, 1e-5)):
        model = MatrixPSF(setup, dtype=dtype)
        monkeypatch.setattr(vpsf, "COMPILED_MIN_ENTRIES", 0)
        a = model.image(w)
        monkeypatch.setattr(vpsf, "COMPILED_MIN_ENTRIES", 1 << 60)
        b = model.image(w)
        assert float((a - b).abs().max() / b.abs().max()) <= tol


@pytest.mark.parametrize("compiled", [False, True])
def test_gradcheck_soft_weights(monkeypatch, compiled):
    import arraysel.physics.volume.psf as vpsf

    monkeypatch.setattr(vpsf, "COMPILED_MIN_ENTRIES", 0 if compiled else 1 << 60)
    setup = _psf_setup(nx=3, ny=2, tilts=(2, 1), halves=(0.5e-3, 0.5e-3, 0.5e-3), pixel_wl=1.0)
    model = MatrixPSF(setup, dtype=torch.float64, pixel_chunk=5)
    w0 = torch.linspace(0.3, 0.9, 6, dtype=torch.float64)[None].requires_grad_(True)

    def f(w):
        return torch.cat([torch.view_as_real(v).flatten() for v in model.planes(w).values()])

    assert torch.autograd.gradcheck(f, (w0,), eps=1e-6, atol=1e-6, rtol=1e-4)


def test_psf_errors():
    setup = _psf_setup(nx=3, ny=3, tilts=(1, 1), halves=(0.5e-3, 0.5e-3, 0.5e-3), pixel_wl=1.0)
    with pytest.raises(ParameterError, match="half_z"):
        MatrixPSFSetup(setup.probe, setup.acq, setup.delays, (0, 0, 1e-3), 1e-3, 1e-3, 2e-3, setup.pixel)
    with pytest.raises(ParameterError, match="delays"):
        MatrixPSFSetup(setup.probe, setup.acq, setup.delays[:, :4], setup.scatterer, 1e-3, 1e-3, 1e-3, setup.pixel)
    bad = setup.delays.copy()
    bad[0, 2] = np.nan
    with pytest.raises(ParameterError, match="finite"):
        MatrixPSFSetup(setup.probe, setup.acq, bad, setup.scatterer, 1e-3, 1e-3, 1e-3, setup.pixel)
    with pytest.raises(ParameterError, match="planes"):
        MatrixPSFSetup(setup.probe, setup.acq, setup.delays, setup.scatterer, 1e-3, 1e-3, 1e-3, setup.pixel,
                       planes=("xy", "zz"))
    with pytest.raises(ParameterError, match="MatrixProbe"):
        MatrixPSFSetup(get_probe("P4-2v"), setup.acq, setup.delays, setup.scatterer, 1e-3, 1e-3, 1e-3, setup.pixel)
    model = MatrixPSF(setup, dtype=torch.float64)
    with pytest.raises(SelectionError, match=r"\(B, 9\)"):
        model.planes(torch.ones(1, 10))
    with pytest.raises(SelectionError, match="empty"):
        model.planes(torch.zeros(1, 9))
    only = MatrixPSF(MatrixPSFSetup(setup.probe, setup.acq, setup.delays, setup.scatterer, 1e-3, 1e-3, 1e-3,
                                    setup.pixel, planes=("xz",)), dtype=torch.float64)
    assert set(only.planes(torch.ones(1, 9))) == {"xz"}


# --------------------------------------------------------------------------- the 1024-element probe
@pytest.mark.slow
def test_matrix_1024_planes_match_pymust():
    """MATRIX-32x32, 9 diverging waves, planes of 32 x 32 (C-plane) and 16 x 32 (xz, yz) pixels
    of lambda / 2 at 30 mm: full, uniform (every second element in x and y: 256) and random
    256-element masks, float32 and float64; SI-MSE <= 1e-4 on every plane."""
    p = get_probe("MATRIX-32x32")
    acq = Acquisition.for_probe(p)
    lam = acq.c / p.fc
    ax, ay = tilt_grid(3, 3, 10, 10)
    setup = MatrixPSFSetup(p, acq, diverging_delays3(p, ax, ay, 10e-3, acq), (0.0, 0.0, 30e-3),
                           half_x=8 * lam, half_y=8 * lam, half_z=4 * lam, pixel=lam / 2)
    masks = _masks(p, 256, seed=5)
    m64 = MatrixPSF(setup, dtype=torch.float64)
    oracle = PyMUSTScene3(p, acq, setup.delays, setup.scatterer, {k: v.numpy() for k, v in m64.coords.items()})
    refs = {name: oracle.planes(m) for name, m in masks.items()}
    w = torch.tensor(np.stack(list(masks.values())))
    for model in (m64, MatrixPSF(setup, dtype=torch.float32)):
        planes = model.planes(w)
        for i, name in enumerate(masks):
            for plane in PLANES:
                got = planes[plane][i].to(torch.complex128).numpy()
                assert si_mse(got, refs[name][plane]) <= 1e-4, (model.dtype, name, plane)


# --------------------------------------------------------------------------- scenes
def test_matrix_probe_in_a_scene_file(tmp_path):
    from arraysel.scenes.schema import load_scene

    f = tmp_path / "m.toml"
    f.write_text('base = "paper"\n[probe]\nname = "MATRIX-32x32"\nnx = 8\nny = 4\npitch_y = 4e-4\n'
                 'fc = 3e6\n[selection]\nk = 16\n', encoding="utf-8")
    scene = load_scene(str(f))
    p = scene.matrix_probe()
    assert isinstance(p, MatrixProbe) and (p.nx, p.ny, p.pitch_y, p.n_elements) == (8, 4, 4e-4, 32)
    with pytest.raises(ParameterError, match="probe.name"):
        scene.psf_setup()  # the 2-D (xz) scene of a 1-D probe
    with pytest.raises(ParameterError, match="probe.name = 'P4-2v'"):
        load_scene("paper").matrix_probe()
    with pytest.raises(ParameterError, match="probe.radius"):
        load_scene(str(f), {"probe": {"radius": 0.05}})
    with pytest.raises(ParameterError, match="probe.nx"):
        load_scene("paper", {"probe": {"nx": 8}})
    with pytest.raises(ParameterError, match="selection.k"):
        load_scene(str(f), {"selection": {"k": 33}})
    with pytest.raises(ParameterError, match="height"):
        load_scene(str(f), {"probe": {"height": 5e-4}})
