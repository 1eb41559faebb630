"""benchmarks/sector_recheck.py, the independent re-check of a sector comparison's selections: its
own metric extraction on images whose answer is known, its geometry, and its bad-input errors
(the PyMUST pipeline at size is the benchmark's, not a test's)."""
from __future__ import annotations

import importlib.util
import math
import os

import numpy as np
import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SCRIPT = os.path.join(ROOT, "benchmarks", "sector_recheck.py")


@pytest.fixture(scope="module")
def mod():
    spec = importlib.util.spec_from_file_location("sector_recheck", SCRIPT)
    m = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(m)
    return m


def _sinc_image(u, v, lobe, shift=(0.0, 0.0)):
    U, V = np.meshgrid(u, v)
    return np.sinc((U - shift[0]) / lobe) * np.sinc((V - shift[1]) / lobe)


def test_separable_sinc_has_its_analytic_lobes(mod):
    """sinc(u/L) sinc(v/L): first nulls at |u| = L or |v| = L, so the main lobe is the square
    inside them; the strongest side lobe is the first one along an axis, sinc(1.4303) = -13.26 dB;
    the -6 dB width is 2 x 0.6025 L (sinc(0.6025) = 10^(-6/20)), times the range on the sphere."""
    lobe, r = 0.05, 0.04
    u = np.arange(-60, 61) * (lobe / 10)
    img = _sinc_image(u, u, lobe)
    res = mod.lobe_metrics(img, u, u, r, (0.0, 0.0))
    first = 20 * math.log10(abs(np.sinc(1.4303)))
    assert res["PSL_dB"] == pytest.approx(first, abs=0.05)
    from scipy.optimize import brentq

    x6 = brentq(lambda x: np.sinc(x) - 10 ** (-6 / 20), 0.1, 0.9)
    assert x6 == pytest.approx(0.6025, abs=1e-4)
    assert res["width_x"] == pytest.approx(2 * x6 * lobe * r, rel=0.003)
    assert res["width_y"] == pytest.approx(res["width_x"], rel=1e-9)
    main = mod.main_lobe(np.abs(img), (60, 60))
    U, V = np.meshgrid(u, u)
    inner = (np.abs(U) < 0.9 * lobe) & (np.abs(V) < 0.9 * lobe)
    assert main[inner].all()                                   # the whole main lobe
    assert not main[(np.abs(U) > 1.1 * lobe) | (np.abs(V) > 1.1 * lobe)].any()   # nothing past the nulls


def test_a_stronger_lobe_elsewhere_is_a_side_lobe_and_the_peak_is_the_points(mod):
    """A copy of the main lobe at +3 dB far from the point (a grating lobe): the point's own peak
    is kept (climbed to from the point's direction) and the PSL is +3 dB."""
    lobe, r = 0.05, 0.05
    u = np.arange(-80, 81) * (lobe / 8)
    img = _sinc_image(u, u, lobe, (-0.2, 0.0)) + 10 ** (3 / 20) * _sinc_image(u, u, lobe, (0.5, 0.0))
    res = mod.lobe_metrics(img, u, u, r, (-0.2, 0.0))
    assert res["peak_uv"] == pytest.approx((-0.2, 0.0), abs=1e-9)
    assert res["PSL_dB"] == pytest.approx(3.0, abs=0.1)


def test_a_shoulder_without_a_null_belongs_to_the_main_lobe(mod):
    """A main lobe with a shoulder (a second Gaussian at -10 dB that does not dip below it by 1 dB)
    has no first null there: the shoulder is main lobe, and the PSL is set by a separate lobe."""
    u = np.linspace(-1, 1, 101)
    U, V = np.meshgrid(u, u)
    g = lambda x, y, s: np.exp(-((U - x) ** 2 + (V - y) ** 2) / (2 * s * s))   # noqa: E731
    img = g(0, 0, 0.08) + 10 ** (-10 / 20) * g(0.15, 0, 0.08) + 10 ** (-20 / 20) * g(-0.6, 0.5, 0.05)
    res = mod.lobe_metrics(img, u, u, 1.0, (0.0, 0.0))
    assert res["PSL_dB"] == pytest.approx(-20.0 - 20 * math.log10(img.max()), abs=0.05)   # not the -6 dB shoulder


def test_width_never_falling_to_half_is_infinite(mod):
    u = np.linspace(-0.1, 0.1, 21)
    img = np.ones((21, 21)) + 0.01 * np.exp(-(u[None] ** 2 + u[:, None] ** 2) / 0.001)
    res = mod.lobe_metrics(img, u, u, 0.05, (0.0, 0.0))
    assert math.isinf(res["width_x"]) and math.isinf(res["width_y"])


def test_geometry(mod):
    pos = mod.element_grid()
    assert pos.shape == (2, 1024)
    assert pos[:, 0] == pytest.approx([-4.65e-3, -4.65e-3]) and pos[:, 1] == pytest.approx([-4.35e-3, -4.65e-3])
    # the catalogue probe's element order (row order, x fastest)
    from arraysel.physics.probes import get_probe

    ref = np.asarray(get_probe("MATRIX-32x32").element_positions())[:, :2].T
    np.testing.assert_allclose(pos, ref, atol=1e-12)
    # a diverging wave steered straight ahead fires the centre elements first, symmetrically
    d = mod.virtual_source_delays(pos, [(0.0, 0.0), (30.0, 0.0)], 8.05e-3, 1540.0)
    assert d.min(1) == pytest.approx([0.0, 0.0], abs=1e-15)
    assert d[0].reshape(32, 32) == pytest.approx(d[0].reshape(32, 32)[::-1, ::-1])
    # steered to +x: the source lies at -x, so the elements at -x fire first
    assert d[1].reshape(32, 32)[:, 0].mean() < d[1].reshape(32, 32)[:, -1].mean()
    g = mod.uv_grid(0.554, 0.0179)
    assert g.size == 63 and g[31] == 0.0 and g[-1] >= 0.554
    # a point's surfaces: the sphere of its range, or the C-plane through it at the same x, y
    pt = mod.point_position(20.0, 0.0, 0.065)
    sph = mod.surface_pixels("sphere", pt, g, g)
    pla = mod.surface_pixels("plane", pt, g, g)
    np.testing.assert_allclose(np.linalg.norm(sph, axis=-1), 0.065, rtol=1e-12)
    np.testing.assert_allclose(pla[..., :2], sph[..., :2], rtol=0, atol=1e-15)
    assert np.all(pla[..., 2] == pt[2])
    with pytest.raises(ValueError, match="--surface"):
        mod.surface_pixels("cone", pt, g, g)


def test_bad_input_names_the_argument(mod, tmp_path):
    assert mod.parse_points("0,0,35; 20,0,65") == [(0.0, 0.0, 35.0), (20.0, 0.0, 65.0)]
    for bad in ("0,0", "0,0,1", "85,0,50", "60,60,50", ""):
        with pytest.raises(ValueError, match=r"--points"):
            mod.parse_points(bad)
    csv = tmp_path / "t.csv"
    csv.write_text("config,elements\nfull,0 1 2\nbad,0 0 1\n", encoding="utf-8")
    assert mod.read_selections([csv], ["full"], 1024)["full"].sum() == 3
    with pytest.raises(ValueError, match="--configs"):
        mod.read_selections([csv], ["spiral"], 1024)
    with pytest.raises(ValueError, match="distinct"):
        mod.read_selections([csv], ["bad"], 1024)
    with pytest.raises(SystemExit):
        mod.main(["--half-angle", "70", "--out", str(tmp_path)])


def test_ray_radius_first_null_and_cap(mod):
    """A ray falling to its lowest value (0.04 at 3.5 pixels) before a rise of more than 1 dB has
    its first null there; its -6 dB distance is 0.5 + 0.5 (0.7 - h) / (0.7 - 0.4) with h = 10^(-6/20),
    0.832, so the cap of 3 times it (2.495) cuts the radius; a ray that never rises has none (inf)."""
    s = np.arange(10) * 0.5
    prof = np.array([[1.0, 0.7, 0.4, 0.2, 0.1, 0.05, 0.045, 0.04, 0.2, 0.1],
                     [1.0, 0.7, 0.4, 0.2, 0.1, 0.05, 0.045, 0.04, 0.039, 0.03]])
    assert mod.ray_radius(s, prof, cap=None).tolist() == [3.5, math.inf]
    r6 = 0.5 + 0.5 * (0.7 - 10 ** (-6 / 20)) / 0.3
    np.testing.assert_allclose(mod.ray_radius(s, prof, cap=3.0), [3 * r6, 3 * r6])
    # a rise of less than 1 dB above the lowest value met is ripple, not a null
    rip = np.array([[1.0, 0.4, 0.1, 0.05, 0.055, 0.04, 0.3]])
    assert mod.ray_radius(np.arange(7) * 0.5, rip, cap=None).tolist() == [2.5]
