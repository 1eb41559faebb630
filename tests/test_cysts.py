"""Anechoic cysts in speckle (arraysel.objective.cysts, docs/sector.md): CR and gCNR on known
answers, the speckle model's statistics, the seeded phantom, the [cysts] keys and their errors,
and the cysts of a tiny sector scene."""
from __future__ import annotations

import copy
import math

import numpy as np
import pytest
import torch

from arraysel.errors import ParameterError
from arraysel.objective.cysts import CystPhantom, CystSettings, contrast_ratio, gcnr, score_cysts
from arraysel.scenes.schema import load_scene
from scene_texts import TINY_SECTOR

#: the tiny sector scene of tests/test_sector.py (8 x 8 elements, two points at 15 mm)
TINY = copy.deepcopy(TINY_SECTOR)

U = np.arange(-31, 32) * 0.0179           # a sector grid (matrix-1024-sector's with margin 1)
LOBE = (0.0537, 0.0537)


def _phantom(**over):
    st = {"points": (0,), "radius": 4e-3, "density": 10.0, "realisations": 8, "seed": 0, **over}
    return CystPhantom(U, U, (0.0, 0.0), 0.05, LOBE, CystSettings(**st))


def _gaussian(width):
    uu, vv = np.meshgrid(U, U)
    return np.exp(-(uu ** 2 + vv ** 2) / (2 * width ** 2)).astype(complex)


def _delta():
    k = np.zeros((U.size, U.size), complex)
    k[31, 31] = 1.0
    return k


# --------------------------------------------------------------------------- the metrics
def test_gcnr_of_identical_disjoint_and_half_overlapping_distributions():
    rng = np.random.default_rng(1)
    a, b = rng.rayleigh(1.0, 40000), rng.rayleigh(1.0, 40000)
    assert gcnr(a, b) < 0.05                                   # one distribution: ~0
    assert gcnr(a, a) == 0.0
    assert gcnr(np.full(50, 2.0), np.full(80, 2.0)) == 0.0     # every sample equal
    assert gcnr(rng.uniform(0, 1, 5000), rng.uniform(2, 3, 5000)) == 1.0   # disjoint
    # uniform on [0, 1] and on [0.5, 1.5]: half of each lies on the other's support
    assert gcnr(rng.uniform(0, 1, 40000), rng.uniform(0.5, 1.5, 40000), bins=60) == pytest.approx(0.5, abs=0.03)


def test_contrast_ratio_of_constant_images():
    assert contrast_ratio(np.full(10, 0.1), np.full(20, 1.0)) == pytest.approx(-20.0)
    assert contrast_ratio(np.full(10, 2.0), np.full(20, 2.0)) == pytest.approx(0.0)
    assert contrast_ratio(np.zeros(10), np.ones(5)) == -240.0
    with pytest.raises(ParameterError, match="inside is empty"):
        contrast_ratio([], [1.0])


# --------------------------------------------------------------------------- the phantom
def test_phantom_is_seeded_and_anechoic():
    a, b = _phantom().fields(), _phantom().fields()
    assert np.array_equal(a, b)
    assert not np.array_equal(a, _phantom(seed=1).fields())
    ph = _phantom()
    assert (a[:, ~ph.keep] == 0).all() and np.abs(a[:, ph.keep]).mean() > 0
    # the disc removed: R hypot(du, dv) <= radius; 4 mm at 50 mm is 4.47 samples of 0.0179
    e = np.arange(-62, 63) * 0.0179                             # the shifts: 2 x 63 - 1 a side
    ey, ex = np.meshgrid(e, e, indexing="ij")
    disc = 0.05 * np.hypot(ex, ey) <= 4e-3
    assert disc.sum() == sum(1 for i in range(-5, 6) for j in range(-5, 6) if 0.05 * 0.0179 * math.hypot(i, j) <= 4e-3)
    assert np.array_equal(ph.keep, ~disc & (np.hypot(ex, ey) < 1))  # and nothing outside the visible region
    assert ph.per_sample == pytest.approx(10 * 0.0179 ** 2 / 0.0537 ** 2)
    m1, m2 = ph.metrics(_gaussian(0.02)), _phantom().metrics(_gaussian(0.02))
    assert m1 == m2


def test_delta_psf_images_the_scatterers_rayleigh_speckle_and_a_dark_cyst():
    ph = _phantom(density=1000.0, realisations=16)
    env = ph.images(_delta())
    # the image of a delta PSF at the point is the field, read at the shifts of the surface's samples
    assert np.allclose(env, np.abs(ph.fields()[:, 31:94, 31:94]))
    ring = env[:, ph.ring]
    assert ring.mean() / ring.std() == pytest.approx(math.sqrt(math.pi / (4 - math.pi)), rel=0.05)  # Rayleigh
    res = ph.metrics(_delta())
    inside = env[:, ph.inside]
    assert inside.max() < 1e-12 * ring.mean() and res["CR_dB"] == -240.0   # dark but for round-off
    # the dark inside fills the first bin alone, but for the ring's samples that fall in it
    n = max(10, round(math.sqrt(inside.size)))
    first = ring.max() / n
    assert res["gCNR"] == pytest.approx(1 - np.mean(ring < first)) and 0.95 < res["gCNR"] < 1


def test_wider_psf_fills_the_cyst():
    crs = [_phantom().metrics(_gaussian(w))["CR_dB"] for w in (0.02, 0.05, 0.1)]
    assert crs[0] < crs[1] < crs[2] < 0
    gs = [_phantom().metrics(_gaussian(w))["gCNR"] for w in (0.02, 0.05, 0.1)]
    assert gs[0] > gs[1] > gs[2]


def test_phantom_refuses_bad_psf_and_tiny_cyst():
    with pytest.raises(ParameterError, match="psf must have shape"):
        _phantom().images(np.ones((3, 3)))
    with pytest.raises(ParameterError, match="radius"):
        CystSettings(points=(0,), radius=0.0)
    with pytest.raises(ParameterError, match="holds no sample"):
        _phantom(radius=1e-4, inside=0.1)


# --------------------------------------------------------------------------- the scene
def _scene(cysts=None, **over):
    tree = copy.deepcopy(TINY)
    tree["cysts"] = {"radius": "2.5 mm", "realisations": 4} if cysts is None else cysts
    for sec, keys in over.items():
        tree.setdefault(sec, {}).update(keys)
    return load_scene(tree)


def test_cyst_keys_and_defaults():
    s = _scene()
    st = CystSettings.from_scene(s)
    assert st.points == (0, 1) and st.radius == pytest.approx(2.5e-3) and st.density == 10.0
    assert st.realisations == 4 and st.inside == 0.8 and st.ring == (1.2, 2.0)
    assert CystSettings.from_scene(load_scene(copy.deepcopy(TINY))) is None
    assert CystSettings.from_scene(_scene({"points": [1], "radius": "2.4 mm"})).points == (1,)


@pytest.mark.parametrize("cysts, key", [
    ({"points": [2]}, r"cysts.points\[0\]"),
    ({"radius": "1 mm"}, "cysts.radius = 1 mm is .* samples"),
    ({"radius": "4 mm"}, "cysts.radius = 4 mm: the background ring"),
    ({"radius": "2.5 mm", "ring_inner": 2.0, "ring_outer": 2.0}, "cysts.ring_outer"),
    ({"density": 0.0}, "cysts.density"),
    ({"realisations": 0}, "cysts.realisations"),
    ({"bins": 3}, "cysts.bins"),
])
def test_cyst_key_errors_name_the_key(cysts, key):
    with pytest.raises(ParameterError, match=key):
        _scene(cysts)


def test_cysts_outside_a_sector_scene_are_refused():
    with pytest.raises(ParameterError, match=r"\[cysts\] applies to sector scenes"):
        load_scene({"base": "paper", "cysts": {"radius": "2 mm"}})


def test_score_cysts_on_a_tiny_sector_scene():
    from arraysel.objective.sector_objective import SectorObjective

    obj = SectorObjective(_scene(), dtype=torch.float64)
    masks = np.zeros((2, obj.n_elements), bool)
    masks[0] = True
    masks[1, ::4] = True
    masks[1, 1::4] = True        # every second column: periodic thinning by 2 in x
    imgs = {i: obj.point_images(masks, i, exact=True) for i in (0, 1)}
    got = score_cysts(obj, masks, images=imgs)
    assert got["CR_dB"].shape == got["gCNR"].shape == (2, 2) and list(got["points"]) == [0, 1]
    assert np.isfinite(got["CR_dB"]).all() and ((got["gCNR"] >= 0) & (got["gCNR"] <= 1)).all()
    assert (got["CR_dB"] < 0).all()
    again = score_cysts(obj, masks[:1], images={i: v[:1] for i, v in imgs.items()})
    assert again["CR_dB"][0] == pytest.approx(got["CR_dB"][0]) and again["gCNR"][0] == pytest.approx(got["gCNR"][0])
    # the images computed here (the fast path when one is cached) are those handed in
    fresh = score_cysts(obj, masks[:1])
    assert fresh["CR_dB"][0] == pytest.approx(got["CR_dB"][0], abs=0.01)
