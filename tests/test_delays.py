"""Tests of arraysel.physics.delays against PyMUST's txdelay (used as an oracle only)."""
from __future__ import annotations

import math

import numpy as np
import pytest

from arraysel.physics.delays import (circular_virtual_source, diverging_delays, focused_delays,
                             plane_wave_delays, plane_wave_tilts)
from arraysel.errors import ParameterError
from arraysel.physics.probes import Acquisition, get_probe

pymust = pytest.importorskip("pymust")

ATOL = 1e-12  # seconds


def _param(name, c):
    """PyMUST PARAM of a catalogue probe, completed with our own geometry fields."""
    p = get_probe(name)
    param = pymust.getparam("P4-2v")
    param.update(Nelements=p.n_elements, pitch=p.pitch, width=p.width, kerf=p.kerf,
                 radius=p.radius, fc=p.fc, c=float(c))
    return p, param


def _check(ours, ref, n_tx, ne):
    ref = np.atleast_2d(np.asarray(ref, dtype=np.float64))
    assert ours.dtype == np.float64 and ours.shape == (n_tx, ne)
    assert ref.shape == ours.shape
    np.testing.assert_allclose(ours, ref, rtol=0, atol=ATOL)
    np.testing.assert_array_equal(ours.min(axis=1), 0.0)


def test_plane_wave_tilts_default():
    t = plane_wave_tilts()
    assert t.dtype == np.float64 and t.shape == (7,)
    np.testing.assert_allclose(np.rad2deg(t), [-10, -20 / 3, -10 / 3, 0, 10 / 3, 20 / 3, 10], atol=1e-12)
    np.testing.assert_allclose(plane_wave_tilts(3, 7.0), np.deg2rad([-7.0, 0.0, 7.0]))
    assert plane_wave_tilts(1, 10).tolist() == [0.0]


@pytest.mark.parametrize("name", ["P4-2v", "L11-5v", "C5-2v", "L7-4"])
@pytest.mark.parametrize("c", [1540.0, 1480.0])
def test_plane_wave_matches_pymust(name, c):
    p, param = _param(name, c)
    tilts = np.concatenate([plane_wave_tilts(7, 10.0), [-0.6, 0.45, 1.2]])
    ours = plane_wave_delays(p, tilts, c)
    _check(ours, pymust.txdelay(param, tilts), tilts.size, p.n_elements)


def test_plane_wave_sign_and_scalar():
    p = get_probe("P4-2v")
    d = plane_wave_delays(p, 0.1)
    assert d.shape == (1, 64)
    assert d[0, -1] > d[0, 0] and d[0, 0] == 0.0  # positive tilt delays the +x elements
    assert np.all(np.diff(d[0]) > 0)
    assert not plane_wave_delays(p, [0.0]).any()
    span = (p.n_elements - 1) * p.pitch * math.sin(0.1) / 1540.0
    assert d[0, -1] == pytest.approx(span, rel=1e-12)
    # Acquisition works in place of c
    np.testing.assert_array_equal(plane_wave_delays(p, 0.1, Acquisition(fs=1e7, c=1500.0)),
                                  plane_wave_delays(p, 0.1, 1500.0))


@pytest.mark.parametrize("name", ["P4-2v", "L12-3v"])
def test_focused_matches_pymust(name):
    p, param = _param(name, 1540.0)
    x0 = np.array([0.0, 0.01, -0.015, 0.004, -0.002, 0.02])
    z0 = np.array([0.03, 0.05, 0.02, -0.01, -0.04, 0.004])
    ours = focused_delays(p, x0, z0, 1540.0)
    _check(ours, pymust.txdelay(x0, z0, param), x0.size, p.n_elements)
    # scalar focus, broadcasting of a scalar against a vector
    _check(focused_delays(p, 0.01, 0.04), pymust.txdelay(0.01, 0.04, param), 1, p.n_elements)
    b = focused_delays(p, 0.0, [0.02, 0.04])
    np.testing.assert_array_equal(b, focused_delays(p, [0.0, 0.0], [0.02, 0.04]))


def test_focused_convex_matches_pymust():
    # PyMUST 0.1.9 takes one focus at a time for a convex array, and converges
    # only when sqrt(x0^2 + (R - z0)^2) < R; it agrees with our z0-sign rule for
    # every virtual source (z0 < 0) and for the foci inside that disk.
    p, param = _param("C5-2v", 1540.0)
    foci = [(0.0, 0.03), (0.01, 0.05), (-0.015, 0.02), (0.02, 0.08), (0.004, -0.01),
            (-0.002, -0.04), (0.0, -p.element_positions()[3]), (0.05, -0.02)]
    for x0, z0 in foci:
        ours = focused_delays(p, x0, z0, 1540.0)
        _check(ours, pymust.txdelay(x0, z0, param), 1, p.n_elements)
    # the centre of curvature as virtual source gives equal delays
    assert np.abs(focused_delays(p, 0.0, -p.element_positions()[3])).max() < 1e-18


def test_focused_convex_deep_focus_converges():
    # z0 > 0 always converges (PyMUST 0.1.9 flips to diverging beyond z0 = 2R)
    p = get_probe("C5-2v")
    d = focused_delays(p, 0.0, 0.15)[0]
    assert d[p.n_elements // 2] == pytest.approx(d.max()) and d[0] == pytest.approx(0.0, abs=1e-18)


def test_focused_and_diverging_shapes():
    p = get_probe("P4-2v")
    f = focused_delays(p, 0.0, 0.03)[0]
    # converging: the outer elements fire first, the centre last
    assert f[0] == pytest.approx(0.0) and f[-1] == pytest.approx(0.0, abs=1e-18)
    assert f[31] == pytest.approx(f.max())
    v = focused_delays(p, 0.0, -0.03)[0]
    # diverging: the centre fires first
    assert v[31] == pytest.approx(0.0, abs=1e-18) and v[0] == pytest.approx(v.max())


@pytest.mark.parametrize("name", ["P4-2v", "L11-5v", "L7-4"])
def test_diverging_matches_pymust(name):
    p, param = _param(name, 1540.0)
    tilts = np.array([0.0, 0.1, -0.3, 0.25, -0.05])
    widths = np.array([0.2, 0.5, 1.0, 1.5, 2.5])
    ours = diverging_delays(p, tilts, widths, 1540.0)
    _check(ours, pymust.txdelay(param, tilts, widths), tilts.size, p.n_elements)
    # scalar width broadcast over the tilts
    ours = diverging_delays(p, tilts, 0.7)
    _check(ours, pymust.txdelay(param, tilts, np.full(tilts.size, 0.7)), tilts.size, p.n_elements)


def test_circular_virtual_source_geometry():
    p = get_probe("P4-2v")
    x0, z0 = circular_virtual_source(p, [0.2], [0.6])
    xe = p.element_positions()[0]
    a_first = math.atan2(xe[0] - x0[0], -z0[0])
    a_last = math.atan2(xe[-1] - x0[0], -z0[0])
    assert z0[0] < 0
    assert a_first == pytest.approx(0.2 - 0.3, abs=1e-12)
    assert a_last == pytest.approx(0.2 + 0.3, abs=1e-12)


# ---------------------------------------------------------------- validation
@pytest.mark.parametrize("tilts", [math.pi / 2, -2.0, [0.0, 1.6], math.nan, math.inf, [], [[0.1]], "a"])
def test_plane_wave_bad_tilts(tilts):
    with pytest.raises(ParameterError, match="tilts"):
        plane_wave_delays(get_probe("P4-2v"), tilts)


@pytest.mark.parametrize("c", [0.0, -1540.0, 100.0, 1e5, math.nan])
def test_bad_speed_of_sound(c):
    p = get_probe("P4-2v")
    with pytest.raises(ParameterError, match="c"):
        plane_wave_delays(p, 0.0, c)
    with pytest.raises(ParameterError, match="c"):
        focused_delays(p, 0.0, 0.03, c)
    with pytest.raises(ParameterError, match="c"):
        diverging_delays(p, 0.0, 0.5, c)


def test_focused_bad_inputs():
    p = get_probe("P4-2v")
    with pytest.raises(ParameterError, match="z0"):
        focused_delays(p, 0.0, 0.0)
    with pytest.raises(ParameterError, match="z0"):
        focused_delays(p, 0.0, [0.02, math.nan])
    with pytest.raises(ParameterError, match="x0"):
        focused_delays(p, math.inf, 0.02)
    with pytest.raises(ParameterError, match=r"x0 and z0"):
        focused_delays(p, [0.0, 0.01], [0.02, 0.03, 0.04])
    with pytest.raises(ParameterError, match="probe"):
        focused_delays("P4-2v", 0.0, 0.02)


def test_diverging_bad_inputs():
    p = get_probe("P4-2v")
    with pytest.raises(ParameterError, match="widths"):
        diverging_delays(p, 0.0, 0.0)
    with pytest.raises(ParameterError, match="widths"):
        diverging_delays(p, 0.0, math.pi)
    with pytest.raises(ParameterError, match="tilts"):
        diverging_delays(p, 1.0, 1.5)  # sector edge beyond pi/2
    with pytest.raises(ParameterError, match="tilts"):
        diverging_delays(p, -1.7, 0.1)
    with pytest.raises(ParameterError, match=r"tilts and widths"):
        diverging_delays(p, [0.0, 0.1], [0.2, 0.3, 0.4])
    with pytest.raises(ParameterError, match="convex"):
        diverging_delays(get_probe("C5-2v"), 0.0, 0.5)
    with pytest.raises(ParameterError, match="n_elements"):
        diverging_delays(get_probe("P4-2v", n_elements=1), 0.0, 0.5)


def test_plane_wave_tilts_bad_inputs():
    with pytest.raises(ParameterError, match="n"):
        plane_wave_tilts(0, 10)
    with pytest.raises(ParameterError, match="n"):
        plane_wave_tilts(2.5, 10)
    with pytest.raises(ParameterError, match="max_deg"):
        plane_wave_tilts(7, 90)
    with pytest.raises(ParameterError, match="max_deg"):
        plane_wave_tilts(7, -1)


@pytest.mark.parametrize("n", [2, 3, 4, 5, 8, 64, 256])
def test_aperture_resampling_equals_scipy_interp1d(n):
    """The transmit aperture's resampling (four points an element, for the earliest transmit
    arrival of the DAS) equals SciPy's cubic ``interp1d`` (not-a-knot; linear up to 3 points)."""
    import scipy.interpolate

    from arraysel.physics.beamform import resample_uniform

    rng = np.random.default_rng(n)
    y = rng.normal(size=n) * 1e-3 + np.linspace(-1e-2, 2e-2, n) ** 2
    t = np.linspace(0, n - 1, 4 * n)
    ref = scipy.interpolate.interp1d(np.arange(n, dtype=float), y, kind="cubic" if n > 3 else "linear")(t)
    assert np.abs(resample_uniform(y, t) - ref).max() <= 1e-13 * np.abs(ref).max()
