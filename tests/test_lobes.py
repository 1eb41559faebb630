"""Per-beam lobe metrics (arraysel.objective.lobes): the main lobe from the point's own PSF, on
cases with known answers (separable sinc and Dirichlet patterns, an Airy pattern wider than the
old fixed guard, a periodic thinning's grating lobe), ripple, edges, several surfaces, batches,
dtypes, gradients and bad input."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.integrate import quad
from scipy.special import j1

from arraysel.errors import NumericalError, ParameterError
from arraysel.objective.lobes import (LOBE_TERMS, MainLobeRule, direction_cosines, lobe_metrics, lobe_widths,
                                      main_lobe_regions, sphere_surface)
from arraysel.objective.metrics3d import PSL_FLOOR_DB, psf3d_metrics
from arraysel.physics.beampattern import BeamPattern, grating_lobe_directions, lattice_periods
from arraysel.physics.probes import get_probe

SINC_SIDE_DB = -13.2619     # the first side lobe of sin(pi x) / (pi x)
AIRY_SIDE_DB = -17.5711     # the first side lobe of 2 J1(x) / x


def uv_grid(n: int, half: float) -> np.ndarray:
    """(n, n, 3) coords (u, v, 0) on [-half, half]^2, rows along v."""
    a = np.linspace(-half, half, n)
    v, u = np.meshgrid(a, a, indexing="ij")
    return np.stack([u, v, np.zeros_like(u)], axis=-1)


def sinc2d(c: np.ndarray, x0: float = 0.0) -> np.ndarray:
    return np.sinc(c[..., 0] - x0) * np.sinc(c[..., 1])


def airy(r: np.ndarray, r_null: float) -> np.ndarray:
    x = 3.8317059702 * r / r_null
    return np.where(x == 0, 1.0, 2 * j1(np.where(x == 0, 1.0, x)) / np.where(x == 0, 1.0, x))


def c_plane(n: int, pitch: float, z0: float) -> np.ndarray:
    a = (np.arange(n) - n // 2) * pitch
    y, x = np.meshgrid(a, a, indexing="ij")
    return np.stack([x, y, np.full_like(x, z0)], axis=-1)


# --------------------------------------------------------------------------
# known answers
# --------------------------------------------------------------------------

@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_separable_sinc_known_answers(dtype):
    c = uv_grid(401, 5.0)                               # step 0.025
    planes = {"p": torch.tensor(sinc2d(c), dtype=dtype)[None]}
    reg = main_lobe_regions(planes, {"p": c}, frame="uv")
    # along the axes and the diagonals the first null is the rectangle |u|, |v| < 1
    rays = reg.rays["p"][0]
    k = rays.numel()
    assert abs(float(rays[0]) - 1.0) <= 0.0125 and abs(float(rays[k // 4]) - 1.0) <= 0.0125
    assert abs(float(rays[k // 8]) - math.sqrt(2)) <= 0.02
    assert not bool(reg.clipped[0])
    m = lobe_metrics(planes, {"p": c}, frame="uv")
    assert set(m) == {"PSL_dB", "ISLR_dB", "width_u_6dB", "width_v_6dB"}
    assert float(m["PSL_dB"][0]) == pytest.approx(SINC_SIDE_DB, abs=0.02)
    # ISLR on this region: (int_{-5}^{5} sinc^2)^2 / (int_{-1}^{1} sinc^2)^2 - 1, by quadrature
    e_main = quad(lambda t: np.sinc(t) ** 2, -1, 1)[0] ** 2
    e_all = quad(lambda t: np.sinc(t) ** 2, -5, 5, limit=400)[0] ** 2
    assert float(m["ISLR_dB"][0]) == pytest.approx(10 * math.log10((e_all - e_main) / e_main), abs=0.01)
    six = 2 * 0.60335      # sinc(x) = 10**(-6/20) at x = 0.60335
    assert float(m["width_u_6dB"][0]) == pytest.approx(six, abs=0.005)
    assert float(m["width_v_6dB"][0]) == pytest.approx(six, abs=0.005)
    assert m["PSL_dB"].dtype == dtype


def _dirichlet_side_db(n: int) -> float:
    """The first side lobe (dB) of |sin(n x) / (n sin x)|, by a fine search between its nulls."""
    x = np.linspace(math.pi / n * 1.0001, 2 * math.pi / n * 0.9999, 200001)
    return float(20 * np.log10(np.abs(np.sin(n * x) / (n * np.sin(x))).max()))


def test_dirichlet_two_way_pattern_of_a_uniform_array():
    probe = get_probe("MATRIX-32x32", nx=8, ny=6)
    bp = BeamPattern.from_probe(probe, n_freq=1, oversample=8, sector_deg=(0, 0), region="visible",
                                dtype=torch.float64)
    lam = float(bp.wavelengths[0])
    img = bp.pattern(torch.ones(1, probe.n_elements))
    reg = main_lobe_regions({"p": img}, {"p": bp.coords}, power=True, frame="uv", target=(0, 0, 0))
    rays = reg.rays["p"][0]
    step = float(bp.du[1] - bp.du[0])
    assert abs(float(rays[0]) - lam / (8 * probe.pitch_x)) <= 0.5 * step          # the first null in u
    assert abs(float(rays[rays.numel() // 4]) - lam / (6 * probe.pitch_y)) <= 0.5 * step
    m = lobe_metrics({"p": img}, {"p": bp.coords}, power=True, frame="uv", target=(0, 0, 0),
                     weights={"p": bp.mean_weight})
    # two-way power: the one-way side lobe of the shorter side (6 elements: the higher one) twice
    assert float(m["PSL_dB"][0]) == pytest.approx(2 * _dirichlet_side_db(6), abs=0.1)
    # ISLR against the exact main-lobe rectangle, summed on the same grid
    du, dv = bp.coords[..., 0].numpy(), bp.coords[..., 1].numpy()
    rect = (np.abs(du) < lam / (8 * probe.pitch_x)) & (np.abs(dv) < lam / (6 * probe.pitch_y))
    p, w = img[0].numpy(), bp.mean_weight.numpy()
    islr = 10 * math.log10((p * w)[~rect].sum() / (p * w)[rect].sum())
    assert float(m["ISLR_dB"][0]) == pytest.approx(islr, abs=0.05)


def test_airy_main_lobe_wider_than_the_old_guard_is_found_whole():
    lam, pitch, z0 = 0.5e-3, 0.05e-3, 30e-3
    r_null = 5 * lam                                    # wider than r_guard = 3.5 wavelengths
    c = c_plane(241, pitch, z0)
    r = np.hypot(c[..., 0], c[..., 1])
    planes = {"xy": torch.tensor(airy(r, r_null))[None]}
    reg = main_lobe_regions(planes, {"xy": c}, target=(0, 0, z0))
    assert torch.allclose(reg.rays["xy"][0], torch.full_like(reg.rays["xy"][0], r_null), atol=pitch)
    assert bool(reg.main["xy"][0][r < r_null - pitch].all()) and not bool(reg.main["xy"][0][r > r_null + pitch].any())
    m = lobe_metrics(planes, {"xy": c}, target=(0, 0, z0))
    assert float(m["PSL_dB"][0]) == pytest.approx(AIRY_SIDE_DB, abs=0.05)
    # the -6 dB width of 2 J1(x) / x: x = 2.2151
    assert float(m["width_x_6dB"][0]) == pytest.approx(2 * 2.2151 / 3.8317 * r_null, abs=pitch)
    # a fixed guard of 3.5 wavelengths counts the main lobe's flank as side lobe
    old = psf3d_metrics(planes, {"xy": c}, wavelength=lam, r_guard=3.5, terms=["PSL_dB"])
    assert float(old["PSL_dB"][0]) > AIRY_SIDE_DB + 6


def test_contour_rule():
    c = uv_grid(401, 5.0)
    planes = {"p": torch.tensor(sinc2d(c))[None]}
    rule = MainLobeRule(method="contour", contour_factor=1.0 / 0.60335)   # the null of a sinc
    rays = main_lobe_regions(planes, {"p": c}, frame="uv", rule=rule).rays["p"][0]
    assert float(rays[0]) == pytest.approx(1.0, abs=0.01)


def test_ripple_on_the_flank_is_not_a_null_but_a_deep_ring_is():
    lam, pitch, z0 = 0.5e-3, 0.025e-3, 30e-3
    c = c_plane(201, pitch, z0)
    r = np.hypot(c[..., 0], c[..., 1])
    base = airy(r, 2e-3)

    def ring(db, at=0.3e-3, w=0.08e-3):
        return 1 - (1 - 10 ** (-db / 20)) * np.exp(-((r - at) / w) ** 2)

    # a ring 0.8 dB deep on the flank: walking outward the amplitude climbs 0.38 dB out of it
    shallow = main_lobe_regions({"xy": torch.tensor(base * ring(0.8))[None]}, {"xy": c}).rays["xy"][0]
    assert torch.allclose(shallow, torch.full_like(shallow, 2e-3), atol=pitch)
    fine = main_lobe_regions({"xy": torch.tensor(base * ring(0.8))[None]}, {"xy": c},
                             rule=MainLobeRule(ripple_db=0.2)).rays["xy"][0]
    assert float(fine.max()) < 0.4e-3               # with a finer tolerance it is a null
    deep = main_lobe_regions({"xy": torch.tensor(base * ring(6.0, at=1e-3, w=0.1e-3))[None]},
                             {"xy": c}).rays["xy"][0]
    assert float(deep.max()) < 1.2e-3               # a ring 6 dB deep is a null
    # a dip that is not a ring (one side only) is walked round by the other rays
    dip = 1 - 0.5 * np.exp(-((c[..., 0] - 1e-3) ** 2 + c[..., 1] ** 2) / (0.1e-3) ** 2)
    reg = main_lobe_regions({"xy": torch.tensor(base * dip)[None]}, {"xy": c})
    rays = reg.rays["xy"][0]
    assert float(rays[0]) < 1.2e-3 and float(rays[rays.numel() // 2]) == pytest.approx(2e-3, abs=pitch)
    assert bool(reg.main["xy"][0][(r < 1.9e-3) & (c[..., 0] < 0)].all())


def test_main_lobe_touching_the_edge():
    c = uv_grid(201, 3.0)
    planes = {"p": torch.tensor(sinc2d(c, x0=2.6))[None]}       # its null at u = 3.6 is outside
    reg = main_lobe_regions(planes, {"p": c}, frame="uv")
    assert bool(reg.clipped[0]) and bool(torch.isinf(reg.rays["p"][0]).any())
    m = lobe_metrics(planes, {"p": c}, frame="uv")
    assert all(bool(torch.isfinite(v).all()) for k, v in m.items() if not k.startswith("width"))
    assert float(m["PSL_dB"][0]) == pytest.approx(SINC_SIDE_DB, abs=0.1)   # the side lobe on its left
    assert math.isinf(float(m["width_u_6dB"][0])) is False


# --------------------------------------------------------------------------
# grating lobes
# --------------------------------------------------------------------------

def test_grating_lobe_of_a_periodic_thinning_where_theory_says():
    probe = get_probe("MATRIX-32x32", nx=16, ny=16)
    bp = BeamPattern.from_probe(probe, n_freq=1, oversample=2, sector_deg=(0, 0), region="visible",
                                dtype=torch.float64)
    lam = float(bp.wavelengths[0])
    thin = np.zeros((16, 16))
    thin[::2, ::2] = 1
    w = torch.tensor(np.stack([thin.ravel(), np.ones(256)]))
    assert lattice_periods(w, 16, 16).tolist() == [[2, 2], [1, 1]]
    img = bp.pattern(w)
    pos = grating_lobe_directions(2 * probe.pitch_x, 2 * probe.pitch_y, [lam], bounds=(-1, 1, -1, 1))
    assert pos.shape[0] == 8 and torch.allclose(pos.abs().max(0).values, torch.full((2,), lam / 0.6e-3, dtype=torch.float64))
    m = lobe_metrics({"p": img[:1]}, {"p": bp.coords}, power=True, frame="uv", target=(0, 0, 0),
                     weights={"p": bp.mean_weight}, grating_uv=pos)
    assert float(m["GLL_dB"][0]) > -0.5 and float(m["GLL_dB"][0]) == pytest.approx(float(m["PSL_dB"][0]))
    # where the strongest side lobe sits: on a predicted position, to within a grid step
    reg = main_lobe_regions({"p": img[:1]}, {"p": bp.coords}, power=True, frame="uv", target=(0, 0, 0))
    side = img[0].masked_fill(reg.main["p"][0] | (bp.mean_weight == 0), 0)
    top = bp.coords.reshape(-1, 3)[side.argmax(), :2]
    assert float((pos - top).norm(dim=1).min()) <= float(bp.du[1] - bp.du[0])
    # the full array's grating lobes (lambda / 0.3 mm = 1.7) fall outside the visible disk: the floor
    full = grating_lobe_directions(probe.pitch_x, probe.pitch_y, [lam], bounds=(-1, 1, -1, 1))
    assert full.shape[0] == 0
    m2 = lobe_metrics({"p": img[1:]}, {"p": bp.coords}, power=True, frame="uv", target=(0, 0, 0), grating_uv=full)
    assert float(m2["GLL_dB"][0]) == PSL_FLOOR_DB


# --------------------------------------------------------------------------
# several surfaces, batches, dtypes, gradients
# --------------------------------------------------------------------------

def _three_planes(n: int = 61, pitch: float = 0.05e-3, z0: float = 30e-3) -> dict:
    a = (np.arange(n) - n // 2) * pitch
    c = {}
    y, x = np.meshgrid(a, a, indexing="ij")
    c["xy"] = np.stack([x, y, np.full_like(x, z0)], -1)
    z, x = np.meshgrid(z0 + a, a, indexing="ij")
    c["xz"] = np.stack([x, np.zeros_like(x), z], -1)
    z, y = np.meshgrid(z0 + a, a, indexing="ij")
    c["yz"] = np.stack([np.zeros_like(y), y, z], -1)
    return c


def _psf3(c: dict, z0: float, wx: float, wy: float) -> dict:
    return {k: torch.tensor(np.sinc(v[..., 0] / wx) * np.sinc(v[..., 1] / wy)
                            * np.exp(-((v[..., 2] - z0) / 0.4e-3) ** 2) * np.exp(2j * np.pi * (v[..., 2] - z0) / 0.25e-3))
            for k, v in c.items()}


def test_several_surfaces_and_batches():
    z0 = 30e-3
    c = _three_planes(z0=z0)
    items = [_psf3(c, z0, 0.8e-3, 1.1e-3), _psf3(c, z0, 1.0e-3, 0.7e-3)]
    batch = {k: torch.stack([it[k] for it in items]) for k in c}
    m = lobe_metrics(batch, c, target=(0, 0, z0))
    assert set(m) == set(LOBE_TERMS["xyz"]) - {"GLL_dB"}
    for i, it in enumerate(items):
        one = lobe_metrics({k: v[None] for k, v in it.items()}, c, target=(0, 0, z0))
        for k in m:
            assert float(m[k][i]) == pytest.approx(float(one[k][0]), rel=1e-9, abs=1e-12)
    # widths along x and y through the peak on the C-plane: sinc(x / wx) at -6 dB
    assert float(m["width_x_6dB"][0]) == pytest.approx(2 * 0.60335 * 0.8e-3, abs=0.05e-3)
    assert float(m["width_y_6dB"][1]) == pytest.approx(2 * 0.60335 * 0.7e-3, abs=0.05e-3)
    reg = main_lobe_regions(batch, c, target=(0, 0, z0))
    assert all(bool(reg.has_lobe[k].all()) for k in c)
    # without a target: the largest value (the scatterer's pixel, on all three planes)
    m2 = lobe_metrics(batch, c)
    assert torch.allclose(m2["PSL_dB"], m["PSL_dB"])
    # float32 agrees
    m32 = lobe_metrics({k: v.to(torch.complex64) for k, v in batch.items()}, c, target=(0, 0, z0))
    assert torch.allclose(m32["PSL_dB"].double(), m["PSL_dB"], atol=1e-3)
    assert torch.allclose(m32["ISLR_dB"].double(), m["ISLR_dB"], atol=1e-3)


def test_gradients_of_psl_and_islr():
    c = uv_grid(11, 2.5)
    base = sinc2d(c) + 0.05 * np.cos(7 * c[..., 0])
    reg = main_lobe_regions({"p": torch.tensor(base)[None]}, {"p": c}, frame="uv")   # regions are detached

    def f(p, term):
        return lobe_metrics({"p": p}, {"p": c}, frame="uv", terms=[term], regions=reg)[term]

    x = torch.tensor(base, dtype=torch.float64)[None].requires_grad_()
    for term in ("PSL_dB", "ISLR_dB"):
        torch.autograd.gradcheck(lambda p: f(p, term), (x,), eps=1e-6, atol=1e-6, rtol=1e-4)
    z = torch.tensor(base * np.exp(1j * c[..., 0]))[None].requires_grad_()
    torch.autograd.gradcheck(lambda p: f(p, "ISLR_dB"), (z,), eps=1e-6, atol=1e-6, rtol=1e-4)
    # the regions found inside give the same values and a finite gradient
    out = lobe_metrics({"p": x}, {"p": c}, frame="uv", terms=["PSL_dB", "ISLR_dB"])
    (out["PSL_dB"] + out["ISLR_dB"]).sum().backward()
    assert bool(torch.isfinite(x.grad).all()) and float(x.grad.abs().sum()) > 0


def test_angle_sampled_surface_and_directions():
    u = np.linspace(-0.5, 0.5, 41)
    s = sphere_surface(60e-3, u, u)
    uv = direction_cosines(s)
    assert torch.allclose(uv[..., 0], torch.tensor(u)[None].expand(41, 41), atol=1e-12)
    assert torch.allclose(uv[..., 1], torch.tensor(u)[:, None].expand(41, 41), atol=1e-12)
    # a PSF on that surface: widths in metres along x, grating lobes placed in u-v
    uu, vv = uv[..., 0].numpy(), uv[..., 1].numpy()
    img = np.sinc(uu / 0.05) * np.sinc(vv / 0.05) + 0.5 * np.sinc((uu - 0.4) / 0.05) * np.sinc(vv / 0.05)
    m = lobe_metrics({"s": torch.tensor(img)[None]}, {"s": s}, grating_uv=np.array([[0.4, 0.0]]))
    assert float(m["GLL_dB"][0]) == pytest.approx(20 * math.log10(0.5), abs=0.1)
    assert float(m["width_x_6dB"][0]) == pytest.approx(60e-3 * 2 * 0.60335 * 0.05, rel=0.03)


# --------------------------------------------------------------------------
# bad input
# --------------------------------------------------------------------------

def test_bad_input():
    c = uv_grid(21, 3.0)
    good = torch.tensor(sinc2d(c))[None]
    with pytest.raises(NumericalError, match="identically zero"):
        lobe_metrics({"p": torch.zeros(2, 21, 21)}, {"p": c}, frame="uv")
    with pytest.raises(NumericalError):
        lobe_metrics({"p": good * float("nan")}, {"p": c}, frame="uv")
    with pytest.raises(ParameterError, match="frame"):
        lobe_metrics({"p": good}, {"p": c}, frame="polar")
    with pytest.raises(ParameterError, match="unknown lobe metric"):
        lobe_metrics({"p": good}, {"p": c}, frame="uv", terms=["width_x_6dB"])
    with pytest.raises(ParameterError, match="grating_uv"):
        lobe_metrics({"p": good}, {"p": c}, frame="uv", terms=["GLL_dB"])
    with pytest.raises(ParameterError, match="coords"):
        lobe_metrics({"p": good}, {"p": c[:5]}, frame="uv")
    with pytest.raises(ParameterError, match="target"):
        lobe_metrics({"p": good}, {"p": c}, frame="uv", target=(50.0, 0, 0))
    with pytest.raises(ParameterError, match="weights"):
        lobe_metrics({"p": good}, {"p": c}, frame="uv", weights={"p": -np.ones((21, 21))})
    with pytest.raises(ParameterError, match="ripple_db"):
        MainLobeRule(ripple_db=0)
    with pytest.raises(ParameterError, match="n_rays"):
        MainLobeRule(n_rays=4)
    with pytest.raises(ParameterError, match="power=True"):
        lobe_metrics({"p": good.to(torch.complex128)}, {"p": c}, frame="uv", power=True)


def test_grid_axes_of_a_wide_sphere_are_read_at_its_middle():
    # at the corner of a sphere sampled out to |u|, |v| = 0.7 a step in u runs mostly along z; the
    # axes along x and y are read where the surface faces the probe
    from arraysel.objective.lobe_regions import _axis_along
    from arraysel.physics.beamgeometry import sphere_surface

    g = np.linspace(-0.705, 0.705, 79)
    pos = sphere_surface(0.05, g, g)
    corner = pos[0, 1] - pos[0, 0]
    assert abs(float(corner[2])) > abs(float(corner[0]))
    assert _axis_along(pos, 0) == 1 and _axis_along(pos, 1) == 0
    assert _axis_along(pos[:1], 0) == 1 and _axis_along(pos[:1], 1) is None   # one row: no axis along y
