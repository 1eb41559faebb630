"""The sector fast path: each point's image on its surface from precomputed transmit and receive
sums (bilinear in the weights), against the exact path on a small matrix probe."""
from __future__ import annotations

import copy

import numpy as np
import pytest
import torch

from arraysel.objective.sector_objective import BEAM_COLUMNS, SectorObjective, sector_fast_state
from arraysel.physics.volume.fast import MatrixFastPSF
from arraysel.physics.volume.sector import MIRRORS, MirroredModel, _mirror_image, mirrors
from arraysel.scenes.schema import load_scene

SMALL = {"name": "small-sector", "probe": {"name": "MATRIX-32x32", "nx": 8, "ny": 8},
         "acquisition": {"fs_over_fc": 4.0},
         "transmit": {"n_tx_x": 3, "n_tx_y": 3, "max_tilt_deg": 20.0, "max_tilt_deg_y": 20.0,
                      "source_distance": "5 mm"},
         "sector": {"points": [[0.0, 0.0, "15 mm"], [10.0, 5.0, "20 mm"], [5.0, 10.0, "20 mm"]], "samples_per_lobe": 3.0, "margin": 1.0,
                    "n_freq": 4, "fresh_random": 3},
         "selection": {"k": 16}}


def _si_mse(a: torch.Tensor, b: torch.Tensor) -> float:
    a, b = a.to(torch.complex128).flatten(), b.to(torch.complex128).flatten()
    s = (a.conj() * b).sum() / (a.conj() * a).sum()
    return float(((s * a - b).abs() ** 2).sum() / (b.abs() ** 2).sum())


@pytest.fixture(scope="module")
def small():
    return SectorObjective(load_scene(copy.deepcopy(SMALL)), dtype=torch.float32)


def _masks(n=64, k=16):
    rng = np.random.default_rng(11)
    out = [np.ones(n, dtype=bool)]
    for _ in range(3):
        m = np.zeros(n, dtype=bool)
        m[rng.choice(n, k, replace=False)] = True
        out.append(m)
    m = np.zeros(n, dtype=bool)
    m[np.arange(n).reshape(8, 8)[::2, ::2].reshape(-1)] = True   # periodic thinning: grating lobes
    out.append(m)
    return np.stack(out)


@pytest.mark.slow
def test_fast_images_equal_the_exact_ones(small):
    masks = _masks()
    w = torch.as_tensor(masks, dtype=torch.float32)
    for i in range(small.n_points):
        assert small.fast_point(i), small.fast_refused
        # point 2 is point 1 seen in the x-y mirror: its images are point 1's, nothing built for it
        assert isinstance(small.exact._fast[i], MirroredModel if i == 2 else MatrixFastPSF)
        fast = small.point_images(w, i)
        exact = small.point_images(w, i, exact=True)
        assert fast.shape == exact.shape == (len(masks), len(small.setup.v), len(small.setup.u))
        for b in range(len(masks)):
            assert _si_mse(fast[b], exact[b]) <= 1e-6, (i, b)
        # a wrong model is caught: the other point's image is far from this one
        other = small.point_images(w[:1], (i + 1) % small.n_points, exact=True)
        assert _si_mse(fast[0], other[0]) > 1e-2


def test_mirrors_find_the_swapped_points(small):
    perms, pairs = mirrors(small.setup)
    assert pairs == {2: (1, "swap")}
    grid = np.arange(64).reshape(8, 8)
    np.testing.assert_array_equal(perms["swap"], grid.T.reshape(-1))
    builtin = SectorObjective("matrix-1024-sector")
    # five models serve the eleven points: the others are mirror images of the 13-degree points
    # (in x and y on both sides, and the diagonals)
    assert mirrors(builtin.setup)[1] == {4: (3, "swap"), 6: (3, "x"), 7: (3, "antiswap"), 8: (5, "x"), 9: (5, "y"),
                                         10: (5, "xy")}
    # transmits steered less far in y break the swap of x and y
    tree = copy.deepcopy(SMALL)
    tree["transmit"]["max_tilt_deg_y"] = 10.0
    assert "swap" not in mirrors(SectorObjective(load_scene(tree)).setup)[0]


def _mirrored_scene():
    tree = copy.deepcopy(SMALL)
    # point 1 and its images in every mirror of the square grid (x, y, both, the swap and the anti-swap)
    tree["sector"]["points"] = [[0.0, 0.0, "15 mm"], [10.0, 5.0, "20 mm"], [5.0, 10.0, "20 mm"],
                                [-10.0, 5.0, "20 mm"], [10.0, -5.0, "20 mm"], [-5.0, -10.0, "20 mm"],
                                [-10.0, -5.0, "20 mm"]]
    return SectorObjective(load_scene(tree), dtype=torch.float32)


def test_mirrors_find_every_mirrored_point():
    obj = _mirrored_scene()
    perms, pairs = mirrors(obj.setup)
    assert set(perms) == set(MIRRORS)
    assert pairs == {2: (1, "swap"), 3: (1, "x"), 4: (1, "y"), 5: (1, "antiswap"), 6: (1, "xy")}
    grid = np.arange(64).reshape(8, 8)   # element index = 8 * row (y) + column (x)
    np.testing.assert_array_equal(perms["x"], grid[:, ::-1].reshape(-1))
    np.testing.assert_array_equal(perms["y"], grid[::-1, :].reshape(-1))
    np.testing.assert_array_equal(perms["swap"], grid.T.reshape(-1))
    np.testing.assert_array_equal(perms["antiswap"], grid[::-1, ::-1].T.reshape(-1))
    # steering less far in y than in x breaks the mirrors that swap x and y, not the flips
    tree = copy.deepcopy(SMALL)
    tree["transmit"]["max_tilt_deg_y"] = 10.0
    assert set(mirrors(SectorObjective(load_scene(tree)).setup)[0]) == {"x", "y", "xy"}


def test_mirrored_model_refuses_an_unknown_mirror():
    with pytest.raises(ValueError, match="mirror name 'z'"):
        MirroredModel(None, np.arange(4), "z")


@pytest.mark.slow
def test_mirrored_points_fast_images_equal_the_exact_ones():
    obj = _mirrored_scene()
    # the mirrored point's exact image is the first point's, of the permuted weights, mirrored
    w = torch.as_tensor(_masks(), dtype=torch.float32)[1:2]
    perms, pairs = mirrors(obj.setup)
    base = {name: obj.point_images(w[:, torch.as_tensor(perms[name])], 1, exact=True) for name in perms}
    for j, (i, name) in pairs.items():
        direct = obj.point_images(w, j, exact=True)
        assert _si_mse(_mirror_image(base[name], name)[0], direct[0]) <= 1e-10, (j, name)
        # and a wrong mirror is caught
        wrong = "y" if name == "x" else "x"
        assert _si_mse(_mirror_image(base[wrong], wrong)[0], direct[0]) > 1e-3, (j, wrong)
    w = torch.as_tensor(_masks(), dtype=torch.float32)
    for j in range(2, obj.n_points):
        assert obj.fast_point(j), obj.fast_refused
        assert isinstance(obj.exact._fast[j], MirroredModel)   # nothing built for it
        fast, exact = obj.point_images(w, j), obj.point_images(w, j, exact=True)
        for b in range(len(w)):
            assert _si_mse(fast[b], exact[b]) <= 1e-6, (j, b)


@pytest.mark.slow
def test_fast_beam_metrics_equal_the_exact_ones(small):
    masks = _masks()
    assert all(small.fast_point(i) for i in range(small.n_points))
    fast = small.beam_metrics(masks)
    exact = small.beam_metrics(masks, exact=True)
    assert set(fast) == set(BEAM_COLUMNS)
    np.testing.assert_allclose(fast["PSL_dB"], exact["PSL_dB"], atol=0.05)
    np.testing.assert_allclose(fast["ISLR_dB"], exact["ISLR_dB"], atol=0.05)
    for c in ("width_x_6dB", "width_y_6dB"):
        np.testing.assert_allclose(fast[c], exact[c], rtol=2e-3)
    # the thinned layout's grating lobe is seen by both
    assert fast["GLL_dB"][-1].max() > -30 and exact["GLL_dB"][-1].max() > -30


def test_beam_loss_penalises_width(small):
    masks = _masks()[:2]
    bm = small.beam_metrics(masks)
    width = (bm["width_x_6dB"].mean(1) + bm["width_y_6dB"].mean(1)) / 2
    loose, s = small.beam_loss(masks, width_cap=10 * float(width.max()))
    np.testing.assert_allclose(loose, bm["PSL_dB"].max(1))
    np.testing.assert_allclose(s["mean_width_m"], width)
    tight, _ = small.beam_loss(masks, width_cap=float(width.min()) / 2, width_weight=10.0)
    np.testing.assert_allclose(tight, bm["PSL_dB"].max(1) + 10.0 * (width / (width.min() / 2) - 1))


@pytest.mark.slow
def test_cached_state_restores_and_fast_can_be_off(small):
    state = sector_fast_state(small, 0)
    assert "refused" not in state
    model = small.exact.fast_from_state(0, state)
    w = torch.as_tensor(_masks()[1:2], dtype=torch.float32)
    assert _si_mse(model.planes(w)["sector"][0], small.point_images(w, 0, exact=True)[0]) <= 1e-6
    with pytest.raises(ValueError):   # the tensors of one point do not fit a surface of another size
        bad = {k: v for k, v in state.items()}
        bad["unsort"] = bad["unsort"][:-1]
        small.exact.fast_from_state(0, bad)
    off = SectorObjective(load_scene(copy.deepcopy(SMALL)), dtype=torch.float32, fast=False)
    assert not off.fast_point(0) and not off.exact.has_fast(0)
    # a small batch takes a cached model but builds none: another k has no entry
    other = SectorObjective(load_scene({**copy.deepcopy(SMALL), "selection": {"k": 15}}), dtype=torch.float32)
    assert not other.fast_point(0, build=False) and 0 not in other.fast_refused
    other.point_images(_masks()[:2], 0)
    assert not other.exact.has_fast(0)
    again = SectorObjective(load_scene(copy.deepcopy(SMALL)), dtype=torch.float32)
    again.point_images(_masks()[:2], 0)
    assert again.exact.has_fast(0)


@pytest.mark.slow
def test_polish_on_beams_lowers_the_per_beam_loss(small):
    from arraysel.errors import ParameterError
    from arraysel.objective.sector_polish import polish_on_beams

    start = _masks()[1]
    full = small.beam_metrics(np.ones((1, 64), dtype=bool))
    cap = 1.2 * float((full["width_x_6dB"].mean() + full["width_y_6dB"].mean()) / 2)
    res = polish_on_beams(small, start, width_cap=cap, seconds=60, batch=16, keep=2, patience=3, seed=1)
    assert res["mask"].sum() == 16 and res["loss"] <= res["start_loss"]
    assert res["accepted"] >= 1 and res["loss"] < res["start_loss"]   # a random start is easy to improve
    loss, _ = small.beam_loss(res["mask"][None], width_cap=cap)
    assert loss[0] == pytest.approx(res["loss"], abs=1e-3)   # float32 sums: the batch changes the rounding
    assert all(b[1] <= a[1] for a, b in zip(res["trace"], res["trace"][1:]))
    again = polish_on_beams(small, start, width_cap=cap, seconds=60, batch=16, keep=2, patience=3, seed=1)
    assert (again["mask"] == res["mask"]).all()
    with pytest.raises(ParameterError, match="mask"):
        polish_on_beams(small, np.ones(64, dtype=bool), width_cap=cap)


@pytest.mark.slow
def test_fast_images_with_separate_receive_masks(small):
    masks = _masks()
    tx = torch.as_tensor(masks[1:3], dtype=torch.float32)
    rx = torch.as_tensor(masks[[3, 4]], dtype=torch.float32)
    for i in (1, 2):   # point 2 through its mirror: both masks mirrored
        assert small.fast_point(i)
        fast = small.point_images(tx, i, receive=rx)
        exact = small.point_images(tx, i, exact=True, receive=rx)
        same = small.point_images(tx, i)
        for b in range(2):
            assert _si_mse(fast[b], exact[b]) <= 1e-6, (i, b)
            assert _si_mse(fast[b], same[b]) > 1e-3   # the receive masks change the image
