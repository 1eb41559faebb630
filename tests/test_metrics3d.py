"""3-D PSF metrics (arraysel.objective.metrics3d): known answers for every metric, the 1-D
definitions recovered on one plane, batches, dtypes, gradients and degenerate input."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from arraysel.errors import NumericalError, ParameterError
from arraysel.objective.metrics import METRIC_NAMES, psf_metrics
from arraysel.objective.metrics3d import (MERIT_NAMES, PSF3D_TERMS, PSL_FLOOR_DB, SIX_DB, c_plane_profiles,
                                          check_planes, main_lobe_widths, normalise_planes, psf3d_metrics,
                                          psf3d_regions)

LAM = 0.5e-3          # wavelength (m)
PITCH = 0.05e-3       # pixel pitch (m)
Z0 = 30e-3            # the scatterer's depth (m)


def _axis(n: int, pitch: float = PITCH) -> np.ndarray:
    return (np.arange(n) - n // 2) * pitch


def three_planes(n: int = 61, pitch: float = PITCH, z0: float = Z0) -> dict[str, np.ndarray]:
    """Coordinates of the C-plane (rows y, columns x), the xz and yz planes (rows z), all through
    (0, 0, z0) at their centre pixel."""
    a = _axis(n, pitch)
    c = {}
    yy, xx = np.meshgrid(a, a, indexing="ij")
    c["xy"] = np.stack([xx, yy, np.full_like(xx, z0)], axis=-1)
    zz, xx = np.meshgrid(z0 + a, a, indexing="ij")
    c["xz"] = np.stack([xx, np.zeros_like(xx), zz], axis=-1)
    zz, yy = np.meshgrid(z0 + a, a, indexing="ij")
    c["yz"] = np.stack([np.zeros_like(yy), yy, zz], axis=-1)
    return c


def sample(f, coords, dtype=torch.complex128) -> dict[str, torch.Tensor]:
    """``f(x, y, z)`` on every plane, as a batch of one."""
    return {k: torch.as_tensor(f(c[..., 0], c[..., 1], c[..., 2] - Z0)[None], dtype=dtype) for k, c in coords.items()}


def gaussian(sx, sy, sz):
    return lambda x, y, z: np.exp(-0.5 * ((x / sx) ** 2 + (y / sy) ** 2 + (z / sz) ** 2))


# ------------------------------------------------------------------ L_PSF


@pytest.mark.parametrize("dtype, tol", [(torch.complex128, 1e-24), (torch.complex64, 1e-10)])
def test_si_mse_zero_for_the_reference_and_a_scaled_phase_rotated_copy(dtype, tol):
    c = three_planes(31)
    f = gaussian(0.3e-3, 0.5e-3, 0.2e-3)
    ref = sample(lambda x, y, z: f(x, y, z) * np.exp(2j * np.pi * z / LAM + 1j * x / 1e-3), c, dtype)
    copy = {k: v * (3.7e5 * complex(math.cos(0.9), math.sin(0.9))) for k, v in ref.items()}
    out = psf3d_metrics({k: torch.cat([ref[k], copy[k]]) for k in ref}, c, wavelength=LAM, planes_ref=ref,
                        terms=["L_PSF"])
    assert out["L_PSF"].shape == (2,)
    assert float(out["L_PSF"].max()) < tol


def test_si_mse_over_all_planes_jointly():
    # a PSF that differs from the reference on one plane only: the joint SI-MSE is that plane's
    # residual energy over the energy of the whole reference set
    c = three_planes(21)
    ref = sample(gaussian(0.3e-3, 0.3e-3, 0.3e-3), c)
    other = {k: v.clone() for k, v in ref.items()}
    other["yz"] = torch.zeros_like(ref["yz"])
    got = float(psf3d_metrics(other, c, wavelength=LAM, planes_ref=ref, terms=["L_PSF"])["L_PSF"])
    e = {k: float((v.abs() ** 2).sum()) for k, v in ref.items()}
    # a* = <k, r>/<k, k> = 1 (k equals r on xy, xz), residual = energy of yz
    assert got == pytest.approx(e["yz"] / sum(e.values()), rel=1e-12)


# ------------------------------------------------------------------ the 1-D definitions on one plane


@pytest.mark.parametrize("dtype", [torch.float64, torch.complex128, torch.float32])
def test_one_plane_gives_the_1d_metrics(dtype):
    g = torch.Generator().manual_seed(4)
    n = 48
    k = torch.randn(3, n, n, dtype=dtype, generator=g)
    k[:, 20, 25] = 30.0           # a clear peak away from the centre
    ref = torch.randn(1, n, n, dtype=dtype, generator=g)
    a = _axis(n)
    zz, xx = np.meshgrid(Z0 + a, a, indexing="ij")
    c = {"xz": np.stack([xx, np.zeros_like(xx), zz], axis=-1)}
    got = psf3d_metrics({"xz": k}, c, wavelength=LAM, planes_ref={"xz": ref}, terms=METRIC_NAMES, r_main=0.3,
                        r_guard=0.5)
    want = psf_metrics(k, pitch=PITCH, wavelength=LAM, kappa_ref=ref[0], r_main=0.3, r_guard=0.5, compiled=False)
    tol = 1e-5 if dtype == torch.float32 else 1e-12
    for name in METRIC_NAMES:
        np.testing.assert_allclose(got[name].numpy(), want[name].numpy(), rtol=tol, atol=tol * 1e-3, err_msg=name)


# ------------------------------------------------------------------ lobe terms on a hand-built m


def test_known_contrast_slr_and_psl_of_a_hand_built_psf():
    n = 41
    c = three_planes(n)
    rm, rg = 1.0, 2.0                         # wavelengths: 10 and 20 pixels
    s = 10 ** (-30 / 20)                      # side level: -30 dB
    planes = {}
    counts = {"main": 0, "side": 0}
    sum_main = 0.0
    for name, cc in c.items():
        r = np.sqrt(cc[..., 0] ** 2 + cc[..., 1] ** 2 + (cc[..., 2] - Z0) ** 2)
        m = np.where(r <= rm * LAM + 1e-12, 0.8, np.where(r >= rg * LAM - 1e-12, s, 0.3))
        m[n // 2, n // 2] = 1.0               # the peak (the same point on the three planes)
        planes[name] = torch.as_tensor(m[None] * np.exp(1j * 0.37), dtype=torch.complex128)
        main = r <= rm * LAM + 1e-12
        counts["main"] += int(main.sum())
        counts["side"] += int((r >= rg * LAM - 1e-12).sum())
        sum_main += float((m[main] ** 2).sum())
    out = psf3d_metrics(planes, c, wavelength=LAM, r_main=rm, r_guard=rg, quantile=0.9)
    sum_side = counts["side"] * s ** 2
    assert float(out["L_SLR_i"]) == pytest.approx(sum_side / sum_main, rel=1e-12)
    assert float(out["L_contrast"]) == pytest.approx((sum_side / counts["side"]) / (sum_main / counts["main"]),
                                                     rel=1e-12)
    assert float(out["L_SLR_q"]) == pytest.approx(s, rel=1e-12)
    assert float(out["L_SLR"]) == pytest.approx(0.5 * (s + sum_side / sum_main), rel=1e-12)
    assert float(out["PSL_dB"]) == pytest.approx(-30.0, abs=1e-9)
    # with a reference equal to it, Mean = (0 + contrast + SLR_q + SLR_i) / 4
    out = psf3d_metrics(planes, c, wavelength=LAM, r_main=rm, r_guard=rg, quantile=0.9, planes_ref=planes)
    assert float(out["Mean"]) == pytest.approx(
        0.25 * float(out["L_contrast"] + out["L_SLR_q"] + out["L_SLR_i"]), rel=1e-9)


def test_psl_of_an_analytic_side_lobe_at_a_known_level():
    # a narrow main lobe and one side lobe 4 wavelengths away in x at -23 dB
    c = three_planes(101)
    main = gaussian(0.05e-3, 0.05e-3, 0.05e-3)
    amp = 10 ** (-23 / 20)

    def f(x, y, z):
        return main(x, y, z) + amp * np.exp(-0.5 * (((x - 4 * LAM) / 0.05e-3) ** 2 + (y / 0.05e-3) ** 2
                                                   + (z / 0.05e-3) ** 2))

    out = psf3d_metrics(sample(f, c), c, wavelength=LAM, r_main=1.0, r_guard=2.0)
    assert float(out["PSL_dB"]) == pytest.approx(-23.0, abs=1e-6)
    reg = psf3d_regions(sample(f, c), c, wavelength=LAM, r_main=1.0, r_guard=2.0)
    assert reg.peak_plane == ["xy"]
    np.testing.assert_allclose(reg.peak_position.numpy(), [[0, 0, Z0]], atol=1e-15)
    # the side lobe lies in the side region, the peak in the main region of every plane
    assert bool(reg.side["xy"][0, 50, 90]) and bool(reg.main["xz"][0, 50, 50])
    assert float(reg.r["xz"][0, 50, 90]) == pytest.approx(4 * LAM)


def test_regions_are_measured_in_3d_from_the_peak():
    c = three_planes(41)
    # peak off-centre in the xz plane, 0.5 mm deeper than the C-plane
    f = gaussian(0.1e-3, 0.1e-3, 0.1e-3)
    planes = sample(lambda x, y, z: f(x, y, z - 0.5e-3), c)
    reg = psf3d_regions(planes, c, wavelength=LAM, r_main=1.0, r_guard=2.0)
    assert reg.peak_plane == ["xz"]            # xz comes before yz: first on ties
    np.testing.assert_allclose(reg.peak_position.numpy(), [[0, 0, Z0 + 0.5e-3]], atol=1e-12)
    # the C-plane's centre is exactly r_main = 0.5 mm away: inside the main region (inclusive)
    assert float(reg.r["xy"][0, 20, 20]) == pytest.approx(0.5e-3)
    assert bool(reg.main["xy"][0, 20, 20])
    # a C-plane pixel at x = 0.9 mm: r = sqrt(0.9^2 + 0.5^2) mm > 1 mm = r_guard
    assert float(reg.r["xy"][0, 20, 38]) == pytest.approx(math.hypot(0.9e-3, 0.5e-3))
    assert bool(reg.side["xy"][0, 20, 38]) and not bool(reg.main["xy"][0, 20, 38])


# ------------------------------------------------------------------ -6 dB widths


def test_widths_of_a_separable_gaussian():
    c = three_planes(161, pitch=0.02e-3)
    sx, sy = 0.4e-3, 0.25e-3
    out = psf3d_metrics(sample(gaussian(sx, sy, 0.2e-3), c), c, wavelength=LAM)
    half = math.sqrt(2 * math.log(1 / SIX_DB))       # -6 dB half width in sigmas
    assert float(out["width_x_6dB"]) == pytest.approx(2 * half * sx, rel=2e-3)
    assert float(out["width_y_6dB"]) == pytest.approx(2 * half * sy, rel=2e-3)


def test_widths_of_a_tent_are_exact_with_linear_interpolation():
    # a separable triangle |1 - |x|/a|: linear between samples, so the interpolated crossings are exact
    c = three_planes(61)
    ax, ay = 0.73e-3, 0.41e-3

    def f(x, y, z):
        return np.maximum(0, 1 - np.abs(x) / ax) * np.maximum(0, 1 - np.abs(y) / ay) * np.exp(-(z / 1e-3) ** 2)

    planes = sample(f, c, torch.float64)
    out = psf3d_metrics(planes, c, wavelength=LAM, terms=["width_x_6dB", "width_y_6dB"])
    assert float(out["width_x_6dB"]) == pytest.approx(2 * ax * (1 - SIX_DB), rel=1e-12)
    assert float(out["width_y_6dB"]) == pytest.approx(2 * ay * (1 - SIX_DB), rel=1e-12)
    # the C-plane transposed (rows along x): the same widths
    ct = {"xy": np.swapaxes(c["xy"], 0, 1)}
    w = main_lobe_widths(planes["xy"].transpose(-1, -2), ct["xy"])
    assert w["x"][0] == pytest.approx(2 * ax * (1 - SIX_DB), rel=1e-12)
    assert w["y"][0] == pytest.approx(2 * ay * (1 - SIX_DB), rel=1e-12)


def test_width_is_inf_when_the_main_lobe_is_wider_than_the_window():
    c = three_planes(21)
    out = psf3d_metrics(sample(gaussian(5e-3, 0.1e-3, 0.1e-3), c), c, wavelength=LAM)
    assert math.isinf(float(out["width_x_6dB"])) and math.isfinite(float(out["width_y_6dB"]))


def test_profiles_pass_through_the_c_plane_peak():
    c = three_planes(31)
    f = gaussian(0.2e-3, 0.2e-3, 0.2e-3)
    planes = sample(lambda x, y, z: f(x - 0.25e-3, y + 0.1e-3, z), c)
    prof = c_plane_profiles(planes["xy"], c["xy"])
    s, a = prof["x"]
    assert s.shape == a.shape == (1, 31)
    np.testing.assert_allclose(s[0], _axis(31))
    assert s[0, np.argmax(a[0])] == pytest.approx(0.25e-3)
    s, a = prof["y"]
    assert s[0, np.argmax(a[0])] == pytest.approx(-0.1e-3)


# ------------------------------------------------------------------ batches, dtypes, scale


def test_batch_equals_items_and_float32_matches_float64():
    g = torch.Generator().manual_seed(1)
    c = three_planes(25)
    base = sample(gaussian(0.2e-3, 0.3e-3, 0.1e-3), c)
    planes = {k: v + 0.05 * torch.randn(3, *v.shape[-2:], dtype=v.dtype, generator=g) for k, v in base.items()}
    planes["xz"][2, 5, 7] += 3.0       # the third item peaks elsewhere: per-item regions
    kw = dict(wavelength=LAM, r_main=0.5, r_guard=1.0, planes_ref=base)
    full = psf3d_metrics(planes, c, **kw)
    assert set(full) == set(PSF3D_TERMS)
    for i in range(3):
        one = psf3d_metrics({k: v[i:i + 1] for k, v in planes.items()}, c, **kw)
        for name in PSF3D_TERMS:
            assert float(one[name][0]) == pytest.approx(float(full[name][i]), rel=1e-12, abs=1e-15), name
    kw["planes_ref"] = {k: v.to(torch.complex64) for k, v in base.items()}
    f32 = psf3d_metrics({k: v.to(torch.complex64) for k, v in planes.items()}, c, **kw)
    for name in PSF3D_TERMS:
        assert f32[name].dtype == torch.float32
        np.testing.assert_allclose(f32[name].numpy(), full[name].numpy(), rtol=2e-4, atol=1e-6, err_msg=name)
    # invariant to the scale of the set (float32 far from 1 included)
    tiny = psf3d_metrics({k: v.to(torch.complex64) * 1e-30 for k, v in planes.items()}, c, **kw)
    for name in PSF3D_TERMS:
        np.testing.assert_allclose(tiny[name].numpy(), full[name].numpy(), rtol=2e-4, atol=1e-6, err_msg=name)


def test_leading_shape_is_kept_and_reference_broadcasts():
    c = three_planes(15)
    base = sample(gaussian(0.2e-3, 0.2e-3, 0.2e-3), c)
    planes = {k: v.expand(2, 3, *v.shape[-2:]) for k, v in base.items()}
    out = psf3d_metrics(planes, c, wavelength=LAM, r_main=0.2, r_guard=0.3, planes_ref=base)
    assert all(v.shape == (2, 3) for v in out.values())
    single = psf3d_metrics({k: v[0] for k, v in base.items()}, c, wavelength=LAM, r_main=0.2, r_guard=0.3)
    assert all(v.shape == () for v in single.values())


def test_normalise_planes_gives_unit_joint_energy():
    c = three_planes(11)
    planes = {k: v * torch.tensor([[[2.0]], [[1e-20]]]) for k, v in sample(gaussian(1e-4, 1e-4, 1e-4), c).items()}
    unit = normalise_planes(planes)
    energy = sum((v.abs() ** 2).sum(dim=(-2, -1)) for v in unit.values())
    np.testing.assert_allclose(energy.numpy(), [1.0, 1.0], rtol=1e-12)
    zero = normalise_planes({k: torch.zeros_like(v) for k, v in planes.items()})
    assert all(bool((v == 0).all()) for v in zero.values())


# ------------------------------------------------------------------ gradients


def test_gradcheck_of_the_differentiable_terms():
    g = torch.Generator().manual_seed(7)
    c = three_planes(7, pitch=0.1e-3)
    names = list(c)
    ref = {k: torch.randn(1, 7, 7, dtype=torch.complex128, generator=g) for k in names}
    x0 = [torch.randn(2, 7, 7, dtype=torch.complex128, generator=g) for _ in names]
    x0[0][:, 3, 3] += 6.0          # one clear peak
    x0[1][1, 2, 2] += 9.0          # ... elsewhere for the second item (per-item regions)

    def f(*xs):
        out = psf3d_metrics(dict(zip(names, xs)), c, wavelength=LAM, planes_ref=ref, r_main=0.2, r_guard=0.35,
                            quantile=0.9, terms=list(METRIC_NAMES) + ["PSL_dB"])
        return torch.stack([out[n] for n in list(METRIC_NAMES) + ["PSL_dB"]])

    xs = tuple(x[:1].clone().requires_grad_(True) for x in x0)
    assert torch.autograd.gradcheck(f, xs, eps=1e-7, atol=1e-6, rtol=1e-4)
    xr = tuple(x.detach().real.clone().requires_grad_(True) for x in x0)
    assert torch.autograd.gradcheck(f, xr, eps=1e-7, atol=1e-6, rtol=1e-4)


@pytest.mark.parametrize("dtype", [torch.complex64, torch.float64])
def test_zero_psf_gives_finite_placeholders_and_gradients(dtype):
    c = three_planes(11)
    ref = sample(gaussian(1e-4, 1e-4, 1e-4), c, dtype)
    planes = {k: torch.zeros(2, 11, 11, dtype=dtype, requires_grad=True) for k in c}
    out = psf3d_metrics(planes, c, wavelength=LAM, planes_ref=ref, r_main=0.2, r_guard=0.3)
    total = sum(out[n].sum() for n in METRIC_NAMES) + out["PSL_dB"].sum()
    out = {k: v.detach() for k, v in out.items()}
    assert float(out["L_PSF"][0]) == pytest.approx(1.0, rel=1e-6)
    for name in ("L_contrast", "L_SLR_q", "L_SLR_i", "L_SLR"):
        assert float(out[name].abs().max()) == 0.0, name
    assert float(out["PSL_dB"][0]) == PSL_FLOOR_DB
    assert math.isinf(float(out["width_x_6dB"][0])) and math.isinf(float(out["width_y_6dB"][0]))
    total.backward()
    assert all(bool(torch.isfinite(p.grad).all()) for p in planes.values())
    with pytest.raises(NumericalError, match="identically zero at batch index"):
        check_planes(planes, c)
    bad = {k: v.detach().clone() for k, v in ref.items()}
    bad["xz"][0, 0, 0] = float("nan")
    with pytest.raises(NumericalError, match="not finite"):
        check_planes(bad, c)
    check_planes(ref, c, ref)


# ------------------------------------------------------------------ bad input


def test_bad_input_names_the_key():
    c = three_planes(11)
    p = sample(gaussian(1e-4, 1e-4, 1e-4), c)
    with pytest.raises(ParameterError, match="coords has no entry for plane 'yz'"):
        psf3d_metrics(p, {k: v for k, v in c.items() if k != "yz"}, wavelength=LAM)
    with pytest.raises(ParameterError, match=r"coords\['xz'\] must have shape \(11, 11, 3\)"):
        psf3d_metrics(p, {**c, "xz": c["xz"][:5]}, wavelength=LAM)
    with pytest.raises(ParameterError, match=r"planes\['xz'\] has leading shape"):
        psf3d_metrics({**p, "xz": p["xz"].expand(2, 11, 11)}, c, wavelength=LAM)
    with pytest.raises(ParameterError, match="needs planes_ref"):
        psf3d_metrics(p, c, wavelength=LAM, terms=["Mean"])
    with pytest.raises(ParameterError, match="planes_ref must have the planes"):
        psf3d_metrics(p, c, wavelength=LAM, planes_ref={"xy": p["xy"]})
    with pytest.raises(ParameterError, match="needs? the C-plane 'xy'"):
        psf3d_metrics({"xz": p["xz"]}, {"xz": c["xz"]}, wavelength=LAM, terms=["width_x_6dB"])
    with pytest.raises(ParameterError, match="wavelength"):
        psf3d_metrics(p, c, wavelength=0.0)
    with pytest.raises(ParameterError, match="r_guard"):
        psf3d_metrics(p, c, wavelength=LAM, r_main=2, r_guard=1)
    with pytest.raises(ParameterError, match="unknown 3-D PSF metric"):
        psf3d_metrics(p, c, wavelength=LAM, terms=["PSL"])
    with pytest.raises(ParameterError, match="is not a C-plane"):
        psf3d_metrics(p, {**c, "xy": c["xz"]}, wavelength=LAM, terms=["width_x_6dB"])
    # without the C-plane the default set leaves the widths out
    out = psf3d_metrics({"xz": p["xz"]}, {"xz": c["xz"]}, wavelength=LAM)
    assert set(out) == {"L_contrast", "L_SLR_q", "L_SLR_i", "L_SLR", "PSL_dB"}
    assert set(MERIT_NAMES) <= set(psf3d_metrics(p, c, wavelength=LAM))
