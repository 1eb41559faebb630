"""Tests of arraysel.physics.probes: catalogue vs PyMUST getparam, geometry, validation."""
from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from arraysel.errors import ParameterError
from arraysel.physics.probes import (Acquisition, Probe, check_sampling, get_probe, list_probes,
                             min_sampling_frequency)

pymust = pytest.importorskip("pymust")

# PyMUST's getparam spelling of each catalogue probe present there.
PYMUST_NAMES = ["L11-5v", "L12-3v", "C5-2v", "P4-2v", "PA4-2/20", "L9-4/38", "LA530",
                "L14-5/38", "L14-5W/60", "P6-3"]
REQUIRED = ["P4-2v", "L11-5v", "L12-3v", "C5-2v", "P6-3", "L7-4"]

# MUST's defaults for fields getparam leaves out (documented in pfield).
MUST_DEFAULTS = {"height": math.inf, "focus": math.inf, "radius": math.inf, "bandwidth": 75.0}


def _must(name):
    return dict(pymust.getparam(name))


def test_catalogue_holds_required_and_all_getparam_probes():
    names = list_probes()
    for n in REQUIRED + PYMUST_NAMES:
        assert n in names
    assert len(set(n.lower() for n in names)) == len(names)


@pytest.mark.parametrize("name", PYMUST_NAMES)
def test_catalogue_matches_getparam(name):
    ref = _must(name)
    p = get_probe(name)
    assert p.name == name
    assert p.n_elements == ref["Nelements"]
    assert p.fc == pytest.approx(ref["fc"], rel=1e-12)
    assert p.pitch == pytest.approx(ref["pitch"], rel=1e-12)
    width = ref.get("width", ref["pitch"] - ref.get("kerf", 0.0))
    assert p.width == pytest.approx(width, rel=1e-9)
    if "kerf" in ref:
        assert p.kerf == pytest.approx(ref["kerf"], rel=1e-9)
    for ours, theirs in [("height", "height"), ("elevation_focus", "focus"),
                         ("radius", "radius"), ("bandwidth", "bandwidth")]:
        expected = ref.get(theirs, MUST_DEFAULTS[theirs])
        got = getattr(p, ours)
        if math.isinf(expected):
            assert math.isinf(got), (ours, got)
        else:
            assert got == pytest.approx(expected, rel=1e-12), ours
    assert p.baffle == "soft"


def test_paper_probe_p4_2v():
    p = get_probe("P4-2v", fc=3.5e6)
    assert (p.n_elements, p.pitch, p.width, p.height, p.elevation_focus) == (64, 0.3e-3, 0.25e-3, 14e-3, 60e-3)
    assert p.kerf == pytest.approx(0.05e-3)
    assert p.bandwidth == 74.0 and p.is_linear and p.baffle == "soft" and p.fc == 3.5e6
    assert p.wavelength(1540.0) == pytest.approx(1540 / 3.5e6)
    assert get_probe("P4-2v").fc == 2.72e6  # override does not leak into the catalogue


@pytest.mark.parametrize("name", PYMUST_NAMES + ["L7-4"])
def test_element_positions_match_pymust(name):
    p = get_probe(name)
    xe, ze, th, h = p.element_positions()
    for a in (xe, ze, th):
        assert a.dtype == np.float64 and a.shape == (p.n_elements,)
    assert isinstance(h, float)
    if name in PYMUST_NAMES:
        param = pymust.getparam(name)
        if "radius" not in param:  # getparam leaves it out for some linear probes
            param.radius = math.inf
    else:  # L7-4 is not in getparam: build the PyMUST param from our own fields
        param = pymust.getparam("P4-2v")
        param.update(Nelements=p.n_elements, pitch=p.pitch, radius=p.radius)
    rx, rz, rth, rh = param.getElementPositions()
    np.testing.assert_allclose(xe, np.ravel(rx), rtol=0, atol=1e-15)
    np.testing.assert_allclose(ze, np.ravel(rz), rtol=0, atol=1e-15)
    np.testing.assert_allclose(th, np.ravel(rth), rtol=0, atol=1e-14)
    assert h == pytest.approx(float(np.ravel(rh)[0]), abs=1e-15)


def test_linear_geometry_conventions():
    p = get_probe("L11-5v")
    xe, ze, th, h = p.element_positions()
    assert xe.mean() == pytest.approx(0.0, abs=1e-18)
    np.testing.assert_allclose(np.diff(xe), p.pitch, rtol=1e-12)
    assert not ze.any() and not th.any() and h == 0.0
    assert p.aperture == pytest.approx(127 * p.pitch)


def test_convex_geometry_conventions():
    p = get_probe("C5-2v")
    assert not p.is_linear
    xe, ze, th, h = p.element_positions()
    # neighbours are one pitch apart, all on the arc centred at (0, -h)
    np.testing.assert_allclose(np.hypot(np.diff(xe), np.diff(ze)), p.pitch, rtol=1e-12)
    np.testing.assert_allclose(np.hypot(xe, ze + h), p.radius, rtol=1e-12)
    assert ze[0] == pytest.approx(0.0, abs=1e-15) and ze[-1] == pytest.approx(0.0, abs=1e-15)
    assert ze[p.n_elements // 2] > 0  # the arc bulges into the medium
    np.testing.assert_allclose(th, np.arctan2(xe, ze + h), atol=1e-14)
    np.testing.assert_allclose(xe, -xe[::-1], atol=1e-15)


def test_get_probe_case_insensitive_and_overrides():
    assert get_probe("p4-2V") == get_probe("P4-2v")
    assert get_probe(" c5-2v ").name == "C5-2v"
    p = get_probe("l12-3v", fc=5e6, n_elements=64, baffle="RIGID")
    assert (p.fc, p.n_elements, p.baffle) == (5e6, 64, "rigid")
    assert get_probe("P4-2v", name="mine").name == "mine"


def test_get_probe_errors():
    with pytest.raises(ParameterError, match=r"(?s)XYZ.*C5-2v.*P4-2v.*L7-4"):
        get_probe("XYZ")
    with pytest.raises(ParameterError, match="frequency"):
        get_probe("P4-2v", frequency=3e6)
    with pytest.raises(ParameterError, match="fc"):
        get_probe("P4-2v", fc=-1.0)
    with pytest.raises(ParameterError, match="name"):
        get_probe(3)


def test_replace_validates():
    p = get_probe("P4-2v")
    q = p.replace(fc=3.5e6)
    assert q.fc == 3.5e6 and p.fc == 2.72e6 and q.pitch == p.pitch
    with pytest.raises(ParameterError, match="width"):
        p.replace(width=1e-3)
    with pytest.raises(ParameterError, match="colour"):
        p.replace(colour="red")
    with pytest.raises(dataclasses.FrozenInstanceError):
        p.fc = 1.0  # type: ignore[misc]


def test_values_normalised():
    p = get_probe("P4-2v", n_elements=np.int64(32), fc=np.float32(3e6), bandwidth=60)
    assert type(p.n_elements) is int and p.n_elements == 32
    assert type(p.fc) is float and type(p.bandwidth) is float
    assert get_probe("P4-2v", baffle=1.75).baffle == 1.75


BASE = dict(name="t", n_elements=8, pitch=3e-4, width=2.5e-4, height=5e-3,
            elevation_focus=2e-2, radius=math.inf, fc=5e6, bandwidth=70.0, baffle="soft")

BAD = [
    ("name", ""), ("name", None),
    ("n_elements", 0), ("n_elements", 2.5), ("n_elements", -3), ("n_elements", "8"), ("n_elements", True),
    ("pitch", 0.0), ("pitch", -1e-4), ("pitch", math.inf), ("pitch", math.nan),
    ("width", 0.0), ("width", 4e-4), ("width", -1e-4),
    ("height", 0.0), ("height", -1.0),
    ("elevation_focus", 0.0), ("elevation_focus", -0.02),
    ("radius", 0.0), ("radius", -0.05),
    ("fc", 0.0), ("fc", -1e6), ("fc", math.inf),
    ("bandwidth", 0.0), ("bandwidth", 200.0), ("bandwidth", -5.0), ("bandwidth", 250.0),
    ("baffle", "hard"), ("baffle", 0.0), ("baffle", -1.0), ("baffle", math.inf), ("baffle", None),
]


@pytest.mark.parametrize("field,value", BAD)
def test_invalid_probe_fields_name_the_field(field, value):
    with pytest.raises(ParameterError, match=field):
        Probe(**dict(BASE, **{field: value}))


def test_convex_arc_must_be_possible():
    # pitch/2/radius > 1: the step between elements cannot exist
    with pytest.raises(ParameterError, match="radius"):
        Probe(**dict(BASE, radius=1e-4))
    # total angle >= pi
    with pytest.raises(ParameterError, match="radius"):
        Probe(**dict(BASE, n_elements=128, pitch=5e-4, width=4e-4, radius=1e-2))
    ok = Probe(**dict(BASE, radius=2e-2))
    assert not ok.is_linear and ok.element_positions()[3] > 0


def test_valid_edge_cases():
    p = Probe(**dict(BASE, width=3e-4, height=math.inf, elevation_focus=math.inf, n_elements=1))
    assert p.kerf == 0.0
    xe, ze, th, h = p.element_positions()
    assert xe.tolist() == [0.0] and ze.tolist() == [0.0] and th.tolist() == [0.0]
    c = Probe(**dict(BASE, n_elements=1, radius=0.01))
    assert c.element_positions()[0].tolist() == [0.0]


def test_wavelength_validates_c():
    p = get_probe("P4-2v")
    with pytest.raises(ParameterError, match="c"):
        p.wavelength(-1540.0)


# ---------------------------------------------------------------- acquisition
def test_acquisition_defaults_and_for_probe():
    p = get_probe("P4-2v", fc=3.5e6)
    a = Acquisition.for_probe(p)
    assert a == Acquisition(fs=14e6, c=1540.0, attenuation=0.0, tx_cycles=1.0)
    b = Acquisition.for_probe(p, fs=20e6, c=1500, attenuation=0.5, tx_cycles=2)
    assert (b.fs, b.c, b.attenuation, b.tx_cycles) == (20e6, 1500.0, 0.5, 2.0)
    assert a.replace(c=1480.0).c == 1480.0
    check_sampling(p, a)


@pytest.mark.parametrize("field,value", [
    ("fs", 0.0), ("fs", -1.0), ("fs", math.inf), ("c", 100.0), ("c", 20000.0), ("c", math.nan),
    ("attenuation", -0.1), ("attenuation", math.inf), ("tx_cycles", 0.0), ("tx_cycles", -1.0),
])
def test_invalid_acquisition_names_the_field(field, value):
    with pytest.raises(ParameterError, match=field):
        Acquisition(**dict(dict(fs=14e6), **{field: value}))


def test_acquisition_unknown_keys():
    with pytest.raises(ParameterError, match="speed"):
        Acquisition.for_probe(get_probe("P4-2v"), speed=1540)
    with pytest.raises(ParameterError, match="speed"):
        Acquisition(fs=1e7).replace(speed=1540)
    with pytest.raises(ParameterError, match="probe"):
        Acquisition.for_probe("P4-2v")


def test_check_sampling_rule():
    p = get_probe("P4-2v", fc=3.5e6)  # bandwidth 74 %
    fmin = 2 * 3.5e6 * (1 + 74 / 200)
    assert min_sampling_frequency(p) == pytest.approx(fmin)
    check_sampling(p, Acquisition(fs=fmin))
    with pytest.raises(ParameterError, match=r"fs = .*need fs >= 2 \* fc \* \(1 \+ bandwidth / 200\)"):
        check_sampling(p, Acquisition(fs=fmin * 0.99))
    with pytest.raises(ParameterError, match="9590000"):
        check_sampling(p, Acquisition(fs=7e6))
