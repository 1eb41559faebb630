"""The fast 3-D PSF (arraysel.physics.volume.fast) against the exact path and PyMUST's 3-D pipeline.

Tolerances: against the exact path, the relative squared error of every plane
``||fast - exact||^2 / ||exact||^2`` <= 1e-6 with ``tol = 1e-6, replicas = 2`` (measured <= 4.3e-7 on
these small probes of lambda / 2 pixels, float32 and float64; with the defaults, replicas = 0, the
interpolation harmonics left out cost 1e-6 to 7e-6 there and 1.7e-5 for a single element, hence the
looser 1e-4 of the defaults' test); against the PyMUST pipeline SI-MSE <= 1e-4 on every plane (as
the exact path's test); gradients: ``gradcheck`` in float64 and the exact path's gradient to 1e-3
relative."""
import math

import numpy as np
import pytest
import torch

from arraysel.errors import NumericalError, ParameterError, SelectionError
from arraysel.physics.probes import Acquisition, get_probe
from arraysel.physics.simus import SimOptions
from arraysel.physics.volume import (PLANES, FastPathUnavailable, FastSettings, MatrixFastPSF, MatrixPSF,
                                     MatrixPSFSetup, diverging_delays3, fast_relative_error, focused_delays3,
                                     peak_normalise, plane_wave_delays3, tilt_grid)

pytestmark = pytest.mark.usefixtures("one_thread")

ACCURATE = FastSettings(tol=1e-6, replicas=2)


def _setup(nx=6, ny=6, scat=(0.5e-3, -0.3e-3, 15e-3), delays="diverging", halves=(2e-3, 2e-3, 1.5e-3),
           pixel_wl=0.5, attenuation=0.0, options=None, planes=PLANES):
    p = get_probe("MATRIX-32x32", nx=nx, ny=ny)
    acq = Acquisition.for_probe(p, attenuation=attenuation)
    ax, ay = tilt_grid(2, 2, 10, 10)
    if delays == "diverging":
        d = diverging_delays3(p, ax, ay, 5e-3, acq)
    elif delays == "plane":
        d = plane_wave_delays3(p, [0.0, 0.15], [0.1, -0.05], acq)
    else:  # focused at the scatterer and beside it
        xs, ys, zs = scat
        d = focused_delays3(p, [xs, xs + 1e-3], [ys, ys], [zs, zs], acq)
    return MatrixPSFSetup(p, acq, d, scat, half_x=halves[0], half_y=halves[1], half_z=halves[2],
                          pixel=pixel_wl * acq.c / p.fc, planes=planes,
                          options=options if options is not None else SimOptions())


def _weights(ne, seed=0):
    """full, two random subsets (a quarter, a half), a single element (k = 1), soft weights in (0, 1)."""
    g = np.random.default_rng(seed)
    rows = [np.ones(ne)]
    for k in (max(2, ne // 4), ne // 2):
        m = np.zeros(ne)
        m[g.choice(ne, k, replace=False)] = 1
        rows.append(m)
    one = np.zeros(ne)
    one[ne // 2 + 1] = 1
    rows.append(one)
    rows.append(g.uniform(0.05, 0.95, ne))
    return torch.tensor(np.stack(rows))


def _plane_errors(fast: dict, exact: dict) -> np.ndarray:
    """(planes, B) relative squared errors."""
    return np.stack([(((fast[k].to(torch.complex128) - exact[k]).abs() ** 2).flatten(1).sum(1)
                      / (exact[k].abs() ** 2).flatten(1).sum(1)).numpy() for k in exact])


CASES = {
    "on-axis shallow, diverging": dict(scat=(0.0, 0.0, 6e-3), halves=(1.5e-3, 1.5e-3, 1e-3)),
    "off-axis deep, plane waves": dict(scat=(2e-3, -1.5e-3, 35e-3), delays="plane"),
    "focused, attenuation 0.5": dict(delays="focused", attenuation=0.5),
    "full-frequency directivity, 2 sub-elements": dict(
        nx=4, ny=5, options=SimOptions(element_splitting=2, full_frequency_directivity=True)),
    "one plane only (xz)": dict(nx=5, ny=4, planes=("xz",)),
}


@pytest.fixture(scope="module")
def exact_models():
    out = {}
    for name, kw in CASES.items():
        out[name] = MatrixPSF(_setup(**kw), dtype=torch.float64)
    return out


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("case", list(CASES))
def test_fast_planes_match_exact(exact_models, case, dtype):
    exact = exact_models[case]
    fast = MatrixFastPSF(exact, ACCURATE, dtype=dtype)
    assert fast.check["max_relative_error"] <= ACCURATE.check_tol and fast.check["masks"] == 3
    w = _weights(exact.n_elements)
    with torch.no_grad():
        ref = exact.planes(w)
        got = fast.planes(w.to(dtype))
    assert set(got) == set(ref) == set(exact.setup.planes)
    for k in ref:
        assert got[k].shape == ref[k].shape and got[k].dtype == fast.cdtype
        assert bool(torch.isfinite(torch.view_as_real(got[k])).all())
    err = _plane_errors(got, ref)
    assert err.max() <= 1e-6, (case, err)
    # one number per selection: the worst plane (what the build's check records)
    np.testing.assert_allclose(fast_relative_error({k: v.to(torch.complex128) for k, v in got.items()}, ref).numpy(),
                               err.max(0), rtol=1e-9)
    s = fast.sizes
    assert s["pixels"] == sum(h * w for h, w in (v.shape[:2] for v in exact.coords.values()))
    assert sum(s["pixels_by_nodes"].values()) == s["pixels"] and max(s["pixels_by_nodes"]) == s["nodes"]
    assert s["harmonics"] == 5 and s["nodes"] >= 4 and s["bytes"] > 0 and len(s["transmit_ranks"]) == exact.setup.n_tx


def test_default_settings_meet_their_check_and_batches_equal_singles(exact_models):
    exact = exact_models["focused, attenuation 0.5"]
    fast = MatrixFastPSF(exact, dtype=torch.float64)  # replicas = 0
    assert fast.sizes["harmonics"] == 1 and fast.check["max_relative_error"] <= FastSettings().check_tol
    w = _weights(exact.n_elements, seed=3)
    with torch.no_grad():
        batch = fast.image(w)
        for i in range(w.shape[0]):
            one = fast.image(w[i])  # a 1-D selection is a batch of one
            assert torch.allclose(batch[i], one[0], rtol=1e-12, atol=1e-12 * float(one.abs().max()))
        assert _plane_errors(fast.planes(w), exact.planes(w)).max() <= 1e-4


# --------------------------------------------------------------------------- against PyMUST
def test_fast_planes_match_pymust():
    pytest.importorskip("pymust")
    from pymust_pipeline3 import PyMUSTScene3, si_mse

    setup = _setup(nx=6, ny=6)
    exact = MatrixPSF(setup, dtype=torch.float64)
    p = setup.probe
    uni = np.zeros((p.ny, p.nx))
    uni[::2, ::2] = 1
    masks = {"full": np.ones(p.n_elements), "uniform": uni.ravel(),
             "random": p.mask(np.random.default_rng(7).choice(p.n_elements, 9, replace=False))}
    oracle = PyMUSTScene3(p, setup.acq, setup.delays, setup.scatterer, {k: v.numpy() for k, v in exact.coords.items()})
    refs = {name: oracle.planes(m) for name, m in masks.items()}
    w = torch.tensor(np.stack(list(masks.values())))
    for dtype in (torch.float64, torch.float32):
        with torch.no_grad():
            planes = MatrixFastPSF(exact, ACCURATE, dtype=dtype).planes(w.to(dtype))
        for i, name in enumerate(masks):
            for plane in PLANES:
                got = planes[plane][i].to(torch.complex128).numpy()
                assert si_mse(got, refs[name][plane]) <= 1e-4, (dtype, name, plane)


@pytest.mark.slow
def test_fast_matrix_1024_planes_match_pymust():
    """The matrix-1024 scene's geometry (MATRIX-32x32, 9 diverging waves 10 mm behind, scatterer at
    30 mm, planes of +-8 lambda (x, y) and +-4 lambda (z), pixel lambda / 3): full, uniform (every
    second element in x and y), random 256 and Fermat-spiral 256 masks; SI-MSE <= 1e-4 on every
    plane, float32, default settings (replicas = 0)."""
    pytest.importorskip("pymust")
    from pymust_pipeline3 import PyMUSTScene3, si_mse

    from arraysel.selectors.layouts import fermat_spiral_layout

    p = get_probe("MATRIX-32x32")
    acq = Acquisition.for_probe(p)
    lam = acq.c / p.fc
    ax, ay = tilt_grid(3, 3, 10, 10)
    setup = MatrixPSFSetup(p, acq, diverging_delays3(p, ax, ay, 10e-3, acq), (0.0, 0.0, 30e-3),
                           half_x=8 * lam, half_y=8 * lam, half_z=4 * lam, pixel=lam / 3)
    exact = MatrixPSF(setup, dtype=torch.float32)
    fast = MatrixFastPSF(exact, dtype=torch.float32)
    uni = np.zeros((32, 32))
    uni[::2, ::2] = 1
    masks = {"full": np.ones(1024), "uniform": uni.ravel(),
             "random": p.mask(np.random.default_rng(5).choice(1024, 256, replace=False)),
             "spiral": p.mask(fermat_spiral_layout((32, 32), 256))}
    oracle = PyMUSTScene3(p, acq, setup.delays, setup.scatterer, {k: v.numpy() for k, v in exact.coords.items()})
    with torch.no_grad():
        planes = fast.planes(torch.tensor(np.stack(list(masks.values())), dtype=torch.float32))
    for i, name in enumerate(masks):
        ref = oracle.planes(masks[name])
        for plane in PLANES:
            got = planes[plane][i].to(torch.complex128).numpy()
            assert si_mse(got, ref[plane]) <= 1e-4, (name, plane)


# --------------------------------------------------------------------------- gradients
@pytest.fixture(scope="module")
def tiny():
    setup = _setup(nx=3, ny=2, halves=(0.5e-3, 0.5e-3, 0.5e-3), pixel_wl=1.0)
    exact = MatrixPSF(setup, dtype=torch.float64)
    return exact, MatrixFastPSF(exact, ACCURATE, dtype=torch.float64)


def test_gradcheck_fast_planes(tiny):
    _, fast = tiny
    w0 = torch.linspace(0.3, 0.9, 6, dtype=torch.float64)[None].requires_grad_(True)

    def f(w):
        return torch.cat([torch.view_as_real(v).flatten() for v in fast.planes(w).values()])

    assert torch.autograd.gradcheck(f, (w0,), eps=1e-6, atol=1e-6, rtol=1e-4)


def test_fast_gradient_agrees_with_exact(tiny):
    exact, fast = tiny
    w = torch.tensor([[0.3, 1.0, 0.0, 0.7, 1.0, 0.5], [1, 1, 1, 1, 1, 1]], dtype=torch.float64)
    grads = []
    for model in (exact, fast):
        wg = w.clone().requires_grad_(True)
        planes = model.planes(wg)
        (sum((v.abs() ** 2).sum() for v in planes.values())
         + sum(v.real.sum() - 0.5 * v.imag.sum() for v in planes.values())).backward()
        grads.append(wg.grad)
    g_ex, g_fast = grads
    assert float((g_fast - g_ex).norm() / g_ex.norm()) <= 1e-3


# --------------------------------------------------------------------------- refusals and bad input
def test_pixel_outside_the_record_is_refused():
    # planes reaching 10 mm below a shallow scatterer read past the end of its echo's record
    exact = MatrixPSF(_setup(nx=4, ny=4, scat=(0.0, 0.0, 12e-3), halves=(1e-3, 1e-3, 10e-3), pixel_wl=2.0),
                      dtype=torch.float64)
    with pytest.raises(FastPathUnavailable, match="outside the RF record"):
        MatrixFastPSF(exact, ACCURATE)


def test_failed_check_is_refused(exact_models):
    exact = exact_models["one plane only (xz)"]
    worst = MatrixFastPSF(exact).check["max_relative_error"]
    with pytest.raises(FastPathUnavailable, match="departs from the exact path.*check selections"):
        MatrixFastPSF(exact, FastSettings(check_tol=worst / 2))
    with pytest.raises(FastPathUnavailable):  # a tolerance below rounding: some step refuses
        MatrixFastPSF(exact, FastSettings(check_tol=1e-15))
    with pytest.raises(FastPathUnavailable, match="48 interpolation nodes|2 interpolation nodes"):
        MatrixFastPSF(exact, FastSettings(max_nodes=2))


@pytest.mark.parametrize("kw, key", [(dict(tol=0.0), "tol"), (dict(tol=0.5), "tol"), (dict(replicas=-1), "replicas"),
                                     (dict(replicas=9), "replicas"), (dict(replicas=1.5), "replicas"),
                                     (dict(max_nodes=1), "max_nodes"), (dict(max_nodes=1000), "max_nodes"),
                                     (dict(check_tol=0.0), "check_tol"), (dict(check_tol=2.0), "check_tol"),
                                     (dict(tol=math.nan), "tol")])
def test_settings_out_of_range_name_the_key(kw, key):
    with pytest.raises(ParameterError, match=key):
        FastSettings(**kw)


def test_bad_arguments_and_empty_selection(tiny):
    exact, fast = tiny
    with pytest.raises(ParameterError, match="dtype"):
        MatrixFastPSF(exact, dtype=torch.float16)
    with pytest.raises(ParameterError, match="settings must be a FastSettings"):
        MatrixFastPSF(exact, {"tol": 1e-5})
    with pytest.raises(ParameterError, match="pixel_chunk"):
        MatrixFastPSF(exact, pixel_chunk=0)
    with pytest.raises(SelectionError, match=r"\(B, 6\)"):
        fast.planes(torch.ones(1, 7, dtype=torch.float64))
    with pytest.raises(SelectionError, match="finite"):
        fast.planes(torch.tensor([[1.0, math.nan, 0, 0, 0, 0]]))
    # an all-zero selection: exactly zero planes and zero gradients, nothing NaN or Inf
    w = torch.zeros(2, 6, dtype=torch.float64)
    w[1, 2] = 1
    w.requires_grad_(True)
    planes = fast.planes(w)
    for v in planes.values():
        assert bool(torch.isfinite(torch.view_as_real(v)).all()) and float(v[0].detach().abs().max()) == 0.0
        assert float(v[1].detach().abs().max()) > 0
    sum((v.abs() ** 2).sum() for v in planes.values()).backward()
    assert bool(torch.isfinite(w.grad).all())
    with pytest.raises(NumericalError, match="all zero"):
        peak_normalise({k: v[:1].detach() for k, v in planes.items()})
    # a float32 selection given to a float64 fast path is evaluated in float64
    assert fast.planes(torch.ones(1, 6, dtype=torch.float32))["xy"].dtype == torch.complex128
